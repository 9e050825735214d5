"""Validation while training: the policy flown on the mission's own runs, the best one kept."""

from __future__ import annotations

import csv
import io
import zipfile

import numpy as np
import pytest
import torch

from agents.policies import load_policy
from agents.training import TrainingConfig, train

RUN = {
    "name": "val",
    "algo": "ppo",
    "env_id": "TriDAR/FinalApproach-v0",
    "perception": "truth",
    "config": {"env__frame_skip": 5, "env__max_episode_steps": 6},
    "train_config": {"env__initial__range_m": 3.0},   # validation flies the mission's 30 m start
    "total_timesteps": 96,
    "n_envs": 2,
    "vec_env": "dummy",
    "seed": 5,
    "checkpoint_every_steps": 32,
    "net_arch": [16],
    "observation_blocks": ["port_position_dock", "port_velocity_dock"],
    "validation": {"every_steps": 32, "episodes": 3, "seed": 40},
    "hyperparams": {"n_steps": 16, "batch_size": 32, "n_epochs": 1},
}


def _weights(path):
    with zipfile.ZipFile(path) as z:
        return torch.load(io.BytesIO(z.read("policy.pth")), weights_only=True)


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    out = tmp_path_factory.mktemp("val") / "run"
    train(TrainingConfig(**RUN), out, progress=False)
    return out


def test_a_row_per_validation_and_the_earliest_best_kept(run):
    with (run / "validation.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    assert [int(r["timesteps"]) for r in rows] == [32, 64, 96]
    for r in rows:
        # From 30 m nothing docks or collides in 30 s: every run meets the time limit.
        assert (int(r["docked"]), int(r["collision"]), int(r["other"])) == (0, 0, 3)
    assert [int(r["best"]) for r in rows] == [1, 0, 0]  # a tie keeps the earliest
    best, ckpt, last = (_weights(run / "best_model.zip"), _weights(run / "checkpoints/model_32_steps.zip"),
                        _weights(run / "model.zip"))
    assert all(torch.equal(best[k], ckpt[k]) for k in best)
    assert not all(torch.equal(best[k], last[k]) for k in best)
    with np.load(run / "best_model_vecnormalize.npz") as a, \
            np.load(run / "checkpoints/vecnormalize_32_steps.npz") as b:
        assert np.array_equal(a["obs_mean"], b["obs_mean"]) and a["obs_mean"].shape == (6,)


def test_the_best_policy_loads_and_flies_the_full_observation(run):
    from tridar_env.env import OBS_DIM

    policy = load_policy(run / "best_model.zip")
    assert policy.obs_shape == (OBS_DIM,)
    a = policy(np.zeros(OBS_DIM, dtype=np.float32))
    assert a.shape == (3,) and np.all(np.abs(a) <= 1.0 + 1e-6)


def test_validation_needs_a_positive_interval():
    with pytest.raises(ValueError, match="every_steps"):
        TrainingConfig(**{**RUN, "validation": {"every_steps": 0}})


def test_validating_does_not_change_what_is_learnt(run, tmp_path):
    plain = tmp_path / "plain"
    train(TrainingConfig(**{**RUN, "validation": None}), plain, progress=False)
    a, b = _weights(run / "model.zip"), _weights(plain / "model.zip")
    assert all(torch.equal(a[k], b[k]) for k in a)
    assert not (plain / "validation.csv").exists() and not (plain / "best_model.zip").exists()


def test_at_start_validates_the_policy_training_starts_from(tmp_path):
    """validation.at_start: a row at 0 steps, and on a tie that starting policy is the best kept
    (not the one after the first update)."""
    out = tmp_path / "run"
    train(TrainingConfig(**{**RUN, "validation": {**RUN["validation"], "at_start": True}}), out, progress=False)
    with (out / "validation.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    assert [int(r["timesteps"]) for r in rows] == [0, 32, 64, 96]
    assert [int(r["best"]) for r in rows] == [1, 0, 0, 0]
    # The 32-step checkpoint is still the starting policy (the first update follows the first
    # 32-step rollout); the 64-step one has been updated.
    best, start, later = (_weights(out / "best_model.zip"), _weights(out / "checkpoints/model_32_steps.zip"),
                          _weights(out / "checkpoints/model_64_steps.zip"))
    assert all(torch.equal(best[k], start[k]) for k in best)
    assert not all(torch.equal(best[k], later[k]) for k in best)
