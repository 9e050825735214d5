"""Fault and environment injection for the scanning sensor (all off by default).

- random dropouts: each sample is lost with ``dropout_prob``;
- spurious returns (sun glint off the target, stray light): each sample is replaced, with
  ``spurious_prob``, by a return at a random range around the target (uniform within +-50 % of the
  median range of the frame's genuine returns, or around the transition range when there are none);
- blackout: frames ``blackout_start_frame`` .. ``+ blackout_frames - 1`` return nothing;
- an occluder: a sphere in the sensor frame (an arm, a boom) that blocks rays and returns its own
  surface, flagged ``spurious`` because it is not the target.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from perception.config import FaultsConfig

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]

__all__ = ["OCCLUDER_REFLECTIVITY", "FaultInjector"]

#: Diffuse reflectivity of the occluder's surface.
OCCLUDER_REFLECTIVITY = 0.5


class FaultInjector:
    """Applies a :class:`~perception.config.FaultsConfig`; stateless apart from the config."""

    def __init__(self, config: FaultsConfig | None = None) -> None:
        self.config = config or FaultsConfig()

    @property
    def active(self) -> bool:
        """True when any per-sample fault (dropout, spurious) is enabled."""
        return self.config.dropout_prob > 0 or self.config.spurious_prob > 0

    def blackout(self, frame_index: int) -> bool:
        """True when frame ``frame_index`` falls inside the configured blackout."""
        c = self.config
        if c.blackout_start_frame is None or c.blackout_frames <= 0:
            return False
        return c.blackout_start_frame <= frame_index < c.blackout_start_frame + c.blackout_frames

    def draw(
        self, rng: np.random.Generator, n: int, genuine_ranges: FloatArray, fallback_range: float
    ) -> tuple[BoolArray, BoolArray, FloatArray]:
        """Per-sample faults for a frame of ``n`` samples.

        Args:
            rng: the generator.
            n: number of samples.
            genuine_ranges: (K,) ranges [m] of the frame's genuine returns.
            fallback_range: centre of the spurious ranges when there are no genuine returns [m].

        Returns:
            ``dropped`` (n,) bool, ``spurious`` (n,) bool and ``spurious_range`` (n,) [m].
        """
        if not self.active:
            return np.zeros(n, bool), np.zeros(n, bool), np.zeros(n)
        u = rng.random((n, 3))
        centre = float(np.median(genuine_ranges)) if genuine_ranges.size else fallback_range
        dropped = u[:, 0] < self.config.dropout_prob
        spurious = u[:, 1] < self.config.spurious_prob
        spurious_range = centre * (0.5 + u[:, 2])
        return dropped, spurious, spurious_range
