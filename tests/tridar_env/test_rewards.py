"""Reward terms: potential-based shaping telescopes, the speed profile, graded near misses."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

import tridar_env  # noqa: F401
from agents.glideslope import GlideslopeController, GlideslopeGains
from perception.config import DockingEnvelopeConfig
from tridar_env.env import envelope_excess
from tridar_env.world import ContactState


def _contact(**kw: float) -> ContactState:
    base = {"axial_distance": 0.0, "lateral_offset": 0.02, "closing_speed": 0.07,
            "lateral_speed": 0.01, "misalignment_deg": 0.5, "angular_rate_deg_s": 0.01}
    return ContactState(**{**base, **kw})


def test_envelope_excess_is_zero_inside_and_relative_outside() -> None:
    e = DockingEnvelopeConfig()
    assert envelope_excess(_contact(), e) == 0.0
    assert envelope_excess(_contact(closing_speed=0.12), e) == pytest.approx(0.2)
    assert envelope_excess(_contact(closing_speed=0.04), e) == pytest.approx(0.2)
    assert envelope_excess(_contact(lateral_offset=0.15), e) == pytest.approx(0.5)
    assert envelope_excess(_contact(misalignment_deg=8.0), e) == pytest.approx(1.0)
    # The worst violation counts.
    assert envelope_excess(_contact(lateral_offset=0.15, lateral_speed=0.08), e) == pytest.approx(1.0)


def _fly(gains: GlideslopeGains | None = None, **kw) -> tuple[list[dict], gym.Env]:
    """Fly the glideslope on truth; each info also gets the true dock-to-port distance."""
    env = gym.make("TriDAR/FinalApproach-v0", perception="truth", **kw)
    obs, info0 = env.reset(seed=3)
    ctl = GlideslopeController(env.unwrapped.cfg, gains)
    infos = [{**info0, "distance": env.unwrapped._distance()}]
    while True:
        obs, _, term, trunc, info = env.step(ctl(obs))
        infos.append({**info, "distance": env.unwrapped._distance()})
        if term or trunc:
            return infos, env


def test_shaping_terms_telescope_to_the_change_of_potential() -> None:
    infos, env = _fly(env__frame_skip=5)
    rw = env.unwrapped.cfg.env.reward
    first, last = infos[0]["contact"], infos[-1]["contact"]
    assert infos[-1]["termination"] == "docked"
    lateral = sum(i["reward_lateral"] for i in infos[1:])
    assert lateral == pytest.approx(rw.lateral * (first.lateral_offset - last.lateral_offset), abs=1e-9)
    progress = sum(i["reward_progress"] for i in infos[1:])
    assert progress == pytest.approx(rw.progress * (infos[0]["distance"] - infos[-1]["distance"]), abs=1e-9)
    # The approach covered the ~30 m start distance: the progress sum is that distance.
    assert 25.0 < progress / rw.progress < 36.0
    dt = env.unwrapped.cfg.env.frame_period_s * 5
    assert all(i["reward_time"] == pytest.approx(-rw.time * dt) for i in infos[1:])


def test_speed_profile_penalises_hovering_more_than_approaching() -> None:
    env = gym.make("TriDAR/FinalApproach-v0", perception="truth")
    env.reset(seed=0)
    hover = [env.step(np.zeros(3, np.float32))[4]["reward_speed_profile"] for _ in range(20)]
    infos, _ = _fly()
    approach = np.mean([i["reward_speed_profile"] for i in infos[1:]])
    # Standing still 30 m out misses the reference (0.2 m/s there) by ~0.2 m/s every second.
    cfg = env.unwrapped.cfg.env
    assert np.mean(hover) == pytest.approx(-cfg.reward.speed_profile * 0.2 * cfg.frame_period_s, rel=0.1)
    assert approach > 0.5 * np.mean(hover)


def test_near_miss_costs_less_than_a_crash_and_is_graded_by_the_excess() -> None:
    near, env = _fly(GlideslopeGains(v_final=0.115, slope=0.012))
    crash, _ = _fly(GlideslopeGains(v_final=0.3, slope=0.05, v_max=0.5))
    rw = env.unwrapped.cfg.env.reward
    e = env.unwrapped.cfg.env.envelope
    for infos in (near, crash):
        assert infos[-1]["termination"] == "collision"
    c = near[-1]["contact"]
    excess = envelope_excess(c, e)
    assert 0.0 < excess < 0.5
    assert near[-1]["reward_collision"] == pytest.approx(-rw.collision * (rw.near_miss + excess))
    assert crash[-1]["reward_collision"] == pytest.approx(-rw.collision)
