"""Campaigns side by side (`agents.campaign_compare`, `tridar-env compare`) on folders the tests
write themselves, with known numbers."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml

from agents.campaign_compare import compare, plot_error_vs_range, read_campaign
from agents.cli import main
from agents.episode import wilson_interval


def _campaign(folder: Path, perception: str, docked: list[bool], *, seed: int = 7,
              err_mm: float = 2.0, done: int | None = None) -> Path:
    """A campaign folder as `tridar-env campaign` leaves it: campaign.yaml and one part per run."""
    (folder / "parts").mkdir(parents=True)
    spec = {"name": folder.name, "env_id": "TriDAR/TumblingTarget-v0", "mission": None,
            "perception": perception, "controller": "sync", "runs": len(docked), "seed": seed,
            "max_steps": None, "config": {}, "dispersions": {"env__initial__range_m": {"uniform": [50, 60]}}}
    (folder / "campaign.yaml").write_text(yaml.safe_dump(spec))
    for i, d in enumerate(docked[:done]):
        rng = np.linspace(60.0, 1.0, 50)
        row = {"index": i, "env_seed": 1000 + i + 17 * seed, "outcome": "docked" if d else "timeout",
               "docked": d, "steps": 1000, "wall_time_s": 20.0 if perception == "tridar" else 60.0,
               "hmi_steps": 1 if (i == 0 and perception == "flash") else 0,
               "rms_pos_err_m": err_mm * 1e-3, "max_pos_err_m": 2 * err_mm * 1e-3,
               "rms_att_err_deg": 0.1, "delta_v_m_s": 2.0, "trace_range_m": rng,
               "trace_pos_err_m": np.where(rng < 10, err_mm, 3 * err_mm) * 1e-3,
               "trace_att_err_deg": np.full(50, 0.1)}
        pd.DataFrame([row]).to_parquet(folder / "parts" / f"run_{i:06d}.parquet", index=False)
    return folder


def test_paired_campaigns_are_compared_run_for_run(tmp_path: Path) -> None:
    a = read_campaign(_campaign(tmp_path / "a", "tridar", [True, True, False, True, False]))
    b = read_campaign(_campaign(tmp_path / "b", "flash", [True, False, True, True, False], err_mm=1.0))
    c = compare([a, b], bins=(0.0, 10.0, 100.0))
    assert c.paired and c.common_runs == 5
    sa, sb = c.summary
    assert (sa["docked"], sb["docked"]) == (3, 3)
    lo, hi = wilson_interval(3, 5)
    assert sa["Wilson 95%"] == f"[{lo:.1%}, {hi:.1%}]"
    assert (sa["valid-but-wrong steps"], sb["valid-but-wrong steps"]) == (0, 1)
    assert sa["wall per step, median run [ms]"] == pytest.approx(20.0) and sb["RMS pos err, median run [mm]"] == pytest.approx(1.0)
    # error by range: 2 mm under 10 m, 6 mm beyond for a; half that for b
    rows = {(r["campaign"], r["range [m]"]): r for r in c.by_range}
    assert rows[("a", "0-10")]["pos RMS [mm]"] == pytest.approx(2.0)
    assert rows[("a", "10-100")]["pos max [mm]"] == pytest.approx(6.0)
    assert rows[("b", "10-100")]["pos RMS [mm]"] == pytest.approx(3.0)
    assert rows[("a", "0-10")]["samples"] == 5 * int(np.sum(np.linspace(60.0, 1.0, 50) < 10))
    (p,) = c.pairs
    assert (p["both docked"], p["only a"], p["only b"], p["neither"]) == (2, 1, 1, 1)


def test_a_running_campaign_is_compared_on_the_runs_both_finished(tmp_path: Path) -> None:
    a = read_campaign(_campaign(tmp_path / "a", "tridar", [True] * 6))
    b = read_campaign(_campaign(tmp_path / "b", "flash", [True] * 6, done=4))
    c = compare([a, b])
    assert c.common_runs == 4 and all(r["runs"] == 4 for r in c.summary)


def test_different_seeds_are_not_paired(tmp_path: Path) -> None:
    a = read_campaign(_campaign(tmp_path / "a", "tridar", [True, False]))
    b = read_campaign(_campaign(tmp_path / "b", "flash", [True, False], seed=8))
    c = compare([a, b])
    assert not c.paired and c.pairs == []
    assert "paired: NO" in c.format()


def test_refusals_name_the_problem(tmp_path: Path) -> None:
    (tmp_path / "empty").mkdir()
    with pytest.raises(ValueError, match="no campaign.yaml"):
        read_campaign(tmp_path / "empty")
    a = read_campaign(_campaign(tmp_path / "a", "tridar", [True, False]))
    with pytest.raises(ValueError, match="at least 2"):
        compare([a])
    with pytest.raises(ValueError, match=r"bins=\[5.0, 1.0\]"):
        compare([a, a], bins=(5.0, 1.0))
    existing = tmp_path / "plot.png"
    existing.write_bytes(b"mine")
    with pytest.raises(ValueError, match="exists"):
        plot_error_vs_range([a, a], existing)
    assert existing.read_bytes() == b"mine"


def test_the_command_prints_the_tables_and_draws_a_new_plot(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    _campaign(tmp_path / "a", "tridar", [True, True, False])
    _campaign(tmp_path / "b", "flash", [True, True, True])
    plot = tmp_path / "err.png"
    assert main(["compare", str(tmp_path / "a"), str(tmp_path / "b"), "--labels", "TriDAR", "flash",
                 "--plot", str(plot)]) == 0
    out = capsys.readouterr().out
    assert "paired: yes" in out
    (pair,) = [line for line in out.splitlines() if line.startswith("| TriDAR vs flash")]
    assert [c.strip() for c in pair.strip("|").split("|")[1:]] == ["2", "0", "1", "0"]
    assert plot.read_bytes()[:4] == b"\x89PNG"
    assert main(["compare", str(tmp_path / "a"), str(tmp_path / "b"), "--labels", "x"]) != 0
