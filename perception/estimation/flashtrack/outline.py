"""The project's best flash tracker: point-to-plane ICP matched along the rays, the frame's outline
and a pose filter (:class:`OutlineFlashTracker`)."""

from __future__ import annotations

import dataclasses
import time
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt

from perception.config import FlashLidarConfig, ICPConfig
from perception.estimation.flashtrack.base import (
    centroid,
    check_frame,
    frame_time,
    stratified_subset,
)
from perception.estimation.flashtrack.icp import IcpFlashTracker, IndexArray, Motion, Sampling
from perception.estimation.registration import RegistrationResult, icp
from perception.estimation.silhouette import FlashGeometry, refine_pose
from perception.geometry import check_rigid
from perception.sensing.pointcloud import PointCloud
from perception.targets import TargetModel

if TYPE_CHECKING:
    from perception.pipeline.filter import PoseFilter

FloatArray = npt.NDArray[np.float64]

__all__ = ["OutlineFlashTracker"]

#: The filter's error state is (dp, dv, dtheta, domega): the pose's rows and columns in it.
_POSE_STATES = np.r_[0:3, 6:9]


class OutlineFlashTracker(IcpFlashTracker):
    """Point-to-plane ICP along the measured rays, refined with the frame's outline, inside a pose
    filter: bench seed003's ``P2Plane+EKF+outline`` (``filtered=False``: ``P2Plane+CV+outline``).

    Per frame, on a stratified subset of ``n_points`` (one point per strip of pixels,
    :func:`~.base.stratified_subset`):

    1. ICP (:func:`perception.estimation.registration.icp`, each point matched to the face its
       measured ray crosses) from the prediction, on a sparser stratified subset of those
       (``icp_points``): it only brings the pose into the refinement's basin, and its cost is
       most of a frame's on the whole subset;
    2. :func:`perception.estimation.silhouette.refine_pose`: one Gauss-Newton on the subset's
       surface rows and on the frame's *outline* (valid pixels next to invalid ones; the model's
       outline must cross between them). Seen face-on, the CYGNSS bus and wings are plates that
       give point-to-plane ICP next to no information about the in-plane position and the roll
       (its Cramer-Rao bound flags ``tx, ty, rz``); the outline fixes them to the pixel
       quantisation of the edges;
    3. with ``filtered``: :class:`perception.pipeline.filter.PoseFilter` (constant velocity and
       rate) fuses the refined pose with the refinement's covariance, and its posterior is the
       estimate. A single frame cannot place an edge that runs with the pixel grid better than
       a pixel (all edges of a box at roll 0, +-45, +-90 deg; 37 mm at 53 m); the refinement's
       covariance counts such a group of parallel edges once, so on those frames the filter leans
       on its prediction. The filter starts on the first :meth:`track` (from the two first
       poses: their difference as velocity and rate); from the second on, the refinement starts
       from the filter's prediction and ICP is skipped (the surface rows take it from there).

    The returned covariance is the refinement's information inverted
    (:func:`~perception.estimation.registration.covariance_from_information`) or, once the filter
    runs, the filter's posterior over the pose; :attr:`last_measurement` keeps the frame's own
    refinement. A :meth:`track` with a ``prediction`` starts from it instead of the filter's (the
    filter still fuses the result).

    Args:
        target: the target model.
        flash: the flash LiDAR (pixel rays, validity rule, range noise); default
            :class:`~perception.config.FlashLidarConfig`.
        icp_config: ICP settings; default point-to-plane matched along the rays.
        n_points: points per frame for the surface rows (None: all); the refinement's
            covariance is the information of exactly these rows and the outline's.
        icp_points: of those, points for ICP (None: all ``n_points``). On bench seed003 and the
            tests' tumbling CYGNSS, 300 leave the refined pose as accurate as 2,000 (ICP's
            answer is only the refinement's start) at a fifth of ICP's cost.
        max_pairs: outline pixel pairs per frame at most (an even stride over the outline). The
            pairs along one edge share its pixel quantisation, which the refinement counts once
            per group of parallel edges: 600 place the outline as well as 1,500 did from 60 m
            to docking, and the close frames' outline runs to thousands of pairs.
        filtered: run the pose filter.
        motion: the prediction without the filter (:class:`~.icp.IcpFlashTracker`).
        process_noise_accel: the filter's white acceleration [m/s^2/sqrt(Hz)]; default the
            pipeline's (:class:`~perception.config.PipelineConfig`).
        process_noise_angacc: its white angular acceleration [rad/s^2/sqrt(Hz)]; default the
            pipeline's.
        rng: the generator of the subsets (or a seed).
        model_seed: seed of the model's surface sampling.
        sampling: how the ``n_points`` are drawn (:class:`~.icp.IcpFlashTracker`).
        refine_options: further keywords of :func:`~perception.estimation.silhouette.refine_pose`.

    Example:
        >>> import numpy as np
        >>> from perception.geometry import make_T
        >>> from perception.sensing.sensors import FlashLidar
        >>> from perception.targets import load_target
        >>> target, lidar, rng = load_target("cygnss"), FlashLidar(), np.random.default_rng(0)
        >>> T = make_T(None, [0.0, 0.0, 30.0])
        >>> tracker = OutlineFlashTracker(target)
        >>> _ = tracker.init(lidar.capture(target, T, rng), T)
        >>> res = tracker.track(lidar.capture(target, T, rng, t=0.2))
        >>> bool(np.abs(res.T_sensor_target[:3, 3] - [0, 0, 30]).max() < 0.005)
        True
    """

    _needs_grid = True

    def __init__(
        self,
        target: TargetModel,
        *,
        flash: FlashLidarConfig | None = None,
        icp_config: ICPConfig | None = None,
        n_points: int | None = 2000,
        icp_points: int | None = 300,
        max_pairs: int = 600,
        filtered: bool = True,
        motion: Motion = "constant_velocity",
        process_noise_accel: float | None = None,
        process_noise_angacc: float | None = None,
        rng: np.random.Generator | int | None = None,
        model_seed: int = 0,
        sampling: Sampling = "stratified",
        refine_options: dict[str, Any] | None = None,
    ) -> None:
        super().__init__(
            target,
            flash=flash,
            icp_config=icp_config or ICPConfig(match_along_rays=True),
            n_points=n_points,
            motion=motion,
            rng=rng,
            model_seed=model_seed,
            sampling=sampling,
        )
        if int(max_pairs) < 1:
            raise ValueError(f"max_pairs={max_pairs}; expected >= 1 outline pair per frame")
        if icp_points is not None and int(icp_points) < 6:
            raise ValueError(f"icp_points={icp_points}; expected >= 6 points per frame or None")
        self.max_pairs = int(max_pairs)
        self.icp_points = None if icp_points is None else int(icp_points)
        self.geometry = FlashGeometry.from_config(self.flash)
        self.refine_options = dict(refine_options or {})
        self.filter: PoseFilter | None = None
        if filtered:
            self.filter = _pose_filter(process_noise_accel, process_noise_angacc)
        self.last_measurement: RegistrationResult | None = None
        self.rejected = 0  # measurements the filter's gate refused
        self._t = 0.0  # time of the last frame [s]

    def reset(self) -> None:
        super().reset()
        if self.filter is not None:
            self.filter.reset()
        self.last_measurement = None

    def init(self, frame: PointCloud, T_sensor_target: npt.ArrayLike) -> RegistrationResult:
        """Start on ``frame`` from ``T_sensor_target``: ICP and the outline refinement from it."""
        t = frame_time(check_frame(frame), None)
        res = super().init(frame, T_sensor_target)
        self._t = t
        return res

    def track(
        self, frame: PointCloud, prediction: npt.ArrayLike | None = None, t: float | None = None
    ) -> RegistrationResult:
        """One frame (see the class docstring and :class:`~.base.FlashTracker`)."""
        if self.filter is None or not self.filter.initialized:
            t0 = time.perf_counter()
            t_k = frame_time(check_frame(frame), t)
            T_prev = self._check_started().copy()
            res = super().track(frame, prediction, t)
            if self.filter is not None:
                self._start_filter(t_k, T_prev, res)
            self._t = t_k
            return dataclasses.replace(res, time_s=time.perf_counter() - t0)
        return self._track_filtered(frame, prediction, t)

    # ------------------------------------------------------------------ the steps
    def _measure(
        self, frame: PointCloud, idx: IndexArray | None, T0: FloatArray, with_icp: bool = True
    ) -> RegistrationResult:
        """ICP (unless ``with_icp`` is False) and the outline refinement on the subset ``idx``."""
        idx_all = np.arange(len(frame)) if idx is None else idx
        converged = True
        if with_icp:
            # ICP only brings the pose into the refinement's basin (its covariance is not
            # published): a sparser subset of the same points does that.
            sub = None if self.icp_points is None else stratified_subset(
                idx_all.size, self.icp_points, self.rng)
            idx_icp = idx_all if sub is None else idx_all[sub]
            res = icp(
                frame.points[idx_icp],
                self.model,
                T0,
                sigma=self.sigma,
                config=self.icp_config,
                directions=frame.directions[idx_icp],
            )
            T0, converged = res.T_sensor_target, res.converged
        ref = refine_pose(
            frame,
            self.target,
            self.model,
            T0,
            self.geometry,
            sigma=self.sigma,
            surface_idx=idx_all,
            max_pairs=self.max_pairs,
            **self.refine_options,
        )
        self.last_measurement = ref
        return dataclasses.replace(ref, converged=converged and ref.converged)

    def _start_filter(self, t: float, T_prev: FloatArray, res: RegistrationResult) -> None:
        """The filter from the two first poses: their difference as velocity and rate."""
        from scipy.spatial.transform import Rotation

        assert self.filter is not None
        T = res.T_sensor_target
        dt = max(t - self._t, 1e-9)
        omega = Rotation.from_matrix(T[:3, :3] @ T_prev[:3, :3].T).as_rotvec() / dt
        self.filter.initialize(
            t, T, res.covariance, velocity=(T[:3, 3] - T_prev[:3, 3]) / dt, omega=omega
        )

    def _track_filtered(
        self, frame: PointCloud, prediction: npt.ArrayLike | None, t: float | None
    ) -> RegistrationResult:
        t0 = time.perf_counter()
        assert self.filter is not None
        frame = check_frame(frame, organised=True)
        t_k = frame_time(frame, t)
        T0 = (
            self.filter.pose_at(t_k)
            if prediction is None
            else check_rigid(prediction, "prediction")
        )
        self._centroid = centroid(frame)
        meas = self._measure(frame, self._subset(frame), T0, with_icp=False)
        update = self.filter.update(t_k, meas.T_sensor_target, meas.covariance)
        reason = meas.reason
        if not update.accepted:
            self.rejected += 1
            reason = (
                f"the filter's gate refused the measurement (Mahalanobis^2 "
                f"{update.mahalanobis2:.3g}); the estimate is its prediction"
            )
        T = self.filter.T_sensor_target
        self._advance(T)
        self._t = t_k
        P = self.filter.target_state()[4][np.ix_(_POSE_STATES, _POSE_STATES)]
        return dataclasses.replace(
            meas,
            T_sensor_target=T,
            covariance=0.5 * (P + P.T),
            reason=reason,
            time_s=time.perf_counter() - t0,
        )


def _pose_filter(accel: float | None, angacc: float | None) -> PoseFilter:
    """The pipeline's pose filter with its default process noise unless given.

    Imported here, not at the top: :mod:`perception.pipeline` sits above the estimators and its
    package imports the pipeline, which may import these trackers (the filter module itself
    imports nothing above :mod:`perception.geometry`).
    """
    from perception.config import PipelineConfig
    from perception.pipeline.filter import PoseFilter

    pc = PipelineConfig()
    qa = pc.process_noise_accel if accel is None else float(accel)
    qw = pc.process_noise_angacc if angacc is None else float(angacc)
    return PoseFilter(qa**2, qw**2)
