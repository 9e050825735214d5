"""The interface every flash tracker has (:class:`FlashTracker`) and what the trackers share: the
frame checks, the frame's time, its centroid and the constant-motion prediction."""

from __future__ import annotations

import math
from typing import Protocol, runtime_checkable

import numpy as np
import numpy.typing as npt

from perception.config import FlashLidarConfig
from perception.estimation.registration import RegistrationResult
from perception.sensing.pointcloud import PointCloud

FloatArray = npt.NDArray[np.float64]

__all__ = [
    "FlashTracker",
    "centroid",
    "flash_range_sigma",
    "frame_time",
    "repeat_motion",
    "stratified_subset",
]

IndexArray = npt.NDArray[np.intp]


@runtime_checkable
class FlashTracker(Protocol):
    """A pose tracker on flash LiDAR frames (:meth:`perception.sensing.sensors.FlashLidar.capture`).

    It starts from a known pose (:meth:`init`: acquisition's, or truth in a benchmark) and then
    follows the target frame by frame (:meth:`track`), each call returning the pose with its
    (6, 6) covariance in :class:`~perception.estimation.registration.RegistrationResult`'s
    convention (position of the target origin [m^2], then attitude about the sensor axes
    [rad^2]) and ``time_s`` covering the whole call.
    """

    def init(self, frame: PointCloud, T_sensor_target: npt.ArrayLike) -> RegistrationResult:
        """Start tracking on ``frame`` from ``T_sensor_target`` (4, 4), forgetting any earlier
        track; returns the first frame's estimate."""
        ...

    def track(
        self, frame: PointCloud, prediction: npt.ArrayLike | None = None, t: float | None = None
    ) -> RegistrationResult:
        """Estimate the pose in ``frame``, from ``prediction`` (4, 4) (e.g. a pipeline filter's,
        at the frame's time) or, when None, from the tracker's own motion model; ``t`` [s] is
        the frame's time (default ``frame.t_start``)."""
        ...

    def reset(self) -> None:
        """Forget the track (loss of track, planned restart); :meth:`init` starts a new one."""
        ...

    @property
    def T_sensor_target(self) -> FloatArray | None:
        """The current estimate (None before :meth:`init` and after :meth:`reset`)."""
        ...


def flash_range_sigma(flash: FlashLidarConfig) -> float:
    """1-sigma range error [m] of a flash LiDAR's error model (uniform: ``d / sqrt(3)``).

    The same number as :attr:`perception.sensing.sensors.FlashLidar.range_sigma`, without
    building the sensor's pixel grid.
    """
    d = flash.range_error_m
    return d / math.sqrt(3.0) if flash.error_model == "uniform" else d


def check_frame(frame: PointCloud, organised: bool = False) -> PointCloud:
    """``frame`` if it is a :class:`PointCloud` (with its organised grid when ``organised``)."""
    if not isinstance(frame, PointCloud):
        # a ValueError, as for every other bad argument of the estimators
        raise ValueError(f"frame is a {type(frame).__name__}; expected a PointCloud")  # noqa: TRY004
    if organised and frame.valid_mask is None:
        raise ValueError("frame has no organised grid (valid_mask); expected a flash frame")
    return frame


def frame_time(frame: PointCloud, t: float | None) -> float:
    """``t`` [s], or the frame's start time when None; finite."""
    out = float(frame.t_start) if t is None else float(t)
    if not math.isfinite(out):
        raise ValueError(f"t={t!r}; expected a finite time [s]")
    return out


def centroid(frame: PointCloud) -> FloatArray | None:
    """Mean of the frame's points [m] (None for an empty frame)."""
    return frame.points.mean(axis=0) if len(frame) else None


def repeat_motion(T_before: FloatArray, T_last: FloatArray) -> FloatArray:
    """The last frame-to-frame motion repeated in the target's frame,
    ``T_last (T_before^-1 T_last)``: a constant roll rate and a constant closing speed along the
    roll axis are predicted exactly (frames at a steady rate)."""
    return T_last @ np.linalg.solve(T_before, T_last)


def stratified_subset(n_total: int, n: int, rng: np.random.Generator) -> IndexArray | None:
    """Indices of ``n`` of ``n_total`` points, one drawn at random from each of ``n`` runs of
    consecutive points of (nearly) equal length (None: ``n >= n_total``, every point).

    A flash frame's points are in the pixel grid's row-major order, so the runs are strips of
    the image: the subset covers the target evenly (the same number of points on every strip of
    rows, none clumped), where a uniform draw leaves holes and clusters that thin the lever arm
    of the rotation. Each point is drawn with probability ``1 / len(its run)``, within one of
    ``n / n_total`` (runs are ``floor`` or ``ceil`` of ``n_total / n`` long). Costs ``n`` random
    numbers, no sort.

    Args:
        n_total: points in the frame.
        n: points wanted (>= 1).
        rng: the generator of the draw.

    Returns:
        (n,) strictly increasing indices into the frame's points, or None.
    """
    if n >= n_total:
        return None
    bounds = (np.arange(n + 1) * (n_total / n)).astype(np.intp)  # run k: [bounds[k], bounds[k+1])
    bounds[-1] = n_total
    lo, width = bounds[:-1], np.diff(bounds)
    return lo + (rng.random(n) * width).astype(np.intp)
