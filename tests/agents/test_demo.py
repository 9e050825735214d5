"""``tridar-env demo`` / ``run`` and the report folder they write."""

from __future__ import annotations

import csv
import json
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from agents.report import LOG_FIELDS, format_summary, mode_timeline, write_video
from agents.cli import main

PNGS = ("trajectory.png", "errors_vs_range.png", "modes.png", "contact.png")


def _read_log(path: Path) -> list[dict[str, str]]:
    with path.open() as f:
        return list(csv.DictReader(f))


def test_demo_docks_and_writes_the_report(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "demo"
    rc = main(["demo", "--perception", "truth", "--out", str(out), "--render-every", "150",
               "--no-progress"])
    text = capsys.readouterr().out
    assert rc == 0, text
    # one screen: result, delta-v, contact vs envelope, modes, estimation error, report path
    lines = text.strip().splitlines()
    assert len(lines) <= 24
    assert "DOCKED" in lines[1] and "glideslope" in lines[0] and "perception=truth" in lines[0]
    assert sum(line.rstrip().endswith(" ok") for line in lines) == 5
    assert any(line.startswith("modes") and "tracking" in line for line in lines)
    assert any(line.startswith("estimation") for line in lines)

    s = json.loads((out / "summary.json").read_text())
    assert s["outcome"] == "docked" and s["controller"] == "glideslope"
    assert all(c["ok"] for c in s["envelope"])
    assert 0.05 <= s["contact"]["closing_speed"] <= 0.10
    assert s["delta_v_m_s"] == pytest.approx(0.58, abs=0.1)
    cfg = yaml.safe_load((out / "config.yaml").read_text())
    assert cfg["name"] == "final_approach" and cfg["env"]["perception"] == "truth"

    rows = _read_log(out / "log.csv")
    assert list(rows[0]) == list(LOG_FIELDS)
    assert len(rows) == s["steps"]
    last = rows[-1]
    assert float(last["closing_speed"]) == pytest.approx(s["contact"]["closing_speed"])
    assert float(last["delta_v"]) == pytest.approx(s["delta_v_m_s"])
    # truth perception: the estimate the controller saw is the truth
    assert float(last["port_z_est"]) == pytest.approx(float(last["port_z_true"]), abs=1e-4)
    assert {r["mode"] for r in rows} == {"tracking"}
    pq = pytest.importorskip("pyarrow.parquet")
    table = pq.read_table(out / "log.parquet")
    assert table.num_rows == len(rows) and table.column_names == list(LOG_FIELDS)

    for name in PNGS:
        data = (out / name).read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 10_000
    video = out / s["files"]["video"]
    assert video.exists() and video.stat().st_size > 10_000
    # the first frame, one every 150 steps, and the last
    assert s["frames"] == 1 + s["steps"] // 150 + (s["steps"] % 150 != 0)


def test_run_mission_with_controller_overrides_and_config_perception(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "run"
    # no --perception: the mode comes from the (overridden) mission config
    rc = main(["run", "final_approach", "--controller", "lqr", "--set", "env.perception=truth",
               "--set", "env.initial.range_m=8", "--set", "env.initial.range_dispersion_m=0",
               "--no-video", "--out", str(out), "--no-progress"])
    text = capsys.readouterr().out
    assert rc == 0, text
    s = json.loads((out / "summary.json").read_text())
    assert s["outcome"] == "docked" and s["controller"] == "lqr" and s["perception"] == "truth"
    assert "video" not in s["files"] and s["frames"] == 0
    cfg = yaml.safe_load((out / "config.yaml").read_text())
    assert cfg["env"]["initial"]["range_m"] == 8
    rows = _read_log(out / "log.csv")
    assert float(rows[0]["axial_distance"]) == pytest.approx(8.0, abs=0.2)
    assert all(r["a3"] == "nan" for r in rows)  # 3-DOF env: no torque columns


def test_run_defaults_to_sync_on_a_six_dof_chaser(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    rc = main(["run", "tumbling_target", "--perception", "truth", "--max-steps", "40",
               "--no-video", "--out", str(tmp_path / "t"), "--no-progress"])
    text = capsys.readouterr().out
    assert rc == 1  # 40 steps do not reach the target
    s = json.loads((tmp_path / "t" / "summary.json").read_text())
    assert s["controller"] == "sync" and s["outcome"] == "timeout" and s["steps"] == 40
    assert "no contact" in text
    rows = _read_log(tmp_path / "t" / "log.csv")
    torques = np.array([[float(r[f"a{i}"]) for i in (3, 4, 5)] for r in rows])
    assert np.all(np.isfinite(torques)) and np.abs(torques).max() > 0.1  # the attitude loop acts


def test_cli_errors_name_the_bad_value(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["run", "final_approach", "--perception", "truth", "--set", "oops"]) == 2
    assert "--set 'oops'" in capsys.readouterr().err
    assert main(["run", "final_approach", "--perception", "truth", "--controller", "nope"]) == 2
    assert "controller='nope' is unknown" in capsys.readouterr().err


def test_video_falls_back_to_gif_without_ffmpeg(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from PIL import Image

    monkeypatch.setitem(sys.modules, "imageio_ffmpeg", None)  # import now raises ImportError
    rng = np.random.default_rng(0)
    frames = [rng.integers(0, 255, (48, 64, 3), dtype=np.uint8) for _ in range(5)]
    path = write_video(frames, tmp_path, fps=5)
    assert path is not None and path.name == "episode.gif"
    with Image.open(path) as im:
        assert im.n_frames == 5 and im.size == (64, 48)
    assert write_video([], tmp_path) is None


def test_mode_timeline_and_summary_stay_on_one_line() -> None:
    t = np.arange(1, 11) * 0.2
    modes = ["search"] * 3 + ["tracking"] * 5 + ["search", "tracking"]
    segs = mode_timeline(t.tolist(), modes, 0.2)
    assert [m for m, _, _ in segs] == ["search", "tracking", "search", "tracking"]
    assert segs[0][1] == 0.0 and segs[0][2] == pytest.approx(0.6)
    assert segs[1][1] == pytest.approx(0.6) and segs[1][2] == pytest.approx(1.6)
    many = [{"mode": ("search", "tracking")[i % 2], "start_s": i, "end_s": i + 1} for i in range(40)]
    s = {
        "env": "X", "controller": "c", "perception": "tridar", "seed": 0, "outcome": "timeout",
        "sim_time_s": 40.0, "steps": 200, "wall_time_s": 1.0, "delta_v_m_s": 0.1,
        "propellant_used_kg": 0.01, "envelope": [], "mode_timeline": many, "acquisitions": 20,
        "max_pos_err_m": float("nan"),
    }
    text = format_summary(s)
    line = next(x for x in text.splitlines() if x.startswith("modes"))
    assert "37 more" in line and len(line) < 100
    assert "no valid pose" in text
