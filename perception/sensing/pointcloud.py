"""Point clouds produced by the sensors: measured points plus per-point metadata.

A :class:`PointCloud` is what leaves the sensor box: points in the sensor frame with the time of
each sample, the ranging subsystem that produced it, an intensity and the 1-sigma range noise of
its subsystem's model (used by ICP covariance). ``true_points`` and ``spurious`` are for debugging
and evaluation only; estimators must not read them. Flash frames also carry the organised grid.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import IntEnum

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]

__all__ = ["PointCloud", "Subsystem"]


class Subsystem(IntEnum):
    """Which ranging subsystem produced a point."""

    TRIANGULATION = 0
    TOF = 1
    FLASH = 2


@dataclass
class PointCloud:
    """One sensor frame.

    Attributes:
        points: (N, 3) float64 [m], sensor frame (+z boresight, +x right, +y down).
        times: (N,) float64 [s], absolute time of each sample.
        subsystem: (N,) int8, :class:`Subsystem` values.
        intensity: (N,) float64, return strength reflectivity * cos(incidence) of the footprint
            (0..1, range independent).
        sigma: (N,) float64 [m], 1-sigma range noise of each point under its subsystem's model.
        directions: (N, 3) float64, unit ray direction of each sample as reported by the sensor
            (sensor frame).
        true_points: (N, 3) float64 [m] or None; noise-free surface point of each sample at its
            sample time along the actual beam (evaluation only; NaN rows for stray-light returns).
        spurious: (N,) bool; stray-light or occluder returns, not on the target (evaluation only).
        organized: (rows, cols, 3) float64 [m] or None; flash grid with NaN at invalid pixels.
        valid_mask: (rows, cols) bool or None; valid pixels of ``organized`` (row-major order of
            ``points``).
        t_start: [s] start of the frame.
        t_end: [s] end of the frame.
    """

    points: FloatArray
    times: FloatArray
    subsystem: npt.NDArray[np.int8]
    intensity: FloatArray
    sigma: FloatArray
    directions: FloatArray
    true_points: FloatArray | None = None
    spurious: BoolArray | None = None
    organized: FloatArray | None = field(default=None, repr=False)
    valid_mask: BoolArray | None = field(default=None, repr=False)
    t_start: float = 0.0
    t_end: float = 0.0

    def __post_init__(self) -> None:
        self.points = np.asarray(self.points, dtype=np.float64).reshape(-1, 3)
        n = self.points.shape[0]

        def vec(name: str, value: npt.ArrayLike, dtype: type) -> np.ndarray:
            arr = np.asarray(value, dtype=dtype).reshape(-1)
            if arr.shape[0] != n:
                raise ValueError(f"PointCloud.{name} has {arr.shape[0]} entries; expected {n}")
            return arr

        self.times = vec("times", self.times, np.float64)
        self.subsystem = vec("subsystem", self.subsystem, np.int8)
        self.intensity = vec("intensity", self.intensity, np.float64)
        self.sigma = vec("sigma", self.sigma, np.float64)
        self.directions = np.asarray(self.directions, dtype=np.float64).reshape(-1, 3)
        if self.directions.shape[0] != n:
            raise ValueError(
                f"PointCloud.directions has {self.directions.shape[0]} rows; expected {n}"
            )
        self.spurious = (
            np.zeros(n, dtype=bool) if self.spurious is None else vec("spurious", self.spurious, bool)
        )
        if self.true_points is not None:
            self.true_points = np.asarray(self.true_points, dtype=np.float64).reshape(-1, 3)
            if self.true_points.shape[0] != n:
                raise ValueError(
                    f"PointCloud.true_points has {self.true_points.shape[0]} rows; expected {n}"
                )
        for name in ("points", "times", "intensity", "sigma", "directions"):
            if not np.all(np.isfinite(getattr(self, name))):
                raise ValueError(f"PointCloud.{name} has non-finite entries; expected finite values")
        if n and (self.subsystem.min() < 0 or self.subsystem.max() > max(Subsystem)):
            raise ValueError(
                f"PointCloud.subsystem values {np.unique(self.subsystem)}; expected Subsystem codes"
            )
        if not (np.isfinite(self.t_start) and np.isfinite(self.t_end)):
            raise ValueError(f"PointCloud t_start={self.t_start}, t_end={self.t_end}; expected finite")
        if (self.organized is None) != (self.valid_mask is None):
            raise ValueError("PointCloud.organized and valid_mask must be given together")
        if self.organized is not None and self.valid_mask is not None:
            self.organized = np.asarray(self.organized, dtype=np.float64)
            self.valid_mask = np.asarray(self.valid_mask, dtype=bool)
            if self.organized.ndim != 3 or self.organized.shape[2] != 3:
                raise ValueError(
                    f"PointCloud.organized has shape {self.organized.shape}; expected (rows, cols, 3)"
                )
            if self.valid_mask.shape != self.organized.shape[:2]:
                raise ValueError(
                    f"PointCloud.valid_mask has shape {self.valid_mask.shape}; expected "
                    f"{self.organized.shape[:2]}"
                )
            if int(self.valid_mask.sum()) != n:
                raise ValueError(
                    f"PointCloud.valid_mask marks {int(self.valid_mask.sum())} pixels; expected {n}"
                )

    # -- construction ----------------------------------------------------------------------------
    @classmethod
    def empty(cls, t: float = 0.0, t_end: float | None = None) -> PointCloud:
        """A cloud with zero points (right dtypes and shapes) for a frame starting at ``t`` [s]."""
        return cls(
            points=np.zeros((0, 3)),
            times=np.zeros(0),
            subsystem=np.zeros(0, dtype=np.int8),
            intensity=np.zeros(0),
            sigma=np.zeros(0),
            directions=np.zeros((0, 3)),
            true_points=np.zeros((0, 3)),
            spurious=np.zeros(0, dtype=bool),
            t_start=float(t),
            t_end=float(t if t_end is None else t_end),
        )

    # -- access ----------------------------------------------------------------------------------
    def __len__(self) -> int:
        return int(self.points.shape[0])

    @property
    def ranges(self) -> FloatArray:
        """(N,) distance of each point from the sensor origin [m]."""
        return np.linalg.norm(self.points, axis=1)

    def select(self, mask: npt.ArrayLike) -> PointCloud:
        """A new cloud with the points where ``mask`` (N,) bool or an index array selects.

        The organised grid is dropped (its pixels no longer match the points).
        """
        idx = np.asarray(mask)
        if idx.dtype == bool and idx.shape != (len(self),):
            raise ValueError(f"select mask has shape {idx.shape}; expected ({len(self)},)")
        return PointCloud(
            points=self.points[idx],
            times=self.times[idx],
            subsystem=self.subsystem[idx],
            intensity=self.intensity[idx],
            sigma=self.sigma[idx],
            directions=self.directions[idx],
            true_points=None if self.true_points is None else self.true_points[idx],
            spurious=None if self.spurious is None else self.spurious[idx],
            t_start=self.t_start,
            t_end=self.t_end,
        )

    def count(self, subsystem: Subsystem) -> int:
        """Number of points produced by ``subsystem``."""
        return int(np.count_nonzero(self.subsystem == int(subsystem)))
