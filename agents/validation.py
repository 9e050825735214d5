"""Validation while training: the policy flown on the evaluation's own start, best one kept.

A PPO run's last policy is not always its best: on a second seed the from-scratch FinalApproach
recipe docked 96 % of 50 truth+noise validation runs at 1.5M and 2.5M steps and 21 % of 200 at
the 3M it stopped on (a late oscillation of its contact speed). :class:`Validation` (a
stable-baselines3 callback, enabled by a training config's ``validation:``) flies the current
policy, deterministically, every ``every_steps`` on ``episodes`` runs of the mission as evaluation
flies it (the ``config`` overrides without ``train_config``'s curriculum, the training
perception), reset seeds ``seed + k`` (the same runs each time, so successive policies are
compared on the same runs; keep them apart from the evaluation's seeds). Each validation is a row
of ``validation.csv`` (:data:`COLUMNS`); the policy with the most docked runs so far (the earliest
on a tie) is saved as ``best_model.zip`` with ``best_model_vecnormalize.npz``, which ``evaluate``
and ``load_policy`` read like ``model.zip``.
"""

from __future__ import annotations

import csv
import time
from pathlib import Path
from typing import Any

import numpy as np
from stable_baselines3.common.callbacks import BaseCallback

__all__ = ["BEST_MODEL_FILE", "BEST_STATS_FILE", "COLUMNS", "VALIDATION_FILE", "Validation", "mean_action"]

BEST_MODEL_FILE = "best_model.zip"
BEST_STATS_FILE = "best_model_vecnormalize.npz"
VALIDATION_FILE = "validation.csv"
COLUMNS = ("timesteps", "wall_s", "episodes", "docked", "collision", "other", "best")


def mean_action(model: Any, vec: Any, obs: np.ndarray, indices: np.ndarray | None) -> np.ndarray:
    """A training model's deterministic action for the full observation ``obs``: the blocks it
    sees (``indices``, None: all), normalised by ``vec`` (its VecNormalize)."""
    x = obs if indices is None else obs[indices]
    return np.asarray(model.predict(vec.normalize_obs(x), deterministic=True)[0], dtype=np.float32)


class Validation(BaseCallback):  # type: ignore[misc]
    """Fly the policy on validation runs every ``every_steps``; keep the best (module docstring).

    Args:
        env: the validation env (one ``gymnasium`` env, the full observation).
        vec: the run's ``VecNormalize`` (its current observation statistics are the policy's).
        out: the run folder (``validation.csv``, ``best_model.zip``, ``best_model_vecnormalize.npz``).
        every_steps: total env steps between validations.
        episodes: runs per validation; ``seed``: run ``k`` resets with ``seed + k``.
        indices: the observation blocks the policy sees (None: all).
        save: ``save(model, vec, model_path, stats_path)`` writes a policy.
        at_start: validate the policy training starts from too (a row at 0 steps).
    """

    def __init__(self, env: Any, vec: Any, out: Path, every_steps: int, episodes: int, seed: int,
                 indices: np.ndarray | None, save: Any, at_start: bool = False) -> None:
        super().__init__()
        self.env, self.vec, self.out = env, vec, Path(out)
        self.every, self.episodes, self.seed = int(every_steps), int(episodes), int(seed)
        self.indices = indices
        self.save = save
        self.at_start = bool(at_start)
        self.best = -1
        self.next_at = self.every
        self._t0 = time.perf_counter()

    def _on_training_start(self) -> None:
        self._t0 = time.perf_counter()
        if self.at_start:
            self.validate()

    def fly(self) -> dict[str, int]:
        """The current policy on the validation runs: how many ended docked, in a collision, or
        otherwise (any other termination, or the time limit)."""
        counts = {"docked": 0, "collision": 0, "other": 0}
        for k in range(self.episodes):
            obs, _ = self.env.reset(seed=self.seed + k)
            while True:
                action = mean_action(self.model, self.vec, obs, self.indices)
                obs, _, term, trunc, info = self.env.step(action)
                if term or trunc:
                    cause = info.get("termination") or "truncated"
                    counts[cause if cause in counts else "other"] += 1
                    break
        return counts

    def _on_step(self) -> bool:
        if self.num_timesteps < self.next_at:
            return True
        while self.next_at <= self.num_timesteps:
            self.next_at += self.every
        self.validate()
        return True

    def validate(self) -> None:
        """Fly the validation runs now; keep the policy if it is the best so far; log a row."""
        counts = self.fly()
        best = counts["docked"] > self.best
        if best:
            self.best = counts["docked"]
            self.save(self.model, self.vec, self.out / BEST_MODEL_FILE, self.out / BEST_STATS_FILE)
        self.logger.record("validation/docked", counts["docked"] / self.episodes)
        path = self.out / VALIDATION_FILE
        new = not path.exists()
        with path.open("a", newline="") as fh:
            w = csv.writer(fh, lineterminator="\n")
            if new:
                w.writerow(COLUMNS)
            w.writerow([self.num_timesteps, f"{time.perf_counter() - self._t0:.6g}", self.episodes,
                        counts["docked"], counts["collision"], counts["other"], int(best)])
