"""The seed-003 tracker: :class:`LineRollTracker` (line roll prior, adaptive voxel grid,
point-to-point ICP; Algorithm 1 of the seed), what each step did (:class:`LineTrackInfo`) and
the seed's ICP settings (:func:`seed003_icp_config`)."""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from perception.config import FlashLidarConfig, ICPConfig
from perception.estimation.linetrack.frames import roll_about_boresight
from perception.estimation.linetrack.lines import (
    Lines,
    _make_detector,
    depth_map,
    detect_lines,
    match_lines,
    roll_variation,
)
from perception.estimation.registration import ModelCloud, RegistrationResult, icp, prepare_model
from perception.estimation.voxel import adaptive_voxel_size, voxel_downsample
from perception.geometry import check_rigid
from perception.sensing.pointcloud import PointCloud
from perception.targets import TargetModel

FloatArray = npt.NDArray[np.float64]

#: Seed 003 section 2.7: ICP stops when its mean squared error changes by less than this [m^2].
SEED_ICP_EPS_M2 = 1e-6


def seed003_icp_config(range_sigma_m: float = 0.01 / math.sqrt(3.0), **overrides: Any) -> ICPConfig:
    """Point-to-point ICP settings of seed 003 section 2.7: 100 iterations, stop when the mean
    squared error changes by less than 1e-6 m^2.

    :func:`~perception.estimation.registration.icp` measures that change relative to its noise-normalised
    cost, so the absolute threshold becomes ``1e-6 / range_sigma_m**2``.

    Args:
        range_sigma_m: 1-sigma range noise of the sensor [m] (default: uniform +-10 mm).
        **overrides: further :class:`~perception.config.ICPConfig` fields.
    """
    if not (math.isfinite(range_sigma_m) and range_sigma_m > 0):
        raise ValueError(f"range_sigma_m={range_sigma_m}; expected a finite sigma > 0 [m]")
    base: dict[str, Any] = {
        "method": "point_to_point",
        "max_iterations": 100,
        "residual_tol": SEED_ICP_EPS_M2 / range_sigma_m**2,
        # PCL's correspondence distance is unbounded by default; 2 m bridges the seed's 1 m of
        # closing per frame.
        "max_correspondence_m": 2.0,
    }
    base.update(overrides)
    return ICPConfig(**base)


@dataclass(frozen=True)
class LineTrackInfo:
    """What the last :meth:`LineRollTracker.update` (or ``init``) did.

    Attributes:
        delta_roll_rad: roll prior applied (0 when no line matched) [rad].
        roll_from_lines: True when ``delta_roll_rad`` came from matched lines.
        n_lines: lines detected in this frame.
        n_matches: matched line pairs with the previous frame.
        voxel_size_m: grid size ``d_k`` of eq. (16) [m].
        n_points_raw: points in the sensor cloud.
        n_points_used: points after voxel simplification (what ICP saw).
        time_lines_s: depth map + lines + matching [s].
        time_voxel_s: simplification [s].
        time_icp_s: ICP [s].
        time_s: the whole call [s].
    """

    delta_roll_rad: float
    roll_from_lines: bool
    n_lines: int
    n_matches: int
    voxel_size_m: float
    n_points_raw: int
    n_points_used: int
    time_lines_s: float
    time_voxel_s: float
    time_icp_s: float
    time_s: float


class LineRollTracker:
    """Seed-003 tracker: line-based roll prior + adaptive voxel grid + point-to-point ICP.

    Args:
        model: the target (body frame).
        q_lines: ``Q``, longest lines per frame entering the similarity matrix.
        alpha: weight of each similarity term, eq. (12).
        threshold: ``T_d``, minimum similarity of a line match.
        d_model: ``d_m`` of eq. (16), grid size at the initial range [m].
        icp_config: ICP settings; default :func:`seed003_icp_config` for the flash config's noise.
        flash: the flash LiDAR the clouds come from (field of view and pixel grid of the depth
            map); default :class:`~perception.config.FlashLidarConfig`.
        floor_gray: grey level of the farthest point in the depth map
            (:mod:`perception.estimation.linetrack`).
        centroid_prior: also predict the position, by the shift of the cloud's centroid since the
            previous frame (not in the seed, whose eq. (17) leaves the closing motion, 1 m per
            frame in its experiments, to ICP).
        roll_outlier_deg: line pairs whose orientation change is farther than this from the
            median change are left out of eq. (14) (None: every pair, as in the seed).
        model_seed: seed of the model's surface sampling.

    Example:
        >>> import numpy as np
        >>> from perception.geometry import make_T
        >>> from perception.sensing.sensors import FlashLidar
        >>> from perception.targets import load_target
        >>> target, lidar, rng = load_target("cygnss"), FlashLidar(), np.random.default_rng(0)
        >>> T0 = make_T(None, [0.0, 0.0, 30.0])
        >>> tracker = LineRollTracker(target)
        >>> _ = tracker.init(lidar.capture(target, T0, rng), T0)
        >>> res = tracker.update(lidar.capture(target, T0, rng))
        >>> bool(abs(res.T_sensor_target[2, 3] - 30.0) < 0.01)
        True
    """

    def __init__(
        self,
        model: TargetModel,
        *,
        q_lines: int = 10,
        alpha: float = 0.25,
        threshold: float = 0.8,
        d_model: float = 0.03,
        icp_config: ICPConfig | None = None,
        flash: FlashLidarConfig | None = None,
        floor_gray: int = 64,
        centroid_prior: bool = True,
        roll_outlier_deg: float | None = 2.0,
        model_seed: int = 0,
    ) -> None:
        if not isinstance(model, TargetModel):
            # a ValueError, as for every other bad argument here
            raise ValueError(f"model is a {type(model).__name__}; expected a TargetModel")  # noqa: TRY004
        if int(q_lines) < 1:
            raise ValueError(f"q_lines={q_lines}; expected >= 1")
        if not (math.isfinite(d_model) and d_model > 0):
            raise ValueError(f"d_model={d_model}; expected a finite grid size > 0 [m]")
        if not (math.isfinite(alpha) and alpha > 0):
            raise ValueError(f"alpha={alpha}; expected a finite weight > 0")
        if not (math.isfinite(threshold)):
            raise ValueError(f"threshold={threshold}; expected a finite similarity")
        self.model = model
        self.flash = flash or FlashLidarConfig()
        sigma = self.flash.range_error_m
        if self.flash.error_model == "uniform":
            sigma /= math.sqrt(3.0)
        self.range_sigma_m = max(sigma, 1e-4)
        self.icp_config = icp_config or seed003_icp_config(self.range_sigma_m)
        self.q_lines = int(q_lines)
        self.alpha = float(alpha)
        self.threshold = float(threshold)
        self.d_model = float(d_model)
        self.floor_gray = int(floor_gray)
        self.centroid_prior = bool(centroid_prior)
        if roll_outlier_deg is not None and not (
            math.isfinite(roll_outlier_deg) and roll_outlier_deg > 0
        ):
            raise ValueError(
                f"roll_outlier_deg={roll_outlier_deg}; expected an angle > 0 [deg] or None"
            )
        self.roll_outlier_rad = None if roll_outlier_deg is None else math.radians(roll_outlier_deg)
        self.model_cloud: ModelCloud = prepare_model(
            model, self.icp_config.model_points, seed=model_seed
        )
        self._detector = _make_detector()
        self._fov = tuple(math.radians(v) for v in self.flash.fov_deg)
        self._shape = (self.flash.rows, self.flash.cols)
        self._T: FloatArray | None = None
        self._lines: Lines | None = None
        self._centroid: FloatArray | None = None
        self._x_init = float("nan")
        self.last: LineTrackInfo | None = None

    @property
    def T_sensor_target(self) -> FloatArray | None:
        """The current pose estimate (None before :meth:`init`)."""
        return None if self._T is None else self._T.copy()

    @property
    def x_init(self) -> float:
        """``X_init`` of eq. (16): range along the boresight at initialisation [m]."""
        return self._x_init

    def lines_of(self, points: FloatArray) -> Lines:
        """Depth map (eq. 4) and lines (eqs. 5-7) of one cloud's points."""
        image, _ = depth_map(points, self._fov, self._shape, floor_gray=self.floor_gray)
        return detect_lines(image, detector=self._detector)

    def reset(self) -> None:
        """Forget the track (the pose, the last frame's lines and centroid); :meth:`init` starts
        a new one."""
        self._T = None
        self._lines = None
        self._centroid = None
        self._x_init = float("nan")
        self.last = None

    def _register(
        self, points: FloatArray, T_pred: FloatArray, voxel: float
    ) -> tuple[RegistrationResult, int, float, float]:
        t0 = time.perf_counter()
        sparse = voxel_downsample(points, voxel)
        t1 = time.perf_counter()
        res = icp(
            sparse, self.model_cloud, T_pred, sigma=self.range_sigma_m, config=self.icp_config
        )
        return res, int(sparse.shape[0]), t1 - t0, time.perf_counter() - t1

    def _failed(self, res: RegistrationResult) -> bool:
        # Too few points or correspondences; a run that hit max_iterations still has a pose.
        return not res.converged and res.n_inliers < max(self.icp_config.min_points, 6)

    def init(
        self, points_or_cloud: PointCloud | npt.ArrayLike, T_sensor_target: npt.ArrayLike
    ) -> RegistrationResult:
        """Start tracking on the first frame from an initial pose (acquisition or truth + error).

        The frame's lines are stored for the next match and ICP refines ``T_sensor_target`` on the
        cloud simplified with ``d_model``; ``X_init`` is the refined range along the boresight.

        Args:
            points_or_cloud: the first frame, a :class:`PointCloud` or (N, 3) points [m], sensor
                frame.
            T_sensor_target: (4, 4) initial pose.

        Returns:
            The ICP result on the first frame (its pose becomes the tracker's state when ICP
            succeeded, otherwise the given pose is kept).
        """
        t0 = time.perf_counter()
        T0 = check_rigid(T_sensor_target, "T_sensor_target")
        if not T0[2, 3] > 0:
            raise ValueError(
                f"T_sensor_target has z = {T0[2, 3]} m; expected the target in front of the sensor"
            )
        points = _points_of(points_or_cloud)
        self._lines = self.lines_of(points)
        self._centroid = _centroid(points)
        t_lines = time.perf_counter() - t0
        res, n_used, t_vox, t_icp = self._register(points, T0, self.d_model)
        self._T = T0.copy() if self._failed(res) else res.T_sensor_target.copy()
        self._x_init = float(self._T[2, 3]) if self._T[2, 3] > 0 else float(T0[2, 3])
        total = time.perf_counter() - t0
        self.last = LineTrackInfo(
            0.0,
            False,
            len(self._lines),
            0,
            self.d_model,
            points.shape[0],
            n_used,
            t_lines,
            t_vox,
            t_icp,
            total,
        )
        return dataclasses.replace(res, time_s=total)

    def update(
        self, cloud: PointCloud | npt.ArrayLike, prediction: npt.ArrayLike | None = None
    ) -> RegistrationResult:
        """Track one frame (seed 003 Algorithm 1).

        Args:
            cloud: the current frame, a :class:`PointCloud` or (N, 3) points [m], sensor frame.
            prediction: (4, 4) pose to start ICP from instead of the roll and centroid priors
                (e.g. a pipeline filter's, which already carries the roll); the frame's lines
                are still detected and kept for the next match.

        Returns:
            The ICP result from the roll-predicted pose (or ``prediction``); ``time_s`` covers
            the whole step. On an ICP failure the tracker keeps the predicted pose.
        """
        if self._T is None or self._lines is None:
            raise RuntimeError("LineRollTracker.update called before init(points, T_sensor_target)")
        t0 = time.perf_counter()
        points = _points_of(cloud)
        lines = self.lines_of(points)
        matches = match_lines(self._lines, lines, self.alpha, self.threshold, self.q_lines)
        droll = roll_variation(self._lines, lines, matches, max_deviation_rad=self.roll_outlier_rad)
        centroid = _centroid(points)
        if prediction is not None:
            T_pred = check_rigid(prediction, "prediction").copy()
        else:
            T_pred = roll_about_boresight(self._T, droll if droll is not None else 0.0)
            if self.centroid_prior and self._centroid is not None and centroid is not None:
                T_pred[:3, 3] += centroid - self._centroid
        self._lines = lines
        self._centroid = centroid
        t_lines = time.perf_counter() - t0
        x_prev = float(self._T[2, 3]) if self._T[2, 3] > 0 else self._x_init
        voxel = adaptive_voxel_size(self.d_model, self._x_init, x_prev)
        res, n_used, t_vox, t_icp = self._register(points, T_pred, voxel)
        self._T = T_pred if self._failed(res) else res.T_sensor_target.copy()
        total = time.perf_counter() - t0
        self.last = LineTrackInfo(
            0.0 if droll is None else droll,
            droll is not None,
            len(lines),
            len(matches),
            voxel,
            points.shape[0],
            n_used,
            t_lines,
            t_vox,
            t_icp,
            total,
        )
        return dataclasses.replace(res, time_s=total)


def _centroid(points: FloatArray) -> FloatArray | None:
    return points.mean(axis=0) if points.shape[0] else None


def _points_of(points_or_cloud: PointCloud | npt.ArrayLike) -> FloatArray:
    if isinstance(points_or_cloud, PointCloud):
        return points_or_cloud.points
    p = np.asarray(points_or_cloud, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"points have shape {p.shape}; expected (N, 3) [m] or a PointCloud")
    return p[np.all(np.isfinite(p), axis=1)]
