"""The TriDAR: sensor + modes + estimators + filter -> :class:`~perception.pipeline.state.StateVector`.

Following the MILD approach (seed 000 section 4.3) the algorithms drive the scanner: each frame the
mode logic decides what to scan (full field, the bearing box, or a region of interest around the
predicted pose) and which algorithm runs on the returns (centroid bearing, PAH acquisition or an
external seed, ICP tracking). Processing time is part of the simulation: a frame's output becomes
available ``latency`` seconds after its scan ends, and no new scan starts while the processor is
busy, so the frame rate follows from scan time plus processing. The configured latencies are used
(not the measured wall time), which keeps runs bitwise reproducible.

:class:`TriDAR` is the frame loop: each frame goes to the handler of the current mode
(:mod:`~perception.pipeline.bearing`, :mod:`~perception.pipeline.search`,
:mod:`~perception.pipeline.tracking`), which share the pipeline's filter and track bookkeeping; the
ambiguity monitor (:mod:`~perception.pipeline.twins`), the slide monitor
(:mod:`~perception.pipeline.slides`), the rival monitor (:mod:`~perception.pipeline.rivals`) and
the publisher (:mod:`~perception.pipeline.publish`) are collaborators.

Output timing: :meth:`TriDAR.step` returns the newest output available at the call time, with the
filter state propagated from its measurement time to the call time (what a navigation filter
publishes); ``StateVector.latency`` is the age of the underlying measurement. A pose older than
``loss_of_track_frames`` frame periods plus the tracking latency is no longer published as valid.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt
from scipy.spatial.transform import Rotation

from perception.config import MissionConfig
from perception.estimation.registration import RegistrationResult, prepare_model
from perception.geometry import check_rigid, fast_rotvec_to_matrix, make_T
from perception.pipeline.bearing import BearingMode
from perception.pipeline.filter import EgoMotion, PoseFilter
from perception.pipeline.modes import ModeLogic, corridor_constraint
from perception.pipeline.observability import ScanPlanner
from perception.pipeline.publish import Publisher
from perception.pipeline.rivals import RivalMonitor
from perception.pipeline.search import SearchMode
from perception.pipeline.state import Mode, StateVector, TruthScene
from perception.pipeline.tracking import TrackingMode, deskew
from perception.pipeline.slides import SlideMonitor
from perception.pipeline.twins import TwinMonitor
from perception.sensing.pointcloud import PointCloud
from perception.sensing.sensors.tridar import TriDARSensor
from perception.targets import TargetModel

FloatArray = npt.NDArray[np.float64]

__all__ = ["PipelineStats", "TriDAR", "approach_pose", "deskew", "nominal_attitude"]

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
    corridor_exits: int = 0  # tracks dropped for leaving the approach corridor
    outline_refinements: int = 0
    outline_accepted: int = 0
    registration_time_s: list[float] = field(default_factory=list)


class TriDAR:
    """The TriDAR box: call :meth:`step` once per frame with the truth scene (or a cloud).

    The mode handlers (``bearing``, ``search``, ``tracking``) and the collaborators (``twins``,
    the ambiguity monitor; ``slides``; ``rivals``; ``publisher``) work on the state kept here: the filter, the track's
    bookkeeping (``n_updates``: accepted updates of the track; ``lost_track``: the filter of the
    last lost track, for reacquisition; ``search_started``), the frame timing and the last cloud
    and registration.

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
        #: The mission's approach corridor (PAH pose constraint) or None: built once, read by
        #: search, tracking and the twin and turn monitors.
        self.corridor = corridor_constraint(self.pc, self.R_nominal)
        self.frame_period = 1.0 / self.pc.frame_rate_hz
        self.max_pose_age = self.pc.loss_of_track_frames * self.frame_period + self.pc.tracking_latency_s + 1e-9
        self.rng = np.random.default_rng(0)
        self.external_seed: tuple[float, FloatArray] | None = None
        self.thermal: Any = None
        if self.pc.thermal_bearing:
            from perception.sensing.sensors.thermal import ThermalImager

            self.thermal = ThermalImager(config.thermal)
        self.bearing = BearingMode(self)
        self.search = SearchMode(self)
        self.tracking = TrackingMode(self)
        self.twins = TwinMonitor(self)
        self.slides = SlideMonitor(self)
        self.rivals = RivalMonitor(self)
        self.publisher = Publisher(self.pc, self.target.T_target_port[:3, 3], self.max_pose_age,
                                   tof_bias_m=config.sensor.tof.bias_m,
                                   accuracy=self.accuracy_at if self.pc.integrity.accuracy_calibration else None)
        self._handlers = {Mode.BEARING: self.bearing, Mode.SEARCH: self.search, Mode.TRACKING: self.tracking}
        self.reset(self.rng)

    # ------------------------------------------------------------------ lifecycle
    def reset(self, rng: np.random.Generator) -> None:
        """Start-up: bearing mode, empty filters, fresh counters; ``rng`` drives the sensor and PAH."""
        self.rng = rng
        self.external_seed = None
        inertia = self.target.inertia if self.pc.target_rotation == "torque_free" else None
        self.filter = PoseFilter(*self.process_noise(),
                                 init_rate_sigma=math.radians(self.pc.initial_rate_sigma_deg_s),
                                 ref_point=self.target.T_target_port[:3, 3], inertia=inertia,
                                 range_bias_m=abs(self.cfg.sensor.tof.bias_m),
                                 scatter_window=self.pc.integrity.accuracy_scatter_window_frames or 0)
        self.ego: EgoMotion | None = None
        self.logic.reset(0.0)
        self.sensor.frame_counter = 0
        self.busy_until = -np.inf
        self.frame_index = 0
        self.last_cloud: PointCloud | None = None
        self.last_result: RegistrationResult | None = None
        self.search_started: float | None = None
        self.last_pose_t = -np.inf
        self.n_updates = 0
        self.lost_track: PoseFilter | None = None
        self.accepted_fitness = 1.0  # fitness of the track's last accepted registration
        for part in (*self._handlers.values(), self.twins, self.slides, self.rivals, self.publisher):
            part.reset()
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

    @property
    def accuracy_table(self) -> Any:
        """The correlated registration error calibrated on this target's model for this
        mission (:func:`perception.pipeline.calibration.calibrate_accuracy` at
        ``calibration.POSES`` aspects by ``REPEATS`` scans over ``approach_ranges``), on a
        fault-free copy of the mission's sensor and from ``CALIBRATION_SEED``: the same model
        and settings give the same table. 10-25 s once per target and settings (cached on the
        target); what ``tridar-env check-target`` shows and ``integrity.accuracy_calibration``
        publishes."""
        from perception.pipeline import calibration as cal

        cfg = self.cfg
        # Fault-free, and without the time of flight's configured range offset: the filter's
        # accuracy covariance carries that one (PoseFilter's range_bias_m), frame by frame.
        clean = cfg.sensor.model_copy(update={"faults": type(cfg.sensor.faults)(),
                                              "tof": cfg.sensor.tof.model_copy(update={"bias_m": 0.0})})
        key = ("accuracy_table", clean.model_dump_json(), cfg.pipeline.model_dump_json(),
               cfg.env.initial.model_dump_json())

        def build() -> Any:
            rng = np.random.default_rng(cal.CALIBRATION_SEED)
            tri = TriDAR(cfg, self.target, sensor=TriDARSensor(clean))
            tri.reset(rng)
            return cal.calibrate_accuracy(tri, cal.approach_ranges(cfg), cal.POSES, cal.REPEATS, rng)

        return self.target.cached(key, build)

    def accuracy_at(self, range_m: float) -> tuple[float, float]:
        """(across, along) [m]: :attr:`accuracy_table` at a sensor-to-port range."""
        across, along, _ = self.accuracy_table.at(range_m)
        return across, along

    def process_noise(self) -> tuple[float, float]:
        """The filter's white acceleration and angular-acceleration densities, squared
        [(m/s^2)^2/Hz, (rad/s^2)^2/Hz]: the mission's ``process_noise_*``, and with ego-motion
        aiding the chaser's IMU noise on top (``dynamics.chaser``). One reading a host step of
        ``env.frame_period_s`` with white noise ``s`` moves the filter's velocity (rate) by
        ``s dt`` a step, a random walk of density ``s^2 dt``; the filter that reads the IMU must
        carry it, or a quiet density (a target in free fall, the chaser's thrust read by the
        IMU) makes it trust a dead-reckoned pose the noisy IMU has already moved."""
        qa, qw = self.pc.process_noise_accel**2, self.pc.process_noise_angacc**2
        if self.pc.ego_motion:
            ch, dt = self.cfg.dynamics.chaser, self.cfg.env.frame_period_s
            qa += ch.accel_noise_m_s2**2 * dt
            qw += math.radians(ch.gyro_noise_deg_s) ** 2 * dt
        return qa, qw

    def prepare(self) -> None:
        """Build what search needs now rather than in the first search frame: the PAH database and
        the target's near-symmetries (about 1 s for the ISS-like port; once per process and target,
        cached on the target), and with ``integrity.accuracy_calibration`` the model's accuracy
        table (:attr:`accuracy_table`, 10-25 s)."""
        self.pah.near_symmetries()
        if self.pc.integrity.accuracy_calibration:
            _ = self.accuracy_table

    # ------------------------------------------------------------------ the frame
    def take_ego(self, t: float, ego: EgoMotion) -> None:
        """Carry the filter to ``t`` [s] over the host's step just flown, then hold ``ego`` from now on.

        ``ego`` is read at the end of that step: its accelerometer gives the step's mean
        acceleration in the sensor axes at the step's end, and the mean rate is that of the
        gyro's readings at the step's two ends. The filter carries the acceleration from the
        step's start, so it is turned back by the step's rotation. (Holding the previous step's
        readings over it lagged the thrust by one step: on a tumbling target the sync chaser's
        manoeuvres put the prediction 6 cm off within a second at 57 m, against a flash
        registration good to 1 mm, and the filter's gate restarted the track every second.
        Applied in the start's axes without turning it back, the thrust of a chaser circling a
        tumbling port at 6 deg/s was off by 1.2 deg, a steady 1-2 mm/s^2 the filter did not
        model: its pose drifted 2-3 cm from registrations good to 0.3 mm, just past its
        protection level.)
        """
        if not isinstance(ego, EgoMotion):
            raise ValueError(f"ego={type(ego).__name__}; expected an EgoMotion")
        # A standing rival (perception.pipeline.rivals) is another hypothesis of the same target
        # seen from the same host: the host's motion carries it as it carries the track. (Left
        # on the motion it had when it stood, a rival that stood while the chaser braked went on
        # braking: 1.3 m off the track in 40 s, all of it on the protection level, and a
        # generated cylinder bus held degraded at 7 m, 2 mm off.)
        for f in (self.filter, self.rivals.rival):
            if f is None:
                continue
            if f.initialized and f.t < t:
                old = self.ego
                omega = ego.omega if old is None else 0.5 * (old.omega + ego.omega)
                # E turns the step's start axes into its end's (PoseFilter._propagate): E^T back.
                turn_back = fast_rotvec_to_matrix(omega * (t - f.t))
                f.set_ego(EgoMotion(omega, ego.accel, ego.gravity_gradient).turned(turn_back))
                f.predict(t)
            f.set_ego(ego)
        self.ego = ego

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
            self.take_ego(t, ego)
        if self.logic.restart_due(t) and self.logic.mode != Mode.BEARING and not self._restart_inhibited():
            self._restart(t)
        if t >= self.busy_until - 1e-12:
            mode = self.logic.mode
            self.stats.frames += 1
            self.stats.frames_by_mode[mode.name.lower()] += 1
            self._handlers[mode].frame(scene, t)
            self.frame_index += 1
        return self.publisher.publish(t, self.logic.mode, self.ego)

    def scan(self, scene: TruthScene | PointCloud, t: float, pattern: Any) -> PointCloud:
        """The frame's cloud: ``scene`` itself if already a cloud, else the sensor's scan of it
        with ``pattern`` starting at ``t`` [s]."""
        if isinstance(scene, PointCloud):
            return scene
        # Faults are indexed by the sensor's nominal frame slots (time), not by processed frames:
        # a 30-frame blackout lasts 30 / frame_rate seconds whatever the modes' processing times.
        cloud = self.sensor.scan(
            self.target, scene.T_sensor_target, pattern, self.rng, motion=scene.motion, t0=t,
            frame_index=round(t * self.pc.frame_rate_hz),
        )
        return cloud

    def _tracking_pattern(self, T_pred: FloatArray, t: float = 0.0) -> tuple[Any, str]:
        """The tracking scan around ``T_pred`` (:meth:`TrackingMode.pattern`; kept for tests)."""
        return self.tracking.pattern(T_pred, t)

    # ------------------------------------------------------------------ planned restarts
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
        self.n_updates = 0
        self.search_started = t if self.logic.mode == Mode.SEARCH else None
