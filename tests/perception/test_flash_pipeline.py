"""The flash-LiDAR pipeline (``perception="flash"``): the TriDAR modes, filter and integrity on
seed 003's sensor, in every environment id."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import tridar_env
from agents.controllers import make_controller
from perception.pipeline.flash import FlashPipeline


def test_check_env_passes_with_the_flash_pipeline() -> None:
    env = gym.make("TriDAR/FinalApproach-v0", perception="flash").unwrapped
    assert isinstance(env.observer.pipeline, FlashPipeline)
    check_env(env, skip_render_check=True)


@pytest.mark.parametrize("env_id", list(tridar_env.ENV_IDS))
def test_every_id_accepts_flash(env_id: str) -> None:
    env = gym.make(env_id, perception="flash")
    obs, _ = env.reset(seed=1)
    for _ in range(3):
        obs, reward, term, trunc, _ = env.step(np.zeros(env.action_space.shape, dtype=np.float32))
        assert np.isfinite(obs).all() and np.isfinite(reward)
        if term or trunc:
            break


def test_flash_pipeline_tracks_a_tumbling_target_through_planned_restarts() -> None:
    """The sync controller on the tumbling CYGNSS with a restart every 15 s: every restart is
    reacquired, the port is tracked to centimetres, and no valid pose is wrong beyond its
    protection level."""
    env = gym.make("TriDAR/TumblingTarget-v0", perception="flash", pipeline__restart_period_s=15.0)
    u = env.unwrapped
    ctrl = make_controller("sync", u.cfg)
    obs, info = env.reset(seed=3)
    ctrl.reset()
    port = np.append(u.target.T_target_port[:3, 3], 1.0)
    errs, hmi, restarts_seen, awaiting, reacquired = [], 0, 0, False, 0
    pipe = u.observer.pipeline
    for _ in range(260):
        obs, _, term, trunc, info = env.step(ctrl(obs))
        sv = u.state_vector
        if pipe.stats.restarts > restarts_seen:
            restarts_seen, awaiting = pipe.stats.restarts, True
        if sv.valid.position and sv.valid.attitude:
            if awaiting:
                reacquired, awaiting = reacquired + 1, False
            if not sv.valid.degraded:
                e = float(np.linalg.norm((sv.T_sensor_target @ port - info["truth_T_sensor_target"] @ port)[:3]))
                errs.append(e)
                hmi += e > sv.protection_level
        if term or trunc:
            break
    assert restarts_seen >= 2 and reacquired == restarts_seen - int(awaiting)
    assert len(errs) > 150
    assert np.median(errs) < 0.01 and max(errs) < 0.1
    assert hmi == 0
    assert pipe.stats.losses == 0
