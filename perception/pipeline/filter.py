"""Relative-motion filters of the TriDAR pipeline.

Long module: the pose filter's motion model (ego motion, tide, tumble), update, floors and two
covariances act on one state and are read together; the host's motion it takes and the bearing
mode's range filter sit beside it.

:class:`PoseFilter` is an error-state (multiplicative) extended Kalman filter over pose
measurements ``T_sensor_target`` with the ICP covariance as measurement noise. Its state is the
target's relative position ``p`` and velocity ``v`` (sensor frame), attitude ``R_sensor_target``
and relative angular velocity ``omega`` (sensor frame). The motion model is constant velocity and
constant angular velocity, driven by white acceleration and angular-acceleration noise (spectral
densities from the mission config); it predicts the pose for the next scan (area-of-interest
steering, ICP initial guess) and over a scan (de-skewing each point at its own time).

**Ego-motion aiding.** A chaser that rotates and thrusts moves the sensor frame, and without
knowing it the filter must treat the chaser's own manoeuvres as process noise: a synchronised
chaser turning at 5 deg/s around a tumbling target makes the relative rate change by the chaser's
angular acceleration, which the filter can only follow with a large angular-acceleration density
(and so a noisy rate). The host knows its motion (gyro, accelerometer, commanded thrust):
:meth:`PoseFilter.set_ego` takes the sensor's inertial angular velocity ``omega_s`` and inertial
acceleration ``a_s`` (sensor coordinates). The filter then models the target's motion
*inertially*: internally it carries the inertial relative velocity ``u`` and the target's inertial
angular velocity ``W``, both in sensor coordinates, and over a step ``dt``

    p' = E (p + u dt + a dt^2 / 2),  u' = E (u + a dt),  R' = E exp(W dt) R,  W' = E W,

with ``E = exp(-omega_s dt)`` the sensor frame's own turn and ``a = G p - a_s`` the target's
acceleration relative to the sensor: the tide ``G p`` of the gravity gradient (``EgoMotion``'s
``gravity_gradient``, from the host's orbit and attitude knowledge) less the sensor's own. Left
out, the tide (``n^2 r`` to ``2 n^2 r``, 1-5e-5 m/s^2 at 10-20 m in low orbit) is a steady force that a filter
with a small acceleration density follows with a lag: on the stock final approach the filtered
port was 4-13 mm behind (the ISS-like port) or 4-9 mm ahead (hubble, whose port faces another
way in LVLH) of unbiased registrations along the line of sight, an error the same every frame
that the covariance did not describe. The relative quantities it publishes
are ``v = u - omega_s x p`` (the time derivative of ``p`` in sensor coordinates) and
``w = W - omega_s``. With no ego data (``omega_s = a_s = 0``) this is the plain constant-velocity
model. With the target's inertia (``inertia=``), ``W`` follows Euler's torque-free equations in
the target body frame instead of staying constant: a nutating tumble is then predicted, not
tracked as noise.

Attitude errors are left perturbations in the sensor frame, ``R_true = exp(dtheta^) R_est``; the
error state is ``[dp, dv, dtheta, domega]`` (12). The measurement is the 6-vector
``[p_meas - p, log(R_meas R^T)]``, whose noise is the registration covariance as
:class:`~perception.estimation.registration.RegistrationResult` reports it (position of the target origin,
then attitude about the sensor axes).

:class:`RangeFilter` is the bearing-mode filter: a two-state (range, range rate) Kalman filter over
centroid ranges, so that the closing rate comes from a filter over time (seed 000 section 3.3).

**Two covariances.** ``P`` is the filter's own: its measurement noise carries the pipeline's
floors (model error, range bias) on top of ICP's, which keeps its gains robust. Those floors are
errors that repeat from frame to frame, not noise the filter averages, so ``P`` shrinks below
them without describing the error the state has. ``P_acc`` (the accuracy covariance) is the
covariance of the same state under the same gains with the registrations' own noise alone
(``cov_acc`` of :meth:`PoseFilter.update`; the Joseph form holds for any gain): what the filter
averaged away of ICP's noise. It also carries the time of flight's range offset
(``range_bias_m``, the sensor's configured bias) as a consider parameter (Schmidt's): one
offset shared by every time-of-flight registration, which the gains take into the state while
the time of flight ranges and let go at their own pace once triangulation takes over. Added
after the fact instead, as the frame's share of it, the published covariance had lost it at the
switch (near 7 m on the stock approach) while the state still held 1-4 mm of it for the next
metre. With ``scatter_window`` the registrations' own noise in ``P_acc`` is ICP's covariance
scaled to the scatter they show about the track (:meth:`PoseFilter.scatter_scale`). The
publisher adds the shape's correlated errors (:mod:`perception.pipeline.publish`), among them
the registrations' bias the sensor model predicts (``TrackingMode.predict_bias``).
``P_acc`` never feeds back into the state.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from perception.geometry import (
    fast_cross,
    fast_matrix_to_rotvec,
    fast_rotvec_to_matrix,
    los_basis,
    make_T,
    skew,
)

FloatArray = npt.NDArray[np.float64]

__all__ = ["EgoMotion", "PoseFilter", "RangeFilter", "UpdateResult", "gravity_gradient"]

#: 99.9% quantile of chi-square with 6 degrees of freedom: innovations beyond it are rejected.
CHI2_6_999 = 22.457744484825323

#: A measurement direction with more variance than this [m^2 or rad^2] is one the registration
#: left unobserved (ICP gives those 1e6, honest ones are far below 1).
UNOBSERVED_VARIANCE = 1.0e2

#: The scatter scale of the accuracy covariance (``scatter_window``) stays within these bounds.
SCATTER_SCALE_MIN, SCATTER_SCALE_MAX = 0.25, 100.0
#: ... is estimated from a track's registrations once this many have been fused (the early
#: updates' gains are large: their residual to the updated state says little of the noise) and
#: applied once the window holds this many degrees of freedom per block.
SCATTER_SETTLE_UPDATES, SCATTER_MIN_DOF = 10, 20

#: Pose and rate indices of the error state, in the order of a (dp, dtheta) 6-vector.
_POSE_IDX = np.array([0, 1, 2, 6, 7, 8])
_RATE_IDX = np.array([3, 4, 5, 9, 10, 11])


def _wn_block(dt: float, q: float) -> FloatArray:
    """Discrete white-noise-acceleration covariance (2x2) per axis for spectral density ``q``."""
    return q * np.array([[dt**3 / 3.0, dt**2 / 2.0], [dt**2 / 2.0, dt]])


@dataclass(frozen=True)
class EgoMotion:
    """The host's own motion, as its gyro and accelerometer give it (sensor coordinates).

    Attributes:
        omega: (3,) inertial angular velocity of the sensor frame [rad/s], sensor coordinates.
        accel: (3,) inertial acceleration of the sensor origin [m/s^2], sensor coordinates
            (thrust / mass plus the lever-arm terms of the chaser's rotation; gravity excluded,
            since the target falls with it).
        gravity_gradient: (3, 3) symmetric tidal tensor ``G`` [1/s^2], sensor coordinates, or
            None (not known). Both bodies fall, but not alike: the target's acceleration
            relative to the sensor from gravity is ``G p`` for a target at ``p``. In a circular
            orbit of mean motion ``n``, ``G = n^2 (3 r r^T - I)`` with ``r`` the unit radial
            (zenith) direction, which the host's orbit and attitude knowledge give; it is the
            Clohessy-Wiltshire model's gravity without the rotating frame's terms (the gyro
            carries those).
    """

    omega: FloatArray
    accel: FloatArray
    gravity_gradient: FloatArray | None = None

    def __post_init__(self) -> None:
        for name in ("omega", "accel"):
            val = np.asarray(getattr(self, name), dtype=np.float64)
            if val.shape != (3,) or not np.all(np.isfinite(val)):
                raise ValueError(f"EgoMotion.{name}={getattr(self, name)!r}; expected a finite (3,) vector")
            object.__setattr__(self, name, val)
        if self.gravity_gradient is not None:
            G = np.asarray(self.gravity_gradient, dtype=np.float64)
            if G.shape != (3, 3) or not np.all(np.isfinite(G)) or not np.allclose(G, G.T, rtol=0.0,
                                                                              atol=1e-9 * (1.0 + np.abs(G).max())):
                raise ValueError(f"EgoMotion.gravity_gradient={self.gravity_gradient!r}; expected a "
                                 "finite symmetric (3, 3) tensor [1/s^2]")
            object.__setattr__(self, "gravity_gradient", 0.5 * (G + G.T))

    def turned(self, M: FloatArray) -> EgoMotion:
        """The same motion in the axes ``M`` (3, 3 rotation) turns these into: ``accel`` and the
        gravity gradient turned, ``omega`` kept (the caller averages it)."""
        G = None if self.gravity_gradient is None else M @ self.gravity_gradient @ M.T
        return EgoMotion(self.omega, M @ self.accel, G)


def gravity_gradient(mean_motion: float, radial: npt.ArrayLike) -> FloatArray:
    """Tidal tensor ``n^2 (3 r r^T - I)`` [1/s^2] of a circular orbit of mean motion ``n``
    [rad/s] about the unit radial direction ``radial`` (any axes; the result is in the same)."""
    n = float(mean_motion)
    r = np.asarray(radial, dtype=np.float64).reshape(3)
    nr = float(np.linalg.norm(r))
    if not (math.isfinite(n) and n >= 0.0) or not (math.isfinite(nr) and nr > 0.0):
        raise ValueError(f"gravity_gradient(mean_motion={mean_motion!r}, radial={radial!r}); "
                         "expected n >= 0 [rad/s] and a finite non-zero direction")
    r = r / nr
    return n * n * (3.0 * np.outer(r, r) - np.eye(3))


def _principal(R: FloatArray, p_ref: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """``(lam, V, W)``: the variances (k,) and unit 6-vectors (6, k; position then attitude) of
    the principal directions a registration's covariance ``R`` (6, 6, at the reference point
    ``p_ref``) observes (variance in (0, UNOBSERVED_VARIANCE)), and their shares (3, k; each
    column sums to 1) along the line of sight to ``p_ref``, across it and in attitude: how
    :meth:`PoseFilter.scatter_scale`'s factors split over them. Whitening along and across
    directly would give the across marginal a share of an unobserved direction's 1e6 that a
    line of sight a hair off its axis picks up."""
    lam, V = np.linalg.eigh(0.5 * (R + R.T))
    obs = (lam > 0.0) & (lam < UNOBSERVED_VARIANCE)
    lam, V = lam[obs], V[:, obs]
    u = los_basis(p_ref)[0]
    w_al = np.square(u @ V[:3])
    w_pos = np.einsum("ij,ij->j", V[:3], V[:3])
    return lam, V, np.stack([w_al, w_pos - w_al, 1.0 - w_pos])


def _euler_rhs(omega: FloatArray, inertia: FloatArray, inertia_inv: FloatArray) -> FloatArray:
    """Torque-free Euler equations, body frame: ``I dw/dt = (I w) x w``."""
    return inertia_inv @ fast_cross(inertia @ omega, omega)


@dataclass(frozen=True)
class UpdateResult:
    """Outcome of a measurement update."""

    accepted: bool
    mahalanobis2: float


class PoseFilter:
    """Error-state EKF over relative pose (see the module docstring).

    Args:
        accel_psd: white acceleration spectral density [(m/s^2)^2 / Hz].
        angacc_psd: white angular-acceleration spectral density [(rad/s^2)^2 / Hz].
        init_velocity_sigma: 1-sigma of the velocity at initialisation [m/s].
        init_rate_sigma: 1-sigma of the angular velocity at initialisation [rad/s].
        gate_chi2: Mahalanobis gate of the 6-dof innovation (rejected beyond it).
        inertia: (3, 3) inertia tensor of the target [kg m^2, target frame]: predict the
            target's inertial rate with Euler's torque-free equations (a tumbling target);
            None: constant inertial rate.
        ref_point: (3,) point of the target body [m, target frame] whose motion the filter
            models (default: the target origin). Tracking the docking port instead of a centre of
            mass 12 m away keeps attitude noise from leaking, through the lever arm, into the
            position and velocity that matter at the port. Inputs and outputs
            (:meth:`initialize`, :meth:`update`, :meth:`pose_at`, :meth:`target_state`) are always
            about the target origin; ``p, v, R, w, P`` are the internal reference-point state.
        range_bias_m: 1-sigma of a range offset common to the registrations' time-of-flight
            points [m] (the sensor's calibration residual, ``sensor.tof.bias_m``): a consider
            parameter of ``P_acc`` only (the class doc's "Two covariances").
        scatter_window: registrations whose scatter about the track scales the measurement
            noise ``P_acc`` takes (:meth:`scatter_scale`; 0: ICP's covariance as it is).
    """

    def __init__(
        self,
        accel_psd: float = 1e-4,
        angacc_psd: float = 1e-4,
        init_velocity_sigma: float = 0.3,
        init_rate_sigma: float = float(np.deg2rad(6.0)),
        gate_chi2: float = CHI2_6_999,
        ref_point: npt.ArrayLike | None = None,
        inertia: npt.ArrayLike | None = None,
        range_bias_m: float = 0.0,
        scatter_window: int = 0,
    ) -> None:
        if not (isinstance(scatter_window, int) and scatter_window >= 0):
            raise ValueError(f"scatter_window={scatter_window!r}; expected an int >= 0 (frames)")
        self.scatter_window = scatter_window
        if not (np.isfinite(range_bias_m) and range_bias_m >= 0):
            raise ValueError(f"range_bias_m={range_bias_m}; expected a finite value >= 0 [m]")
        for name, val in (("accel_psd", accel_psd), ("angacc_psd", angacc_psd),
                          ("init_velocity_sigma", init_velocity_sigma),
                          ("init_rate_sigma", init_rate_sigma), ("gate_chi2", gate_chi2)):
            if not (np.isfinite(val) and val > 0):
                raise ValueError(f"{name}={val}; expected a finite value > 0")
        self.qa = float(accel_psd)
        self.qw = float(angacc_psd)
        self.sv0 = float(init_velocity_sigma)
        self.sw0 = float(init_rate_sigma)
        self.gate = float(gate_chi2)
        self.r = np.zeros(3) if ref_point is None else np.asarray(ref_point, dtype=np.float64).reshape(3)
        if not np.all(np.isfinite(self.r)):
            raise ValueError(f"ref_point={self.r.tolist()}; expected a finite (3,) point [m]")
        self.inertia: FloatArray | None = None
        self._inertia_inv: FloatArray | None = None
        if inertia is not None:
            J = np.asarray(inertia, dtype=np.float64)
            if J.shape != (3, 3) or not np.all(np.isfinite(J)) or not np.allclose(J, J.T) \
                    or np.min(np.linalg.eigvalsh(0.5 * (J + J.T))) <= 0:
                raise ValueError(f"inertia={J.tolist()}; expected a symmetric positive-definite (3, 3)")
            self.inertia = 0.5 * (J + J.T)
            self._inertia_inv = np.linalg.inv(self.inertia)
        self.initialized = False
        self.t = 0.0
        self.p = np.zeros(3)
        self.u = np.zeros(3)  # inertial velocity of the reference point, sensor coordinates
        self.R = np.eye(3)
        self.W = np.zeros(3)  # inertial angular velocity of the target, sensor coordinates
        self.P = np.eye(12)
        self.P_acc = np.eye(12)
        self.range_bias_var = float(range_bias_m) ** 2
        self.c_acc = np.zeros(12)  # covariance of P_acc's error with the range offset [m^2...]
        # The track's last registrations' residuals to the updated state, whitened by their own
        # covariance: (sum of squares, dof) along the line of sight and across it
        # (a tuple, rebound each update, so that copy() may share it).
        self.scatter: tuple[tuple[float, ...], ...] = ()
        self.n_fused = 0  # updates since initialize
        self.ego_omega = np.zeros(3)
        self.ego_accel = np.zeros(3)
        self.ego_gradient = np.zeros((3, 3))  # the tide: target acceleration G p (EgoMotion)
        self._q_cache: dict[float, FloatArray] = {}  # process noise by step length

    # ------------------------------------------------------------------ relative rates
    @property
    def v(self) -> FloatArray:
        """Velocity of the reference point: time derivative of ``p`` in sensor coordinates."""
        return self.u - fast_cross(self.ego_omega, self.p)

    @property
    def w(self) -> FloatArray:
        """Angular velocity of the target relative to the sensor, sensor coordinates [rad/s]."""
        return self.W - self.ego_omega

    def set_ego(self, ego: EgoMotion | None) -> None:
        """The sensor's inertial rate and acceleration from now on (None: a still sensor).

        The filter keeps its inertial state; only the split into "target" and "sensor" motion of
        what it publishes changes. Call :meth:`predict` to the measurement time of the old values
        first when the host's motion changed in between.
        """
        if ego is None:
            self.ego_omega, self.ego_accel = np.zeros(3), np.zeros(3)
            self.ego_gradient = np.zeros((3, 3))
        else:
            self.ego_omega, self.ego_accel = ego.omega.copy(), ego.accel.copy()
            G = ego.gravity_gradient
            self.ego_gradient = np.zeros((3, 3)) if G is None else G.copy()

    # ------------------------------------------------------------------ reference point
    def _pose_jacobian(self, R: FloatArray) -> FloatArray:
        """(6, 6) map of (dp, dtheta) at the target origin to the reference point."""
        J = np.eye(6)
        J[:3, 3:] = -skew(R @ self.r)
        return J

    def _to_ref(self, T: FloatArray, cov: FloatArray) -> tuple[FloatArray, FloatArray]:
        J = self._pose_jacobian(T[:3, :3])
        return make_T(T[:3, :3], T[:3, 3] + T[:3, :3] @ self.r), J @ cov @ J.T

    def _origin_jacobian(self) -> FloatArray:
        """(12, 12) map of the internal error state to the target origin's (p, v, dtheta, w)."""
        A = skew(self.R @ self.r)
        J = np.eye(12)
        J[0:3, 6:9] = A  # dp = dp_ref + [a]x dtheta
        J[3:6, 9:12] = A  # dv = dv_ref + [a]x domega + [w]x [a]x dtheta
        J[3:6, 6:9] = skew(self.w) @ A
        # internal (p, u, dtheta, W) -> (p, v, dtheta, w) of the reference point: v = u - ws x p
        J[3:6, 0:3] = -skew(self.ego_omega)
        return J

    def target_state(self) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray]:
        """``(p, v, R, w, P)`` of the target origin: position, velocity, attitude, rate, (12, 12)."""
        a = self.R @ self.r
        J = self._origin_jacobian()
        w, v = self.w, self.v
        return (self.p - a, v - fast_cross(w, a), self.R.copy(), w.copy(), J @ self.P @ J.T)

    def accuracy_covariance(self) -> FloatArray:
        """(12, 12) ``P_acc`` about the target origin, laid out as :meth:`target_state`'s ``P``."""
        J = self._origin_jacobian()
        return J @ self.P_acc @ J.T

    # ------------------------------------------------------------------ lifecycle
    def reset(self) -> None:
        """Forget everything (loss of track, planned restart)."""
        self.initialized = False

    def initialize(
        self, t: float, T_sensor_target: FloatArray, cov_pose: FloatArray,
        velocity: FloatArray | None = None, omega: FloatArray | None = None,
        cov_acc: FloatArray | None = None, tof_share: float = 0.0,
    ) -> None:
        """Start from a pose (and optionally rates), with ``cov_pose`` (6, 6) over (dp, dtheta);
        all about the target origin (velocity of the origin, rate in the sensor frame).
        ``cov_acc``: the pose's accuracy covariance (``P_acc``; default ``cov_pose``).
        ``tof_share``: the fraction of its points the time of flight ranged (their common range
        offset, ``range_bias_m``, is in the pose as it is)."""
        T_sensor_target = np.asarray(T_sensor_target, dtype=np.float64)
        self.P_acc = self._initial_P(self._to_ref(T_sensor_target, cov_pose if cov_acc is None else cov_acc)[1])
        T_ref, cov_pose = self._to_ref(T_sensor_target, cov_pose)
        # The pose is the measurement: its error holds the range offset in full.
        h = self._bias_row(T_ref[:3, 3], tof_share)
        self.c_acc = self.range_bias_var * h
        self.P_acc = self.P_acc + self.range_bias_var * np.outer(h, h)
        self.scatter = ()
        self.n_fused = 0
        self.t = float(t)
        self.p = T_ref[:3, 3].copy()
        self.R = T_ref[:3, :3].copy()
        w = np.zeros(3) if omega is None else np.asarray(omega, dtype=np.float64)
        self.W = w + self.ego_omega
        v0 = np.zeros(3) if velocity is None else np.asarray(velocity, dtype=np.float64)
        self.u = v0 + np.cross(w, self.R @ self.r) + np.cross(self.ego_omega, self.p)
        self.P = self._initial_P(cov_pose)
        self.initialized = True

    def _initial_P(self, cov_pose: FloatArray) -> FloatArray:
        """(12, 12) start covariance: ``cov_pose`` (6, 6, reference point) and the rates' priors."""
        P = np.zeros((12, 12))
        P[0:3, 0:3] = cov_pose[:3, :3]
        P[6:9, 6:9] = cov_pose[3:, 3:]
        P[0:3, 6:9] = cov_pose[:3, 3:]
        P[6:9, 0:3] = cov_pose[3:, :3]
        P[3:6, 3:6] = np.eye(3) * self.sv0**2
        P[9:12, 9:12] = np.eye(3) * self.sw0**2
        return P

    # ------------------------------------------------------------------ prediction
    def _propagate(self, dt: float) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray, FloatArray]:
        """Mean state after ``dt`` and the pieces of the Jacobian: ``(p, u, R, W, E, G)``.

        ``E`` turns sensor coordinates at the start into those at the end; ``G`` (3, 3) is the
        Jacobian of ``W'`` with respect to ``W`` (``E`` for a constant rate).
        """
        E = fast_rotvec_to_matrix(-self.ego_omega * dt)
        # The target's origin (its centre of mass) falls freely; the reference point turns about
        # it with the body. Relative to the sensor it accelerates by the tide G pc (gravity's
        # difference over the separation) less the sensor's own acceleration, held over the step.
        lever = self.R @ self.r
        pc = self.p - lever
        uc = self.u - fast_cross(self.W, lever)
        a = self.ego_gradient @ pc - self.ego_accel
        pc = E @ (pc + uc * dt + 0.5 * a * dt * dt)
        uc = E @ (uc + a * dt)
        if self.inertia is None or self._inertia_inv is None:
            R = E @ fast_rotvec_to_matrix(self.W * dt) @ self.R
            W = E @ self.W
            lever = R @ self.r
            return pc + lever, uc + fast_cross(W, lever), R, W, E, E
        # Torque-free tumble: RK4 on Euler's equations in the body frame, the attitude following
        # the body rate (midpoint rotation per sub-step).
        J, Ji = self.inertia, self._inertia_inv
        om0 = self.R.T @ self.W
        om = om0
        n = max(1, int(np.ceil(abs(dt) / 0.05)))
        h = dt / n
        dR = np.eye(3)
        for _ in range(n):
            k1 = _euler_rhs(om, J, Ji)
            k2 = _euler_rhs(om + 0.5 * h * k1, J, Ji)
            k3 = _euler_rhs(om + 0.5 * h * k2, J, Ji)
            k4 = _euler_rhs(om + h * k3, J, Ji)
            om_next = om + h / 6.0 * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
            dR = dR @ fast_rotvec_to_matrix(0.5 * (om + om_next) * h)
            om = om_next
        R = E @ self.R @ dR
        W = R @ om
        # d(dW') / d(dW): the linearised Euler equations over the step, in sensor coordinates.
        A = Ji @ (skew(J @ om0) - skew(om0) @ J)
        G = E @ self.R @ (np.eye(3) + A * dt) @ self.R.T
        lever = R @ self.r
        return pc + lever, uc + fast_cross(W, lever), R, W, E, G

    def _F_Q(self, dt: float, E: FloatArray, G: FloatArray) -> tuple[FloatArray, FloatArray]:
        F = np.zeros((12, 12))
        Gt = self.ego_gradient  # d(acceleration) / dp: the tide
        F[0:3, 0:3] = E @ (np.eye(3) + 0.5 * dt * dt * Gt)
        F[0:3, 3:6] = E * dt
        F[3:6, 0:3] = E @ (Gt * dt)
        F[3:6, 3:6] = E
        F[6:9, 6:9] = E @ fast_rotvec_to_matrix(self.W * dt)
        F[6:9, 9:12] = E * dt
        F[9:12, 9:12] = G
        return F, self._Q(dt)

    def _Q(self, dt: float) -> FloatArray:
        """Process noise over ``dt`` (isotropic per block, so the frame turn leaves it alone)."""
        cache = self._q_cache
        Q = cache.get(dt)
        if Q is None:
            Q = np.zeros((12, 12))
            qa, qw = _wn_block(dt, self.qa), _wn_block(dt, self.qw)
            for i in range(3):
                for (a, b), q in (((0, 3), qa), ((6, 9), qw)):
                    idx = [a + i, b + i]
                    Q[np.ix_(idx, idx)] = q
            if len(cache) < 64:
                cache[dt] = Q
        return Q

    def pose_at(self, t: float) -> FloatArray:
        """Predicted ``T_sensor_target`` (of the target origin) at time ``t`` (no state change)."""
        p, _, R, _, _, _ = self._propagate(float(t) - self.t)
        return make_T(R, p - R @ self.r)

    def copy(self) -> PoseFilter:
        """An independent snapshot of the state.

        Cheap (no deep copy): the filter never writes into its state arrays, it rebinds them, so
        the snapshot may share them. The process-noise cache is shared too (same ``dt``, same Q).
        """
        return copy.copy(self)

    def motion(self) -> Callable[[float], FloatArray]:
        """``t -> T_sensor_target`` from the current state (for de-skewing a scan)."""
        return self.copy().pose_at

    def predict(self, t: float) -> None:
        """Propagate the state and covariance to time ``t`` (>= current time)."""
        dt = float(t) - self.t
        if dt < 0:
            raise ValueError(f"predict to t={t} before the filter time {self.t}")
        if dt == 0:
            return
        p, u, R, W, E, G = self._propagate(dt)
        F, Q = self._F_Q(dt, E, G)
        self.p, self.u, self.R, self.W = p, u, R, W
        self.P = F @ self.P @ F.T + Q
        self.P_acc = F @ self.P_acc @ F.T + Q
        self.c_acc = F @ self.c_acc
        self.t = float(t)

    # ------------------------------------------------------------------ update
    def update(self, t: float, T_meas: FloatArray, cov_pose: FloatArray,
               cov_acc: FloatArray | None = None, tof_share: float = 0.0) -> UpdateResult:
        """Fuse a pose measurement taken at time ``t`` with covariance ``cov_pose`` over (dp, dtheta).

        Innovations beyond the chi-square gate are rejected (the state is only predicted).
        ``cov_acc``: the measurement's own noise for ``P_acc`` (default ``cov_pose``); it never
        changes the gain. ``tof_share``: the fraction of the registration's points the time of
        flight ranged, which carry the common range offset (``range_bias_m``) into ``P_acc``.
        """
        self.predict(t)
        T_meas = np.asarray(T_meas, dtype=np.float64)
        R_acc = None if cov_acc is None else self._to_ref(T_meas, cov_acc)[1]
        T_meas, cov_pose = self._to_ref(T_meas, cov_pose)
        z, H, S, d2 = self._innovation(T_meas, cov_pose)
        if not np.isfinite(d2) or d2 > self.gate:
            return UpdateResult(False, d2)
        K = np.linalg.solve(S, H @ self.P).T
        lam, V = np.linalg.eigh(0.5 * (cov_pose + cov_pose.T))
        N = V[:, lam > UNOBSERVED_VARIANCE]
        if N.size:
            # A direction this registration leaves unobserved is not updated, nor its rate: no
            # gain along it (the Joseph form below is exact for any gain, so its variance stays
            # the prior's). The optimal gain would put a little of the other directions'
            # information on it; with the null direction estimated a few degrees differently
            # each frame, a run of degenerate registrations (a cylinder bus's roll) summed that
            # into a roll pinned to a fraction of a degree that no frame had observed, and the
            # track flew a false roll rate published valid.
            B = np.zeros((12, 2 * N.shape[1]))
            B[_POSE_IDX, :N.shape[1]] = N
            B[_RATE_IDX, N.shape[1]:] = N
            K = K - B @ (B.T @ K)
        dx = K @ z
        self.p = self.p + dx[0:3]
        self.u = self.u + dx[3:6]
        self.R = fast_rotvec_to_matrix(dx[6:9]) @ self.R
        self.W = self.W + dx[9:12]
        I_KH = np.eye(12) - K @ H
        self.P = I_KH @ self.P @ I_KH.T + K @ cov_pose @ K.T  # Joseph form: stays SPD
        self.P = 0.5 * (self.P + self.P.T)
        R_acc = cov_pose if R_acc is None else R_acc
        principal = None
        if self.scatter_window:
            principal = _principal(R_acc, T_meas[:3, 3])
            R_acc = self._scattered(R_acc, *principal)
        # The same gain on ICP's noise and on the range offset the time-of-flight points share,
        # the same every frame (a consider parameter, Schmidt's): the error after the update
        # is (I - K H) e + K h b + K v, b the offset, h its direction in the measurement.
        Kh = K @ self._bias_row(T_meas[:3, 3], tof_share)[_POSE_IDX]
        A_c = I_KH @ self.c_acc
        self.P_acc = (I_KH @ self.P_acc @ I_KH.T + K @ R_acc @ K.T
                      + np.outer(A_c, Kh) + np.outer(Kh, A_c) + self.range_bias_var * np.outer(Kh, Kh))
        self.P_acc = 0.5 * (self.P_acc + self.P_acc.T)
        self.c_acc = A_c + self.range_bias_var * Kh
        self.n_fused += 1
        if principal is not None and self.n_fused > SCATTER_SETTLE_UPDATES:
            lam, V, W = principal
            r = np.concatenate([T_meas[:3, 3] - self.p, fast_matrix_to_rotvec(T_meas[:3, :3] @ self.R.T)])
            y2 = np.square(V.T @ r) / lam
            self.scatter = (*self.scatter[-(self.scatter_window - 1):],
                            tuple(float(x) for pair in zip(W[:2] @ y2, W[:2].sum(axis=1)) for x in pair))
        return UpdateResult(True, d2)

    def _scattered(self, R: FloatArray, lam: FloatArray, V: FloatArray, W: FloatArray) -> FloatArray:
        """The (6, 6) registration covariance ``R`` (reference point) with :meth:`scatter_scale`'s
        factors, given its observed principal directions (:func:`_principal`): each keeps its
        axis, and its variance takes the factors of along and across the line of sight (and 1
        for the attitude) in the shares its unit vector has of each. A congruence ``D R D`` would turn the directions,
        and the variance of one the registration barely observes (metres, or the 1e6 of an
        unobserved one) would leak into directions the gain acts on: the published position
        sigma went from 1.4 mm to 27 mm at hubble's switch to triangulation that way. What it
        leaves unobserved is kept as it is."""
        s_al, s_ac = self.scatter_scale()
        if s_al == s_ac == 1.0:
            return R
        g = (np.array([s_al, s_ac, 1.0]) @ W - 1.0) * lam
        return R + (V * g) @ V.T  # added, not rebuilt: R's small entries keep their precision

    def scatter_scale(self) -> tuple[float, float]:
        """(along the line of sight, across it) factors on the registrations' position
        covariance that ``P_acc`` takes.

        Covariance matching (Mehra's adaptive filtering, on the accuracy covariance alone): the
        residuals of the track's last ``scatter_window`` registrations to the state they updated,
        whitened by the registrations' own covariance over the directions they observe, have a
        mean square of 1 per degree of freedom when ICP's Cramer-Rao covariance describes their
        scatter. On some shapes it does not: on a generated assembly at 6-30 m the registrations
        scattered 2-2.5x their bound across the line of sight, frame after frame, and the
        published covariance, which averages them, was overconfident by as much (NEES 6-12); on
        others they scatter less. Along the line of sight (the time of flight's range noise,
        the switch to triangulation) and across it they differ, so each has its factor: the
        mean square, within [SCATTER_SCALE_MIN, SCATTER_SCALE_MAX], or 1 until the window holds
        SCATTER_MIN_DOF degrees of freedom there. The attitude keeps ICP's covariance: scaled
        the same way, its NEES moved away from 3 on the tuning runs (log-RMS over ten shapes
        1.00-1.10 -> 1.13-1.17; hubble's 1.8 -> 0.9). A settled filter's gain is small,
        so the residual to the updated state is the registration's own error less a small share
        (checked against the truth on recorded tracks: 5.45 vs 5.65, 1.02 vs 1.04). Errors the
        same every frame (a shape's bias at an aspect) do not show in it: the publisher's
        correlated terms carry those.
        """
        out = []
        for i in (0, 2):
            q = sum(w[i] for w in self.scatter)
            k = sum(w[i + 1] for w in self.scatter)
            out.append(min(max(q / k, SCATTER_SCALE_MIN), SCATTER_SCALE_MAX) if k >= SCATTER_MIN_DOF else 1.0)
        return out[0], out[1]

    def _innovation(self, T_ref: FloatArray, cov_ref: FloatArray
                    ) -> tuple[FloatArray, FloatArray, FloatArray, float]:
        """``(z, H, S, d2)`` of a pose measurement at the reference point (``T_ref``, its
        covariance ``cov_ref``) against the state as it is: the innovation (dp, dtheta), the
        measurement matrix, the innovation covariance and the gate's statistic (inf when ``S``
        is singular)."""
        z = np.concatenate([
            T_ref[:3, 3] - self.p,
            fast_matrix_to_rotvec(T_ref[:3, :3] @ self.R.T),
        ])
        H = np.zeros((6, 12))
        H[0:3, 0:3] = np.eye(3)
        H[3:6, 6:9] = np.eye(3)
        S = H @ self.P @ H.T + cov_ref
        S = 0.5 * (S + S.T)
        try:
            Sinv_z = np.linalg.solve(S, z)
        except np.linalg.LinAlgError:
            return z, H, S, float("inf")
        return z, H, S, float(z @ Sinv_z)

    def mahalanobis2(self, t: float, T_meas: FloatArray, cov_pose: FloatArray) -> float:
        """The gate's statistic of a pose measurement taken at ``t`` (>= the filter's time) with
        covariance ``cov_pose``, both about the target origin, without fusing it (the filter is
        left as it is)."""
        f = self.copy()
        f.predict(t)
        T_ref, cov_ref = f._to_ref(np.asarray(T_meas, dtype=np.float64), cov_pose)
        return f._innovation(T_ref, cov_ref)[3]

    def moved_to(self, T_meas: FloatArray, cov_pose: FloatArray) -> PoseFilter:
        """A copy of the filter, at its time, with its pose moved onto the measurement
        ``T_meas`` (target origin, taken at the filter's time) along every direction
        ``cov_pose`` observes; along those it leaves unobserved (variance beyond
        ``UNOBSERVED_VARIANCE``, where a degenerate registration's pose is wherever ICP left
        it) the pose stays the filter's. Rates and covariances are the filter's."""
        T_ref, cov_ref = self._to_ref(np.asarray(T_meas, dtype=np.float64), cov_pose)
        z = self._innovation(T_ref, cov_ref)[0]
        lam, V = np.linalg.eigh(0.5 * (cov_ref + cov_ref.T))
        O = V[:, lam <= UNOBSERVED_VARIANCE]
        dz = O @ (O.T @ z)
        g = self.copy()
        g.p = self.p + dz[0:3]
        g.R = fast_rotvec_to_matrix(dz[3:6]) @ self.R
        return g

    @staticmethod
    def _bias_row(p_ref: FloatArray, tof_share: float) -> FloatArray:
        """(12,) error of the state that a unit range offset of a registration puts in it (the
        pose block only): its time-of-flight points (``tof_share`` of them) move along their
        rays, the registered pose along the line of sight to the reference point ``p_ref``."""
        s = float(tof_share)
        if not (np.isfinite(s) and 0.0 <= s <= 1.0):
            raise ValueError(f"tof_share={tof_share}; expected a fraction in [0, 1]")
        h = np.zeros(12)
        n = float(np.linalg.norm(p_ref))
        if s > 0.0 and n > 0.0:
            h[0:3] = s * p_ref / n
        return h

    def rate_doubt(self, T_meas: FloatArray, since_t: float) -> FloatArray:
        """The velocity [m/s] and angular-rate [rad/s] errors, (6,), that alone would explain how
        far the pose ``T_meas`` (target origin, taken at the filter's time) is from the
        filter's, built up since ``since_t`` [s] (its last accepted update): what a restart on
        registrations the gate rejected should doubt in the rates it keeps."""
        T_ref, _ = self._to_ref(np.asarray(T_meas, dtype=np.float64), np.zeros((6, 6)))
        dt = max(self.t - float(since_t), 1e-3)
        dp = T_ref[:3, 3] - self.p
        dth = fast_matrix_to_rotvec(T_ref[:3, :3] @ self.R.T)
        return np.concatenate([dp, dth]) / dt

    def floor_velocity(self, axis: npt.ArrayLike, sigma: float) -> None:
        """Raise the velocity variance along ``axis`` (sensor coordinates) to at least ``sigma**2``
        [(m/s)^2], as process noise injected now (the other directions and the cross terms are
        left alone, so the covariance stays positive definite).

        Registrations along an axis the scan leaves weak carry an error that persists from frame
        to frame (a slide): a filter that averages them as independent becomes sure of a
        velocity the scans never observed, then ignores the registrations that would correct
        it.
        """
        self._floor(slice(3, 6), axis, sigma, "floor_velocity")

    def floor_position(self, axis: npt.ArrayLike, sigma: float) -> None:
        """Raise the position variance along ``axis`` (sensor coordinates) to at least
        ``sigma**2`` [m^2], as :meth:`floor_velocity` does the velocity's.

        The same slide's registrations are not independent: their error along it is one offset
        seen again, so averaging ``n`` of them does not divide its variance by ``n``. Floored,
        the position stays as uncertain along the slide as one registration says it is.
        """
        self._floor(slice(0, 3), axis, sigma, "floor_position")

    def floor_turn(self, axis: npt.ArrayLike, pivot: npt.ArrayLike, sigma: float) -> None:
        """Raise the attitude variance about ``axis`` (sensor coordinates), a turn about the
        line through ``pivot`` (sensor frame [m]), to at least ``sigma**2`` [rad^2], as
        :meth:`floor_position` does the position's. The reference point moves with the turn, so
        the variance goes in along ``[e x (p - pivot), e]``, not along the attitude alone: a roll
        about a bus's axis leaves a point on that axis where it is.
        """
        q = np.asarray(pivot, dtype=np.float64).reshape(3)
        if not np.all(np.isfinite(q)):
            raise ValueError(f"floor_turn(pivot={q.tolist()}); expected a finite pivot [m]")
        self._floor(slice(6, 9), axis, sigma, "floor_turn", lever=self.p - q)

    def _floor(self, block: slice, axis: npt.ArrayLike, sigma: float, name: str,
               lever: FloatArray | None = None) -> None:
        """Raise the variance of ``block`` along ``axis`` to ``sigma**2``; with ``lever``, an
        attitude turn that also moves the reference point by ``e x lever`` (position block)."""
        e = np.asarray(axis, dtype=np.float64).reshape(3)
        n = float(np.linalg.norm(e))
        if not (np.isfinite(n) and n > 0 and np.isfinite(sigma)):
            raise ValueError(f"{name}(axis={e.tolist()}, sigma={sigma}); expected a finite "
                             "non-zero axis and a finite sigma")
        e = e / n
        u = np.zeros(12)
        u[block] = e
        if lever is not None:
            u[0:3] = np.cross(e, lever)
        for name_P in ("P", "P_acc"):  # a slide is an error either covariance must carry
            P = getattr(self, name_P)
            gap = float(sigma) ** 2 - float(e @ P[block, block] @ e)
            if gap > 0.0:
                setattr(self, name_P, P + gap * np.outer(u, u))

    @property
    def T_sensor_target(self) -> FloatArray:
        """Current pose of the target origin."""
        return make_T(self.R, self.p - self.R @ self.r)


class RangeFilter:
    """Two-state (range, range rate) Kalman filter for bearing mode.

    Args:
        accel_psd: white acceleration spectral density along the line of sight [(m/s^2)^2/Hz].
    """

    def __init__(self, accel_psd: float = 1e-4) -> None:
        if not (np.isfinite(accel_psd) and accel_psd > 0):
            raise ValueError(f"accel_psd={accel_psd}; expected a finite value > 0")
        self.q = float(accel_psd)
        self.initialized = False
        self.t = 0.0
        self.x = np.zeros(2)
        self.P = np.eye(2)
        self.n_updates = 0

    def reset(self) -> None:
        self.initialized = False
        self.n_updates = 0

    def update(self, t: float, range_m: float, sigma_m: float, accel: float = 0.0) -> None:
        """Fuse a range measurement [m] with 1-sigma ``sigma_m`` taken at time ``t``; ``accel``
        [m/s^2] is the known range acceleration since the last update (the host's own thrust
        along the line of sight, from its accelerometer)."""
        r2 = max(float(sigma_m), 1e-4) ** 2
        if not self.initialized:
            self.t, self.x, self.P = float(t), np.array([range_m, 0.0]), np.diag([r2, 1.0])
            self.initialized = True
            self.n_updates = 1
            return
        dt = max(float(t) - self.t, 0.0)
        F = np.array([[1.0, dt], [0.0, 1.0]])
        self.x = F @ self.x
        if accel != 0.0:
            self.x = self.x + np.array([0.5 * accel * dt * dt, accel * dt])
        self.P = F @ self.P @ F.T + _wn_block(dt, self.q)
        S = self.P[0, 0] + r2
        K = self.P[:, 0] / S
        self.x = self.x + K * (range_m - self.x[0])
        self.P = self.P - np.outer(K, self.P[0, :])
        self.P = 0.5 * (self.P + self.P.T)
        self.t = float(t)
        self.n_updates += 1

    @property
    def range(self) -> float:
        return float(self.x[0])

    @property
    def range_rate(self) -> float:
        return float(self.x[1])

    @property
    def rate_valid(self) -> bool:
        """The rate is a measurement once two ranges have been fused."""
        return self.initialized and self.n_updates >= 2
