"""``DockingEnv``: rendezvous and docking seen through a TriDAR (Gymnasium API)."""

from __future__ import annotations

import math
from pathlib import Path
from typing import TYPE_CHECKING, Any

import gymnasium as gym
import numpy as np
import numpy.typing as npt
from gymnasium import spaces

from perception.config import (
    ConfigError,
    DockingEnvelopeConfig,
    MissionConfig,
    flatten_overrides,
    resolve_config,
    short_repr,
)
from perception.geometry import fast_cross, fast_matrix_to_quat, fast_quat_to_matrix, invert
from perception.pipeline.state import Mode, StateVector, Validity
from perception.targets import TargetModel, load_target
from tridar_env.observers import Observer, TriDARObserver, make_observer
from tridar_env.fly_around import FlyAroundTask
from tridar_env.schedule import decision_frames
from tridar_env.world import ContactState, World

if TYPE_CHECKING:
    from tridar_env.render import RenderState

FloatArray = npt.NDArray[np.float64]

#: (name, size, unit, description) of every block of the flat observation, in order.
OBSERVATION_STRUCTURE: tuple[tuple[str, int, str, str], ...] = (
    ("mode_onehot", 3, "-", "TriDAR mode: bearing, search, tracking"),
    ("valid", 8, "-", "validity: bearing, range, range_rate, position, velocity, attitude, angular_velocity, "
     "degraded (the pose's protection level exceeds its alert limit: not valid for closing in)"),
    ("port_position_dock", 3, "m", "port origin in the chaser docking frame (+z ahead)"),
    ("port_velocity_dock", 3, "m/s", "rate of port_position_dock"),
    ("q_dock_port", 4, "-", "port attitude in the docking frame, scalar first (identity = aligned)"),
    ("omega_port_dock", 3, "rad/s", "port angular velocity relative to the chaser, docking frame"),
    ("range", 1, "m", "sensor-to-target range"),
    ("range_rate", 1, "m/s", "range rate (negative closing)"),
    ("bearing", 2, "rad", "azimuth (+x) and elevation (up) of the target in the sensor frame"),
    ("fitness", 1, "-", "inlier fraction of the last registration"),
    ("fuel_fraction", 1, "-", "propellant left / initial propellant"),
    ("time_fraction", 1, "-", "elapsed steps / max_episode_steps"),
    ("chaser_rate_body", 3, "rad/s", "chaser inertial angular velocity, body frame (gyro)"),
    ("protection_level", 1, "m", "bound on the port position error at the integrity risk (0: no pose)"),
    ("alert_limit", 1, "m", "port position error tolerated at this range (0: no pose)"),
)
OBS_DIM = sum(s for _, s, _, _ in OBSERVATION_STRUCTURE)

#: Termination causes reported in ``info["termination"]``.
CAUSES = ("docked", "collision", "out_of_bounds", "out_of_fuel", "corridor_exit", "completed", "keep_out")


def observation_slices() -> dict[str, slice]:
    """Name -> slice of the flat observation vector."""
    out, i = {}, 0
    for name, size, _, _ in OBSERVATION_STRUCTURE:
        out[name] = slice(i, i + size)
        i += size
    return out


_SLICES = observation_slices()

#: ``info["mode"]`` of each mode.
_MODE_NAMES = {m: m.name.lower() for m in Mode}


def _resolve_config(
    config: str | Path | MissionConfig | dict[str, Any] | None, overrides: dict[str, Any]
) -> MissionConfig:
    """The mission a ``config`` argument names, with ``overrides`` on top (a ``ConfigError``
    naming the field for anything else, a config of the wrong type included)."""
    if isinstance(config, MissionConfig):
        if overrides:
            return resolve_config(None, {**flatten_overrides(config.model_dump(mode="json")), **overrides})
        return config
    if isinstance(config, dict):
        return resolve_config(None, {**config, **overrides})
    if config is not None and not isinstance(config, (str, Path)):
        raise ConfigError(
            f"config={short_repr(config)} ({type(config).__name__}); expected a mission YAML path, "
            "a mission name, a MissionConfig or a dict of overrides"
        )
    return resolve_config(config, overrides)


def as_action(action: Any, shape: tuple[int, ...], name: str = "action") -> FloatArray:
    """A policy's action as float64 of ``shape``, or a one-line ``ValueError`` naming what is wrong.

    Real numbers of any numeric dtype are accepted (``Box(-1, 1)`` in float32 is what the space
    samples); booleans, strings, complex numbers and Python objects are refused, as are a wrong
    shape (extra axes of length 1 aside) and NaN or inf. Values outside [-1, 1] are the caller's
    to clip.
    """
    try:
        a = np.asarray(action)
    except (ValueError, TypeError, OverflowError) as exc:  # ragged nesting, unconvertible objects
        raise ValueError(f"{name}={short_repr(action)} is not an array of numbers ({exc}); "
                         f"expected {shape} floats in [-1, 1]") from None
    if a.dtype.kind not in "iuf":
        raise ValueError(f"{name}={short_repr(action)} has dtype {a.dtype}; expected {shape} real numbers "
                         "(float32) in [-1, 1]")
    if a.shape != shape and a.squeeze().shape != shape:  # (1, 3) for (3,) is fine, (3, 2) for (2, 3) not
        raise ValueError(f"{name} has shape {a.shape}; expected {shape}")
    a = a.astype(np.float64).reshape(shape)
    finite = np.isfinite(a)
    if not finite.all():
        if a.ndim > 1:  # a batch: name the first environment's row
            i = int(np.flatnonzero(~finite.all(axis=tuple(range(1, a.ndim))))[0])
            name, a = f"{name}[{i}]", a[i]
        raise ValueError(
            f"{name}={short_repr(a.tolist())} contains NaN or inf; expected finite values in [-1, 1]"
        )
    return a


def make_target(cfg: MissionConfig) -> TargetModel:
    """The target model a mission config names (a library target or a mesh file with its port)."""
    tc = cfg.target
    try:
        if Path(tc.name).suffix:
            port = (tc.port_position_m, tc.port_axis) if tc.port_position_m is not None else None
            return load_target(tc.name, scale=tc.scale, port=port, mass=tc.mass_kg, reflectivity=tc.reflectivity)
        return load_target(tc.name)
    except OSError as exc:  # a missing mesh, a name too long for the file system
        raise ConfigError(f"target.name={short_repr(tc.name)}: {exc.strerror or exc}; expected a library "
                          "target or a readable mesh file") from None


def envelope_excess(c: ContactState, e: DockingEnvelopeConfig) -> float:
    """Largest relative violation of the capture envelope at a contact (0 inside it).

    Each limit contributes ``value / limit - 1`` when exceeded (and the axial speed
    ``1 - value / minimum`` when too slow); the largest is returned.
    """
    v = c.closing_speed
    slow = 1.0 - v / e.axial_speed_min_m_s if e.axial_speed_min_m_s > 0 and v < e.axial_speed_min_m_s else 0.0
    return max(
        0.0, slow,
        v / e.axial_speed_max_m_s - 1.0,
        c.lateral_offset / e.lateral_offset_max_m - 1.0,
        c.lateral_speed / e.lateral_speed_max_m_s - 1.0,
        c.misalignment_deg / e.misalignment_max_deg - 1.0,
        c.angular_rate_deg_s / e.angular_rate_max_deg_s - 1.0,
    )


class DockingEnv(gym.Env[npt.NDArray[np.float32], npt.NDArray[np.float32]]):
    """Rendezvous and docking with a target seen only through a simulated TriDAR.

    ## Description
    A chaser spacecraft approaches a target (an ISS-like port, a tumbling microsatellite, ...) in
    the target's Hill/LVLH frame under Clohessy-Wiltshire (or two-body) relative motion. The agent
    sees the TriDAR state vector — mode, validity flags, estimated relative pose and rates — never
    the simulator's truth (which is in ``info`` for logging). One step is one TriDAR frame
    (``frame_period_s``, default 0.2 s = 5 Hz) times ``frame_skip``; the control is held over it
    and the pipeline still processes every frame (the agent sees the step's last state vector).

    ## Action Space
    ``Box(-1, 1, (3,))`` thrust per axis scaled to ``max_thrust_n`` [N], in the chaser body frame
    (or LVLH, per ``dynamics.chaser.thrust_frame``). With ``dynamics.chaser.attitude: controlled``
    it is ``Box(-1, 1, (6,))``: thrust then body torque scaled to ``max_torque_nm`` [N m]. Values
    outside [-1, 1] are clipped and counted in ``info["clipped_actions"]``; NaN, inf, booleans,
    strings, complex numbers or a wrong shape raise a one-line ``ValueError``.

    ## Observation Space
    ``Box((OBS_DIM,), float32)``, laid out by :data:`OBSERVATION_STRUCTURE`:

    =====================  ====  =======  =============================================================
    block                  size  unit     meaning
    =====================  ====  =======  =============================================================
    mode_onehot            3     -        bearing / search / tracking
    valid                  8     -        bearing, range, range_rate, position, velocity, attitude, rate,
                                          degraded (protection level above the alert limit)
    port_position_dock     3     m        estimated port origin in the chaser docking frame
    port_velocity_dock     3     m/s      its rate
    q_dock_port            4     -        estimated port attitude in the docking frame (w, x, y, z)
    omega_port_dock        3     rad/s    port angular velocity relative to the chaser
    range, range_rate      1+1   m, m/s   to the target
    bearing                2     rad      azimuth, elevation in the sensor frame
    fitness                1     -        registration inlier fraction
    fuel_fraction          1     -        propellant left
    time_fraction          1     -        elapsed / max steps
    chaser_rate_body       3     rad/s    chaser gyro
    protection_level       1     m        bound on the port position error (integrity risk)
    alert_limit            1     m        error tolerated at this range
    =====================  ====  =======  =============================================================

    Invalid blocks hold zeros (never stale numbers); the validity flags say which. A degraded pose
    (``valid`` flag 8) keeps its numbers, so a controller can back away on it, but must not close
    in on it.

    ## Rewards
    ``progress`` (decrease of the true dock-to-port distance), ``lateral`` (decrease of the
    offset from the port axis), ``alignment`` (-(1 - cos) of the line of sight off the port axis),
    ``speed_limit`` (closing faster than ``floor + gain * distance``), ``speed_profile`` (closing
    speed off ``min(mid-envelope speed + speed_profile_gain_s * distance, speed_profile_max_m_s)``),
    ``time`` (per second),
    ``fuel`` (propellant used [kg]), ``success`` (docked), ``collision`` (graded for a port contact
    just outside the envelope, see :func:`envelope_excess`) and ``corridor`` (leaving the corridor
    or the bounds); each weighted by ``env.reward`` and reported as ``info["reward_<name>"]``;
    they sum to the reward. ``progress`` and ``lateral`` are potential-based shaping.

    ## Starting State
    The chaser docking frame faces the port on its axis at ``env.initial.range_m`` (dispersed),
    with lateral and velocity dispersions; the target holds LVLH, holds inertial, or tumbles.

    ## Episode End
    Terminated on ``docked`` (contact inside the IDSS-like envelope ``env.envelope``),
    ``collision`` (contact outside it, or the hull meets the mesh), ``out_of_bounds``,
    ``out_of_fuel`` or ``corridor_exit``; truncated by ``TimeLimit`` (``max_episode_steps``).

    ## Tasks and step length
    ``env.task: fly_around`` (FlyAround-v0) replaces docking's termination and rewards with the
    fly-around's (:mod:`tridar_env.fly_around`: ``completed``, ``keep_out``; ``reward_sweep``...).
    ``env.decision_schedule`` (FarRendezvous-v0) lengthens a step with the range the agent last
    saw (:func:`tridar_env.schedule.decision_frames`); ``info["step_dt"]`` is each step's length.

    ## Arguments
    ``config``: mission YAML path, bare mission name, ``MissionConfig`` or a dict of overrides;
    ``perception``: ``"tridar"`` | ``"truth"`` | ``"truth+noise"`` (overrides the config);
    ``render_mode``: ``"rgb_array"`` or ``"human"``; ``**overrides``: nested config values
    (``env__frame_skip=2``).

    Example:
        >>> import gymnasium as gym, tridar_env
        >>> env = gym.make("TriDAR/FinalApproach-v0", perception="truth")
        >>> obs, info = env.reset(seed=0)
        >>> obs.shape == env.observation_space.shape
        True
    """

    metadata = {"render_modes": ["rgb_array", "human"], "render_fps": 5}

    def __init__(
        self,
        config: str | Path | MissionConfig | dict[str, Any] | None = None,
        *,
        perception: str | None = None,
        render_mode: str | None = None,
        **overrides: Any,
    ) -> None:
        if perception is not None:
            overrides["env__perception"] = perception
        self.cfg = _resolve_config(config, overrides)
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(f"render_mode={render_mode!r}; expected one of {self.metadata['render_modes']}")
        self.render_mode = render_mode
        self.target = make_target(self.cfg)
        self.world = World(self.cfg, self.target)
        self.observer: Observer = make_observer(self.cfg, self.target)
        ch = self.cfg.dynamics.chaser
        n_act = 6 if ch.attitude == "controlled" else 3
        self.action_space = spaces.Box(-1.0, 1.0, shape=(n_act,), dtype=np.float32)
        self._obs_low, self._obs_high = self._bounds()
        self.observation_space = spaces.Box(self._obs_low, self._obs_high, dtype=np.float32)
        self._T_dock_sensor = invert(self.world.T_chaser_dock) @ self.world.T_chaser_sensor
        self._T_target_port = np.array(self.target.T_target_port, dtype=np.float64)
        self._obs_low64 = self._obs_low.astype(np.float64)
        self._obs_high64 = self._obs_high.astype(np.float64)
        self._validity_flags: dict[Validity, FloatArray] = {}  # observation block per flag set
        self._steps = 0
        self._ready = False
        self._state: StateVector | None = None
        self._prev_distance = 0.0
        self._prev_lateral = 0.0
        self._fly_around = FlyAroundTask(self.cfg.env) if self.cfg.env.task == "fly_around" else None
        pipeline = self.cfg.env.perception in ("tridar", "flash")
        self._pre_frame = pipeline and self.cfg.env.decision_schedule is not None
        self._every_frame = pipeline and self.cfg.env.decision_schedule is None
        self._step_dt = 0.0
        self._decision_range: float | None = None
        self._renderer: Any = None
        self.history: list[dict[str, Any]] = []

    # ------------------------------------------------------------------ spaces
    def _bounds(self) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.float32]]:
        R = 2.0 * self.cfg.env.max_range_m + 50.0
        per_block = {
            "mode_onehot": (0.0, 1.0), "valid": (0.0, 1.0), "port_position_dock": (-R, R),
            "port_velocity_dock": (-20.0, 20.0), "q_dock_port": (-1.0, 1.0),
            "omega_port_dock": (-np.pi, np.pi), "range": (0.0, R), "range_rate": (-20.0, 20.0),
            "bearing": (-np.pi, np.pi), "fitness": (0.0, 1.0), "fuel_fraction": (0.0, 1.0),
            "time_fraction": (0.0, 1.0), "chaser_rate_body": (-np.pi, np.pi),
            "protection_level": (0.0, R), "alert_limit": (0.0, R),
        }
        lo = np.concatenate([np.full(s, per_block[n][0]) for n, s, _, _ in OBSERVATION_STRUCTURE])
        hi = np.concatenate([np.full(s, per_block[n][1]) for n, s, _, _ in OBSERVATION_STRUCTURE])
        return lo.astype(np.float32), hi.astype(np.float32)

    @property
    def observation_structure(self) -> tuple[tuple[str, int, str, str], ...]:
        """Every block of the observation with its size, unit and meaning."""
        return OBSERVATION_STRUCTURE

    # ------------------------------------------------------------------ observation
    def _observation(self, sv: StateVector) -> npt.NDArray[np.float32]:
        v = sv.valid
        S = _SLICES
        obs = np.zeros(OBS_DIM)
        obs[int(sv.mode)] = 1.0  # mode_onehot
        flags = self._validity_flags.get(v)
        if flags is None:
            flags = self._validity_flags[v] = v.as_array().astype(np.float64)
        obs[S["valid"]] = flags
        if v.position and v.attitude:
            R_ds = self._T_dock_sensor[:3, :3]
            R_st = fast_quat_to_matrix(sv.quaternion)
            T_st = np.empty((4, 4))
            T_st[:3, :3] = R_st
            T_st[:3, 3] = sv.position
            T_st[3] = (0.0, 0.0, 0.0, 1.0)
            T_dock_port = self._T_dock_sensor @ T_st @ self._T_target_port
            obs[S["port_position_dock"]] = T_dock_port[:3, 3]
            obs[S["q_dock_port"]] = fast_matrix_to_quat(T_dock_port[:3, :3])
            if v.velocity and v.angular_velocity:
                r_port_s = R_st @ self._T_target_port[:3, 3]
                obs[S["port_velocity_dock"]] = R_ds @ (sv.velocity + fast_cross(sv.angular_velocity, r_port_s))
            if v.angular_velocity:
                obs[S["omega_port_dock"]] = R_ds @ sv.angular_velocity
        if v.range:
            obs[S["range"]] = sv.range
        if v.range_rate:
            obs[S["range_rate"]] = sv.range_rate
        if v.bearing:
            obs[S["bearing"]] = sv.bearing
        obs[S["fitness"]] = sv.fitness
        w = self.world
        fuel0 = self.cfg.dynamics.chaser.propellant_kg
        obs[S["fuel_fraction"]] = w.mass.propellant_kg / fuel0 if fuel0 > 0 else 0.0
        obs[S["time_fraction"]] = self._steps / self.cfg.env.max_episode_steps
        obs[S["chaser_rate_body"]] = w.gyro()
        obs[S["protection_level"]] = sv.protection_level
        obs[S["alert_limit"]] = sv.alert_limit
        # np.clip in place, without its dispatch overhead (NaN propagates the same way).
        np.maximum(obs, self._obs_low64, out=obs)
        np.minimum(obs, self._obs_high64, out=obs)
        return obs.astype(np.float32)

    # ------------------------------------------------------------------ API
    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[npt.NDArray[np.float32], dict[str, Any]]:
        super().reset(seed=seed)
        self.world.reset(self.np_random)
        self.observer.reset(self.np_random)
        self._steps = 0
        self._ready = True
        self._prev_distance = self._distance()
        self._prev_lateral = self.world.contact().lateral_offset
        if self._fly_around is not None:
            self._fly_around.reset(self.world)
        self._step_dt = 0.0
        if self.cfg.env.initial.pose_known and isinstance(self.observer, TriDARObserver):
            # Undocking: the mated relative pose is known; it seeds the first acquisition.
            self.observer.pipeline.seed_pose(self.world.sensor_truth().T_sensor_target, self.world.t)
        self._state = self.observer.observe(self.world, self.np_random)
        self._decision_range = float(self._state.range) if self._state.valid.range else None
        self.history = []
        info = self._info(self._state, {}, "", 0)
        self._log(info)
        if self.render_mode == "human":
            self.render()
        return self._observation(self._state), info

    def step(
        self, action: npt.ArrayLike
    ) -> tuple[npt.NDArray[np.float32], float, bool, bool, dict[str, Any]]:
        if not self._ready:
            raise RuntimeError("DockingEnv.step() called before reset(); call reset() first")
        a = as_action(action, self.action_space.shape)
        clipped = int(np.count_nonzero(np.abs(a) > 1.0))
        a = np.minimum(np.maximum(a, -1.0), 1.0)
        ch = self.cfg.dynamics.chaser
        thrust = a[:3] * ch.max_thrust_n
        torque = a[3:] * ch.max_torque_nm if a.size == 6 else None
        fuel_before = self.world.mass.propellant_kg
        cause = ""
        frames = decision_frames(self.cfg.env, self._decision_range)
        for i in range(frames):
            self.world.step(thrust, torque)
            if self._fly_around is not None:
                self._fly_around.after_frame(self.world)
            cause = self._termination()
            if cause:
                break
            if i < frames - 1 and (self._every_frame or (i == frames - 2 and self._pre_frame)):
                # The pipeline runs at its frame rate whatever the decision rate (its tracking,
                # filter and integrity checks are built for it). With a decision schedule it
                # takes the frame before the decision only: what it publishes at the decision
                # (a frame's output is available only after its processing latency).
                self.observer.observe(self.world, self.np_random)
        self._step_dt = self.cfg.env.frame_period_s * frames  # the step's planned length [s]
        self._steps += 1
        sv = self.observer.observe(self.world, self.np_random)
        self._state = sv
        if sv.valid.range:
            self._decision_range = float(sv.range)
        fuel_used = fuel_before - self.world.mass.propellant_kg
        terms = (self._fly_around.reward_terms(self.world, cause, fuel_used, self._step_dt)
                 if self._fly_around is not None else self._reward_terms(cause, fuel_used))
        reward = float(sum(terms.values()))
        info = self._info(sv, terms, cause, clipped)
        self._log(info)
        if cause:
            self._ready = False
        if self.render_mode == "human":
            self.render()
        return self._observation(sv), reward, bool(cause), False, info

    # ------------------------------------------------------------------ physics outcomes
    def _distance(self) -> float:
        T_lp, T_ld = self.world.T_lvlh_port, self.world.T_lvlh_dock
        d = T_ld[:3, 3] - T_lp[:3, 3]
        return math.sqrt(float(d @ d))

    def _port_contact(self, c: ContactState) -> bool:
        """The docking interface meets the port: the dock has just reached the port plane from
        the front (no deeper than the hull radius behind it) near the axis. A chaser far behind
        the plane of a port that has turned away (a tumbling target) is not touching it."""
        hull = self.cfg.dynamics.chaser.hull_radius_m
        return -hull <= c.axial_distance <= 0.0 and c.lateral_offset <= hull

    def _termination(self) -> str:
        if self._fly_around is not None:
            return self._fly_around.termination(self.world)
        w, env = self.world, self.cfg.env
        c = w.contact()
        if self._port_contact(c):
            e = env.envelope
            inside = (
                e.axial_speed_min_m_s <= c.closing_speed <= e.axial_speed_max_m_s
                and c.lateral_offset <= e.lateral_offset_max_m
                and c.lateral_speed <= e.lateral_speed_max_m_s
                and c.misalignment_deg <= e.misalignment_max_deg
                and c.angular_rate_deg_s <= e.angular_rate_max_deg_s
            )
            return "docked" if inside else "collision"
        if w.hull_touches():
            return "collision"
        r = w.state[:3]
        if math.sqrt(float(r @ r)) > env.max_range_m:
            return "out_of_bounds"
        if env.corridor_half_angle_deg is not None and c.axial_distance > 2.0:
            off = math.degrees(math.atan2(c.lateral_offset, c.axial_distance))
            if off > env.corridor_half_angle_deg or c.axial_distance < 0:
                return "corridor_exit"
        if w.mass.propellant_kg <= 0.0:
            return "out_of_fuel"
        return ""

    def _reward_terms(self, cause: str, fuel_used: float) -> dict[str, float]:
        env = self.cfg.env
        rw = env.reward
        c = self.world.contact()
        d = self._distance()
        progress = self._prev_distance - d
        lateral = self._prev_lateral - c.lateral_offset
        self._prev_distance, self._prev_lateral = d, c.lateral_offset
        los = np.arctan2(c.lateral_offset, max(c.axial_distance, 1e-3))
        dt = self._step_dt
        v_max = env.speed_limit_floor_m_s + env.speed_limit_gain_s * max(c.axial_distance, 0.0)
        e = env.envelope
        v_ref = min(0.5 * (e.axial_speed_min_m_s + e.axial_speed_max_m_s)
                    + env.speed_profile_gain_s * max(c.axial_distance, 0.0), env.speed_profile_max_m_s)
        collision = 0.0
        if cause == "collision":
            collision = -rw.collision
            if self._port_contact(c):
                collision *= min(1.0, rw.near_miss + envelope_excess(c, env.envelope))
        return {
            "reward_progress": rw.progress * progress,
            "reward_lateral": rw.lateral * lateral,
            "reward_alignment": -rw.alignment * (1.0 - float(np.cos(los))),
            "reward_speed_limit": -rw.speed_limit * max(0.0, c.closing_speed - v_max),
            "reward_speed_profile": -rw.speed_profile * abs(c.closing_speed - v_ref) * dt,
            "reward_time": -rw.time * dt,
            "reward_fuel": -rw.fuel * fuel_used,
            "reward_success": rw.success if cause == "docked" else 0.0,
            "reward_collision": collision,
            "reward_corridor": -rw.corridor if cause in ("corridor_exit", "out_of_bounds") else 0.0,
        }

    def _info(self, sv: StateVector, terms: dict[str, float], cause: str, clipped: int) -> dict[str, Any]:
        w = self.world
        truth = w.sensor_truth()
        c = w.contact()
        pos_err = att_err = float("nan")
        info: dict[str, Any] = dict(terms)
        if sv.valid.position:
            dp = sv.position - truth.T_sensor_target[:3, 3]
            pos_err = math.sqrt(float(dp @ dp))
        if sv.valid.attitude:
            # trace(R_true^T R_est) without forming the product
            tr = float(np.sum(truth.T_sensor_target[:3, :3] * fast_quat_to_matrix(sv.quaternion)))
            att_err = math.degrees(math.acos(min(max((tr - 1.0) / 2.0, -1.0), 1.0)))
        mode = _MODE_NAMES.get(sv.mode)
        info.update(
            t=w.t,
            mode=mode if mode is not None else Mode(sv.mode).name.lower(),
            termination=cause,
            clipped_actions=clipped,
            truth_r_lvlh=w.state[:3].copy(),
            truth_v_lvlh=w.state[3:].copy(),
            truth_T_sensor_target=truth.T_sensor_target,
            contact=c,
            propellant_kg=w.mass.propellant_kg,
            delta_v=w.delta_v,
            n_points=sv.n_points,
            step_dt=self._step_dt,
        )
        if self._fly_around is not None:
            info.update(self._fly_around.info(w))
        # Estimation errors only when there is an estimate (NaN in info would break equality
        # checks such as Gymnasium's determinism test); consumers use .get(key, nan).
        if sv.valid.position:
            info["estimate_position_error_m"] = pos_err
        if sv.valid.attitude:
            info["estimate_attitude_error_deg"] = att_err
        return info

    def _log(self, info: dict[str, Any]) -> None:
        self.history.append({
            "t": info["t"], "r": info["truth_r_lvlh"], "mode": info["mode"],
            "pos_err": info.get("estimate_position_error_m", float("nan")),
            "att_err": info.get("estimate_attitude_error_deg", float("nan")),
            "est_r": self._estimated_chaser_lvlh(),
        })

    def _estimated_chaser_lvlh(self) -> FloatArray | None:
        sv = self._state
        if sv is None or not sv.valid.position:
            return None
        # Chaser position from the estimated target position and the chaser's own attitude.
        T_ls = self.world.T_lvlh_sensor
        target_in_lvlh_from_est = T_ls[:3, :3] @ sv.position + T_ls[:3, 3]
        return self.world.state[:3] - target_in_lvlh_from_est

    @property
    def state_vector(self) -> StateVector | None:
        """The latest TriDAR state vector (what the observation was built from)."""
        return self._state

    # ------------------------------------------------------------------ rendering
    def render(self) -> npt.NDArray[np.uint8] | None:
        if self.render_mode is None:
            gym.logger.warn("render() called without a render_mode; pass render_mode='rgb_array'")
            return None
        if self._renderer is None:
            from tridar_env.render import Renderer

            self._renderer = Renderer()
        frame = self._renderer.draw(self._render_state())
        if self.render_mode == "human":
            self._renderer.show(frame)
            return None
        return frame

    def _render_state(self) -> RenderState:
        """What a frame shows: the logged truth and estimate paths and the current scene."""
        from tridar_env.render import RenderState

        w, hist, sv = self.world, self.history, self._state
        est = [h["est_r"] for h in hist if h["est_r"] is not None]
        last = hist[-1] if hist else {}
        valid_range = sv is not None and sv.valid.range
        return RenderState(
            t=w.t,
            r_lvlh=np.array([h["r"] for h in hist]) if hist else w.state[None, :3],
            est_r_lvlh=np.array(est) if est else None,
            T_lvlh_port=w.T_lvlh_port,
            corridor_half_angle_deg=(
                self.cfg.env.corridor_half_angle_deg or self.cfg.pipeline.corridor.half_angle_deg
            ),
            target=self.target,
            T_sensor_target=w.sensor_truth().T_sensor_target,
            fov_deg=self.cfg.sensor.fov_deg,
            cloud_points=getattr(self.observer.last_cloud, "points", None),
            mode=last.get("mode", "-"),
            range_m=sv.range if valid_range else None,
            range_rate_m_s=sv.range_rate if valid_range else None,
            pos_err_m=last.get("pos_err", np.nan),
            att_err_deg=last.get("att_err", np.nan),
        )

    def close(self) -> None:
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None
