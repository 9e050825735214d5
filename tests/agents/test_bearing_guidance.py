"""Bearing-mode guidance (agents.bearing_guidance): the law on synthetic observations, its hand-over
to the pose-based controllers, and one closed loop on the full pipeline (issue 19)."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

import tridar_env  # noqa: F401  (registers the ids)
from agents.bearing_guidance import BearingGuidance, line_of_sight
from agents.controllers import make_controller
from agents.glideslope import GlideslopeController
from agents.lqr import LQRController
from perception.config import MissionConfig, load_config
from tridar_env.env import OBS_DIM, observation_slices

S = observation_slices()
HEALTHY = [1, 1, 1, 1, 1, 1, 1, 0]


@pytest.fixture(scope="module")
def cfg() -> MissionConfig:
    return load_config("rendezvous", env__perception="truth")


def _bearing_obs(rng: float, range_rate: float | None, az: float = 0.0, el: float = 0.0) -> np.ndarray:
    """Bearing-mode observation (no pose; garbage in the invalid pose blocks)."""
    obs = np.zeros(OBS_DIM, dtype=np.float32)
    obs[S["mode_onehot"]] = [1.0, 0.0, 0.0]
    obs[S["valid"]] = [1, 1, 0 if range_rate is None else 1, 0, 0, 0, 0, 0]
    obs[S["port_position_dock"]] = [5.0, -3.0, 2.0]  # not valid: must be ignored
    obs[S["port_velocity_dock"]] = [0.5, 0.5, -0.5]
    obs[S["range"]] = rng
    obs[S["range_rate"]] = 0.0 if range_rate is None else range_rate
    obs[S["bearing"]] = [az, el]
    obs[S["fuel_fraction"]] = 1.0
    return obs


def _healthy_obs(z: float, vz: float = 0.0) -> np.ndarray:
    obs = np.zeros(OBS_DIM, dtype=np.float32)
    obs[S["mode_onehot"]] = [0.0, 0.0, 1.0]
    obs[S["valid"]] = HEALTHY
    obs[S["port_position_dock"]] = [0.3, -0.2, z]
    obs[S["port_velocity_dock"]] = [0.0, 0.0, vz]
    obs[S["q_dock_port"]] = [0.0, 1.0, 0.0, 0.0]
    obs[S["range"]] = z + 1.0
    obs[S["range_rate"]] = vz
    obs[S["bearing"]] = [0.0, 0.0]
    obs[S["fuel_fraction"]] = 1.0
    return obs


# ---------------------------------------------------------------------- the law
def test_speed_profile_shrinks_with_range_and_stops_at_the_hold_point(cfg: MissionConfig) -> None:
    bg = BearingGuidance(cfg)
    g = bg.g
    z = np.linspace(0.0, 800.0, 801)
    v = np.array([bg.desired_speed(x) for x in z])
    assert np.all(np.diff(v) >= 0.0)  # never faster closer in
    assert v.max() == pytest.approx(g.v_max)
    assert np.all(v[z <= g.hold_range_m] == 0.0)  # no closing inside the hold point
    # about the glideslope's own top speed (0.30 m/s) at the search hand-over range
    assert 0.2 <= bg.desired_speed(cfg.pipeline.bearing_to_search_range_m) <= 0.4


def test_closes_along_the_line_of_sight(cfg: MissionConfig) -> None:
    bg = BearingGuidance(cfg)
    az, el = 0.02, -0.01
    a = bg(_bearing_obs(400.0, 0.0, az, el)).astype(np.float64)
    los = line_of_sight([az, el])  # the mount is not rotated on this chaser
    assert a @ los > 0.5 * np.linalg.norm(a) > 0.0  # mostly toward the target
    # the pose blocks are not valid: other garbage, same action
    bg2 = BearingGuidance(cfg)
    obs = _bearing_obs(400.0, 0.0, az, el)
    obs[S["port_position_dock"]] = [-9.0, 9.0, 1.0]
    np.testing.assert_array_equal(bg2(obs), a.astype(np.float32))


def _fly(bg: BearingGuidance, x0: np.ndarray, steps: int) -> tuple[np.ndarray, np.ndarray]:
    """Close the loop on exact bearing / range / range rate of a double integrator: the target's
    centre of mass at ``x`` from the chaser's, body frame, ``x'' = -a``. Returns the ranges and
    closing speeds per step."""
    x, xd = x0.astype(np.float64), np.zeros(3)
    t_cs = bg.t_cs
    ranges, closing = [], []
    for _ in range(steps):
        c = x - t_cs
        r = float(np.linalg.norm(c))
        rr = float(c @ xd) / r
        obs = _bearing_obs(r, rr, np.arctan2(c[0], c[2]), np.arctan2(-c[1], np.hypot(c[0], c[2])))
        act = bg(obs).astype(np.float64)
        a = act * bg.max_thrust / (bg.dry + bg.prop0)
        x, xd = x + xd * bg.dt - 0.5 * a * bg.dt**2, xd - a * bg.dt
        ranges.append(r)
        closing.append(-rr)
    return np.array(ranges), np.array(closing)


def test_closed_loop_on_synthetic_bearings_slows_with_range_and_holds(cfg: MissionConfig) -> None:
    bg = BearingGuidance(cfg)
    ranges, closing = _fly(bg, np.array([8.0, -6.0, 400.0]), round(3000.0 / bg.dt))
    hold = bg.g.hold_range_m
    assert ranges.min() > hold - 15.0  # never closes inside the hold point (centroid != port)
    assert abs(ranges[-1] - hold) < 25.0  # holds there
    assert closing.max() <= bg.g.v_max + 0.05
    far, near = closing[(ranges < 300) & (ranges > 250)], closing[(ranges < 130) & (ranges > 100)]
    assert far.mean() > near.mean() + 0.1  # slower closer in
    assert abs(closing[-100:]).max() < 0.02  # at rest at the hold point
    p, _ = bg.port()
    assert np.hypot(p[0], p[1]) < 1.0  # on the approach axis (the estimate's port)


def test_brakes_when_the_range_rate_is_not_valid(cfg: MissionConfig) -> None:
    bg = BearingGuidance(cfg)
    for _ in range(20):
        bg.update(_bearing_obs(300.0, -0.4))
        bg.applied(np.zeros(3))
    assert bg.accel(_bearing_obs(300.0, -0.4))[2] > 0.0  # slower than the profile: speeds up
    obs = _bearing_obs(300.0, None)
    bg.update(obs)
    assert bg.accel(obs)[2] < -0.02  # closing at ~0.4 m/s with no range rate: brakes


@pytest.mark.parametrize("make", [GlideslopeController, LQRController])
def test_hands_over_to_the_pose_law_on_a_healthy_pose(cfg: MissionConfig, make: type) -> None:
    ctrl = make(cfg)
    for _ in range(10):
        ctrl(_bearing_obs(300.0, -0.2, 0.01, 0.0))
        assert ctrl.law == "bearing"
    healthy = _healthy_obs(190.0, -0.25)
    act = ctrl(healthy)
    assert ctrl.law == "pose" and ctrl.safety.mode == "nominal"
    np.testing.assert_array_equal(act, make(cfg)(healthy))  # exactly the pose law's action
    # the pose lost far out: back on the bearing
    ctrl(_bearing_obs(185.0, -0.25, 0.0, 0.0))
    assert ctrl.law == "bearing"
    # lost close in: the collision-avoidance rules, not the bearing law
    close = make(cfg)
    close(_healthy_obs(30.0, -0.1))
    close(_bearing_obs(31.0, -0.1))
    assert close.law == "safety" and close.safety.mode == "avoid"
    blind = make(cfg)
    blind(_bearing_obs(40.0, -0.2))
    assert blind.law == "safety" and blind.safety.mode == "blind"


def test_registry_glideslope_embeds_the_bearing_law(cfg: MissionConfig) -> None:
    ctrl = make_controller("glideslope", cfg)
    assert isinstance(ctrl.bearing, BearingGuidance)


# ---------------------------------------------------------------------- closed loop, pipeline
def test_pipeline_rendezvous_closes_in_and_starts_search() -> None:
    """From ~300 m on the full pipeline, the glideslope (bearing law before acquisition) closes in
    and the TriDAR leaves bearing mode. The old controllers drifted away in bearing mode."""
    env = gym.make("TriDAR/Rendezvous-v0", env__initial__range_m=300.0)
    ctrl = make_controller("glideslope", env.unwrapped.cfg)
    obs, info = env.reset(seed=123)
    ctrl.reset()
    r0 = float(np.linalg.norm(info["truth_r_lvlh"]))
    modes = set()
    for _ in range(700):  # 350 s
        obs, _, term, trunc, info = env.step(ctrl(obs))
        modes.add(info["mode"])
        assert not term and not trunc
        if info["mode"] != "bearing":
            break
    assert modes - {"bearing"}, "still in bearing mode after 350 s"
    assert float(np.linalg.norm(info["truth_r_lvlh"])) < r0 - 60.0
    env.close()
