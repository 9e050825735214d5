"""ICP on flash frames, frame to frame: :class:`IcpFlashTracker` (the seed's point-to-point
baseline on the whole cloud, or our point-to-plane ICP on a uniform subset from a predicted
pose)."""

from __future__ import annotations

import dataclasses
import time
from typing import Literal

import numpy as np
import numpy.typing as npt

from perception.config import FlashLidarConfig, ICPConfig
from perception.estimation.flashtrack.base import (
    centroid,
    check_frame,
    flash_range_sigma,
    frame_time,
    IndexArray,
    repeat_motion,
    stratified_subset,
)
from perception.estimation.registration import ModelCloud, RegistrationResult, icp, prepare_model
from perception.geometry import check_rigid
from perception.sensing.pointcloud import PointCloud
from perception.targets import TargetModel

FloatArray = npt.NDArray[np.float64]

__all__ = ["MOTION_MODELS", "SAMPLINGS", "IcpFlashTracker", "Motion", "Sampling"]

Motion = Literal["previous", "centroid", "constant_velocity"]
MOTION_MODELS: tuple[str, ...] = ("previous", "centroid", "constant_velocity")
Sampling = Literal["uniform", "stratified"]
SAMPLINGS: tuple[str, ...] = ("uniform", "stratified")


class IcpFlashTracker:
    """ICP on each flash frame from a predicted pose (a :class:`~.base.FlashTracker`).

    Per frame: a random subset of the frame's points (``n_points``, drawn as ``sampling`` says;
    TriDAR-like sparse sensing, the cost of ICP bounded whatever the range), ICP
    (:func:`perception.estimation.registration.icp`) from the prediction, and the result as the
    new estimate (ICP's Cramer-Rao covariance with it). The measured rays go to ICP when it
    matches along them (``icp_config.match_along_rays``); otherwise it takes each point's ray
    from the point itself. The covariance is consistent when ICP reaches the minimum (matched
    along the rays from a constant-velocity prediction: NEES ~6 on the tests' tumbling CYGNSS)
    and optimistic when it stops in a direction the frame barely constrains (the in-plane
    position of a face-on plate, from the centroid prediction: NEES ~100).

    Args:
        target: the target model (body frame).
        flash: the flash LiDAR the frames come from (its range noise); default
            :class:`~perception.config.FlashLidarConfig`.
        icp_config: ICP settings; default :class:`~perception.config.ICPConfig` (point-to-plane).
        n_points: points per frame given to ICP (None: all of them).
        sampling: how the subset is drawn: ``"uniform"`` (any ``n_points`` of the frame, equally
            likely) or ``"stratified"`` (one from each of ``n_points`` runs of the frame's
            row-major pixel order, :func:`~.base.stratified_subset`: even cover of the target).
        motion: the prediction when :meth:`track` gets none: ``"previous"`` (the last estimate:
            the seed's baseline), ``"centroid"`` (the last estimate moved by the shift of the
            frame's centroid since the previous frame: the flash frames of seed 003 close in by
            1 m per frame, twice ICP's default gate) or ``"constant_velocity"`` (the last
            frame-to-frame motion repeated, :func:`~.base.repeat_motion`, what the pipeline's
            filter supplies; ``"centroid"`` on the first frame after :meth:`init`).
        rng: the generator of the subsets (or a seed); default ``np.random.default_rng(0)``.
        model_seed: seed of the model's surface sampling.

    Example:
        >>> import numpy as np
        >>> from perception.geometry import make_T
        >>> from perception.sensing.sensors import FlashLidar
        >>> from perception.targets import load_target
        >>> target, lidar, rng = load_target("cygnss"), FlashLidar(), np.random.default_rng(0)
        >>> T = make_T(None, [0.0, 0.0, 30.0])
        >>> tracker = IcpFlashTracker(target)
        >>> _ = tracker.init(lidar.capture(target, T, rng), T)
        >>> res = tracker.track(lidar.capture(target, T, rng, t=0.2))
        >>> bool(abs(res.T_sensor_target[2, 3] - 30.0) < 0.01), res.covariance.shape
        (True, (6, 6))
    """

    def __init__(
        self,
        target: TargetModel,
        *,
        flash: FlashLidarConfig | None = None,
        icp_config: ICPConfig | None = None,
        n_points: int | None = 2000,
        motion: Motion = "centroid",
        rng: np.random.Generator | int | None = None,
        model_seed: int = 0,
        sampling: Sampling = "uniform",
    ) -> None:
        if not isinstance(target, TargetModel):
            # a ValueError, as for every other bad argument here
            raise ValueError(f"target is a {type(target).__name__}; expected a TargetModel")  # noqa: TRY004
        if n_points is not None and int(n_points) < 6:
            raise ValueError(f"n_points={n_points}; expected >= 6 points per frame or None (all)")
        if motion not in MOTION_MODELS:
            raise ValueError(f"motion={motion!r}; expected one of {list(MOTION_MODELS)}")
        if sampling not in SAMPLINGS:
            raise ValueError(f"sampling={sampling!r}; expected one of {list(SAMPLINGS)}")
        self.target = target
        self.flash = flash or FlashLidarConfig()
        self.icp_config = icp_config or ICPConfig()
        self.sigma = flash_range_sigma(self.flash)
        self.n_points = None if n_points is None else int(n_points)
        self.motion: Motion = motion
        self.sampling: Sampling = sampling
        self.rng = (
            rng
            if isinstance(rng, np.random.Generator)
            else np.random.default_rng(0 if rng is None else rng)
        )
        self.model: ModelCloud = prepare_model(
            target, self.icp_config.model_points, seed=model_seed
        )
        self._T: FloatArray | None = None
        self._T_before: FloatArray | None = None  # the estimate before _T (constant velocity)
        self._centroid: FloatArray | None = None

    # ------------------------------------------------------------------ FlashTracker
    @property
    def T_sensor_target(self) -> FloatArray | None:
        return None if self._T is None else self._T.copy()

    def reset(self) -> None:
        self._T = self._T_before = self._centroid = None

    def init(self, frame: PointCloud, T_sensor_target: npt.ArrayLike) -> RegistrationResult:
        """Start on ``frame`` from ``T_sensor_target``: ICP from it."""
        t0 = time.perf_counter()
        frame = check_frame(frame, organised=self._needs_grid)
        T0 = check_rigid(T_sensor_target, "T_sensor_target")
        self.reset()
        self._centroid = centroid(frame)
        res = self._measure(frame, self._subset(frame), T0)
        self._T = res.T_sensor_target.copy()
        return dataclasses.replace(res, time_s=time.perf_counter() - t0)

    def track(
        self, frame: PointCloud, prediction: npt.ArrayLike | None = None, t: float | None = None
    ) -> RegistrationResult:
        """ICP on ``frame`` from ``prediction``, or from the motion model's."""
        t0 = time.perf_counter()
        frame = check_frame(frame, organised=self._needs_grid)
        frame_time(frame, t)
        T0 = self._start(frame, prediction)
        res = self._measure(frame, self._subset(frame), T0)
        self._advance(res.T_sensor_target)
        return dataclasses.replace(res, time_s=time.perf_counter() - t0)

    # ------------------------------------------------------------------ the steps
    _needs_grid = False  # the outline tracker reads the frame's organised grid

    def _check_started(self) -> FloatArray:
        if self._T is None:
            raise RuntimeError(
                f"{type(self).__name__}.track called before init(frame, T_sensor_target)"
            )
        return self._T

    def predict(self, frame: PointCloud) -> FloatArray:
        """The pose the motion model predicts for ``frame`` (no state change)."""
        T = self._check_started()
        if self.motion == "constant_velocity" and self._T_before is not None:
            return repeat_motion(self._T_before, T)
        T_pred = T.copy()
        c = centroid(frame)
        if self.motion != "previous" and c is not None and self._centroid is not None:
            T_pred[:3, 3] += c - self._centroid
        return T_pred

    def _start(self, frame: PointCloud, prediction: npt.ArrayLike | None) -> FloatArray:
        """The pose ICP starts from; moves the centroid on to this frame's."""
        self._check_started()
        T0 = self.predict(frame) if prediction is None else check_rigid(prediction, "prediction")
        self._centroid = centroid(frame)
        return T0

    def _advance(self, T_new: FloatArray) -> None:
        self._T_before, self._T = self._T, T_new.copy()

    def _subset(self, frame: PointCloud) -> IndexArray | None:
        """Indices of this frame's random subset (None: every point)."""
        n = len(frame)
        if self.n_points is None or n <= self.n_points:
            return None
        if self.sampling == "stratified":
            return stratified_subset(n, self.n_points, self.rng)
        return self.rng.choice(n, self.n_points, replace=False)

    def _measure(
        self, frame: PointCloud, idx: IndexArray | None, T0: FloatArray
    ) -> RegistrationResult:
        """ICP on the subset ``idx`` of ``frame`` from ``T0``."""
        points = frame.points if idx is None else frame.points[idx]
        directions = None
        if self.icp_config.match_along_rays:
            directions = frame.directions if idx is None else frame.directions[idx]
        return icp(
            points, self.model, T0, sigma=self.sigma, config=self.icp_config, directions=directions
        )
