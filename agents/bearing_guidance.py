"""Bearing-mode guidance: close on the target from bearing, range and range rate alone.

Far out the TriDAR publishes no pose (bearing mode, beyond ``pipeline.bearing_to_search_range_m``;
search mode until acquisition): only the centroid ``bearing`` of its returns, their ``range`` and a
filtered ``range_rate``, each with a ``valid`` flag. The pose-based laws (:mod:`agents.glideslope`,
:mod:`agents.lqr`) have nothing to fly there; this law brings the chaser in to where the pipeline
can acquire, then hands back.

**Estimate.** A Kalman filter on the chaser's position and velocity ``s = [r, v]`` from the
target's centre of mass, in the docking frame (the body axes), driven by the chaser's own applied
accelerations through the CW model when the docking frame is constant in LVLH
(:func:`agents.lqr.docking_frame_model`, passed in by the pose-based controllers; the double
integrator otherwise). Each valid bearing and
range gives the target centroid ``c = t_sensor + R_chaser_sensor (range * u)`` (``u`` the line of
sight), measured as ``r = -c`` with ``sigma_range_m`` along ``u`` and ``sigma_bearing_rad * range``
across it; a valid range rate measures ``-u . v``. The centroid of the returns is not the centre of
mass (a face of the target): a bias of a few metres that matters only for where the chaser holds.

**Law** (docking frame, ``p`` the port estimate ``-r + lever - dock``, ``lever`` the port from the
target's centre of mass, mission knowledge passed in when the docking frame is constant; else zero):

* across the docking axis a soft PD, ``a_xy = kp_lat p_xy + kd_lat p'_xy``, flies the chaser onto
  the approach axis (with a frame that is not constant: onto the line of sight);
* along it, a closing speed that shrinks with distance,
  ``v_des = clip(slope * (z - hold_range_m), 0, v_max)``, tracked by a speed loop ``kv``: fast far
  out, about the glideslope's own 0.3 m/s at the search hand-over range, zero at the hold point
  (``hold_range_m``). It never closes inside the hold point on a bearing, and holds axial progress
  while the lateral error exceeds ``lateral_cone * z``;
* a range rate that is not valid brakes (``v_des = 0`` on the filter's velocity); no bearing or
  range at all: the filter coasts on the chaser's own accelerations and the law brakes on it.

**Far out** (beyond ``far_range_m``, FarRendezvous-v0 from kilometres): the closing speed keeps
growing with distance, ``v_des = min(v_far_max, v_des(far_range_m) + far_slope * (z - far_range_m))``,
a forced-motion approach down the axis that keeps the target inside the sensors' fields of view
(a CW transfer or V-bar hop from 5 km swings 10-25 deg off the axis, out of a body-fixed
imager's field under the docking attitude law); the CW model's own accelerations at the estimate
are cancelled (feedforward), so the loops see a double integrator. The measurement sigmas grow
with range there (``sigma_range_fraction``, ``sigma_rate_fraction``: the coarse range source
and its differentiated rate), and with the environment's decision schedule (steps that lengthen
with range, :func:`tridar_env.schedule.decision_frames`) the filter predicts over each step's own
length, known from the last valid range the controller saw, as the environment knows it.

**Engagement.** The pose-based controllers call :meth:`BearingGuidance.engaged` when they have no
healthy pose: it is true only with a valid range beyond ``engage_range_m`` (above the final
approach's start, so the close-in loss-of-track rules of :mod:`agents.safety` keep their say).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from scipy.spatial.transform import Rotation

from perception.config import ChaserConfig, MissionConfig
from tridar_env.dynamics import cw_acceleration
from tridar_env.env import observation_slices
from tridar_env.schedule import decision_frames

_S = observation_slices()
FloatArray = npt.NDArray[np.float64]

#: ``valid`` flags (observation order).
_BEARING, _RANGE, _RATE = 0, 1, 2


@dataclass
class BearingGains:
    """Tunables of :class:`BearingGuidance` (SI units)."""

    v_max: float = 0.5  # [m/s] closing speed far out
    slope: float = 0.0025  # [1/s] v_des = slope * (distance - hold); 0.33 m/s at 200 m
    hold_range_m: float = 70.0  # [m] never closes inside this on a bearing alone
    engage_range_m: float = 60.0  # [m] flies only beyond this range (final approach keeps its rules)
    kv: float = 0.1  # [1/s] axial speed loop
    kp_lat: float = 4e-4  # [1/s^2] across the approach axis (50 s time constant)
    kd_lat: float = 0.03  # [1/s]
    lateral_cone: float = 0.2  # hold axial progress while |lateral| > cone * z + 2 m
    sigma_range_m: float = 2.0  # centroid range error (a face, not the centre of mass)
    sigma_bearing_rad: float = 2e-3  # centroid direction error (returns wander over the target)
    sigma_range_rate: float = 0.02  # [m/s]
    accel_noise: float = 2e-4  # [m/s^2/sqrt(Hz)] process noise (CW residuals, centroid drift)
    far_range_m: float = 600.0  # [m] beyond this: the far-range profile and CW feedforward
    far_slope: float = 0.001  # [1/s] closing speed gained per metre beyond far_range_m
    v_far_max: float = 2.5  # [m/s]
    sigma_range_fraction: float = 0.003  # far out: range sigma >= this * range
    sigma_rate_fraction: float = 1e-4  # far out: range-rate sigma >= this * range [1/s]


def line_of_sight(bearing: npt.ArrayLike) -> FloatArray:
    """(3,) unit vector of an ``(azimuth, elevation)`` [rad] bearing in the sensor frame
    (+z boresight, +x right, +y down; elevation up)."""
    az, el = (float(b) for b in np.asarray(bearing, dtype=np.float64).reshape(2))
    return np.array([np.sin(az) * np.cos(el), -np.sin(el), np.cos(az) * np.cos(el)])


def sensor_mount(ch: ChaserConfig) -> tuple[FloatArray, FloatArray]:
    """``(R_cs (3, 3), t_cs (3,))``: the sensor's attitude and position [m] in the chaser body, from
    the chaser config ``ch`` (``sensor_rpy_deg``, ``sensor_position_m``)."""
    return (Rotation.from_euler("xyz", ch.sensor_rpy_deg, degrees=True).as_matrix(),
            np.asarray(ch.sensor_position_m, dtype=np.float64))


def returns_centroid(obs: npt.NDArray[np.floating], R_cs: FloatArray, t_cs: FloatArray
                     ) -> tuple[FloatArray, FloatArray]:
    """The returns' centroid [m] from the chaser's centre of mass (body frame) and the line of
    sight (body frame) from an observation's ``bearing`` and ``range``, the sensor mounted at
    ``t_cs`` (3,) with attitude ``R_cs`` (3, 3) in the body."""
    u = R_cs @ line_of_sight(obs[_S["bearing"]])
    return t_cs + float(obs[_S["range"]][0]) * u, u


class BearingGuidance:
    """Closes on the target along the line of sight on bearing, range and range rate (module doc).

    Standalone it is a controller (``obs -> action``, thrust only, body frame); the pose-based
    controllers embed it for the phase before acquisition (:meth:`update`, :meth:`engaged`,
    :meth:`accel`, :meth:`applied`).

    Args:
        cfg: the mission config (chaser mass, thrust, sensor mount, dock, step).
        gains: tunables.
        model: discrete ``(A (6, 6), B (6, 3))`` of the chaser's ``[r, v]`` in the docking frame
            over the step (:func:`agents.lqr.docking_frame_model`); default the double integrator.
        lever: (3,) the port from the target's centre of mass in the docking frame [m], when that
            frame is constant (:func:`agents.lqr.port_lever_dock`); default zero (aim the
            target's centroid onto the docking axis).

    Attributes:
        has_estimate: the filter has been initialised by a valid bearing and range.
        s: (6,) chaser position and velocity from the target's centre of mass, docking frame.
        P: (6, 6) its covariance.
    """

    def __init__(
        self,
        cfg: MissionConfig,
        gains: BearingGains | None = None,
        model: tuple[FloatArray, FloatArray] | None = None,
        lever: npt.ArrayLike | None = None,
        model_for_dt: Callable[[float], tuple[FloatArray, FloatArray]] | None = None,
        cw: tuple[float, FloatArray] | None = None,
    ) -> None:
        ch = cfg.dynamics.chaser
        self.g = gains or BearingGains()
        self.env_cfg = cfg.env
        dt = self.dt = float(cfg.env.frame_period_s * cfg.env.frame_skip)
        if model is None:
            model = (np.block([[np.eye(3), dt * np.eye(3)], [np.zeros((3, 3)), np.eye(3)]]),
                     np.vstack([0.5 * dt**2 * np.eye(3), dt * np.eye(3)]))
        self.A, self.B = (np.asarray(m, dtype=np.float64) for m in model)
        # Steps that lengthen with range: one model per step length (built on first use).
        self.model_for_dt = model_for_dt
        self._models: dict[int, tuple[FloatArray, FloatArray, FloatArray]] = {}
        # (n, R_lvlh_dock) for the CW feedforward far out (None: no feedforward).
        self.cw = None if cw is None else (float(cw[0]), np.asarray(cw[1], dtype=np.float64))
        self.lever = np.zeros(3) if lever is None else np.asarray(lever, dtype=np.float64).reshape(3)
        self.dock = np.asarray(ch.dock_position_m, dtype=np.float64)
        self.R_cs, self.t_cs = sensor_mount(ch)
        self.dry, self.prop0, self.max_thrust = ch.dry_mass_kg, ch.propellant_kg, ch.max_thrust_n
        self.six_dof = ch.attitude == "controlled"
        q = self.g.accel_noise**2
        self.Q = np.kron(np.array([[dt**3 / 3.0, dt**2 / 2.0], [dt**2 / 2.0, dt]]) * q, np.eye(3))
        self.reset()

    def reset(self) -> None:
        """Forget the episode (no estimate, no applied acceleration)."""
        self.has_estimate = False
        self.s = np.zeros(6)
        self.P = np.eye(6)
        self._a_prev = np.zeros(3)
        self._last_range: float | None = None  # the last valid range seen (decision schedule)
        self._frames_next = self.env_cfg.frame_skip  # frames of the step the last action flies

    def _step_model(self, frames: int) -> tuple[FloatArray, FloatArray, FloatArray]:
        """``(A, B, Q)`` over a step of ``frames`` frames."""
        if self.env_cfg.decision_schedule is None or frames == self.env_cfg.frame_skip:
            return self.A, self.B, self.Q
        m = self._models.get(frames)
        if m is None:
            dt = self.env_cfg.frame_period_s * frames
            if self.model_for_dt is not None:
                A, B = self.model_for_dt(dt)
            else:
                A = np.block([[np.eye(3), dt * np.eye(3)], [np.zeros((3, 3)), np.eye(3)]])
                B = np.vstack([0.5 * dt**2 * np.eye(3), dt * np.eye(3)])
            q = self.g.accel_noise**2
            Q = np.kron(np.array([[dt**3 / 3.0, dt**2 / 2.0], [dt**2 / 2.0, dt]]) * q, np.eye(3))
            m = self._models[frames] = (np.asarray(A, dtype=np.float64), np.asarray(B, dtype=np.float64), Q)
        return m

    # ------------------------------------------------------------------ estimate
    def _centroid(self, obs: npt.NDArray[np.floating]) -> tuple[FloatArray, FloatArray]:
        """Target centroid from the chaser's centre of mass (body frame) and the line of sight."""
        return returns_centroid(obs, self.R_cs, self.t_cs)

    def update(self, obs: npt.NDArray[np.floating]) -> None:
        """Predict over the last step with the applied acceleration, then take this observation's
        bearing, range and range rate (those that are valid)."""
        valid = obs[_S["valid"]]
        if self.has_estimate:
            A, B, Q = self._step_model(self._frames_next)
            self.s = A @ self.s + B @ self._a_prev
            self.P = A @ self.P @ A.T + Q
        if valid[_RANGE] > 0.5 and self.env_cfg.decision_schedule is not None:
            self._last_range = float(obs[_S["range"]][0])
            self._frames_next = decision_frames(self.env_cfg, self._last_range)
        if valid[_BEARING] < 0.5 or valid[_RANGE] < 0.5:
            return
        g = self.g
        c, u = self._centroid(obs)
        rng = float(np.linalg.norm(c))
        across = max(g.sigma_bearing_rad * rng, 0.2)
        sigma_range, sigma_rate = g.sigma_range_m, g.sigma_range_rate
        if rng > g.far_range_m:
            sigma_range = max(sigma_range, g.sigma_range_fraction * rng)
            sigma_rate = max(sigma_rate, g.sigma_rate_fraction * rng)
        R_pos = across**2 * np.eye(3) + (sigma_range**2 - across**2) * np.outer(u, u)
        rate_ok = valid[_RATE] > 0.5
        rr = float(obs[_S["range_rate"]][0])
        if not self.has_estimate:
            v0 = -u * rr if rate_ok else np.zeros(3)
            self.s = np.concatenate([-c, v0])
            self.P = np.zeros((6, 6))
            self.P[:3, :3] = R_pos
            self.P[3:, 3:] = np.eye(3) * (0.3**2 if rate_ok else 1.0)
            if rate_ok:
                self.P[3:, 3:] += (sigma_rate**2 - 0.3**2) * np.outer(u, u)
            self.has_estimate = True
            return
        H = np.zeros((4 if rate_ok else 3, 6))
        H[:3, :3] = np.eye(3)
        z = -c
        Rm = R_pos
        if rate_ok:
            H[3, 3:] = -u
            z = np.append(z, rr)
            Rm = np.zeros((4, 4))
            Rm[:3, :3] = R_pos
            Rm[3, 3] = sigma_rate**2
        S = H @ self.P @ H.T + Rm
        K = np.linalg.solve(S, H @ self.P).T
        self.s = self.s + K @ (z - H @ self.s)
        I_KH = np.eye(6) - K @ H
        self.P = I_KH @ self.P @ I_KH.T + K @ Rm @ K.T

    def port(self) -> tuple[FloatArray, FloatArray]:
        """Estimated port position [m] and its rate [m/s] in the docking frame."""
        return -self.s[:3] + self.lever - self.dock, -self.s[3:]

    def engaged(self, obs: npt.NDArray[np.floating]) -> bool:
        """This law should fly: an estimate, and a valid range beyond ``engage_range_m``."""
        valid = obs[_S["valid"]]
        return bool(
            self.has_estimate and valid[_RANGE] > 0.5
            and float(obs[_S["range"]][0]) > self.g.engage_range_m
        )

    def far(self, obs: npt.NDArray[np.floating]) -> bool:
        """Beyond ``far_range_m`` (an estimate and a valid range): this law flies whatever the
        pose, since the pose-based laws' speeds are sized for the last few hundred metres."""
        valid = obs[_S["valid"]]
        return bool(
            self.has_estimate and valid[_RANGE] > 0.5
            and float(obs[_S["range"]][0]) > self.g.far_range_m
        )

    # ------------------------------------------------------------------ law
    def desired_speed(self, z: float) -> float:
        """Closing speed [m/s] at distance ``z`` [m] to the port along the axis."""
        g = self.g
        return float(np.clip(g.slope * (z - g.hold_range_m), 0.0, g.v_max))

    def accel(self, obs: npt.NDArray[np.floating]) -> FloatArray:
        """Body (docking-frame) acceleration [m/s^2] of the law, before the thrust limit; zero
        before the first estimate."""
        if not self.has_estimate:
            return np.zeros(3)
        g = self.g
        p, p_dot = self.port()
        z = float(p[2])
        lat = float(np.hypot(p[0], p[1]))
        rate_ok = obs[_S["valid"]][_RATE] > 0.5
        v_des = self.desired_speed(z) if rate_ok else 0.0
        far = z > g.far_range_m
        if far and rate_ok:
            v_des = min(g.v_far_max, self.desired_speed(g.far_range_m) + g.far_slope * (z - g.far_range_m))
        if lat > g.lateral_cone * z + 2.0:
            v_des = 0.0
        # Over long steps (decision schedule) the speed loops would overshoot: no loop corrects
        # more than half its error within one step.
        dt = self.env_cfg.frame_period_s * self._frames_next
        kv, kd = min(g.kv, 0.5 / dt), min(g.kd_lat, 0.5 / dt)
        kp = g.kp_lat if kd == g.kd_lat else min(g.kp_lat, 0.25 * kd * kd)
        a = np.empty(3)
        a[:2] = kp * p[:2] + kd * p_dot[:2]
        a[2] = kv * (p_dot[2] + v_des)
        if far and self.cw is not None:
            a -= self.cw_accel()
        return a

    def cw_accel(self) -> FloatArray:
        """The CW model's natural acceleration of the chaser at the estimate, docking frame
        [m/s^2]: ``[3 n^2 x + 2 n y', -2 n x', -n^2 z]`` in LVLH."""
        assert self.cw is not None
        n, R = self.cw
        return R.T @ cw_acceleration(n, R @ self.s[:3], R @ self.s[3:])

    def applied(self, a_body: npt.ArrayLike) -> None:
        """Record the body acceleration [m/s^2] the returned action commands (after limits)."""
        self._a_prev = np.asarray(a_body, dtype=np.float64).reshape(3).copy()

    # ------------------------------------------------------------------ standalone
    def __call__(self, obs: npt.NDArray[np.floating]) -> npt.NDArray[np.float32]:
        self.update(obs)
        mass = self.dry + self.prop0 * float(obs[_S["fuel_fraction"]][0])
        thrust = self.accel(obs) * mass / self.max_thrust
        thrust = thrust / max(1.0, float(np.max(np.abs(thrust))))
        self.applied(thrust * self.max_thrust / mass)
        if self.six_dof:
            thrust = np.concatenate([thrust, np.zeros(3)])
        return thrust.astype(np.float32)
