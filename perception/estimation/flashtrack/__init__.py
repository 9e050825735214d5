"""Pose trackers on flash LiDAR frames (seed 003), one interface: :class:`FlashTracker`.

A flash frame (:meth:`perception.sensing.sensors.FlashLidar.capture`: every pixel at one instant,
an organised grid) is tracked frame to frame from a known pose::

    tracker = make_flash_tracker("p2plane+ekf+outline", target)
    tracker.init(first_frame, T_sensor_target)   # acquisition's pose (truth + error in a bench)
    for frame in frames:
        res = tracker.track(frame)               # or track(frame, prediction=T_pred, t=t)
        res.T_sensor_target, res.covariance      # (4, 4) and (6, 6)

Every call returns a :class:`~perception.estimation.registration.RegistrationResult`
(``T_sensor_target``, ``fitness``, ``inlier_rmse``, ``converged``, ``iterations``, ``covariance``
(6, 6) from the registration's information matrix or the tracker's filter, ``time_s`` of the
whole call). The trackers:

- :class:`Seed003Tracker`: the seed's method (depth map, LSD line roll prior, adaptive voxel grid,
  point-to-point ICP), around :class:`perception.estimation.linetrack.LineRollTracker`;
- :class:`IcpFlashTracker`: ICP from a prediction (the seed's point-to-point baseline on the whole
  cloud, or our point-to-plane on a uniform subset; last pose, centroid shift or constant
  velocity);
- :class:`OutlineFlashTracker`: the project's best, point-to-plane along the rays, the frame's
  outline and a pose filter (bench seed003: max ~0.1 deg / 5 mm from 60 m to 10 m on the tumbling
  CYGNSS, ~10-20 ms per frame).

:func:`make_flash_tracker` builds them by the names of bench seed003's rows
(:data:`FLASH_TRACKER_KINDS`). The modules: :mod:`.base` (the interface and shared steps),
:mod:`.icp`, :mod:`.outline`, :mod:`.seed003`, :mod:`.factory`. Import from here.
"""

from perception.estimation.flashtrack.base import (
    FlashTracker,
    flash_range_sigma,
    repeat_motion,
    stratified_subset,
)
from perception.estimation.flashtrack.factory import (
    BEST_FLASH_TRACKER,
    FLASH_TRACKER_KINDS,
    make_flash_tracker,
)
from perception.estimation.flashtrack.icp import MOTION_MODELS, SAMPLINGS, IcpFlashTracker
from perception.estimation.flashtrack.outline import OutlineFlashTracker
from perception.estimation.flashtrack.seed003 import Seed003Tracker

__all__ = [
    "BEST_FLASH_TRACKER",
    "FLASH_TRACKER_KINDS",
    "MOTION_MODELS",
    "SAMPLINGS",
    "FlashTracker",
    "IcpFlashTracker",
    "OutlineFlashTracker",
    "Seed003Tracker",
    "flash_range_sigma",
    "make_flash_tracker",
    "repeat_motion",
    "stratified_subset",
]
