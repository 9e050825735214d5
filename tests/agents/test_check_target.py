"""``tridar-env check-target``: the readiness report on a generated mesh, and a refused mesh."""

from __future__ import annotations

import csv
import math

import pytest

from agents.cli import main
from agents.commands.check_target import MapRow, verdict
from perception.shapes import save_generated


def _args(path, port, axis) -> list[str]:
    # "--port=-0.1" style is not accepted by nargs=3; plain decimals are (no exponent notation)
    return [str(path), "--port", *(f"{v:.6f}" for v in port), "--axis", *(f"{v:.6f}" for v in axis)]


def test_flat_face_map_and_verdict(tmp_path, capsys):
    stl = tmp_path / "flat.stl"
    port, axis = save_generated("flat_face", 11, stl)
    out = tmp_path / "report"
    rc = main(["check-target", *_args(stl, port, axis), "--no-campaign", "--out", str(out)])
    text = capsys.readouterr().out
    assert rc == 0
    assert "(c) observability map" in text and "VERDICT:" in text
    assert any(w in text for w in ("VERDICT: READY", "VERDICT: DEGRADED", "VERDICT: NOT READY"))
    with (out / "observability.csv").open(newline="") as f:
        rows = list(csv.DictReader(f))
    assert [float(r["range_m"]) for r in rows] == [30.0, 20.0, 10.0, 5.0, 3.0, 2.0, 1.0]
    for r in rows:
        assert math.isfinite(float(r["port_bound_m"])) and math.isfinite(float(r["attitude_bound_deg"]))
    assert float(rows[0]["port_bound_m"]) < 0.1  # 30 m: the whole target in view pins all six axes
    for name in ("report.txt", "observability.png"):
        assert (out / name).is_file()
    assert not (out / "rows.csv").exists()  # no campaign
    # the correlated error calibrated on the model: millimetres along the line of sight (the time
    # of flight's 5 mm bias where it ranges), a figure per range that some aspect observed
    assert "(c') correlated registration error calibrated" in text
    with (out / "accuracy_calibration.csv").open(newline="") as f:
        cal = list(csv.DictReader(f))
    assert len(cal) == 8
    along = [float(r["along_m"]) for r in cal if int(r["n_along"]) > 0]
    assert len(along) >= 4 and all(0.0 <= a < 0.02 for a in along)
    assert all(math.isnan(float(r["across_m"])) == (int(r["n_across"]) == 0) for r in cal)


def test_nan_vertex_mesh_refused_in_one_line(tmp_path, capsys):
    stl = tmp_path / "broken.stl"
    stl.write_text(
        "solid broken\n"
        "facet normal 0 0 1\nouter loop\nvertex 0 0 0\nvertex 1 0 0\nvertex nan 1 0\nendloop\nendfacet\n"
        "facet normal 0 0 1\nouter loop\nvertex 0 0 0\nvertex 1 0 1\nvertex 0 1 1\nendloop\nendfacet\n"
        "endsolid broken\n"
    )
    out = tmp_path / "report"
    rc = main(["check-target", str(stl), "--port", "0", "0", "0", "--axis", "0", "0", "1",
               "--no-campaign", "--out", str(out)])
    captured = capsys.readouterr()
    assert rc == 2
    err = captured.err.strip()
    assert len(err.splitlines()) == 1
    assert "broken.stl" in err and "non-finite" in err
    assert not out.exists()  # nothing written for a refused mesh


def test_port_without_axis_refused(tmp_path, capsys):
    stl = tmp_path / "flat.stl"
    save_generated("flat_face", 11, stl)
    rc = main(["check-target", str(stl), "--port", "0", "0", "1", "--no-campaign",
               "--out", str(tmp_path / "r")])
    assert rc == 2
    assert "--port and --axis" in capsys.readouterr().err


def _row(r: float, weak: list[str], planner_weak: list[str], pl: float = 0.01) -> MapRow:
    return MapRow(range_m=r, sensor_range_m=r + 2.1, region="port", port_bound_m=pl / 5, attitude_bound_deg=0.1, weak_axes=weak,
                  n_hits=300, predicted_pl_m=pl, alert_limit_m=0.08, planner_region="port",
                  planner_port_bound_m=pl / 5, planner_attitude_bound_deg=0.1, planner_weak_axes=planner_weak)


def test_a_correlated_error_beyond_the_allowance_is_a_degraded_verdict():
    row = MapRow(range_m=10.0, sensor_range_m=10.5, region="docking_area", port_bound_m=0.002,
                 attitude_bound_deg=0.05, weak_axes=[], n_hits=400, predicted_pl_m=0.01,
                 alert_limit_m=0.1, planner_region="docking_area", planner_port_bound_m=0.002,
                 planner_attitude_bound_deg=0.05)
    word, reasons = verdict([row], None, [], ["12.3 m"])
    assert word == "DEGRADED" and any("12.3 m" in r and "allowance" in r for r in reasons)
    assert verdict([row], None, [], [])[0] == "READY"


def test_verdict_words():
    good = [_row(r, [], []) for r in (30.0, 10.0, 3.0, 1.0)]
    assert verdict(good, None, [])[0] == "READY"
    weak_far = [_row(30.0, ["rz"], []), *good[1:]]
    word, reasons = verdict(weak_far, None, [])
    assert word == "DEGRADED" and any("30 m" in r for r in reasons)
    blind = [good[0], good[1], _row(3.0, ["tx", "ty"], ["tx"], 1e3), _row(1.0, ["tx", "ty"], ["tx"], 1e3)]
    word, reasons = verdict(blind, None, [])
    assert word == "NOT READY" and any("inside 5 m" in r for r in reasons)
    camp = {"truth": {"docked_pct": 100.0, "terminations": "docked 2"},
            "tridar": {"docked_pct": 100.0, "terminations": "docked 2", "hmi": 1, "mi": 1,
                       "max_err_valid_m": 0.2}}
    word, reasons = verdict(good, camp, [])
    assert word == "NOT READY" and any("hazardously misleading" in r for r in reasons)
    camp["tridar"]["hmi"] = camp["tridar"]["mi"] = 0
    word, reasons = verdict(good, camp, [((2.0, 5.0), 100, 0.3)])
    assert word == "DEGRADED" and any("2-5 m (30 %" in r for r in reasons)


@pytest.mark.parametrize("bad", [["--runs", "0"]])
def test_bad_runs_refused(tmp_path, bad, capsys):
    stl = tmp_path / "flat.stl"
    port, axis = save_generated("flat_face", 11, stl)
    assert main(["check-target", *_args(stl, port, axis), *bad, "--out", str(tmp_path / "r")]) == 2
