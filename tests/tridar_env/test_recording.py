"""Recording to MCAP: ROS 2 schemas read back with the ``mcap`` reader, the config inside as JSON,
replay bitwise equal to the live run, refusal of an existing file, damaged files keep good frames."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("mcap_ros2")

from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory

from agents.replay import load_recording, replay
from perception.config import MissionConfig
from tests.recorded_run import record_run
from tridar_env.recording import RecordMCAP, state_to_dict

ROS2_SCHEMAS = {
    "/tridar/points": "sensor_msgs/msg/PointCloud2",
    "/tridar/estimate": "geometry_msgs/msg/PoseWithCovarianceStamped",
    "/truth/pose": "geometry_msgs/msg/PoseStamped",
}


@pytest.fixture(scope="module")
def run(tmp_path_factory: pytest.TempPathFactory):
    return record_run(tmp_path_factory.mktemp("rec"))


def test_mcap_reads_back_with_ros2_schemas(run) -> None:
    with open(run.path, "rb") as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        assert reader.get_header().profile == "ros2"
        summary = reader.get_summary()
        by_topic = {ch.topic: (ch, summary.schemas[ch.schema_id]) for ch in summary.channels.values()}
        for topic, name in ROS2_SCHEMAS.items():
            ch, schema = by_topic[topic]
            assert schema.name == name and schema.encoding == "ros2msg" and ch.message_encoding == "cdr"
            text = schema.data.decode()
            assert "=" * 80 + "\nMSG: std_msgs/Header" in text  # dependencies, ros2msg style
        for topic in ("/tridar/state", "/tridar/scan_region", "/env/step"):
            ch, schema = by_topic[topic]
            assert ch.message_encoding == "json" and schema.encoding == "jsonschema"
            assert json.loads(schema.data)["type"] == "object"
        state_schema = json.loads(by_topic["/tridar/state"][1].data)
        assert {"mode", "pose_valid", "protection_level"} <= set(state_schema["properties"])
        clouds = [m for _, ch, _, m in reader.iter_decoded_messages(topics=["/tridar/points"])]
    assert clouds, "no PointCloud2 messages"
    last = clouds[-1]
    names = [f.name for f in last.fields]
    assert names[:6] == ["x", "y", "z", "t", "intensity", "sigma"] and "subsystem" in names
    assert last.header.frame_id == "tridar" and last.width == len(run.last_cloud_points)
    off = {f.name: f.offset for f in last.fields}
    dt = np.dtype({"names": ["x", "y", "z"], "formats": ["<f8"] * 3,
                   "offsets": [off["x"], off["y"], off["z"]], "itemsize": last.point_step})
    rec = np.frombuffer(bytes(last.data), dtype=dt, count=last.width)
    xyz = np.column_stack([rec["x"], rec["y"], rec["z"]])
    np.testing.assert_array_equal(xyz, run.last_cloud_points)  # full precision
    with open(run.path, "rb") as fh:
        reader = make_reader(fh)
        att = {a.name: a for a in reader.iter_attachments()}
        meta = {m.name: m.metadata for m in reader.iter_metadata()}
    cfg = MissionConfig.model_validate_json(att["mission_config.json"].data)  # JSON text, not pickle
    assert cfg == run.cfg
    assert meta["tridar-env"]["perception"] == "tridar"


def test_estimate_message_carries_pose_and_covariance(run) -> None:
    with open(run.path, "rb") as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        est = [m for _, _, _, m in reader.iter_decoded_messages(topics=["/tridar/estimate"])]
        states = [json.loads(m.data) for _, _, m in reader.iter_messages(topics=["/tridar/state"])]
    assert est and states
    valid = [s for s in states if s["valid"]["position"] and s["valid"]["attitude"]]
    assert len(est) == len(valid)
    last = est[-1].pose
    cov = np.array(last.covariance).reshape(6, 6)
    assert np.all(np.diag(cov) > 0) and np.allclose(cov, cov.T)
    q = np.array([last.pose.orientation.w, last.pose.orientation.x, last.pose.orientation.y,
                  last.pose.orientation.z])
    assert abs(np.linalg.norm(q) - 1.0) < 1e-9
    assert {"mode", "protection_level", "pose_valid"} <= set(states[-1])


def test_replay_with_recorded_settings_is_bitwise(run) -> None:
    src = load_recording(run.path)
    res = replay(src.items, src.cfg, exact=True)
    assert res.compared > 0 and res.bitwise_equal == res.compared
    modes = {int(sv.mode) for sv in res.states}
    assert {1, 2} <= modes, f"the run should search and track; modes {modes}"
    # Against the env's own state vectors too (not only the recorded copies): the last pipeline
    # output at each step's time is what the env observed.
    by_t = {sv.t: state_to_dict(sv) for sv in res.states}
    for sv in run.live:
        assert json.dumps(by_t[sv.t], sort_keys=True) == json.dumps(state_to_dict(sv), sort_keys=True)


def test_replay_with_other_settings_differs_but_runs(run) -> None:
    src = load_recording(run.path)
    from agents.replay import resolve_replay_config

    cfg = resolve_replay_config(src.cfg, None, {"pipeline__icp__max_iterations": 3})
    res = replay(src.items, cfg, exact=False)
    assert not res.exact and len(res.states) == res.frames_offered
    e = res.errors()
    ok = np.isfinite(e["pos_err_m"])
    assert ok.any() and np.nanmedian(e["pos_err_m"]) < 0.1


def test_existing_file_is_refused_and_untouched(tmp_path: Path) -> None:
    import gymnasium as gym

    target = tmp_path / "mine.mcap"
    target.write_bytes(b"not yours")
    env = gym.make("TriDAR/FinalApproach-v0", perception="truth")
    with pytest.raises(ValueError, match="exists; refusing"):
        RecordMCAP(env, target)
    assert target.read_bytes() == b"not yours"
    from agents.cli import main

    assert main(["demo", "--perception", "truth", "--max-steps", "2", "--no-video", "--no-progress",
                 "--out", str(tmp_path / "rep"), "--record", str(target)]) == 2
    assert target.read_bytes() == b"not yours"
    env.close()


def test_truncated_file_keeps_good_frames(run, tmp_path: Path) -> None:
    raw = run.path.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(raw[: int(len(raw) * 0.6)])
    lines: list[str] = []
    src = load_recording(cut, warn=lines.append)
    assert len(lines) == 1 and str(cut) in lines[0] and "truncated" in lines[0]
    full = load_recording(run.path)
    n_cut = sum(it.kind == "frame" for it in src.items)
    assert 0 < n_cut < sum(it.kind == "frame" for it in full.items)
    res = replay(src.items, src.cfg, exact=True)
    assert res.bitwise_equal == res.compared == n_cut


def test_truth_perception_records_states_without_clouds(tmp_path: Path) -> None:
    import gymnasium as gym

    from tridar_env.mcap_log import read_mcap

    path = tmp_path / "truth.mcap"
    env = RecordMCAP(gym.make("TriDAR/FinalApproach-v0", perception="truth"), path)
    env.reset(seed=0)
    for _ in range(3):
        env.step(np.zeros(3, dtype=np.float32))
    env.close()
    c = read_mcap(path)
    topics = c.topics()
    assert topics["/truth/pose"] == "geometry_msgs/msg/PoseStamped"
    assert "/tridar/points" not in topics and len(c.topic("/env/step")) == 4
    with pytest.raises(ValueError, match="no pipeline frames"):
        load_recording(path)


def test_cdr_encoders_match_mcap_ros2_support() -> None:
    """The direct CDR encoders write the bytes mcap-ros2-support's generic encoder writes."""
    from mcap_ros2._dynamic import serialize_dynamic

    from tridar_env import ros2msgs as m

    rng = np.random.default_rng(0)
    n = 9
    msgs = {
        "sensor_msgs/msg/PointCloud2": m.pointcloud2(
            rng.random((n, 3)), rng.random(n), rng.random(n), rng.random(n), rng.random((n, 3)),
            rng.integers(0, 2, n).astype(np.int8), rng.random(n) < 0.2, 12.345678901),
        "geometry_msgs/msg/PoseStamped": m.pose_stamped(3.2, rng.random(3), np.array([0.5, 0.5, 0.5, 0.5])),
        "geometry_msgs/msg/PoseWithCovarianceStamped": m.pose_with_covariance_stamped(
            7.0, rng.random(3), np.array([1.0, 0.0, 0.0, 0.0]), rng.random((12, 12)), frame_id="sensor_x"),
    }
    assert set(msgs) == set(m.ENCODERS)
    for name, msg in msgs.items():
        reference = serialize_dynamic(name, m.MSG_TEXT[name])[name]
        assert m.ENCODERS[name](msg) == reference(msg), name
