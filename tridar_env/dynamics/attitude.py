"""Target attitude: torque-free rigid body and the three target attitude modes.

Attitudes are scalar-first Hamilton quaternions ``(w, x, y, z)``, ``w >= 0``; rates are inertial
angular velocities in body coordinates [rad/s].

* :func:`principal_axes`, :func:`spin_with_nutation`: principal axes and tumbling initial states.
* :func:`rigid_body_rates`, :class:`RigidBodyAttitude`: Euler's equations and quaternion
  kinematics, integrated with DOP853.
* :class:`TargetAttitudeModel`: ``"lvlh_hold"``, ``"inertial_hold"`` or ``"tumble"``, read out
  as ``R_lvlh_target`` (target body -> LVLH).
"""

from __future__ import annotations

from typing import Literal

import numpy as np
import numpy.typing as npt
from scipy.integrate import solve_ivp
from scipy.spatial.transform import Rotation

from perception.geometry import fast_quat_to_matrix, rotation_z
from tridar_env.dynamics._checks import (
    _array,
    _finite_scalar,
    _inertia,
    _non_negative,
    _quat_wxyz,
)
from tridar_env.dynamics.frames import _rotation_from_wxyz, _wxyz

__all__ = [
    "RigidBodyAttitude",
    "TargetAttitudeModel",
    "principal_axes",
    "rigid_body_rates",
    "spin_with_nutation",
]

FloatArray = npt.NDArray[np.float64]

# Torque-free attitude integration: DOP853 at these tolerances keeps energy and momentum to
# ~1e-12 relative per 1,000 s at tumble rates of a few deg/s (the tests check 1e-9).
_ATT_RTOL = 1e-12
_ATT_ATOL = 1e-14


def principal_axes(inertia: npt.ArrayLike) -> tuple[FloatArray, FloatArray]:
    """Principal moments and axes of a body inertia tensor.

    Args:
        inertia: ``(3, 3)`` inertia tensor about the centre of mass, body frame [kg m^2].

    Returns:
        ``(moments, axes)``: ``(3,)`` ascending principal moments [kg m^2] and ``(3, 3)``
        rotation whose columns are the unit principal axes in body coordinates
        (right-handed, ``inertia = axes @ diag(moments) @ axes.T``).

    Raises:
        ValueError: If ``inertia`` is not a valid inertia tensor.
    """
    moments, axes = np.linalg.eigh(_inertia("inertia", inertia))
    if np.linalg.det(axes) < 0.0:
        axes[:, 2] = -axes[:, 2]
    return moments, axes


def spin_with_nutation(
    inertia: npt.ArrayLike,
    spin_rate_rad_s: float,
    nutation_rad: float = 0.0,
    axis: Literal["max", "min"] = "max",
    phase_rad: float = 0.0,
    h_direction: npt.ArrayLike | None = None,
) -> tuple[FloatArray, FloatArray]:
    """Return an initial attitude and body rate spinning about a principal axis, with nutation.

    The two tumbling cases of seed 003 sect. 3.1: a rapid spin about the maximum or minimum
    inertia axis (``nutation_rad=0``), or a spin with a nutation angle. The angular momentum
    ``H`` makes ``nutation_rad`` with the chosen principal axis ``e_s``; its transverse part
    points at ``phase_rad`` from the intermediate principal axis towards the third axis.
    ``spin_rate_rad_s`` is the body rate component about ``e_s``, so
    ``|H| = J_s spin_rate / cos(nutation)``.

    Args:
        inertia: ``(3, 3)`` body inertia tensor [kg m^2].
        spin_rate_rad_s: Body rate about the spin axis [rad/s] (sign sets the spin sense).
        nutation_rad: Angle between ``H`` and the spin axis [rad], in ``[0, pi/2)``.
        axis: ``"max"`` or ``"min"`` inertia axis.
        phase_rad: Direction of the transverse momentum about the spin axis [rad].
        h_direction: ``(3,)`` inertial direction to align ``H`` with; ``None`` for an
            identity initial attitude.

    Returns:
        ``(q0, omega0_body)``: ``(4,)`` scalar-first quaternion of the body in the inertial
        frame (``w >= 0``) and ``(3,)`` body angular velocity [rad/s].

    Raises:
        ValueError: On an invalid inertia, axis or angle.
    """
    moments, axes = principal_axes(inertia)
    rate = _finite_scalar("spin_rate_rad_s", spin_rate_rad_s)
    nut = _finite_scalar("nutation_rad", nutation_rad)
    if not 0.0 <= nut < 0.5 * np.pi:
        raise ValueError(f"nutation_rad={nutation_rad!r} must be in [0, pi/2)")
    phase = _finite_scalar("phase_rad", phase_rad)
    if axis == "max":
        k, t1, t2 = 2, 1, 0
    elif axis == "min":
        k, t1, t2 = 0, 1, 2
    else:
        raise ValueError(f"axis={axis!r} must be 'max' or 'min'")
    h_mag = moments[k] * rate / np.cos(nut)
    h_principal = np.zeros(3)
    h_principal[k] = h_mag * np.cos(nut)
    h_principal[t1] = abs(h_mag) * np.sin(nut) * np.cos(phase)
    h_principal[t2] = abs(h_mag) * np.sin(nut) * np.sin(phase)
    omega_body = axes @ (h_principal / moments)

    if h_direction is None or rate == 0.0:
        q0 = np.array([1.0, 0.0, 0.0, 0.0])
    else:
        target = _array("h_direction", h_direction, 3, batch=False)
        if not np.any(target):
            raise ValueError(f"h_direction={target.tolist()} must be non-zero")
        h_body = axes @ h_principal
        rot, _ = Rotation.align_vectors(target[None, :], h_body[None, :])
        q0 = _wxyz(rot)
    return q0, omega_body


def rigid_body_rates(
    qw: float, qx: float, qy: float, qz: float, p: float, q: float, r: float,
    inertia_rows: list[list[float]], inertia_inv_rows: list[list[float]], torque: list[float],
) -> tuple[float, float, float, float, float, float, float]:
    """Time derivative of ``(quaternion, body rate)`` of a rigid body under a body torque.

    Quaternion kinematics ``dq = q (x) (0, w) / 2`` and Euler's equations
    ``dw = I^-1 (torque - w x (I w))``, in plain floats: integrators call this thousands of times
    on a 7-vector, where numpy's per-call overhead (np.cross above all) would be most of the cost.
    """
    (i00, i01, i02), (i10, i11, i12), (i20, i21, i22) = inertia_rows
    (j00, j01, j02), (j10, j11, j12), (j20, j21, j22) = inertia_inv_rows
    t0, t1, t2 = torque
    h0 = i00 * p + i01 * q + i02 * r
    h1 = i10 * p + i11 * q + i12 * r
    h2 = i20 * p + i21 * q + i22 * r
    e0 = t0 - (q * h2 - r * h1)
    e1 = t1 - (r * h0 - p * h2)
    e2 = t2 - (p * h1 - q * h0)
    return (
        -0.5 * (qx * p + qy * q + qz * r),
        0.5 * (qw * p + qy * r - qz * q),
        0.5 * (qw * q + qz * p - qx * r),
        0.5 * (qw * r + qx * q - qy * p),
        j00 * e0 + j01 * e1 + j02 * e2,
        j10 * e0 + j11 * e1 + j12 * e2,
        j20 * e0 + j21 * e1 + j22 * e2,
    )


class RigidBodyAttitude:
    """Torque-free rigid body: Euler's equations + quaternion kinematics.

    ``I w_dot = -w x (I w)`` with the full inertia tensor, ``q_dot = q (x) [0, w] / 2`` with
    ``q`` the body-to-inertial quaternion and ``w`` the inertial angular velocity in body
    coordinates. Integrated with DOP853 (rtol 1e-12) and renormalised at the end of a step;
    kinetic energy and inertial angular momentum stay within ~1e-12 relative over 1,000 s.

    Args:
        inertia: ``(3, 3)`` inertia about the centre of mass, body frame [kg m^2].

    Example:
        >>> body = RigidBodyAttitude(np.diag([10.0, 20.0, 30.0]))
        >>> q, w = body.step([1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.1], 1.0)
        >>> bool(np.allclose(w, [0.0, 0.0, 0.1]))
        True
    """

    def __init__(self, inertia: npt.ArrayLike) -> None:
        self.inertia = _inertia("inertia", inertia)
        self.inertia_inv = np.linalg.inv(self.inertia)
        self._inertia_rows = self.inertia.tolist()
        self._inertia_inv_rows = self.inertia_inv.tolist()
        self._torque = np.zeros(3)

    def _rhs(self, _t: float, y: FloatArray) -> FloatArray:
        return np.array(rigid_body_rates(
            *y.tolist(), self._inertia_rows, self._inertia_inv_rows, self._torque.tolist()
        ))

    def _check(
        self, q_wxyz: npt.ArrayLike, omega_body: npt.ArrayLike
    ) -> tuple[FloatArray, FloatArray]:
        return _quat_wxyz("q_wxyz", q_wxyz), _array("omega_body", omega_body, 3, batch=False)

    def step(
        self,
        q_wxyz: npt.ArrayLike,
        omega_body: npt.ArrayLike,
        dt: float,
        torque_body: npt.ArrayLike | None = None,
    ) -> tuple[FloatArray, FloatArray]:
        """Propagate the attitude by ``dt``, optionally under a constant body torque [N m].

        Args:
            q_wxyz: ``(4,)`` body-to-inertial unit quaternion, scalar first.
            omega_body: ``(3,)`` inertial angular velocity in body coordinates [rad/s].
            dt: Step [s], >= 0.

        Returns:
            ``(q, omega)`` at ``t + dt``: ``(4,)`` unit quaternion with ``w >= 0`` and ``(3,)``
            body rate [rad/s].

        Raises:
            ValueError: On a non-unit or non-finite quaternion, bad rate or negative ``dt``.
        """
        q0, w0 = self._check(q_wxyz, omega_body)
        dt = _non_negative("dt", dt)
        if dt == 0.0:
            return _wxyz(_rotation_from_wxyz(q0)), w0.copy()
        if torque_body is None:
            q, w = self.propagate(q0, w0, np.array([dt]))
            return q[0], w[0]
        self._torque = _array("torque_body", torque_body, 3, batch=False)
        try:
            q, w = self.propagate(q0, w0, np.array([dt]))
        finally:
            self._torque = np.zeros(3)
        return q[0], w[0]

    def propagate(
        self, q_wxyz: npt.ArrayLike, omega_body: npt.ArrayLike, times: npt.ArrayLike
    ) -> tuple[FloatArray, FloatArray]:
        """Propagate in one integration and sample at several times.

        Args:
            q_wxyz: ``(4,)`` initial body-to-inertial quaternion, scalar first.
            omega_body: ``(3,)`` initial body rate [rad/s].
            times: ``(T,)`` non-decreasing times after the initial epoch [s], all > 0.

        Returns:
            ``(q, omega)``: ``(T, 4)`` unit quaternions (``w >= 0``) and ``(T, 3)`` body rates.
        """
        q0, w0 = self._check(q_wxyz, omega_body)
        t = np.asarray(times, dtype=np.float64)
        if t.ndim != 1 or t.size == 0:
            raise ValueError(f"times has shape {t.shape}; expected (T,) with T >= 1")
        if not np.all(np.isfinite(t)) or np.any(t <= 0.0) or np.any(np.diff(t) < 0.0):
            raise ValueError(f"times={t!r} must be finite, > 0 and non-decreasing")
        sol = solve_ivp(
            self._rhs,
            (0.0, float(t[-1])),
            np.concatenate([q0, w0]),
            method="DOP853",
            t_eval=t,
            rtol=_ATT_RTOL,
            atol=_ATT_ATOL,
        )
        if not sol.success:
            raise RuntimeError(f"attitude integration failed: {sol.message}")
        q = sol.y[:4].T
        q = q / np.linalg.norm(q, axis=1, keepdims=True)
        q = np.where(q[:, :1] < 0.0, -q, q)
        return q, sol.y[4:].T.copy()

    def kinetic_energy(self, omega_body: npt.ArrayLike) -> float:
        """Rotational kinetic energy ``w . I w / 2`` [J]."""
        w = np.asarray(omega_body, dtype=np.float64)
        return float(0.5 * w @ self.inertia @ w)

    def angular_momentum_inertial(
        self, q_wxyz: npt.ArrayLike, omega_body: npt.ArrayLike
    ) -> FloatArray:
        """Angular momentum ``R(q) I w`` in the inertial frame ``(3,)`` [kg m^2/s]."""
        w = np.asarray(omega_body, dtype=np.float64)
        return _rotation_from_wxyz(np.asarray(q_wxyz, dtype=np.float64)).apply(self.inertia @ w)


_ATTITUDE_MODES = ("lvlh_hold", "inertial_hold", "tumble")


class TargetAttitudeModel:
    """Target attitude relative to LVLH for the three target behaviours.

    * ``"lvlh_hold"``: fixed in LVLH (an ISS-like attitude-controlled station).
    * ``"inertial_hold"``: fixed in inertial space; seen from LVLH it turns at ``-n`` about z.
    * ``"tumble"``: torque-free rigid body (:class:`RigidBodyAttitude`).

    The attitude is propagated in an inertial frame ``I`` that coincides with LVLH at the
    reset epoch; LVLH turns relative to ``I`` at ``+n`` about its z (orbit normal, circular
    orbit), so ``R_lvlh_target(t) = Rz(n t)^T R_I_target(t)`` at output.

    Args:
        mode: ``"lvlh_hold"``, ``"inertial_hold"`` or ``"tumble"``.
        n: Mean motion of the target orbit [rad/s], >= 0.
        inertia: ``(3, 3)`` body inertia [kg m^2]; required for ``"tumble"``.

    Example:
        >>> model = TargetAttitudeModel("inertial_hold", n=mean_motion(400e3))
        >>> model.reset([1.0, 0.0, 0.0, 0.0])
        >>> model.step(10.0)
        >>> model.q_lvlh_target.shape
        (4,)
    """

    def __init__(
        self,
        mode: Literal["lvlh_hold", "inertial_hold", "tumble"],
        n: float,
        inertia: npt.ArrayLike | None = None,
    ) -> None:
        if mode not in _ATTITUDE_MODES:
            raise ValueError(f"mode={mode!r} must be one of {_ATTITUDE_MODES}")
        self.mode = mode
        self.n = _non_negative("n", n)
        self._body: RigidBodyAttitude | None = None
        if mode == "tumble":
            if inertia is None:
                raise ValueError("inertia=None; mode 'tumble' needs a (3, 3) inertia tensor")
            self._body = RigidBodyAttitude(inertia)
        elif inertia is not None:
            _inertia("inertia", inertia)
        self.t = 0.0
        self._q0_lvlh_target = np.array([1.0, 0.0, 0.0, 0.0])
        self._R0_lvlh_target = np.eye(3)
        self._q_i_target = self._q0_lvlh_target.copy()  # tumble only
        self._omega_body = np.zeros(3)
        # Tumbling: states at the next steps of equal length, from one integration per chunk
        # (one solve_ivp call per step dominated the environment's step time).
        self._chunk: tuple[float, FloatArray, FloatArray] | None = None
        self._chunk_i = 0

    def reset(self, q_lvlh_target: npt.ArrayLike, omega_body: npt.ArrayLike | None = None) -> None:
        """Set the attitude at the new epoch ``t = 0``.

        Args:
            q_lvlh_target: ``(4,)`` target attitude in LVLH, scalar first.
            omega_body: ``(3,)`` target inertial angular velocity in body coordinates [rad/s];
                ``"tumble"`` only (default zero); must be ``None`` for the hold modes.

        Raises:
            ValueError: On a bad quaternion or rate, or a rate given to a hold mode.
        """
        q = _quat_wxyz("q_lvlh_target", q_lvlh_target)
        if self.mode == "tumble":
            w = np.zeros(3) if omega_body is None else _array("omega_body", omega_body, 3, False)
        elif omega_body is not None:
            raise ValueError(
                f"omega_body={np.asarray(omega_body).tolist()} given for mode={self.mode!r}; "
                "the hold modes set the rate themselves"
            )
        elif self.mode == "lvlh_hold":
            # Co-rotating with LVLH: inertial rate n about the orbit normal.
            w = _rotation_from_wxyz(q).inv().apply([0.0, 0.0, self.n])
        else:
            w = np.zeros(3)
        self.t = 0.0
        self._q0_lvlh_target = q
        self._R0_lvlh_target = fast_quat_to_matrix(q)
        self._R0_lvlh_target.setflags(write=False)
        self._q_i_target = q.copy()
        self._omega_body = w
        self._chunk = None

    #: Steps integrated at once in tumble mode.
    CHUNK_STEPS = 256

    def step(self, dt: float) -> None:
        """Advance by ``dt`` [s] (>= 0).

        In tumble mode, runs of equal steps are integrated in chunks of :attr:`CHUNK_STEPS` by one
        dense DOP853 solve (same tolerances as :class:`RigidBodyAttitude`), then read back.
        """
        dt = _non_negative("dt", dt)
        self.t += dt
        if self._body is None or dt == 0.0:
            return
        if self._chunk is None or self._chunk[0] != dt or self._chunk_i >= self.CHUNK_STEPS:
            times = dt * np.arange(1, self.CHUNK_STEPS + 1)
            q, w = self._body.propagate(self._q_i_target, self._omega_body, times)
            self._chunk = (dt, q, w)
            self._chunk_i = 0
        _, q, w = self._chunk
        self._q_i_target, self._omega_body = q[self._chunk_i].copy(), w[self._chunk_i].copy()
        self._chunk_i += 1

    @property
    def rotation_lvlh_target(self) -> Rotation:
        """Target attitude in LVLH as a ``Rotation`` (body coordinates -> LVLH)."""
        q0 = _rotation_from_wxyz(self._q0_lvlh_target)
        if self.mode == "lvlh_hold":
            return q0
        lvlh_from_inertial = Rotation.from_rotvec([0.0, 0.0, -self.n * self.t])
        if self.mode == "inertial_hold":
            return lvlh_from_inertial * q0
        return lvlh_from_inertial * _rotation_from_wxyz(self._q_i_target)

    @property
    def R_lvlh_target(self) -> FloatArray:
        """``(3, 3)`` rotation mapping target-body coordinates to LVLH (a new array).

        Same rotation as :attr:`rotation_lvlh_target`, built with matrix products in plain numpy
        (to round-off): this is read every step and a SciPy ``Rotation`` costs tens of us.
        """
        if self.mode == "lvlh_hold":
            return self._R0_lvlh_target.copy()
        lvlh_from_inertial = rotation_z(-self.n * self.t)
        if self.mode == "inertial_hold":
            return lvlh_from_inertial @ self._R0_lvlh_target
        return lvlh_from_inertial @ fast_quat_to_matrix(self._q_i_target)

    @property
    def q_lvlh_target(self) -> FloatArray:
        """``(4,)`` scalar-first quaternion of the target in LVLH, ``w >= 0``."""
        return _wxyz(self.rotation_lvlh_target)

    @property
    def omega_body(self) -> FloatArray:
        """``(3,)`` target angular velocity relative to inertial, body coordinates [rad/s]."""
        return self._omega_body.copy()

    @property
    def omega_rel_lvlh_body(self) -> FloatArray:
        """``(3,)`` target angular velocity relative to LVLH, body coordinates [rad/s]."""
        lvlh_rate_body = self.rotation_lvlh_target.inv().apply([0.0, 0.0, self.n])
        return self._omega_body - lvlh_rate_body
