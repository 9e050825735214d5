"""Replay on data from elsewhere: a PLY folder written with trimesh from simulated scans of known
poses replays with centimetre accuracy; PCD files read back exactly; a ROS 2 bag-style MCAP with
``PointCloud2`` in ROS axes replays the same; bad files are one line each and the rest is kept."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest
import trimesh

from agents.cli import main
from agents.replay_sources import RawFrame, clouds_from_mcap, load_folder, read_pcd, to_cloud
from perception.config import config_path, load_config
from perception.geometry import fast_matrix_to_quat
from perception.pipeline import TriDAR
from perception.pipeline.tridar import approach_pose
from tridar_env.env import make_target

FRAMES = 25


@pytest.fixture(scope="module")
def scans():
    """Full-field scans of the ISS-like port closing from 18 m with a lateral offset: (t, cloud,
    T_sensor_target) per frame at the pipeline's frame rate."""
    cfg = load_config(config_path("final_approach"))
    target = make_target(cfg)
    tri = TriDAR(cfg, target)
    rng = np.random.default_rng(7)
    out = []
    for i in range(FRAMES):
        t = i / cfg.pipeline.frame_rate_hz
        T = approach_pose(cfg, target, 18.0 - 0.1 * t, lateral=(0.3, -0.2))
        out.append((t, tri.sensor.scan(target, T, tri.bearing.full_field(), rng, t0=t), T))
    return out


def _write_truth(path: Path, scans) -> None:
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["t", "x", "y", "z", "qw", "qx", "qy", "qz"])
        for t, _, T in scans:
            w.writerow([repr(float(v)) for v in (t, *T[:3, 3], *fast_matrix_to_quat(T[:3, :3]))])


def _errors(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    with open(path) as fh:
        rows = list(csv.DictReader(fh))
    valid = np.array([int(r["pose_valid"]) for r in rows], dtype=bool)
    pe = np.array([float(r["pos_err_m"]) for r in rows])
    ae = np.array([float(r["att_err_deg"]) for r in rows])
    return valid, pe, ae


def _assert_accurate(csv_path: Path) -> None:
    valid, pe, ae = _errors(csv_path)
    assert valid.sum() >= FRAMES - 8, f"only {valid.sum()} valid poses of {FRAMES} frames"
    assert np.median(pe[valid]) < 0.02 and pe[valid].max() < 0.05, pe[valid]
    assert np.median(ae[valid]) < 0.2, ae[valid]


def test_ply_folder_replays_with_expected_accuracy(scans, tmp_path: Path, capsys) -> None:
    folder = tmp_path / "frames"
    folder.mkdir()
    rows = []
    for i, (t, cloud, _) in enumerate(scans):
        name = f"frame_{i:03d}.ply"
        trimesh.PointCloud(cloud.points).export(folder / name)  # float32, as scanners write them
        rows.append((name, t))
    # A file cut short, listed like the good ones: one line, the others kept.
    bad = folder / "frame_012b.ply"
    bad.write_bytes((folder / "frame_012.ply").read_bytes()[:300])
    rows.append((bad.name, 2.45))
    with open(folder / "timestamps.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["file", "t"])
        w.writerows(rows)
    _write_truth(tmp_path / "truth.csv", scans)
    out = tmp_path / "err.csv"
    code = main(["replay", str(folder), "--truth", str(tmp_path / "truth.csv"), "--mission",
                 "final_approach", "--csv", str(out)])
    assert code == 0
    err = capsys.readouterr().err.strip().splitlines()
    bad_lines = [ln for ln in err if "frame_012b.ply" in ln]
    assert len(bad_lines) == 1 and "truncated" in bad_lines[0], err
    _assert_accurate(out)


def test_frames_without_times_need_a_rate(scans, tmp_path: Path) -> None:
    for i, (_, cloud, _) in enumerate(scans[:3]):
        trimesh.PointCloud(cloud.points).export(tmp_path / f"f{i}.ply")
    with pytest.raises(ValueError, match="--rate"):
        load_folder(tmp_path)
    frames = load_folder(tmp_path, rate_hz=5.0)
    assert [f.t for f in frames] == [0.0, 0.2, 0.4]


def test_pcd_ascii_and_binary_read_back(scans, tmp_path: Path) -> None:
    _, cloud, _ = scans[0]
    p, inten = cloud.points, cloud.intensity
    n = len(p)
    head = ("# .PCD v0.7\nVERSION 0.7\nFIELDS x y z intensity\nSIZE 8 8 8 8\nTYPE F F F F\n"
            f"COUNT 1 1 1 1\nWIDTH {n}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\n")
    body = "\n".join(" ".join(repr(float(v)) for v in (*p[i], inten[i])) for i in range(n))
    (tmp_path / "a.pcd").write_text(head + "DATA ascii\n" + body + "\n")
    rec = np.column_stack([p, inten]).astype("<f8")
    (tmp_path / "b.pcd").write_bytes((head + "DATA binary\n").encode() + rec.tobytes())
    (tmp_path / "c.pcd").write_bytes((head + "DATA binary\n").encode() + rec.tobytes()[:100])
    for name in ("a.pcd", "b.pcd"):
        f = read_pcd(tmp_path / name)
        np.testing.assert_array_equal(np.column_stack([f["x"], f["y"], f["z"]]), p)
        np.testing.assert_array_equal(f["intensity"], inten)
    with pytest.raises(ValueError, match="truncated"):
        read_pcd(tmp_path / "c.pcd")


def test_bag_topic_in_ros_axes_replays(scans, tmp_path: Path) -> None:
    from mcap_ros2.writer import Writer

    from tridar_env.ros2msgs import msgdef, stamp

    R_ros_optical = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    bag = tmp_path / "bag.mcap"
    with open(bag, "wb") as fh, Writer(fh) as w:
        schema = w.register_msgdef("sensor_msgs/msg/PointCloud2", msgdef("sensor_msgs/msg/PointCloud2"))
        w.register_msgdef("std_msgs/msg/String", "string data\n")
        for t, cloud, _ in scans:
            xyz = (cloud.points @ R_ros_optical.T).astype("<f4")
            rec = np.zeros(len(xyz), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("intensity", "<f4")])
            rec["x"], rec["y"], rec["z"] = xyz.T
            rec["intensity"] = cloud.intensity
            fields = [{"name": n, "offset": 4 * i, "datatype": 7, "count": 1}
                      for i, n in enumerate(("x", "y", "z", "intensity"))]
            w.write_message("/lidar/points", schema, {
                "header": {"stamp": stamp(t), "frame_id": "lidar"}, "height": 1, "width": len(rec),
                "fields": fields, "is_bigendian": False, "point_step": 16, "row_step": 16 * len(rec),
                "data": rec.tobytes(), "is_dense": True}, log_time=int(t * 1e9))
    frames = clouds_from_mcap(bag, "/lidar/points")
    assert len(frames) == FRAMES
    sensor = TriDAR(load_config(config_path("final_approach")), make_target(
        load_config(config_path("final_approach")))).sensor
    back = to_cloud(frames[0], sensor, axes="ros")
    np.testing.assert_allclose(back.points, scans[0][1].points, atol=1e-5)
    _write_truth(tmp_path / "truth.csv", scans)
    out = tmp_path / "err.csv"
    assert main(["replay", str(bag), "--topic", "/lidar/points", "--axes", "ros", "--truth",
                 str(tmp_path / "truth.csv"), "--csv", str(out)]) == 0
    _assert_accurate(out)
    assert main(["replay", str(bag), "--topic", "/nothing"]) == 2


def test_bad_points_are_dropped_with_one_line(scans) -> None:
    _, cloud, _ = scans[0]
    xyz = cloud.points.copy()
    xyz[:5] = np.nan
    xyz[5] = 0.0
    lines: list[str] = []
    frame = RawFrame(0.0, {"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2]}, "lab/frame0.pcd")
    c = to_cloud(frame, None, warn=lines.append)
    assert len(c) == len(xyz) - 6
    assert lines == [f"lab/frame0.pcd: 6 of {len(xyz)} points not finite or at the origin; dropped"]


def test_demo_record_then_replay_is_bitwise(tmp_path: Path, capsys) -> None:
    rec = tmp_path / "demo.mcap"
    code = main(["demo", "--max-steps", "20", "--no-video", "--no-progress", "--out",
                 str(tmp_path / "report"), "--record", str(rec)])
    assert code in (0, 1) and rec.is_file()
    capsys.readouterr()
    assert main(["replay", str(rec), "--plot", str(tmp_path / "e.png")]) == 0
    out = capsys.readouterr().out
    line = next(ln for ln in out.splitlines() if "bitwise equal" in ln)
    n, m = line.rsplit(": ", 1)[1].split(" of ")
    assert int(n) == int(m) > 0
    assert (tmp_path / "e.png").stat().st_size > 0


def test_campaign_records_every_run(tmp_path: Path) -> None:
    import os

    from agents.runner import RECORD_DIR_ENV

    rec = tmp_path / "recs"
    args = ["campaign", "final_approach_truth", "--serial", "--runs", "2", "--max-steps", "3",
            "--out", str(tmp_path / "camp"), "--record", str(rec), "--no-plots", "--no-progress"]
    assert main(args) == 0
    assert sorted(p.name for p in rec.glob("*.mcap")) == ["run-000000.mcap", "run-000001.mcap"]
    assert RECORD_DIR_ENV not in os.environ
    foreign = tmp_path / "foreign"
    foreign.mkdir()
    (foreign / "notes.txt").write_text("mine")
    args[args.index(str(rec))] = str(foreign)
    args[args.index(str(tmp_path / "camp"))] = str(tmp_path / "camp2")
    assert main(args) == 2
    assert [p.name for p in foreign.iterdir()] == ["notes.txt"]
