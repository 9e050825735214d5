"""TruthVectorEnv: the batched truth environments against DockingEnv, step by step."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from scipy.stats import chi2

import tridar_env  # noqa: F401  (registers the ids)
from agents.controllers import make_controller
from perception.geometry import fast_matrix_to_quat, fast_quat_to_matrix
from tridar_env.env import DockingEnv, observation_slices
from tridar_env.vector import TruthVectorEnv, _matrix_to_quat, _quat_to_matrix

N = 4


def _pair(env_id: str, **kw):
    batched = gym.make_vec(env_id, num_envs=N, vectorization_mode="vector_entry_point", **kw)
    reference = gym.make_vec(env_id, num_envs=N, vectorization_mode="sync", **kw)
    return batched, reference


@pytest.mark.parametrize(
    ("env_id", "kw", "scale", "steps"),
    [
        ("TriDAR/FinalApproach-v0", {"perception": "truth"}, 1.0, 1200),
        ("TriDAR/FinalApproach-v0", {"perception": "truth+noise", "max_episode_steps": 150}, 0.3, 400),
        # The tumbling id's chaser is 6-DOF; with the ideal attitude law it batches.
        ("TriDAR/TumblingTarget-v0",
         {"perception": "truth+noise", "dynamics__chaser__attitude": "ideal", "max_episode_steps": 120}, 1.0, 300),
    ],
)
def test_matches_single_envs_step_by_step(env_id: str, kw: dict, scale: float, steps: int) -> None:
    """Same seeds, same actions: observations, rewards, terminations, truncations and causes are
    identical, bit for bit, through autoresets."""
    batched, reference = _pair(env_id, **kw)
    o1, _ = batched.reset(seed=3)
    o2, _ = reference.reset(seed=3)
    np.testing.assert_array_equal(o1, o2)
    rng = np.random.default_rng(0)
    ends = 0
    for _ in range(steps):
        a = (scale * rng.uniform(-1.0, 1.0, (N, 3))).astype(np.float32)
        o1, r1, te1, tr1, i1 = batched.step(a)
        o2, r2, te2, tr2, i2 = reference.step(a)
        np.testing.assert_array_equal(te1, te2)
        np.testing.assert_array_equal(tr1, tr2)
        np.testing.assert_array_equal(o1, o2)
        np.testing.assert_array_equal(r1, r2)
        for i in np.flatnonzero(te1):
            assert i1["termination"][i] == i2["termination"][i]
        ends += int(te1.sum() + tr1.sum())
    assert ends >= 3  # autoresets were exercised
    batched.close()
    reference.close()


def test_quaternion_rows_are_the_single_envs_conversions() -> None:
    """The batched conversions are ``fast_matrix_to_quat`` and ``fast_quat_to_matrix`` row by row,
    bit for bit, through every branch of Shepperd's method, in a mixed batch and a uniform one."""
    R = Rotation.random(400, random_state=0).as_matrix()
    diag = np.stack([R[:, 0, 0], R[:, 1, 1], R[:, 2, 2], np.trace(R, axis1=1, axis2=2)], axis=1)
    branch = np.argmax(diag, axis=1)
    assert set(branch.tolist()) == {0, 1, 2, 3}
    for batch in (R, R[branch == 1]):
        q = _matrix_to_quat(batch)
        np.testing.assert_array_equal(q, np.stack([fast_matrix_to_quat(r) for r in batch]))
        np.testing.assert_array_equal(_quat_to_matrix(q), np.stack([fast_quat_to_matrix(x) for x in q]))


def test_truth_plus_noise_follows_its_sigmas() -> None:
    """The noise is there, with the configured size: the port position's error over many
    environments has the position sigma (the attitude error turns the target about the port)."""
    kw = {"env__truth_noise_position_m": 0.02, "env__truth_noise_correlation_s": 0.0}
    truth = TruthVectorEnv(256, "final_approach", perception="truth", **kw)
    noisy = TruthVectorEnv(256, "final_approach", perception="truth+noise", **kw)
    o_t, _ = truth.reset(seed=1)
    o_n, _ = noisy.reset(seed=1)
    err = (o_n - o_t)[:, observation_slices()["port_position_dock"]]
    assert np.std(err) == pytest.approx(0.02, rel=0.1)
    assert abs(np.mean(err)) < 0.004
    # The protection level bounds that error at the integrity risk: 0.02 m per axis at the port.
    pl = o_n[:, observation_slices()["protection_level"]]
    assert np.allclose(pl, 0.02 * np.sqrt(chi2.isf(noisy.cfg.pipeline.integrity.risk, 3)), rtol=1e-5)
    assert np.all(np.linalg.norm(err, axis=1) < pl[:, 0])


def test_glideslope_docks_every_env_and_rewards_sum() -> None:
    """Four scripted approaches on truth dock inside the envelope; the reward is the sum of its
    terms; a docked environment restarts on the next step."""
    env = TruthVectorEnv(N, "final_approach", perception="truth")
    cfg = env.cfg
    ctrls = [make_controller("glideslope", cfg) for _ in range(N)]
    for c in ctrls:
        c.reset()
    obs, _ = env.reset(seed=11)
    done = np.zeros(N, dtype=bool)
    causes = [""] * N
    for _ in range(cfg.env.max_episode_steps):
        act = np.stack([c(o) for c, o in zip(ctrls, obs)])
        obs, reward, term, trunc, info = env.step(act)
        terms = sum(info[k] for k in info if k.startswith("reward_"))
        np.testing.assert_allclose(reward, terms, rtol=1e-12, atol=1e-12)
        for i in np.flatnonzero((term | trunc) & ~done):
            causes[i] = info["termination"][i]
            done[i] = True
            assert info["delta_v"][i] > 0
        if done.all():
            break
    assert causes == ["docked"] * N
    # The next step resets the ones that just finished: fresh time, full-range observation.
    last = term | trunc
    obs, reward, term, trunc, info = env.step(np.zeros((N, 3), dtype=np.float32))
    assert last.any()
    assert np.all(info["t"][last] == 0.0) and not term[last].any() and np.all(reward[last] == 0.0)
    assert np.all(obs[last, observation_slices()["range"].start] > 20.0)  # range back at the start


def test_bad_input_is_rejected_with_the_field_named() -> None:
    with pytest.raises(ValueError, match="env.perception='tridar'"):
        gym.make_vec("TriDAR/FinalApproach-v0", num_envs=2, vectorization_mode="vector_entry_point")
    with pytest.raises(ValueError, match="dynamics.chaser.attitude='controlled'"):
        TruthVectorEnv(2, "tumbling_target", perception="truth")
    env = TruthVectorEnv(2, "final_approach", perception="truth")
    with pytest.raises(RuntimeError, match="before reset"):
        env.step(np.zeros((2, 3)))
    env.reset(seed=0)
    bad = np.zeros((2, 3))
    bad[1, 2] = np.nan
    with pytest.raises(ValueError, match=r"actions\[1\]"):
        env.step(bad)
    with pytest.raises(ValueError, match="shape"):
        env.step(np.zeros(3))
    _, _, _, _, info = env.step(np.full((2, 3), 2.0))
    assert info["clipped_actions"].tolist() == [3, 3]


def test_spaces_match_the_single_env() -> None:
    env = TruthVectorEnv(3, "final_approach", perception="truth")
    single = DockingEnv("final_approach", perception="truth")
    assert env.single_observation_space == single.observation_space
    assert env.single_action_space == single.action_space
    obs, _ = env.reset(seed=0)
    assert obs.shape == (3, *single.observation_space.shape) and obs.dtype == np.float32
    assert all(single.observation_space.contains(o) for o in obs)
