"""The TriDAR: sensor + modes + estimators + filter -> :class:`~perception.pipeline.state.StateVector`.

Following the MILD approach (seed 000 section 4.3) the algorithms drive the scanner: each frame the
mode logic decides what to scan (full field, the bearing box, or a region of interest around the
predicted pose) and which algorithm runs on the returns (centroid bearing, PAH acquisition or an
external seed, ICP tracking). Processing time is part of the simulation: a frame's output becomes
available ``latency`` seconds after its scan ends, and no new scan starts while the processor is
busy, so the frame rate follows from scan time plus processing. The configured latencies are used
(not the measured wall time), which keeps runs bitwise reproducible.

Output timing: :meth:`TriDAR.step` returns the newest output available at the call time, with the
filter state propagated from its measurement time to the call time (what a navigation filter
publishes); ``StateVector.latency`` is the age of the underlying measurement. A pose older than
``loss_of_track_frames`` frame periods plus the tracking latency is no longer published as valid.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt
from scipy.spatial.transform import Rotation

from perception.config import ICPConfig, MissionConfig
from perception.pipeline.filter import EgoMotion, PoseFilter, RangeFilter
from perception.geometry import (
    check_rigid,
    cross_rows,
    fast_matrix_to_quat,
    make_T,
    pose_error,
    skew,
)
from perception.pipeline.integrity import (
    alert_limit,
    integrity_factor,
    port_covariance,
    protection_level,
    turn_about,
)
from perception.pipeline.modes import FrameVerdict, ModeLogic
from perception.numeric import median
from perception.pipeline.observability import ScanPlanner
from perception.sensing.pointcloud import PointCloud
from perception.estimation.registration import RegistrationResult, icp, prepare_model
from perception.sensing.scan_patterns import angles_to_directions, make_pattern, steer_to_region
from perception.sensing.sensors.tridar import TriDARSensor
from perception.pipeline.state import INVALID_VARIANCE, Mode, StateVector, TruthScene, Validity
from perception.targets import RegionOfInterest, TargetModel

FloatArray = npt.NDArray[np.float64]

__all__ = ["TriDAR", "PipelineStats", "nominal_attitude", "approach_pose", "deskew"]

#: Points a frame needs for a bearing fix and for a registration.
MIN_BEARING_POINTS = 3
MIN_REGISTRATION_POINTS = 12
R_PORT_DOCK = np.diag([1.0, -1.0, -1.0])


def nominal_attitude(cfg: MissionConfig, target: TargetModel) -> FloatArray:
    """``R_sensor_target`` on the nominal approach: the docking frame facing the port.

    The chaser docking frame has +z along the docking axis; facing the port means
    ``R_port_dock = diag(1, -1, -1)``; the sensor mount comes from the chaser config.
    """
    ch = cfg.dynamics.chaser
    R_chaser_sensor = Rotation.from_euler("xyz", ch.sensor_rpy_deg, degrees=True).as_matrix()
    R_target_dock = target.T_target_port[:3, :3] @ R_PORT_DOCK  # chaser dock frame == body axes
    return R_chaser_sensor.T @ R_target_dock.T


def approach_pose(
    cfg: MissionConfig, target: TargetModel, range_m: float, lateral: tuple[float, float] = (0.0, 0.0)
) -> FloatArray:
    """``T_sensor_target`` on the nominal approach: docking frame facing the port, the port at
    ``(lateral_x, lateral_y, range_m)`` in the sensor frame (scripted trajectories, tests)."""
    R = nominal_attitude(cfg, target)
    p_port_s = np.array([lateral[0], lateral[1], range_m], dtype=np.float64)
    return make_T(R, p_port_s - R @ target.T_target_port[:3, 3])


def deskew(cloud: PointCloud, motion_T: Any, t_ref: float) -> FloatArray:
    """Move every point to where it would be at ``t_ref`` under a constant-rate motion estimate.

    Args:
        cloud: points with their sample times.
        motion_T: an object with ``p``, ``v``, ``R``, ``w``, ``t`` (a :class:`PoseFilter` state).
        t_ref: reference time [s].

    Returns:
        (N, 3) de-skewed points [m], sensor frame.
    """
    if len(cloud) == 0:
        return cloud.points.copy()
    f = motion_T
    tau_i = cloud.times - f.t
    tau_r = t_ref - f.t
    p_i = f.p + np.outer(tau_i, f.v)
    p_r = f.p + f.v * tau_r
    x = cloud.points - p_i
    w = np.asarray(f.w, dtype=np.float64)
    rate = float(np.sqrt(w @ w))
    if rate == 0.0:
        return x + p_r
    # Rodrigues about the one axis w / |w|, by the angle rate (tau_r - tau_i) of each point.
    k = w / rate
    ang = rate * (tau_r - tau_i)
    c, s = np.cos(ang)[:, None], np.sin(ang)[:, None]
    kx = cross_rows(np.broadcast_to(k, x.shape), x)
    return x * c + kx * s + np.outer(x @ k, k) * (1.0 - c) + p_r


@dataclass
class PipelineStats:
    """Counters and timings of a run (for benchmarks and reports)."""

    frames: int = 0
    frames_by_mode: dict[str, int] = field(default_factory=lambda: {"bearing": 0, "search": 0, "tracking": 0})
    acquisitions: list[tuple[float, float]] = field(default_factory=list)  # (search start, acquired)
    losses: int = 0
    restarts: int = 0
    rejected_candidates: int = 0
    filter_reinits: int = 0
    symmetry_checks: int = 0
    symmetry_switches: int = 0
    reacquired_from_track: int = 0
    outline_refinements: int = 0
    outline_accepted: int = 0
    registration_time_s: list[float] = field(default_factory=list)


@dataclass
class _Output:
    """A frame's result, published once the processor is done with it."""

    available_t: float
    mode: Mode
    kind: str  # "bearing" | "pose" | "none"
    t_meas: float
    n_points: int
    fitness: float = 0.0
    bearing: FloatArray | None = None
    range_m: float = 0.0
    range_sigma: float = 0.0
    range_rate: float | None = None
    filt: PoseFilter | None = None
    n_updates: int = 0
    ambiguity_m: float = 0.0  # port offset to a twin pose the scan cannot rule out [m]
    lever_m: float = math.inf  # RMS distance of the frame's points from their centroid [m]


def _lever(points: FloatArray) -> float:
    """RMS distance [m] of points from their centroid (inf for none)."""
    if len(points) == 0:
        return math.inf
    return float(np.sqrt(np.mean(np.sum((points - points.mean(axis=0)) ** 2, axis=1))))


class TriDAR:
    """The TriDAR box: call :meth:`step` once per frame with the truth scene (or a cloud).

    Args:
        config: the mission configuration (sensor, pipeline, chaser mount for the corridor).
        target: the target model (reference model and PAH database).
        sensor: a sensor to use instead of ``TriDARSensor(config.sensor)``.
        pah: a PAH database to use instead of building (or reusing) one for ``target``.
    """

    def __init__(
        self,
        config: MissionConfig,
        target: TargetModel,
        *,
        sensor: TriDARSensor | None = None,
        pah: Any | None = None,
    ) -> None:
        self.cfg = config
        self.pc = config.pipeline
        self.target = target  # the sensor scans it
        # What the estimator knows of it (the simplified mesh of a dense CAD file).
        self.model_target = target.model_view()
        self.sensor = sensor if sensor is not None else TriDARSensor(config.sensor)
        self.model = prepare_model(self.model_target, self.pc.icp.model_points)
        self._pah = pah
        self.logic = ModeLogic(self.pc, self.sensor.transition_range_m)
        self.planner: ScanPlanner | None = None
        if self.pc.scan_plan.mode == "observability":
            self.planner = ScanPlanner(self.model_target, self.sensor, self.model, self.pc.scan_plan,
                                       self.pc.icp.noise_floor_fraction)
        self.R_nominal = nominal_attitude(config, target)
        self.frame_period = 1.0 / self.pc.frame_rate_hz
        self.max_pose_age = self.pc.loss_of_track_frames * self.frame_period + self.pc.tracking_latency_s + 1e-9
        self.rng = np.random.default_rng(0)
        self.external_seed: tuple[float, FloatArray] | None = None
        self.reset(self.rng)

    # ------------------------------------------------------------------ lifecycle
    def reset(self, rng: np.random.Generator) -> None:
        """Start-up: bearing mode, empty filters, fresh counters; ``rng`` drives the sensor and PAH."""
        self.rng = rng
        self.external_seed = None
        inertia = self.target.inertia if self.pc.target_rotation == "torque_free" else None
        self.filter = PoseFilter(self.pc.process_noise_accel**2, self.pc.process_noise_angacc**2,
                                 init_rate_sigma=math.radians(self.pc.initial_rate_sigma_deg_s),
                                 ref_point=self.target.T_target_port[:3, 3], inertia=inertia)
        self._ego: EgoMotion | None = None
        self.range_filter = RangeFilter(self.pc.process_noise_accel**2)
        self.logic.reset(0.0)
        self.sensor.frame_counter = 0
        self.busy_until = -np.inf
        self.frame_index = 0
        self.last_cloud: PointCloud | None = None
        self.last_result: RegistrationResult | None = None
        self._outputs: list[_Output] = []
        self._published: _Output | None = None
        self._bearing: tuple[FloatArray, float] | None = None  # (centroid, t) of the last fix
        self._search_started: float | None = None
        self._last_pose_t = -np.inf
        self._n_updates = 0
        self._gate_rejects = 0
        self._rejected: list[tuple[float, FloatArray, FloatArray]] = []  # since the last update
        self._sym_checked_t = -np.inf
        self._amb_checked_t = -np.inf
        self._ambiguity_m = 0.0
        # Near-symmetric turns of the track's pose the scans have not yet ruled out: None, all of
        # them (a track that PAH started from nothing); empty for a track that carries a prior.
        self._twins_open: set[int] | None = set()
        self._sym_votes = 0
        self._sym_candidate = -1
        self._lost_track: PoseFilter | None = None
        self._frame_pattern: tuple[Any, float] | None = None  # (pattern, start time) of the frame
        if self.planner is not None:
            self.planner.reset()
        self.stats = PipelineStats()

    def seed_pose(self, T_sensor_target: npt.ArrayLike, t: float) -> None:
        """An external initial guess for search (GPS, ground, another sensor), valid at ``t``."""
        self.external_seed = (float(t), check_rigid(T_sensor_target, "T_sensor_target").copy())

    @property
    def mode(self) -> Mode:
        return self.logic.mode

    @property
    def pah(self) -> Any:
        """The PAH database of the target (built once per target and configuration)."""
        if self._pah is None:
            from perception.estimation.pah import PAHDatabase

            key = ("pah_db", self.pc.pah.model_dump_json())
            mt = self.model_target
            self._pah = mt.cached(key, lambda: PAHDatabase.build(mt, self.pc.pah))
        return self._pah

    def prepare(self) -> None:
        """Build what search needs now rather than in the first search frame: the PAH database and
        the target's near-symmetries (about 1 s for the ISS-like port; once per process and target,
        cached on the target)."""
        self.pah.near_symmetries()

    # ------------------------------------------------------------------ the frame
    def step(self, scene: TruthScene | PointCloud, t: float, ego: EgoMotion | None = None) -> StateVector:
        """Run one frame at time ``t`` [s] and publish the newest available state.

        Args:
            scene: the truth scene to scan (simulation), or an already acquired cloud.
            t: current time [s].
            ego: the host's gyro and accelerometer at ``t`` (sensor coordinates), used from
                now on when ``pipeline.ego_motion`` is set (ignored otherwise).
        """
        if not np.isfinite(t):
            raise ValueError(f"t={t!r}; expected a finite time [s]")
        if ego is not None and self.pc.ego_motion:
            if not isinstance(ego, EgoMotion):
                raise ValueError(f"ego={type(ego).__name__}; expected an EgoMotion")
            # The old rates held until now; the new ones from now on.
            if self.filter.initialized and self.filter.t < t:
                self.filter.predict(t)
            self.filter.set_ego(ego)
            self._ego = ego
        if self.logic.restart_due(t) and self.logic.mode != Mode.BEARING and not self._restart_inhibited():
            self._restart(t)
        if t >= self.busy_until - 1e-12:
            self._process_frame(scene, t)
        return self._publish(t)

    def _restart_inhibited(self) -> bool:
        """A planned restart waits while the estimated port is inside ``restart_inhibit_range_m``."""
        limit = self.pc.restart_inhibit_range_m
        if limit <= 0.0 or not self.filter.initialized:
            return False
        T = self.filter.T_sensor_target
        port = T[:3, :3] @ self.target.T_target_port[:3, 3] + T[:3, 3]
        return bool(np.linalg.norm(port) < limit)

    def _restart(self, t: float) -> None:
        self.stats.restarts += 1
        rng_m = float(np.linalg.norm(self.filter.T_sensor_target[:3, 3])) if self.filter.initialized else None
        self.logic.restart(t, rng_m)
        self.filter.reset()
        self._n_updates = 0
        self._search_started = t if self.logic.mode == Mode.SEARCH else None

    def _scan(self, scene: TruthScene | PointCloud, t: float, pattern: Any) -> PointCloud:
        if isinstance(scene, PointCloud):
            return scene
        # Faults are indexed by the sensor's nominal frame slots (time), not by processed frames:
        # a 30-frame blackout lasts 30 / frame_rate seconds whatever the modes' processing times.
        cloud = self.sensor.scan(
            self.target, scene.T_sensor_target, pattern, self.rng, motion=scene.motion, t0=t,
            frame_index=int(round(t * self.pc.frame_rate_hz)),
        )
        return cloud

    def _process_frame(self, scene: TruthScene | PointCloud, t: float) -> None:
        mode = self.logic.mode
        self.stats.frames += 1
        self.stats.frames_by_mode[mode.name.lower()] += 1
        if mode == Mode.BEARING:
            self._bearing_frame(scene, t)
        elif mode == Mode.SEARCH:
            self._search_frame(scene, t)
        else:
            self._tracking_frame(scene, t)
        self.frame_index += 1

    # ------------------------------------------------------------------ bearing
    def _full_field(self, n_points: int | None = None) -> Any:
        sc = self.cfg.sensor.scan
        phase = (self.frame_index * sc.phase_step) % (2 * np.pi)
        return make_pattern(
            sc.pattern, n_points or sc.n_points, self.sensor.fov_rad, phase=phase,
            sample_rate_hz=sc.sample_rate_hz, max_accel_rad_s2=sc.max_mirror_accel_rad_s2,
        )

    def _bearing_fix(self, cloud: PointCloud, t: float, min_points: int = MIN_BEARING_POINTS) -> _Output:
        """Centroid bearing and filtered range from a cloud (any mode)."""
        if len(cloud) < min_points:
            return _Output(t, self.logic.mode, "none", t, len(cloud))
        c = cloud.points.mean(axis=0)
        r = np.sqrt(np.einsum("ij,ij->i", cloud.points, cloud.points))
        t_mid = float(cloud.times.mean())
        rng_m = median(r)
        # Spread of returns over the target dominates the centroid's range error far out.
        sigma = float(max(r.std() / math.sqrt(len(r)), median(cloud.sigma)))
        self.range_filter.update(t_mid, rng_m, sigma)
        self._bearing = (c, t_mid)
        bearing = np.array([np.arctan2(c[0], c[2]), np.arctan2(-c[1], np.hypot(c[0], c[2]))])
        return _Output(
            t, self.logic.mode, "bearing", t_mid, len(cloud), bearing=bearing,
            range_m=self.range_filter.range, range_sigma=sigma,
            range_rate=self.range_filter.range_rate if self.range_filter.rate_valid else None,
        )

    def _bearing_frame(self, scene: TruthScene | PointCloud, t: float) -> None:
        # Full field until a fix; then the scan is steered onto the last fix (a small, far target
        # gets a handful of the full-field samples, and every sample once steered).
        recent = self._bearing is not None and t - self._bearing[1] <= 5.0
        cloud = self._scan(scene, t, self._search_pattern() if recent else self._full_field())
        if recent and len(cloud) < MIN_BEARING_POINTS:
            self._bearing = None  # lost it: back to the full field next frame
        self.last_cloud = cloud
        # In the full field a single return already gives a direction to steer onto; the steered
        # scans that follow must then confirm it with MIN_BEARING_POINTS returns.
        out = self._bearing_fix(cloud, t, MIN_BEARING_POINTS if recent else 1)
        self.busy_until = cloud.t_end + self.pc.bearing_latency_s
        out.available_t = self.busy_until
        self._outputs.append(out)
        self.logic.after_bearing(
            t, out.range_m if out.kind == "bearing" else None, len(cloud), MIN_BEARING_POINTS
        )
        if self.logic.mode == Mode.SEARCH:
            self._search_started = t

    # ------------------------------------------------------------------ search
    def _search_pattern(self) -> Any:
        """Steer onto the last bearing fix (a cube of the target's radius around the centroid)."""
        sc = self.cfg.sensor.scan
        if self._bearing is None:
            return self._full_field()
        c, _ = self._bearing
        rad = self.target.radius
        box = RegionOfInterest("bearing", (0.0, 0.0, 0.0), (rad, rad, rad))
        try:
            return steer_to_region(
                sc.pattern, make_T(None, c), box, self.sensor.fov_rad, margin=0.2,
                n_points=sc.n_points, phase=(self.frame_index * sc.phase_step) % (2 * np.pi),
                sample_rate_hz=sc.sample_rate_hz, max_accel_rad_s2=sc.max_mirror_accel_rad_s2,
            )
        except ValueError:
            return self._full_field()

    def _constraint(self) -> Any:
        if not self.pc.use_corridor:
            return None
        from perception.estimation.pah import PoseConstraint

        return PoseConstraint.from_corridor(self.pc.corridor, self.R_nominal)

    def _search_frame(self, scene: TruthScene | PointCloud, t: float) -> None:
        if self._search_started is None:
            self._search_started = t
        cloud = self._scan(scene, t, self._search_pattern())
        self.last_cloud = cloud
        out = self._bearing_fix(cloud, t)
        self.busy_until = cloud.t_end + self.pc.search_latency_s
        out.available_t = self.busy_until
        if self.logic.search_too_far(t, out.range_m if out.kind == "bearing" else None):
            self._outputs.append(out)
            return
        if len(cloud) < MIN_REGISTRATION_POINTS:
            self._outputs.append(out)
            return
        t_ref = float(np.mean(cloud.times))
        constraint = self._constraint()
        sigma = cloud.sigma
        icp_cfg = self.logic.icp_config_for(cloud.subsystem)
        expected = max(median(sigma), self.pc.measurement_floor_m)
        res, admitted, verdict, from_track, from_pah = None, False, None, None, False
        lost = self._lost_track
        if lost is not None and t_ref - lost.t <= self.pc.reacquire_window_s:
            # Reacquisition from the lost track's prediction (cheap); PAH only if that fails.
            res = icp(cloud.points, self.model, lost.pose_at(t_ref), sigma=sigma,
                      directions=cloud.directions, config=icp_cfg)
            verdict = self.logic.judge(res.converged, res.fitness, res.inlier_rmse, expected,
                                       res.T_sensor_target, lost.pose_at(t_ref), acquisition=True)
            admitted = constraint is None or bool(constraint.admits(res.T_sensor_target))
            from_track = lost if (verdict.good and admitted) else None
        if from_track is None:
            if self.external_seed is not None:
                res = icp(cloud.points, self.model, self.external_seed[1], sigma=sigma,
                          directions=cloud.directions, config=icp_cfg)
                self.external_seed = None
            else:
                # No wall-clock budget: the polygon budget bounds the work, and a run must not
                # depend on how busy the machine is (its latency is simulated, not measured).
                res = self.pah.localize(cloud.points, self.rng, constraint=constraint,
                                        sigma=sigma, max_time_s=math.inf)
                from_pah = True
            verdict = self.logic.judge(res.converged, res.fitness, res.inlier_rmse, expected,
                                       res.T_sensor_target, None, acquisition=True)
            if verdict.good and from_pah and res.reason:
                # PAH validates its own answer (its score reached accept_fitness with almost no
                # point seen through the model) and says why not otherwise; ICP's fitness alone
                # is lenient (a pose 11 deg off on the iss_port cone fits 100 % within its gate
                # with 3 % of the points behind the surface). Search again on the next scan.
                verdict = FrameVerdict(False, f"PAH: {res.reason}")
            admitted = constraint is None or bool(constraint.admits(res.T_sensor_target))
        assert res is not None and verdict is not None
        self.last_result = res
        self.stats.registration_time_s.append(res.time_s)
        if verdict.good and admitted:
            if from_track is not None:
                self.stats.reacquired_from_track += 1
                self.filter.initialize(t_ref, res.T_sensor_target, self._measurement_cov(res),
                                       velocity=from_track.target_state()[1], omega=from_track.w)
            else:
                self.filter.initialize(t_ref, res.T_sensor_target, self._measurement_cov(res))
            self._lost_track = None
            self._gate_rejects = 0
            self._rejected = []
            self._n_updates = 1
            # PAH's answer may be a twin of the truth until the scans rule the twins out; a seed or
            # the lost track's prediction already has (the track's continuity carries that on).
            self._twins_open = None if from_pah else set()
            self._ambiguity_m = 0.0
            self._last_pose_t = t_ref
            self.stats.acquisitions.append((self._search_started, t))
            self._search_started = None
            self.logic.go(t, Mode.TRACKING, f"acquired (fitness {res.fitness:.2f})")
            out = _Output(self.busy_until, Mode.TRACKING, "pose", t_ref, len(cloud), fitness=res.fitness,
                          lever_m=_lever(cloud.points),
                          bearing=out.bearing, range_m=out.range_m, range_rate=out.range_rate,
                          filt=self.filter.copy(), n_updates=self._n_updates)
        elif not admitted:
            self.stats.rejected_candidates += 1
        self._outputs.append(out)

    def _measurement_cov(self, res: RegistrationResult) -> FloatArray:
        """Registration covariance plus the configured floors (what the bound leaves out).

        The floors are added about the filter's reference point (the docking port), where the
        scan looks and where they were measured: added about a centre of mass 12 m behind the
        port, the attitude floor alone would put 0.3 deg x 12 m = 6 cm of position error on a
        port whose position is known to a few millimetres.
        """
        a = res.T_sensor_target[:3, :3] @ self.target.T_target_port[:3, 3]
        J = np.eye(6)
        J[:3, 3:] = -skew(a)  # origin -> port: dp_port = dp - [a]x dtheta
        cov = J @ res.covariance @ J.T
        cov.flat[0:21:7] += self.pc.measurement_floor_m**2
        cov.flat[21::7] += math.radians(self.pc.measurement_floor_deg) ** 2
        J[:3, 3:] = skew(a)  # and back
        cov = J @ cov @ J.T
        return 0.5 * (cov + cov.T)

    # ------------------------------------------------------------------ tracking
    def _tracking_pattern(self, T_pred: FloatArray, t: float = 0.0) -> tuple[Any, str]:
        rng_m = float(np.linalg.norm(T_pred[:3, 3]))
        region = self.logic.region_for_range(rng_m)
        roi = self.target.regions.get(region) or self.target.regions["whole"]
        if self.planner is not None:
            weak = self.last_result is not None and bool(self.last_result.degenerate_axes)
            roi, _ = self.planner.choose(T_pred, region, self.frame_index, t, weak)
            region = roi.name
        try:
            pattern = self.sensor.make_scan_pattern(self.frame_index, T_pred, roi)
        except ValueError:
            pattern = self._full_field()
        return pattern, region

    def _tracking_frame(self, scene: TruthScene | PointCloud, t: float) -> None:
        f = self.filter
        T_start = f.pose_at(t)
        pattern, _ = self._tracking_pattern(T_start, t)
        cloud = self._scan(scene, t, pattern)
        self.last_cloud = cloud
        self.busy_until = cloud.t_end + self.pc.tracking_latency_s
        n = len(cloud)
        if n < MIN_REGISTRATION_POINTS:
            reason = f"{n} points; tracking needs >= {MIN_REGISTRATION_POINTS}"
            lost = self.logic.record(t, FrameVerdict(False, reason))
            self._after_loss(lost, t)
            self._outputs.append(_Output(self.busy_until, self.logic.mode, "none", t, n))
            return
        t_ref = float(0.5 * (cloud.t_start + cloud.t_end))
        pts = deskew(cloud, f, t_ref)
        T_pred = f.pose_at(t_ref)
        # On an established track (rates estimated, the last frames accepted) the prediction is
        # within a few sigma of the answer: ICP starts in its fine phase.
        settled = (self.pc.fine_only_tracking and self._n_updates >= 3
                   and self.logic.bad_frames == 0 and self._gate_rejects == 0)
        icp_cfg = self.logic.icp_config_for(cloud.subsystem)
        res = icp(pts, self.model, T_pred, sigma=cloud.sigma, directions=cloud.directions,
                  config=icp_cfg, coarse=not settled)
        self._frame_pattern = None if isinstance(scene, PointCloud) else (pattern, t)
        res = self._outline_refine(res, pts, cloud)
        self.last_result = res
        self.stats.registration_time_s.append(res.time_s)
        expected = max(median(cloud.sigma), self.pc.measurement_floor_m)
        # With a running filter the consistency test is its innovation gate, which weighs each
        # direction by the registration's covariance: a pose that slides along a direction the
        # geometry leaves unobservable (degenerate_axes) is not a jump, it is uninformative.
        verdict = self.logic.judge(res.converged, res.fitness, res.inlier_rmse, expected,
                                   res.T_sensor_target, None)
        if verdict.good:
            cov = self._measurement_cov(res)
            upd = f.update(t_ref, res.T_sensor_target, cov)
            if upd.accepted:
                self._gate_rejects = 0
                self._rejected = []
                self._n_updates += 1
                self._last_pose_t = t_ref
            else:
                # The registration is sound but the filter disagrees: an unmodelled manoeuvre or an
                # overconfident filter. After a few such frames that agree with one another,
                # restart the filter on them (keeping the rates) rather than dropping a good track.
                # Rejected registrations that disagree with one another as well (ICP in another
                # basin each frame: the roll of a near-cylindrical bus 20-40 deg off under a 2 deg
                # sigma) are not a track to restart on: they count towards loss of track.
                self._gate_rejects += 1
                self._rejected = [*self._rejected, (t_ref, res.T_sensor_target, cov)]
                self._rejected = self._rejected[-self.pc.filter_reinit_frames:]
                restart = None
                if self._gate_rejects >= self.pc.filter_reinit_frames and not res.degenerate_axes:
                    restart = self._restart_on_rejected(f)
                if restart is not None:
                    self.filter = f = restart
                    self._rejected = []
                    self.stats.filter_reinits += 1
                    self._gate_rejects = 0
                    self._n_updates = 1
                    self._last_pose_t = t_ref
                else:
                    verdict = self.logic.judge(True, res.fitness, res.inlier_rmse, expected,
                                               res.T_sensor_target, None, filter_accepted=False)
        if verdict.good and self._n_updates > 0:
            self._monitor_twins(pts, cloud, res, t_ref, icp_cfg)
        lost = self.logic.record(t, verdict)
        self._after_loss(lost, t)
        out = _Output(self.busy_until, self.logic.mode, "pose" if self.logic.mode == Mode.TRACKING else "none",
                      t_ref, n, fitness=res.fitness, filt=f.copy(), n_updates=self._n_updates,
                      ambiguity_m=self._ambiguity_m, lever_m=_lever(pts))
        bfix = self._bearing_fix(cloud, t)
        out.bearing, out.range_m, out.range_rate = bfix.bearing, bfix.range_m, bfix.range_rate
        self._outputs.append(out)

    def _restart_on_rejected(self, f: PoseFilter) -> PoseFilter | None:
        """A filter restarted on the registrations the gate rejected in a row (keeping ``f``'s
        rates and their covariance: the motion between the frames is the track's), if each of
        them passes the gate of the one restarted on those before it; else None."""
        v_origin = f.target_state()[1]
        g = f.copy()
        (t0, T0, C0), *rest = self._rejected
        g.initialize(t0, T0, C0, velocity=v_origin, omega=f.w)
        P = g.P.copy()
        for rates in (slice(3, 6), slice(9, 12)):
            P[rates, rates] = f.P[rates, rates]
        g.P = P
        for t_k, T_k, C_k in rest:
            if not g.update(t_k, T_k, C_k).accepted:
                return None
        return g

    def _outline_refine(self, res: RegistrationResult, pts: FloatArray, cloud: PointCloud) -> RegistrationResult:
        """Where ICP left axes unobserved, add what the scan says about the outline.

        The samples of the frame's pattern that gave no return bound the target as much as the
        returns locate its surface: where the scan's curve crosses the outline, the model's
        outline must cross the same short arc (:func:`perception.estimation.silhouette.scan_outline_pairs`,
        the scanning form of seed 003's depth-map outline). A flat face seen head-on, which
        point-to-plane ICP cannot place in its plane, is placed by its edges. The refinement is
        kept when it converges, observes more axes than ICP did and stays within a frame's jump of
        ICP's pose; its covariance is the joint information's.
        """
        if not (res.degenerate_axes and self.pc.outline_refinement and self._frame_pattern is not None):
            return res
        from perception.estimation.silhouette import FlashGeometry, refine_with_outline, scan_outline_pairs

        pattern, t0 = self._frame_pattern
        dirs = angles_to_directions(pattern.az, pattern.el)
        returned = np.isin(t0 + pattern.times, cloud.times)
        a, b = scan_outline_pairs(dirs, returned)
        if a.size < 3:
            return res
        geom = FlashGeometry(dirs, 1, dirs.shape[0], 0.05, 0.0, math.inf)
        icp_cfg = self.logic.icp_config_for(cloud.subsystem)
        ref = refine_with_outline(
            pts, cloud.directions, cloud.sigma, dirs[a], dirs[b], self.model_target, self.model,
            res.T_sensor_target, geom, noise_floor_fraction=icp_cfg.noise_floor_fraction,
            back_facing_cos=icp_cfg.back_facing_cos, gate_m=max(3.0 * res.inlier_rmse, 0.05),
        )
        self.stats.outline_refinements += 1
        if not ref.converged or len(ref.degenerate_axes) >= len(res.degenerate_axes):
            return res
        # A refinement that turns or moves the pose further than a frame may jump has found
        # another basin of the outline (a near-symmetric twin), not the slide it is there for.
        dt, dr = pose_error(ref.T_sensor_target, res.T_sensor_target)
        if dt > self.pc.max_jump_m or dr > self.pc.max_jump_deg:
            return res
        self.stats.outline_accepted += 1
        return dataclasses.replace(ref, fitness=res.fitness, inlier_rmse=res.inlier_rmse,
                                   n_inliers=res.n_inliers, time_s=res.time_s + ref.time_s)

    def _monitor_twins(self, pts: FloatArray, cloud: PointCloud, res: RegistrationResult,
                       t_ref: float, icp_cfg: ICPConfig) -> None:
        """Ambiguity monitor (tracking): does a near-symmetric turn of the tracked pose explain
        the scan as well, or better?

        ICP runs from ``T @ G`` for each near-symmetry ``G`` of the model (PAH's near-symmetry
        search) and the converged alternatives are scored as PAH ranks hypotheses
        (:meth:`~perception.estimation.pah.PAHDatabase.verify_poses`). Two uses, on their own schedules:

        - integrity (``integrity.ambiguity_check_period_s``, and on every new track's first
          ``confirm_frames`` frames): while a twin scores within ``ambiguity_margin`` of the
          tracked pose, or above it, the scan cannot tell them apart and the port may be where the
          twin puts it: the protection level grows by the port's offset between the two poses
          (a roll twin of a nearly symmetric bus, locked at acquisition, was 0.45 m off at 10-15 m
          under a 3 cm protection level);
        - switching (``symmetry_check_period_s``): a twin whose score beats the tracked pose's by
          ``symmetry_margin`` gets a vote, and ``symmetry_switch_checks`` votes in a row for the
          same turn move the track there (the filter restarts on it, keeping its rates). A track
          that locked onto the flipped twin of a nearly symmetric target at 60 m, where the
          features that tell them apart are a few noisy points, is put right once they are
          resolved.
        """
        ig = self.pc.integrity
        amb_due = ig.ambiguity_check_period_s is not None and self._twins_open != set() and (
            self._n_updates <= ig.confirm_frames
            or t_ref - self._amb_checked_t >= ig.ambiguity_check_period_s - 1e-9)
        sym_due = self.pc.symmetry_check_period_s is not None and \
            t_ref - self._sym_checked_t >= self.pc.symmetry_check_period_s - 1e-9
        if not (amb_due or sym_due):
            return
        G = self.pah.near_symmetries()
        if amb_due:
            self._amb_checked_t = t_ref
        if sym_due:
            self._sym_checked_t = t_ref
        if len(G) == 0:
            self._twins_open, self._ambiguity_m = set(), 0.0
            return
        self.stats.symmetry_checks += 1
        score0, alts = self._twins(pts, cloud, res, icp_cfg, G)
        T = res.T_sensor_target
        if amb_due:
            # A twin stays open while it explains the scan about as well (or better); one that
            # explains it clearly worse, or does not converge, is ruled out for this track.
            # The mission's approach corridor, where configured, rules out a twin as PAH's search
            # does (a plate flipped about an in-plane axis is the same solid, port behind it).
            corridor = self._constraint()
            close = {i: a for i, a, s_alt in alts if s_alt >= score0 - ig.ambiguity_margin
                     and (corridor is None or corridor.admits(a.T_sensor_target))}
            prev = set(range(len(G))) if self._twins_open is None else self._twins_open
            self._twins_open = prev & set(close)
            r = self.model_target.T_target_port[:3, 3]
            port = T[:3, :3] @ r + T[:3, 3]
            self._ambiguity_m = max(
                (float(np.linalg.norm(close[i].T_sensor_target[:3, :3] @ r
                                      + close[i].T_sensor_target[:3, 3] - port))
                 for i in self._twins_open), default=0.0)
        if not sym_due:
            return
        best = max(alts, key=lambda a: a[2], default=None)
        if best is None or best[2] <= score0 + self.pc.symmetry_margin:
            self._sym_votes, self._sym_candidate = 0, -1
            return
        best_i, best_res, _ = best
        self._sym_votes = self._sym_votes + 1 if best_i == self._sym_candidate else 1
        self._sym_candidate = best_i
        if self._sym_votes < self.pc.symmetry_switch_checks:
            return
        best_res = self._outline_refine(best_res, pts, cloud)
        f = self.filter
        v_origin = f.target_state()[1]
        f.initialize(t_ref, best_res.T_sensor_target, self._measurement_cov(best_res),
                     velocity=v_origin, omega=f.w)
        self.last_result = best_res
        self.stats.symmetry_switches += 1
        self._sym_votes, self._sym_candidate = 0, -1
        self._n_updates = max(self._n_updates, 3)
        # The old pose is now a twin (clearly worse); the others are judged again from here.
        self._twins_open, self._amb_checked_t = None, -np.inf

    def _twins(self, pts: FloatArray, cloud: PointCloud, res: RegistrationResult, icp_cfg: ICPConfig,
               G: FloatArray) -> tuple[float, list[tuple[int, RegistrationResult, float]]]:
        """The tracked pose's PAH score and the converged near-symmetric alternatives
        ``(turn index, registration, score)``."""
        pah = self.pah
        T = res.T_sensor_target
        sigma, dirs = cloud.sigma, cloud.directions
        fit, score = pah.verify_poses(pts, sigma, np.concatenate([T[None], T @ G]), dirs)
        # Turns that show the sensor another side of the target explain little even before ICP:
        # only the near-fits are polished (with capped work: a turn that is not a better basin
        # need not converge) and scored again.
        cfg = icp_cfg.model_copy(update={"max_iterations": min(icp_cfg.max_iterations, 10)})
        alts: list[tuple[int, RegistrationResult]] = []
        for i in np.flatnonzero(fit[1:] >= 0.5 * fit[0]):
            alt = icp(pts, self.model, T @ G[i], sigma=sigma, directions=dirs, config=cfg)
            if alt.converged:
                alts.append((int(i), alt))
        if not alts:
            return float(score[0]), []
        _, s_alt = pah.verify_poses(pts, sigma, np.stack([a.T_sensor_target for _, a in alts]), dirs)
        return float(score[0]), [(i, a, float(s)) for (i, a), s in zip(alts, s_alt)]

    def _after_loss(self, lost: bool, t: float) -> None:
        if lost:
            self.stats.losses += 1
            if self.filter.initialized:
                self._lost_track = self.filter.copy()
            self.filter.reset()
            self._n_updates = 0
            self._search_started = t

    # ------------------------------------------------------------------ publishing
    def _publish(self, t: float) -> StateVector:
        ready = [o for o in self._outputs if o.available_t <= t + 1e-9]
        if ready:
            self._published = ready[-1]
            self._outputs = [o for o in self._outputs if o.available_t > t + 1e-9]
        out = self._published
        mode = self.logic.mode
        if out is None:
            return StateVector.invalid(t, mode)
        bearing_ok = out.bearing is not None and (t - out.t_meas) <= self.max_pose_age
        valid_kw: dict[str, bool] = {}
        kw: dict[str, Any] = {}
        if bearing_ok:
            valid_kw.update(bearing=True, range=True, range_rate=out.range_rate is not None)
            kw.update(bearing=out.bearing, range=out.range_m,
                      range_rate=out.range_rate if out.range_rate is not None else 0.0)
        cov = np.eye(12) * INVALID_VARIANCE
        pose_fresh = out.kind == "pose" and out.filt is not None and (t - out.t_meas) <= self.max_pose_age
        if pose_fresh and mode == Mode.TRACKING and out.filt is not None:
            f = out.filt.copy()
            if self._ego is not None:
                f.set_ego(self._ego)  # the host's latest rates carry the state to now
            if t > f.t:
                f.predict(t)
            fp, fv, fR, fw, fP = f.target_state()
            rates_ok = out.n_updates >= 3
            valid_kw.update(position=True, attitude=True, velocity=rates_ok, angular_velocity=rates_ok)
            rng_m = float(np.linalg.norm(fp))
            kw.update(position=fp, quaternion=fast_matrix_to_quat(fR), range=rng_m,
                      bearing=np.array([np.arctan2(fp[0], fp[2]), np.arctan2(-fp[1], np.hypot(fp[0], fp[2]))]))
            valid_kw.update(bearing=True, range=True)
            blocks = [slice(0, 3), slice(6, 9)]
            if rates_ok:
                kw.update(velocity=fv, angular_velocity=fw, range_rate=float(fp @ fv / max(rng_m, 1e-9)))
                valid_kw["range_rate"] = True
                blocks += [slice(3, 6), slice(9, 12)]
            # The registrations' correlated error does not average down: published on top.
            ig = self.pc.integrity
            r_port = self.target.T_target_port[:3, 3]
            port_rng = float(np.linalg.norm(fp + fR @ r_port))
            fP = fP.copy()
            # The correlated displacement b of the scanned surface turns the registration by up
            # to b over the scan's lever arm: published on the attitude as the position's is,
            # as a turn about the port (the origin moves with it; the port's bound does not).
            bias = max(ig.bias_m, ig.bias_rad * port_rng)
            fP.flat[0:36:13] += bias**2
            fP = turn_about(fP, fR, r_port, (bias / max(out.lever_m, 1e-3)) ** 2)
            for a in blocks:
                for b in blocks:
                    cov[a, b] = fP[a, b]
            # Integrity: the port's error bound from the filter's full pose covariance (the
            # unobservable directions of the registrations grow there, not in the floors).
            pl = protection_level(port_covariance(fP, fR, r_port), integrity_factor(ig.risk))
            pl += out.ambiguity_m  # the port may be where a twin the scan allows puts it
            al = alert_limit(port_rng, ig.alert_limit_m, ig.alert_limit_range_m)
            kw.update(protection_level=pl, alert_limit=al)
            # A track is trusted once confirmed by a few accepted frames (its rates estimated; an
            # acquisition's transient is not yet inside the filter's covariance).
            valid_kw["degraded"] = pl > al or out.n_updates < ig.confirm_frames
        return StateVector(
            t=t, mode=mode, valid=Validity(**valid_kw), covariance=cov, fitness=out.fitness,
            n_points=out.n_points, latency=max(t - out.t_meas, 0.0), **kw,
        )
