"""Bearing mode across ranges (seed 000 section 5): the coarse range source against its noise
model, the range filter's use of the host's own thrust, the thermal-to-LIDAR hand-over without a
jump, and the slide monitor's rule."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.stats import chi2

from perception.config import load_config
from perception.estimation.registration import RegistrationResult
from perception.geometry import make_T
from perception.pipeline import TriDAR
from perception.pipeline.filter import EgoMotion, RangeFilter, gravity_gradient
from perception.pipeline.state import TruthScene
from perception.sensing.sensors import RelativeMotion
from perception.targets import load_target


@pytest.fixture(scope="module")
def iss() -> object:
    return load_target("iss_port")


def _scene(T: np.ndarray, t: float, v: np.ndarray | None = None, sun: np.ndarray | None = None) -> TruthScene:
    motion = RelativeMotion(T, np.zeros(3) if v is None else v, np.zeros(3), t_ref=t)
    return TruthScene(T, t, motion, sun_direction_target=sun)


def test_coarse_range_matches_its_noise_model(iss) -> None:
    """Measurements of a target 20 km out: mean at the near surface along the line of sight to
    its centre, spread the configured sqrt(sigma^2 + (fraction * range)^2) (chi-square bounds)."""
    cfg = load_config("far_rendezvous", pipeline__coarse_range__sigma_m=4.0,
                      pipeline__coarse_range__sigma_fraction=0.001)
    tri = TriDAR(cfg, iss)
    tri.reset(np.random.default_rng(7))
    got: list[tuple[float, float]] = []
    tri.bearing._fuse = lambda t, r, s: got.append((r, s))  # record the raw measurements
    R = make_T(np.diag([1.0, -1.0, -1.0]), None)[:3, :3]
    T = make_T(R, [30.0, -20.0, 20_000.0])
    for k in range(600):
        tri.bearing.coarse_range(_scene(T, float(k)), float(k))
    # Once per period: a call 0.5 s after a measurement measures nothing.
    tri.bearing.coarse_range(_scene(T, 599.5), 599.5)
    r = np.array([g[0] for g in got])
    s = got[0][1]
    assert len(r) == 600
    assert s == pytest.approx(math.hypot(4.0, 0.001 * np.mean(r)), rel=1e-3)
    # Truth: the first surface along the line of sight to the centre.
    from perception.sensing.sensors.raycast import cast_rays

    p = T[:3, 3]
    origin = R.T @ -p
    face, rng_hit, _ = cast_rays(iss, origin, (R.T @ (p / np.linalg.norm(p)))[None])
    if face[0] >= 0:
        truth = float(rng_hit[0])
    else:  # the line of sight threads the truss: the closest point of the mesh
        from trimesh.proximity import closest_point

        truth = float(closest_point(iss.mesh, origin[None])[1][0])
    assert 19_970.0 < truth < 20_000.0
    n = len(r)
    assert abs(r.mean() - truth) < 4.0 * s / math.sqrt(n)
    var_ratio = r.var(ddof=1) / s**2
    assert chi2.ppf(0.0005, n - 1) / (n - 1) < var_ratio < chi2.ppf(0.9995, n - 1) / (n - 1)


def test_range_filter_follows_known_thrust_without_lag() -> None:
    """Range under a constant known acceleration: with the accelerometer's along-range term the
    filter's rate tracks the truth; without it the rate lags by far more than its noise."""
    rng = np.random.default_rng(1)
    a, r0, v0 = -0.01, 3000.0, 0.0
    with_acc, without = RangeFilter(4e-8), RangeFilter(4e-8)
    for k in range(200):
        t = 2.0 * k
        r = r0 + v0 * t + 0.5 * a * t * t + rng.normal(0.0, 2.0)
        with_acc.update(t, r, 2.0, accel=a)
        without.update(t, r, 2.0)
    v_true = v0 + a * 398.0
    assert abs(with_acc.range_rate - v_true) < 0.05
    assert abs(without.range_rate - v_true) > 0.5


@pytest.mark.parametrize("tide", [True, False])
def test_bearing_range_filter_predicts_the_tide(iss, tide: bool) -> None:
    """A target 3 km below the chaser (along the radial), both coasting: the range grows under
    the tide alone, ``2 n^2 r`` (7.7e-3 m/s^2 here). With the IMU's gravity gradient the bearing
    mode's range filter follows its rate; without it, it lags by far more than its noise (the
    accelerometer reads nothing). Measured after 400 s: 1 mm/s off with it, 1.5 m/s without."""
    tri = TriDAR(load_config("far_rendezvous"), iss)
    tri.reset(np.random.default_rng(3))
    bm = tri.bearing
    u = np.array([0.0, 0.0, 1.0])  # the line of sight, along the radial
    n = 1.13e-3
    tri.ego = EgoMotion(np.zeros(3), np.zeros(3), gravity_gradient(n, u) if tide else None)
    bm.last_los = u
    rng = np.random.default_rng(1)
    lam = math.sqrt(2.0) * n  # r'' = 2 n^2 r: r = r0 cosh(lam t) from rest
    for k in range(200):
        t = 2.0 * k
        bm._fuse(t, 3000.0 * math.cosh(lam * t) + rng.normal(0.0, 2.0), 2.0)
    v_true = 3000.0 * lam * math.sinh(lam * 398.0)
    err = abs(bm.range_filter.range_rate - v_true)
    if tide:
        assert err < 0.05  # [m/s]
    else:
        assert err > 0.5


def test_thermal_then_lidar_bearing_hand_over_without_a_jump(iss) -> None:
    """Closing from 4.5 km to 1.2 km at 10 m/s, frame pairs every 10 s (the far mission's
    schedule): thermal bearings first, LIDAR bearings once in its link budget; the published
    range follows the truth throughout, and across the hand-over neither range nor bearing
    jumps by more than the coarse source's and the imager's own errors allow."""
    cfg = load_config("far_rendezvous")
    tri = TriDAR(cfg, iss)
    tri.reset(np.random.default_rng(3))
    R = np.diag([1.0, -1.0, -1.0])
    u = np.array([0.01, -0.005, 1.0])
    u /= np.linalg.norm(u)
    speed = 10.0
    sun = np.array([0.6, 0.0, 0.8])
    rows = []
    for k in range(330):
        for dt in (0.0, 0.5):
            t = 10.0 * k + dt
            rng_m = 4500.0 - speed * t
            T = make_T(R, u * rng_m)
            tri.ego = EgoMotion(np.zeros(3), np.zeros(3))
            sv = tri.step(_scene(T, t, v=-speed * u, sun=sun), t)
        if sv.valid.bearing:
            rows.append((t, rng_m, sv.bearing_source, sv.range if sv.valid.range else np.nan,
                         *sv.bearing, sv.range_rate if sv.valid.range_rate else np.nan))
    src = [r[2] for r in rows]
    assert src[0] == "thermal" and "lidar" in src
    i = src.index("lidar")
    assert rows[i][1] < 3500.0  # the LIDAR picks it up inside ~3 km
    # The published range tracks the truth (the near surface is ~10-25 m in front of the centre).
    err = np.array([r[3] - r[1] for r in rows if np.isfinite(r[3])])
    assert np.all(np.abs(err) < 60.0)
    # Across the hand-over: range jump (beyond the 10 s of closing) and bearing jump.
    before, after = rows[i - 1], rows[i]
    d_range = (after[3] - before[3]) + speed * (after[0] - before[0])
    sigma = math.hypot(cfg.pipeline.coarse_range.sigma_m, cfg.pipeline.coarse_range.sigma_fraction * before[1])
    assert abs(d_range) < 5.0 * sigma + 15.0
    d_bearing = math.hypot(after[4] - before[4], after[5] - before[5])
    assert d_bearing < 0.004  # the target's half-width at 3 km is ~0.007 rad
    # Closing rate from both sources: within 1 m/s of -10 m/s once the filter has settled.
    rates = np.array([r[6] for r in rows[5:] if np.isfinite(r[6])])
    assert np.median(np.abs(rates + speed)) < 1.0


def _result(T: np.ndarray, sigma: float) -> RegistrationResult:
    return RegistrationResult(T, fitness=1.0, inlier_rmse=0.02, converged=True, iterations=5,
                              covariance=np.diag([sigma**2] * 3 + [1e-8] * 3))


def _monitor_at_85_m(iss, **overrides):  # type: ignore[no-untyped-def]
    """A slide monitor of the fly-around pipeline, a 3 mm registration 85 m out on the boresight,
    a stand-in cloud, and the ICP settings: ``(cfg, monitor, T, res, cloud, pts, icp_cfg)``."""
    cfg = load_config("fly_around", **overrides)
    T = make_T(np.eye(3), [0.0, 0.0, 85.0])
    cloud = type("C", (), {"sigma": np.full(5, 0.025), "directions": None})()
    return cfg, TriDAR(cfg, iss).slides, T, _result(T, 0.003), cloud, np.zeros((5, 3)), cfg.pipeline.icp


def test_slide_monitor_inflates_only_a_direction_icp_does_not_come_back_along(iss, monkeypatch) -> None:
    """A pose ICP brings back from both pushes is left alone; one it leaves where it started
    gets ``o / (1 - rho)`` of variance along the pushed axis, turning with the target."""
    import perception.pipeline.slides as slides

    cfg, mon, T, res, cloud, pts, icp_cfg = _monitor_at_85_m(iss)

    def comes_back(points, model, T0, **kw):
        return _result(T, 0.003)

    monkeypatch.setattr(slides, "icp", comes_back)
    out = mon.apply(pts, cloud, res, 0.0, icp_cfg, 0)
    assert mon.axis_target is None and out is res
    recovered = {"frac": 0.25}

    def stays(points, model, T0, **kw):  # comes back three quarters of the way
        T1 = T0.copy()
        T1[:3, 3] = T[:3, 3] + recovered["frac"] * (T0[:3, 3] - T[:3, 3])
        return _result(T1, 0.003)

    monkeypatch.setattr(slides, "icp", stays)
    mon.reset()
    out = mon.apply(pts, cloud, res, 0.0, icp_cfg, 0)
    d = max(3 * 0.003, cfg.pipeline.integrity.slide_probe_fraction * 85.0)
    o = 0.25 * d
    assert mon.sigma_m == pytest.approx(o / 0.75)
    e = mon.axis_target
    added = out.covariance[:3, :3] - res.covariance[:3, :3]
    np.testing.assert_allclose(added, mon.sigma_m**2 * np.outer(e, e), atol=1e-15)
    # Held until the next probe and turning with the target.
    R = make_T(np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]), [0.0, 0.0, 85.0])
    out2 = mon.apply(pts, cloud, _result(R, 0.003), 0.5, icp_cfg, 5)
    e2 = R[:3, :3] @ e
    np.testing.assert_allclose(out2.covariance[:3, :3] - 0.003**2 * np.eye(3),
                               mon.sigma_m**2 * np.outer(e2, e2), atol=1e-15)


def test_slide_monitor_takes_a_second_basin_at_its_offset_and_holds_a_slide(iss, monkeypatch) -> None:
    """A second basin that catches every push at the same place is uncertain by its offset (not
    extrapolated as a slide); with a hold, a slide once found stays on the registrations for
    ``slide_hold_s`` whatever the probes between say, across a new track, and then expires;
    without one (the default) the next probe that finds nothing clears it."""
    import perception.pipeline.slides as slides

    hold = 30.0
    cfg, mon, T, res, cloud, pts, icp_cfg = _monitor_at_85_m(iss, pipeline__integrity__slide_hold_s=hold)
    period = cfg.pipeline.integrity.slide_check_period_s
    assert hold > 2 * period
    basin = 0.016

    def second_basin(points, model, T0, **kw):  # every push on the + side lands 1.6 cm off
        T1 = T.copy()
        push = T0[:3, 3] - T[:3, 3]
        if push.sum() > 0:
            T1[:3, 3] += basin * push / np.linalg.norm(push)
        return _result(T1, 0.003)

    monkeypatch.setattr(slides, "icp", second_basin)
    out = mon.apply(pts, cloud, res, 0.0, icp_cfg, 0)
    e = mon.axis_target
    assert mon.sigma_m == pytest.approx(basin, rel=1e-9)
    np.testing.assert_allclose(out.covariance[:3, :3] - res.covariance[:3, :3],
                               basin**2 * np.outer(e, e), atol=1e-15)

    # Probes that find nothing do not clear a held slide, nor does a new track ...
    monkeypatch.setattr(slides, "icp", lambda points, model, T0, **kw: _result(T, 0.003))
    for t in np.arange(period, hold - 1e-6, period):
        out = mon.apply(pts, cloud, res, float(t), icp_cfg, 10)
        assert mon.axis_target is None  # the probe itself found no slide
        np.testing.assert_allclose(out.covariance[:3, :3] - res.covariance[:3, :3],
                                   basin**2 * np.outer(e, e), atol=1e-15)
    mon.start()
    assert mon.apply(pts, cloud, res, hold - 1e-3, icp_cfg, 0) is not res
    # ... but time does.
    assert mon.apply(pts, cloud, res, hold + period, icp_cfg, 10) is res
    assert mon.held == []

    # No hold (the default; fly_around holds 10 s): the next probe decides.
    mon = _monitor_at_85_m(iss, pipeline__integrity__slide_hold_s=0.0)[1]
    monkeypatch.setattr(slides, "icp", second_basin)
    mon.apply(pts, cloud, res, 0.0, icp_cfg, 0)
    assert mon.apply(pts, cloud, res, 0.5 * period, icp_cfg, 10) is not res  # until the next probe
    monkeypatch.setattr(slides, "icp", lambda points, model, T0, **kw: _result(T, 0.003))
    assert mon.apply(pts, cloud, res, period, icp_cfg, 10) is res


def test_slide_keeps_the_filters_velocity_along_it_uncertain(iss, monkeypatch) -> None:
    """With ``slide_velocity_time_s``, a slide of sigma s keeps the track filter's velocity
    variance along the slide's axis (turning with the target) at least ``(s / tau)**2``; the
    other directions are left alone, and with no slide nothing changes."""
    import perception.pipeline.slides as slides
    from perception.pipeline.filter import PoseFilter

    tau = 10.0
    cfg, mon, T, res, cloud, pts, icp_cfg = _monitor_at_85_m(
        iss, pipeline__integrity__slide_velocity_time_s=tau)

    def stays(points, model, T0, **kw):  # ICP stops where it starts: a slide
        return _result(T0, 0.003)

    monkeypatch.setattr(slides, "icp", stays)
    mon.apply(pts, cloud, res, 0.0, icp_cfg, 0)
    assert mon.sigma_m > 0
    R = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    f = PoseFilter(init_velocity_sigma=1e-4)
    f.initialize(0.0, make_T(R, [0.0, 0.0, 85.0]), np.eye(6) * 1e-6)
    P0 = f.P.copy()
    mon.loosen(f)
    e = R @ mon.axis_target
    np.testing.assert_allclose(f.P - P0, np.pad(((mon.sigma_m / tau) ** 2 - 1e-8) * np.outer(e, e),
                                                ((3, 6), (3, 6))), atol=1e-15)
    monkeypatch.setattr(slides, "icp", lambda points, model, T0, **kw: _result(T, 0.003))
    mon.apply(pts, cloud, res, 5.0, icp_cfg, 10)  # the next probe finds none
    P1 = f.P.copy()
    mon.loosen(f)
    np.testing.assert_array_equal(f.P, P1)
