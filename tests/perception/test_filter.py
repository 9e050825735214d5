"""Pose and range filters: convergence on known motion, consistency, gating."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from perception.geometry import make_T, pose_error
from perception.pipeline.filter import EgoMotion, PoseFilter, RangeFilter, gravity_gradient
from perception.pipeline.integrity import integrity_factor


def _truth(t: float, p0, v, R0, w) -> np.ndarray:
    return make_T(Rotation.from_rotvec(np.asarray(w) * t).as_matrix() @ R0, np.asarray(p0) + np.asarray(v) * t)


def test_pose_filter_converges_on_constant_velocity_truth() -> None:
    rng = np.random.default_rng(0)
    p0, v = np.array([0.5, -0.3, 20.0]), np.array([0.01, -0.02, -0.10])
    R0 = Rotation.from_euler("xyz", [10, -20, 30], degrees=True).as_matrix()
    w = np.radians([0.5, -1.0, 3.0])
    sp, sa = 0.01, np.radians(0.2)
    cov = np.diag([sp**2] * 3 + [sa**2] * 3)
    f = PoseFilter(accel_psd=1e-6, angacc_psd=1e-8)
    dt = 0.2
    errs_v, errs_w = [], []
    for k in range(300):
        t = k * dt
        T = _truth(t, p0, v, R0, w)
        Tm = make_T(Rotation.from_rotvec(rng.normal(0, sa, 3)).as_matrix() @ T[:3, :3],
                    T[:3, 3] + rng.normal(0, sp, 3))
        if not f.initialized:
            f.initialize(t, Tm, cov)
            continue
        res = f.update(t, Tm, cov)
        assert res.accepted
        errs_v.append(np.linalg.norm(f.v - v))
        errs_w.append(np.linalg.norm(f.w - w))
    assert errs_v[-1] < 2e-3 and np.degrees(errs_w[-1]) < 0.05
    # Filtering beats a single measurement: position error well under the 1-sigma noise.
    dp, da = pose_error(f.T_sensor_target, _truth(299 * dt, p0, v, R0, w))
    assert dp < sp and da < np.degrees(sa)
    # Consistency: the velocity error is within 3 sigma of the filter's own covariance.
    sv = np.sqrt(np.diag(f.P)[3:6])
    assert np.all(np.abs(f.v - v) < 4 * sv)


def test_prediction_follows_the_motion_model() -> None:
    f = PoseFilter()
    R0 = np.eye(3)
    f.initialize(0.0, make_T(R0, [0, 0, 10]), np.eye(6) * 1e-6, velocity=[0, 0, -0.1], omega=[0, 0, 0.1])
    T = f.pose_at(2.0)
    np.testing.assert_allclose(T[:3, 3], [0, 0, 9.8], atol=1e-12)
    np.testing.assert_allclose(Rotation.from_matrix(T[:3, :3]).as_rotvec(), [0, 0, 0.2], atol=1e-12)
    m = f.motion()
    np.testing.assert_allclose(m(2.0), T, atol=1e-12)
    with pytest.raises(ValueError, match="before the filter time"):
        f.predict(-1.0)


def test_innovation_gate_rejects_a_jump() -> None:
    f = PoseFilter(accel_psd=1e-6, angacc_psd=1e-8)
    cov = np.eye(6) * 1e-4
    f.initialize(0.0, make_T(None, [0, 0, 10]), cov, velocity=np.zeros(3))
    f.P[3:6, 3:6] = np.eye(3) * 1e-6
    ok = f.update(0.2, make_T(None, [0.005, 0, 10]), cov)
    assert ok.accepted
    bad = f.update(0.4, make_T(None, [1.0, 0, 10]), cov)
    assert not bad.accepted and bad.mahalanobis2 > 22
    assert abs(f.p[0]) < 0.05  # the jump did not pull the state


def test_range_filter_estimates_closing_rate() -> None:
    rng = np.random.default_rng(1)
    f = RangeFilter(accel_psd=1e-8)
    assert not f.rate_valid
    for k in range(200):
        t = 0.2 * k
        f.update(t, 300.0 - 0.25 * t + rng.normal(0, 0.05), 0.05)
    assert f.rate_valid
    assert f.range_rate == pytest.approx(-0.25, abs=0.005)
    assert f.range == pytest.approx(300.0 - 0.25 * 0.2 * 199, abs=0.05)


def test_bad_filter_parameters_named() -> None:
    with pytest.raises(ValueError, match="accel_psd"):
        PoseFilter(accel_psd=-1.0)
    with pytest.raises(ValueError, match="accel_psd"):
        RangeFilter(accel_psd=float("nan"))


def test_reference_point_filter_reports_the_target_origin() -> None:
    """Filtering the port 12 m from the centre of mass still reports the origin's state exactly."""
    rng = np.random.default_rng(2)
    p0, v = np.array([0.2, -0.1, 30.0]), np.array([0.0, 0.01, -0.05])
    R0 = Rotation.from_euler("xyz", [5, 10, -15], degrees=True).as_matrix()
    w = np.radians([0.0, 0.0, 0.5])
    r = np.array([0.0, 12.0, 0.0])
    sp, sa = 0.01, np.radians(0.3)
    cov = np.diag([sp**2] * 3 + [sa**2] * 3)
    f = PoseFilter(accel_psd=1e-6, angacc_psd=1e-8, ref_point=r)
    for k in range(200):
        t = 0.2 * k
        T = _truth(t, p0, v, R0, w)
        Tm = make_T(Rotation.from_rotvec(rng.normal(0, sa, 3)).as_matrix() @ T[:3, :3], T[:3, 3] + rng.normal(0, sp, 3))
        if not f.initialized:
            f.initialize(t, Tm, cov)
        else:
            f.update(t, Tm, cov)
    T = _truth(199 * 0.2, p0, v, R0, w)
    p, vel, R, om, P = f.target_state()
    np.testing.assert_allclose(f.T_sensor_target, make_T(R, p), atol=1e-12)
    assert np.linalg.norm(p - T[:3, 3]) < 0.05 and np.linalg.norm(vel - v) < 0.01
    assert np.degrees(np.linalg.norm(om - w)) < 0.05
    assert P.shape == (12, 12) and np.all(np.linalg.eigvalsh(0.5 * (P + P.T)) > -1e-12)


def _rotating_sensor_run(ego: bool, steps: int = 400, seed: int = 3):
    """A still, spinning target seen from a sensor that turns and thrusts (piecewise constant).

    Returns the RMS relative-rate [deg/s] and velocity [m/s] errors over the last 150 frames.
    """
    rng = np.random.default_rng(seed)
    dt = 0.2
    P_I = np.array([0.3, -0.2, 8.0])  # target origin, inertial [m]
    Om_I = np.radians([0.5, -1.0, 3.0])  # target inertial rate, inertial coordinates
    R_It0 = Rotation.from_euler("xyz", [170, 5, 40], degrees=True).as_matrix()
    R_Is, S, S_dot = np.eye(3), np.zeros(3), np.zeros(3)
    sp, sa = 0.01, np.radians(0.3)
    cov = np.diag([sp**2] * 3 + [sa**2] * 3)
    # Without ego data the host's manoeuvres are process noise: the best of a sweep (0.05 / 0.005
    # diverges, 0.5 / 0.05 and up are noisier).
    f = PoseFilter(accel_psd=1e-6 if ego else 0.2**2, angacc_psd=1e-8 if ego else 0.02**2)
    ew, ev = [], []
    for k in range(steps):
        t = k * dt
        # the host's motion over [t, t + dt): a slow tumble of its own and on/off thrust
        w_s = np.radians(5.0) * np.array([np.sin(0.3 * t), np.cos(0.2 * t), 0.5 * np.sin(0.1 * t)])
        a_I = 0.02 * np.array([np.sign(np.sin(0.5 * t)), 0.0, np.sign(np.cos(0.3 * t))])
        R_It = Rotation.from_rotvec(Om_I * t).as_matrix() @ R_It0
        R_sI = R_Is.T
        T = make_T(R_sI @ R_It, R_sI @ (P_I - S))
        w_true = R_sI @ Om_I - w_s
        v_true = R_sI @ (-S_dot) - np.cross(w_s, T[:3, 3])
        Tm = make_T(Rotation.from_rotvec(rng.normal(0, sa, 3)).as_matrix() @ T[:3, :3],
                    T[:3, 3] + rng.normal(0, sp, 3))
        if not f.initialized:
            if ego:
                f.set_ego(EgoMotion(w_s, R_sI @ a_I))
            f.initialize(t, Tm, cov)
        else:
            f.update(t, Tm, cov)  # predicted over [t - dt, t) with the motion then in force
            if ego:
                f.set_ego(EgoMotion(w_s, R_sI @ a_I))
            if k >= steps - 150:
                ew.append(np.linalg.norm(f.w - w_true))
                ev.append(np.linalg.norm(f.v - v_true))
        # propagate the host exactly over the step
        R_Is = R_Is @ Rotation.from_rotvec(w_s * dt).as_matrix()
        S = S + S_dot * dt + 0.5 * a_I * dt * dt
        S_dot = S_dot + a_I * dt
    return np.degrees(np.sqrt(np.mean(np.square(ew)))), float(np.sqrt(np.mean(np.square(ev))))


def test_ego_motion_takes_the_hosts_rotation_out_of_the_process_noise() -> None:
    """With the host's gyro and accelerometer the filter models the target inertially: a
    manoeuvring sensor no longer costs rate accuracy."""
    ego_w, ego_v = _rotating_sensor_run(ego=True)
    plain_w, plain_v = _rotating_sensor_run(ego=False)
    assert ego_w < 0.05 and ego_v < 0.005  # [deg/s], [m/s]
    assert ego_w < plain_w / 10 and ego_v < plain_v / 10  # measured: 0.013 vs 1.0, 0.0017 vs 0.084


def _cw_drift(n: float, rho0: np.ndarray, rho_dot0: np.ndarray, t: float) -> np.ndarray:
    """The chaser's LVLH position at ``t`` on a free Clohessy-Wiltshire drift (x radial, y along
    track, z orbit normal): ``expm(A t)`` of the CW equations, independent of the filter's model."""
    from scipy.linalg import expm

    A = np.zeros((6, 6))
    A[0:3, 3:6] = np.eye(3)
    A[3, 0], A[5, 2] = 3.0 * n * n, -n * n
    A[3, 4], A[4, 3] = 2.0 * n, -2.0 * n
    return (expm(A * t) @ np.concatenate([rho0, rho_dot0]))[:3]


@pytest.mark.parametrize("rho0", [[0.0, -20.0, 0.0], [-15.0, 0.0, 0.0], [4.0, -8.0, 6.0]])
def test_the_tide_keeps_the_prediction_on_a_free_drift(rho0: list[float]) -> None:
    """A chaser holding LVLH (its sensor axes the LVLH axes, the gyro reading the orbit rate)
    coasting near the target: with the gravity gradient the filter predicts the target's fall
    relative to it as the CW equations do; without, it is off by the tide's n^2 r t^2 / 2."""
    n = 1.1e-3  # [rad/s], low orbit
    rho0 = np.asarray(rho0)
    rho_dot0 = np.array([0.004, 0.03, -0.002])
    w_s = np.array([0.0, 0.0, n])  # LVLH turns at n about the orbit normal
    G = gravity_gradient(n, [1.0, 0.0, 0.0])
    np.testing.assert_allclose(G @ np.array([1.0, 2.0, 3.0]), n * n * np.array([2.0, -2.0, -3.0]))
    errs = {}
    for tide in (True, False):
        f = PoseFilter(accel_psd=1e-10, angacc_psd=1e-10)
        f.set_ego(EgoMotion(w_s, np.zeros(3), G if tide else None))
        # the target, relative to the sensor, is at -rho and moves at -rho_dot (sensor axes)
        f.initialize(0.0, make_T(np.eye(3), -rho0), 1e-8 * np.eye(6), velocity=-rho_dot0,
                     omega=np.zeros(3))
        for k in range(1, 601):
            f.predict(0.5 * k)
        truth = -_cw_drift(n, rho0, rho_dot0, 300.0)
        errs[tide] = float(np.linalg.norm(f.T_sensor_target[:3, 3] - truth))
    # Measured: 0.3-0.8 mm with the tide against 0.7-1.6 m without (300 s).
    assert errs[True] < 2e-3
    assert errs[False] > 0.3
    # The tide's variance is carried as a state dependence: F holds G, so P stays symmetric PSD.
    assert np.all(np.linalg.eigvalsh(0.5 * (f.P + f.P.T)) > -1e-12)


def test_ego_motion_input_is_checked() -> None:
    with pytest.raises(ValueError, match="EgoMotion.omega"):
        EgoMotion(np.array([0.0, np.nan, 0.0]), np.zeros(3))
    with pytest.raises(ValueError, match="EgoMotion.accel"):
        EgoMotion(np.zeros(3), np.zeros(2))
    with pytest.raises(ValueError, match="EgoMotion.gravity_gradient"):
        EgoMotion(np.zeros(3), np.zeros(3), np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]]))
    with pytest.raises(ValueError, match="EgoMotion.gravity_gradient"):
        EgoMotion(np.zeros(3), np.zeros(3), np.full((3, 3), np.nan))
    with pytest.raises(ValueError, match="mean_motion"):
        gravity_gradient(1e-3, [0.0, 0.0, 0.0])
    with pytest.raises(ValueError, match="inertia"):
        PoseFilter(inertia=np.diag([1.0, -1.0, 2.0]))


def test_torque_free_model_predicts_a_nutating_tumble() -> None:
    """With the target's inertia the prediction follows Euler's equations (exact over 20 s),
    where a constant-rate model drifts by degrees."""
    from scipy.integrate import solve_ivp

    J = np.diag([1.83, 7.04, 8.19])  # the cygnss-like target's principal inertia [kg m^2]
    om0 = np.radians([1.0, 0.8, 5.0])  # spin about the major axis with a nutation
    R0 = Rotation.from_euler("xyz", [20, -10, 5], degrees=True).as_matrix()

    def rhs(_t, y):
        om = y[:3]
        dom = np.linalg.solve(J, np.cross(J @ om, om))
        R = y[3:].reshape(3, 3)
        return np.r_[dom, (R @ np.array([[0, -om[2], om[1]], [om[2], 0, -om[0]], [-om[1], om[0], 0]])).ravel()]

    sol = solve_ivp(rhs, (0, 20.0), np.r_[om0, R0.ravel()], rtol=1e-12, atol=1e-12)
    R_true = Rotation.from_matrix(sol.y[3:, -1].reshape(3, 3)).as_matrix()
    errs = {}
    for name, inertia in (("euler", J), ("constant", None)):
        f = PoseFilter(inertia=inertia)
        f.initialize(0.0, make_T(R0, [0, 0, 10]), np.eye(6) * 1e-8, velocity=np.zeros(3), omega=R0 @ om0)
        for k in range(1, 101):
            f.predict(0.2 * k)
        errs[name] = pose_error(f.T_sensor_target, make_T(R_true, [0, 0, 10]))[1]
        if name == "euler":
            np.testing.assert_allclose(f.R.T @ f.w, sol.y[:3, -1], atol=1e-8)
    assert errs["euler"] < 1e-4 and errs["constant"] > 1.0  # [deg]


def _slide_run(tau: float | None, seed: int) -> tuple[float, float]:
    """A converged filter sure of a wrong velocity (5 cm/s, 2 mm/s sigma) along x takes 200 s of
    registrations whose x error is a slide (a random walk, 2 cm per frame) reported as such (1 m
    sigma added along x); returns the worst |x error| / x sigma after the first 10 s and the
    final x error [m]."""
    rng = np.random.default_rng(seed)
    f = PoseFilter(accel_psd=(2e-4) ** 2, angacc_psd=(2e-5) ** 2)
    T = make_T(np.eye(3), np.array([0.0, 0.0, 120.0]))
    cov = np.diag([0.005**2] * 3 + [np.radians(0.05) ** 2] * 3)
    f.initialize(0.0, T, cov, velocity=np.array([0.05, 0.0, 0.0]))
    P = f.P.copy()
    P[3:6, 3:6] = np.eye(3) * 0.002**2
    f.P = P
    s, e = 1.0, np.array([1.0, 0.0, 0.0])
    cov_slide = cov.copy()
    cov_slide[:3, :3] += s * s * np.outer(e, e)
    bias, worst = 0.0, 0.0
    for k in range(1, 401):
        t = 0.5 * k
        bias += rng.normal(0.0, 0.02)
        Tm = T.copy()
        Tm[:3, 3] += bias * e + rng.normal(0.0, 0.005, 3)
        if tau is not None:
            f.floor_velocity(e, s / tau)
        f.update(t, Tm, cov_slide)
        if t > 10.0:
            worst = max(worst, abs(f.p[0]) / np.sqrt(f.P[0, 0]))
    return worst, abs(f.p[0])


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_velocity_floor_keeps_a_slide_inside_the_covariance(seed: int) -> None:
    """Without the floor the filter averages the slide away, keeps its wrong velocity and ends
    many sigma off; with it (slide sigma / 10 s) the error stays inside 3 sigma throughout."""
    worst_off, _ = _slide_run(None, seed)
    worst_on, err_on = _slide_run(10.0, seed)
    assert worst_off > 5.0
    assert worst_on < 3.0
    assert err_on < 0.5


def test_velocity_floor_only_raises_the_variance_along_its_axis() -> None:
    f = PoseFilter()
    f.initialize(0.0, make_T(np.eye(3), [0.0, 0.0, 50.0]), np.eye(6) * 1e-6)
    P0 = f.P.copy()
    axis = np.array([1.0, 2.0, 2.0])
    e = axis / 3.0
    f.floor_velocity(axis, 1.0)  # above the 0.3 m/s init sigma: raised to exactly 1 m/s
    assert e @ f.P[3:6, 3:6] @ e == pytest.approx(1.0)
    dP = f.P - P0
    np.testing.assert_allclose(dP[3:6, 3:6], (1.0 - 0.09) * np.outer(e, e), atol=1e-12)
    dP[3:6, 3:6] = 0.0
    assert not dP.any()
    f.floor_velocity(axis, 0.1)  # already above: unchanged
    assert e @ f.P[3:6, 3:6] @ e == pytest.approx(1.0)
    assert np.all(np.linalg.eigvalsh(f.P) > 0)
    with pytest.raises(ValueError, match="floor_velocity"):
        f.floor_velocity([0.0, 0.0, 0.0], 1.0)


def _offset_run(floor: bool) -> float:
    """A filter restarted on four registrations that share one offset along a held slide (1.5 m
    along x, the slide reported at 2 m sigma there, millimetres elsewhere) then takes 40 more
    of them (no velocity floor: the position's own averaging is what is tested); returns the
    worst |x error| / the protection level along x (risk 1e-3) of the state published after
    each update: the filter's copy, floored at the slide's sigma when ``floor``."""
    f = PoseFilter(accel_psd=(2e-4) ** 2, angacc_psd=(2e-5) ** 2)
    T = make_T(np.eye(3), np.array([0.0, 0.0, 85.0]))
    s, e = 2.0, np.array([1.0, 0.0, 0.0])
    cov = np.diag([0.005**2] * 3 + [np.radians(0.05) ** 2] * 3)
    cov[:3, :3] += s * s * np.outer(e, e)
    Tm = T.copy()
    Tm[:3, 3] += 1.5 * e
    f.initialize(0.0, Tm, cov, velocity=np.zeros(3))
    P = f.P.copy()
    P[3:6, 3:6] = np.eye(3) * 0.002**2  # a restart keeps the track's (converged) rates
    f.P = P
    k_pl = integrity_factor(1e-3)
    worst = 0.0
    for k in range(1, 44):
        assert f.update(0.5 * k, Tm, cov).accepted
        pub = f.copy()
        if floor:
            pub.floor_position(e, s)
        assert abs(pub.p[0] - f.p[0]) == 0.0  # the floor moves the bound, never the estimate
        worst = max(worst, abs(pub.p[0]) / (k_pl * np.sqrt(pub.P[0, 0])))
    return worst


def test_position_floor_keeps_a_shared_slide_offset_inside_the_protection_level() -> None:
    """Averaged as independent, 44 registrations with one 1.5 m offset along a 2 m slide put
    the filter's protection level under the error; the published copy floored at the slide's
    sigma covers it, and the floor itself is exactly the slide's variance along its axis only."""
    assert _offset_run(False) > 1.0
    assert _offset_run(True) < 0.5
    f = PoseFilter()
    f.initialize(0.0, make_T(np.eye(3), [0.0, 0.0, 50.0]), np.eye(6) * 1e-6)
    P0 = f.P.copy()
    e = np.array([2.0, 1.0, 2.0]) / 3.0
    f.floor_position(3.0 * e, 0.4)
    assert e @ f.P[:3, :3] @ e == pytest.approx(0.16)
    dP = f.P - P0
    np.testing.assert_allclose(dP[:3, :3], (0.16 - 1e-6) * np.outer(e, e), atol=1e-12)
    dP[:3, :3] = 0.0
    assert not dP.any()
    with pytest.raises(ValueError, match="floor_position"):
        f.floor_position([np.nan, 0.0, 1.0], 0.4)


def _roll_null_cov(o: np.ndarray, a: np.ndarray, tilt_rad: float, rng: np.random.Generator) -> np.ndarray:
    """A registration covariance that leaves the roll about the axis along z through ``a``
    unobserved (1e6 along it, as ICP reports it), its null direction estimated ``tilt_rad`` off
    in a random direction (ICP's null vector moves a little from frame to frame); 1 cm and
    0.2 deg on the observed directions. Twist about the target origin ``o``."""
    axis = Rotation.from_rotvec(tilt_rad * np.array([*rng.normal(size=2), 0.0]) / np.sqrt(2.0)).apply([0, 0, 1.0])
    u = np.concatenate([np.cross(axis, o - a), axis])
    cov = np.diag([1e-4] * 3 + [np.radians(0.2) ** 2] * 3)
    return cov + 1e6 * np.outer(u, u) / float(u @ u)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_direction_no_registration_observes_is_never_pinned(seed: int) -> None:
    """Registrations that each leave a bus's roll unobserved (null vectors a few degrees apart,
    the roll following whatever the prediction said) leave the roll and its rate as uncertain as
    they started, however many there are, while everything they observe converges; one
    registration that pins the roll pins it. (Fused optimally, these 40 frames brought the roll's
    variance from 1e6 down to 0.0007-0.0012, on no evidence.)"""
    rng = np.random.default_rng(seed)
    o = np.array([0.3, -0.2, 30.0])
    a = o + np.array([1.2, 0.4, 0.0])  # the roll axis passes 1.3 m from the target origin
    f = PoseFilter(accel_psd=1e-6, angacc_psd=1e-8, init_rate_sigma=np.radians(6.0))
    u_true = np.concatenate([np.cross([0, 0, 1.0], o - a), [0, 0, 1.0]])
    u_true /= np.linalg.norm(u_true)
    idx = [0, 1, 2, 6, 7, 8]
    rate_idx = [3, 4, 5, 9, 10, 11]
    for k in range(40):
        t = 0.2 * k
        # the registration rolls 0.5 deg a frame about the bus axis (a drift the scans allow)
        roll = make_T(Rotation.from_rotvec([0, 0, np.radians(0.5 * k)]).as_matrix())
        Tm = make_T(None, a) @ roll @ make_T(None, o - a + rng.normal(0, 0.01, 3))
        cov = _roll_null_cov(o, a, np.radians(3.0), rng)
        if k == 0:
            f.initialize(t, Tm, cov)
            prior = float(u_true @ f.P[np.ix_(idx, idx)] @ u_true)
            continue
        assert f.update(t, Tm, cov).accepted
    roll_var = float(u_true @ f.P[np.ix_(idx, idx)] @ u_true)
    rate_var = float(u_true @ f.P[np.ix_(rate_idx, rate_idx)] @ u_true)
    assert roll_var >= 0.5 * prior  # still unknown (about 1e5 m^2 + rad^2 along it)
    assert np.sqrt(rate_var) >= 0.9 * np.radians(6.0) / np.linalg.norm(u_true[3:])
    # what the registrations observe is known better than one registration says
    lam, V = np.linalg.eigh(cov)
    Pp = f.P[np.ix_(idx, idx)]
    for k in np.flatnonzero(lam < 1.0):
        assert float(V[:, k] @ Pp @ V[:, k]) < lam[k]
    # one registration that pins the roll (where the last ones had it) pins it
    full = np.diag([1e-4] * 3 + [np.radians(0.2) ** 2] * 3)
    roll = make_T(Rotation.from_rotvec([0, 0, np.radians(20.0)]).as_matrix())
    assert f.update(8.0, make_T(None, a) @ roll @ make_T(None, o - a), full).accepted
    assert float(u_true @ f.P[np.ix_(idx, idx)] @ u_true) < np.radians(1.0) ** 2


def test_a_restart_on_rejected_registrations_doubts_the_rates_it_keeps() -> None:
    """A track sure of a false 1.5 deg/s roll rate (a slow basin change taught it) about a still
    target: the registrations are rejected, and the filter restarted on them keeps the rate but
    as doubtful as the rejected registration says (the rate error that alone explains it); the
    following registrations then take it out in a few frames. Kept as sure as it was, every
    restart drifted the roll off again."""
    from types import SimpleNamespace

    from perception.pipeline.tracking import TrackingMode

    w_false = np.radians(1.5)
    T = make_T(None, [0.2, -0.1, 20.0])
    cov = np.diag([1e-6] * 3 + [np.radians(0.05) ** 2] * 3)

    def restarted(doubt: bool) -> float:
        f = PoseFilter(accel_psd=1e-8, angacc_psd=1e-10)
        f.initialize(0.0, T, cov, velocity=np.zeros(3), omega=[0.0, 0.0, w_false])
        f.P[3:6, 3:6] = np.eye(3) * 1e-8
        f.P[9:12, 9:12] = np.eye(3) * 1e-10
        rejected = []
        for t in (0.4, 0.6, 0.8):  # the still target's pose, 0.6-1.2 deg from the prediction
            assert not f.update(t, T, cov).accepted
            rejected.append((t, T, cov, cov, 0.0))
        d = f.rate_doubt(T, 0.0)
        np.testing.assert_allclose(d[3:], [0.0, 0.0, -w_false], atol=np.radians(0.01))
        np.testing.assert_allclose(d[:3], 0.0, atol=1e-9)
        tm = TrackingMode.__new__(TrackingMode)
        tm.tri = SimpleNamespace(last_pose_t=0.0)
        tm.rejected = rejected[-2:]
        g = tm._restart_on_rejected(f)
        assert g is not None
        if doubt:
            assert np.sqrt(g.P[11, 11]) >= 0.9 * w_false  # as doubtful as the rate error
        else:
            g.P[9:12, 9:12] = f.P[9:12, 9:12]  # the restart as it was: the rate kept, as sure
        for k in range(1, 16):  # frames of the still target
            g.update(0.8 + 0.2 * k, T, cov)
        return abs(float(g.w[2]))

    assert restarted(doubt=True) < np.radians(0.1)
    assert restarted(doubt=False) > np.radians(1.0)


def test_the_accuracy_covariance_is_the_error_covariance_of_the_gains_the_filter_uses() -> None:
    """Registrations with ICP's own noise (0.5 mm, 0.02 deg, a pivot 1.5 m off: correlated
    position and attitude) fused with floors on top (1 cm, 0.3 deg), as the pipeline does: the
    filter's ``P`` is far too pessimistic for the error the state has, ``P_acc`` describes it
    (NEES of the pose over 400 seeded runs inside the chi-square(6) mean's 99.9 % band), and
    passing ``cov_acc`` leaves the state and ``P`` bitwise as they were."""
    from scipy.stats import chi2

    from perception.geometry import skew

    J = np.eye(6)
    J[:3, 3:] = -skew([0.0, 1.5, 0.0])
    R_icp = J @ np.diag([5e-4**2] * 3 + [np.radians(0.02) ** 2] * 3) @ J.T
    R_f = R_icp + np.diag([0.01**2] * 3 + [np.radians(0.3) ** 2] * 3)
    L = np.linalg.cholesky(R_icp)
    T0 = make_T(Rotation.from_euler("xyz", [5, -10, 30], degrees=True).as_matrix(), [0.3, -0.2, 12.0])
    rng = np.random.default_rng(5)
    n_runs = 400
    nees_acc, nees_filt = np.empty(n_runs), np.empty(n_runs)
    for k in range(n_runs):
        f = PoseFilter(accel_psd=1e-14, angacc_psd=1e-16)  # a still target: no process noise
        g = PoseFilter(accel_psd=1e-14, angacc_psd=1e-16)

        def meas() -> np.ndarray:
            d = L @ rng.standard_normal(6)
            return make_T(Rotation.from_rotvec(d[3:]).as_matrix() @ T0[:3, :3], T0[:3, 3] + d[:3])

        T = meas()
        f.initialize(0.0, T, R_f, velocity=np.zeros(3), omega=np.zeros(3), cov_acc=R_icp)
        g.initialize(0.0, T, R_f, velocity=np.zeros(3), omega=np.zeros(3))
        for i in range(1, 25):
            T = meas()
            assert f.update(0.2 * i, T, R_f, R_icp).accepted and g.update(0.2 * i, T, R_f).accepted
        assert np.array_equal(f.P, g.P) and np.array_equal(f.p, g.p) and np.array_equal(f.R, g.R)
        Te = f.T_sensor_target
        e = np.concatenate([Te[:3, 3] - T0[:3, 3], Rotation.from_matrix(Te[:3, :3] @ T0[:3, :3].T).as_rotvec()])
        _, _, _, _, P = f.target_state()
        A = f.accuracy_covariance()
        idx = [0, 1, 2, 6, 7, 8]
        nees_acc[k] = e @ np.linalg.solve(A[np.ix_(idx, idx)], e)
        nees_filt[k] = e @ np.linalg.solve(P[np.ix_(idx, idx)], e)
    lo, hi = chi2.ppf([0.0005, 0.9995], 6 * n_runs) / n_runs
    assert lo < nees_acc.mean() < hi
    assert nees_filt.mean() < 0.1 * lo  # the floors' covariance: pessimistic tenfold and more


def test_the_accuracy_covariance_carries_the_time_of_flight_range_offset_as_the_gains_take_it() -> None:
    """A range offset common to every time-of-flight registration (one draw per run from the
    configured 5 mm sigma, along the line of sight) is not noise the filter averages: it takes
    it into the state, and when the scans switch to triangulation it lets it go at the gains'
    pace. ``range_bias_m`` carries it into ``P_acc`` as a consider parameter: the position NEES
    over 400 seeded runs is inside the chi-square(3) mean's 99.9 % band at the end of the
    time-of-flight frames, two frames after the switch and at the end; without it the end of
    the time-of-flight frames is far outside. The state and ``P`` are bitwise those of the
    filter without it."""
    from scipy.stats import chi2

    R_icp = np.diag([5e-4**2] * 3 + [np.radians(0.02) ** 2] * 3)
    R_f = R_icp + np.diag([0.01**2] * 3 + [np.radians(0.3) ** 2] * 3)
    L = np.linalg.cholesky(R_icp)
    T0 = make_T(Rotation.from_euler("xyz", [5, -10, 30], degrees=True).as_matrix(), [0.3, -0.2, 12.0])
    u = T0[:3, 3] / np.linalg.norm(T0[:3, 3])
    sigma_b = 0.005
    rng = np.random.default_rng(8)
    n_runs, checks = 400, (24, 27, 49)
    nees = {c: np.empty(n_runs) for c in checks}
    nees_without = np.empty(n_runs)
    for k in range(n_runs):
        f = PoseFilter(accel_psd=1e-14, angacc_psd=1e-16, range_bias_m=sigma_b)
        g = PoseFilter(accel_psd=1e-14, angacc_psd=1e-16)
        b = sigma_b * rng.standard_normal()
        for i in range(50):
            share = 1.0 if i < 25 else 0.0
            d = L @ rng.standard_normal(6)
            T = make_T(Rotation.from_rotvec(d[3:]).as_matrix() @ T0[:3, :3], T0[:3, 3] + d[:3] + share * b * u)
            if i == 0:
                for h in (f, g):
                    h.initialize(0.0, T, R_f, velocity=np.zeros(3), omega=np.zeros(3), cov_acc=R_icp,
                                 tof_share=share)
            else:
                assert f.update(0.2 * i, T, R_f, R_icp, tof_share=share).accepted
                assert g.update(0.2 * i, T, R_f, R_icp, tof_share=share).accepted
            e = f.T_sensor_target[:3, 3] - T0[:3, 3]
            if i in checks:
                nees[i][k] = e @ np.linalg.solve(f.accuracy_covariance()[0:3, 0:3], e)
            if i == checks[0]:
                nees_without[k] = e @ np.linalg.solve(g.accuracy_covariance()[0:3, 0:3], e)
        assert np.array_equal(f.P, g.P) and np.array_equal(f.p, g.p) and np.array_equal(f.R, g.R)
    lo, hi = chi2.ppf([0.0005, 0.9995], 3 * n_runs) / n_runs
    for c in checks:
        assert lo < nees[c].mean() < hi, (c, nees[c].mean(), lo, hi)
    assert nees_without.mean() > 10 * hi


@pytest.mark.parametrize("k2", [4.0, 0.5])
def test_the_accuracy_covariance_takes_the_scatter_the_registrations_show(k2: float) -> None:
    """Registrations whose positions scatter ``k2`` times the variance their covariance claims
    (ICP's bound wrong by a factor, as on shapes where the scan's samples fall differently each
    frame; the attitude as claimed): with ``scatter_window`` the filter's ``scatter_scale``
    finds the factor along and across the line of sight from the registrations' residuals to
    the state (no truth), and the accuracy covariance's pose NEES over 200 seeded runs is
    inside the chi-square(6) mean's 99.9 % band; without it, off by the factor. The state and
    ``P`` are bitwise those of the filter without it (nothing in the loop reads ``P_acc``)."""
    from scipy.stats import chi2

    R_icp = np.diag([5e-4**2] * 3 + [np.radians(0.02) ** 2] * 3)
    R_f = R_icp + np.diag([0.01**2] * 3 + [np.radians(0.3) ** 2] * 3)
    L = np.diag([np.sqrt(k2)] * 3 + [1.0] * 3) @ np.linalg.cholesky(R_icp)
    T0 = make_T(Rotation.from_euler("xyz", [5, -10, 30], degrees=True).as_matrix(), [0.3, -0.2, 12.0])
    rng = np.random.default_rng(11)
    n_runs, n_frames = 200, 150
    nees_with, nees_without, scales = np.empty(n_runs), np.empty(n_runs), np.empty((n_runs, 2))
    idx = [0, 1, 2, 6, 7, 8]
    for k in range(n_runs):
        f = PoseFilter(accel_psd=1e-14, angacc_psd=1e-16, scatter_window=50)
        g = PoseFilter(accel_psd=1e-14, angacc_psd=1e-16)
        for i in range(n_frames):
            d = L @ rng.standard_normal(6)
            T = make_T(Rotation.from_rotvec(d[3:]).as_matrix() @ T0[:3, :3], T0[:3, 3] + d[:3])
            if i == 0:
                for h in (f, g):
                    h.initialize(0.0, T, R_f, velocity=np.zeros(3), omega=np.zeros(3), cov_acc=R_icp)
                assert f.scatter_scale() == (1.0, 1.0)  # nothing seen yet
            else:
                assert f.update(0.2 * i, T, R_f, R_icp).accepted and g.update(0.2 * i, T, R_f, R_icp).accepted
        assert np.array_equal(f.P, g.P) and np.array_equal(f.p, g.p) and np.array_equal(f.R, g.R)
        assert len(f.scatter) == 50
        scales[k] = f.scatter_scale()
        Te = f.T_sensor_target
        e = np.concatenate([Te[:3, 3] - T0[:3, 3], Rotation.from_matrix(Te[:3, :3] @ T0[:3, :3].T).as_rotvec()])
        nees_with[k] = e @ np.linalg.solve(f.accuracy_covariance()[np.ix_(idx, idx)], e)
        nees_without[k] = e @ np.linalg.solve(g.accuracy_covariance()[np.ix_(idx, idx)], e)
    # Each run's factors from 50 frames (50 and 100 dof): within 10 % on average.
    assert np.allclose(scales.mean(axis=0), k2, rtol=0.1), scales.mean(axis=0)
    lo, hi = chi2.ppf([0.0005, 0.9995], 6 * n_runs) / n_runs
    assert lo < nees_with.mean() < hi, (nees_with.mean(), lo, hi)
    assert not lo < nees_without.mean() < hi
    assert np.isclose(nees_without.mean() / 3.0 - 1.0, k2, rtol=0.25)  # 3 k2 + 3


def test_the_scatter_scale_leaves_out_what_a_registration_does_not_observe() -> None:
    """A registration that leaves a direction unobserved (ICP's 1e6 along it) adds only the
    directions it observes to the scatter window; its dof are counted as such, and a residual
    along the unobserved direction, however large, changes nothing."""
    R_icp = np.diag([4e-6, 4e-6, 1e6, 1e-6, 1e-6, 1e-6])
    R_f = R_icp + np.diag([1e-4] * 3 + [1e-4] * 3)
    f = PoseFilter(accel_psd=1e-14, angacc_psd=1e-16, scatter_window=40)
    T0 = make_T(np.eye(3), [0.0, 0.0, 8.0])
    rng = np.random.default_rng(2)
    f.initialize(0.0, T0, R_f, velocity=np.zeros(3), omega=np.zeros(3), cov_acc=R_icp)
    for i in range(1, 60):
        d = np.concatenate([2e-3 * rng.standard_normal(2), [5.0 * rng.standard_normal()], 1e-3 * rng.standard_normal(3)])
        T = make_T(Rotation.from_rotvec(d[3:]).as_matrix(), T0[:3, 3] + d[:3])
        assert f.update(0.2 * i, T, R_f, R_icp).accepted
    # The line of sight (z) is the unobserved axis: no dof along it, two across, three turns.
    dof = np.array([w[1::2] for w in f.scatter])
    assert np.allclose(dof, [0.0, 2.0], atol=1e-3)
    s_al, s_ac = f.scatter_scale()
    assert s_al == 1.0  # never observed: left alone (whatever the residuals along it)
    assert 0.6 < s_ac < 1.5  # the observed axes scatter as claimed
    with pytest.raises(ValueError, match="scatter_window"):
        PoseFilter(scatter_window=-1)


def test_the_scatter_factors_keep_each_registration_direction_on_its_axis() -> None:
    """The factors go onto the registration covariance's principal directions in their shares
    of along / across the line of sight (the attitude's share keeps 1): every eigenvector stays one (a weakly
    observed direction's metres, or an unobserved direction's 1e6 that couples position and
    attitude, cannot leak into the well-observed directions), an unobserved one keeps its
    variance, and a pure along / across direction takes exactly its factor."""
    from perception.pipeline.filter import UNOBSERVED_VARIANCE

    rng = np.random.default_rng(4)
    Q = np.linalg.qr(rng.standard_normal((6, 6)))[0]
    Q[:, 0] = np.array([0.0, 0.0, 1.0, 0.0, 0.0, 0.0])  # along the line of sight (p on +z)
    Q[:, 1] = np.array([1.0, 0.0, 0.0, 0.0, 0.0, 0.0])  # across
    Q[:, 2] = np.array([0.0, 0.0, 0.0, 0.0, 0.0, 1.0])  # attitude
    Q[:, 3] = np.array([0.0, 0.6, 0.0, 0.8, 0.0, 0.0])  # a turn about x that moves y: unobserved
    Q[:, 4] = np.array([0.0, 0.8, 0.0, -0.6, 0.0, 0.0])  # its observed complement
    Q[:, 5] = np.array([0.0, 0.0, 0.0, 0.0, 1.0, 0.0])
    lam = np.array([1e-6, 4e-6, 1e-8, 1e3, 3.0, 2e-8])
    R = (Q * lam) @ Q.T
    f = PoseFilter(scatter_window=10)
    f.scatter = tuple([(16.0, 4.0, 4.0, 8.0)] * 10)  # factors 4 and 0.5
    assert f.scatter_scale() == (4.0, 0.5)
    from perception.pipeline.filter import _principal

    Rs = f._scattered(R, *_principal(R, np.array([0.0, 0.0, 8.0])))
    expected = np.array([4.0, 0.5, 1.0, 1.0, 0.64 * 0.5 + 0.36, 1.0]) * lam  # attitude: 1
    expected[3] = lam[3]  # unobserved: as it was
    assert lam[3] > UNOBSERVED_VARIANCE > lam[4]
    for j in range(6):
        assert np.allclose(Rs @ Q[:, j], expected[j] * Q[:, j], rtol=0.0, atol=1e-4 * lam[j])
