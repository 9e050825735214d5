"""FarRendezvous-v0 and FlyAround-v0: the decision schedule, the pointing attitude law, the Sun and
eclipse, the fly-around task's bookkeeping, and the scripted controllers on truth."""

from __future__ import annotations

import math

import gymnasium as gym
import numpy as np
import pytest

import tridar_env  # noqa: F401  (registers the ids)
from agents.controllers import make_controller
from perception.config import EnvConfig, load_config
from tridar_env.dynamics import mean_motion
from tridar_env.env import DockingEnv, observation_slices
from tridar_env.schedule import decision_frames
from tridar_env.world import World


def test_decision_frames_lengthen_with_range_up_to_the_cap() -> None:
    env = EnvConfig(decision_schedule={"start_m": 300.0, "step_m": 50.0, "max_frames": 60}, frame_skip=2)
    r = np.linspace(0.0, 10_000.0, 2001)
    f = np.array([decision_frames(env, float(x)) for x in r])
    assert f[0] == 2 and f[-1] == 60
    assert np.all(np.diff(f) >= 0)  # monotonic
    assert decision_frames(env, 300.0 + 50.0 * 7 + 1e-6) == 2 + 7
    assert decision_frames(env, None) == 2 and decision_frames(env, float("nan")) == 2
    assert decision_frames(EnvConfig(frame_skip=3), 9e3) == 3  # no schedule: frame_skip


def _world(**overrides) -> World:
    cfg = load_config("fly_around", **overrides)
    return World(cfg, DockingEnv(cfg).target)


def test_pointing_law_aims_at_the_centre_and_its_rate_is_the_attitude_derivative() -> None:
    """Body +z on the target's centre of mass at every step, +x along h x z; the published
    angular velocity equals the finite-difference rate of the attitude (out-of-plane motion too)."""
    w = _world(env__perception="truth")
    w.reset(np.random.default_rng(4))
    w.state = np.array([30.0, 80.0, 12.0, -0.3, 0.2, 0.05])
    w._invalidate()
    thrust = np.array([3.0, -2.0, 1.0])
    for _ in range(40):
        R0, om = w.R_lvlh_chaser.copy(), w.omega_chaser_lvlh.copy()
        r = w.state[:3]
        np.testing.assert_allclose(R0[:, 2], -r / np.linalg.norm(r), atol=1e-12)
        h_x_z = np.cross([0.0, 0.0, 1.0], R0[:, 2])
        np.testing.assert_allclose(R0[:, 0], h_x_z / np.linalg.norm(h_x_z), atol=1e-12)
        np.testing.assert_allclose(R0.T @ R0, np.eye(3), atol=1e-12)
        w.step(thrust)
        R1, om1 = w.R_lvlh_chaser, w.omega_chaser_lvlh
        # R1 = exp([w] dt) R0 to second order: the midpoint rate
        dR = R1 @ R0.T
        rotvec = np.array([dR[2, 1] - dR[1, 2], dR[0, 2] - dR[2, 0], dR[1, 0] - dR[0, 1]]) / 2.0
        np.testing.assert_allclose(rotvec / w.dt, 0.5 * (om + om1), atol=2e-6)


def test_sun_goes_round_once_per_orbit_and_eclipse_is_behind_the_earth() -> None:
    w = _world(env__perception="truth", dynamics__orbit__sun_phase_deg=0.0)
    w.reset(np.random.default_rng(0))
    n = mean_motion(w.cfg.dynamics.orbit.altitude_m)
    s0 = w.sun_direction_lvlh()
    assert s0 is not None
    np.testing.assert_allclose(s0, [1.0, 0.0, 0.0], atol=1e-12)  # local noon
    w.t = 0.5 * math.pi / n  # a quarter orbit later the Sun is along -V-bar
    np.testing.assert_allclose(w.sun_direction_lvlh(), [0.0, -1.0, 0.0], atol=1e-9)
    w.t = math.pi / n  # midnight: in the Earth's shadow
    assert w.sun_direction_lvlh() is None
    # A 400 km orbit spends ~38 % of its period in the cylindrical shadow.
    ts = np.linspace(0.0, 2.0 * math.pi / n, 3601)
    dark = 0
    for t in ts:
        w.t = float(t)
        dark += w.sun_direction_lvlh() is None
    assert 0.35 < dark / len(ts) < 0.41
    # High beta: never in eclipse.
    w2 = _world(env__perception="truth", dynamics__orbit__sun_beta_deg=75.0, dynamics__orbit__sun_phase_deg=180.0)
    w2.reset(np.random.default_rng(0))
    assert w2.sun_direction_lvlh() is not None
    # The scene hands the sensor the Sun in the target frame (None in eclipse).
    w.t = 0.0
    w._invalidate()
    sc = w.scene()
    np.testing.assert_allclose(sc.sun_direction_target, w.R_lvlh_target.T @ w.sun_direction_lvlh(), atol=1e-12)


def test_fly_around_on_truth_completes_and_its_rewards_add_up() -> None:
    """The scripted fly-around completes one turn inside the band; the sweep reward totals
    ``sweep * swept`` (potential-based), the terms sum to each reward, the truth never enters
    the keep-out sphere and the swept angle matches the phase's unwrapped change."""
    env = gym.make("TriDAR/FlyAround-v0", perception="truth")
    u = env.unwrapped
    ctrl = make_controller("fly_around", u.cfg)
    obs, info = env.reset(seed=2)
    ctrl.reset()
    total_sweep = 0.0
    phases = [math.atan2(info["truth_r_lvlh"][1], info["truth_r_lvlh"][0])]
    min_r_after_depart = math.inf
    while True:
        obs, reward, term, trunc, info = env.step(ctrl(obs))
        terms = {k: v for k, v in info.items() if k.startswith("reward_")}
        assert reward == pytest.approx(sum(terms.values()), abs=1e-12)
        total_sweep += terms["reward_sweep"]
        r = info["truth_r_lvlh"]
        phases.append(math.atan2(r[1], r[0]))
        if ctrl.phase == "circle":
            min_r_after_depart = min(min_r_after_depart, float(np.linalg.norm(r)))
        if term or trunc:
            break
    fa = u.cfg.env.fly_around
    assert info["termination"] == "completed"
    assert info["swept_deg"] >= fa.sweep_deg
    assert abs(info["standoff_error_m"]) <= fa.band_m
    assert total_sweep == pytest.approx(u.cfg.env.fly_around_reward.sweep * math.radians(info["swept_deg"]), rel=1e-9)
    assert math.degrees(np.unwrap(phases)[-1] - phases[0]) == pytest.approx(info["swept_deg"], abs=1e-6)
    assert min_r_after_depart > fa.keep_out_radius_m + 30.0
    assert info["delta_v"] < 10.0


def test_fly_around_flies_on_a_degraded_pose_bounded_inside_its_band_and_holds_without_one() -> None:
    """"Degraded" is the docking's verdict; circling at 100 m in a 15 m band the controller still
    flies on a pose bounded within a third of the band (its estimate is the pose's), and without
    one it dead-reckons and, after ``hold_s``, stops its reference round the circle."""
    env = gym.make("TriDAR/FlyAround-v0", perception="truth")
    ctrl = make_controller("fly_around", env.unwrapped.cfg)
    obs, _ = env.reset(seed=4)
    ctrl.reset()
    while ctrl.phase != "circle":
        obs, *_ = env.step(ctrl(obs))
    S = observation_slices()
    limit = ctrl.g.usable_pl_fraction * ctrl.fa.band_m
    assert limit == pytest.approx(5.0)
    for pl, usable in [(0.9 * limit, True), (1.1 * limit, False)]:
        c = make_controller("fly_around", env.unwrapped.cfg)
        c.reset()
        c(obs)  # a healthy fix first
        bad = obs.copy()
        bad[S["valid"]][7] = 1.0
        bad[S["valid"]][:3] = 0.0  # no range either (range-aided flight: the next test)
        bad[S["protection_level"]] = pl
        bad[S["port_position_dock"].start] += np.float32(1.0)  # shifted: taken only if usable
        theta = []
        # (the frozen observation lags the reference by 0.6 m/s: under max_lag_m for 15 s)
        for _ in range(round((c.g.hold_s + 2.0) / c.dt)):
            c(bad)
            theta.append(c.theta_ref)
        assert c.law == ("pose" if usable else "dead_reckoning"), pl
        r_pose = c._from_pose(bad)[0]
        assert (np.linalg.norm(c.r - r_pose) < 1e-6) == usable
        moving = theta[-1] != theta[-2]
        assert moving == usable  # without a usable pose for hold_s the reference stops


def _fly_unusable(range_valid: bool, seconds: float) -> tuple[list[float], float, float, str, float]:
    """FlyAround on truth, circling: the controller's estimate is knocked 8 m out in radius, then
    for ``seconds`` every pose is degraded beyond a usable bound (the bearing, range and range
    rate kept or cleared). Returns the truth standoff errors [m], the controller's radius error
    at the end [m], the reference's advance [deg], the law, and the swept angle gained [deg]."""
    env = gym.make("TriDAR/FlyAround-v0", perception="truth")
    ctrl = make_controller("fly_around", env.unwrapped.cfg)
    obs, info = env.reset(seed=4)
    ctrl.reset()
    while ctrl.phase != "circle" or info["swept_deg"] < 20.0:
        obs, _, term, trunc, info = env.step(ctrl(obs))
        assert not (term or trunc)
    S = observation_slices()
    ctrl.r = ctrl.r * (1.0 + 8.0 / float(np.linalg.norm(ctrl.r)))
    theta0, swept0, band = ctrl.theta_ref, info["swept_deg"], []
    for _ in range(round(seconds / ctrl.dt)):
        bad = obs.copy()
        bad[S["valid"]][7] = 1.0
        bad[S["protection_level"]] = 2.0 * ctrl.fa.band_m
        if not range_valid:
            bad[S["valid"]][:3] = 0.0
        obs, _, term, trunc, info = env.step(ctrl(bad))
        band.append(info["standoff_error_m"])
        assert not term
    r_err = float(np.linalg.norm(ctrl.r) - np.linalg.norm(info["truth_r_lvlh"]))
    return band, r_err, math.degrees(abs(ctrl.theta_ref - theta0)), ctrl.law, info["swept_deg"] - swept0


def test_fly_around_without_a_usable_pose_flies_on_on_range_and_holds_without_it() -> None:
    """Seed 91's stall: where the truss slides the pose stayed unusable for 800 s. With the range
    and range rate the controller keeps its radius measured (an 8 m radial error in its estimate
    is taken out), its reference keeps moving, and the chaser sweeps on inside the band; with
    neither pose nor range it stops its reference after ``hold_s`` and its radius error stays."""
    band, r_err, advance, law, swept = _fly_unusable(True, 200.0)
    assert law == "range_aided"
    assert abs(r_err) < 1.0
    fa = load_config("fly_around", env__perception="truth").env.fly_around
    assert max(abs(b) for b in band) < 0.5 * fa.band_m
    full = math.degrees(0.6 * 200.0 / fa.standoff_m)  # v_circle 0.6 m/s for 200 s
    assert advance > 0.8 * full and swept > 0.5 * full
    _, r_err_blind, advance_blind, law_blind, _ = _fly_unusable(False, 200.0)
    assert law_blind == "dead_reckoning"
    assert r_err_blind > 4.0
    assert advance_blind < math.degrees(0.6 * 12.0 / fa.standoff_m)  # hold_s (10 s) and a step


def test_fly_around_reference_waiting_for_a_chaser_off_it_is_closed_on() -> None:
    """A chaser 30 m ahead of its reference on the circle (over ``max_lag_m``: the reference had
    stopped while the chaser coasted on dead reckoning): the reference waits as a point at rest,
    the law (on its double integrator: the CW terms are cancelled) closes on it, and the
    reference moves on. (Kept circling, the waiting reference pulled the chaser to the PD's
    balance kd v / kp ~ 54 m ahead of it, and neither moved again: a run stalled 4,000 s.)"""
    from tridar_env.dynamics import cw_acceleration

    cfg = load_config("fly_around", env__perception="truth")
    ctrl = make_controller("fly_around", cfg)
    ctrl.reset()
    R, g = ctrl.fa.standoff_m, ctrl.g
    ctrl.phase, ctrl.has_estimate, ctrl.theta_ref = "circle", True, 0.0
    ahead = ctrl.fa.direction * 30.0 / R
    ctrl.r = R * np.array([math.cos(ahead), math.sin(ahead), 0.0])
    ctrl.v = np.zeros(3)
    moved_at = None
    for k in range(round(600.0 / ctrl.dt)):
        theta0 = ctrl.theta_ref
        a = ctrl.accel_lvlh() + cw_acceleration(ctrl.n, ctrl.r, ctrl.v)
        ctrl.v = ctrl.v + a * ctrl.dt
        ctrl.r = ctrl.r + ctrl.v * ctrl.dt
        if ctrl.theta_ref != theta0 and moved_at is None:
            moved_at = k * ctrl.dt
    assert moved_at is not None and moved_at < 300.0
    ref = R * np.array([math.cos(ctrl.theta_ref), math.sin(ctrl.theta_ref), 0.0])
    assert np.linalg.norm(ref - ctrl.r) < g.max_lag_m  # following it round
    assert math.degrees(ctrl.fa.direction * ctrl.theta_ref) > 45.0


def test_fly_around_keep_out_and_out_of_bounds_end_the_episode() -> None:
    env = DockingEnv("fly_around", perception="truth")
    env.reset(seed=0)
    w = env.world
    # Inside the keep-out sphere, 90 deg off the port axis (radial, beside the truss).
    w.state = np.array([30.0, 0.0, 0.0, 0.0, 0.0, 0.0])
    w._invalidate()
    _, reward, term, _, info = env.step(np.zeros(3, dtype=np.float32))
    assert term and info["termination"] == "keep_out" and info["reward_keep_out"] < 0
    env.reset(seed=0)
    w.state = np.array([0.0, 350.0, 0.0, 0.0, 0.0, 0.0])
    w._invalidate()
    _, _, term, _, info = env.step(np.zeros(3, dtype=np.float32))
    assert term and info["termination"] == "out_of_bounds" and info["reward_exit"] < 0
    # Leaving along the port axis inside the keep-out sphere is the departure, not a violation.
    env.reset(seed=0)
    _, _, term, _, info = env.step(np.zeros(3, dtype=np.float32))
    assert not term


def test_fly_around_config_rejects_a_band_reaching_into_the_keep_out() -> None:
    from perception.config import ConfigError

    with pytest.raises((ConfigError, ValueError), match="keep_out_radius_m"):
        load_config("fly_around", env__fly_around__standoff_m=50.0, env__fly_around__band_m=15.0)


def test_far_rendezvous_on_truth_docks_in_a_few_thousand_steps_with_long_steps_far_out() -> None:
    env = gym.make("TriDAR/FarRendezvous-v0", perception="truth")
    u = env.unwrapped
    ctrl = make_controller("glideslope", u.cfg)
    obs, info = env.reset(seed=1)
    ctrl.reset()
    first_dt = None
    laws = set()
    steps = 0
    while True:
        obs, _, term, trunc, info = env.step(ctrl(obs))
        steps += 1
        laws.add(ctrl.law)
        if first_dt is None:
            first_dt = info["step_dt"]
        # A step's length follows the schedule of the range the controller saw.
        if term or trunc:
            break
    assert info["termination"] == "docked"
    assert first_dt == pytest.approx(30.0)  # 60 frames of 0.5 s from ~5 km
    assert steps < 5000
    assert info["t"] > 3000.0  # kilometres at metres per second
    assert {"bearing", "pose"} <= laws
    assert info["delta_v"] < 25.0  # forced motion down the V-bar costs ~2 n per metre


def test_new_ids_refuse_the_batched_truth_env_with_one_clear_line() -> None:
    for env_id in ("TriDAR/FarRendezvous-v0", "TriDAR/FlyAround-v0"):
        with pytest.raises(ValueError, match="cannot batch") as exc:
            gym.make_vec(env_id, num_envs=2, vectorization_mode="vector_entry_point", perception="truth")
        assert "\n" not in str(exc.value)
