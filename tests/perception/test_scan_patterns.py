"""Scan patterns: timing, documented density profiles, smoothness, phase and AOI steering."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from perception.config import SensorConfig
from perception.geometry import make_T
from perception.sensing.scan_patterns import (
    PATTERNS,
    ScanPattern,
    angles_to_directions,
    directions_to_angles,
    lissajous,
    make_pattern,
    raster,
    region_angular_box,
    rosette,
    spiral,
    steer_to_region,
)
from perception.targets import RegionOfInterest

FOV = np.radians(30.0)


def _uv(p: ScanPattern, half: float = FOV / 2) -> tuple[np.ndarray, np.ndarray]:
    return p.az / half, p.el / half


@pytest.mark.parametrize("name", PATTERNS)
def test_timing_and_fov(name: str) -> None:
    p = make_pattern(name, 1000, FOV)
    assert len(p) == 1000 and p.name == name
    np.testing.assert_allclose(np.diff(p.times), 1e-4)  # 10,000 samples/s
    assert p.times[0] == 0.0 and p.duration == pytest.approx(0.1)
    p.check_fov(FOV)
    # The pattern fills the field of view (within a few percent at the edges).
    lo, hi = p.angular_box()
    if name == "spiral":  # fills the inscribed disc
        assert np.hypot(p.az, p.el).max() == pytest.approx(FOV / 2, rel=0.01)
    else:
        np.testing.assert_allclose(hi, FOV / 2, rtol=0.03)
        np.testing.assert_allclose(lo, -FOV / 2, rtol=0.03)
    slow = make_pattern(name, 1000, FOV, sample_rate_hz=5000.0)
    assert slow.duration == pytest.approx(0.2)


def test_density_profiles_match_seed000_fig7() -> None:
    """Rosette densest at the centre, Lissajous at the corners, spiral area-uniform."""

    def radial_ratio(p: ScanPattern) -> float:
        u, v = _uv(p)
        r = np.hypot(u, v)
        inner = np.count_nonzero(r < 0.35) / (np.pi * 0.35**2)
        outer = np.count_nonzero((r > 0.6) & (r < 0.9)) / (np.pi * (0.9**2 - 0.6**2))
        return inner / outer

    def corner_ratio(p: ScanPattern) -> float:
        u, v = _uv(p)
        corner = np.count_nonzero((np.abs(u) > 0.7) & (np.abs(v) > 0.7)) / (4 * 0.3**2)
        centre = np.count_nonzero((np.abs(u) < 0.3) & (np.abs(v) < 0.3)) / 0.6**2
        return corner / max(centre, 1e-9)

    for phase in (0.0, 0.37, 1.3):
        assert radial_ratio(rosette(1000, FOV, phase)) > 2.0
        assert corner_ratio(lissajous(1000, FOV, phase)) > 3.0
        assert 0.8 < radial_ratio(spiral(1000, FOV, phase)) < 1.25
    # Spiral: equal radial spacing between turns (uniform ring populations by area).
    u, v = _uv(spiral(4000, FOV))
    r = np.hypot(u, v)
    edges = np.linspace(0.2, 1.0, 5)
    counts = np.histogram(r, edges)[0] / np.diff(edges**2)
    assert counts.max() / counts.min() < 1.15


@pytest.mark.parametrize("name", PATTERNS)
def test_mirror_acceleration_bounded(name: str) -> None:
    limit = SensorConfig().scan.max_mirror_accel_rad_s2
    p = make_pattern(name, 1000, FOV, max_accel_rad_s2=limit)
    assert p.peak_acceleration() <= limit
    # Finite differences of both mirror axes stay under the configured limit.
    for angle in (p.az, p.el):
        assert np.max(np.abs(np.diff(angle, 2))) / 1e-4**2 <= limit
    # A tight limit lowers the number of cycles until it fits, or fails naming the parameter.
    tight = make_pattern(name, 1000, FOV, max_accel_rad_s2=limit / 10)
    assert tight.peak_acceleration() <= limit / 10
    with pytest.raises(ValueError, match="max_accel_rad_s2"):
        make_pattern(name, 1000, FOV, max_accel_rad_s2=1.0)


def test_lissajous_acceleration_matches_analytic() -> None:
    p = lissajous(1000, FOV, cycles=9)
    # el = A sin(2 pi 10 s / T): peak acceleration A (2 pi 10 / 0.1)^2.
    expected = FOV / 2 * (2 * np.pi * 10 / 0.1) ** 2
    assert p.peak_acceleration() == pytest.approx(expected, rel=0.01)
    # A steered, smaller region needs proportionally less acceleration.
    small = p.scaled([0.0, 0.0], [FOV / 20, FOV / 20])
    assert small.peak_acceleration() == pytest.approx(expected / 10, rel=0.01)


@pytest.mark.parametrize("name", PATTERNS)
def test_phase_advances_coverage(name: str) -> None:
    a = make_pattern(name, 1000, FOV, phase=0.0)
    b = make_pattern(name, 1000, FOV, phase=0.37)
    assert b.phase == 0.37
    assert not np.allclose(a.az, b.az) or not np.allclose(a.el, b.el)
    # Two frames with different phases cover more 1-degree cells than one frame twice.
    cell = np.radians(1.0)

    def cells(*ps: ScanPattern) -> int:
        return len({(i, j) for p in ps for i, j in zip(np.floor(p.az / cell), np.floor(p.el / cell))})

    assert cells(a, b) > cells(a) * 1.1


def test_direction_convention_round_trip() -> None:
    az = np.array([0.0, 0.2, -0.1, 0.0])
    el = np.array([0.0, 0.0, 0.0, 0.25])
    d = angles_to_directions(az, el)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0)
    np.testing.assert_allclose(d[0], [0, 0, 1])
    assert d[1, 0] > 0 and d[2, 0] < 0  # az toward +x (right)
    assert d[3, 1] < 0  # el toward -y (up)
    np.testing.assert_allclose(np.arctan2(d[:, 0], d[:, 2]), az, atol=1e-15)
    az2, el2 = directions_to_angles(d)
    np.testing.assert_allclose(az2, az, atol=1e-15)
    np.testing.assert_allclose(el2, el, atol=1e-15)


@settings(max_examples=25, deadline=None)
@given(
    x=st.floats(-3, 3),
    y=st.floats(-3, 3),
    z=st.floats(8, 60),
    yaw=st.floats(-np.pi, np.pi),
    name=st.sampled_from(PATTERNS),
)
def test_steering_covers_region_exactly(x: float, y: float, z: float, yaw: float, name: str) -> None:
    region = RegionOfInterest("box", (0.1, -0.2, 0.3), (1.0, 0.6, 0.4))
    T = make_T(Rotation.from_euler("zyx", [yaw, 0.3, -0.2]), [x, y, z])
    try:
        p = steer_to_region(name, T, region, FOV, margin=0.1, n_points=800)
    except ValueError as exc:
        # Steering refuses (one line) only a region whose image misses the field of view (3 m off
        # the axis at 8 m, turned away), never one that can be scanned.
        assert "outside the field of view" in str(exc) and "\n" not in str(exc)
        lo0, hi0 = region_angular_box(T, region)
        assert np.any(lo0 > FOV / 2) or np.any(hi0 < -FOV / 2)
        return
    p.check_fov(FOV)
    # The projected corners bound the region's image: sample the box surface, project, and check
    # every sample falls inside the steered pattern's box (margin included), and the pattern spans
    # the region's image (no large waste around it) when the image is inside the FOV.
    rng = np.random.default_rng(0)
    pts = np.asarray(region.center) + rng.uniform(-1, 1, (2000, 3)) * np.asarray(region.half_extents)
    ps = pts @ T[:3, :3].T + T[:3, 3]
    az, el = np.arctan2(ps[:, 0], ps[:, 2]), np.arctan2(-ps[:, 1], ps[:, 2])
    box = region_angular_box(T, region)
    assert box is not None
    lo, hi = p.angular_box()
    inside_fov = (np.abs(az) < FOV / 2) & (np.abs(el) < FOV / 2)
    az, el = az[inside_fov], el[inside_fov]
    if name in ("rosette", "spiral"):
        # Round patterns: the region's image lies inside the pattern's ellipse.
        c, h = 0.5 * (lo + hi), 0.5 * (hi - lo)
        clipped = np.any(np.abs(box[0]) > FOV / 2 * 0.75) or np.any(np.abs(box[1]) > FOV / 2 * 0.75)
        if not clipped:
            assert np.all(((az - c[0]) / h[0]) ** 2 + ((el - c[1]) / h[1]) ** 2 <= 1.02)
        grow = np.sqrt(2.0) * 1.1
    else:
        assert np.all((az >= lo[0] - 1e-3 * FOV) & (az <= hi[0] + 1e-3 * FOV))
        assert np.all((el >= lo[1] - 1e-3 * FOV) & (el <= hi[1] + 1e-3 * FOV))
        grow = 1.1
    # No large waste around the region: the scanned box is at most the grown image.
    assert np.all(hi - lo <= np.maximum(box[1] - box[0], 2e-3) * grow + 1e-9)


def test_steering_clips_to_fov_and_rejects_unreachable_regions() -> None:
    region = RegionOfInterest("box", (0, 0, 0), (1.0, 1.0, 1.0))
    # Region half out of the FOV: the pattern is clipped to the FOV edge.
    T = make_T(None, [2.2, 0.0, 5.0])
    p = steer_to_region("rosette", T, region, FOV)
    p.check_fov(FOV)
    assert p.az.max() == pytest.approx(FOV / 2, rel=1e-6)
    # Region straddling the sensor plane: whole FOV.
    full = steer_to_region("lissajous", make_T(None, [0, 0, 0.5]), region, FOV)
    np.testing.assert_allclose(full.angular_box()[1], FOV / 2, rtol=0.03)
    with pytest.raises(ValueError, match="behind the sensor"):
        steer_to_region("rosette", make_T(None, [0, 0, -10.0]), region, FOV)
    with pytest.raises(ValueError, match="outside the field of view"):
        steer_to_region("rosette", make_T(None, [30.0, 0, 10.0]), region, FOV)
    # A ScanPattern is remapped affinely (same waveform, new box).
    base = raster(500, FOV)
    moved = steer_to_region(base, make_T(None, [0.5, -0.5, 20.0]), region, FOV)
    lo, hi = moved.angular_box()
    assert np.all(hi - lo < FOV / 2)
    ub = (base.az - base.az.min()) / np.ptp(base.az)
    um = (moved.az - moved.az.min()) / np.ptp(moved.az)
    np.testing.assert_allclose(ub, um, atol=1e-12)


def test_bad_arguments_name_the_parameter() -> None:
    with pytest.raises(ValueError, match="n_points"):
        rosette(2, FOV)
    with pytest.raises(ValueError, match="sample_rate_hz"):
        rosette(100, FOV, sample_rate_hz=-10.0)
    with pytest.raises(ValueError, match="fov_rad"):
        rosette(100, -0.1)
    with pytest.raises(ValueError, match="fov_rad"):
        rosette(100, 4.0)
    with pytest.raises(ValueError, match="phase"):
        rosette(100, FOV, phase=float("nan"))
    with pytest.raises(ValueError, match="name"):
        make_pattern("zigzag", 100, FOV)
    with pytest.raises(ValueError, match="margin"):
        steer_to_region("rosette", make_T(None, [0, 0, 10.0]), np.zeros((8, 3)), FOV, margin=-1)
    with pytest.raises(ValueError, match="T_sensor_target"):
        region_angular_box(np.full((4, 4), np.nan), np.zeros((8, 3)))
    big = spiral(100, np.radians(40.0))
    with pytest.raises(ValueError, match="pattern"):
        big.check_fov(FOV)
