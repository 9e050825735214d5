"""Bearing mode: find the target in the full field, then steer the scan onto it; and the centroid
bearing and filtered range every mode publishes next to (or instead of) a pose.

A far target gets a handful of the full field's samples; once a return gives a direction, the
scan is steered onto a box of the target's radius around the last fix (:meth:`BearingMode.steered`,
which search scans as well), where every sample can hit it.

Across ranges (seed 000 section 5: the thermal imager at tens of kilometres, the LIDAR within its
link budget, ~3 km): with ``pipeline.thermal_bearing`` a frame with no LIDAR returns takes the
thermal imager's bearing instead (``bearing_source`` "thermal"), and with
``pipeline.coarse_range.enabled`` a coarse range source (radar- or relative-GPS-like, to the
target's near surface) feeds the same range filter as the LIDAR's returns, once per
``coarse_range.period_s``. One filter fuses both, weighted by their sigmas, so the published range
and range rate carry on through the hand-over between the sources; the filter's prediction takes
the host's own thrust along the line of sight from its accelerometer (``ego``).
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt
from trimesh.proximity import closest_point

from perception.geometry import make_T
from perception.numeric import median
from perception.pipeline.filter import RangeFilter
from perception.pipeline.publish import FrameOutput
from perception.pipeline.state import Mode, TruthScene
from perception.sensing.pointcloud import PointCloud
from perception.sensing.scan_patterns import make_pattern, steer_to_region
from perception.sensing.sensors.raycast import cast_rays
from perception.targets import RegionOfInterest

if TYPE_CHECKING:
    from perception.pipeline.tridar import TriDAR

FloatArray = npt.NDArray[np.float64]

__all__ = ["MIN_BEARING_POINTS", "BearingMode"]

#: Points a frame needs for a bearing fix.
MIN_BEARING_POINTS = 3


class BearingMode:
    """Bearing mode's frames, and the bearing fix and scan patterns the other modes share.

    State: the range filter of the fixes and the last fix ``(centroid, t)``.

    Args:
        tri: the pipeline (configuration, sensor, mode logic, frame timing).
    """

    def __init__(self, tri: TriDAR) -> None:
        self.tri = tri
        self.reset()

    def reset(self) -> None:
        self.range_filter = RangeFilter(self.tri.pc.process_noise_accel**2)
        self.last_fix: tuple[FloatArray, float] | None = None  # (centroid, t) of the last fix
        self.last_coarse_t: float | None = None  # time of the last coarse range measurement
        self.last_los: FloatArray | None = None  # (3,) unit line of sight of the last bearing

    def _range_accel(self) -> float:
        """The known acceleration along the range [m/s^2]: the host's own, ``-u . a``
        (accelerometer), and the tide's, ``r u . G u`` (gravity gradient ``G``; at 1 km in low
        orbit up to 2.6e-3 m/s^2, a steady force a range filter would otherwise lag behind)."""
        ego, u = self.tri.ego, self.last_los
        if ego is None or u is None or not self.tri.pc.ego_motion:
            return 0.0
        a = -float(u @ ego.accel)
        rf = self.range_filter
        if ego.gravity_gradient is not None and rf.initialized:
            a += rf.range * float(u @ ego.gravity_gradient @ u)
        return a

    def _fuse(self, t: float, range_m: float, sigma: float) -> None:
        self.range_filter.update(t, range_m, sigma, accel=self._range_accel())

    def coarse_range(self, scene: TruthScene | PointCloud, t: float) -> None:
        """The coarse range source's measurement at ``t`` when one is due (module docstring):
        the range along the line of sight to the target's centre to its first surface (the
        closest point of the mesh when that ray misses), plus its noise."""
        tri = self.tri
        cr = tri.pc.coarse_range
        if not cr.enabled or not isinstance(scene, TruthScene):
            return
        if self.last_coarse_t is not None and t - self.last_coarse_t < cr.period_s - 1e-9:
            return
        T = scene.T_sensor_target
        p = T[:3, 3]
        r = math.sqrt(float(p @ p))
        if r > cr.max_range_m or r <= 0.0:
            return
        R = T[:3, :3]
        origin = R.T @ (-p)
        face, rng_hit, _ = cast_rays(tri.target, origin, (R.T @ (p / r))[None, :])
        if face[0] >= 0:
            surf = float(rng_hit[0])
        else:
            surf = float(closest_point(tri.target.mesh, origin[None, :])[1][0])
        sigma = math.hypot(cr.sigma_m, cr.sigma_fraction * surf)
        self.last_coarse_t = t
        if self.last_los is None:
            self.last_los = p / r
        self._fuse(t, surf + sigma * float(tri.rng.standard_normal()), sigma)

    # ------------------------------------------------------------------ scan patterns
    def full_field(self, n_points: int | None = None) -> Any:
        """The configured pattern over the whole field, its phase stepped each frame."""
        tri = self.tri
        sc = tri.cfg.sensor.scan
        phase = (tri.frame_index * sc.phase_step) % (2 * np.pi)
        return make_pattern(
            sc.pattern, n_points or sc.n_points, tri.sensor.fov_rad, phase=phase,
            sample_rate_hz=sc.sample_rate_hz, max_accel_rad_s2=sc.max_mirror_accel_rad_s2,
        )

    def steered(self) -> Any:
        """Steer onto the last bearing fix (a cube of the target's radius around the centroid)."""
        tri = self.tri
        sc = tri.cfg.sensor.scan
        if self.last_fix is None:
            return self.full_field()
        c, _ = self.last_fix
        rad = tri.target.radius
        box = RegionOfInterest("bearing", (0.0, 0.0, 0.0), (rad, rad, rad))
        try:
            return steer_to_region(
                sc.pattern, make_T(None, c), box, tri.sensor.fov_rad, margin=0.2,
                n_points=sc.n_points, phase=(tri.frame_index * sc.phase_step) % (2 * np.pi),
                sample_rate_hz=sc.sample_rate_hz, max_accel_rad_s2=sc.max_mirror_accel_rad_s2,
            )
        except ValueError:
            return self.full_field()

    # ------------------------------------------------------------------ the fix
    def fix(self, cloud: PointCloud, t: float, min_points: int = MIN_BEARING_POINTS) -> FrameOutput:
        """Centroid bearing and filtered range from a cloud (any mode)."""
        mode = self.tri.logic.mode
        if len(cloud) < min_points:
            return FrameOutput(t, mode, "none", t, len(cloud))
        c = cloud.points.mean(axis=0)
        r = np.sqrt(np.einsum("ij,ij->i", cloud.points, cloud.points))
        t_mid = float(cloud.times.mean())
        rng_m = median(r)
        # Spread of returns over the target dominates the centroid's range error far out.
        sigma = float(max(r.std() / math.sqrt(len(r)), median(cloud.sigma)))
        rf = self.range_filter
        if self.tri.pc.coarse_range.enabled or self.tri.pc.thermal_bearing:
            self.last_los = c / max(math.sqrt(float(c @ c)), 1e-9)
            self._fuse(t_mid, rng_m, sigma)
        else:
            rf.update(t_mid, rng_m, sigma)
        self.last_fix = (c, t_mid)
        bearing = np.array([np.arctan2(c[0], c[2]), np.arctan2(-c[1], np.hypot(c[0], c[2]))])
        return FrameOutput(
            t, mode, "bearing", t_mid, len(cloud), bearing=bearing,
            range_m=rf.range, range_sigma=sigma,
            range_rate=rf.range_rate if rf.rate_valid else None, bearing_source="lidar",
        )

    def thermal_fix(self, scene: TruthScene | PointCloud, t: float) -> FrameOutput | None:
        """The thermal imager's bearing (and the range filter's range, when it has one) at ``t``,
        or None without a detection."""
        tri = self.tri
        if tri.thermal is None or not isinstance(scene, TruthScene):
            return None
        det = tri.thermal.observe(
            tri.target, scene.T_sensor_target, tri.rng,
            sun_direction_target=scene.sun_direction_target, t=t,
        )
        if det is None:
            return None
        self.last_los = np.asarray(det.direction, dtype=np.float64)
        rf = self.range_filter
        ranged = rf.initialized
        if ranged:  # cue the LIDAR: its next scans are steered onto the thermal bearing
            self.last_fix = (self.last_los * rf.range, t)
        return FrameOutput(
            t, tri.logic.mode, "bearing", t, det.n_pixels, bearing=np.asarray(det.bearing, dtype=np.float64),
            range_m=rf.range if ranged else 0.0, range_valid=ranged,
            range_rate=rf.range_rate if rf.rate_valid else None, bearing_source="thermal",
        )

    # ------------------------------------------------------------------ the frame
    def frame(self, scene: TruthScene | PointCloud, t: float) -> None:
        """One bearing frame at ``t`` [s]: scan, fix, and hand over to search once the fix holds."""
        tri = self.tri
        # Full field until a fix; then the scan is steered onto the last fix (a small, far target
        # gets a handful of the full-field samples, and every sample once steered).
        recent = self.last_fix is not None and t - self.last_fix[1] <= 5.0
        cloud = tri.scan(scene, t, self.steered() if recent else self.full_field())
        if recent and len(cloud) < MIN_BEARING_POINTS:
            self.last_fix = None  # lost it: back to the full field next frame
        tri.last_cloud = cloud
        # In the full field a single return already gives a direction to steer onto; the steered
        # scans that follow must then confirm it with MIN_BEARING_POINTS returns.
        self.coarse_range(scene, t)
        out = self.fix(cloud, t, MIN_BEARING_POINTS if recent else 1)
        if out.kind == "none" and tri.thermal is not None:
            out = self.thermal_fix(scene, t) or out
        tri.busy_until = cloud.t_end + tri.pc.bearing_latency_s
        out.available_t = tri.busy_until
        tri.publisher.append(out)
        tri.logic.after_bearing(
            t, out.range_m if out.kind == "bearing" else None, len(cloud), MIN_BEARING_POINTS
        )
        if tri.logic.mode == Mode.SEARCH:
            tri.search_started = t
