"""``run_episode``'s integrity bookkeeping, on a scripted environment whose every step is known:
pose availability, valid-but-wrong steps (error beyond the protection level, degraded poses
excepted), planned restarts reacquired, and a restart still pending when the episode ends."""

from __future__ import annotations

from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest

from agents.episode import run_episode
from perception.geometry import make_T
from perception.pipeline.state import Validity
from tridar_env.world import ContactState

#: (restarts so far, pose valid, degraded, port error [m], protection level [m]) per step.
SCRIPT = [
    (0, True, False, 0.01, 0.05),   # healthy
    (0, True, False, 0.09, 0.05),   # valid-but-wrong
    (0, True, True, 0.30, 0.20),    # degraded: beyond its bound, but not claimed valid
    (1, False, False, 0.0, 0.0),    # planned restart: no pose
    (1, False, False, 0.0, 0.0),
    (1, True, False, 0.02, 0.05),   # reacquired
    (2, False, False, 0.0, 0.0),    # second restart
    (2, True, True, 0.01, 0.50),    # reacquired (degraded counts as a pose)
    (3, False, False, 0.0, 0.0),    # third restart, the episode ends before a pose
]


class ScriptedEnv:
    """Plays :data:`SCRIPT` (ends ``completed`` on its last step)."""

    def __init__(self, script: list[tuple[int, bool, bool, float, float]]) -> None:
        self.script = script
        self.target = SimpleNamespace(T_target_port=make_T(np.eye(3), [0.0, 0.0, 1.0]))
        self.observer = SimpleNamespace(pipeline=SimpleNamespace(
            stats=SimpleNamespace(restarts=0, losses=0, symmetry_switches=0)))
        self.state_vector = None
        self.unwrapped = self
        self.k = 0

    def _info(self, T_truth: np.ndarray, termination: str = "") -> dict:
        return {"mode": "tracking", "step_dt": 0.5, "t": 0.5 * self.k, "truth_T_sensor_target": T_truth,
                "estimate_position_error_m": float("nan"), "estimate_attitude_error_deg": float("nan"),
                "termination": termination, "delta_v": 0.0, "propellant_kg": 10.0,
                "contact": ContactState(*(float("nan"),) * 6), "n_points": 0}

    def reset(self, seed: int | None = None) -> tuple[np.ndarray, dict]:
        self.k = 0
        return np.zeros(3, dtype=np.float32), self._info(make_T(np.eye(3), [0.0, 0.0, 20.0]))

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict]:
        restarts, valid, degraded, err, pl = self.script[self.k]
        self.k += 1
        T_truth = make_T(np.eye(3), [0.0, 0.0, 20.0 - self.k])
        T_est = T_truth.copy()
        T_est[0, 3] += err  # the port error is the translation error (the target does not turn)
        self.observer.pipeline.stats.restarts = restarts
        v = replace(Validity(), position=valid, attitude=valid, degraded=degraded)
        self.state_vector = SimpleNamespace(valid=v, T_sensor_target=T_est, protection_level=pl)
        done = self.k == len(self.script)
        return (np.zeros(3, dtype=np.float32), 0.0, done, False,
                self._info(T_truth, "completed" if done else ""))


def test_run_episode_counts_poses_misleading_steps_and_restarts_as_scripted() -> None:
    r = run_episode(ScriptedEnv(SCRIPT), lambda obs: np.zeros(3), seed=0)
    assert r.outcome == "completed" and r.steps == len(SCRIPT)
    assert r.pose_fraction == pytest.approx(5 / 9)
    assert r.hmi_steps == 1  # the degraded step beyond its bound is not counted
    assert (r.restarts, r.restarts_reacquired, r.restarts_pending) == (3, 2, 1)
    row = r.row()
    assert row["restarts_pending"] == 1 and row["hmi_steps"] == 1


def test_a_restart_never_reacquired_before_a_later_one_is_not_counted_reacquired() -> None:
    """Two restarts in a row with no pose between them: only the second can be reacquired."""
    script = [(1, False, False, 0.0, 0.0), (2, False, False, 0.0, 0.0), (2, True, False, 0.0, 0.05)]
    r = run_episode(ScriptedEnv(script), lambda obs: np.zeros(3), seed=0)
    assert (r.restarts, r.restarts_reacquired, r.restarts_pending) == (2, 1, 0)
