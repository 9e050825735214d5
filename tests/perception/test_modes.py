"""Mode logic: transitions, strategies by range, frame judgement, restarts."""

from __future__ import annotations

import numpy as np
import pytest

from perception.config import ICPConfig, PipelineConfig, load_config
from perception.geometry import make_T
from perception.pipeline.modes import FrameVerdict, ModeLogic
from perception.pipeline import TriDAR, approach_pose
from perception.sensing.pointcloud import Subsystem
from perception.pipeline.state import Mode
from perception.targets import load_target


def _logic(**kw) -> ModeLogic:
    return ModeLogic(PipelineConfig(**kw), transition_range_m=7.0)


def test_startup_bearing_then_search_inside_range() -> None:
    m = _logic(bearing_to_search_range_m=200.0)
    assert m.mode == Mode.BEARING
    m.after_bearing(0.0, 450.0, 100, 12)
    assert m.mode == Mode.BEARING
    m.after_bearing(1.0, 150.0, 3, 12)  # too few returns
    assert m.mode == Mode.BEARING
    m.after_bearing(2.0, 150.0, 100, 12)
    assert m.mode == Mode.SEARCH
    assert m.search_too_far(3.0, 300.0) and m.mode == Mode.BEARING
    assert [e.target for e in m.events] == [Mode.SEARCH, Mode.BEARING]


def test_region_by_range_follows_fig9() -> None:
    m = _logic(roi_whole_above_m=20.0, roi_port_below_m=5.0)
    assert m.region_for_range(50.0) == "whole"
    assert m.region_for_range(10.0) == "docking_area"
    assert m.region_for_range(3.0) == "port"


def test_triangulation_settings_on_triangulation_data() -> None:
    tri = ICPConfig(max_iterations=12)
    m = _logic(icp_triangulation=tri)
    T, F = int(Subsystem.TRIANGULATION), int(Subsystem.TOF)
    assert m.icp_config_for([T, T, F]) is m.cfg.icp_triangulation
    assert m.icp_config_for([T, F, F]) is m.cfg.icp
    assert m.icp_config_for([T, F]) is m.cfg.icp  # no majority
    assert m.icp_config_for(np.zeros(0, dtype=np.int8)) is m.cfg.icp
    plain = _logic()
    assert plain.icp_config_for([T, T]) is plain.cfg.icp  # none configured


def test_triangulation_settings_follow_the_scan_not_the_target_origin() -> None:
    """At the ISS-like port the sensor ranges the hatch at 3 m by triangulation while the
    target's origin is 12 m away, beyond the 7 m transition: the scan's points decide."""
    cfg = load_config("final_approach", pipeline__icp_triangulation__max_iterations=12)
    target = load_target("iss_port")
    tri = TriDAR(cfg, target)
    T = approach_pose(cfg, target, 3.0)
    assert np.linalg.norm(T[:3, 3]) > tri.sensor.transition_range_m
    pattern, _ = tri._tracking_pattern(T)
    cloud = tri.sensor.scan(target, T, pattern, np.random.default_rng(0))
    assert cloud.count(Subsystem.TRIANGULATION) > 0.9 * len(cloud)
    assert tri.logic.icp_config_for(cloud.subsystem) is cfg.pipeline.icp_triangulation


def test_loss_of_track_after_k_bad_frames() -> None:
    m = _logic(loss_of_track_frames=3)
    m.go(0.0, Mode.TRACKING, "test")
    bad = FrameVerdict(False, "fitness")
    assert not m.record(0.2, bad) and not m.record(0.4, bad)
    assert not m.record(0.6, FrameVerdict(True))  # a good frame resets the count
    assert not m.record(0.8, bad) and not m.record(1.0, bad)
    assert m.record(1.2, bad)
    assert m.mode == Mode.SEARCH and "loss of track" in m.events[-1].reason


def test_judge_checks_fit_noise_and_jump() -> None:
    m = _logic(min_fitness=0.5, max_inlier_rmse_factor=4.0, max_jump_m=0.5, max_jump_deg=10.0)
    T = make_T(None, [0, 0, 10])
    assert m.judge(True, 0.9, 0.01, 0.01, T, T).good
    assert not m.judge(False, 0.3, 0.01, 0.01, T, T).good
    assert m.judge(False, 0.9, 0.01, 0.01, T, T).good  # slow convergence with a good fit
    assert "fitness" in m.judge(True, 0.3, 0.01, 0.01, T, T).reason
    assert "RMSE" in m.judge(True, 0.9, 0.2, 0.01, T, T).reason
    assert "jump" in m.judge(True, 0.9, 0.01, 0.01, make_T(None, [1, 0, 10]), T).reason


def test_planned_restarts_every_period() -> None:
    m = _logic(restart_period_s=300.0)
    m.go(0.0, Mode.TRACKING, "acquired")
    assert not m.restart_due(299.0)
    assert m.restart_due(300.0)
    m.restart(300.0, 30.0)
    assert m.mode == Mode.SEARCH and not m.restart_due(400.0) and m.restart_due(600.0)
    m.restart(600.0, 400.0)  # far away: back to bearing
    assert m.mode == Mode.BEARING
    assert _logic().restart_due(1e9) is False  # off by default


def test_hysteresis_is_validated() -> None:
    with pytest.raises(ValueError, match="search_to_bearing_range_m"):
        _logic(bearing_to_search_range_m=200.0, search_to_bearing_range_m=100.0)
    assert np.isfinite(_logic().transition_range_m)
