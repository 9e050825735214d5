"""The registration benchmark's error-to-bound statistics."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from agents.benchmarks.registration import _BoundStats
from perception.geometry import make_T


def _result(err: np.ndarray, cov: np.ndarray, degenerate: list[str]) -> SimpleNamespace:
    # estimate = truth shifted by -err (the statistics take truth - estimate)
    return SimpleNamespace(T_sensor_target=make_T(np.eye(3), -err), covariance=cov,
                           degenerate_axes=degenerate)


def test_bound_stats_match_the_covariance_that_drew_the_errors() -> None:
    rng = np.random.default_rng(0)
    sig = np.array([0.002, 0.001, 0.004])
    cov = np.diag(np.r_[sig**2, np.full(3, 1e-6)])
    bias = np.array([0.0, 0.0, 0.005])  # a TOF-like range bias along the boresight
    stats = _BoundStats()
    for _ in range(4000):
        stats.add(_result(bias + sig * rng.standard_normal(3), cov, []), np.eye(4))
    # a degenerate frame carries a placeholder variance and a large error: it is only counted
    stats.add(_result(np.array([1.0, 0.0, 0.0]), 1e6 * np.eye(6), ["tx"]), np.eye(4))
    c = stats.columns()
    assert c["degenerate"] == 1
    assert c["std/crlb pos"] == pytest.approx(1.0, abs=0.03)
    assert c["bias_mm"] == pytest.approx(5.0, abs=0.2)
    expected_rms = np.sqrt((np.sum(sig**2) + 0.005**2) / np.sum(sig**2))
    assert c["rms/crlb pos"] == pytest.approx(expected_rms, rel=0.03)
    assert c["rms/crlb rot"] == pytest.approx(0.0, abs=1e-9)  # no rotation error was drawn


def test_bound_stats_with_only_degenerate_frames_report_nan() -> None:
    stats = _BoundStats()
    stats.add(_result(np.zeros(3), 1e6 * np.eye(6), ["tx"]), np.eye(4))
    c = stats.columns()
    assert c["degenerate"] == 1 and np.isnan(c["rms/crlb pos"])


def test_acquisition_bench_logs_each_case_and_adds_the_multi_scan_rows(tmp_path, capsys) -> None:
    import argparse
    import json

    from agents.benchmarks.registration import add_arguments, run_acquisition

    parser = argparse.ArgumentParser()
    add_arguments(parser)
    log = tmp_path / "acq.jsonl"
    args = parser.parse_args(["--no-peers", "--acq-only", "3", "--acq-scans", "2",
                              "--acq-log", str(log)])
    run_acquisition(args)
    out = capsys.readouterr().out
    for method in ("pah unconstrained", "pah constrained", "pah unconstrained, 2 scans",
                   "pah constrained, 2 scans"):
        assert f"| {method} " in out
    rows = [json.loads(line) for line in log.read_text().splitlines()]
    # One line per target and method, for case 3 only, with the pose error of the answer.
    assert len(rows) == 8 and {r["case"] for r in rows} == {3}
    assert {r["target"] for r in rows} == {"cubesat", "cygnss"}
    for r in rows:
        assert r["ok"] == (r["e_m"] < 0.05 and r["e_deg"] < 2.0)
        assert r["n_points"] > 50 and r["t_s"] > 0
    # The further scans come from their own generator: the single-scan case is the benchmark's.
    single = [r for r in rows if r["method"] == "pah unconstrained"]
    assert {r["target"]: r["range_m"] for r in single}["cubesat"] == pytest.approx(
        {r["target"]: r["range_m"] for r in rows if r["method"].endswith("2 scans")}["cubesat"]
    )
    with pytest.raises(ValueError, match="acq-scans"):
        run_acquisition(parser.parse_args(["--no-peers", "--acq-only", "3", "--acq-scans", "0"]))
