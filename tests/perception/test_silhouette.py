"""Outline rows of flash frames: pairs, quantisation variance, and the in-plane fix they bring."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from perception.config import FlashLidarConfig, ICPConfig
from perception.geometry import pose_error
from perception.estimation.linetrack import T_from_seed_pose
from perception.estimation.registration import icp, prepare_model
from perception.sensing.sensors import FlashLidar
from perception.estimation.silhouette import (
    FlashGeometry,
    _edge_quantisation_variance,
    outline_pairs,
    outline_rows,
    refine_pose,
)
from perception.targets import load_target

SIGMA = 0.01 / math.sqrt(3.0)


@pytest.fixture(scope="module")
def cygnss():
    return load_target("cygnss")


def test_outline_pairs_are_the_block_perimeter():
    v = np.zeros((5, 6), dtype=bool)
    v[1:3, 2:5] = True  # 2 x 3 block, away from the border
    a, b = outline_pairs(v)
    assert a.size == 2 * (2 + 3)  # one pair per side of each boundary pixel
    assert v.reshape(-1)[a].all() and not v.reshape(-1)[b].any()
    ra, ca = np.divmod(a, 6)
    rb, cb = np.divmod(b, 6)
    assert np.all(np.abs(ra - rb) + np.abs(ca - cb) == 1)
    # a block touching the border: the border is not outline
    w = np.zeros((3, 3), dtype=bool)
    w[:, 0] = True
    a, b = outline_pairs(w)
    assert a.size == 3 and np.all(b % 3 == 1)


def test_edge_quantisation_counts_a_grid_aligned_edge_once():
    n, period = 40, 0.03
    edge = np.zeros(n, dtype=np.int64)
    # every pair at the same sub-pixel phase: one unknown offset for the whole edge
    var = _edge_quantisation_variance(edge, np.full(n, 0.3), np.full(n, period))
    np.testing.assert_allclose(var, n * period**2 / 12.0, rtol=0.01)
    # phases spread over the pixel (an edge at a generic slope): as good as independent pairs
    var = _edge_quantisation_variance(edge, np.mod(0.37 * np.arange(n), 1.0), np.full(n, period))
    np.testing.assert_allclose(var, period**2 / 12.0, rtol=1e-9)


def test_model_outline_at_truth_matches_the_measured_one(cygnss):
    lidar = FlashLidar(FlashLidarConfig())
    T = T_from_seed_pose([25.0, 1.0, -0.5], np.radians([33.0, 4.0, 1.0]))
    cloud = lidar.capture(cygnss, T, np.random.default_rng(3))
    geom = FlashGeometry.from_config(lidar.config)
    np.testing.assert_array_equal(geom.directions, lidar.pixel_directions)
    a, b = outline_pairs(cloud.valid_mask)
    rows = outline_rows(cygnss, prepare_model(cygnss), T, geom.directions[a], geom.directions[b],
                        geom)
    assert rows.r.size > 0.95 * a.size
    # at the true pose every model crossing lies between its pair's two rays: the midpoint's
    # distance from the silhouette plane is at most half the pair's footprint
    pitch = np.max(np.linalg.norm(geom.directions[b] - geom.directions[a], axis=1))  # [rad]
    half = 0.5 * pitch * np.linalg.norm(rows.s, axis=1)
    assert np.mean(np.abs(rows.r) <= half + 1e-4) > 0.97
    assert abs(float(np.mean(rows.r))) < 2e-3  # no bias on a generic roll (33 deg)


def test_refine_pose_fixes_what_point_to_plane_cannot_see(cygnss):
    lidar = FlashLidar(FlashLidarConfig())
    rng = np.random.default_rng(7)
    T_true = T_from_seed_pose([45.0, 0.0, 0.0], np.radians([20.0, 0.0, 0.0]))  # face-on
    cloud = lidar.capture(cygnss, T_true, rng)
    # start 12 mm off across the boresight and 0.4 deg off in roll: on the face-on plates
    # point-to-plane ICP gets its in-plane pull only from points falling off the edges
    T0 = T_true.copy()
    T0[:3, :3] = Rotation.from_rotvec([0.0, 0.0, math.radians(0.4)]).as_matrix() @ T0[:3, :3]
    T0[:3, 3] += [0.009, -0.008, 0.0]
    cfg = ICPConfig(match_along_rays=True)
    mc = prepare_model(cygnss, cfg.model_points)
    idx = rng.choice(len(cloud), 2000, replace=False)
    res = icp(cloud.points[idx], mc, T0, sigma=SIGMA, config=cfg, directions=cloud.directions[idx])
    pos_icp, _ = pose_error(res.T_sensor_target, T_true)
    # its own Cramer-Rao bound says so: the in-plane position is unobservable to it
    assert {"tx", "ty"} <= set(res.degenerate_axes)
    geom = FlashGeometry.from_config(lidar.config)
    ref = refine_pose(cloud, cygnss, mc, res.T_sensor_target, geom, sigma=SIGMA, surface_idx=idx)
    pos, rot = pose_error(ref.T_sensor_target, T_true)
    assert pos < 0.001 and pos < 0.6 * pos_icp and rot < 0.03
    # the covariance with the outline is a bound, not a cap: in-plane observable at sub-mm
    assert not ref.degenerate_axes
    sd = np.sqrt(np.diag(ref.covariance))
    assert np.all(sd[:2] < 0.001) and sd[5] < math.radians(0.05)
    assert np.all(np.abs(ref.T_sensor_target[:2, 3] - T_true[:2, 3]) < 3.0 * sd[:2])
    # same input, same answer
    again = refine_pose(cloud, cygnss, mc, res.T_sensor_target, geom, sigma=SIGMA, surface_idx=idx)
    np.testing.assert_array_equal(again.T_sensor_target, ref.T_sensor_target)
