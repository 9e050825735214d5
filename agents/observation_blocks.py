"""The blocks of the observation a policy sees: a subset of :data:`tridar_env.env.OBSERVATION_STRUCTURE`.

A policy trained on the truth+noise stand-in meets on the full pipeline values it never saw in
training: the registration fitness (always 1 on truth), the protection level (a constant on
truth+noise), the mode and validity flags (always tracking and valid). VecNormalize divides each
by the spread it had in training (next to 0), so a fitness of 0.9 reaches the network as -10 and
the policy flies on noise. A training config's ``observation_blocks`` names the blocks the policy
sees; :class:`VecSelectObservation` hands SB3 only those while training, and the saved policy
selects the same ones from the full observation when it flies (:class:`agents.policies.SB3Policy`).

Example:
    >>> from agents.observation_blocks import block_indices
    >>> block_indices(["range", "range_rate"]).tolist()
    [24, 25]
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import numpy.typing as npt
from gymnasium import spaces
from stable_baselines3.common.vec_env import VecEnv, VecEnvWrapper

from tridar_env.env import OBSERVATION_STRUCTURE, observation_slices

__all__ = ["BLOCK_NAMES", "VecSelectObservation", "block_indices", "check_blocks"]

BLOCK_NAMES = tuple(name for name, _, _, _ in OBSERVATION_STRUCTURE)


def check_blocks(blocks: Sequence[str]) -> list[str]:
    """``blocks`` as a list, or ValueError naming the unknown or repeated block."""
    names = list(blocks)
    if not names:
        raise ValueError("observation_blocks=[]; expected at least one of " + ", ".join(BLOCK_NAMES))
    for name in names:
        if name not in BLOCK_NAMES:
            raise ValueError(f"observation_blocks: {name!r} is not a block of the observation; "
                             f"expected some of {', '.join(BLOCK_NAMES)}")
        if names.count(name) > 1:
            raise ValueError(f"observation_blocks: {name!r} is listed {names.count(name)} times")
    return names


def block_indices(blocks: Sequence[str]) -> npt.NDArray[np.intp]:
    """Indices into the full observation of ``blocks``, in the order given."""
    where = observation_slices()
    names = check_blocks(blocks)
    return np.concatenate([np.arange(where[n].start, where[n].stop) for n in names]).astype(np.intp)


class VecSelectObservation(VecEnvWrapper):  # type: ignore[misc]
    """A ``VecEnv`` whose observations (terminal ones included) keep only ``blocks``."""

    def __init__(self, venv: VecEnv, blocks: Sequence[str]) -> None:
        self.indices = block_indices(blocks)
        box = venv.observation_space
        space = spaces.Box(box.low[self.indices], box.high[self.indices], dtype=box.dtype)
        super().__init__(venv, observation_space=space)

    def reset(self) -> npt.NDArray[Any]:
        return self.venv.reset()[:, self.indices]

    def step_wait(self) -> Any:
        obs, rewards, dones, infos = self.venv.step_wait()
        for info in infos:
            if "terminal_observation" in info:
                info["terminal_observation"] = np.asarray(info["terminal_observation"])[self.indices]
        return obs[:, self.indices], rewards, dones, infos
