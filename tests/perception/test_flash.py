"""Flash LiDAR (seed 003 section 3.1): grid geometry, error models, organised output, edge cases."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from scipy import stats
from scipy.spatial.transform import Rotation

from perception.config import FlashLidarConfig
from perception.geometry import invert, make_T, transform_points
from perception.sensing.pointcloud import Subsystem
from perception.sensing.sensors import FlashLidar, make_sensor
from perception.targets import load_target


@pytest.fixture(scope="module")
def cygnss():
    return load_target("cygnss")


def pose(r: float = 15.0) -> np.ndarray:
    return make_T(Rotation.from_euler("xyz", [20, -15, 35], degrees=True), [0.2, -0.1, r])


def test_seed003_defaults_and_organised_frame(cygnss) -> None:
    flash = make_sensor(FlashLidarConfig())
    assert isinstance(flash, FlashLidar)
    frame = flash.capture(cygnss, pose(), np.random.default_rng(0), t=2.5)
    assert frame.organized is not None and frame.valid_mask is not None
    assert frame.organized.shape == (500, 500, 3) and frame.valid_mask.shape == (500, 500)
    valid = frame.valid_mask
    assert len(frame) == valid.sum() > 10_000
    assert np.all(np.isnan(frame.organized[~valid])) and np.all(np.isfinite(frame.organized[valid]))
    np.testing.assert_array_equal(frame.points, frame.organized[valid])  # row-major order
    assert np.all(frame.times == 2.5) and frame.t_start == frame.t_end == 2.5
    assert np.all(frame.subsystem == Subsystem.FLASH)
    # Valid pixels are exactly those whose ray hits the mesh (trimesh reference, no grazing here
    # beyond the 85 deg limit except a few rim pixels).
    T_target_sensor = invert(pose())
    d = flash.pixel_directions @ T_target_sensor[:3, :3].T
    o = np.broadcast_to(T_target_sensor[:3, 3], d.shape)
    ref_hit = cygnss.mesh.ray.intersects_any(o, d)
    assert np.count_nonzero(ref_hit & ~valid.reshape(-1)) < 0.01 * ref_hit.sum()
    assert not np.any(valid.reshape(-1) & ~ref_hit)


def test_uniform_error_within_dmax_and_true_points_on_mesh(cygnss) -> None:
    cfg = FlashLidarConfig(rows=200, cols=200, range_error_m=0.01, error_model="uniform")
    flash = FlashLidar(cfg)
    frame = flash.capture(cygnss, pose(12.0), np.random.default_rng(1))
    assert frame.true_points is not None
    resid = frame.ranges - np.linalg.norm(frame.true_points, axis=1)
    assert np.all(np.abs(resid) <= 0.01)
    assert stats.kstest(resid, "uniform", args=(-0.01, 0.02)).pvalue > 1e-3
    np.testing.assert_allclose(frame.sigma, 0.01 / np.sqrt(3))
    # Error along the ray: the point and its true point share the pixel direction.
    unit = frame.points / frame.ranges[:, None]
    np.testing.assert_allclose(unit, frame.directions, atol=1e-12)
    body = transform_points(invert(pose(12.0)), frame.true_points)
    _, dist, _ = trimesh.proximity.closest_point(cygnss.mesh, body[::20])
    assert dist.max() < 1e-6


def test_gaussian_error_model(cygnss) -> None:
    cfg = FlashLidarConfig(rows=200, cols=200, range_error_m=0.02, error_model="gaussian")
    frame = FlashLidar(cfg).capture(cygnss, pose(12.0), np.random.default_rng(2))
    resid = frame.ranges - np.linalg.norm(frame.true_points, axis=1)
    assert stats.kstest(resid, "norm", args=(0.0, 0.02)).pvalue > 1e-3
    np.testing.assert_allclose(frame.sigma, 0.02)


def test_pixel_geometry_matches_seed003_eq4() -> None:
    flash = FlashLidar(FlashLidarConfig(rows=4, cols=6, fov_deg=(30.0, 20.0)))
    d = flash.pixel_directions.reshape(4, 6, 3)
    az = np.degrees(np.arctan2(d[..., 0], d[..., 2]))
    down = np.degrees(np.arctan2(d[..., 1], d[..., 2]))
    np.testing.assert_allclose(az[0], (np.arange(6) + 0.5) * 5.0 - 15.0, atol=1e-12)
    np.testing.assert_allclose(down[:, 0], (np.arange(4) + 0.5) * 5.0 - 10.0, atol=1e-12)
    assert np.all(d[0, :, 1] < 0)  # row 0 is the top of the image (-y is up)


def test_same_seed_identical_and_empty_cases(cygnss) -> None:
    flash = FlashLidar(FlashLidarConfig(rows=120, cols=120))
    a = flash.capture(cygnss, pose(), np.random.default_rng(7))
    b = flash.capture(cygnss, pose(), np.random.default_rng(7))
    np.testing.assert_array_equal(a.points, b.points)
    np.testing.assert_array_equal(a.organized, b.organized)
    for T in (make_T(None, [0, 0, -15.0]), make_T(None, [40.0, 0, 10.0]), make_T(None, [0, 0, 400.0])):
        e = flash.capture(cygnss, T, np.random.default_rng(0))
        assert len(e) == 0 and e.points.shape == (0, 3) and e.points.dtype == np.float64
        assert e.organized is not None and np.all(np.isnan(e.organized)) and not e.valid_mask.any()
    bad = pose()
    bad[2, 3] = np.inf
    with pytest.raises(ValueError, match="T_sensor_target"):
        flash.capture(cygnss, bad, np.random.default_rng(0))
    with pytest.raises(ValueError, match="t="):
        flash.capture(cygnss, pose(), np.random.default_rng(0), t=float("nan"))
