"""The truth simulation behind the environment: relative orbit, target and chaser attitude, mass.

Everything here is truth. The environment hands the sensor a :class:`~perception.state.TruthScene`
built from it and exposes it in ``info`` for logging; observations never read it directly.

Frames: LVLH/Hill of the target (origin at the target centre of mass; x radial, y along-track,
z orbit normal); target body (``T_lvlh_target``); chaser body (``T_lvlh_chaser``) with the docking
mechanism at ``T_chaser_dock`` (its +z is the docking axis) and the TriDAR at ``T_chaser_sensor``
(+z boresight). The ideal attitude law keeps the chaser docking frame parallel to the port frame,
facing it: ``R_port_dock = diag(1, -1, -1)``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt
import trimesh
from scipy.spatial.transform import Rotation

from perception.config import MissionConfig
from perception.geometry import invert, make_T
from perception.sensors.motion import RelativeMotion
from perception.state import TruthScene
from perception.targets import TargetModel
from tridar_env.dynamics import (
    ChaserMass,
    CWPropagator,
    NonlinearRelativePropagator,
    TargetAttitudeModel,
    mean_motion,
    spin_with_nutation,
)

FloatArray = npt.NDArray[np.float64]

#: The docking frame faces the port: x along port x, z against port z.
R_PORT_DOCK = np.diag([1.0, -1.0, -1.0])


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
    q: FloatArray, w: FloatArray, inertia: FloatArray, torque: FloatArray, dt: float, substeps: int = 4
) -> tuple[FloatArray, FloatArray]:
    """Rigid body under a constant body torque: classical RK4 with renormalisation.

    Used for the chaser, whose torque changes every step (a fresh adaptive solve per step would
    dominate the step time); at the chaser's rates (< 0.2 rad/s) and 0.05 s substeps the local
    error is far below the attitude noise of any sensor.

    Args:
        q: (4,) body-to-inertial quaternion, scalar first.
        w: (3,) inertial angular velocity, body frame [rad/s].
        inertia: (3, 3) [kg m^2].
        torque: (3,) body torque [N m].
        dt: step [s].
    """
    inv = np.linalg.inv(inertia)

    def f(y: FloatArray) -> FloatArray:
        qw, qx, qy, qz, p, r1, r2 = y[0], y[1], y[2], y[3], y[4], y[5], y[6]
        om = y[4:7]
        dw = inv @ (torque - np.cross(om, inertia @ om))
        return np.array([
            -0.5 * (qx * p + qy * r1 + qz * r2),
            0.5 * (qw * p + qy * r2 - qz * r1),
            0.5 * (qw * r1 + qz * p - qx * r2),
            0.5 * (qw * r2 + qx * r1 - qy * p),
            dw[0], dw[1], dw[2],
        ])

    y = np.concatenate([q, w])
    h = dt / substeps
    for _ in range(substeps):
        k1 = f(y)
        k2 = f(y + 0.5 * h * k1)
        k3 = f(y + 0.5 * h * k2)
        k4 = f(y + h * k3)
        y = y + h / 6.0 * (k1 + 2 * k2 + 2 * k3 + k4)
        y[:4] /= np.linalg.norm(y[:4])
    if y[0] < 0:
        y[:4] = -y[:4]
    return y[:4], y[4:]


class World:
    """Truth state and its propagation for one episode.

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
        self.T_chaser_sensor = make_T(
            Rotation.from_euler("xyz", ch.sensor_rpy_deg, degrees=True), ch.sensor_position_m
        )
        self.T_chaser_dock = make_T(None, ch.dock_position_m)
        self.controlled_attitude = ch.attitude == "controlled"
        m0 = ch.dry_mass_kg + ch.propellant_kg
        side = 2.0 * ch.hull_radius_m
        self.chaser_inertia = np.eye(3) * m0 * side**2 / 6.0  # uniform cube of the hull's size
        self.t = 0.0
        self.state = np.zeros(6)
        self.mass = ChaserMass(ch.dry_mass_kg, ch.propellant_kg, ch.isp_s, ch.max_thrust_n)
        self._q_i_chaser = np.array([1.0, 0.0, 0.0, 0.0])
        self._w_chaser = np.zeros(3)
        self.delta_v = 0.0
        # Frames derived from the state are computed once per step (scipy Rotation objects are
        # costly to build); the cache is cleared whenever the state changes.
        self._memo: dict[str, Any] = {}

    def _cached(self, key: str, build: Callable[[], Any]) -> Any:
        if key not in self._memo:
            self._memo[key] = build()
        return self._memo[key]

    # ------------------------------------------------------------------ reset
    def reset(self, rng: np.random.Generator) -> None:
        """Draw the initial state from the config's dispersions."""
        cfg, ch, ta = self.cfg, self.cfg.dynamics.chaser, self.cfg.dynamics.target_attitude
        ini = cfg.env.initial
        self.t = 0.0
        self.delta_v = 0.0
        self._memo.clear()
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
        T_lp = self.T_lvlh_target @ self.target.T_target_port
        axis = T_lp[:3, 2]
        dist = ini.range_m + ini.range_dispersion_m * rng.standard_normal()
        dist = max(dist, 0.5 * ini.range_m)
        lateral = rng.standard_normal(3) * ini.lateral_dispersion_m
        lateral -= axis * (lateral @ axis)
        r_dock = T_lp[:3, 3] + axis * dist + lateral
        R_lc = T_lp[:3, :3] @ R_PORT_DOCK
        r_chaser = r_dock - R_lc @ self.T_chaser_dock[:3, 3]
        v = -axis * ini.closing_speed_m_s + rng.standard_normal(3) * ini.velocity_dispersion_m_s
        self.state = np.concatenate([r_chaser, v])
        if self.controlled_attitude:
            err = Rotation.from_rotvec(rng.standard_normal(3) * np.deg2rad(1.0))
            R_i_c = err * Rotation.from_matrix(R_lc)  # inertial frame == LVLH at t = 0
            self._q_i_chaser = np.roll(R_i_c.as_quat(), 1)
            self._w_chaser = R_i_c.inv().apply([0.0, 0.0, self.n])  # co-rotating with LVLH
        self._memo.clear()

    # ------------------------------------------------------------------ frames
    @property
    def R_lvlh_target(self) -> FloatArray:
        return self._cached("R_lt", lambda: self.target_attitude.R_lvlh_target)

    @property
    def T_lvlh_target(self) -> FloatArray:
        return self._cached("T_lt", lambda: make_T(self.R_lvlh_target))

    @property
    def omega_target_lvlh(self) -> FloatArray:
        """Target angular velocity relative to LVLH, LVLH coordinates [rad/s]."""
        def build() -> FloatArray:
            if self.target_attitude.mode == "lvlh_hold":
                return np.zeros(3)
            lvlh_rate_body = self.R_lvlh_target.T @ np.array([0.0, 0.0, self.n])
            return self.R_lvlh_target @ (self.target_attitude.omega_body - lvlh_rate_body)

        return self._cached("w_t", build)

    @property
    def R_lvlh_chaser(self) -> FloatArray:
        def build() -> FloatArray:
            if not self.controlled_attitude:
                return self.R_lvlh_target @ self.target.T_target_port[:3, :3] @ R_PORT_DOCK
            lvlh_from_i = Rotation.from_rotvec([0.0, 0.0, -self.n * self.t])
            q = self._q_i_chaser
            return (lvlh_from_i * Rotation.from_quat([q[1], q[2], q[3], q[0]])).as_matrix()

        return self._cached("R_lc", build)

    @property
    def omega_chaser_lvlh(self) -> FloatArray:
        """Chaser angular velocity relative to LVLH, LVLH coordinates [rad/s]."""
        if not self.controlled_attitude:
            return self.omega_target_lvlh
        return self.R_lvlh_chaser @ self._w_chaser - np.array([0.0, 0.0, self.n])

    @property
    def T_lvlh_chaser(self) -> FloatArray:
        return self._cached("T_lc", lambda: make_T(self.R_lvlh_chaser, self.state[:3]))

    @property
    def T_lvlh_sensor(self) -> FloatArray:
        return self._cached("T_ls", lambda: self.T_lvlh_chaser @ self.T_chaser_sensor)

    @property
    def T_lvlh_dock(self) -> FloatArray:
        return self._cached("T_ld", lambda: self.T_lvlh_chaser @ self.T_chaser_dock)

    @property
    def T_lvlh_port(self) -> FloatArray:
        return self._cached("T_lp", lambda: self.T_lvlh_target @ self.target.T_target_port)

    @property
    def chaser_angular_velocity_body(self) -> FloatArray:
        """Chaser inertial angular velocity in its body frame [rad/s] (an IMU would read it)."""
        if self.controlled_attitude:
            return self._w_chaser.copy()
        return self.R_lvlh_chaser.T @ (self.omega_chaser_lvlh + np.array([0.0, 0.0, self.n]))

    # ------------------------------------------------------------------ step
    def step(self, thrust_n: FloatArray, torque_nm: FloatArray | None = None) -> FloatArray:
        """Hold thrust (chaser body or LVLH, per config) and torque over one frame.

        Returns:
            (3,) thrust actually applied, LVLH [N] (after saturation and propellant limits).
        """
        R_lc = self.R_lvlh_chaser
        self._memo.clear()
        thrust_lvlh = R_lc @ thrust_n if self.cfg.dynamics.chaser.thrust_frame == "body" else thrust_n
        m_before = self.mass.mass_kg
        accel, applied = self.mass.apply(thrust_lvlh, self.dt)
        self.delta_v += float(np.linalg.norm(applied)) / m_before * self.dt
        self.state = self._trans.step(self.state, accel)
        self.target_attitude.step(self.dt)
        if self.controlled_attitude:
            tq = np.zeros(3) if torque_nm is None else np.asarray(torque_nm, dtype=np.float64)
            self._q_i_chaser, self._w_chaser = rk4_attitude(
                self._q_i_chaser, self._w_chaser, self.chaser_inertia, tq, self.dt
            )
        self.t += self.dt
        self._memo.clear()
        return applied

    # ------------------------------------------------------------------ observation of truth
    def sensor_truth(self) -> SensorTruth:
        """True relative kinematics of the target in the sensor frame."""
        return self._cached("sensor_truth", self._sensor_truth)

    def _sensor_truth(self) -> SensorTruth:
        T_ls = self.T_lvlh_sensor
        R_ls = T_ls[:3, :3]
        T_st = invert(T_ls) @ self.T_lvlh_target
        w_c = self.omega_chaser_lvlh
        r_cs = self.R_lvlh_chaser @ self.T_chaser_sensor[:3, 3]
        v_s = self.state[3:] + np.cross(w_c, r_cs)
        p = T_st[:3, 3]
        vel = R_ls.T @ (-v_s) - np.cross(R_ls.T @ w_c, p)
        omega = R_ls.T @ (self.omega_target_lvlh - w_c)
        return SensorTruth(T_st, vel, omega)

    def scene(self) -> TruthScene:
        """The frame handed to the sensor, with first-order relative motion over the frame."""
        st = self.sensor_truth()
        motion = RelativeMotion(st.T_sensor_target, st.velocity, st.angular_velocity, t_ref=self.t)
        return TruthScene(st.T_sensor_target, self.t, motion)

    def contact(self) -> ContactState:
        """Relative docking geometry (truth)."""
        return self._cached("contact", self._contact)

    def _contact(self) -> ContactState:
        T_lp = self.T_lvlh_port
        T_ld = self.T_lvlh_dock
        R_lp = T_lp[:3, :3]
        d = R_lp.T @ (T_ld[:3, 3] - T_lp[:3, 3])
        w_c, w_t = self.omega_chaser_lvlh, self.omega_target_lvlh
        v_dock = self.state[3:] + np.cross(w_c, T_ld[:3, 3] - self.state[:3])
        v_port = np.cross(w_t, T_lp[:3, 3])
        rv = R_lp.T @ (v_dock - v_port)
        cosang = float(np.clip(-(T_ld[:3, 2] @ R_lp[:, 2]), -1.0, 1.0))
        return ContactState(
            axial_distance=float(d[2]),
            lateral_offset=float(np.hypot(d[0], d[1])),
            closing_speed=float(-rv[2]),
            lateral_speed=float(np.hypot(rv[0], rv[1])),
            misalignment_deg=float(np.degrees(np.arccos(cosang))),
            angular_rate_deg_s=float(np.degrees(np.linalg.norm(w_c - w_t))),
        )

    def hull_clearance(self) -> float:
        """Distance [m] from the chaser hull sphere to the target mesh (inf when far away)."""
        r = self.state[:3]
        hull = self.cfg.dynamics.chaser.hull_radius_m
        if np.linalg.norm(r) > self.target.radius + hull + 0.5:
            return float("inf")
        p_target = self.T_lvlh_target[:3, :3].T @ r
        _, dist, _ = trimesh.proximity.closest_point(self.target.mesh, p_target[None])
        return float(dist[0]) - hull
