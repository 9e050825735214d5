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

When the pose is not valid (bearing mode, search, loss of track) the rule is **never act on a stale
pose**: null the measured range rate if it is closing (a braking impulse along the line of sight,
which is known from the bearing), otherwise coast with zero thrust. Inside ``commit_range_m`` of the
port (the last valid pose said so) the approach is committed: braking there would turn a nominal
contact into a too-slow one, so the controller coasts (zero thrust) at its closing speed instead.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from perception.config import MissionConfig
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
        self._last_axial = float("inf")

    def reset(self) -> None:
        """Forget the last valid axial distance (the only memory: the commit rule)."""
        self._last_axial = float("inf")

    def _mass(self, obs: npt.NDArray[np.floating]) -> float:
        return self.dry + self.prop0 * float(obs[_S["fuel_fraction"]][0])

    def accel_command(self, obs: npt.NDArray[np.floating]) -> npt.NDArray[np.float64]:
        """Desired chaser acceleration, body frame [m/s^2]."""
        g = self.g
        valid = obs[_S["valid"]]
        pose_ok = valid[3] > 0.5 and valid[4] > 0.5
        if not pose_ok:
            if self._last_axial <= g.commit_range_m:
                return np.zeros(3)  # committed: coast into contact
            # No trusted pose: brake a closing range rate along the line of sight, else coast.
            if valid[2] > 0.5 and obs[_S["range_rate"]][0] < -0.01:
                az, el = obs[_S["bearing"]]
                los = np.array([np.sin(az) * np.cos(el), -np.sin(el), np.cos(az) * np.cos(el)])
                return -g.kv * float(obs[_S["range_rate"]][0]) * -los
            return np.zeros(3)
        p = obs[_S["port_position_dock"]].astype(np.float64)
        v = obs[_S["port_velocity_dock"]].astype(np.float64)
        z = max(p[2], 0.0)
        self._last_axial = z
        lat = np.hypot(p[0], p[1])
        v_des = float(np.clip(g.slope * z, g.v_final, g.v_max))
        if z > g.commit_range_m and lat > g.lateral_cone * z + 0.05:
            v_des = 0.0  # hold point until the lateral error is inside the cone
        a = np.empty(3)
        a[:2] = g.kp_lat * p[:2] + g.kd_lat * v[:2]
        a[2] = g.kv * (v[2] + v_des)
        return a

    def __call__(self, obs: npt.NDArray[np.floating]) -> npt.NDArray[np.float32]:
        a = self.accel_command(obs)
        thrust = a * self._mass(obs) / self.max_thrust
        if not self.six_dof:
            return np.clip(thrust, -1.0, 1.0).astype(np.float32)
        torque = np.zeros(3)
        valid = obs[_S["valid"]]
        if valid[5] > 0.5:
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
