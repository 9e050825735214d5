"""Decision intervals that lengthen with range (``env.decision_schedule``): how many frames a step
of :class:`~tridar_env.env.DockingEnv` holds its action for. Controllers that predict over a step
(:mod:`agents.bearing_guidance`) call the same function on the range they saw."""

from __future__ import annotations

import math

from perception.config import EnvConfig

__all__ = ["decision_frames"]


def decision_frames(env: EnvConfig, range_m: float | None) -> int:
    """Frames a step holds its action for (``env.decision_schedule``), from the range [m] of the
    state vector the agent saw before acting (None: no valid range; ``frame_skip`` then).

    Example:
        >>> from perception.config import EnvConfig
        >>> env = EnvConfig(decision_schedule={"start_m": 300, "step_m": 50, "max_frames": 60})
        >>> decision_frames(env, 100.0), decision_frames(env, 1000.0), decision_frames(env, 9e3)
        (1, 15, 60)
    """
    ds = env.decision_schedule
    if ds is None or range_m is None or not math.isfinite(range_m):
        return env.frame_skip
    extra = max(0.0, range_m - ds.start_m) / ds.step_m
    return int(min(env.frame_skip + math.floor(extra), max(ds.max_frames, env.frame_skip)))
