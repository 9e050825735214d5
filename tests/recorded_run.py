"""A short recorded FinalApproach run shared by the recording, replay and viewer tests."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import gymnasium as gym

import tridar_env  # noqa: F401  (registers the ids)
from agents.controllers import make_controller
from tridar_env.recording import RecordMCAP

#: Env steps of the recorded run: enough for search, acquisition and tracking.
STEPS = 60


@dataclass
class RecordedRun:
    path: Path
    cfg: Any
    live: list[Any]  # the env's state vector after reset and after each step
    last_cloud_points: Any


def record_run(folder: Path, steps: int = STEPS, **overrides: Any) -> RecordedRun:
    """Fly ``steps`` steps of TriDAR/FinalApproach-v0 (glideslope, seed 3) into ``folder/run.mcap``."""
    path = folder / "run.mcap"
    env = RecordMCAP(gym.make("TriDAR/FinalApproach-v0", config=overrides or None), path, label="test")
    ctrl = make_controller("glideslope", env.unwrapped.cfg)
    obs, _ = env.reset(seed=3)
    live = [env.unwrapped.state_vector]
    for _ in range(steps):
        obs, _, term, trunc, _ = env.step(ctrl(obs))
        live.append(env.unwrapped.state_vector)
        if term or trunc:
            break
    pts = env.unwrapped.observer.last_cloud.points.copy()
    cfg = env.unwrapped.cfg
    env.close()
    return RecordedRun(path, cfg, live, pts)
