"""Seed-003 line tracker: frames, depth map, lines, matching, roll, voxel grid, the tracker."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from perception.config import FlashLidarConfig
from perception.geometry import make_T, pose_error
from perception.estimation.linetrack import (
    SEED_FROM_OURS,
    LineRollTracker,
    Lines,
    T_from_seed_pose,
    depth_map,
    detect_lines,
    gaussian_downsample,
    line_similarity,
    match_lines,
    roll_about_boresight,
    roll_variation,
    seed003_icp_config,
    seed_pose_from_T,
)
from perception.sensing.sensors import FlashLidar
from perception.targets import load_target
from perception.estimation.voxel import adaptive_voxel_size, voxel_downsample

FOV = math.radians(20.0)


@pytest.fixture(scope="module")
def cygnss():
    return load_target("cygnss")


@pytest.fixture(scope="module")
def lidar():
    return FlashLidar(FlashLidarConfig())


# ---------------------------------------------------------------------------------------------
# Seed frames
# ---------------------------------------------------------------------------------------------
def test_seed_axes_are_a_proper_permutation():
    P = SEED_FROM_OURS
    assert np.allclose(P @ P.T, np.eye(3)) and np.isclose(np.linalg.det(P), 1.0)
    # seed X (toward the target) = our +z, seed Y = our +x (right), seed Z = our +y (down)
    assert np.allclose(P @ [0, 0, 1], [1, 0, 0])
    assert np.allclose(P @ [1, 0, 0], [0, 1, 0])
    assert np.allclose(P @ [0, 1, 0], [0, 0, 1])


@pytest.mark.parametrize(
    ("rpy_deg", "axis"), [((30, 0, 0), "z"), ((0, 20, 0), "x"), ((0, 0, -40), "y")]
)
def test_seed_roll_pitch_yaw_are_rotations_about_our_z_x_y(rpy_deg, axis):
    T = T_from_seed_pose([60.0, 0.0, 0.0], np.radians(rpy_deg))
    angle = sum(rpy_deg)
    assert np.allclose(T[:3, :3], Rotation.from_euler(axis, angle, degrees=True).as_matrix())
    assert np.allclose(T[:3, 3], [0.0, 0.0, 60.0])  # 60 m along the seed's X = our boresight


def test_seed_lateral_offset_is_our_x():
    T = T_from_seed_pose([60.0, 10.0, -2.0], [0, 0, 0])
    assert np.allclose(T[:3, 3], [10.0, -2.0, 60.0])


def test_seed_pose_round_trip():
    rng = np.random.default_rng(3)
    for _ in range(20):
        pos = rng.uniform(-50, 50, 3)
        rpy = np.array([rng.uniform(-3.1, 3.1), rng.uniform(-1.5, 1.5), rng.uniform(-3.1, 3.1)])
        p2, a2 = seed_pose_from_T(T_from_seed_pose(pos, rpy))
        assert np.allclose(p2, pos) and np.allclose(a2, rpy)


def test_seed_eq2_matrix_is_the_transpose_of_our_attitude():
    # Seed eq. (2): third row (sin t, -cos t sin f, cos t cos f), first column
    # (cos s cos t, -sin s cos t, sin t): that is (Rx(f) Ry(t) Rz(s))^T.
    f, t, s = np.radians([25.0, 8.0, -12.0])
    R_eq2 = np.array([
        [math.cos(s) * math.cos(t),
         math.sin(s) * math.cos(f) + math.cos(s) * math.sin(t) * math.sin(f),
         math.sin(s) * math.sin(f) - math.cos(s) * math.cos(f) * math.sin(t)],
        [-math.sin(s) * math.cos(t),
         math.cos(s) * math.cos(f) - math.sin(s) * math.sin(f) * math.sin(t),
         math.cos(s) * math.sin(f) + math.sin(s) * math.sin(t) * math.cos(f)],
        [math.sin(t), -math.cos(t) * math.sin(f), math.cos(t) * math.cos(f)],
    ])
    T = T_from_seed_pose([10.0, 0, 0], [f, t, s])
    R_seed = SEED_FROM_OURS @ T[:3, :3] @ SEED_FROM_OURS.T
    assert np.allclose(R_seed, R_eq2.T, atol=1e-12)


def test_seed_pose_rejects_bad_input():
    with pytest.raises(ValueError, match="position_seed"):
        T_from_seed_pose([1.0, 2.0], [0, 0, 0])
    with pytest.raises(ValueError, match="rpy_seed_rad"):
        T_from_seed_pose([1.0, 2.0, 3.0], [0, np.nan, 0])


# ---------------------------------------------------------------------------------------------
# Depth map and downsampling
# ---------------------------------------------------------------------------------------------
def _pixel_point(r: int, c: int, z: float, shape=(500, 500), fov=FOV) -> np.ndarray:
    rows, cols = shape
    ax = (c + 0.5 - cols / 2) * fov / cols
    ay = (r + 0.5 - rows / 2) * fov / rows
    return np.array([z * math.tan(ax), z * math.tan(ay), z])


def test_depth_map_follows_eq4():
    pts = np.array([
        _pixel_point(10, 20, 30.0),
        _pixel_point(250, 250, 31.0),
        _pixel_point(499, 0, 32.0),
        _pixel_point(10, 20, 31.5),  # same pixel, farther: the nearer one wins
        [0.0, 0.0, -5.0],  # behind the sensor
        [100.0, 0.0, 1.0],  # outside the field of view
    ])
    img, valid = depth_map(pts, FOV, (500, 500))
    assert img.dtype == np.uint8 and img.shape == (500, 500)
    assert img[10, 20] == 255 and img[250, 250] == 128 and img[499, 0] == 0
    assert valid.sum() == 3 and valid[499, 0]
    img64, _ = depth_map(pts, (FOV, FOV), (500, 500), floor_gray=64)
    assert img64[10, 20] == 255 and img64[499, 0] == 64 and img64[250, 250] == round(64 + 191 / 2)
    assert img64[0, 0] == 0  # background stays below every target pixel


def test_depth_map_matches_flash_pixels(cygnss, lidar):
    T = make_T(Rotation.from_euler("z", 30, degrees=True), [0.3, -0.2, 20.0])
    frame = lidar.capture(cygnss, T, np.random.default_rng(0))
    _, valid = depth_map(frame.points, FOV, (500, 500))
    assert np.array_equal(valid, frame.valid_mask)


def test_depth_map_rejects_bad_arguments():
    with pytest.raises(ValueError, match="fov_rad"):
        depth_map(np.zeros((1, 3)), -1.0, (10, 10))
    with pytest.raises(ValueError, match="shape"):
        depth_map(np.zeros((1, 3)), 0.3, (1, 10))
    with pytest.raises(ValueError, match="floor_gray"):
        depth_map(np.zeros((1, 3)), 0.3, (10, 10), floor_gray=255)


def test_gaussian_downsample_is_5x5_sigma1_factor2():
    img = np.zeros((41, 41), np.uint8)
    img[20, 20] = 250
    small = gaussian_downsample(img)
    assert small.shape == (21, 21)
    assert np.array_equal(small, cv2.GaussianBlur(img, (5, 5), 1.0)[::2, ::2])
    full = cv2.GaussianBlur(img.astype(np.float64), (5, 5), 1.0)
    _, xs = np.mgrid[:41, :41]
    var = np.sum(full * (xs - 20) ** 2) / full.sum()
    assert var == pytest.approx(1.0, abs=0.1)  # sigma 1 (truncated to 5x5)


# ---------------------------------------------------------------------------------------------
# Lines, similarity, matching
# ---------------------------------------------------------------------------------------------
def _rectangle(angle_deg: float, size=(160, 60), shape=(400, 400), bright=200) -> np.ndarray:
    img = np.zeros(shape, np.uint8)
    box = cv2.boxPoints(((200.0, 200.0), size, angle_deg))
    cv2.fillPoly(img, [np.round(box).astype(np.int32)], bright)
    return img


def test_detect_lines_finds_rectangle_sides():
    lines = detect_lines(_rectangle(0.0))
    top = lines.subset(lines.longest(4))
    assert len(top) == 4
    assert np.allclose(np.sort(top.length), [58, 58, 158, 158], atol=3)
    # directed orientations: two long sides point opposite ways, two short sides likewise
    ang = np.sort(np.round(np.degrees(top.angle) / 90.0) * 90.0 % 360)
    assert np.array_equal(ang, [0, 90, 180, 270])
    assert np.all(top.gradient > 20)
    assert np.allclose(top.midpoint.mean(axis=0), [200, 200], atol=3)


def test_detect_lines_on_blank_image_is_empty():
    lines = detect_lines(np.zeros((100, 100), np.uint8))
    assert len(lines) == 0 and lines.segments.shape == (0, 4)


def _lines(length, gradient, angle, mid) -> Lines:
    length = np.asarray(length, float)
    angle = np.asarray(angle, float)
    mid = np.asarray(mid, float).reshape(-1, 2)
    d = np.stack([np.cos(angle), np.sin(angle)], axis=1) * length[:, None] / 2
    seg = np.hstack([mid - d, mid + d])
    return Lines(seg, length, np.asarray(gradient, float), angle, mid)


def test_line_similarity_eqs_8_to_12():
    a = _lines([100.0], [40.0], [0.0], [[200.0, 100.0]])
    b = _lines([80.0], [50.0], [math.radians(60)], [[100.0, 100.0]])
    sm = line_similarity(a, b, alpha=0.25)
    expected = 0.25 * (0.8 + 0.8 + 0.5 + 0.5 * (0.5 + 1.0))
    assert sm.shape == (1, 1) and sm[0, 0] == pytest.approx(expected)
    # opposite directions do not contribute an orientation term
    c = _lines([100.0], [40.0], [math.pi], [[200.0, 100.0]])
    assert line_similarity(a, c)[0, 0] == pytest.approx(0.75)


def test_match_lines_threshold_and_top_q():
    prev = _lines([100, 80, 60, 10], [30, 30, 30, 30], [0.1, 1.2, -2.0, 0.5],
                  [[100, 100], [300, 200], [200, 350], [50, 50]])
    rot = 0.05
    cur = _lines([99, 81, 59, 10], [31, 30, 29, 30], prev.angle + rot,
                 prev.midpoint + 2.0)
    m = match_lines(prev, cur, q=3)
    assert sorted(zip(m.prev, m.cur)) == [(0, 0), (1, 1), (2, 2)]  # the short line is not in Q
    assert np.all(m.score > 0.95)
    assert roll_variation(prev, cur, m) == pytest.approx(rot)
    assert len(match_lines(prev, cur, threshold=0.999)) == 0
    assert roll_variation(prev, cur, match_lines(prev, cur, threshold=0.999)) is None
    with pytest.raises(ValueError, match="q=0"):
        match_lines(prev, cur, q=0)


def test_roll_variation_wraps_and_rejects_outliers():
    prev = _lines([50, 50, 50], [9, 9, 9], [3.1, 0.0, 1.0], [[10, 10], [20, 20], [30, 30]])
    cur = _lines([50, 50, 50], [9, 9, 9], [-3.1, 0.1, 1.9], [[10, 10], [20, 20], [30, 30]])
    m = match_lines(prev, cur, threshold=0.0)
    d = np.array([2 * math.pi - 6.2, 0.1, 0.9])  # across +-pi the change is +0.083, not -6.2
    assert roll_variation(prev, cur, m) == pytest.approx(d.mean())
    robust = roll_variation(prev, cur, m, max_deviation_rad=math.radians(2.0))
    assert robust == pytest.approx(np.mean(d[:2]))


def _roll_lines(cygnss, lidar, roll_deg, rng, distance=25.0, offset=(0.0, 0.0)):
    T = T_from_seed_pose([distance, *offset], np.radians([roll_deg, 0.0, 0.0]))
    frame = lidar.capture(cygnss, T, rng)
    img, _ = depth_map(frame.points, FOV, (500, 500), floor_gray=64)
    return detect_lines(img)


@pytest.mark.parametrize(("roll0", "step"), [(125.0, -5.0), (40.0, 7.0), (-80.0, 3.0)])
def test_known_roll_step_is_recovered_from_depth_maps(cygnss, lidar, roll0, step):
    rng = np.random.default_rng(11)
    a = _roll_lines(cygnss, lidar, roll0, rng, offset=(1.0, -0.5))
    b = _roll_lines(cygnss, lidar, roll0 + step, rng, offset=(1.0, -0.5))
    m = match_lines(a, b, 0.25, 0.8, 10)
    assert len(m) >= 4
    droll = roll_variation(a, b, m, max_deviation_rad=math.radians(2.0))
    assert math.degrees(droll) == pytest.approx(step, abs=0.4)


def test_roll_prior_rotates_about_boresight_through_target(cygnss):
    T = T_from_seed_pose([30.0, 2.0, -1.0], np.radians([10.0, 5.0, 3.0]))
    T_pred = roll_about_boresight(T, math.radians(5.0))
    T_true = T_from_seed_pose([30.0, 2.0, -1.0], np.radians([15.0, 5.0, 3.0]))
    assert np.allclose(T_pred[:3, 3], T[:3, 3])
    _, deg = pose_error(T_pred, T_true)
    assert deg < 0.6  # pure roll about the boresight vs about the tilted target axis
    assert np.allclose(roll_about_boresight(T_from_seed_pose([30, 0, 0], [0.2, 0, 0]), 0.1),
                       T_from_seed_pose([30, 0, 0], [0.3, 0, 0]))


# ---------------------------------------------------------------------------------------------
# Voxel grid
# ---------------------------------------------------------------------------------------------
def test_adaptive_voxel_size_eq16():
    assert adaptive_voxel_size(0.05, 60.0, 60.0) == pytest.approx(0.05)
    assert adaptive_voxel_size(0.05, 60.0, 10.0) == pytest.approx(0.05 * math.exp(50 / 60))
    assert adaptive_voxel_size(0.05, 60.0, 90.0) == pytest.approx(0.05 * math.exp(-0.5))
    with pytest.raises(ValueError, match="x_prev=0"):
        adaptive_voxel_size(0.05, 60.0, 0.0)


def test_voxel_downsample_matches_reference():
    rng = np.random.default_rng(5)
    pts = rng.uniform(-1.0, 1.0, (3000, 3)) + [0.0, 0.0, 20.0]
    d = 0.25
    out = voxel_downsample(pts, d)
    groups: dict[tuple[int, int, int], list[np.ndarray]] = {}
    for p in pts:  # reference, loop on purpose
        groups.setdefault(tuple(np.floor(p / d).astype(int)), []).append(p)
    ref = np.array([np.mean(groups[k], axis=0) for k in sorted(groups)])
    assert out.shape == ref.shape
    assert np.allclose(out, ref)
    assert voxel_downsample(np.zeros((0, 3)), 0.1).shape == (0, 3)
    with pytest.raises(ValueError, match="voxel_size"):
        voxel_downsample(pts, 0.0)
    with pytest.raises(ValueError, match="shape"):
        voxel_downsample(np.zeros((4, 2)), 0.1)


# ---------------------------------------------------------------------------------------------
# Tracker
# ---------------------------------------------------------------------------------------------
def test_seed_icp_config():
    cfg = seed003_icp_config(0.01)
    assert cfg.method == "point_to_point" and cfg.max_iterations == 100
    assert cfg.residual_tol == pytest.approx(1e-6 / 0.01**2)


def test_tracker_follows_roll_and_approach(cygnss, lidar):
    rng = np.random.default_rng(2)
    tracker = LineRollTracker(cygnss)
    truth = [T_from_seed_pose([30.0 - k, 0.5, 0.0], np.radians([60.0 - 5.0 * k, 0.0, 0.0]))
             for k in range(4)]
    T0 = roll_about_boresight(truth[0], math.radians(0.5))
    T0[:3, 3] += [0.01, -0.01, 0.02]
    res = tracker.init(lidar.capture(cygnss, truth[0], rng), T0)
    assert tracker.x_init == pytest.approx(30.0, abs=0.05)
    for T_true in truth[1:]:
        x_prev = tracker.T_sensor_target[2, 3]
        res = tracker.update(lidar.capture(cygnss, T_true, rng))
        info = tracker.last
        assert info.roll_from_lines and math.degrees(info.delta_roll_rad) == pytest.approx(-5, abs=1)
        assert info.n_points_used < info.n_points_raw
        # eq. (16) on the previous estimate: the grid grows as the chaser closes in
        assert info.voxel_size_m == pytest.approx(adaptive_voxel_size(0.03, tracker.x_init, x_prev))
        m, deg = pose_error(res.T_sensor_target, T_true)
        assert m < 0.03 and deg < 1.0
    assert tracker.last.voxel_size_m > 0.03 * math.exp(1.5 / 30.0)
    assert np.allclose(tracker.T_sensor_target, res.T_sensor_target)


def test_tracker_rejects_misuse(cygnss):
    tracker = LineRollTracker(cygnss)
    with pytest.raises(RuntimeError, match="before init"):
        tracker.update(np.zeros((10, 3)))
    with pytest.raises(ValueError, match="d_model"):
        LineRollTracker(cygnss, d_model=0.0)
    with pytest.raises(ValueError, match="q_lines"):
        LineRollTracker(cygnss, q_lines=0)
    with pytest.raises(ValueError, match="in front"):
        tracker.init(np.ones((10, 3)), make_T(None, [0, 0, -5.0]))
