"""Fly-around controller: undock, back out along the port axis, circle the target at the standoff.

The scripted controller of ``TriDAR/FlyAround-v0`` (seed 000 section 5, STS-131's undocking and
fly-around of the ISS). It reads only the observation and mission knowledge (the target holds
LVLH, its design data: the port's place and axis; the chaser's pointing attitude law):

**Estimate.** A usable pose (position, velocity and attitude valid, and not degraded, or degraded
with a protection level under a third of the standoff band) gives the chaser's position and
velocity about the target's centre of mass in LVLH: the port's attitude in the docking frame
turns the docking frame into LVLH (``R_lvlh_dock = R_lvlh_port R_dock_port^T``), the port's
position and rate in the docking frame, with the gyro's rate relative to LVLH, give
``r = r_port - R_lvlh_dock (p + dock)`` and ``r' = -R_lvlh_dock (p' + w x (p + dock))``. Without
a usable pose the controller dead-reckons ``[r, r']`` with the CW model and its own commanded
accelerations, and takes its attitude from the pointing law at that estimate.

**Range-aided.** Without a usable pose the TriDAR still measures the range to its returns and the
range rate (the bearing mode's figures, published in every mode). The returns' centroid is not
the centre of mass: at each usable pose the controller notes the offset ``b = |r| - |c|`` (``c``
the centroid from the chaser's centre of mass, from range and bearing), and while the pose is not
usable it pulls its dead-reckoned ``|r|`` toward ``|c| + b`` and its radial speed toward the range
rate (``range_gain``, ``rate_gain`` per step). The radius, which the standoff band and the
keep-out sphere are about, stays measured; only the phase round the circle is dead-reckoned.
Measured on FlyAround (seed 91): where the ISS-like truss slides, the pose stayed beyond a usable
bound for 800 s; a controller that stopped its reference after ``hold_s`` stayed at that aspect
and timed out (1 of the first 24 runs), or flew on only once the track had slid 17 m and been
dropped.

"Degraded" is the docking's verdict: the protection level passed an alert limit set for the port
(centimetres to decimetres). Circling at 100 m inside a 15 m band with a 40 m keep-out sphere, a
pose bounded within a few metres is plenty, so the controller weighs the bound against its own
tolerance rather than the docking's. Measured on FlyAround (seed 83): where the ISS-like truss
slides, the held slide kept the pose degraded at metre-level bounds; a controller waiting for a
healthy pose there stopped its reference, stayed at the same aspect, and timed out (2 of the
first 8 runs).

**Law** (LVLH accelerations; the CW model's own accelerations at the estimate are cancelled, so
the loops act on a double integrator):

* ``depart``: out along the port axis at a speed that ramps up from ``v_depart_min`` with the
  distance from the port and down again toward the standoff circle (at most ``v_depart``), a PD
  keeping the chaser on the axis (inside the keep-out sphere's departure cone);
* ``circle``: once within ``capture_m`` of the standoff radius, a reference point goes round the
  circle of radius ``standoff_m`` in the orbital plane at ``v_circle`` (in ``direction``), starting
  from the chaser's own phase; its centripetal acceleration is fed forward and a PD
  (``omega_n``, ``zeta``) tracks it. The reference waits while the chaser lags it by more than
  ``max_lag_m``, while neither a usable pose nor a range has come for ``hold_s``, or after
  ``range_hold_s`` on range-aided dead reckoning alone (a point at rest, which the chaser then
  closes on), so a lost track holds the chaser on the circle rather than flying it round blind.

The environment ends the episode (``completed``) once the swept angle reaches the configured sweep
inside the standoff band.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from scipy.spatial.transform import Rotation

from agents.bearing_guidance import returns_centroid, sensor_mount
from agents.lqr import saturate
from perception.config import MissionConfig
from tridar_env.dynamics import cw_acceleration, cw_stm, mean_motion
from tridar_env.env import make_target, observation_slices
from tridar_env.world import pointing_frame

_S = observation_slices()
FloatArray = npt.NDArray[np.float64]

#: ``valid`` flags (observation order).
_BEARING, _RANGE, _RATE, _POSITION, _VELOCITY, _ATTITUDE, _DEGRADED = 0, 1, 2, 3, 4, 5, 7


@dataclass
class FlyAroundGains:
    """Tunables of :class:`FlyAroundController` (SI units)."""

    v_depart: float = 0.5  # [m/s] top departure speed along the port axis
    v_depart_min: float = 0.05  # [m/s] at the port
    depart_slope: float = 0.02  # [1/s] departure speed gained per metre from the port / lost toward the circle
    capture_m: float = 8.0  # [m] within this of the standoff radius the circle starts
    v_circle: float = 0.6  # [m/s] speed of the reference round the circle
    max_lag_m: float = 10.0  # [m] the reference waits while the chaser lags it by more
    omega_n: float = 0.02  # [rad/s] tracking loop's natural frequency
    zeta: float = 0.9
    kp_axis: float = 0.004  # [1/s^2] back onto the port axis while departing
    kd_axis: float = 0.15  # [1/s]
    hold_s: float = 10.0  # [s] without a usable pose or a range for this long the reference stops
    range_hold_s: float = 600.0  # [s] on range-aided dead reckoning for this long it stops too
    range_gain: float = 0.05  # per step: share of the range residual taken into |r|
    rate_gain: float = 0.05  # per step: share of the range-rate residual taken into the radial speed
    usable_pl_fraction: float = 1.0 / 3.0  # a degraded pose whose protection level is under this
    # fraction of the standoff band is still flown on (module docstring)


class FlyAroundController:
    """Maps an observation to a normalised thrust ``[-1, 1]^3`` in the chaser body frame.

    Args:
        cfg: the mission config (``env.task: fly_around``, ``dynamics.chaser.attitude: pointing``,
            the target holding LVLH).
        gains: tunables.

    Attributes:
        phase: ``"depart"`` or ``"circle"``.
        law: which estimate flew the last step (``"pose"`` on a usable pose, ``"range_aided"``,
            ``"dead_reckoning"``).
        r, v: (3,) the estimated chaser position and velocity about the target's centre of mass,
            LVLH [m, m/s].
    """

    def __init__(self, cfg: MissionConfig, gains: FlyAroundGains | None = None) -> None:
        ch, env = cfg.dynamics.chaser, cfg.env
        if env.task != "fly_around" or ch.attitude != "pointing":
            raise ValueError(
                f"FlyAroundController expects env.task='fly_around' (got {env.task!r}) and "
                f"dynamics.chaser.attitude='pointing' (got {ch.attitude!r})"
            )
        if cfg.dynamics.target_attitude.mode != "lvlh_hold" or ch.thrust_frame != "body":
            raise ValueError("FlyAroundController expects target_attitude.mode='lvlh_hold' and "
                             "chaser.thrust_frame='body'")
        self.g = gains or FlyAroundGains()
        self.cfg = cfg
        self.fa = env.fly_around
        self.n = mean_motion(cfg.dynamics.orbit.altitude_m)
        self.dt = env.frame_period_s * env.frame_skip
        self.phi, self.gamma = cw_stm(self.n, self.dt)
        target = make_target(cfg)
        R_lt = Rotation.from_euler("xyz", cfg.dynamics.target_attitude.initial_rpy_deg, degrees=True).as_matrix()
        T_tp = target.T_target_port
        self.R_lvlh_port = R_lt @ T_tp[:3, :3]
        self.r_port = R_lt @ T_tp[:3, 3]
        self.axis = self.R_lvlh_port[:, 2]
        self.dock = np.asarray(ch.dock_position_m, dtype=np.float64)
        self.dry, self.prop0, self.max_thrust = ch.dry_mass_kg, ch.propellant_kg, ch.max_thrust_n
        self.R_cs, self.t_cs = sensor_mount(ch)
        self.reset()

    def reset(self) -> None:
        """Forget the episode."""
        self.phase = "depart"
        self.law = "pose"
        self.has_estimate = False
        self.r = np.zeros(3)
        self.v = np.zeros(3)
        self.theta_ref = 0.0
        self.blind_s = 0.0
        self.ranged_s = 0.0
        self.centroid_offset_m: float | None = None
        self._a_prev = np.zeros(3)

    # ------------------------------------------------------------------ estimate
    def _from_pose(self, obs: npt.NDArray[np.floating]) -> tuple[FloatArray, FloatArray, FloatArray]:
        q = obs[_S["q_dock_port"]].astype(np.float64)
        R_dp = Rotation.from_quat([q[1], q[2], q[3], q[0]]).as_matrix()
        R_ld = self.R_lvlh_port @ R_dp.T
        p = obs[_S["port_position_dock"]].astype(np.float64) + self.dock
        p_dot = obs[_S["port_velocity_dock"]].astype(np.float64)
        w = obs[_S["chaser_rate_body"]].astype(np.float64) - R_ld.T @ np.array([0.0, 0.0, self.n])
        r = self.r_port - R_ld @ p
        v = -R_ld @ (p_dot + np.cross(w, p))
        return r, v, R_ld

    def _centroid_range(self, obs: npt.NDArray[np.floating]) -> float | None:
        """``|c|`` [m]: the returns' centroid from the chaser's centre of mass (None: no valid
        bearing and range)."""
        valid = obs[_S["valid"]]
        if valid[_BEARING] < 0.5 or valid[_RANGE] < 0.5:
            return None
        return float(np.linalg.norm(returns_centroid(obs, self.R_cs, self.t_cs)[0]))

    def update(self, obs: npt.NDArray[np.floating]) -> bool:
        """Take this observation (or dead-reckon, range-aided when it can); True on a usable
        pose (module docstring)."""
        valid = obs[_S["valid"]]
        bounded = (valid[_DEGRADED] < 0.5 or float(obs[_S["protection_level"]][0])
                   <= self.g.usable_pl_fraction * self.fa.band_m)
        usable = (valid[_POSITION] > 0.5 and valid[_VELOCITY] > 0.5 and valid[_ATTITUDE] > 0.5
                  and bounded)
        if self.has_estimate:
            s = self.phi @ np.concatenate([self.r, self.v]) + self.gamma @ self._a_prev
            self.r, self.v = s[:3], s[3:]
        c = self._centroid_range(obs)
        if usable:
            self.r, self.v, _ = self._from_pose(obs)
            self.has_estimate = True
            self.blind_s = self.ranged_s = 0.0
            if c is not None:
                self.centroid_offset_m = float(np.linalg.norm(self.r)) - c
        elif self.has_estimate and c is not None and self.centroid_offset_m is not None:
            rn = float(np.linalg.norm(self.r))
            u = self.r / rn
            self.r = self.r + self.g.range_gain * (c + self.centroid_offset_m - rn) * u
            if valid[_RATE] > 0.5:
                rr = float(obs[_S["range_rate"]][0])
                self.v = self.v + self.g.rate_gain * (rr - float(self.v @ u)) * u
            self.blind_s = 0.0
            self.ranged_s += self.dt
        else:
            self.blind_s += self.dt
        return usable

    # ------------------------------------------------------------------ law
    def accel_lvlh(self) -> FloatArray:
        """The law's LVLH acceleration [m/s^2] at the current estimate."""
        g, fa = self.g, self.fa
        r, v = self.r, self.v
        rn = float(np.linalg.norm(r))
        if self.phase == "depart" and abs(rn - fa.standoff_m) <= g.capture_m:
            self.phase = "circle"
            self.theta_ref = math.atan2(r[1], r[0])
        if self.phase == "depart":
            d = r - self.r_port
            along = float(d @ self.axis)
            lateral = d - along * self.axis
            speed = min(g.v_depart, g.v_depart_min + g.depart_slope * max(along, 0.0),
                        g.v_depart_min + g.depart_slope * max(fa.standoff_m - rn, 0.0))
            v_along = float(v @ self.axis)
            kv = 2.0 * g.zeta * g.omega_n
            a = kv * (speed - v_along) * self.axis
            a += -g.kp_axis * lateral - g.kd_axis * (v - v_along * self.axis)
        else:
            w = fa.direction * g.v_circle / fa.standoff_m
            ref = fa.standoff_m * np.array([math.cos(self.theta_ref), math.sin(self.theta_ref), 0.0])
            lag = float(np.linalg.norm(ref - r))
            moving = lag <= g.max_lag_m and self.blind_s <= g.hold_s and self.ranged_s <= g.range_hold_s
            if moving:
                self.theta_ref += w * self.dt
                ref = fa.standoff_m * np.array([math.cos(self.theta_ref), math.sin(self.theta_ref), 0.0])
            # a waiting reference is a point at rest: with its circling velocity kept, it pulled a
            # chaser that had coasted past it to the PD's balance kd v / kp (54 m at 0.6 m/s)
            # ahead of it, beyond max_lag_m, and neither moved again (a run stalled 4,000 s)
            v_ref = np.cross([0.0, 0.0, w], ref) if moving else np.zeros(3)
            a_ref = np.cross([0.0, 0.0, w], v_ref)
            kp, kd = g.omega_n**2, 2.0 * g.zeta * g.omega_n
            a = a_ref + kp * (ref - r) + kd * (v_ref - v)
        return a - cw_acceleration(self.n, r, v)

    def __call__(self, obs: npt.NDArray[np.floating]) -> npt.NDArray[np.float32]:
        usable = self.update(obs)
        self.law = "pose" if usable else ("range_aided" if self.ranged_s > 0.0 and self.blind_s == 0.0
                                          else "dead_reckoning")
        if not self.has_estimate:
            self._a_prev = np.zeros(3)
            return np.zeros(3, dtype=np.float32)
        a = self.accel_lvlh()
        R_ld = self._from_pose(obs)[2] if usable else pointing_frame(self.r)[0]
        mass = self.dry + self.prop0 * float(obs[_S["fuel_fraction"]][0])
        thrust = saturate(R_ld.T @ a * mass / self.max_thrust)
        self._a_prev = R_ld @ thrust * self.max_thrust / mass
        return thrust.astype(np.float32)
