"""Tests for tridar_env.dynamics: CW, nonlinear relative motion, attitude and propellant."""

from __future__ import annotations

import doctest

import numpy as np
import pytest
from scipy.integrate import solve_ivp
from scipy.linalg import expm
from scipy.spatial.transform import Rotation

from tridar_env import dynamics
from tridar_env.dynamics import (
    G0,
    J2_EARTH,
    ChaserMass,
    CWPropagator,
    NonlinearRelativePropagator,
    RigidBodyAttitude,
    TargetAttitudeModel,
    circular_orbit_state,
    cw_stm,
    eci_from_relative_lvlh,
    gravity_acceleration,
    lvlh_frame,
    mass_flow_rate,
    mean_motion,
    principal_axes,
    propellant_used,
    relative_lvlh_from_eci,
    saturate_thrust,
    spin_with_nutation,
)

ALT = 400e3  # [m]
N = mean_motion(ALT)  # [rad/s]
PERIOD = 2.0 * np.pi / N  # [s]

# A physical asymmetric tensor with products of inertia (principal ~11.8, 19.7, 28.5 kg m^2).
# (diag(10, 20, 30) plus off-diagonal terms is not one: it breaks J1 + J2 >= J3.)
INERTIA_ASYM = np.array([[12.0, 1.0, -0.5], [1.0, 20.0, 2.0], [-0.5, 2.0, 28.0]])


def cw_matrix(n: float) -> np.ndarray:
    """Continuous CW system matrix A for x_dot = A x + B a."""
    a = np.zeros((6, 6))
    a[:3, 3:] = np.eye(3)
    a[3, 0], a[3, 4] = 3.0 * n * n, 2.0 * n
    a[4, 3] = -2.0 * n
    a[5, 2] = -n * n
    return a


def rot_wxyz(q: np.ndarray) -> Rotation:
    """Rotation from scalar-first quaternion(s)."""
    return Rotation.from_quat(np.asarray(q)[..., [1, 2, 3, 0]])


def angle_between(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Angle [rad] between rows of u and v, accurate near 0."""
    cross = np.linalg.norm(np.cross(u, v), axis=-1)
    return np.arctan2(cross, np.sum(u * v, axis=-1))


# ----------------------------------------------------------------------------------------------
# mean motion and CW
# ----------------------------------------------------------------------------------------------


def test_mean_motion_iss_period() -> None:
    # ISS-like 400 km: T = 2 pi sqrt(a^3 / mu) = 5553.6 s (92.56 min).
    assert PERIOD == pytest.approx(5553.62, abs=0.01)


@pytest.mark.parametrize("dt", [1e-3, 1.0, 30.0, 1000.0, PERIOD])
def test_cw_stm_matches_van_loan_matrix_exponential(dt: float) -> None:
    # expm([[A, B], [0, 0]] dt) = [[Phi, Gamma], [0, I]]: an independent route to the ZOH model.
    aug = np.zeros((9, 9))
    aug[:6, :6] = cw_matrix(N)
    aug[3:6, 6:] = np.eye(3)
    ref = expm(aug * dt)
    phi, gamma = cw_stm(N, dt)
    np.testing.assert_allclose(phi, ref[:6, :6], rtol=1e-12, atol=1e-12 * max(1.0, dt))
    # expm's round-off is relative to the block's largest entry (4.6e7 s^2 at one period, where
    # (1 - cos n dt) / n^2 is 0 in closed form and ~5e-7 in the reference with scipy 1.17)
    scale = float(np.max(np.abs(ref[:6, 6:])))
    np.testing.assert_allclose(gamma, ref[:6, 6:], rtol=1e-12, atol=1e-13 * max(1.0, scale))


def test_cw_gamma_small_step_has_no_cancellation() -> None:
    # n dt = 1e-7: (1-c)/n^2 and (theta - sin theta)/n^2 must keep full relative precision.
    # Reference: Gamma = sum_k A^k B dt^(k+1) / (k+1)!, exact in double after a few terms.
    dt = 1e-4
    a_mat = cw_matrix(N)
    term = np.vstack([np.zeros((3, 3)), np.eye(3)]) * dt
    ref = np.zeros((6, 3))
    for k in range(1, 8):
        ref += term
        term = a_mat @ term * dt / (k + 1)
    _, gamma = cw_stm(N, dt)
    np.testing.assert_allclose(gamma, ref, rtol=1e-12, atol=0.0)
    # The along-track/radial coupling 2 (theta - sin theta) / n^2 -> n dt^3 / 3.
    assert gamma[0, 1] == pytest.approx(N * dt**3 / 3.0, rel=1e-9)


def test_cw_zoh_matches_numerical_integration_with_thrust() -> None:
    rng = np.random.default_rng(7)
    dt, steps = 20.0, 15
    accels = rng.uniform(-2e-3, 2e-3, size=(steps, 3))  # [m/s^2], changes every step
    x0 = np.array([120.0, -300.0, 40.0, 0.05, -0.1, 0.02])
    prop = CWPropagator(N, dt)
    a_mat = cw_matrix(N)

    x_cw = x0.copy()
    x_num = x0.copy()
    for a in accels:
        x_cw = prop.step(x_cw, a)
        sol = solve_ivp(
            lambda _t, x, a=a: a_mat @ x + np.concatenate([np.zeros(3), a]),
            (0.0, dt),
            x_num,
            method="DOP853",
            rtol=1e-12,
            atol=1e-12,
        )
        x_num = sol.y[:, -1]
        assert np.max(np.abs(x_cw[:3] - x_num[:3])) < 1e-9  # [m]
        assert np.max(np.abs(x_cw[3:] - x_num[3:])) < 1e-11  # [m/s]
    coast = np.linalg.matrix_power(prop.phi, steps) @ x0
    assert np.linalg.norm(x_cw[:3] - coast[:3]) > 10.0  # the thrust mattered [m]


def test_cw_batch_equals_single_steps() -> None:
    rng = np.random.default_rng(1)
    states = rng.normal(0.0, 100.0, size=(5, 6))
    accels = rng.normal(0.0, 1e-3, size=(5, 3))
    prop = CWPropagator(N, 5.0)
    batch = prop.step_batch(states, accels)
    singles = np.stack([prop.step(s, a) for s, a in zip(states, accels, strict=True)])
    np.testing.assert_allclose(batch, singles, rtol=0.0, atol=1e-12)
    shared = prop.step(states, accels[0])  # (3,) accel broadcast over the batch
    np.testing.assert_allclose(shared[2], prop.step(states[2], accels[0]), atol=1e-12)


def test_cw_vbar_hold_stays_put() -> None:
    # Any point on the V-bar at rest is an equilibrium of the CW equations.
    prop = CWPropagator(N, PERIOD / 100.0)
    x = np.array([0.0, -250.0, 0.0, 0.0, 0.0, 0.0])
    for _ in range(100):
        x = prop.step(x)
    np.testing.assert_allclose(x, [0.0, -250.0, 0.0, 0.0, 0.0, 0.0], atol=1e-9)


def test_cw_radial_impulse_gives_closed_two_by_one_ellipse() -> None:
    # Radial impulse dv from the origin (textbook CW free motion):
    #   x(t) = dv/n sin(nt),  y(t) = -2 dv/n (1 - cos nt)
    # a closed 2:1 ellipse: y(T/2) = -4 dv/n, back at the origin after one period, no drift.
    dv = 0.1  # [m/s]
    x0 = np.array([0.0, 0.0, 0.0, dv, 0.0, 0.0])
    for frac, x_ref, y_ref in [
        (0.25, dv / N, -2.0 * dv / N),
        (0.5, 0.0, -4.0 * dv / N),
        (1.0, 0.0, 0.0),
    ]:
        phi, _ = cw_stm(N, frac * PERIOD)
        x = phi @ x0
        assert x[0] == pytest.approx(x_ref, abs=1e-9)
        assert x[1] == pytest.approx(y_ref, abs=1e-9)
    phi, _ = cw_stm(N, PERIOD)
    np.testing.assert_allclose(phi @ x0, x0, atol=1e-9)


def test_cw_along_track_impulse_and_radial_offset_drift() -> None:
    # After one period: along-track impulse dv -> y = -6 pi dv / n, x = 0;
    # radial offset x0 at rest -> y = -12 pi x0 (x back to x0).
    phi, _ = cw_stm(N, PERIOD)
    dv, x0 = 0.01, 10.0
    after = phi @ np.array([0.0, 0.0, 0.0, 0.0, dv, 0.0])
    assert after[0] == pytest.approx(0.0, abs=1e-9)
    assert after[1] == pytest.approx(-6.0 * np.pi * dv / N, rel=1e-12)
    after = phi @ np.array([x0, 0.0, 0.0, 0.0, 0.0, 0.0])
    assert after[0] == pytest.approx(x0, abs=1e-9)
    assert after[1] == pytest.approx(-12.0 * np.pi * x0, rel=1e-12)
    # Cross-track: z(t) = z0 cos(nt), a pure harmonic.
    phi, _ = cw_stm(N, PERIOD / 3.0)
    assert (phi @ np.array([0.0, 0.0, 5.0, 0.0, 0.0, 0.0]))[2] == pytest.approx(-2.5, abs=1e-12)


# ----------------------------------------------------------------------------------------------
# nonlinear relative motion
# ----------------------------------------------------------------------------------------------


def _run_both(scale: float) -> tuple[np.ndarray, np.ndarray]:
    x0 = scale * np.array([1.0, -0.5, 0.3, 1e-3, -2e-3, 1e-3])  # [m], [m/s]
    accel = scale * np.array([1e-6, -2e-6, 5e-7])  # [m/s^2]
    cw = CWPropagator(N, 30.0)
    nl = NonlinearRelativePropagator(ALT, j2=False, dt=30.0)
    x_cw, x_nl = x0.copy(), x0.copy()
    for _ in range(20):  # 600 s
        x_cw = cw.step(x_cw, accel)
        x_nl = nl.step(x_nl, accel)
    return x_cw, x_nl


def test_nonlinear_agrees_with_cw_to_first_order() -> None:
    # Scaling the whole initial state and thrust by 2 doubles the linear (CW) answer; the
    # nonlinear residual is second order in the offset, so it quadruples.
    x_cw1, x_nl1 = _run_both(100.0)
    x_cw2, x_nl2 = _run_both(200.0)
    err1 = np.linalg.norm(x_cw1[:3] - x_nl1[:3])
    err2 = np.linalg.norm(x_cw2[:3] - x_nl2[:3])
    assert err1 < 1e-5 * np.linalg.norm(x_cw1[:3])  # ~1.5 mm over ~300 m
    assert err2 / err1 == pytest.approx(4.0, rel=0.02)
    np.testing.assert_allclose(x_cw2, 2.0 * x_cw1, rtol=1e-12)


def test_nonlinear_batch_matches_single() -> None:
    states = np.array([[10.0, -50.0, 3.0, 0.0, 0.01, 0.0], [-20.0, 5.0, 0.0, 0.02, 0.0, -0.01]])
    accel = np.array([1e-4, 0.0, -1e-4])
    batch = NonlinearRelativePropagator(ALT, j2=True, dt=10.0).step(states, accel)
    for i in range(2):
        single = NonlinearRelativePropagator(ALT, j2=True, dt=10.0).step(states[i], accel)
        np.testing.assert_allclose(batch[i], single, atol=1e-8)


def test_nonlinear_target_stays_at_origin_and_orbit_is_kept() -> None:
    prop = NonlinearRelativePropagator(ALT, j2=True, dt=60.0)
    x = np.zeros(6)
    for _ in range(10):
        x = prop.step(x)
    np.testing.assert_allclose(x, 0.0, atol=1e-12)
    assert prop.t == pytest.approx(600.0)
    # Two-body: after one period the target is back where it started.
    prop = NonlinearRelativePropagator(ALT, j2=False, dt=PERIOD / 4.0)
    start = prop.target_state_eci
    for _ in range(4):
        prop.step(np.zeros(6))
    np.testing.assert_allclose(prop.target_state_eci[:3], start[:3], atol=1e-3)
    prop.reset()
    np.testing.assert_array_equal(prop.target_state_eci, start)
    assert prop.t == 0.0


def test_lvlh_eci_round_trip_and_frame() -> None:
    target = circular_orbit_state(ALT, np.deg2rad(51.6), 0.3, 1.1)
    acc = gravity_acceleration(target[:3], j2=J2_EARTH)
    rel = np.array([[30.0, -120.0, 8.0, 0.1, -0.02, 0.03], [0.0, 0.0, 0.0, 0.0, 0.0, 0.0]])
    chaser = eci_from_relative_lvlh(target, rel, acc)
    np.testing.assert_allclose(relative_lvlh_from_eci(target, chaser, acc), rel, atol=1e-9)
    rot, omega = lvlh_frame(target[:3], target[3:])
    np.testing.assert_allclose(rot.T @ rot, np.eye(3), atol=1e-15)
    assert np.linalg.det(rot) == pytest.approx(1.0)
    assert rot[:, 1] @ target[3:] > 0.0  # +y is along the velocity
    assert omega[2] == pytest.approx(N, rel=1e-12)  # circular orbit: LVLH turns at +n about z


def test_lvlh_velocity_is_exact_rotating_frame_derivative_under_j2() -> None:
    # The LVLH relative velocity must equal d/dt of the LVLH relative position, including the
    # out-of-plane LVLH rate r a_z / h that J2 adds (zero at the node, so start at u = 45 deg).
    target0 = circular_orbit_state(ALT, np.deg2rad(51.6), arg_latitude_rad=np.pi / 4)
    rel0 = np.array([200.0, -800.0, 500.0, 0.1, 0.05, -0.2])
    acc0 = gravity_acceleration(target0[:3], j2=J2_EARTH)
    chaser0 = eci_from_relative_lvlh(target0, rel0, acc0)
    y0 = np.concatenate([target0, chaser0 - target0])  # relative part integrated directly

    def rhs(_t: float, y: np.ndarray) -> np.ndarray:
        g_t = gravity_acceleration(y[:3], j2=J2_EARTH)
        g_c = gravity_acceleration(y[:3] + y[6:9], j2=J2_EARTH)
        return np.concatenate([y[3:6], g_t, y[9:], g_c - g_t])

    h = 0.5  # [s]
    positions = []
    for t_end in (-h, h):
        y = solve_ivp(rhs, (0.0, t_end), y0, method="DOP853", rtol=1e-13, atol=1e-12).y[:, -1]
        rot, _ = lvlh_frame(y[:3], y[3:6])
        positions.append(rot.T @ y[6:9])
    rate_fd = (positions[1] - positions[0]) / (2.0 * h)
    np.testing.assert_allclose(rel0[3:], rate_fd, atol=1e-6)  # [m/s]
    # The test is sensitive: dropping the J2 normal-acceleration term misses by > 1e-4 m/s.
    wrong = relative_lvlh_from_eci(target0, chaser0)  # Keplerian LVLH rate
    assert np.max(np.abs(wrong[3:] - rate_fd)) > 1e-4


# ----------------------------------------------------------------------------------------------
# attitude
# ----------------------------------------------------------------------------------------------


def test_torque_free_tumble_conserves_energy_and_momentum() -> None:
    body = RigidBodyAttitude(INERTIA_ASYM)
    direction = np.array([0.6, -0.5, 0.62])
    w = np.deg2rad(5.0) * direction / np.linalg.norm(direction)  # 5 deg/s tumble
    q = np.array([0.9, 0.1, -0.3, 0.2])
    q /= np.linalg.norm(q)
    energy0 = body.kinetic_energy(w)
    h0 = body.angular_momentum_inertial(q, w)
    w_start = w.copy()
    for _ in range(1000):  # 1,000 s in 1-s steps, through the public step()
        q, w = body.step(q, w, 1.0)
        assert q[0] >= 0.0
    assert abs(body.kinetic_energy(w) - energy0) / energy0 < 1e-9
    assert np.linalg.norm(body.angular_momentum_inertial(q, w) - h0) / np.linalg.norm(h0) < 1e-9
    assert np.linalg.norm(q) == pytest.approx(1.0, abs=1e-15)
    assert np.linalg.norm(w - w_start) > 1e-3  # it really tumbled (rates changed)


@pytest.mark.parametrize("which", [0, 2])  # min and max principal axes (both stable)
def test_steady_spin_about_principal_axis_stays_steady(which: int) -> None:
    moments, axes = principal_axes(INERTIA_ASYM)
    np.testing.assert_allclose(axes @ np.diag(moments) @ axes.T, INERTIA_ASYM, atol=1e-12)
    w0 = 0.3 * axes[:, which]  # [rad/s], ~17 deg/s
    body = RigidBodyAttitude(INERTIA_ASYM)
    q, w = body.propagate([1.0, 0.0, 0.0, 0.0], w0, np.linspace(10.0, 200.0, 20))
    np.testing.assert_allclose(w, np.broadcast_to(w0, w.shape), atol=1e-10)
    spin_axis_inertial = rot_wxyz(q).apply(axes[:, which])
    np.testing.assert_allclose(
        spin_axis_inertial, np.broadcast_to(axes[:, which], w.shape), atol=1e-10
    )
    # The attitude turned by 0.3 rad/s * t about that fixed axis.
    expected = Rotation.from_rotvec(0.3 * 200.0 * axes[:, which])
    error = rot_wxyz(q[-1]) * expected.inv()
    assert error.magnitude() < 1e-9


@pytest.mark.parametrize("axis", ["max", "min"])
def test_spin_with_nutation_angle_is_requested_and_constant(axis: str) -> None:
    # Axisymmetric body (symmetry axis = max or min axis): the angle between H and the symmetry
    # axis is a constant of the motion, and the spin rate about the axis is constant too.
    inertia = np.diag([20.0, 20.0, 30.0]) if axis == "max" else np.diag([20.0, 30.0, 30.0])
    sym = np.array([0.0, 0.0, 1.0]) if axis == "max" else np.array([1.0, 0.0, 0.0])
    r = Rotation.from_euler("xyz", [0.3, -0.7, 1.2])  # products of inertia in the body frame
    inertia_body = r.as_matrix() @ inertia @ r.as_matrix().T
    sym_body = r.apply(sym)
    nutation, rate = np.deg2rad(15.0), np.deg2rad(30.0)
    q0, w0 = spin_with_nutation(inertia_body, rate, nutation, axis=axis, phase_rad=0.4)
    body = RigidBodyAttitude(inertia_body)

    h_body0 = inertia_body @ w0
    assert float(angle_between(h_body0, sym_body)) == pytest.approx(nutation, abs=1e-12)
    assert float(w0 @ sym_body) == pytest.approx(rate, rel=1e-12)

    _q, w = body.propagate(q0, w0, np.linspace(5.0, 300.0, 60))
    h_body = w @ inertia_body  # (T, 3), inertia symmetric
    np.testing.assert_allclose(angle_between(h_body, sym_body[None, :]), nutation, atol=1e-9)
    np.testing.assert_allclose(w @ sym_body, rate, rtol=1e-9)
    # The transverse rate really precesses in the body (not a trivial steady spin).
    assert np.ptp(w[:, np.argmax(np.abs(np.cross(sym_body, [1.0, 0.0, 0.0])))]) > 1e-3


def test_spin_with_nutation_asymmetric_and_h_direction() -> None:
    nutation = np.deg2rad(10.0)
    _moments, axes = principal_axes(INERTIA_ASYM)
    target = np.array([0.0, 0.0, 1.0])
    q0, w0 = spin_with_nutation(INERTIA_ASYM, 0.2, nutation, axis="max", h_direction=target)
    h_body = INERTIA_ASYM @ w0
    assert float(angle_between(h_body, axes[:, 2])) == pytest.approx(nutation, abs=1e-12)
    h_inertial = rot_wxyz(q0).apply(h_body)
    np.testing.assert_allclose(h_inertial / np.linalg.norm(h_inertial), target, atol=1e-12)
    assert q0[0] >= 0.0
    # Zero nutation is a pure spin about the principal axis.
    _, w_pure = spin_with_nutation(INERTIA_ASYM, 0.2, 0.0, axis="min")
    np.testing.assert_allclose(w_pure, 0.2 * axes[:, 0], atol=1e-15)


def test_target_attitude_hold_modes() -> None:
    q0 = Rotation.from_euler("zyx", [0.4, -0.2, 0.1]).as_quat()[[3, 0, 1, 2]]
    lvlh = TargetAttitudeModel("lvlh_hold", N)
    lvlh.reset(q0)
    inertial = TargetAttitudeModel("inertial_hold", N)
    inertial.reset([1.0, 0.0, 0.0, 0.0])
    for _ in range(10):
        lvlh.step(PERIOD / 40.0)
        inertial.step(PERIOD / 40.0)
    # LVLH hold: fixed in LVLH, inertial rate n about the orbit normal.
    np.testing.assert_allclose(lvlh.q_lvlh_target, q0 * np.sign(q0[0]), atol=1e-15)
    np.testing.assert_allclose(lvlh.omega_rel_lvlh_body, 0.0, atol=1e-18)
    np.testing.assert_allclose(lvlh.R_lvlh_target @ lvlh.omega_body, [0.0, 0.0, N], atol=1e-18)
    # Inertial hold after a quarter orbit: the body x axis, radial at t0, now points at -V-bar.
    np.testing.assert_allclose(inertial.R_lvlh_target[:, 0], [0.0, -1.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(inertial.omega_rel_lvlh_body, [0.0, 0.0, -N], atol=1e-18)


def test_target_attitude_tumble_reduces_to_hold_modes() -> None:
    inertia = np.diag([10.0, 20.0, 25.0])
    q0 = np.array([1.0, 0.0, 0.0, 0.0])
    # No rate: tumble == inertial hold.
    tumble = TargetAttitudeModel("tumble", N, inertia)
    tumble.reset(q0)
    hold = TargetAttitudeModel("inertial_hold", N)
    hold.reset(q0)
    # Body spinning at n about its max axis, which is the orbit normal: tumble == LVLH hold.
    spin = TargetAttitudeModel("tumble", N, inertia)
    spin.reset(q0, [0.0, 0.0, N])
    for _ in range(5):
        for model in (tumble, hold, spin):
            model.step(300.0)
    np.testing.assert_allclose(tumble.q_lvlh_target, hold.q_lvlh_target, atol=1e-12)
    np.testing.assert_allclose(spin.q_lvlh_target, q0, atol=1e-10)
    np.testing.assert_allclose(spin.omega_rel_lvlh_body, 0.0, atol=1e-15)


# ----------------------------------------------------------------------------------------------
# propellant
# ----------------------------------------------------------------------------------------------


def test_propellant_and_saturation() -> None:
    thrust = np.array([3.0, -4.0, 0.0])  # |T| = 5 N
    assert propellant_used(thrust, 10.0, 300.0) == pytest.approx(50.0 / (300.0 * G0), rel=1e-15)
    assert propellant_used(thrust, 10.0, 300.0, norm="l1") == pytest.approx(70.0 / (300.0 * G0))
    assert mass_flow_rate(thrust, 220.0) == pytest.approx(5.0 / (220.0 * G0))
    np.testing.assert_allclose(
        mass_flow_rate(np.stack([thrust, 2.0 * thrust]), 300.0),
        [5.0 / (300.0 * G0), 10.0 / (300.0 * G0)],
    )
    np.testing.assert_array_equal(saturate_thrust(thrust, 3.5), [3.0, -3.5, 0.0])
    np.testing.assert_array_equal(saturate_thrust(thrust, [1.0, 10.0, 1.0]), [1.0, -4.0, 0.0])


def test_chaser_mass_burns_and_runs_dry() -> None:
    chaser = ChaserMass(dry_mass_kg=100.0, propellant_kg=0.01, isp=200.0, max_thrust_N=2.0)
    accel, applied = chaser.apply([5.0, 0.0, 0.0], 1.0)  # saturates to 2 N
    np.testing.assert_allclose(applied, [2.0, 0.0, 0.0])
    np.testing.assert_allclose(accel, [2.0 / 100.01, 0.0, 0.0])
    assert chaser.propellant_kg == pytest.approx(0.01 - 2.0 / (200.0 * G0))
    left = chaser.propellant_kg
    _, applied = chaser.apply([2.0, 0.0, 0.0], 100.0)  # would need ~0.1 kg: scaled to what is left
    assert applied[0] == pytest.approx(left * 200.0 * G0 / 100.0)
    assert chaser.propellant_kg == 0.0
    accel, _ = chaser.apply([2.0, 0.0, 0.0], 1.0)
    np.testing.assert_array_equal(accel, 0.0)


# ----------------------------------------------------------------------------------------------
# validation
# ----------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("call", "field"),
    [
        (lambda: mean_motion(-1.0), "altitude_m"),
        (lambda: cw_stm(N, -1.0), "dt"),
        (lambda: cw_stm(0.0, 1.0), "n"),
        (lambda: CWPropagator(N, float("nan")), "dt"),
        (lambda: CWPropagator(N, 1.0).step([0.0, np.inf, 0.0, 0.0, 0.0, 0.0]), "state"),
        (lambda: CWPropagator(N, 1.0).step(np.zeros(5)), "state"),
        (lambda: CWPropagator(N, 1.0).step(np.zeros(6), [0.0, np.nan, 0.0]), "accel"),
        (lambda: NonlinearRelativePropagator(ALT, dt=0.0), "dt"),
        (lambda: NonlinearRelativePropagator(ALT).step(np.full(6, np.nan)), "state"),
        (lambda: RigidBodyAttitude(np.diag([1.0, -2.0, 3.0])), "inertia"),
        (lambda: RigidBodyAttitude(np.diag([1.0, 1.0, 3.0])), "triangle inequality"),
        (lambda: RigidBodyAttitude(np.array([[1, 0.5, 0], [0, 1, 0], [0, 0, 1.0]])), "symmetric"),
        (lambda: RigidBodyAttitude(np.eye(2)), "inertia"),
        (lambda: RigidBodyAttitude(np.eye(3)).step([1.0, 0, 0, 0], [0, 0, 0.1], -1.0), "dt"),
        (lambda: RigidBodyAttitude(np.eye(3)).step([2.0, 0, 0, 0], [0, 0, 0.1], 1.0), "q_wxyz"),
        (lambda: RigidBodyAttitude(np.eye(3)).step([1.0, 0, 0, 0], [0, np.nan, 0], 1.0), "omega"),
        (lambda: spin_with_nutation(np.eye(3), 0.1, np.pi / 2), "nutation_rad"),
        (lambda: spin_with_nutation(np.eye(3), 0.1, 0.1, axis="mid"), "axis"),  # type: ignore[arg-type]
        (lambda: TargetAttitudeModel("spin", N), "mode"),  # type: ignore[arg-type]
        (lambda: TargetAttitudeModel("tumble", N), "inertia"),
        (lambda: TargetAttitudeModel("lvlh_hold", N).reset([1.0, 0, 0, 0], [0, 0, 1.0]), "omega"),
        (lambda: propellant_used([1.0, 0.0, 0.0], 1.0, 0.0), "isp"),
        (lambda: propellant_used([1.0, 0.0, 0.0], -1.0, 300.0), "dt"),
        (lambda: saturate_thrust([1.0, 0.0, 0.0], -1.0), "max_thrust_N"),
        (lambda: ChaserMass(0.0, 1.0, 300.0, 1.0), "dry_mass_kg"),
    ],
)
def test_bad_inputs_raise_value_error_naming_the_field(call, field: str) -> None:  # type: ignore[no-untyped-def]
    with pytest.raises(ValueError, match=field):
        call()


def test_docstring_examples_run() -> None:
    result = doctest.testmod(dynamics, extraglobs={"np": np})
    assert result.attempted >= 4
    assert result.failed == 0
