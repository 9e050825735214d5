"""TriDAR hybrid scanner: noise models, subsystem switch, link budget, materials, motion, faults."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from scipy import stats
from scipy.spatial.transform import Rotation

from perception.config import (
    BeamConfig,
    FaultsConfig,
    OccluderConfig,
    PointingConfig,
    SensorConfig,
    TOFConfig,
    TriangulationConfig,
)
from perception.geometry import make_T
from perception.sensing.pointcloud import PointCloud, Subsystem
from perception.sensing.scan_patterns import ScanPattern, make_pattern, rosette, steer_to_region
from perception.sensing.sensors import RelativeMotion, TriDARSensor, make_sensor
from perception.sensing.sensors.raycast import sphere_hits
from perception.targets import TargetModel, load_target


def plate(size: float = 4.0, reflectivity: float = 0.5, specular: bool = False) -> TargetModel:
    """A thin square plate in the target x-y plane, its front face toward target -z."""
    mesh = trimesh.creation.box(extents=(size, size, 0.02))
    nf = len(mesh.faces)
    return TargetModel(
        name="plate",
        mesh=mesh,
        reflectivity=np.full(nf, reflectivity),
        specular=np.full(nf, specular),
        T_target_port=np.eye(4),
        mass=10.0,
        inertia=np.eye(3),
    )


def at_range(r: float, tilt_deg: float = 0.0) -> np.ndarray:
    """Plate centre on the boresight at ``r``, tilted about the sensor y axis."""
    return make_T(Rotation.from_euler("y", tilt_deg, degrees=True), [0.0, 0.0, r + 0.01])


def quiet(**sections: object) -> SensorConfig:
    """A sensor with pointing errors off and one sub-ray, plus the given overrides."""
    base = {
        "pointing": PointingConfig(resolution_rad=0.0, jitter_rad=0.0),
        "beam": BeamConfig(subrays=1),
    }
    base.update(sections)
    return SensorConfig(**base)  # type: ignore[arg-type]


def plate_scan(
    sensor: TriDARSensor,
    target: TargetModel,
    T: np.ndarray,
    n: int = 2000,
    seed: int = 0,
    half_angle_deg: float | None = None,
) -> PointCloud:
    """Raster over the inner 80 % of the plate's image, or over +-half_angle_deg about boresight."""
    if half_angle_deg is not None:
        pattern = make_pattern("raster", n, np.radians(2 * half_angle_deg))
    else:
        pattern = steer_to_region(
            "raster", T, target.regions["whole"], sensor.fov_rad, margin=0.0, n_points=n
        )
        lo, hi = pattern.angular_box()
        pattern = pattern.scaled(0.5 * (lo + hi), 0.4 * (hi - lo))
    return sensor.scan(target, T, pattern, np.random.default_rng(seed))


def _check_variance(resid: np.ndarray, sigma: np.ndarray) -> None:
    """Normalised residuals have unit variance and zero mean within sampling error."""
    z = resid / sigma
    n = z.size
    s2 = np.sum((z - z.mean()) ** 2)
    assert stats.chi2.ppf(1e-4, n - 1) < s2 < stats.chi2.ppf(1 - 1e-4, n - 1)
    assert abs(z.mean()) < 4.0 / np.sqrt(n)


@pytest.mark.parametrize("r", [1.0, 3.0, 5.5])
def test_triangulation_noise_is_k_r_squared(r: float) -> None:
    sensor = TriDARSensor(quiet())
    cloud = plate_scan(sensor, plate(), at_range(r), n=3000)
    assert len(cloud) > 2500
    assert np.all(cloud.subsystem == Subsystem.TRIANGULATION)
    true_r = np.linalg.norm(cloud.true_points, axis=1)
    expected = 5e-4 * true_r**2
    np.testing.assert_allclose(cloud.sigma, expected, rtol=1e-12)
    _check_variance(cloud.ranges - true_r, expected)
    # 0.5 mm at 1 m (the documented anchor of the model)
    assert sensor.range_sigma(1.0, Subsystem.TRIANGULATION) == pytest.approx(5e-4)


@pytest.mark.parametrize("r", [10.0, 60.0, 250.0])
def test_tof_noise_constant_with_bias(r: float) -> None:
    cfg = quiet(tof=TOFConfig(noise_sigma_m=0.02, bias_m=0.01))
    sensor = TriDARSensor(cfg)
    cloud = plate_scan(sensor, plate(size=8.0), at_range(r), n=3000)
    assert len(cloud) > 2500
    assert np.all(cloud.subsystem == Subsystem.TOF)
    resid = cloud.ranges - np.linalg.norm(cloud.true_points, axis=1)
    np.testing.assert_allclose(cloud.sigma, 0.02)
    _check_variance(resid - 0.01, np.full(resid.size, 0.02))


def test_subsystem_switch_at_transition_range() -> None:
    sensor = TriDARSensor(quiet())
    transition = sensor.transition_range_m
    assert transition == pytest.approx(np.sqrt(0.025 / 5e-4))  # where k r^2 meets the TOF sigma
    near = plate_scan(sensor, plate(), at_range(transition - 0.3), n=500, half_angle_deg=1.0)
    far = plate_scan(sensor, plate(), at_range(transition + 0.3), n=500, half_angle_deg=1.0)
    assert len(near) > 400 and np.all(near.subsystem == Subsystem.TRIANGULATION)
    assert len(far) > 400 and np.all(far.subsystem == Subsystem.TOF)
    # An explicit transition moves the switch.
    moved = TriDARSensor(quiet(transition_range_m=12.0))
    for r, expected in ((11.5, Subsystem.TRIANGULATION), (12.5, Subsystem.TOF)):
        c = plate_scan(moved, plate(), at_range(r), n=300, half_angle_deg=1.0)
        assert len(c) > 250 and np.all(c.subsystem == expected)


def test_tof_fills_triangulation_holes_and_saturates_close() -> None:
    # Dark plate below the triangulation signal floor: TOF fills in below the transition.
    sensor = TriDARSensor(quiet(triangulation=TriangulationConfig(min_signal=0.2)))
    dark = plate_scan(sensor, plate(reflectivity=0.1), at_range(4.0), n=400)
    assert len(dark) > 300 and np.all(dark.subsystem == Subsystem.TOF)
    # Bright plate closer than the saturation range: TOF saturates, triangulation only.
    bright = plate_scan(sensor, plate(reflectivity=0.8), at_range(1.5), n=400)
    assert np.all(bright.subsystem == Subsystem.TRIANGULATION)
    no_tri = TriDARSensor(quiet(triangulation=TriangulationConfig(min_signal=0.95)))
    assert len(plate_scan(no_tri, plate(reflectivity=0.8), at_range(1.5), n=400)) == 0


def test_tof_max_range_follows_link_budget() -> None:
    def points(refl: float, power: float, r: float) -> int:
        cfg = quiet(tof=TOFConfig(max_range_ref_m=300.0, power_fraction=power))
        target = plate(size=10.0, reflectivity=refl)
        return len(plate_scan(TriDARSensor(cfg), target, at_range(r), n=200))

    for refl, power in [(0.8, 1.0), (0.1, 1.0), (0.8, 0.08)]:
        r_max = 300.0 * np.sqrt(refl * power)  # signal = refl * P * (R_ref / r)^2 >= 1
        assert TriDARSensor(quiet(tof=TOFConfig(max_range_ref_m=300.0, power_fraction=power))).tof_max_range(refl) == pytest.approx(r_max)
        assert points(refl, power, 0.97 * r_max) > 150
        assert points(refl, power, 1.03 * r_max) == 0
    # STS-128: at <10 % power the default sensor still reaches the ISS at ~457 m on a 0.3 surface.
    sts128 = TriDARSensor(SensorConfig(tof=TOFConfig(power_fraction=0.08)))
    assert sts128.tof_max_range(0.3) > 457.0
    assert sts128.tof_max_range(0.3) < TriDARSensor().tof_max_range(0.3) * 0.3


def test_grazing_and_specular_dropouts() -> None:
    sensor = TriDARSensor(quiet())  # grazing limit 80 deg, specular cone 5 deg

    def n_points(target: TargetModel, tilt: float) -> int:
        return len(plate_scan(sensor, target, at_range(3.0, tilt), n=300, half_angle_deg=0.5))

    assert n_points(plate(), 78.0) == 300
    assert n_points(plate(), 82.0) == 0
    shiny = plate(specular=True)
    assert n_points(shiny, 0.0) == 300 and n_points(shiny, 4.0) == 300
    assert n_points(shiny, 6.0) == 0 and n_points(shiny, 30.0) == 0
    # Intensity is reflectivity * cos(incidence).
    tilted = plate_scan(sensor, plate(reflectivity=0.6), at_range(3.0, 40.0), n=300)
    normal = -np.array([np.sin(np.radians(40)), 0, np.cos(np.radians(40))])  # R_y(40) @ -z
    np.testing.assert_allclose(tilted.intensity, 0.6 * np.abs(tilted.directions @ normal), atol=2e-3)


def test_beam_divergence_mixes_or_drops_edge_samples() -> None:
    """A step edge: near plate half covering a far plate; wide beam straddles the edge."""
    near = trimesh.creation.box(extents=(2.0, 4.0, 0.02), transform=make_T(None, [-1.0, 0, -0.5]))
    far = trimesh.creation.box(extents=(4.0, 4.0, 0.02), transform=make_T(None, [0.0, 0, 0.0]))
    mesh = trimesh.util.concatenate([near, far])
    nf = len(mesh.faces)
    target = TargetModel("step", mesh, np.full(nf, 0.2), np.zeros(nf, bool), np.eye(4), 1.0, np.eye(3))
    T = make_T(None, [0.0, 0.0, 3.0])
    # A scan line across the edge (x = 0 at 3 - 0.5 m); the beam is 0.02 rad wide (5 cm there).
    n = 400
    az = np.linspace(-0.1, 0.1, n)
    line = ScanPattern(az=az, el=np.zeros(n), times=np.arange(n) * 1e-4)
    wide = BeamConfig(divergence_rad=0.02, subrays=9, mixed_range_tolerance_m=0.05)
    # TOF off (link budget fails): triangulation alone gives mixed ranges between the surfaces.
    tri_only = TriDARSensor(quiet(beam=wide, tof=TOFConfig(power_fraction=1e-9)))
    c = tri_only.scan(target, T, line, np.random.default_rng(0))
    r_true = np.linalg.norm(c.true_points, axis=1)
    mixed = (r_true > 2.5 + 0.05) & (r_true < 3.0 - 0.05)
    assert 3 <= mixed.sum() < 40
    # With TOF the mixed triangulation samples are replaced by TOF first-echo ranges.
    both = TriDARSensor(quiet(beam=wide))
    c2 = both.scan(target, T, line, np.random.default_rng(0))
    tof_pts = c2.subsystem == Subsystem.TOF
    assert tof_pts.sum() >= mixed.sum() - 2
    r2 = np.linalg.norm(c2.true_points[tof_pts], axis=1)
    assert np.all(r2 < 2.5 + 0.06)  # first echo: the near plate
    # Without divergence there is no mixing at all.
    sharp = TriDARSensor(quiet(beam=BeamConfig(divergence_rad=0.0, subrays=1), tof=TOFConfig(power_fraction=1e-9)))
    r3 = np.linalg.norm(sharp.scan(target, T, line, np.random.default_rng(0)).true_points, axis=1)
    assert not np.any((r3 > 2.55) & (r3 < 2.95))


def test_pointing_quantisation_and_jitter() -> None:
    res = 1e-3
    sensor = TriDARSensor(SensorConfig(pointing=PointingConfig(resolution_rad=res, jitter_rad=2e-3)))
    T = at_range(4.0)
    pattern = steer_to_region("rosette", T, plate().regions["whole"], sensor.fov_rad, n_points=800)
    c = sensor.scan(plate(size=10.0), T, pattern, np.random.default_rng(1))
    az = np.arctan2(c.directions[:, 0], c.directions[:, 2])
    np.testing.assert_allclose(az / res, np.round(az / res), atol=1e-6)
    # Lateral error between reported point and true point ~ jitter * range.
    true_dirs = c.true_points / np.linalg.norm(c.true_points, axis=1, keepdims=True)
    ang = np.arccos(np.clip(np.sum(true_dirs * c.directions, axis=1), -1, 1))
    assert 1e-3 < np.median(ang) < 5e-3


def test_motion_distortion_of_a_spinning_target() -> None:
    """Spin about the boresight: every sample sees the target rotated by omega * (t_i - t0)."""
    target = load_target("cygnss")
    cfg = quiet(
        triangulation=TriangulationConfig(noise_k_per_m=0.0),
        tof=TOFConfig(noise_sigma_m=0.0, bias_m=0.0),
    )
    sensor = TriDARSensor(cfg)
    R0 = Rotation.from_euler("xy", [40.0, 30.0], degrees=True)
    centre = np.array([0.0, 0.0, 6.0])
    T0 = make_T(R0, centre)
    omega = 1.0  # rad/s: 5.7 deg over a 0.1 s frame
    pattern = steer_to_region("lissajous", T0, target.regions["whole"], sensor.fov_rad, n_points=1000)
    t0 = 3.0
    static = sensor.scan(target, T0, pattern, np.random.default_rng(0), t0=t0)
    motion = RelativeMotion(T0, np.zeros(3), np.array([0.0, 0.0, omega]))
    moving = sensor.scan(target, T0, pattern, np.random.default_rng(0), motion=motion, t0=t0)
    np.testing.assert_allclose(moving.times, t0 + pattern.times[np.searchsorted(t0 + pattern.times, moving.times)])

    def distance_to_static_mesh(points: np.ndarray) -> np.ndarray:
        body = (points - centre) @ R0.as_matrix()
        return np.abs(trimesh.proximity.signed_distance(target.mesh, body))

    assert np.max(distance_to_static_mesh(static.points)) < 1e-6
    # Undo each sample's rotation about the spin axis: the moving scan lands on the static mesh.
    angle = omega * (moving.times - t0)
    undo = Rotation.from_rotvec(-angle[:, None] * np.array([0.0, 0.0, 1.0]))
    back = undo.apply(moving.points - centre) + centre
    assert np.max(distance_to_static_mesh(back)) < 1e-6
    # Without undoing it the cloud is visibly distorted, by up to omega * T * lever arm.
    lever = np.linalg.norm((moving.points - centre)[:, :2], axis=1)
    d = distance_to_static_mesh(moving.points)
    assert np.all(d <= 2 * lever * np.sin(angle / 2) + 1e-6)
    late = angle > 0.5 * omega * pattern.duration
    assert np.median(d[late]) > 0.01
    # A callable motion gives the same cloud (slerp is exact for a constant rate).
    fn = lambda t: motion.poses([t], t_ref=t0)[0]
    via_fn = sensor.scan(target, T0, pattern, np.random.default_rng(0), motion=fn, t0=t0)
    np.testing.assert_allclose(via_fn.points, moving.points, atol=1e-9)


@pytest.mark.parametrize("omega", [[0.3, -1.2, 0.7], [0.0, 0.0, 0.0], [1e-9, 0.0, -2e-9], [0.0, 40.0, 0.0]])
def test_relative_motion_poses_are_the_rotation_vector_exponential(omega: list[float]) -> None:
    """The closed-form constant-rate poses equal scipy's ``exp(omega dt) R0`` for small, zero,
    tiny and several-turn angles, before and after the reference time."""
    R0 = Rotation.from_euler("zyx", [20.0, -35.0, 60.0], degrees=True).as_matrix()
    T0 = make_T(R0, np.array([0.4, -0.2, 12.0]))
    v = np.array([0.01, 0.02, -0.05])
    motion = RelativeMotion(T0, v, np.array(omega), t_ref=2.0)
    t = np.linspace(1.5, 2.5, 401)
    T = motion.poses(t)
    ref = Rotation.from_rotvec((t - 2.0)[:, None] * np.array(omega)).as_matrix() @ R0
    np.testing.assert_allclose(T[:, :3, :3], ref, atol=1e-14)
    np.testing.assert_allclose(T[:, :3, 3], T0[:3, 3] + (t - 2.0)[:, None] * v, atol=1e-15)
    assert np.array_equal(T[:, 3], np.tile([0.0, 0.0, 0.0, 1.0], (t.size, 1)))


def test_same_seed_identical_cloud() -> None:
    target = load_target("cygnss")
    cfg = SensorConfig(faults=FaultsConfig(dropout_prob=0.1, spurious_prob=0.05))
    sensor = TriDARSensor(cfg)
    T = make_T(Rotation.from_euler("xyz", [10, 20, 30], degrees=True), [0.3, -0.2, 5.0])
    pattern = sensor.make_scan_pattern(3, T, target.regions["whole"])
    a = sensor.scan(target, T, pattern, np.random.default_rng(42), frame_index=3)
    b = sensor.scan(target, T, pattern, np.random.default_rng(42), frame_index=3)
    c = sensor.scan(target, T, pattern, np.random.default_rng(43), frame_index=3)
    assert len(a) > 100
    for f in ("points", "times", "subsystem", "intensity", "sigma", "directions", "spurious"):
        np.testing.assert_array_equal(getattr(a, f), getattr(b, f))
    np.testing.assert_array_equal(a.true_points, b.true_points)
    assert len(a) != len(c) or not np.array_equal(a.points, c.points)


def test_empty_scans_are_empty_clouds() -> None:
    sensor = TriDARSensor()
    target = load_target("cygnss")
    pattern = rosette(500, sensor.fov_rad)
    rng = np.random.default_rng(0)
    for T in (
        make_T(None, [0.0, 0.0, -10.0]),  # behind
        make_T(None, [50.0, 0.0, 10.0]),  # outside the field of view
        make_T(None, [0.0, 0.0, 5000.0]),  # beyond the link budget
    ):
        c = sensor.scan(target, T, pattern, rng)
        assert len(c) == 0
        assert c.points.shape == (0, 3) and c.points.dtype == np.float64
        assert c.subsystem.dtype == np.int8 and c.times.shape == (0,)
        assert c.t_end == pytest.approx(c.t_start + 0.05)


def test_bad_input_raises_naming_the_parameter() -> None:
    sensor = TriDARSensor()
    target = load_target("cubesat")
    pattern = rosette(100, sensor.fov_rad)
    rng = np.random.default_rng(0)
    bad = make_T(None, [0, 0, 5.0])
    bad[0, 3] = np.nan
    with pytest.raises(ValueError, match="T_sensor_target"):
        sensor.scan(target, bad, pattern, rng)
    with pytest.raises(ValueError, match="pattern"):
        sensor.scan(target, make_T(None, [0, 0, 5.0]), rosette(100, np.radians(50.0)), rng)
    with pytest.raises(ValueError, match="t0"):
        sensor.scan(target, make_T(None, [0, 0, 5.0]), pattern, rng, t0=float("inf"))
    with pytest.raises(ValueError, match="omega_sensor"):
        RelativeMotion(np.eye(4), np.zeros(3), np.array([0.0, np.nan, 0.0]))
    with pytest.raises(ValueError, match="motion"):
        sensor.scan(target, make_T(None, [0, 0, 5.0]), pattern, rng, motion=lambda t: np.full((4, 4), np.nan))
    with pytest.raises(ValueError, match="frame_index"):
        sensor.scan(target, make_T(None, [0, 0, 5.0]), pattern, rng, frame_index=-1)
    with pytest.raises(ValueError, match="reflectivity"):
        sensor.tof_max_range(-0.5)


def test_faults_dropout_spurious_blackout_occluder() -> None:
    target = plate(size=6.0)
    T = at_range(5.0)
    n = 4000
    base = quiet()
    clean = plate_scan(TriDARSensor(base), target, T, n=n)
    # Dropouts: binomial thinning at the configured probability.
    drop = plate_scan(TriDARSensor(quiet(faults=FaultsConfig(dropout_prob=0.3))), target, T, n=n)
    frac = 1 - len(drop) / len(clean)
    assert abs(frac - 0.3) < 4 * np.sqrt(0.3 * 0.7 / len(clean))
    # Spurious returns: flagged, no true point, ranges around the target.
    sp = plate_scan(TriDARSensor(quiet(faults=FaultsConfig(spurious_prob=0.1))), target, T, n=n)
    k = int(sp.spurious.sum())
    assert abs(k / n - 0.1) < 4 * np.sqrt(0.1 * 0.9 / n)
    assert np.all(np.isnan(sp.true_points[sp.spurious])) and np.all(np.isfinite(sp.true_points[~sp.spurious]))
    centre = np.median(sp.ranges[~sp.spurious])
    r_sp = sp.ranges[sp.spurious]
    assert np.all((r_sp >= 0.49 * centre) & (r_sp <= 1.51 * centre))
    # Blackout of frames 2..4 by frame index; the counter advances when no index is given.
    sensor = TriDARSensor(quiet(faults=FaultsConfig(blackout_start_frame=2, blackout_frames=3)))
    pattern = steer_to_region("rosette", T, target.regions["whole"], sensor.fov_rad, n_points=200)
    sizes = [len(sensor.scan(target, T, pattern, np.random.default_rng(i))) for i in range(7)]
    assert sizes[2] == sizes[3] == sizes[4] == 0 and min(sizes[:2] + sizes[5:]) > 100
    # Occluder: a sphere between sensor and plate returns its own (non-target) surface.
    occ = OccluderConfig(center_m=(0.0, 0.0, 2.0), radius_m=0.3)
    oc = plate_scan(TriDARSensor(quiet(faults=FaultsConfig(occluder=occ))), target, T, n=n)
    on_sphere = np.abs(np.linalg.norm(oc.true_points - [0, 0, 2.0], axis=1) - 0.3) < 1e-9
    assert on_sphere.sum() > 50
    np.testing.assert_array_equal(oc.spurious, on_sphere)
    expected = np.isfinite(sphere_hits(oc.directions, [0, 0, 2.0], 0.3))
    np.testing.assert_array_equal(on_sphere, expected)


def test_make_sensor_and_default_pattern() -> None:
    sensor = make_sensor(SensorConfig())
    assert isinstance(sensor, TriDARSensor)
    p0, p1 = sensor.make_scan_pattern(0), sensor.make_scan_pattern(1)
    assert p0.name == "rosette" and len(p0) == 1000
    assert p1.phase == pytest.approx(0.37)
    assert p0.peak_acceleration() <= sensor.config.scan.max_mirror_accel_rad_s2
    with pytest.raises(ValueError, match="config"):
        make_sensor("tridar")  # type: ignore[arg-type]


def test_sts128_reduced_power_still_acquires_iss_at_457m() -> None:
    """Seed 000 section 5.5: <10 % laser power, the ISS acquired at ~457 m; at 1 % it is not."""
    iss = load_target("iss_port")
    T = make_T(Rotation.from_euler("x", 90, degrees=True), [0.0, 0.0, 457.0])
    for power, expect_points in ((0.08, True), (0.01, False)):
        sensor = TriDARSensor(SensorConfig(tof=TOFConfig(power_fraction=power)))
        pattern = sensor.make_scan_pattern(0, T, iss.regions["whole"])
        c = sensor.scan(iss, T, pattern, np.random.default_rng(0))
        assert (len(c) > 50) == expect_points
        assert np.all(c.subsystem == Subsystem.TOF)


def test_pointcloud_container() -> None:
    e = PointCloud.empty(1.5)
    assert len(e) == 0 and e.t_start == e.t_end == 1.5 and e.ranges.shape == (0,)
    n = 4
    pts = np.arange(12.0).reshape(n, 3)
    c = PointCloud(pts, np.arange(n) * 0.1, np.array([0, 1, 0, 1]), np.ones(n), np.full(n, 0.01),
                   pts / np.linalg.norm(pts, axis=1, keepdims=True), true_points=pts.copy())
    np.testing.assert_allclose(c.ranges, np.linalg.norm(pts, axis=1))
    s = c.select(c.subsystem == Subsystem.TOF)
    assert len(s) == 2 and c.count(Subsystem.TOF) == 2
    np.testing.assert_array_equal(s.points, pts[[1, 3]])
    assert s.spurious is not None and not s.spurious.any()
    with pytest.raises(ValueError, match="times"):
        PointCloud(pts, np.zeros(3), np.zeros(n), np.ones(n), np.ones(n), pts)
    bad = pts.copy()
    bad[0, 0] = np.nan
    with pytest.raises(ValueError, match="points"):
        PointCloud(bad, np.zeros(n), np.zeros(n), np.ones(n), np.ones(n), pts)
    with pytest.raises(ValueError, match="subsystem"):
        PointCloud(pts, np.zeros(n), np.full(n, 7), np.ones(n), np.ones(n), pts)
    with pytest.raises(ValueError, match="select mask"):
        c.select(np.array([True, False]))


def test_scan_command_writes_ply_and_png(tmp_path, capsys) -> None:
    from agents.cli import main

    out = tmp_path / "scan.ply"
    assert main(["scan", "--target", "cygnss", "--range", "20", "--pattern", "rosette",
                 "-o", str(out)]) == 0
    cloud = trimesh.load(out)
    n = int(capsys.readouterr().out.split()[0])
    assert len(cloud.vertices) == n > 50
    # The port faces the sensor at 20 m: every point lies within the target's size of that range.
    assert np.all(np.abs(np.linalg.norm(cloud.vertices, axis=1) - 20.0) < 2.0)
    png = out.with_suffix(".png")
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # An existing file is a user's until proven otherwise: refused, untouched; --force replaces.
    png.write_bytes(b"user's picture")
    before = out.read_bytes()
    assert main(["scan", "--target", "cygnss", "--range", "20", "-o", str(out)]) == 2
    assert "exists; pass --force" in capsys.readouterr().err
    assert png.read_bytes() == b"user's picture" and out.read_bytes() == before
    assert main(["scan", "--target", "cygnss", "--range", "20", "-o", str(out), "--force"]) == 0
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert main(["scan", "--target", "cygnss", "--range", "20", "-o", str(tmp_path), "--force"]) == 2
