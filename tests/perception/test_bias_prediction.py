"""The registrations' bias predicted from the sensor model (TrackingMode.predict_bias) against
the bias noisy scans actually have, on a generated shape."""

from __future__ import annotations

import dataclasses

import numpy as np

from perception.config import load_config
from perception.estimation.registration import icp
from perception.geometry import los_basis
from perception.pipeline import TriDAR, approach_pose
from perception.shapes import generate_target
from perception.targets import RegionOfInterest


def _measured_and_predicted(divergence_rad: float, n: int = 12) -> tuple[np.ndarray, np.ndarray]:
    """Across-sight port errors [mm] (mean over ``n`` noisy scans) and the predicted bias [mm]
    (mean of the probes), a generated boxes-and-booms target at 22 m, 0.57 m off the axis, its
    port region doubled scanned (what the planner picks there in flight)."""
    target = generate_target("boxes_and_booms", 9494)
    cfg = load_config("final_approach", pipeline__integrity__bias_prediction_frames=5)
    s = cfg.sensor
    cfg = cfg.model_copy(update={"sensor": s.model_copy(update={
        "tof": s.tof.model_copy(update={"bias_m": 0.0}),
        "beam": s.beam.model_copy(update={"divergence_rad": divergence_rad})})})
    tri = TriDAR(cfg, target)
    T = approach_pose(cfg, target, 22.0, (0.4, 0.4))
    r_port = target.T_target_port[:3, 3]
    port = T[:3, :3] @ r_port + T[:3, 3]
    B = los_basis(port)
    h = 2.0 * max(target.regions["port"].half_extents)
    roi = RegionOfInterest("port_x2", tuple(r_port), (h, h, h))
    rng = np.random.default_rng(1)
    tm = tri.tracking
    errors, probes = [], []
    for k in range(n):
        pattern = tri.sensor.make_scan_pattern(k, T, roi)
        cloud = tri.sensor.scan(target, T, pattern, rng)
        icp_cfg = tri.logic.icp_config_for(cloud.subsystem)
        res = icp(cloud.points, tri.model, T, sigma=cloud.sigma, directions=cloud.directions,
                  config=icp_cfg, coarse=False)
        assert res.converged
        Te = res.T_sensor_target
        errors.append(B @ (Te[:3, :3] @ r_port + Te[:3, 3] - port))
        tm.frame_pattern = (pattern, 0.0)
        tm.bias_frames = cfg.pipeline.integrity.bias_prediction_frames  # due now
        tm.bias_probes = ()
        tm.predict_bias(dataclasses.replace(res, T_sensor_target=T, degenerate_axes=[]), icp_cfg)
        assert len(tm.bias_probes) == 1
        probes.append(B @ tm.bias_probes[0])
    return 1e3 * np.mean(errors, axis=0), 1e3 * np.mean(probes, axis=0)


def test_the_predicted_bias_is_the_footprints_bias_the_scans_have() -> None:
    """At 22 m the beam's 0.5 mrad footprint (11 mm) dilates every edge the port region cuts, and
    12 noisy scans register 4 and 3.5 mm off across the line of sight (the same each scan:
    their standard error is 0.7 mm). The sensor model's prediction (the same patterns, noise-free,
    registered from the truth) lands within a third of it and in its direction; along the
    line of sight both are nil."""
    measured, predicted = _measured_and_predicted(5e-4)
    m, p = measured[1:], predicted[1:]
    assert np.linalg.norm(m) > 3.0  # the bias is there (mm)
    assert np.linalg.norm(p - m) < 0.4 * np.linalg.norm(m)
    assert float(m @ p) / (np.linalg.norm(m) * np.linalg.norm(p)) > 0.9
    assert abs(predicted[0]) < 0.5


def test_without_a_footprint_no_bias_is_predicted_nor_measured() -> None:
    """The same scans with a beam of no width: the registrations are unbiased (within 3 standard
    errors) and the prediction is nil."""
    measured, predicted = _measured_and_predicted(1e-7)
    assert np.all(np.abs(measured[1:]) < 1.6)
    assert np.all(np.abs(predicted) < 0.05)


def test_the_bias_prediction_is_off_when_not_configured() -> None:
    """``integrity.bias_prediction_frames: null`` turns the probe off: no probe, no bias."""
    cfg = load_config("final_approach", pipeline__integrity__bias_prediction_frames=None)
    tri = TriDAR(cfg, generate_target("boxes_and_booms", 9494))
    tm = tri.tracking
    tm.frame_pattern = (tri.sensor.make_scan_pattern(0, np.eye(4), tri.target.regions["whole"]), 0.0)
    tm.predict_bias(dataclasses.replace(
        icp(np.zeros((0, 3)), tri.model, np.eye(4)), converged=True, degenerate_axes=[]), None)
    assert tm.bias_probes == () and tm.bias_covariance() is None
