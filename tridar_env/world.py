"""The truth simulation behind the environment: relative orbit, target and chaser attitude, mass.

Long module: one truth state (orbit, attitudes, mass, the IMU that reads it) that every reader
shares through the same cached views.

Everything here is truth. The environment hands the sensor a :class:`~perception.pipeline.state.TruthScene`
built from it and exposes it in ``info`` for logging; observations never read it directly.

Frames: LVLH/Hill of the target (origin at the target centre of mass; x radial, y along-track,
z orbit normal); target body (``T_lvlh_target``); chaser body (``T_lvlh_chaser``) with the docking
mechanism at ``T_chaser_dock`` (its +z is the docking axis) and the TriDAR at ``T_chaser_sensor``
(+z boresight). The ideal attitude law keeps the chaser docking frame parallel to the port frame,
facing it: ``R_port_dock = diag(1, -1, -1)``.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt
import trimesh
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from perception.config import MissionConfig
from perception.geometry import fast_cross, fast_invert, fast_quat_to_matrix, make_T, rotation_z
from perception.pipeline.filter import EgoMotion, gravity_gradient
from perception.pipeline.state import TruthScene
from perception.sensing.sensors.motion import RelativeMotion
from perception.targets import TargetModel
from tridar_env.dynamics import (
    ChaserMass,
    CWPropagator,
    NonlinearRelativePropagator,
    TargetAttitudeModel,
    mean_motion,
    rigid_body_rates,
    spin_with_nutation,
)

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]

#: The docking frame faces the port: x along port x, z against port z.
R_PORT_DOCK = np.diag([1.0, -1.0, -1.0])
R_PORT_DOCK.setflags(write=False)

_LAST_ROW = np.array([0.0, 0.0, 0.0, 1.0])
# Longest edge of the subdivided mesh whose vertices bound the hull clearance from below [m].
_SURFACE_EDGE_M = 0.5


def _pose(R: FloatArray, t: FloatArray | None = None) -> FloatArray:
    """4x4 transform from a (3, 3) rotation and a (3,) translation (``make_T`` without checks)."""
    T = np.empty((4, 4))
    T[:3, :3] = R
    T[:3, 3] = 0.0 if t is None else t
    T[3] = _LAST_ROW
    return T


def _aim_sensor(R_lvlh_chaser: FloatArray, r_chaser: FloatArray, T_chaser_sensor: FloatArray) -> FloatArray:
    """The chaser attitude nearest ``R_lvlh_chaser`` whose sensor boresight (+z) points at the
    target's centre of mass (LVLH origin), the chaser at ``r_chaser``: the smallest turn, found again
    from the moved sensor (the turn moves it about the chaser's centre) until it is nil."""
    R = np.asarray(R_lvlh_chaser, dtype=np.float64)
    for _ in range(50):
        los = -(r_chaser + R @ T_chaser_sensor[:3, 3])
        b = R @ T_chaser_sensor[:3, 2]
        axis = np.cross(b, los)
        s, c = float(np.linalg.norm(axis)), float(b @ los)
        if s <= 1e-12 * max(abs(c), 1e-300):
            if c >= 0.0:  # on target (or the sensor at the centre of mass: nothing to aim at)
                return R
            axis = np.cross(b, np.eye(3)[int(np.argmin(np.abs(b)))])  # pointing straight away
            axis /= np.linalg.norm(axis)
            R = Rotation.from_rotvec(np.pi * axis).as_matrix() @ R
            continue
        R = Rotation.from_rotvec(axis * (math.atan2(s, c) / s)).as_matrix() @ R
    return R


def _frozen(a: FloatArray) -> FloatArray:
    """Mark an array that is shared for a whole episode read-only (mutating it is a bug)."""
    a.setflags(write=False)
    return a


_ORBIT_NORMAL = _frozen(np.array([0.0, 0.0, 1.0]))
_RADIAL = _frozen(np.array([1.0, 0.0, 0.0]))  # LVLH +x, the zenith


def pointing_frame(r: FloatArray) -> tuple[FloatArray, float]:
    """``R_lvlh_chaser`` of the pointing law at chaser position ``r`` [m, LVLH] (``r`` not zero)
    and ``|h x z|``: body +z at the target's centre of mass, body +x along ``h x z`` (``h`` the
    orbit normal; radial when looking along it, then ``|h x z|`` is taken as 1), +y completing."""
    rn = max(math.sqrt(float(r @ r)), 1e-12)
    z = -r / rn
    hz = fast_cross(_ORBIT_NORMAL, z)
    nx = math.sqrt(float(hz @ hz))
    if nx < 1e-6:  # looking along the orbit normal: any roll; keep +x radial
        hz, nx = np.array([1.0, 0.0, 0.0]), 1.0
    x = hz / nx
    return np.column_stack([x, fast_cross(z, x), z]), nx


def hull_touches_mesh(target: TargetModel, p_target: FloatArray, hull_radius: float) -> BoolArray:
    """Whether a hull sphere at each of the points (M, 3) [m, target frame] touches the mesh.

    Exact (the closest-point query's ``distance <= hull_radius``), but the query runs only for
    points near the surface: every point of the mesh lies within ``edge`` of a vertex of the mesh
    subdivided to edges of at most ``edge`` (its distance to its triangle's farthest corner is at
    most the longest edge), so the distance to the mesh is at least the distance to the nearest
    such vertex less ``edge``; when that bound clears the hull, the answer is no.
    """
    tree, edge = target.cached(("surface_vertices", _SURFACE_EDGE_M), lambda: _surface_vertices(target))
    d, _ = tree.query(p_target)
    touches = np.zeros(p_target.shape[0], dtype=bool)
    near = np.flatnonzero(d - edge <= hull_radius)
    if near.size:
        _, dist, _ = trimesh.proximity.closest_point(target.mesh, p_target[near])
        touches[near] = dist <= hull_radius
    return touches


def _surface_vertices(target: TargetModel) -> tuple[cKDTree, float]:
    """KD-tree of the vertices of the target mesh subdivided to short edges, and the longest edge
    left [m]."""
    mesh = target.mesh
    v, f = trimesh.remesh.subdivide_to_size(mesh.vertices, mesh.faces, max_edge=_SURFACE_EDGE_M)
    tri = v[f]
    edge = float(np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=2).max())
    return cKDTree(v), edge


@dataclass(frozen=True)
class ContactState:
    """Relative geometry of the chaser docking frame and the target port, at one instant.

    Attributes:
        axial_distance: dock origin ahead of the port plane along the port axis [m] (> 0 outside).
        lateral_offset: distance of the dock origin from the port axis [m].
        closing_speed: axial approach speed [m/s] (> 0 when closing).
        lateral_speed: speed across the port axis [m/s].
        misalignment_deg: angle between the docking axis and the (reversed) port axis [deg].
        angular_rate_deg_s: relative angular rate chaser vs target [deg/s].
    """

    axial_distance: float
    lateral_offset: float
    closing_speed: float
    lateral_speed: float
    misalignment_deg: float
    angular_rate_deg_s: float


@dataclass(frozen=True)
class SensorTruth:
    """True relative kinematics of the target seen from the sensor (for truth observers, logs)."""

    T_sensor_target: FloatArray
    velocity: FloatArray  # d/dt of the target origin in sensor coordinates [m/s]
    angular_velocity: FloatArray  # target relative to sensor, sensor coordinates [rad/s]


def rk4_attitude(
    q: FloatArray,
    w: FloatArray,
    inertia: FloatArray,
    torque: FloatArray,
    dt: float,
    substeps: int = 4,
    inertia_inv: FloatArray | None = None,
) -> tuple[FloatArray, FloatArray]:
    """Rigid body under a constant body torque: classical RK4 with renormalisation.

    Used for the chaser, whose torque changes every step (a fresh adaptive solve per step would
    dominate the step time); at the chaser's rates (< 0.2 rad/s) and 0.05 s substeps the local
    error is far below the attitude noise of any sensor. The 7-state right-hand side is evaluated
    in plain floats: at this size numpy's per-call overhead is most of the cost.

    Args:
        q: (4,) body-to-inertial quaternion, scalar first.
        w: (3,) inertial angular velocity, body frame [rad/s].
        inertia: (3, 3) [kg m^2].
        torque: (3,) body torque [N m].
        dt: step [s].
        substeps: RK4 steps per ``dt``.
        inertia_inv: (3, 3) inverse of ``inertia`` when the caller has it (saves an inversion).

    Returns:
        ``(q, w)`` after ``dt``: (4,) unit quaternion with ``w >= 0`` and (3,) rate [rad/s].
    """
    inv = np.linalg.inv(inertia) if inertia_inv is None else inertia_inv
    rows = np.asarray(inertia, dtype=np.float64).tolist()
    inv_rows = np.asarray(inv, dtype=np.float64).tolist()
    tq = np.asarray(torque, dtype=np.float64).reshape(3).tolist()

    def f(*y: float) -> tuple[float, float, float, float, float, float, float]:
        return rigid_body_rates(*y, rows, inv_rows, tq)

    y0, y1, y2, y3 = np.asarray(q, dtype=np.float64).reshape(4).tolist()
    y4, y5, y6 = np.asarray(w, dtype=np.float64).reshape(3).tolist()
    h = dt / substeps
    hh, h6 = 0.5 * h, h / 6.0
    for _ in range(substeps):
        a0, a1, a2, a3, a4, a5, a6 = f(y0, y1, y2, y3, y4, y5, y6)
        b0, b1, b2, b3, b4, b5, b6 = f(
            y0 + hh * a0, y1 + hh * a1, y2 + hh * a2, y3 + hh * a3, y4 + hh * a4, y5 + hh * a5, y6 + hh * a6
        )
        c0, c1, c2, c3, c4, c5, c6 = f(
            y0 + hh * b0, y1 + hh * b1, y2 + hh * b2, y3 + hh * b3, y4 + hh * b4, y5 + hh * b5, y6 + hh * b6
        )
        d0, d1, d2, d3, d4, d5, d6 = f(
            y0 + h * c0, y1 + h * c1, y2 + h * c2, y3 + h * c3, y4 + h * c4, y5 + h * c5, y6 + h * c6
        )
        y0 += h6 * (a0 + 2 * b0 + 2 * c0 + d0)
        y1 += h6 * (a1 + 2 * b1 + 2 * c1 + d1)
        y2 += h6 * (a2 + 2 * b2 + 2 * c2 + d2)
        y3 += h6 * (a3 + 2 * b3 + 2 * c3 + d3)
        y4 += h6 * (a4 + 2 * b4 + 2 * c4 + d4)
        y5 += h6 * (a5 + 2 * b5 + 2 * c5 + d5)
        y6 += h6 * (a6 + 2 * b6 + 2 * c6 + d6)
        n = math.sqrt(y0 * y0 + y1 * y1 + y2 * y2 + y3 * y3)
        y0, y1, y2, y3 = y0 / n, y1 / n, y2 / n, y3 / n
    if y0 < 0:
        y0, y1, y2, y3 = -y0, -y1, -y2, -y3
    return np.array([y0, y1, y2, y3]), np.array([y4, y5, y6])


class World:
    """Truth state and its propagation for one episode.

    Frames derived from the state are built lazily, at most once per state (``_memo``, cleared on
    every change of the state); those that cannot change during an episode (an LVLH-holding
    target, the chaser that follows it, the mounts) are built once per reset and shared
    read-only.

    Args:
        cfg: the mission configuration.
        target: the target model (shared, read-only).
    """

    def __init__(self, cfg: MissionConfig, target: TargetModel) -> None:
        self.cfg = cfg
        self.target = target
        dyn = cfg.dynamics
        self.dt = float(cfg.env.frame_period_s)
        self.n = mean_motion(dyn.orbit.altitude_m)
        if dyn.orbit.model == "cw":
            self._trans: CWPropagator | NonlinearRelativePropagator = CWPropagator(self.n, self.dt)
        else:
            self._trans = NonlinearRelativePropagator(
                dyn.orbit.altitude_m, np.deg2rad(dyn.orbit.inclination_deg), dyn.orbit.j2, self.dt
            )
        ta = dyn.target_attitude
        self.target_attitude = TargetAttitudeModel(
            ta.mode, self.n, target.inertia if ta.mode == "tumble" else None
        )
        ch = dyn.chaser
        self.T_chaser_sensor = _frozen(make_T(
            Rotation.from_euler("xyz", ch.sensor_rpy_deg, degrees=True), ch.sensor_position_m
        ))
        self.T_chaser_dock = _frozen(make_T(None, ch.dock_position_m))
        self.controlled_attitude = ch.attitude == "controlled"
        self.pointing_attitude = ch.attitude == "pointing"
        orb = dyn.orbit
        beta, phase = math.radians(orb.sun_beta_deg), math.radians(orb.sun_phase_deg)
        self._sun_beta, self._sun_phase0 = beta, phase
        r_orbit = 6_378_137.0 + orb.altitude_m
        # The target is in the Earth's cylindrical shadow when the Sun is behind the Earth and the
        # Sun line passes within an Earth radius of the target: s . x < -sqrt(1 - (R_E / r)^2).
        self._shadow_cos = -math.sqrt(max(0.0, 1.0 - (6_378_137.0 / r_orbit) ** 2))
        m0 = ch.dry_mass_kg + ch.propellant_kg
        side = 2.0 * ch.hull_radius_m
        self.chaser_inertia = np.eye(3) * m0 * side**2 / 6.0  # uniform cube of the hull's size
        self._chaser_inertia_inv = np.linalg.inv(self.chaser_inertia)
        self._thrust_in_body = ch.thrust_frame == "body"
        self._hull_radius = float(ch.hull_radius_m)
        # Beyond this distance from the target origin the hull cannot touch the mesh.
        self._mesh_reach = float(target.radius) + self._hull_radius + 0.5
        self._n_lvlh = _frozen(np.array([0.0, 0.0, self.n]))  # LVLH rate vs inertial, LVLH axes
        self._zero3 = _frozen(np.zeros(3))
        T_tp = np.asarray(target.T_target_port, dtype=np.float64)
        self._T_target_port = _frozen(T_tp.copy())
        self._R_target_dock = _frozen(T_tp[:3, :3] @ R_PORT_DOCK)  # ideal chaser attitude law
        self._t_chaser_sensor = _frozen(self.T_chaser_sensor[:3, 3].copy())
        self.t = 0.0
        self.state = np.zeros(6)
        self.mass = ChaserMass(ch.dry_mass_kg, ch.propellant_kg, ch.isp_s, ch.max_thrust_n)
        self._q_i_chaser = np.array([1.0, 0.0, 0.0, 0.0])
        self._w_chaser = np.zeros(3)
        self.delta_v = 0.0
        # IMU: the last step's thrust acceleration and angular acceleration, the gyro bias and
        # the generator of the readings' noise (the env's, from reset).
        self._thrust_accel_lvlh = np.zeros(3)
        self._alpha_body = np.zeros(3)
        self._gyro_bias = np.zeros(3)
        self._imu_rng = np.random.default_rng(0)
        # Frames derived from the state, computed once per state; reset to the episode's constant
        # frames (``_const``) whenever the state changes.
        self._memo: dict[str, Any] = {}
        # Frames that stay put for a whole episode (set in reset): key -> read-only array.
        self._const: dict[str, FloatArray] = {}

    def _cached(self, key: str, build: Callable[[], Any]) -> Any:
        memo = self._memo
        value = memo.get(key)
        if value is None:
            value = memo[key] = build()
        return value

    def _invalidate(self) -> None:
        """Forget the frames of the previous state (keeping the episode's constant ones)."""
        self._memo = dict(self._const)

    # ------------------------------------------------------------------ reset
    def reset(self, rng: np.random.Generator) -> None:
        """Draw the initial state from the config's dispersions."""
        cfg, ch, ta = self.cfg, self.cfg.dynamics.chaser, self.cfg.dynamics.target_attitude
        ini = cfg.env.initial
        self.t = 0.0
        self.delta_v = 0.0
        self._thrust_accel_lvlh = np.zeros(3)
        self._alpha_body = np.zeros(3)
        self._imu_rng = rng
        self._const = {}
        self._invalidate()
        self.mass = ChaserMass(ch.dry_mass_kg, ch.propellant_kg, ch.isp_s, ch.max_thrust_n)
        if isinstance(self._trans, NonlinearRelativePropagator):
            self._trans.reset()
        q0 = Rotation.from_euler("xyz", ta.initial_rpy_deg, degrees=True)
        q0_wxyz = np.roll(q0.as_quat(), 1)
        if ta.mode == "tumble":
            _, w_body = spin_with_nutation(
                self.target.inertia, np.deg2rad(ta.spin_rate_deg_s), np.deg2rad(ta.nutation_deg),
                axis=ta.spin_axis, phase_rad=float(rng.uniform(0.0, 2.0 * np.pi)),
            )
            self.target_attitude.reset(q0_wxyz, w_body)
        else:
            self.target_attitude.reset(q0_wxyz)
        self._freeze_constant_frames()
        T_lp = self.T_lvlh_target @ self.target.T_target_port
        axis = T_lp[:3, 2]
        dist = ini.range_m + ini.range_dispersion_m * rng.standard_normal()
        dist = max(dist, 0.5 * ini.range_m if ini.range_min_m is None else ini.range_min_m)
        lateral = rng.standard_normal(3) * ini.lateral_dispersion_m
        lateral -= axis * (lateral @ axis)
        r_dock = T_lp[:3, 3] + axis * dist + lateral
        R_lc = T_lp[:3, :3] @ R_PORT_DOCK
        r_chaser = r_dock - R_lc @ self.T_chaser_dock[:3, 3]
        v = -axis * ini.closing_speed_m_s + rng.standard_normal(3) * ini.velocity_dispersion_m_s
        self.state = np.concatenate([r_chaser, v])
        if self.controlled_attitude:
            err = Rotation.from_rotvec(rng.standard_normal(3) * np.deg2rad(1.0))
            R_start = _aim_sensor(R_lc, r_chaser, self.T_chaser_sensor) if ini.aim_sensor else R_lc
            R_i_c = err * Rotation.from_matrix(R_start)  # inertial frame == LVLH at t = 0
            self._q_i_chaser = np.roll(R_i_c.as_quat(), 1)
            self._w_chaser = R_i_c.inv().apply([0.0, 0.0, self.n])  # co-rotating with LVLH
        sb = math.radians(ch.gyro_bias_deg_s)
        self._gyro_bias = rng.normal(0.0, sb, 3) if sb > 0 else np.zeros(3)
        self._invalidate()

    def _freeze_constant_frames(self) -> None:
        """Build once the frames an LVLH-holding target (and an ideal chaser) keep all episode.

        They seed ``_memo`` after every step, so the properties below find them without
        rebuilding; they are read-only because every step shares them.
        """
        self._const = {}
        self._invalidate()
        if self.target_attitude.mode != "lvlh_hold":
            return
        names = ["R_lvlh_target", "T_lvlh_target", "omega_target_lvlh", "T_lvlh_port"]
        if not self.controlled_attitude and not self.pointing_attitude:
            names += ["R_lvlh_chaser", "chaser_angular_velocity_body"]
        for name in names:
            getattr(self, name)  # builds and memoises
        self._const = {k: _frozen(v) for k, v in self._memo.items()}
        self._invalidate()

    # ------------------------------------------------------------------ frames
    @property
    def R_lvlh_target(self) -> FloatArray:
        return self._cached("R_lt", lambda: self.target_attitude.R_lvlh_target)

    @property
    def T_lvlh_target(self) -> FloatArray:
        return self._cached("T_lt", lambda: _pose(self.R_lvlh_target))

    @property
    def omega_target_lvlh(self) -> FloatArray:
        """Target angular velocity relative to LVLH, LVLH coordinates [rad/s]."""
        def build() -> FloatArray:
            if self.target_attitude.mode == "lvlh_hold":
                return np.zeros(3)
            # R (w_body - R^T n_lvlh) = R w_body - n_lvlh
            return self.R_lvlh_target @ self.target_attitude.omega_body - self._n_lvlh

        return self._cached("w_t", build)

    def _pointing(self) -> tuple[FloatArray, FloatArray]:
        """The pointing law's attitude ``R_lvlh_chaser`` and its angular velocity relative to
        LVLH (LVLH coordinates): body +z at the target's centre of mass, body +x along
        ``h x z`` (``h`` the orbit normal, +z LVLH), body +y completing the frame."""
        def build() -> tuple[FloatArray, FloatArray]:
            r, v = self.state[:3], self.state[3:]
            rn = math.sqrt(float(r @ r))
            if rn < 1e-6:  # at the centre of mass itself: no direction to aim; the docking attitude
                return self.R_lvlh_target @ self._R_target_dock, np.zeros(3)
            R, nx = pointing_frame(r)
            x, y, z = R[:, 0], R[:, 1], R[:, 2]
            z_dot = -(v - (-z) * float(-z @ v)) / rn
            h = _ORBIT_NORMAL
            x_dot = (fast_cross(h, z_dot) - x * float(x @ fast_cross(h, z_dot))) / nx
            w = fast_cross(z, z_dot) + z * float(x_dot @ y)
            return R, w

        return self._cached("pointing", build)

    @property
    def R_lvlh_chaser(self) -> FloatArray:
        def build() -> FloatArray:
            if self.pointing_attitude:
                return self._pointing()[0]
            if not self.controlled_attitude:
                return self.R_lvlh_target @ self._R_target_dock
            # LVLH turns at +n about z relative to the inertial frame it matched at t = 0.
            return rotation_z(-self.n * self.t) @ fast_quat_to_matrix(self._q_i_chaser)

        return self._cached("R_lc", build)

    @property
    def omega_chaser_lvlh(self) -> FloatArray:
        """Chaser angular velocity relative to LVLH, LVLH coordinates [rad/s]."""
        if self.pointing_attitude:
            return self._pointing()[1]
        if not self.controlled_attitude:
            return self.omega_target_lvlh
        return self._cached("w_c", lambda: self.R_lvlh_chaser @ self._w_chaser - self._n_lvlh)

    @property
    def T_lvlh_chaser(self) -> FloatArray:
        return self._cached("T_lc", lambda: _pose(self.R_lvlh_chaser, self.state[:3]))

    @property
    def T_lvlh_sensor(self) -> FloatArray:
        return self._cached("T_ls", lambda: self.T_lvlh_chaser @ self.T_chaser_sensor)

    @property
    def T_lvlh_dock(self) -> FloatArray:
        return self._cached("T_ld", lambda: self.T_lvlh_chaser @ self.T_chaser_dock)

    @property
    def T_lvlh_port(self) -> FloatArray:
        return self._cached("T_lp", lambda: self.T_lvlh_target @ self._T_target_port)

    @property
    def chaser_angular_velocity_body(self) -> FloatArray:
        """Chaser inertial angular velocity in its body frame [rad/s] (an IMU would read it)."""
        if self.controlled_attitude:
            return self._w_chaser.copy()
        return self._cached(
            "w_c_body", lambda: self.R_lvlh_chaser.T @ (self.omega_chaser_lvlh + self._n_lvlh)
        ).copy()

    # ------------------------------------------------------------------ step
    def step(self, thrust_n: FloatArray, torque_nm: FloatArray | None = None) -> FloatArray:
        """Hold thrust (chaser body or LVLH, per config) and torque over one frame.

        Returns:
            (3,) thrust actually applied, LVLH [N] (after saturation and propellant limits).
        """
        thrust_lvlh = self.R_lvlh_chaser @ thrust_n if self._thrust_in_body else thrust_n
        m_before = self.mass.mass_kg
        w_before = self.chaser_angular_velocity_body
        accel, applied = self.mass.apply(thrust_lvlh, self.dt)
        self._thrust_accel_lvlh = np.asarray(accel, dtype=np.float64)
        self.delta_v += math.sqrt(float(applied @ applied)) / m_before * self.dt
        self.state = self._trans.step(self.state, accel)
        self.target_attitude.step(self.dt)
        if self.controlled_attitude:
            tq = self._zero3 if torque_nm is None else np.asarray(torque_nm, dtype=np.float64)
            self._q_i_chaser, self._w_chaser = rk4_attitude(
                self._q_i_chaser, self._w_chaser, self.chaser_inertia, tq, self.dt,
                inertia_inv=self._chaser_inertia_inv,
            )
        self.t += self.dt
        self._invalidate()
        self._alpha_body = (self.chaser_angular_velocity_body - w_before) / self.dt
        return applied

    def gyro(self) -> FloatArray:
        """This step's gyro reading [rad/s], body frame: the inertial rate plus the bias and white
        noise of ``dynamics.chaser`` (one reading per step, shared by every consumer)."""
        def build() -> FloatArray:
            w = self.chaser_angular_velocity_body + self._gyro_bias
            s = math.radians(self.cfg.dynamics.chaser.gyro_noise_deg_s)
            return w + self._imu_rng.normal(0.0, s, 3) if s > 0 else w

        return self._cached("gyro", build)

    def sensor_ego(self) -> EgoMotion:
        """What the chaser's IMU tells the sensor about its own motion (sensor coordinates).

        The gyro's reading (:meth:`gyro`), and the sensor origin's inertial acceleration: the
        thrust acceleration of the last step plus the lever-arm terms of the chaser's rotation
        (``alpha x r + w x (w x r)``, with ``alpha`` the mean angular acceleration of the last
        step), less the tide over the sensor's offset from the centre of mass, plus the
        accelerometer's white noise; and the orbit's gravity gradient in the sensor axes
        (``n^2 (3 r r^T - I)``, ``r`` the LVLH radial), which the filter needs to predict the
        target's fall relative to the chaser.
        """
        R_cs, r = self.T_chaser_sensor[:3, :3], self.T_chaser_sensor[:3, 3]
        w = self.chaser_angular_velocity_body
        a_body = self.R_lvlh_chaser.T @ self._thrust_accel_lvlh
        a_body = a_body + fast_cross(self._alpha_body, r) + fast_cross(w, fast_cross(w, r))
        sa = self.cfg.dynamics.chaser.accel_noise_m_s2
        if sa > 0:
            a_body = a_body + self._imu_rng.normal(0.0, sa, 3)
        # The tide: the host knows the local vertical in its axes (orbit and attitude
        # determination), so the gravity gradient it hands the filter is the true one. An
        # accelerometer at the sensor, off the centre of mass by r, also reads the tide over r
        # (-G r): the target's acceleration relative to the sensor is then exactly G p - accel.
        G = gravity_gradient(self.n, self.T_lvlh_sensor[:3, :3].T @ _RADIAL)
        r_s = R_cs.T @ r
        return EgoMotion(R_cs.T @ self.gyro(), R_cs.T @ a_body - G @ r_s, G)

    # ------------------------------------------------------------------ observation of truth
    def sensor_truth(self) -> SensorTruth:
        """True relative kinematics of the target in the sensor frame."""
        return self._cached("sensor_truth", self._sensor_truth)

    def _sensor_truth(self) -> SensorTruth:
        T_ls = self.T_lvlh_sensor
        R_sl = T_ls[:3, :3].T
        T_st = fast_invert(T_ls) @ self.T_lvlh_target
        w_c = self.omega_chaser_lvlh
        r_cs = self.R_lvlh_chaser @ self._t_chaser_sensor
        v_s = self.state[3:] + fast_cross(w_c, r_cs)
        p = T_st[:3, 3]
        vel = R_sl @ (-v_s) - fast_cross(R_sl @ w_c, p)
        omega = R_sl @ (self.omega_target_lvlh - w_c)
        return SensorTruth(T_st, vel, omega)

    def scene(self) -> TruthScene:
        """The frame handed to the sensor, with first-order relative motion over the frame."""
        st = self.sensor_truth()
        motion = RelativeMotion(st.T_sensor_target, st.velocity, st.angular_velocity, t_ref=self.t)
        sun = self.sun_direction_lvlh()
        sun_t = None if sun is None else self.R_lvlh_target.T @ sun
        return TruthScene(st.T_sensor_target, self.t, motion, sun_direction_target=sun_t)

    def sun_direction_lvlh(self) -> FloatArray | None:
        """(3,) unit vector toward the Sun in LVLH at ``t``, or None in the Earth's shadow.

        The Sun is fixed inertially; LVLH turns at the mean motion about its +z, so the Sun's
        in-plane direction goes round once per orbit (``dynamics.orbit.sun_phase_deg`` at t = 0,
        ``sun_beta_deg`` above the plane)."""
        phase = self._sun_phase0 - self.n * self.t
        cb = math.cos(self._sun_beta)
        s = np.array([cb * math.cos(phase), cb * math.sin(phase), math.sin(self._sun_beta)])
        return None if s[0] < self._shadow_cos else s

    def contact(self) -> ContactState:
        """Relative docking geometry (truth)."""
        return self._cached("contact", self._contact)

    def _contact(self) -> ContactState:
        T_lp = self.T_lvlh_port
        T_ld = self.T_lvlh_dock
        R_lp = T_lp[:3, :3]
        p_port, p_dock = T_lp[:3, 3], T_ld[:3, 3]
        d0, d1, d2 = (R_lp.T @ (p_dock - p_port)).tolist()
        w_c, w_t = self.omega_chaser_lvlh, self.omega_target_lvlh
        v_dock = self.state[3:] + fast_cross(w_c, p_dock - self.state[:3])
        v_port = fast_cross(w_t, p_port)
        v0, v1, v2 = (R_lp.T @ (v_dock - v_port)).tolist()
        cosang = min(max(-float(T_ld[:3, 2] @ R_lp[:, 2]), -1.0), 1.0)
        dw = w_c - w_t
        return ContactState(
            axial_distance=d2,
            lateral_offset=math.hypot(d0, d1),
            closing_speed=-v2,
            lateral_speed=math.hypot(v0, v1),
            misalignment_deg=math.degrees(math.acos(cosang)),
            angular_rate_deg_s=math.degrees(math.sqrt(float(dw @ dw))),
        )

    def hull_clearance(self) -> float:
        """Distance [m] from the chaser hull sphere to the target mesh (inf when far away)."""
        r = self.state[:3]
        hull = self._hull_radius
        if math.sqrt(float(r @ r)) > self._mesh_reach:
            return float("inf")
        p_target = self.T_lvlh_target[:3, :3].T @ r
        _, dist, _ = trimesh.proximity.closest_point(self.target.mesh, p_target[None])
        return float(dist[0]) - hull

    def hull_touches(self) -> bool:
        """``hull_clearance() <= 0``, exactly, at the cost of a KD-tree query unless the hull is
        close to the mesh (see :func:`hull_touches_mesh`)."""
        r = self.state[:3]
        if math.sqrt(float(r @ r)) > self._mesh_reach:
            return False
        p_target = self.T_lvlh_target[:3, :3].T @ r
        return bool(hull_touches_mesh(self.target, p_target[None], self._hull_radius)[0])
