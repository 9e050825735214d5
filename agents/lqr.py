"""Discrete LQR on the Clohessy-Wiltshire model, tracking an aim point that slides in along the port axis.

The controller reads only the observation (never ``info`` truth); the chaser's mass, thrust limit
and step come from the mission config.

Model. The state is the docking-frame position and velocity of the chaser's dock relative to the
port, ``x = [r, v] = -[p, p_dot]`` (``p`` = ``port_position_dock``), the input the chaser's
acceleration ``u`` in the docking frame (``p'' = -u``). With the ideal attitude law and a target held
in LVLH (the ISS-like port of ``TriDAR/FinalApproach-v0``), the docking frame is a *constant*
rotation ``R = R_lvlh_dock`` of LVLH, so the exact discrete CW model at the env step rotates into
it: ``A = diag(R^T, R^T) Phi diag(R, R)``, ``B = diag(R^T, R^T) Gamma R`` (:func:`cw_stm`). ``R`` is
mission knowledge (where the station's port faces: the target library's port frame and the
configured target attitude), not an estimate. Two approximations, both documented: the CW terms act
on the port-relative position rather than the centre-of-mass one (the port's offset from the
target's centre of mass adds a constant ~3 n^2 dx, 1e-5 m/s^2 for 10 m, which feedback absorbs), and
when ``R`` is not constant (a target that is not LVLH-held, or a chaser that controls its own
attitude) the model falls back to the double integrator ``Phi = [[I, dt I], [0, I]]``,
``Gamma = [[dt^2/2 I], [dt I]]`` - the CW terms are then left to feedback (n = 1.1e-3 rad/s).

Law. ``K`` from ``scipy.linalg.solve_discrete_are``; ``u = u_ff - K (x - x_aim)`` with the
feed-forward ``u_ff = B^+ (x_aim[k+1] - A x_aim[k])`` that makes the aim trajectory a solution of
the model, then saturation at ``max_thrust / mass`` that scales the whole vector (keeping its
direction). The aim point lies on the port axis at distance ``z_aim`` and slides in at the
glideslope rate ``clip(slope * z_aim, v_final, v_max)``; it continues through the port plane so that contact happens at ``v_final`` (inside the capture
envelope's 0.05-0.10 m/s). It pauses (a hold point) while the chaser lags it by more than
``max_lag_m`` or sits outside the lateral cone, except inside ``commit_range_m`` where a stop would
turn contact into a collision.

Integrity (:mod:`agents.safety`, DESIGN.md "Integrity"): the law flies only a *healthy* pose
(position and velocity valid, not degraded). From the last healthy pose the controller
dead-reckons the port with its own saturated commands (through ``A``, ``B`` when the docking frame
is constant, else in free fall with the gyro); on an invalid or degraded pose it brakes the closing
speed to zero and holds, and when the loss outlasts ``safety.hold_s`` (3 s) retreats, inside
``safety.hold_range_m`` (5 m), along the docking axis to that hold point at ``safety.v_retreat``,
never closing in; only a healthy pose lost in the last ``safety.commit_range_m`` (0.4 m), on the
axis and inside the envelope's closing speeds, coasts into contact (a degraded one there, or a
lost one off the axis, backs away at once). The approach resumes once the pose has been healthy
for as long as it was lost (at most, and after a retreat, ``safety.resume_s``), the aim point
restarting from the new estimate. Before the first healthy pose of
an episode there is nothing to dead-reckon: a closing range rate is braked along the line of sight
(bearing) when both are valid, else the chaser coasts (:func:`loss_of_track_accel`). Far out (a
valid range beyond ``bearing.engage_range_m``) with no healthy pose, the bearing law of
:mod:`agents.bearing_guidance` flies instead and hands back at the first healthy pose.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import numpy.typing as npt
import scipy.linalg
from scipy.spatial.transform import Rotation

from agents.bearing_guidance import BearingGains, BearingGuidance
from agents.safety import CollisionAvoidance, SafetyGains
from perception.config import MissionConfig
from perception.targets import load_target
from tridar_env.dynamics import cw_stm, mean_motion
from tridar_env.env import make_target, observation_slices

_S = observation_slices()
FloatArray = npt.NDArray[np.float64]

#: The docking frame faces the port: x along port x, z against port z.
R_PORT_DOCK = np.diag([1.0, -1.0, -1.0])


@dataclass
class LQRGains:
    """Weights and aim-point schedule of :class:`LQRController` (SI units)."""

    q_pos: float = 1.0  # [1/m^2] state weight, position error
    q_vel: float = 125.0  # [s^2/m^2] state weight, velocity error
    r_acc: float = 2500.0  # [s^4/m^2] input weight
    slope: float = 0.02  # [1/s] aim speed = slope * aim distance
    v_final: float = 0.07  # [m/s] closing speed at contact (envelope 0.05-0.10)
    v_max: float = 0.30  # [m/s]
    z_end: float = -2.0  # [m] the aim runs this far through the port plane
    max_lag_m: float = 1.0  # [m] hold the aim while the chaser lags it by more
    lateral_cone: float = 0.15  # hold the aim while |lateral| > cone * z + 0.05
    commit_range_m: float = 1.0  # [m] no hold inside this distance (a stop there is a collision)
    brake_gain: float = 0.4  # [1/s] loss-of-track braking of a closing range rate (no fix yet)
    safety: SafetyGains = field(default_factory=SafetyGains)  # lost or degraded track
    bearing: BearingGains = field(default_factory=BearingGains)  # no healthy pose, far out


def dock_frame_in_lvlh(cfg: MissionConfig) -> FloatArray | None:
    """``R_lvlh_dock`` [-] when it is constant, else ``None``.

    Constant when the target holds its attitude in LVLH and the chaser flies the ideal attitude law
    (its docking frame parallel to the port frame, facing it).
    """
    if cfg.dynamics.target_attitude.mode != "lvlh_hold" or cfg.dynamics.chaser.attitude != "ideal":
        return None
    tc = cfg.target
    if Path(tc.name).suffix:
        port = (tc.port_position_m, tc.port_axis) if tc.port_position_m is not None else None
        target = load_target(tc.name, scale=tc.scale, port=port, mass=tc.mass_kg)
    else:
        target = load_target(tc.name)
    R_lt = Rotation.from_euler(
        "xyz", cfg.dynamics.target_attitude.initial_rpy_deg, degrees=True
    ).as_matrix()
    return R_lt @ target.T_target_port[:3, :3] @ R_PORT_DOCK


def port_lever_dock(cfg: MissionConfig) -> FloatArray:
    """(3,) the port from the target's centre of mass [m], in the docking frame of a chaser
    aligned with the port (``R_PORT_DOCK``): the target's design data."""
    T_tp = make_target(cfg).T_target_port
    return R_PORT_DOCK.T @ T_tp[:3, :3].T @ T_tp[:3, 3]


def docking_frame_model(
    n: float, dt: float, R_lvlh_dock: FloatArray | None
) -> tuple[FloatArray, FloatArray]:
    """Discrete ``(A (6, 6), B (6, 3))`` of ``[r, v]`` in the docking frame over ``dt`` [s].

    Args:
        n: mean motion [rad/s].
        dt: step [s].
        R_lvlh_dock: constant docking-frame rotation, or ``None`` for the double integrator.
    """
    if R_lvlh_dock is None:
        A = np.block([[np.eye(3), dt * np.eye(3)], [np.zeros((3, 3)), np.eye(3)]])
        B = np.vstack([0.5 * dt**2 * np.eye(3), dt * np.eye(3)])
        return A, B
    phi, gamma = cw_stm(n, dt)
    Rt = scipy.linalg.block_diag(R_lvlh_dock.T, R_lvlh_dock.T)
    return Rt @ phi @ Rt.T, Rt @ gamma @ R_lvlh_dock


def loss_of_track_accel(obs: npt.NDArray[np.floating], gain: float) -> FloatArray:
    """The invalid-pose rule: body acceleration [m/s^2] that brakes a closing range rate.

    Uses only the bearing and range rate (valid in bearing mode); zero (coast) otherwise or when
    the range is not closing faster than 1 cm/s.
    """
    valid = obs[_S["valid"]]
    rr = float(obs[_S["range_rate"]][0])
    if valid[0] > 0.5 and valid[2] > 0.5 and rr < -0.01:
        az, el = (float(x) for x in obs[_S["bearing"]])
        los = np.array([np.sin(az) * np.cos(el), -np.sin(el), np.cos(az) * np.cos(el)])
        return gain * rr * los  # accelerate away from the target along the line of sight
    return np.zeros(3)


def saturate(u: npt.NDArray[np.floating]) -> FloatArray:
    """Scale a normalised command so that no axis exceeds 1, keeping its direction."""
    u = np.asarray(u, dtype=np.float64)
    m = float(np.max(np.abs(u))) if u.size else 0.0
    return u / m if m > 1.0 else u


class LQRController:
    """CW-model discrete LQR toward a moving aim point on the port axis (3-DOF thrust).

    Args:
        cfg: the mission config (chaser mass, thrust limit, thrust frame, env step, orbit).
        gains: weights and schedule.
        R_lvlh_dock: override the docking-frame rotation (default :func:`dock_frame_in_lvlh`).

    Attributes:
        K: (3, 6) LQR gain on ``[r, v]`` error.
        z_aim: current aim distance along the port axis [m] (``nan`` before the first pose).
    """

    def __init__(
        self,
        cfg: MissionConfig,
        gains: LQRGains | None = None,
        R_lvlh_dock: FloatArray | None = None,
    ) -> None:
        ch = cfg.dynamics.chaser
        self.cfg = cfg
        self.g = gains or LQRGains()
        self.dt = float(cfg.env.frame_period_s * cfg.env.frame_skip)
        self.R = R_lvlh_dock if R_lvlh_dock is not None else dock_frame_in_lvlh(cfg)
        if ch.thrust_frame == "lvlh" and self.R is None:
            raise ValueError(
                "dynamics.chaser.thrust_frame='lvlh' needs a constant docking frame "
                "(target_attitude.mode='lvlh_hold', chaser.attitude='ideal')"
            )
        self.thrust_frame = ch.thrust_frame
        self.dry = ch.dry_mass_kg
        self.prop0 = ch.propellant_kg
        self.max_thrust = ch.max_thrust_n
        self.six_dof = ch.attitude == "controlled"
        self.A, self.B = docking_frame_model(mean_motion(cfg.dynamics.orbit.altitude_m), self.dt, self.R)
        g = self.g
        Q = np.diag([g.q_pos] * 3 + [g.q_vel] * 3)
        Rw = g.r_acc * np.eye(3)
        P = scipy.linalg.solve_discrete_are(self.A, self.B, Q, Rw)
        self.K = np.linalg.solve(Rw + self.B.T @ P @ self.B, self.B.T @ P @ self.A)
        self._B_pinv = np.linalg.pinv(self.B)
        env = cfg.env.envelope
        self.safety = CollisionAvoidance(
            self.dt, ch.dock_position_m, (env.axial_speed_min_m_s, env.axial_speed_max_m_s),
            g.safety,
            model=(self.A, self.B) if self.R is not None else None,
            lever=port_lever_dock(cfg) if self.R is not None else (0.0, 0.0, 0.0),
            lateral_max_m=env.lateral_offset_max_m,
        )
        n = mean_motion(cfg.dynamics.orbit.altitude_m)
        R = self.R
        self.bearing = BearingGuidance(
            cfg, g.bearing, model=(self.A, self.B),
            lever=port_lever_dock(cfg) if self.R is not None else None,
            model_for_dt=lambda step: docking_frame_model(n, step, R),
            cw=None if R is None else (n, R),
        )
        self.law = "pose"
        self.reset()

    def reset(self) -> None:
        """Forget the aim point, the dead-reckoned port and the avoidance state."""
        self.z_aim = float("nan")
        self.safety.reset()
        self.bearing.reset()
        self.law = "pose"  # which law flew the last step: "pose", "bearing" or "safety"

    def _mass(self, obs: npt.NDArray[np.floating]) -> float:
        return self.dry + self.prop0 * float(obs[_S["fuel_fraction"]][0])

    def _aim_speed(self, z: float) -> float:
        g = self.g
        return float(np.clip(g.slope * z, g.v_final, g.v_max))

    def _aim_state(self, z: float) -> FloatArray:
        if z <= self.g.z_end:
            return np.array([0.0, 0.0, -z, 0.0, 0.0, 0.0])
        return np.array([0.0, 0.0, -z, 0.0, 0.0, self._aim_speed(z)])

    def accel_command(self, obs: npt.NDArray[np.floating]) -> FloatArray:
        """Desired chaser acceleration in the docking frame [m/s^2] (before saturation)."""
        g = self.g
        valid = obs[_S["valid"]]
        p = obs[_S["port_position_dock"]].astype(np.float64)
        p_dot = obs[_S["port_velocity_dock"]].astype(np.float64)
        d = self.safety.d
        mode = self.safety.update(obs, p + d if valid[3] > 0.5 else None, p_dot if valid[4] > 0.5 else None)
        self.bearing.update(obs)
        self.law = "safety" if mode != "nominal" else "pose"
        if self.bearing.far(obs):
            self.law = "bearing"  # kilometres out: the far-range profile, pose or not
            self.z_aim = float("nan")
            return self.bearing.accel(obs)
        if mode != "nominal":
            self.z_aim = float("nan")  # restart the aim from the next healthy pose
            if mode in ("avoid", "blind") and self.bearing.engaged(obs):
                self.law = "bearing"  # far out with no healthy pose: close on bearing and range
                return self.bearing.accel(obs)
            if mode == "blind":
                return loss_of_track_accel(obs, g.brake_gain)
            return self.safety.accel(obs)
        x = -np.concatenate([p, p_dot])
        z = float(p[2])  # distance to the port along the docking axis
        if not np.isfinite(self.z_aim):
            self.z_aim = z
        lateral = float(np.hypot(p[0], p[1]))
        hold = z > g.commit_range_m and (
            z - self.z_aim > g.max_lag_m or lateral > g.lateral_cone * z + 0.05
        )
        z_next = self.z_aim
        if not hold and self.z_aim > g.z_end:
            z_next = max(self.z_aim - self._aim_speed(self.z_aim) * self.dt, g.z_end)
        x_aim = self._aim_state(self.z_aim)
        if hold:
            x_aim[3:] = 0.0
            x_next = x_aim.copy()
        else:
            x_next = self._aim_state(z_next)
        u_ff = self._B_pinv @ (x_next - self.A @ x_aim)
        self.z_aim = z_next
        return u_ff - self.K @ (x - x_aim)

    def __call__(self, obs: npt.NDArray[np.floating]) -> npt.NDArray[np.float32]:
        a = self.accel_command(obs)
        if self.thrust_frame == "lvlh":
            assert self.R is not None
            a = self.R @ a
        mass = self._mass(obs)
        thrust = saturate(a * mass / self.max_thrust)
        applied = thrust * self.max_thrust / mass
        if self.thrust_frame == "lvlh" and self.R is not None:
            applied = self.R.T @ applied  # back into the docking frame
        self.safety.applied(applied)
        self.bearing.applied(applied)
        if self.six_dof:
            thrust = np.concatenate([thrust, np.zeros(3)])  # no attitude control: use sync
        return thrust.astype(np.float32)
