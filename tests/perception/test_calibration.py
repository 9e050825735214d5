"""The published covariance calibrated on the target's own model (perception.pipeline.calibration)."""

from __future__ import annotations

import numpy as np
import pytest

from perception.config import load_config
from perception.pipeline import TriDAR, approach_pose
from perception.pipeline.calibration import AccuracyTable, calibrate_accuracy, calibration_ranges
from perception.pipeline.integrity import integrity_factor, port_covariance, protection_level, turn_about
from perception.pipeline.state import TruthScene
from perception.shapes import generate_target


def _table(cfg, target, poses: int = 6):  # type: ignore[no-untyped-def]
    tri = TriDAR(cfg, target)
    return tri, tri.accuracy_table()


def test_calibration_finds_the_time_of_flights_range_bias_along_the_line_of_sight() -> None:
    """A 3 cm range bias on the time of flight is a correlated error along the line of sight at
    every range it ranges (beyond the transition), the same at every aspect: the calibration
    reports it there (with the shape's own offset of a few millimetres), not across the line of
    sight, and not where triangulation ranges."""
    target = generate_target("assembly", 11)
    kw = dict(pipeline__integrity__accuracy_calibration_poses=6, pipeline__integrity__accuracy_calibration_ranges=6)
    tri0, plain = _table(load_config("final_approach", sensor__tof__bias_m=0.0, **kw), target)
    _, biased = _table(load_config("final_approach", sensor__tof__bias_m=0.03, **kw), target)
    tof = tri0.sensor.transition_range_m
    seen = np.isfinite(biased.along_m)
    far = seen & (biased.range_m > 1.2 * tof)
    near = seen & (biased.range_m < 0.8 * tof)
    assert far.sum() >= 2 and near.sum() >= 1
    np.testing.assert_allclose(biased.along_m[far], 0.03, atol=0.008)
    assert np.all(plain.along_m[np.isfinite(plain.along_m) & (plain.range_m > 1.2 * tof)] < 0.012)
    # across it, millimetres within 30 m (the beam's footprint grows beyond)
    assert np.nanmax(biased.across_m[biased.range_m < 30.0]) < 0.008
    # triangulation does not see the time of flight's bias
    assert np.all(biased.along_m[near] < 0.012)
    # a figure is a 1-sigma over the aspects that observed it (NaN where none did)
    assert biased.samples.shape == (len(biased.range_m), 3) and biased.samples.max() <= 6
    assert np.array_equal(np.isfinite(biased.along_m), biased.samples[:, 0] > 0)


def test_calibration_is_the_models_own_and_leaves_the_closed_loop_alone() -> None:
    """The calibration draws from its own generator: it is the same table every time, and a
    pipeline with it publishes the same poses, protection levels and validity as one without,
    only another covariance (its figures, clipped to the protection level's allowance)."""
    target = generate_target("assembly", 7)
    cfg_on = load_config("final_approach", pipeline__use_corridor=False,
                         pipeline__integrity__accuracy_calibration_poses=4,
                         pipeline__integrity__ambiguity_check_period_s=None)
    cfg_off = load_config("final_approach", pipeline__use_corridor=False,
                          pipeline__integrity__ambiguity_check_period_s=None)
    ranges = calibration_ranges(2.0, 20.0, 3)
    a = calibrate_accuracy(TriDAR(cfg_on, target), ranges, 4, 3, np.random.default_rng(5))
    b = calibrate_accuracy(TriDAR(cfg_on, target), ranges, 4, 3, np.random.default_rng(5))
    for f in ("range_m", "across_m", "along_m", "attitude_rad", "samples"):
        assert np.array_equal(getattr(a, f), getattr(b, f), equal_nan=True)

    def track(cfg):  # type: ignore[no-untyped-def]
        tri = TriDAR(cfg, target)
        tri.reset(np.random.default_rng(1))
        tri.prepare()
        T0 = approach_pose(cfg, target, 4.0)
        tri.seed_pose(T0, 0.0)
        svs = [tri.step(TruthScene(T0, 0.2 * k), 0.2 * k) for k in range(20)]
        return tri, [sv for sv in svs if sv.valid.position]

    on, svs_on = track(cfg_on)
    off, svs_off = track(cfg_off)
    assert on.publisher.accuracy is not None and off.publisher.accuracy is None
    assert len(svs_on) == len(svs_off) >= 10
    ig = cfg_on.pipeline.integrity
    k = integrity_factor(ig.risk)
    r = target.T_target_port[:3, 3]
    changed = 0
    for x, y in zip(svs_on, svs_off, strict=True):
        assert np.array_equal(x.position, y.position) and np.array_equal(x.quaternion, y.quaternion)
        assert x.protection_level == y.protection_level and x.valid == y.valid
        changed += not np.array_equal(x.covariance, y.covariance)
        R = x.T_sensor_target[:3, :3]
        assert x.protection_level >= protection_level(port_covariance(x.covariance, R, r), k)
    assert changed == len(svs_on)


def test_published_covariance_carries_the_calibrated_figures_at_the_range_clipped_to_the_allowance() -> None:
    """Across and along the line of sight at the port, and in attitude as a turn about the port:
    exactly the table's figures interpolated at the port's range, each no larger than the
    protection level's allowance there; nothing else moves."""
    target = generate_target("assembly", 7)
    cfg = load_config("final_approach", pipeline__use_corridor=False,
                      pipeline__integrity__ambiguity_check_period_s=None)
    ig = cfg.pipeline.integrity

    def table(across: float, along: float, att: float) -> AccuracyTable:
        return AccuracyTable(np.array([1.0, 10.0]), np.full(2, across), np.full(2, along),
                             np.full(2, att), np.full((2, 3), 3))

    def track(tab):  # type: ignore[no-untyped-def]
        tri = TriDAR(cfg, target)
        tri.reset(np.random.default_rng(1))
        tri.publisher.accuracy = tab
        T0 = approach_pose(cfg, target, 4.0)
        tri.seed_pose(T0, 0.0)
        svs = [tri.step(TruthScene(T0, 0.2 * k), 0.2 * k) for k in range(16)]
        return [sv for sv in svs if sv.valid.position]

    zero, small, huge = track(table(0.0, 0.0, 0.0)), track(table(0.001, 0.002, 1e-4)), track(table(1.0, 1.0, 1.0))
    r = target.T_target_port[:3, 3]
    assert len(zero) >= 8
    for a, b, h in zip(zero, small, huge, strict=True):
        assert np.array_equal(a.position, b.position) and a.protection_level == h.protection_level
        R = a.T_sensor_target[:3, :3]
        port = R @ r + a.position
        u = port / np.linalg.norm(port)
        P = np.eye(3) - np.outer(u, u)
        expect = a.covariance.copy()
        expect[0:3, 0:3] += 0.001**2 * P + 0.002**2 * np.outer(u, u)
        np.testing.assert_allclose(b.covariance, turn_about(expect, R, r, 1e-8), atol=1e-15)
        # clipped: never more than the protection level's allowance (bias_m at 4 m, triangulated)
        bias = max(ig.bias_m, ig.bias_rad * float(np.linalg.norm(port)))
        d = port_covariance(h.covariance, R, r) - port_covariance(a.covariance, R, r)
        np.testing.assert_allclose(d, bias**2 * np.eye(3), atol=1e-12)
        k = integrity_factor(ig.risk)
        assert h.protection_level >= protection_level(port_covariance(h.covariance, R, r), k)


def test_bad_calibration_settings_are_refused_with_the_value() -> None:
    with pytest.raises(ValueError, match="calibration ranges 5.0..2.0 m"):
        calibration_ranges(5.0, 2.0, 4)
    with pytest.raises(ValueError, match="accuracy_calibration_repeats"):
        load_config("final_approach", pipeline__integrity__accuracy_calibration_repeats=1)
    with pytest.raises(ValueError, match="accuracy_calibration_poses"):
        load_config("final_approach", pipeline__integrity__accuracy_calibration_poses=0)
