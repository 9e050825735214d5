"""The flash-LiDAR pipeline: seed 003's sensor in the TriDAR box's modes, filter and integrity.

:class:`FlashPipeline` is :class:`~perception.pipeline.tridar.TriDAR` with the flash LiDAR of seed
003 (:class:`~perception.sensing.sensors.FlashLidar`, ``MissionConfig.flash``) in place of the
scanning sensor, so a scanning and a flash sensor can be compared closed loop on the same runs
(``perception="flash"`` in the environment):

* **bearing** (beyond ``bearing_to_search_range_m``): the centroid of the frame's returns, as
  for the scanning sensor, on a subset of ``search_points`` of them;
* **search**: PAH (and reacquisition from a lost track's prediction, or from an external seed) on
  a random subset of ``search_points`` returns of the organised frame: PAH was built for sparse
  scans, and a few thousand returns over the target carry its polygons;
* **tracking**: the flash tracker (:func:`~perception.estimation.flashtrack.make_flash_tracker`,
  ``p2plane+cv+outline`` by default: point-to-plane ICP matched along the rays with the outline
  refinement, its own covariance consistent (NEES ~6), no filter of its own, since the pipeline's
  filter is the one that predicts) from the filter's prediction, on a stratified subset of the
  frame (a bounded cost per frame whatever the range); a new track (acquisition,
  reacquisition) starts the tracker afresh on the acquired pose. The filter's gate, the
  restarts, the twin monitor (on a random subset of :data:`TWIN_POINTS` returns), the slide
  monitor and the integrity rule are the TriDAR pipeline's.

A flash frame is taken at one instant (no scan distortion, nothing to de-skew); the sensor
faults of ``sensor.faults`` belong to the scanning sensor and are not applied.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt

from perception.config import FlashLidarConfig, MissionConfig
from perception.estimation.flashtrack import make_flash_tracker
from perception.numeric import median
from perception.pipeline.publish import tof_share
from perception.pipeline.state import Mode, TruthScene
from perception.pipeline.tracking import TrackingMode
from perception.pipeline.tridar import TriDAR
from perception.sensing.pointcloud import PointCloud
from perception.sensing.sensors import FlashLidar
from perception.targets import TargetModel

FloatArray = npt.NDArray[np.float64]

__all__ = ["TWIN_POINTS", "FlashPipeline", "FlashSensor"]

#: Returns of a tracking frame the twin monitor scores its alternatives on and polishes with
#: ICP (every ``symmetry_check_period_s``): the CYGNSS's twin is a half turn off, which 1,000
#: returns over the target tell apart at half the cost of 2,000.
TWIN_POINTS = 1000


class FlashSensor:
    """The flash LiDAR behind the pipeline's scanning interface (a scan pattern means nothing to
    a sensor that lights the whole field at once).

    Args:
        config: the flash LiDAR's configuration.
    """

    def __init__(self, config: FlashLidarConfig) -> None:
        self.flash = FlashLidar(config)
        self.config = config
        self.frame_counter = 0
        self.transition_range_m = 0.0  # one subsystem: no triangulation range

    @property
    def fov_rad(self) -> FloatArray:
        """(2,) full field of view (az, el) [rad]."""
        return np.radians(np.asarray(self.config.fov_deg, dtype=np.float64))

    def scan(self, target: TargetModel, T_sensor_target: FloatArray, pattern: Any,
             rng: np.random.Generator, motion: Any = None, t0: float = 0.0, frame_index: int = 0) -> PointCloud:
        """One flash frame at ``t0`` [s] (``pattern``, ``motion`` and ``frame_index`` unused)."""
        del pattern, motion, frame_index
        self.frame_counter += 1
        return self.flash.capture(target, T_sensor_target, rng, t=t0)


class FlashTrackingMode(TrackingMode):
    """Tracking on flash frames with the flash tracker from the filter's prediction."""

    def frame(self, scene: TruthScene | PointCloud, t: float) -> None:
        tri = self.tri
        assert isinstance(tri, FlashPipeline)
        f = tri.filter
        cloud = self.take(scene, t, None)
        if cloud is None:
            return
        t_ref = float(cloud.t_start)
        T_pred = f.pose_at(t_ref)
        tracker = tri.flash_tracker
        if tri.n_updates <= 1 or tracker.T_sensor_target is None:
            tracker.reset()  # a new track: the tracker starts on the acquired pose
            res = tracker.init(cloud, T_pred)
        else:
            res = tracker.track(cloud, prediction=T_pred, t=t_ref)
        res = tri.slides.apply(cloud.points, cloud, res, t_ref, tri.pc.icp, tri.n_updates)
        tri.last_result = res
        tri.stats.registration_time_s.append(res.time_s)
        expected = max(median(cloud.sigma), tri.pc.measurement_floor_m)
        share = tof_share(cloud.subsystem)
        verdict = tri.logic.judge(res.converged, res.fitness, res.inlier_rmse, expected,
                                  res.T_sensor_target, None)
        if verdict.good:
            verdict = self._update(t_ref, res, expected, verdict, share)
        if verdict.good and tri.n_updates > 0:
            sub = tri.subset(cloud, tri.twin_points)
            tri.twins.monitor(sub.points, sub, res, t_ref, tri.pc.icp)
            if tri.slides.switch(cloud.points, cloud, t_ref):
                tracker.reset()  # the tracker starts again on the moved track's pose
        if self.conclude(cloud, cloud.points, t, t_ref, res, verdict, share):
            tracker.reset()


class FlashPipeline(TriDAR):
    """The TriDAR pipeline on flash frames (module docstring); ``step`` as :class:`TriDAR`'s.

    Args:
        config: the mission configuration (``flash`` for the sensor; ``pipeline`` for the modes,
            filter and integrity).
        target: the target model.
        pah: a PAH database to use instead of building (or reusing) one.
        tracker: kind of :func:`~perception.estimation.flashtrack.make_flash_tracker`.
        search_points: returns of a frame that bearing and search use (a random subset).
        tracker_options: keywords of the tracker's class (default its own: for the outline
            trackers 2,000 stratified returns, ICP on 300 of them, 600 outline pairs, the
            per-frame cost bounded whatever the range).
        twin_points: returns of a tracking frame the twin monitor scores and polishes its
            alternatives on (a random subset).
    """

    def __init__(self, config: MissionConfig, target: TargetModel, *, pah: Any | None = None,
                 tracker: str = "p2plane+cv+outline", search_points: int = 2000,
                 tracker_options: dict[str, Any] | None = None,
                 twin_points: int = TWIN_POINTS) -> None:
        if search_points < 20:
            raise ValueError(f"search_points={search_points}; expected >= 20")
        if twin_points < 20:
            raise ValueError(f"twin_points={twin_points}; expected >= 20")
        self.search_points = int(search_points)
        self.twin_points = int(twin_points)
        self.tracker_kind = tracker
        self.tracker_options = dict(tracker_options or {})
        super().__init__(config, target, sensor=FlashSensor(config.flash), pah=pah)  # type: ignore[arg-type]
        self.planner = None  # the flash frame covers the whole target: no region to choose
        self.tracking = FlashTrackingMode(self)
        self._handlers[Mode.TRACKING] = self.tracking
        self.flash_tracker = self._make_tracker(np.random.default_rng(0))

    def _make_tracker(self, rng: np.random.Generator) -> Any:
        options = {"filtered": False, **self.tracker_options}
        return make_flash_tracker(self.tracker_kind, self.model_target, flash=self.cfg.flash,
                                  rng=rng, **options)

    def reset(self, rng: np.random.Generator) -> None:
        super().reset(rng)
        if hasattr(self, "flash_tracker"):
            self.flash_tracker = self._make_tracker(rng)

    def subset(self, cloud: PointCloud, n: int | None = None) -> PointCloud:
        """At most ``n`` (default ``search_points``) returns of ``cloud``, drawn at random (in
        pixel order)."""
        n = self.search_points if n is None else int(n)
        if len(cloud) <= n:
            return cloud
        idx = np.sort(self.rng.choice(len(cloud), n, replace=False))
        return cloud.select(idx)

    def scan(self, scene: TruthScene | PointCloud, t: float, pattern: Any) -> PointCloud:
        """The whole flash frame in tracking mode; a subset of it in bearing and search."""
        cloud = super().scan(scene, t, pattern)
        return cloud if self.logic.mode == Mode.TRACKING else self.subset(cloud)
