"""Thermal infrared imager (seed 000: the ISS detected at 43.4 km, day and night): radiometry
against Planck's law, bearing errors and detection rates against the model's own predictions
(SNR, IFOV), the footprint window, determinism, bad inputs."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import trimesh
from scipy import integrate, stats
from scipy.spatial.transform import Rotation

from perception.config import ConfigError, MissionConfig, ThermalImagerConfig, load_config
from perception.geometry import make_T
from perception.sensing.sensors import make_sensor
from perception.sensing.sensors.thermal import band_radiance
from perception.sensors import ThermalDetection, ThermalFrame, ThermalImager
from perception.targets import TargetModel, load_target

#: The oblique aspect of the module docstring's table, off the boresight by a few pixels.
R_OBLIQUE = Rotation.from_euler("xyz", [15.0, -20.0, 30.0], degrees=True)
#: The Sun 45 deg off the line of sight, behind the sensor, in the sensor frame.
SUN_SENSOR = np.array([0.5, -0.3, -0.8]) / np.linalg.norm([0.5, -0.3, -0.8])


@pytest.fixture(scope="module")
def iss():
    return load_target("iss_port")


@pytest.fixture(scope="module")
def imager():
    return ThermalImager()


def pose(r: float) -> np.ndarray:
    return make_T(R_OBLIQUE, [0.0075 * r, -0.005 * r, r])  # ~14 and 9 pixels off the boresight


def sun_target(T: np.ndarray) -> np.ndarray:
    return T[:3, :3].T @ SUN_SENSOR


def plate(size: float, thickness: float = 0.05) -> TargetModel:
    """A square plate (the test's own shape), its faces normal to the target z axis."""
    mesh = trimesh.creation.box(extents=(size, size, thickness))
    nf = len(mesh.faces)
    return TargetModel(
        "plate", mesh, np.full(nf, 0.5), np.zeros(nf, bool), np.eye(4), 10.0, np.eye(3)
    )


def bearing_of(d: np.ndarray) -> np.ndarray:
    return np.array([math.atan2(d[0], d[2]), math.atan2(-d[1], math.hypot(d[0], d[2]))])


def true_centroid_bearing(imager: ThermalImager, frame: ThermalFrame) -> np.ndarray:
    """Bearing of the noise-free frame's radiance centroid (all its flux): what the detector
    estimates."""
    v = frame.signal - frame.background
    y = np.arange(v.shape[0])[:, None] + frame.row0 + 0.5
    x = np.arange(v.shape[1])[None, :] + frame.col0 + 0.5
    s = v.sum()
    return bearing_of(imager.pixel_direction((v * y).sum() / s, (v * x).sum() / s))


def planck_band(T: float, band_um: tuple[float, float] = (8.0, 14.0)) -> float:
    h, c, k = 6.62607015e-34, 299_792_458.0, 1.380649e-23
    f = lambda lam: 2 * h * c**2 / lam**5 / math.expm1(h * c / (lam * k * T))
    return integrate.quad(f, band_um[0] * 1e-6, band_um[1] * 1e-6, epsabs=0, epsrel=1e-10)[0]


# -- radiometry ------------------------------------------------------------------------------------
def test_band_radiance_and_noise_equivalent_radiance_follow_planck(imager) -> None:
    for T in (3.0, 200.0, 230.0, 300.0, 330.0, 600.0):
        assert float(band_radiance(T)) == pytest.approx(planck_band(T), rel=1e-4, abs=1e-12)
    dLdT = (planck_band(300.01) - planck_band(299.99)) / 0.02
    assert imager.noise_sigma == pytest.approx(0.08 * dLdT, rel=1e-4)
    assert float(band_radiance(0.0)) == 0.0


def test_plate_radiance_is_the_radiative_balance_by_day_and_eclipse_by_night() -> None:
    """A 10 m plate at 200 m fills the central pixels: their radiance is eps * L_band(T) with T
    from eps sigma T^4 = eps sigma T_shade^4 + alpha S cos(theta)."""
    cfg = ThermalImagerConfig(psf_sigma_px=0.5)
    im = ThermalImager(cfg)
    target = plate(10.0)
    T = make_T(Rotation.from_euler("y", 180, degrees=True), [0.0, 0.0, 200.0])  # +z face to us
    cos_sun = math.cos(math.radians(40.0))
    sun = np.array([math.sin(math.radians(40.0)), 0.0, cos_sun])  # target frame, on the +z side
    centre = lambda f: f.signal[f.signal.shape[0] // 2, f.signal.shape[1] // 2]
    rng = np.random.default_rng(0)
    day = im.capture(target, T, rng, sun_direction_target=sun)
    night = im.capture(target, T, rng)
    eps, sb = cfg.emissivity, 5.670374419e-8
    t_sun = (
        cfg.shade_temperature_k**4 + cfg.solar_absorptivity * 1361.0 * cos_sun / (eps * sb)
    ) ** 0.25
    assert 300.0 < t_sun < 330.0
    assert centre(day) == pytest.approx(eps * planck_band(t_sun), rel=1e-3)
    assert centre(night) == pytest.approx(eps * planck_band(cfg.eclipse_temperature_k), rel=1e-3)
    # The face turned away from the Sun sits at the shade temperature; a grey body from the
    # reflectivity (0.5) radiates with emissivity 0.5.
    back = im.capture(target, T, rng, sun_direction_target=-sun)
    assert centre(back) == pytest.approx(eps * planck_band(cfg.shade_temperature_k), rel=1e-3)
    grey = ThermalImager(cfg.model_copy(update={"grey_from_reflectivity": True}))
    assert centre(grey.capture(target, T, rng)) == pytest.approx(
        0.5 * planck_band(cfg.eclipse_temperature_k), rel=1e-3
    )


def test_self_shadowing_cools_the_shaded_face() -> None:
    """A 10 m plate under a 12 m shade 20 m above it, the Sun straight down (+z), seen obliquely
    past the shade's edge: with shadow rays the plate sits at the shade temperature, without
    them at the radiative balance of a face under a normal Sun."""
    near = trimesh.creation.box(extents=(10.0, 10.0, 0.05))
    shade = trimesh.creation.box(extents=(12.0, 12.0, 0.05))
    shade.apply_translation([0.0, 0.0, 20.0])
    mesh = trimesh.util.concatenate([near, shade])
    nf = len(mesh.faces)
    target = TargetModel(
        "shaded", mesh, np.full(nf, 0.5), np.zeros(nf, bool), np.eye(4), 1.0, np.eye(3)
    )
    # Sensor axes in the target frame: boresight along -(1, 0, 1)/sqrt(2), toward the plate.
    s2 = math.sqrt(0.5)
    R_target_sensor = np.array([[-s2, 0.0, -s2], [0.0, 1.0, 0.0], [s2, 0.0, -s2]])
    T = make_T(R_target_sensor.T, [0.0, 0.0, 200.0])
    sun = np.array([0.0, 0.0, 1.0])
    cfg = ThermalImagerConfig()
    rng = np.random.default_rng(0)
    values = {}
    for shadows in (True, False):
        im = ThermalImager(cfg.model_copy(update={"self_shadowing": shadows}))
        f = im.capture(target, T, rng, sun_direction_target=sun)
        values[shadows] = f.signal[240 - f.row0, 320 - f.col0]  # the plate's centre
        assert f.n_rays > f.n_pixels  # sub-rays, and shadow rays when cast
    eps, sb = cfg.emissivity, 5.670374419e-8
    t_sun = (cfg.shade_temperature_k**4 + cfg.solar_absorptivity * 1361.0 / (eps * sb)) ** 0.25
    assert values[True] == pytest.approx(eps * planck_band(cfg.shade_temperature_k), rel=1e-3)
    assert values[False] == pytest.approx(eps * planck_band(t_sun), rel=1e-3)


# -- statistics against the model's own prediction ------------------------------------------------
@pytest.mark.parametrize(("light", "range_m"), [("night", 30_000.0), ("day", 60_000.0)])
def test_bearing_errors_match_the_predicted_sigma(imager, iss, light: str, range_m: float) -> None:
    """300 seeded frames at a peak SNR of ~15-18: the bearing error's std per axis is inside the
    chi-square 99.9 % band of the predicted sigma widened by 10 % (the model's own error: the
    aperture, the ratio estimator), its mean within 0.2 sigma, and the sigma the detector claims
    within 10 % of the prediction."""
    T = pose(range_m)
    sun = sun_target(T) if light == "day" else None
    snr = imager.predicted_snr(iss, T, sun_direction_target=sun)
    assert 12.0 < snr < 25.0
    sigma = imager.predicted_bearing_sigma_rad(iss, T, sun_direction_target=sun)
    assert 0.05 * imager.ifov_rad < sigma < 0.2 * imager.ifov_rad  # sub-pixel centroiding
    rng = np.random.default_rng(7)
    n = 300
    errors, claimed = np.empty((n, 2)), np.empty(n)
    for i in range(n):
        frame = imager.capture(iss, T, rng, sun_direction_target=sun, t=float(i))
        det = imager.detect(frame)
        assert det is not None and det.t == float(i)
        errors[i] = det.bearing - true_centroid_bearing(imager, frame)
        claimed[i] = det.sigma_rad
    dof = n - 1
    lo = stats.chi2.ppf(0.0005, dof) / dof * 0.9**2
    hi = stats.chi2.ppf(0.9995, dof) / dof * 1.1**2
    ratio = errors.var(axis=0, ddof=1) / sigma**2
    assert np.all((lo < ratio) & (ratio < hi)), (ratio, lo, hi)
    assert np.all(np.abs(errors.mean(axis=0)) < 0.2 * sigma), errors.mean(axis=0) / sigma
    assert np.median(claimed) == pytest.approx(sigma, rel=0.1)
    # The radiance centroid is on the target: within its apparent radius of its origin.
    offset = true_centroid_bearing(imager, frame) - bearing_of(T[:3, 3])
    assert np.linalg.norm(offset) < iss.radius / range_m


def test_detection_rate_matches_the_probability_and_falls_with_range(imager, iss) -> None:
    """400 seeded frames per range: the detection rate is inside the binomial 99.9 % interval
    around ``detection_probability`` (plus 0.02 for the model); the probability is ~1 at 40 km
    by night (seed 000: 43.4 km), intermediate at 55-65 km and nil at 150 km."""
    rng = np.random.default_rng(11)
    n = 400
    probs = {}
    for r_km in (40, 55, 60, 65, 150):
        T = pose(r_km * 1e3)
        p = imager.detection_probability(iss, T)
        rate = np.mean([imager.observe(iss, T, rng) is not None for _ in range(n)])
        half = stats.norm.ppf(0.9995) * math.sqrt(max(p * (1 - p), 1e-4) / n) + 0.02
        assert abs(rate - p) < half, (r_km, rate, p)
        probs[r_km] = p
    assert probs[40] > 0.999 and probs[150] < 1e-4
    assert 0.1 < probs[60] < 0.9 and probs[65] < probs[55]
    # By day the sunlit side carries the detection much further.
    T = pose(80e3)
    assert imager.detection_probability(iss, T, sun_direction_target=sun_target(T)) > 0.99
    assert imager.detection_probability(iss, T) < 0.2


def test_detection_rate_with_a_minimum_blob_size(iss) -> None:
    """min_blob_pixels = 3: the Poisson-binomial tail of the lit-pixel count."""
    imager = ThermalImager(ThermalImagerConfig(min_blob_pixels=3))
    T = pose(48e3)
    p = imager.detection_probability(iss, T)
    assert 0.2 < p < 0.8
    rng = np.random.default_rng(3)
    n = 400
    rate = np.mean([imager.observe(iss, T, rng) is not None for _ in range(n)])
    assert abs(rate - p) < stats.norm.ppf(0.9995) * math.sqrt(p * (1 - p) / n) + 0.02
    assert p < ThermalImager().detection_probability(iss, T)


def test_generated_box_bearing_is_unbiased_and_its_claimed_sigma_holds() -> None:
    """A 6 m cube at 15 km (0.7 pixel, peak SNR ~28 by night): its radiance centroid is its
    centre, so the error against the true direction, normalised by the sigma the detector claims,
    is ~N(0, 1) (the sub-ray grid's own centroid bias, ~0.01 pixel, is well inside)."""
    mesh = trimesh.creation.box(extents=(6.0, 6.0, 6.0))
    nf = len(mesh.faces)
    cube = TargetModel(
        "cube", mesh, np.full(nf, 0.3), np.zeros(nf, bool), np.eye(4), 50.0, np.eye(3)
    )
    imager = ThermalImager()
    T = make_T(
        Rotation.from_euler("xyz", [10.0, 20.0, 5.0], degrees=True), [-225.0, 112.5, 15_000.0]
    )
    truth = bearing_of(T[:3, 3])
    rng = np.random.default_rng(5)
    z = []
    for _ in range(200):
        det = imager.observe(cube, T, rng)
        assert det is not None
        z.append((det.bearing - truth) / det.sigma_rad)
    z = np.asarray(z)
    assert np.all(np.abs(z.mean(axis=0)) < 0.3)
    chi2 = float(np.sum(z**2))
    dof = z.size
    assert stats.chi2.ppf(0.0005, dof) * 0.8 < chi2 < stats.chi2.ppf(0.9995, dof) * 1.2, chi2 / dof


# -- rendering -------------------------------------------------------------------------------------
def test_far_frames_render_a_small_window(imager, iss) -> None:
    rng = np.random.default_rng(0)
    near = imager.capture(iss, pose(1_000.0), rng)
    far = imager.capture(iss, pose(40_000.0), rng)
    assert far.n_pixels * 30 < near.n_pixels < 640 * 480 // 10
    assert far.n_rays < 10_000 and far.subrays > near.subrays
    assert far.shape == near.shape == (480, 640)
    assert 0 <= far.row0 < 480 and 0 <= far.col0 < 640
    # The window holds the target: the brightest pixel is inside, away from the window's edge.
    r, c = np.unravel_index(np.argmax(far.signal), far.signal.shape)
    assert 2 <= r < far.signal.shape[0] - 2 and 2 <= c < far.signal.shape[1] - 2


def test_the_window_holds_every_pixel_that_sees_the_target(imager, iss) -> None:
    """Whole-frame pixel-centre rays (trimesh, not the imager's caster): every pixel that sees
    the target is inside the rendered window, and lit in its noise-free signal."""
    rows, cols = imager.shape
    grid = imager.pixel_direction(np.arange(rows)[:, None] + 0.5, np.arange(cols)[None, :] + 0.5)
    poses = [
        pose(1_000.0),
        pose(5_000.0),  # further out, pixel centres would miss a target of two pixels
        make_T(Rotation.from_euler("zyx", [70.0, 10.0, -40.0], degrees=True), [-9.0, 6.0, 150.0]),
        make_T(R_OBLIQUE, [-110.0, 75.0, 900.0]),  # near the frame's corner, partly outside
    ]
    for T in poses:
        R = T[:3, :3]
        d = grid.reshape(-1, 3) @ R
        o = np.broadcast_to(-(R.T @ T[:3, 3]), d.shape)
        seen = (np.asarray(iss.ray.intersects_first(o, d)) >= 0).reshape(rows, cols)
        assert seen.any()
        frame = imager.capture(iss, T, np.random.default_rng(0))
        r, c = np.nonzero(seen)
        h, w = frame.signal.shape
        assert frame.row0 <= r.min() and r.max() < frame.row0 + h
        assert frame.col0 <= c.min() and c.max() < frame.col0 + w
        assert np.all(frame.signal[r - frame.row0, c - frame.col0] > frame.background)


def test_same_seed_same_frame_bitwise(iss) -> None:
    T = pose(20_000.0)
    sun = sun_target(T)
    a = ThermalImager().capture(iss, T, np.random.default_rng(42), sun_direction_target=sun)
    b = ThermalImager().capture(iss, T, np.random.default_rng(42), sun_direction_target=sun)
    assert a.image.tobytes() == b.image.tobytes() and (a.row0, a.col0) == (b.row0, b.col0)
    c = ThermalImager().capture(iss, T, np.random.default_rng(43), sun_direction_target=sun)
    assert a.image.tobytes() != c.image.tobytes()
    da, db = ThermalImager().detect(a), ThermalImager().detect(b)
    assert isinstance(da, ThermalDetection) and db is not None
    assert da.bearing.tobytes() == db.bearing.tobytes() and da.sigma_rad == db.sigma_rad


def test_day_is_brighter_than_night(imager, iss) -> None:
    T = pose(20_000.0)
    day = imager.capture(iss, T, np.random.default_rng(0), sun_direction_target=sun_target(T))
    night = imager.capture(iss, T, np.random.default_rng(0))
    assert (day.signal - day.background).sum() > 2.0 * (night.signal - night.background).sum()
    snr_day = imager.predicted_snr(iss, T, sun_direction_target=sun_target(T))
    assert snr_day > 2.0 * imager.predicted_snr(iss, T)
    assert imager.predicted_bearing_sigma_rad(
        iss, T, sun_direction_target=sun_target(T)
    ) < imager.predicted_bearing_sigma_rad(iss, T)


def test_nothing_seen_behind_outside_or_beyond_range(imager, iss) -> None:
    rng = np.random.default_rng(0)
    cases = {
        "behind": make_T(None, [0.0, 0.0, -5_000.0]),
        "outside the field": make_T(None, [5_000.0, 0.0, 5_000.0]),
        "beyond max_range_m": make_T(None, [0.0, 0.0, 250_000.0]),
    }
    for name, T in cases.items():
        frame = imager.capture(iss, T, rng)
        assert frame.n_pixels == 0, name
        assert imager.detect(frame) is None and imager.observe(iss, T, rng) is None, name
        assert imager.detection_probability(iss, T) == 0.0, name
        assert imager.predicted_snr(iss, T) == 0.0, name
        assert imager.predicted_bearing_sigma_rad(iss, T) == math.inf, name
    # Inside the bounding sphere the whole frame is rendered.
    assert imager.capture(plate(2.0), make_T(None, [0.0, 0.0, 1.0]), rng).n_pixels == 480 * 640


# -- inputs and config -----------------------------------------------------------------------------
def test_bad_inputs_name_the_field_and_value(imager, iss) -> None:
    rng = np.random.default_rng(0)
    T = pose(10_000.0)
    bad_T = T.copy()
    bad_T[0, 3] = np.nan
    cases = [
        (lambda: imager.capture(iss, bad_T, rng), ["T_sensor_target", "nan"]),
        (lambda: imager.capture(iss, np.eye(3), rng), ["T_sensor_target", "(3, 3)"]),
        (lambda: imager.observe(iss, 2.0 * T, rng), ["T_sensor_target", "rigid"]),
        (
            lambda: imager.capture(iss, T, rng, sun_direction_target=[1.0, 0.0]),
            ["sun_direction_target", "(2,)"],
        ),
        (
            lambda: imager.predicted_snr(iss, T, sun_direction_target=[0.0, 0.0, 0.0]),
            ["sun_direction_target", "[0.0, 0.0, 0.0]"],
        ),
        (
            lambda: imager.detection_probability(iss, T, sun_direction_target=[np.inf, 0, 0]),
            ["sun_direction_target", "inf"],
        ),
        (lambda: imager.capture(iss, T, rng, t=float("nan")), ["t=nan"]),
        (lambda: imager.capture(iss, T, None), ["rng=None"]),  # type: ignore[arg-type]
        (lambda: imager.capture("iss_port", T, rng), ["target=str"]),  # type: ignore[arg-type]
        (lambda: imager.detect(np.zeros((4, 4))), ["frame=ndarray"]),  # type: ignore[arg-type]
    ]
    for call, words in cases:
        with pytest.raises(ValueError) as info:
            call()
        assert all(w in str(info.value) for w in words), str(info.value)
    frame = imager.capture(iss, T, rng)
    with pytest.raises(ValueError, match=r"frame.image has shape \(5,\)"):
        imager.detect(dataclasses.replace(frame, image=np.zeros(5)))


def test_config_defaults_bounds_and_preset() -> None:
    assert MissionConfig().thermal == ThermalImagerConfig()
    assert isinstance(make_sensor(ThermalImagerConfig()), ThermalImager)
    cfg = load_config("configs/sensors/thermal_imager.yaml")
    assert cfg.thermal.rows == 480 and cfg.thermal.netd_k == 0.08 and cfg.target.name == "iss_port"
    assert ThermalImager(cfg.thermal).ifov_rad == pytest.approx(math.radians(20.0) / 640)
    for key, value, words in [
        ("thermal__netd_k", -1.0, ["thermal.netd_k", "-1"]),
        ("thermal__max_range_m", 1e9, ["thermal.max_range_m", "1000000"]),
        ("thermal__band_um", [14.0, 8.0], ["band_um", "(14.0, 8.0)"]),
        ("thermal__supersampling", 8, ["supersampling=8", "max_supersampling=4"]),
    ]:
        overrides = {key: value}
        if key == "thermal__supersampling":
            overrides["thermal__max_supersampling"] = 4
        with pytest.raises(ConfigError) as info:
            load_config(None, **overrides)
        assert all(w in str(info.value) for w in words), str(info.value)
