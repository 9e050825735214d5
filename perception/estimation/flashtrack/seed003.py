"""Seed 003's tracker behind the flash-tracker interface: :class:`Seed003Tracker`."""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt

from perception.config import FlashLidarConfig, ICPConfig
from perception.estimation.flashtrack.base import check_frame, frame_time
from perception.estimation.linetrack import LineRollTracker, LineTrackInfo
from perception.estimation.registration import RegistrationResult
from perception.sensing.pointcloud import PointCloud
from perception.targets import TargetModel

FloatArray = npt.NDArray[np.float64]

__all__ = ["Seed003Tracker"]


class Seed003Tracker:
    """Zhao, Xu and Bo's method (a :class:`~.base.FlashTracker`): the frame's depth map, LSD lines
    matched with the previous frame's for a roll prior, the cloud simplified on a voxel grid that
    grows as the range shrinks, point-to-point ICP from the prior
    (:class:`perception.estimation.linetrack.LineRollTracker`, whose docstrings give the
    equations and our deviations). The covariance is ICP's Cramer-Rao bound on the simplified
    cloud, far tighter than the method's error (NEES ~1,600 on the tests' tumbling CYGNSS, 6 for
    a consistent one): point-to-point ICP stops on the seed's rule short of the minimum, and the
    voxel grid's centroids are biased. Use it as a weight, not as an integrity bound.

    Args:
        target: the target model.
        flash: the flash LiDAR (field of view and pixel grid of the depth map, range noise);
            default :class:`~perception.config.FlashLidarConfig`.
        q_lines: ``Q``, longest lines matched per frame.
        d_model: ``d_m`` of eq. (16), the grid size at the initial range [m].
        icp_config: ICP settings; default the seed's point-to-point
            (:func:`perception.estimation.linetrack.seed003_icp_config`). Bench seed003's
            ``Lines+P2Plane`` row is ``ICPConfig(max_correspondence_m=2.0)``.
        **options: further keywords of :class:`~perception.estimation.linetrack.LineRollTracker`
            (``alpha``, ``threshold``, ``floor_gray``, ``centroid_prior``, ``roll_outlier_deg``,
            ``model_seed``).

    Example:
        >>> import numpy as np
        >>> from perception.geometry import make_T
        >>> from perception.sensing.sensors import FlashLidar
        >>> from perception.targets import load_target
        >>> target, lidar, rng = load_target("cygnss"), FlashLidar(), np.random.default_rng(0)
        >>> T = make_T(None, [0.0, 0.0, 30.0])
        >>> tracker = Seed003Tracker(target)
        >>> _ = tracker.init(lidar.capture(target, T, rng), T)
        >>> res = tracker.track(lidar.capture(target, T, rng, t=0.2))
        >>> bool(abs(res.T_sensor_target[2, 3] - 30.0) < 0.01)
        True
    """

    def __init__(
        self,
        target: TargetModel,
        *,
        flash: FlashLidarConfig | None = None,
        q_lines: int = 10,
        d_model: float = 0.03,
        icp_config: ICPConfig | None = None,
        **options: Any,
    ) -> None:
        self.lines = LineRollTracker(
            target, q_lines=q_lines, d_model=d_model, flash=flash, icp_config=icp_config, **options
        )

    @property
    def T_sensor_target(self) -> FloatArray | None:
        return self.lines.T_sensor_target

    @property
    def info(self) -> LineTrackInfo | None:
        """What the last call did: roll prior, lines, grid size, points used, timings."""
        return self.lines.last

    def reset(self) -> None:
        self.lines.reset()

    def init(self, frame: PointCloud, T_sensor_target: npt.ArrayLike) -> RegistrationResult:
        """Start on ``frame`` from ``T_sensor_target`` (lines stored, ICP on the cloud simplified
        with ``d_model``)."""
        self.lines.reset()
        return self.lines.init(check_frame(frame), T_sensor_target)

    def track(
        self, frame: PointCloud, prediction: npt.ArrayLike | None = None, t: float | None = None
    ) -> RegistrationResult:
        """Seed 003 Algorithm 1 on ``frame``; a ``prediction`` replaces the roll and centroid
        priors (see :meth:`LineRollTracker.update`)."""
        frame = check_frame(frame)
        frame_time(frame, t)
        if self.lines.T_sensor_target is None:
            raise RuntimeError("Seed003Tracker.track called before init(frame, T_sensor_target)")
        return self.lines.update(frame, prediction)
