"""A policy that sees only some blocks of the observation: in training, in its saved form, in flight."""

from __future__ import annotations

import numpy as np
import pytest

from agents.observation_blocks import BLOCK_NAMES, VecSelectObservation, block_indices
from agents.policies import load_policy
from agents.training import TrainingConfig, load_training, train
from tridar_env.env import OBS_DIM, OBSERVATION_STRUCTURE

BLOCKS = ["port_position_dock", "port_velocity_dock", "range", "range_rate"]

RUN = {
    "name": "blocks",
    "algo": "ppo",
    "env_id": "TriDAR/FinalApproach-v0",
    "perception": "truth+noise",
    "config": {"env__frame_skip": 5, "env__max_episode_steps": 12, "env__initial__range_m": 6.0},
    "total_timesteps": 96,
    "n_envs": 2,
    "vec_env": "batched",
    "seed": 2,
    "checkpoint_every_steps": None,
    "net_arch": [16],
    "observation_blocks": BLOCKS,
    "hyperparams": {"n_steps": 24, "batch_size": 48, "n_epochs": 1},
}


def test_indices_follow_the_structure():
    k, where = 0, {}
    for name, size, _, _ in OBSERVATION_STRUCTURE:
        where[name] = list(range(k, k + size))
        k += size
    assert k == OBS_DIM and set(BLOCK_NAMES) == set(where)
    assert block_indices(["range", "port_position_dock"]).tolist() == where["range"] + where["port_position_dock"]
    assert block_indices(BLOCK_NAMES).tolist() == list(range(OBS_DIM))


@pytest.mark.parametrize(
    "blocks, words",
    [([], "at least one"), (["range", "speed"], "'speed' is not a block"), (["range", "range"], "listed 2 times")],
)
def test_bad_blocks_are_named(tmp_path, blocks, words):
    with pytest.raises(ValueError, match=words):
        TrainingConfig(**{**RUN, "observation_blocks": blocks})
    p = tmp_path / "t.yaml"
    p.write_text(f"name: x\nobservation_blocks: {blocks}\n")
    with pytest.raises(Exception, match=words):
        load_training(p)


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    out = tmp_path_factory.mktemp("blocks") / "run"
    train(TrainingConfig(**RUN), out, progress=False)
    return out


def test_the_network_sees_the_blocks_and_flies_on_the_full_observation(run):
    policy = load_policy(run)
    idx = block_indices(BLOCKS)
    assert tuple(policy.model.observation_space.shape) == (len(idx),) and policy.obs_shape == (OBS_DIM,)
    rng = np.random.default_rng(0)
    obs = rng.normal(size=OBS_DIM).astype(np.float32)
    # What the network gets: the blocks of the full observation, normalised by the run's statistics.
    with np.load(run / "vecnormalize.npz", allow_pickle=False) as z:
        mean, var, eps, clip = z["obs_mean"], z["obs_var"], float(z["epsilon"]), float(z["clip_obs"])
    assert mean.shape == (len(idx),)
    expect = np.clip((obs[idx].astype(np.float64) - mean) / np.sqrt(var + eps), -clip, clip)
    assert np.allclose(policy.normalize(obs), expect, atol=1e-6)
    # Blocks it does not see do not move its action; one it sees does.
    other = obs.copy()
    other[np.setdiff1d(np.arange(OBS_DIM), idx)] = rng.normal(size=OBS_DIM - len(idx))
    assert np.array_equal(policy(obs), policy(other))
    moved = obs.copy()
    moved[idx[0]] += 50.0
    assert not np.array_equal(policy(obs), policy(moved))
    with pytest.raises(ValueError, match="shape"):
        policy(obs[idx])


def test_terminal_observations_are_selected_too():
    from agents.vec_adapter import make_batched_vec_env

    venv = VecSelectObservation(
        make_batched_vec_env("TriDAR/FinalApproach-v0", 2, seed=4,
                             env_kwargs={"perception": "truth", "env__max_episode_steps": 3}), BLOCKS)
    full = make_batched_vec_env("TriDAR/FinalApproach-v0", 2, seed=4,
                                env_kwargs={"perception": "truth", "env__max_episode_steps": 3})
    idx = block_indices(BLOCKS)
    try:
        assert venv.observation_space.shape == (len(idx),)
        assert np.array_equal(venv.reset(), full.reset()[:, idx])
        act = np.zeros((2, 3), dtype=np.float32)
        for _ in range(3):
            o, _, d, infos = venv.step(act)
            fo, _, fd, finfos = full.step(act)
            assert np.array_equal(o, fo[:, idx]) and np.array_equal(d, fd)
        assert d.all()
        for info, finfo in zip(infos, finfos):
            assert np.array_equal(info["terminal_observation"], finfo["terminal_observation"][idx])
    finally:
        venv.close()
        full.close()
