"""The per-step fast paths agree with the reference (SciPy / generic numpy) math to round-off.

The truth step avoids SciPy ``Rotation`` objects and numpy's generic small-array helpers; these
tests hold the fast code to the straightforward formulation it replaced: the geometry helpers
against SciPy on random inputs, the attitude integrators against their numpy form, and the world's
frames, contact geometry and sensor truth against the formulas written with ``np.cross``,
``invert`` and ``Rotation``.
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import tridar_env
from perception.config import load_config
from perception.geometry import (
    fast_cross,
    fast_invert,
    fast_matrix_to_quat,
    fast_matrix_to_rotvec,
    fast_quat_to_matrix,
    invert,
    make_T,
    matrix_to_quat,
    quat_to_matrix,
    rotation_z,
)
from perception.targets import load_target
from tridar_env.dynamics import (
    ChaserMass,
    RigidBodyAttitude,
    TargetAttitudeModel,
    mean_motion,
    propellant_used,
    saturate_thrust,
)
from tridar_env.env import observation_slices
from tridar_env.world import R_PORT_DOCK, World, rk4_attitude

TOL = 1e-12
N = mean_motion(400e3)


# ------------------------------------------------------------------ geometry helpers
def test_fast_cross_matches_numpy() -> None:
    rng = np.random.default_rng(0)
    a, b = rng.standard_normal((2, 500, 3)) * rng.uniform(1e-3, 1e3, (2, 500, 1))
    ref = np.cross(a, b)
    out = np.array([fast_cross(x, y) for x, y in zip(a, b)])
    np.testing.assert_allclose(out, ref, rtol=0, atol=TOL * np.abs(ref).max())


def test_fast_quaternion_conversions_match_scipy() -> None:
    rng = np.random.default_rng(1)
    q = rng.standard_normal((2000, 4)) * rng.uniform(0.1, 10.0, (2000, 1))  # not unit: normalised
    np.testing.assert_allclose(
        np.array([fast_quat_to_matrix(x) for x in q]), quat_to_matrix(q), rtol=0, atol=TOL
    )
    R = Rotation.random(2000, random_state=2).as_matrix()
    np.testing.assert_allclose(
        np.array([fast_matrix_to_quat(r) for r in R]), matrix_to_quat(R), rtol=0, atol=TOL
    )


@pytest.mark.parametrize(
    "rotvec",
    [[0, 0, 0], [np.pi, 0, 0], [0, np.pi, 0], [0, 0, np.pi], [1e-9, 0, 0],
     [np.pi - 1e-9, 0, 0], [2.0, -1.0, 0.5], [0, -np.pi / 2, 0], [1.2, 1.2, 1.2]],
)
def test_fast_matrix_to_quat_every_branch(rotvec: list[float]) -> None:
    """Every Shepperd branch (each diagonal entry and the trace largest) and 180 deg turns."""
    R = Rotation.from_rotvec(rotvec).as_matrix()
    q = fast_matrix_to_quat(R)
    assert q[0] >= 0.0
    np.testing.assert_allclose(q, matrix_to_quat(R), rtol=0, atol=TOL)
    np.testing.assert_allclose(fast_quat_to_matrix(q), R, rtol=0, atol=TOL)


@pytest.mark.parametrize("scale", [1e-12, 1e-6, 1e-3, 0.3, 3.0, np.pi - 1e-9])
def test_fast_matrix_to_rotvec_matches_scipy(scale: float) -> None:
    """Small angles (the filter's innovations, series branch), large ones, and near 180 deg."""
    rng = np.random.default_rng(7)
    axes = rng.standard_normal((300, 3))
    v = axes / np.linalg.norm(axes, axis=1, keepdims=True) * scale * rng.uniform(0.5, 1.0, (300, 1))
    R = Rotation.from_rotvec(v).as_matrix()
    out = np.array([fast_matrix_to_rotvec(r) for r in R])
    np.testing.assert_allclose(out, Rotation.from_matrix(R).as_rotvec(), rtol=0, atol=TOL)
    if scale < 3.0:
        np.testing.assert_allclose(out, v, rtol=1e-9, atol=TOL)


def test_fast_quat_to_matrix_rejects_zero() -> None:
    with pytest.raises(ValueError, match="norm"):
        fast_quat_to_matrix(np.zeros(4))


def test_fast_invert_and_rotation_z_match_reference() -> None:
    rng = np.random.default_rng(3)
    for rot, t in zip(Rotation.random(200, random_state=4), rng.standard_normal((200, 3)) * 50):
        T = make_T(rot, t)
        np.testing.assert_allclose(fast_invert(T), invert(T), rtol=0, atol=TOL * 50)
    for angle in rng.uniform(-10.0, 10.0, 200):
        np.testing.assert_allclose(
            rotation_z(angle), Rotation.from_rotvec([0.0, 0.0, angle]).as_matrix(), rtol=0, atol=TOL
        )


# ------------------------------------------------------------------ attitude and mass
def _rk4_numpy(q, w, inertia, torque, dt, substeps=4):  # type: ignore[no-untyped-def]
    """The reference formulation: numpy arrays and np.cross."""
    inv = np.linalg.inv(inertia)

    def f(y):  # type: ignore[no-untyped-def]
        qw, qx, qy, qz, p, r1, r2 = y
        om = y[4:7]
        dw = inv @ (torque - np.cross(om, inertia @ om))
        return np.array([
            -0.5 * (qx * p + qy * r1 + qz * r2), 0.5 * (qw * p + qy * r2 - qz * r1),
            0.5 * (qw * r1 + qz * p - qx * r2), 0.5 * (qw * r2 + qx * r1 - qy * p), *dw,
        ])

    y = np.concatenate([q, w])
    h = dt / substeps
    for _ in range(substeps):
        k1 = f(y)
        k2 = f(y + 0.5 * h * k1)
        k3 = f(y + 0.5 * h * k2)
        k4 = f(y + h * k3)
        y = y + h / 6.0 * (k1 + 2 * k2 + 2 * k3 + k4)
        y[:4] /= np.linalg.norm(y[:4])
    if y[0] < 0:
        y[:4] = -y[:4]
    return y[:4], y[4:]


def test_rk4_attitude_matches_numpy_reference() -> None:
    rng = np.random.default_rng(5)
    inertia = np.array([[12.0, 1.0, -0.5], [1.0, 20.0, 2.0], [-0.5, 2.0, 28.0]])
    for _ in range(50):
        q = Rotation.random(random_state=rng).as_quat()[[3, 0, 1, 2]]
        q = -q if q[0] < 0 else q
        w, tq = rng.standard_normal(3) * 0.2, rng.standard_normal(3)
        q_ref, w_ref = q, w
        q_out, w_out = q, w
        for _ in range(20):
            q_ref, w_ref = _rk4_numpy(q_ref, w_ref, inertia, tq, 0.2)
            q_out, w_out = rk4_attitude(q_out, w_out, inertia, tq, 0.2)
        np.testing.assert_allclose(q_out, q_ref, rtol=0, atol=TOL)
        np.testing.assert_allclose(w_out, w_ref, rtol=0, atol=TOL)
        assert q_out[0] >= 0.0


def test_rigid_body_rhs_matches_numpy_reference() -> None:
    rng = np.random.default_rng(6)
    inertia = np.array([[12.0, 1.0, -0.5], [1.0, 20.0, 2.0], [-0.5, 2.0, 28.0]])
    body = RigidBodyAttitude(inertia)
    body._torque = np.array([0.3, -0.1, 0.2])
    for _ in range(100):
        y = rng.standard_normal(7)
        om = y[4:]
        dw = np.linalg.inv(inertia) @ (body._torque - np.cross(om, inertia @ om))
        np.testing.assert_allclose(body._rhs(0.0, y)[4:], dw, rtol=0, atol=TOL)


@pytest.mark.parametrize("mode", ["lvlh_hold", "inertial_hold", "tumble"])
def test_target_attitude_matrix_matches_rotation(mode: str) -> None:
    inertia = np.diag([10.0, 14.0, 20.0]) if mode == "tumble" else None
    model = TargetAttitudeModel(mode, N, inertia)  # type: ignore[arg-type]
    q0 = Rotation.from_euler("xyz", [10.0, -30.0, 75.0], degrees=True).as_quat()[[3, 0, 1, 2]]
    model.reset(q0, [0.02, -0.05, 0.04] if mode == "tumble" else None)
    for _ in range(40):
        model.step(7.0)
        np.testing.assert_allclose(
            model.R_lvlh_target, model.rotation_lvlh_target.as_matrix(), rtol=0, atol=TOL
        )


def test_chaser_mass_apply_matches_saturate_and_propellant_used() -> None:
    rng = np.random.default_rng(7)
    for norm in ("l2", "l1"):
        mass = ChaserMass(100.0, 5.0, 220.0, [4.0, 5.0, 6.0], norm)  # type: ignore[arg-type]
        for _ in range(50):
            cmd = rng.standard_normal(3) * 8.0
            prop, m = mass.propellant_kg, mass.mass_kg
            thrust = saturate_thrust(cmd, [4.0, 5.0, 6.0])
            need = float(propellant_used(thrust, 0.2, 220.0, norm))  # type: ignore[arg-type]
            accel, applied = mass.apply(cmd, 0.2)
            np.testing.assert_allclose(applied, thrust, rtol=1e-15)
            np.testing.assert_allclose(accel, thrust / m, rtol=1e-15)
            assert mass.propellant_kg == pytest.approx(prop - need, rel=1e-14)


# ------------------------------------------------------------------ world
def _reference_frames(w: World) -> dict[str, np.ndarray]:
    """The world's frames and truth outputs written with Rotation, make_T, invert, np.cross."""
    ta = w.target_attitude
    R_lt = ta.rotation_lvlh_target.as_matrix()
    T_lt = make_T(R_lt)
    if ta.mode == "lvlh_hold":
        w_t = np.zeros(3)
    else:
        w_t = R_lt @ (ta.omega_body - R_lt.T @ np.array([0.0, 0.0, w.n]))
    if w.controlled_attitude:
        q = w._q_i_chaser
        R_lc = (Rotation.from_rotvec([0.0, 0.0, -w.n * w.t])
                * Rotation.from_quat([q[1], q[2], q[3], q[0]])).as_matrix()
        w_c = R_lc @ w._w_chaser - np.array([0.0, 0.0, w.n])
    else:
        R_lc = R_lt @ w.target.T_target_port[:3, :3] @ R_PORT_DOCK
        w_c = w_t
    T_lc = make_T(R_lc, w.state[:3])
    T_ls, T_ld = T_lc @ w.T_chaser_sensor, T_lc @ w.T_chaser_dock
    T_lp = T_lt @ w.target.T_target_port
    # sensor truth
    R_ls = T_ls[:3, :3]
    T_st = invert(T_ls) @ T_lt
    v_s = w.state[3:] + np.cross(w_c, R_lc @ w.T_chaser_sensor[:3, 3])
    vel = R_ls.T @ (-v_s) - np.cross(R_ls.T @ w_c, T_st[:3, 3])
    omega = R_ls.T @ (w_t - w_c)
    # contact
    R_lp = T_lp[:3, :3]
    d = R_lp.T @ (T_ld[:3, 3] - T_lp[:3, 3])
    v_dock = w.state[3:] + np.cross(w_c, T_ld[:3, 3] - w.state[:3])
    rv = R_lp.T @ (v_dock - np.cross(w_t, T_lp[:3, 3]))
    cosang = float(np.clip(-(T_ld[:3, 2] @ R_lp[:, 2]), -1.0, 1.0))
    contact = np.array([
        d[2], np.hypot(d[0], d[1]), -rv[2], np.hypot(rv[0], rv[1]),
        np.degrees(np.arccos(cosang)), np.degrees(np.linalg.norm(w_c - w_t)),
    ])
    return {
        "R_lvlh_target": R_lt, "T_lvlh_target": T_lt, "omega_target_lvlh": w_t,
        "R_lvlh_chaser": R_lc, "omega_chaser_lvlh": w_c, "T_lvlh_chaser": T_lc,
        "T_lvlh_sensor": T_ls, "T_lvlh_dock": T_ld, "T_lvlh_port": T_lp,
        "chaser_angular_velocity_body": R_lc.T @ (w_c + np.array([0.0, 0.0, w.n]))
        if not w.controlled_attitude else w._w_chaser,
        "T_sensor_target": T_st, "velocity": vel, "angular_velocity": omega, "contact": contact,
    }


@pytest.mark.parametrize("mission", ["final_approach", "tumbling_target", "rendezvous"])
def test_world_frames_and_truth_match_reference(mission: str) -> None:
    cfg = load_config(mission)
    w = World(cfg, load_target(cfg.target.name))
    rng = np.random.default_rng(8)
    w.reset(rng)
    for k in range(60):
        tq = rng.standard_normal(3) * 0.2 if w.controlled_attitude else None
        w.step(rng.standard_normal(3) * 2.0, tq)
        if k % 6:
            continue
        ref = _reference_frames(w)
        st, c = w.sensor_truth(), w.contact()
        got = {name: getattr(w, name) for name in ref if hasattr(w, name)}
        got.update(T_sensor_target=st.T_sensor_target, velocity=st.velocity,
                   angular_velocity=st.angular_velocity)
        got["contact"] = np.array([c.axial_distance, c.lateral_offset, c.closing_speed,
                                   c.lateral_speed, c.misalignment_deg, c.angular_rate_deg_s])
        for name, value in ref.items():
            scale = max(1.0, float(np.abs(value).max()))
            # arccos near 0 turns round-off e into sqrt(e): the angle gets a looser bound.
            atol = 1e-6 if name == "contact" else TOL * scale
            np.testing.assert_allclose(got[name], value, rtol=0, atol=atol, err_msg=name)


def test_world_episode_constant_frames_are_shared_read_only() -> None:
    cfg = load_config("final_approach")
    w = World(cfg, load_target(cfg.target.name))
    w.reset(np.random.default_rng(0))
    T_lp = w.T_lvlh_port
    w.step(np.ones(3))
    assert w.T_lvlh_port is T_lp  # the LVLH-holding target's port is built once per reset
    with pytest.raises(ValueError, match="read-only"):
        T_lp[0, 3] = 1.0
    w.reset(np.random.default_rng(1))
    assert w.T_lvlh_port is not T_lp


# ------------------------------------------------------------------ env
def _reference_observation(env, sv) -> np.ndarray:  # type: ignore[no-untyped-def]
    """The observation written with StateVector.T_sensor_target (SciPy), matrix_to_quat, np.cross."""
    v = sv.valid
    s = observation_slices()
    obs = np.zeros(sum(sl.stop - sl.start for sl in s.values()))
    obs[int(sv.mode)] = 1.0
    obs[s["valid"]] = v.as_array()
    T_ds, T_tp = env._T_dock_sensor, env.target.T_target_port
    if v.position and v.attitude:
        T_dp = T_ds @ sv.T_sensor_target @ T_tp
        obs[s["port_position_dock"]] = T_dp[:3, 3]
        obs[s["q_dock_port"]] = matrix_to_quat(T_dp[:3, :3])
        if v.velocity and v.angular_velocity:
            r_port_s = sv.T_sensor_target[:3, :3] @ T_tp[:3, 3]
            obs[s["port_velocity_dock"]] = T_ds[:3, :3] @ (sv.velocity + np.cross(sv.angular_velocity, r_port_s))
        if v.angular_velocity:
            obs[s["omega_port_dock"]] = T_ds[:3, :3] @ sv.angular_velocity
    obs[s["range"]] = sv.range if v.range else 0.0
    obs[s["range_rate"]] = sv.range_rate if v.range_rate else 0.0
    obs[s["bearing"]] = sv.bearing if v.bearing else 0.0
    obs[s["fitness"]] = sv.fitness
    obs[s["fuel_fraction"]] = env.world.mass.propellant_kg / env.cfg.dynamics.chaser.propellant_kg
    obs[s["time_fraction"]] = env._steps / env.cfg.env.max_episode_steps
    obs[s["chaser_rate_body"]] = env.world.chaser_angular_velocity_body
    obs[s["protection_level"]] = sv.protection_level
    obs[s["alert_limit"]] = sv.alert_limit
    return np.clip(obs, env.observation_space.low, env.observation_space.high).astype(np.float32)


@pytest.mark.parametrize("env_id", list(tridar_env.ENV_IDS))
def test_observation_and_info_match_reference(env_id: str) -> None:
    env = gym.make(env_id, perception="truth+noise")
    obs, info = env.reset(seed=5)
    env.action_space.seed(5)
    u = env.unwrapped
    for _ in range(30):
        sv = u.state_vector
        np.testing.assert_allclose(obs, _reference_observation(u, sv), rtol=0, atol=2e-6)
        T_true = info["truth_T_sensor_target"]
        pos_err = np.linalg.norm(sv.position - T_true[:3, 3])
        dR = T_true[:3, :3].T @ sv.T_sensor_target[:3, :3]
        att_err = np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1, 1)))
        assert info["estimate_position_error_m"] == pytest.approx(pos_err, rel=1e-12, abs=1e-15)
        assert info["estimate_attitude_error_deg"] == pytest.approx(att_err, rel=1e-9, abs=1e-6)
        np.testing.assert_allclose(sv.quaternion, matrix_to_quat(quat_to_matrix(sv.quaternion)), atol=TOL)
        obs, _, term, trunc, info = env.step(env.action_space.sample())
        if term or trunc:
            break


@pytest.mark.parametrize("env_id", list(tridar_env.ENV_IDS))
def test_same_seed_bitwise_identical_truth_rollouts_every_id(env_id: str) -> None:
    def rollout(seed: int) -> list[tuple]:
        env = gym.make(env_id, perception="truth")
        obs, info = env.reset(seed=seed)
        env.action_space.seed(seed)
        out = [(obs, 0.0, info["truth_r_lvlh"], info["truth_T_sensor_target"].copy())]
        for _ in range(80):
            obs, r, term, trunc, info = env.step(env.action_space.sample())
            out.append((obs, r, info["truth_r_lvlh"], info["truth_T_sensor_target"].copy()))
            if term or trunc:
                break
        return out

    a, b = rollout(21), rollout(21)
    assert len(a) == len(b)
    for (oa, ra, pa, Ta), (ob, rb, pb, Tb) in zip(a, b):
        np.testing.assert_array_equal(oa, ob)
        assert ra == rb
        np.testing.assert_array_equal(pa, pb)
        np.testing.assert_array_equal(Ta, Tb)


def test_fast_rotvec_to_matrix_matches_scipy() -> None:
    from perception.geometry import fast_rotvec_to_matrix

    rng = np.random.default_rng(7)
    for scale in (1e-9, 1e-5, 1e-3, 0.3, 3.0):
        for v in rng.standard_normal((50, 3)) * scale:
            np.testing.assert_allclose(fast_rotvec_to_matrix(v), Rotation.from_rotvec(v).as_matrix(),
                                       atol=2e-15, rtol=0)
    np.testing.assert_array_equal(fast_rotvec_to_matrix(np.zeros(3)), np.eye(3))
