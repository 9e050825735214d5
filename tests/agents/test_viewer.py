"""The rerun viewer's file: ``tridar-env view FILE.mcap --save FILE.rrd`` writes an .rrd that, read
back with rerun's own reader, holds the expected entity paths with one entry per recorded item."""

from __future__ import annotations

from pathlib import Path

import pytest

rr = pytest.importorskip("rerun")
pytest.importorskip("mcap_ros2")

from agents.cli import main
from agents.viewer import ENTITY_PATHS
from tests.recorded_run import record_run
from tridar_env.mcap_log import read_mcap


@pytest.fixture(scope="module")
def run(tmp_path_factory: pytest.TempPathFactory):
    return record_run(tmp_path_factory.mktemp("view"), steps=25)


def _rows_by_entity(rrd: Path) -> dict[str, int]:
    rows: dict[str, int] = {}
    for chunk in rr.chunk.RrdReader(rrd).stream():
        rows[chunk.entity_path] = rows.get(chunk.entity_path, 0) + chunk.num_rows
    return rows


def test_saved_rrd_holds_the_expected_entities(run, tmp_path: Path) -> None:
    rrd = tmp_path / "run.rrd"
    assert main(["view", str(run.path), "--save", str(rrd)]) == 0
    rows = _rows_by_entity(rrd)
    missing = {f"/{p}" for p in ENTITY_PATHS} - set(rows)
    assert not missing, f"entities missing from {rrd}: {sorted(missing)}"
    c = read_mcap(run.path)
    # One point cloud per recorded scan, one truth transform per truth message, one scalar per
    # published state: the viewer shows every recorded frame, not a sample.
    assert rows["/sensor/points"] == len(c.topic("/tridar/points")) > 0
    assert rows["/sensor/target_truth"] == len(c.topic("/truth/pose"))
    assert rows["/plots/mode"] == len(c.topic("/tridar/state"))
    assert rows["/plots/position_error_m"] > 0


def test_save_refuses_an_existing_file(run, tmp_path: Path, capsys) -> None:
    rrd = tmp_path / "keep.rrd"
    rrd.write_bytes(b"someone's")
    assert main(["view", str(run.path), "--save", str(rrd)]) == 2
    assert rrd.read_bytes() == b"someone's"
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "exists" in err[0]


def test_no_display_is_one_line_not_a_hang(run, monkeypatch, capsys) -> None:
    import sys

    if not sys.platform.startswith("linux"):
        pytest.skip("the display check is for Linux")
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    assert main(["view", str(run.path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--save" in err[0]
