"""With frame_skip the agent decides less often, but the pipeline still processes every frame."""

from __future__ import annotations

import gymnasium as gym
import numpy as np

import tridar_env  # noqa: F401  (registers the ids)


def _states(frame_skip: int, actions: np.ndarray) -> list:
    env = gym.make("TriDAR/FinalApproach-v0", perception="tridar", env__frame_skip=frame_skip)
    env.reset(seed=7)
    out = []
    for a in actions:
        for _ in range(5 // frame_skip):
            env.step(a)
        out.append(env.unwrapped._state)
    env.close()
    return out


def test_skipped_frames_are_still_tracked_bitwise():
    actions = np.array([[0.0, 0.0, 0.3], [0.1, -0.1, 0.3], [0.0, 0.0, 0.0]] * 4, dtype=np.float32)
    every = _states(1, actions)
    skipped = _states(5, actions)
    assert any(s.valid.position for s in skipped[:3])  # tracking within a few seconds
    for a, b in zip(every, skipped):
        assert a.t == b.t and a.valid == b.valid and a.mode == b.mode
        assert np.array_equal(a.position, b.position) and np.array_equal(a.quaternion, b.quaternion)
        assert np.array_equal(a.covariance, b.covariance)
