"""Glideslope docking controller on the TriDAR state vector (V-bar / R-bar approaches).

The controller reads only the observation (never ``info`` truth). In the chaser docking frame the
port sits at ``p`` (+z ahead); the chaser's own acceleration ``a`` (body frame) moves it as
``p'' = -a``. The law:

* axial: track a closing speed that falls linearly with distance (the glideslope),
  ``v_des = clip(gain * (z - z_hold), v_final, v_max)``, reaching ``v_final`` (inside the capture
  envelope's axial window) before contact;
* lateral: a PD that drives the port onto the docking axis, with a braking rule that stops the axial
  approach (hold point) while the lateral error exceeds the cone ``lateral_cone * z``;
* attitude (6-DOF option): a PD on the port attitude error and relative rate.

Integrity (:mod:`agents.safety`, DESIGN.md "Integrity"): the law flies only a *healthy* pose
(position and velocity valid, not degraded). The controller dead-reckons the port from its last
healthy pose with its own commanded accelerations (through the CW model when its docking frame is
constant in LVLH, else in free fall with the gyro), and when the pose is invalid or
degraded it brakes the closing speed to zero and holds; when no healthy pose has come back within
``safety.hold_s`` (3 s) and it is inside ``safety.hold_range_m`` (5 m) of the port, it retreats
along the docking axis to that hold point at ``safety.v_retreat``; lateral motion is nulled. It
never coasts into the target on a lost track. The one exception is a
healthy pose lost (not degraded) in the last ``safety.commit_range_m`` (0.4 m), on the axis and
inside the envelope's closing speeds: braking there would turn a docking into a too-slow contact,
so the chaser coasts in. A degraded pose there, or a lost one off the axis, aborts (backs away at
once). The approach resumes once the pose has been healthy for as long as it was lost (at most,
and after a retreat, ``safety.resume_s``). Before the first healthy pose of an episode (acquisition)
there is nothing to dead-reckon: a closing range rate is braked along the line of sight (known
from the bearing) when it is measured, else the chaser coasts.

Far out (a valid range beyond ``bearing.engage_range_m``, 60 m) with no healthy pose - bearing
mode, search before acquisition, or a pose lost or degraded there - the bearing law of
:mod:`agents.bearing_guidance` flies instead: it closes on bearing, range and range rate down
the approach axis at a speed that shrinks with range, holding short of ``bearing.hold_range_m``,
and hands back to this law at the first healthy pose (``law`` says which flew the last step).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from agents.bearing_guidance import BearingGains, BearingGuidance
from agents.lqr import dock_frame_in_lvlh, docking_frame_model, port_lever_dock
from agents.safety import CollisionAvoidance, SafetyGains
from perception.config import MissionConfig
from tridar_env.dynamics import mean_motion
from tridar_env.env import observation_slices

_S = observation_slices()


@dataclass
class GlideslopeGains:
    """Tunables of :class:`GlideslopeController` (SI units)."""

    v_final: float = 0.07  # [m/s] closing speed at contact (envelope 0.05-0.10)
    v_max: float = 0.30  # [m/s]
    slope: float = 0.012  # [1/s] v_des = slope * distance
    kv: float = 0.6  # [1/s] axial speed loop
    kp_lat: float = 0.02  # [1/s^2]
    kd_lat: float = 0.35  # [1/s]
    lateral_cone: float = 0.15  # hold axial progress while |lateral| > cone * z + 0.05
    commit_range_m: float = 1.0  # [m] no hold point closer than this (a stop there is a collision)
    kp_att: float = 0.4  # [1/s^2] attitude loop (6-DOF)
    kd_att: float = 1.2  # [1/s]
    # lost or degraded track; a degraded pose far out closes to the hold point (agents.safety)
    safety: SafetyGains = field(default_factory=lambda: SafetyGains(v_degraded_close=0.1))
    bearing: BearingGains = field(default_factory=BearingGains)  # no healthy pose, far out


class GlideslopeController:
    """Maps an observation to a normalised action ``[-1, 1]``.

    Args:
        cfg: the mission config (for the chaser's own mass, thrust and torque limits).
        gains: controller gains.
    """

    def __init__(self, cfg: MissionConfig, gains: GlideslopeGains | None = None) -> None:
        ch = cfg.dynamics.chaser
        self.cfg = cfg
        self.g = gains or GlideslopeGains()
        self.dry = ch.dry_mass_kg
        self.prop0 = ch.propellant_kg
        self.max_thrust = ch.max_thrust_n
        self.max_torque = ch.max_torque_nm
        self.six_dof = ch.attitude == "controlled"
        if ch.thrust_frame != "body":
            raise ValueError("GlideslopeController expects dynamics.chaser.thrust_frame='body'")
        m0 = ch.dry_mass_kg + ch.propellant_kg
        self.inertia = m0 * (2.0 * ch.hull_radius_m) ** 2 / 6.0
        self.dock = np.array(ch.dock_position_m, dtype=np.float64)
        env = cfg.env.envelope
        dt = cfg.env.frame_period_s * cfg.env.frame_skip
        R = dock_frame_in_lvlh(cfg)  # constant docking frame: dead-reckon with the CW model
        n = mean_motion(cfg.dynamics.orbit.altitude_m)
        model = None if R is None else docking_frame_model(n, dt, R)
        self.safety = CollisionAvoidance(
            dt, self.dock, (env.axial_speed_min_m_s, env.axial_speed_max_m_s), self.g.safety,
            model=model, lever=port_lever_dock(cfg) if model is not None else (0.0, 0.0, 0.0),
            lateral_max_m=env.lateral_offset_max_m,
        )
        self.bearing = BearingGuidance(
            cfg, self.g.bearing, model=model,
            lever=port_lever_dock(cfg) if model is not None else None,
            model_for_dt=lambda step: docking_frame_model(n, step, R),
            cw=None if R is None else (n, R),
        )
        self.law = "pose"  # which law flew the last step: "pose", "bearing" or "safety"

    def reset(self) -> None:
        """Forget the episode (the dead-reckoned port, the avoidance state, the bearing filter)."""
        self.safety.reset()
        self.bearing.reset()
        self.law = "pose"

    def _mass(self, obs: npt.NDArray[np.floating]) -> float:
        return self.dry + self.prop0 * float(obs[_S["fuel_fraction"]][0])

    def accel_command(self, obs: npt.NDArray[np.floating]) -> npt.NDArray[np.float64]:
        """Desired chaser acceleration, body frame [m/s^2]."""
        g = self.g
        valid = obs[_S["valid"]]
        p = obs[_S["port_position_dock"]].astype(np.float64)
        v = obs[_S["port_velocity_dock"]].astype(np.float64)
        mode = self.safety.update(
            obs, p + self.dock if valid[3] > 0.5 else None, v if valid[4] > 0.5 else None
        )
        self.bearing.update(obs)
        self.law = "safety" if mode != "nominal" else "pose"
        if self.bearing.far(obs):
            self.law = "bearing"  # kilometres out: the far-range profile, pose or not
            return self.bearing.accel(obs)
        if mode in ("avoid", "blind") and self.bearing.engaged(obs):
            self.law = "bearing"  # far out with no healthy pose: close on the bearing and range
            return self.bearing.accel(obs)
        if mode in ("avoid", "commit"):
            return self.safety.accel(obs)
        if mode == "blind":
            # No pose yet: brake a closing range rate along the line of sight, else coast.
            if valid[2] > 0.5 and obs[_S["range_rate"]][0] < -0.01:
                az, el = obs[_S["bearing"]]
                los = np.array([np.sin(az) * np.cos(el), -np.sin(el), np.cos(az) * np.cos(el)])
                return -g.kv * float(obs[_S["range_rate"]][0]) * -los
            return np.zeros(3)
        z = max(p[2], 0.0)
        lat = np.hypot(p[0], p[1])
        v_des = float(np.clip(g.slope * z, g.v_final, g.v_max))
        if z > g.commit_range_m and lat > g.lateral_cone * z + 0.05:
            v_des = 0.0  # hold point until the lateral error is inside the cone
        a = np.empty(3)
        a[:2] = g.kp_lat * p[:2] + g.kd_lat * v[:2]
        a[2] = g.kv * (v[2] + v_des)
        return a

    def executed(self, action: npt.ArrayLike, obs: npt.NDArray[np.floating]) -> None:
        """Record ``action`` as the one flown (the controller's own, at the end of each call; or
        another policy's, while the controller labels its states alongside it: DAgger in
        :mod:`agents.pretrain`): the safety layer's and the bearing law's dead reckoning carry
        the thrust that was applied."""
        thrust = np.clip(np.asarray(action, dtype=np.float64).reshape(-1)[:3], -1.0, 1.0)
        a = thrust * self.max_thrust / self._mass(obs)
        self.safety.applied(a)
        self.bearing.applied(a)

    def __call__(self, obs: npt.NDArray[np.floating]) -> npt.NDArray[np.float32]:
        a = self.accel_command(obs)
        mass = self._mass(obs)
        thrust = a * mass / self.max_thrust
        if self.safety.mode in ("nominal", "blind") and self.law != "bearing":
            thrust = np.clip(thrust, -1.0, 1.0)
        else:  # an avoidance (or the bearing law) keeps its direction at the thrust limit
            thrust = thrust / max(1.0, float(np.max(np.abs(thrust))))
        self.executed(thrust, obs)
        if not self.six_dof:
            return thrust.astype(np.float32)
        torque = np.zeros(3)
        valid = obs[_S["valid"]]
        if valid[5] > 0.5 and valid[7] < 0.5:
            q = obs[_S["q_dock_port"]].astype(np.float64)
            # Desired: port frame = dock frame rotated by R_PORT_DOCK (x along, z against).
            from scipy.spatial.transform import Rotation

            R_dp = Rotation.from_quat([q[1], q[2], q[3], q[0]]).as_matrix()
            R_err = R_dp @ np.diag([1.0, -1.0, -1.0])
            err = Rotation.from_matrix(R_err).as_rotvec()
            w_rel = obs[_S["omega_port_dock"]].astype(np.float64) if valid[6] > 0.5 else np.zeros(3)
            torque = self.inertia * (self.g.kp_att * err + self.g.kd_att * w_rel)
        return np.clip(
            np.concatenate([thrust, torque / self.max_torque]), -1.0, 1.0
        ).astype(np.float32)
