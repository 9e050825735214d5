"""Truth dynamics: chaser relative orbital motion and target attitude.

Long module: moved whole from ``tridar_env/dynamics.py``; the next commit splits it by job.

Frames (see DESIGN.md):

* ECI: Earth-centred inertial, z along the Earth's pole (the J2 axis).
* LVLH / Hill of the target: x radial (away from Earth), y along-track (+V-bar), z orbit normal
  (``r x v``). For a circular orbit it rotates relative to inertial space at ``+n`` about its z.
* Target body: fixed to the target, origin at its centre of mass. Its attitude is
  ``R_lvlh_target`` at the API edge (scalar-first Hamilton quaternion ``(w, x, y, z)``, ``w >= 0``).

Relative states are ``(6,)`` ``[x, y, z, vx, vy, vz]`` of the chaser with respect to the target,
expressed in LVLH with velocities taken in the rotating frame, in [m] and [m/s]. Accelerations
are chaser thrust accelerations in LVLH [m/s^2], held constant in LVLH over a step (zero-order
hold), the convention of the Clohessy-Wiltshire (CW) input matrix.

Contents:

* :func:`mean_motion`, :func:`cw_stm`, :class:`CWPropagator`: CW with the exact closed-form
  state transition and zero-order-hold input matrix.
* :class:`NonlinearRelativePropagator`: both spacecraft under two-body gravity (+ optional J2)
  integrated in ECI, with exact LVLH <-> ECI conversion (:func:`lvlh_frame`,
  :func:`relative_lvlh_from_eci`, :func:`eci_from_relative_lvlh`).
* :class:`RigidBodyAttitude`, :func:`principal_axes`, :func:`spin_with_nutation`,
  :class:`TargetAttitudeModel`: torque-free target attitude.
* :func:`mass_flow_rate`, :func:`propellant_used`, :func:`saturate_thrust`, :class:`ChaserMass`:
  chaser propellant bookkeeping.
"""

from __future__ import annotations

import math
from typing import Literal

import numpy as np
import numpy.typing as npt
from scipy.integrate import solve_ivp
from scipy.spatial.transform import Rotation

from perception.geometry import fast_quat_to_matrix, rotation_z

__all__ = [
    "G0",
    "J2_EARTH",
    "MU_EARTH",
    "R_EARTH",
    "CWPropagator",
    "ChaserMass",
    "NonlinearRelativePropagator",
    "RigidBodyAttitude",
    "TargetAttitudeModel",
    "circular_orbit_state",
    "cw_stm",
    "eci_from_relative_lvlh",
    "gravity_acceleration",
    "lvlh_frame",
    "mass_flow_rate",
    "mean_motion",
    "principal_axes",
    "propellant_used",
    "relative_lvlh_from_eci",
    "saturate_thrust",
    "spin_with_nutation",
]

FloatArray = npt.NDArray[np.float64]

MU_EARTH = 3.986004418e14
"""Earth's gravitational parameter [m^3/s^2] (WGS-84 / EGM)."""
R_EARTH = 6378137.0
"""Earth's equatorial radius [m] (WGS-84)."""
J2_EARTH = 1.08262668e-3
"""Earth's second zonal harmonic [-] (EGM-96, unnormalised)."""
G0 = 9.80665
"""Standard gravity [m/s^2], the Isp reference."""

_DEFAULT_INCLINATION_RAD = float(np.deg2rad(51.6))

# Torque-free attitude integration: DOP853 at these tolerances keeps energy and momentum to
# ~1e-12 relative per 1,000 s at tumble rates of a few deg/s (the tests check 1e-9).
_ATT_RTOL = 1e-12
_ATT_ATOL = 1e-14
# Orbit integration: relative states are integrated directly (not as differences of two
# absolute states) so their absolute tolerance can sit far below the target's.
_ORB_RTOL = 1e-12
_ORB_ATOL_TARGET = (1e-6, 1e-9)  # [m], [m/s]
_ORB_ATOL_REL = (1e-9, 1e-12)  # [m], [m/s]


# --------------------------------------------------------------------------------------------
# validation helpers
# --------------------------------------------------------------------------------------------


def _finite_scalar(name: str, value: float) -> float:
    try:
        x = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name}={value!r} is not a real number") from None
    if not math.isfinite(x):
        raise ValueError(f"{name}={value!r} must be finite")
    return x


def _positive(name: str, value: float) -> float:
    x = _finite_scalar(name, value)
    if x <= 0.0:
        raise ValueError(f"{name}={value!r} must be > 0")
    return x


def _non_negative(name: str, value: float) -> float:
    x = _finite_scalar(name, value)
    if x < 0.0:
        raise ValueError(f"{name}={value!r} must be >= 0")
    return x


def _array(name: str, value: npt.ArrayLike, last: int, batch: bool) -> FloatArray:
    """Return ``value`` as float64 with trailing dimension ``last``; (last,) or (B, last)."""
    arr = np.asarray(value, dtype=np.float64)
    shape = arr.shape
    ok_shape = shape == (last,) or (batch and len(shape) == 2 and shape[1] == last)
    if not ok_shape:
        want = f"({last},)" + (f" or (B, {last})" if batch else "")
        raise ValueError(f"{name} has shape {arr.shape}; expected {want}")
    if not np.isfinite(arr).all():
        raise ValueError(f"{name}={arr!r} contains non-finite values")
    return arr


def _inertia(name: str, value: npt.ArrayLike) -> FloatArray:
    """Validate a body inertia tensor: finite, symmetric, positive definite, triangle inequality."""
    inertia = np.asarray(value, dtype=np.float64)
    if inertia.shape != (3, 3):
        raise ValueError(f"{name} has shape {inertia.shape}; expected (3, 3)")
    if not np.all(np.isfinite(inertia)):
        raise ValueError(f"{name}={inertia.tolist()} contains non-finite values")
    scale = float(np.max(np.abs(inertia)))
    if not np.allclose(inertia, inertia.T, rtol=0.0, atol=1e-9 * scale):
        raise ValueError(f"{name}={inertia.tolist()} is not symmetric")
    inertia = 0.5 * (inertia + inertia.T)
    moments = np.linalg.eigvalsh(inertia)
    if moments[0] <= 0.0:
        raise ValueError(
            f"{name}={inertia.tolist()} is not positive definite (principal moments {moments})"
        )
    # A physical mass distribution has J1 + J2 >= J3 (equality for a flat plate).
    if moments[0] + moments[1] < moments[2] * (1.0 - 1e-9):
        raise ValueError(
            f"{name}={inertia.tolist()} violates the triangle inequality: principal moments "
            f"{moments} have {moments[0]:.6g} + {moments[1]:.6g} < {moments[2]:.6g}"
        )
    return inertia


def _quat_wxyz(name: str, value: npt.ArrayLike) -> FloatArray:
    q = _array(name, value, 4, batch=False)
    norm = float(np.linalg.norm(q))
    if abs(norm - 1.0) > 1e-6:
        raise ValueError(f"{name}={q.tolist()} has norm {norm:.9g}; expected a unit quaternion")
    return q / norm


def _rotation_from_wxyz(q_wxyz: FloatArray) -> Rotation:
    # Explicit reorder rather than ``scalar_first=`` (SciPy >= 1.14 only).
    return Rotation.from_quat(np.asarray(q_wxyz, dtype=np.float64)[..., [1, 2, 3, 0]])


def _wxyz(rotation: Rotation) -> FloatArray:
    """Scalar-first unit quaternion(s) with ``w >= 0``."""
    q = np.asarray(rotation.as_quat(), dtype=np.float64)[..., [3, 0, 1, 2]]
    return np.where(q[..., :1] < 0.0, -q, q)


# --------------------------------------------------------------------------------------------
# Clohessy-Wiltshire
# --------------------------------------------------------------------------------------------


def mean_motion(altitude_m: float, mu: float = MU_EARTH, r_earth: float = R_EARTH) -> float:
    """Mean motion of a circular orbit.

    Args:
        altitude_m: Orbit altitude above ``r_earth`` [m], >= 0.
        mu: Gravitational parameter [m^3/s^2].
        r_earth: Reference (equatorial) radius [m].

    Returns:
        Mean motion ``n = sqrt(mu / a^3)`` [rad/s] with ``a = r_earth + altitude_m``.

    Raises:
        ValueError: If an argument is non-finite or out of range.
    """
    h = _non_negative("altitude_m", altitude_m)
    mu = _positive("mu", mu)
    r_earth = _positive("r_earth", r_earth)
    a = r_earth + h
    return float(np.sqrt(mu / a**3))


def _one_minus_cos(theta: float) -> float:
    # 2 sin^2(theta/2) has no cancellation for small theta.
    return 2.0 * np.sin(0.5 * theta) ** 2


def _theta_minus_sin(theta: float) -> float:
    # theta - sin(theta) loses all digits for small theta; use its Taylor series there
    # (8 terms: truncation < theta^19 / 19!, below double precision for |theta| < 0.5).
    if abs(theta) < 0.5:
        t2 = theta * theta
        total = 0.0
        term = theta * t2 / 6.0  # theta^3 / 3!
        for k in range(8):
            total += term
            term *= -t2 / ((2 * k + 4) * (2 * k + 5))
        return total
    return theta - np.sin(theta)


def cw_stm(n: float, dt: float) -> tuple[FloatArray, FloatArray]:
    """Exact discrete CW dynamics with a zero-order-hold acceleration.

    ``x_{k+1} = Phi @ x_k + Gamma @ a`` for ``x = [x, y, z, vx, vy, vz]`` in LVLH and ``a``
    the LVLH acceleration held constant over ``dt``. ``Gamma = int_0^dt Phi(dt - s) B ds`` with
    ``B = [0; I]``, evaluated in closed form. With ``theta = n dt``, ``s = sin theta``,
    ``c = cos theta``::

        Phi = [[4-3c,       0, 0,    s/n,       2(1-c)/n,     0  ],
               [6(s-theta), 1, 0,   -2(1-c)/n,  (4s-3theta)/n, 0  ],
               [0,          0, c,    0,         0,            s/n],
               [3n s,       0, 0,    c,         2s,           0  ],
               [-6n(1-c),   0, 0,   -2s,        4c-3,         0  ],
               [0,          0, -n s, 0,         0,            c  ]]

        Gamma = [[(1-c)/n^2,        2(theta-s)/n^2,            0        ],
                 [-2(theta-s)/n^2,  4(1-c)/n^2 - 3 dt^2 / 2,   0        ],
                 [0,                0,                         (1-c)/n^2],
                 [s/n,              2(1-c)/n,                  0        ],
                 [-2(1-c)/n,        4s/n - 3 dt,               0        ],
                 [0,                0,                         s/n      ]]

    Args:
        n: Mean motion of the target's circular orbit [rad/s], > 0.
        dt: Step [s], >= 0.

    Returns:
        ``(Phi, Gamma)``: ``(6, 6)`` and ``(6, 3)`` float64 ([s] and [s^2]-scaled entries).

    Raises:
        ValueError: If ``n`` is not positive or ``dt`` is negative or non-finite.
    """
    n = _positive("n", n)
    dt = _non_negative("dt", dt)
    th = n * dt
    s, c = float(np.sin(th)), float(np.cos(th))
    omc = _one_minus_cos(th)
    tms = _theta_minus_sin(th)

    phi = np.array(
        [
            [4.0 - 3.0 * c, 0.0, 0.0, s / n, 2.0 * omc / n, 0.0],
            [-6.0 * tms, 1.0, 0.0, -2.0 * omc / n, (4.0 * s - 3.0 * th) / n, 0.0],
            [0.0, 0.0, c, 0.0, 0.0, s / n],
            [3.0 * n * s, 0.0, 0.0, c, 2.0 * s, 0.0],
            [-6.0 * n * omc, 0.0, 0.0, -2.0 * s, 4.0 * c - 3.0, 0.0],
            [0.0, 0.0, -n * s, 0.0, 0.0, c],
        ]
    )
    n2 = n * n
    gamma = np.array(
        [
            [omc / n2, 2.0 * tms / n2, 0.0],
            [-2.0 * tms / n2, 4.0 * omc / n2 - 1.5 * dt * dt, 0.0],
            [0.0, 0.0, omc / n2],
            [s / n, 2.0 * omc / n, 0.0],
            [-2.0 * omc / n, 4.0 * s / n - 3.0 * dt, 0.0],
            [0.0, 0.0, s / n],
        ]
    )
    return phi, gamma


class CWPropagator:
    """Clohessy-Wiltshire relative motion with a cached exact discrete model.

    Args:
        n: Mean motion [rad/s], > 0 (see :func:`mean_motion`).
        dt: Step [s], > 0.

    Example:
        >>> prop = CWPropagator(mean_motion(400e3), dt=1.0)
        >>> state = prop.step(np.array([0.0, -100.0, 0.0, 0.0, 0.0, 0.0]), np.zeros(3))
        >>> bool(np.allclose(state, [0.0, -100.0, 0.0, 0.0, 0.0, 0.0]))
        True
    """

    def __init__(self, n: float, dt: float) -> None:
        self.n = _positive("n", n)
        self.dt = _positive("dt", dt)
        self.phi, self.gamma = cw_stm(self.n, self.dt)
        self.phi.setflags(write=False)
        self.gamma.setflags(write=False)

    def step(self, state: npt.ArrayLike, accel: npt.ArrayLike | None = None) -> FloatArray:
        """Advance one step.

        Args:
            state: ``(6,)`` or ``(B, 6)`` LVLH relative state [m, m/s].
            accel: ``(3,)`` or ``(B, 3)`` LVLH thrust acceleration [m/s^2] held over the step;
                ``None`` for coasting.

        Returns:
            The state after ``dt``, same shape as ``state``.

        Raises:
            ValueError: On bad shapes or non-finite values.
        """
        x = _array("state", state, 6, batch=True)
        out = x @ self.phi.T
        if accel is not None:
            a = _array("accel", accel, 3, batch=True)
            if a.ndim == 2 and (x.ndim == 1 or a.shape[0] != x.shape[0]):
                raise ValueError(f"accel has shape {a.shape}; state has shape {x.shape}")
            out = out + a @ self.gamma.T
        return out

    def step_batch(self, states: npt.ArrayLike, accels: npt.ArrayLike | None = None) -> FloatArray:
        """Advance ``B`` independent chasers one step: ``(B, 6), (B, 3) | (3,) -> (B, 6)``."""
        x = _array("states", states, 6, batch=True)
        if x.ndim != 2:
            raise ValueError(f"states has shape {x.shape}; expected (B, 6)")
        return self.step(x, accels)


# --------------------------------------------------------------------------------------------
# nonlinear relative motion
# --------------------------------------------------------------------------------------------


def gravity_acceleration(
    r_eci: npt.ArrayLike,
    mu: float = MU_EARTH,
    j2: float = 0.0,
    r_earth: float = R_EARTH,
) -> FloatArray:
    """Point-mass gravity plus the J2 zonal term.

    Args:
        r_eci: ``(..., 3)`` position(s) in ECI [m] (z along the Earth's pole).
        mu: Gravitational parameter [m^3/s^2].
        j2: Second zonal harmonic [-]; 0 for two-body motion, :data:`J2_EARTH` for Earth.
        r_earth: Equatorial radius used with ``j2`` [m].

    Returns:
        ``(..., 3)`` acceleration [m/s^2].
    """
    r = np.asarray(r_eci, dtype=np.float64)
    r2 = np.sum(r * r, axis=-1, keepdims=True)
    rn = np.sqrt(r2)
    acc = -mu * r / (r2 * rn)
    if j2 != 0.0:
        z2_r2 = r[..., 2:3] ** 2 / r2
        k = -1.5 * j2 * mu * r_earth**2 / (r2 * r2 * rn)
        factor = np.concatenate([1.0 - 5.0 * z2_r2, 1.0 - 5.0 * z2_r2, 3.0 - 5.0 * z2_r2], axis=-1)
        acc = acc + k * r * factor
    return acc


def lvlh_frame(
    r_eci: npt.ArrayLike, v_eci: npt.ArrayLike, a_eci: npt.ArrayLike | None = None
) -> tuple[FloatArray, FloatArray]:
    """LVLH axes of an orbiting body and the angular velocity of the LVLH frame.

    Args:
        r_eci: ``(3,)`` target position [m].
        v_eci: ``(3,)`` target velocity [m/s].
        a_eci: ``(3,)`` target total acceleration [m/s^2]; only its orbit-normal component
            matters (it tilts the orbit plane). ``None`` for Keplerian motion.

    Returns:
        ``(R_eci_lvlh, omega_lvlh)``: ``(3, 3)`` rotation whose columns are the LVLH axes in
        ECI (maps LVLH coordinates to ECI), and ``(3,)`` angular velocity of LVLH relative to
        ECI expressed in LVLH [rad/s]: ``[r a_z / |h|, 0, |h| / r^2]``.
    """
    r = np.asarray(r_eci, dtype=np.float64)
    v = np.asarray(v_eci, dtype=np.float64)
    h = np.cross(r, v)
    rn = float(np.linalg.norm(r))
    hn = float(np.linalg.norm(h))
    if rn == 0.0 or hn == 0.0:
        raise ValueError(f"r_eci={r.tolist()}, v_eci={v.tolist()} do not define an orbit plane")
    x = r / rn
    z = h / hn
    y = np.cross(z, x)
    rot = np.column_stack([x, y, z])
    a_normal = 0.0 if a_eci is None else float(np.dot(np.asarray(a_eci, dtype=np.float64), z))
    omega = np.array([rn * a_normal / hn, 0.0, hn / rn**2])
    return rot, omega


def relative_lvlh_from_eci(
    target_eci: npt.ArrayLike,
    chaser_eci: npt.ArrayLike,
    target_accel_eci: npt.ArrayLike | None = None,
) -> FloatArray:
    """Chaser state relative to the target, in the target's rotating LVLH frame.

    ``rho = R^T (r_c - r_t)``, ``rho_dot = R^T (v_c - v_t) - omega x rho``.

    Args:
        target_eci: ``(6,)`` target position and velocity in ECI [m, m/s].
        chaser_eci: ``(6,)`` or ``(B, 6)`` chaser position and velocity in ECI [m, m/s].
        target_accel_eci: ``(3,)`` target acceleration [m/s^2] (see :func:`lvlh_frame`).

    Returns:
        Relative LVLH state(s), same shape as ``chaser_eci``.
    """
    t = np.asarray(target_eci, dtype=np.float64)
    c = np.asarray(chaser_eci, dtype=np.float64)
    rot, omega = lvlh_frame(t[:3], t[3:], target_accel_eci)
    rho = (c[..., :3] - t[:3]) @ rot
    rho_dot = (c[..., 3:] - t[3:]) @ rot - np.cross(omega, rho)
    return np.concatenate([rho, rho_dot], axis=-1)


def eci_from_relative_lvlh(
    target_eci: npt.ArrayLike,
    relative_lvlh: npt.ArrayLike,
    target_accel_eci: npt.ArrayLike | None = None,
) -> FloatArray:
    """Inverse of :func:`relative_lvlh_from_eci`: chaser ECI state(s) ``(6,)`` or ``(B, 6)``."""
    t = np.asarray(target_eci, dtype=np.float64)
    x = np.asarray(relative_lvlh, dtype=np.float64)
    rot, omega = lvlh_frame(t[:3], t[3:], target_accel_eci)
    rho, rho_dot = x[..., :3], x[..., 3:]
    r_c = t[:3] + rho @ rot.T
    v_c = t[3:] + (rho_dot + np.cross(omega, rho)) @ rot.T
    return np.concatenate([r_c, v_c], axis=-1)


def circular_orbit_state(
    altitude_m: float,
    inclination_rad: float = _DEFAULT_INCLINATION_RAD,
    raan_rad: float = 0.0,
    arg_latitude_rad: float = 0.0,
    mu: float = MU_EARTH,
    r_earth: float = R_EARTH,
) -> FloatArray:
    """ECI state ``(6,)`` [m, m/s] on a circular orbit (prograde for inclination < pi/2)."""
    h = _non_negative("altitude_m", altitude_m)
    inc = _finite_scalar("inclination_rad", inclination_rad)
    if not 0.0 <= inc <= np.pi:
        raise ValueError(f"inclination_rad={inclination_rad!r} must be in [0, pi]")
    raan = _finite_scalar("raan_rad", raan_rad)
    u = _finite_scalar("arg_latitude_rad", arg_latitude_rad)
    a = _positive("r_earth", r_earth) + h
    speed = np.sqrt(_positive("mu", mu) / a)
    to_eci = Rotation.from_euler("ZX", [raan, inc])  # perifocal (node-aligned) -> ECI
    r = to_eci.apply([a * np.cos(u), a * np.sin(u), 0.0])
    v = to_eci.apply([-speed * np.sin(u), speed * np.cos(u), 0.0])
    return np.concatenate([r, v])


class NonlinearRelativePropagator:
    """Relative motion from both spacecraft's absolute orbits (two-body, optionally + J2).

    The target's absolute ECI state is kept inside and advanced with every :meth:`step`. The
    chaser's LVLH state is converted to ECI exactly, both bodies are integrated together with
    ``solve_ivp`` (DOP853, rtol 1e-12) and the result is converted back to the target's LVLH
    frame at the end of the step. The relative position and velocity are integrated directly
    (``rho'' = g(r_t + rho) - g(r_t) + a_thrust``) to keep millimetre-level relative accuracy
    on top of a 7,000-km orbit. The thrust acceleration is constant in the rotating LVLH frame
    over the step (the CW zero-order-hold convention), rotated to ECI along the way.

    With ``j2=True`` the target starts with circular-orbit velocity but its orbit is then
    perturbed (not circular); the LVLH frame follows the actual target state.

    Args:
        altitude_m: Target circular-orbit altitude [m].
        inclination_rad: Target orbit inclination [rad] (default 51.6 deg, ISS).
        j2: Include Earth's J2 on both spacecraft.
        dt: Step [s], > 0.
        raan_rad: Right ascension of the ascending node [rad].
        arg_latitude_rad: Initial argument of latitude [rad].
        mu: Gravitational parameter [m^3/s^2].
        r_earth: Equatorial radius [m].

    Example:
        >>> prop = NonlinearRelativePropagator(400e3, j2=False, dt=10.0)
        >>> state = prop.step(np.array([0.0, -50.0, 0.0, 0.0, 0.0, 0.0]), np.zeros(3))
        >>> bool(np.allclose(state, [0.0, -50.0, 0.0, 0.0, 0.0, 0.0], atol=1e-6))
        True
    """

    def __init__(
        self,
        altitude_m: float,
        inclination_rad: float = _DEFAULT_INCLINATION_RAD,
        j2: bool = False,
        dt: float = 1.0,
        *,
        raan_rad: float = 0.0,
        arg_latitude_rad: float = 0.0,
        mu: float = MU_EARTH,
        r_earth: float = R_EARTH,
    ) -> None:
        self.altitude_m = _non_negative("altitude_m", altitude_m)
        self.inclination_rad = _finite_scalar("inclination_rad", inclination_rad)
        self.dt = _positive("dt", dt)
        self.mu = _positive("mu", mu)
        self.r_earth = _positive("r_earth", r_earth)
        self.j2 = J2_EARTH if j2 else 0.0
        self.n = mean_motion(self.altitude_m, self.mu, self.r_earth)
        self._initial = circular_orbit_state(
            self.altitude_m,
            self.inclination_rad,
            raan_rad,
            arg_latitude_rad,
            self.mu,
            self.r_earth,
        )
        self._target = self._initial.copy()
        self.t = 0.0

    def reset(self, target_state_eci: npt.ArrayLike | None = None, t0: float = 0.0) -> None:
        """Restart the target's orbit.

        Args:
            target_state_eci: ``(6,)`` target ECI state at ``t0`` [m, m/s]; ``None`` for the
                configured circular orbit.
            t0: Epoch [s].
        """
        if target_state_eci is None:
            self._target = self._initial.copy()
        else:
            self._target = _array("target_state_eci", target_state_eci, 6, batch=False).copy()
            lvlh_frame(self._target[:3], self._target[3:])  # rejects degenerate states
        self.t = _finite_scalar("t0", t0)

    @property
    def target_state_eci(self) -> FloatArray:
        """``(6,)`` current target ECI state [m, m/s] (a copy)."""
        return self._target.copy()

    def _gravity(self, r: FloatArray) -> FloatArray:
        return gravity_acceleration(r, self.mu, self.j2, self.r_earth)

    def _target_frame(self) -> tuple[FloatArray, FloatArray]:
        r, v = self._target[:3], self._target[3:]
        return lvlh_frame(r, v, self._gravity(r))

    def lvlh_to_eci(self, state: npt.ArrayLike) -> FloatArray:
        """Chaser ECI state(s) from LVLH relative state(s) ``(6,)``/``(B, 6)`` at time ``t``."""
        x = _array("state", state, 6, batch=True)
        return eci_from_relative_lvlh(self._target, x, self._gravity(self._target[:3]))

    def eci_to_lvlh(self, chaser_state_eci: npt.ArrayLike) -> FloatArray:
        """LVLH relative state(s) from chaser ECI state(s) ``(6,)``/``(B, 6)`` at time ``t``."""
        x = _array("chaser_state_eci", chaser_state_eci, 6, batch=True)
        return relative_lvlh_from_eci(self._target, x, self._gravity(self._target[:3]))

    def step(self, state: npt.ArrayLike, accel: npt.ArrayLike | None = None) -> FloatArray:
        """Advance target and chaser(s) by ``dt``.

        Args:
            state: ``(6,)`` or ``(B, 6)`` chaser LVLH relative state(s) at time ``t`` [m, m/s].
            accel: ``(3,)`` or ``(B, 3)`` LVLH thrust acceleration [m/s^2]; ``None`` to coast.

        Returns:
            Relative LVLH state(s) at ``t + dt`` in the new target LVLH frame.

        Raises:
            ValueError: On bad shapes or non-finite values.
            RuntimeError: If the integrator fails.
        """
        x = _array("state", state, 6, batch=True)
        single = x.ndim == 1
        xb = np.atleast_2d(x)
        nb = xb.shape[0]
        if accel is None:
            a_lvlh = np.zeros((nb, 3))
        else:
            a = _array("accel", accel, 3, batch=True)
            if a.ndim == 2 and a.shape[0] != nb:
                raise ValueError(f"accel has shape {a.shape}; state has shape {x.shape}")
            a_lvlh = np.broadcast_to(a, (nb, 3))

        rot, omega = self._target_frame()
        rho = xb[:, :3] @ rot.T
        rho_dot = (xb[:, 3:] + np.cross(omega, xb[:, :3])) @ rot.T
        y0 = np.concatenate([self._target, rho.ravel(), rho_dot.ravel()])

        def rhs(_t: float, y: FloatArray) -> FloatArray:
            r_t, v_t = y[:3], y[3:6]
            rho_ = y[6 : 6 + 3 * nb].reshape(nb, 3)
            g_t = self._gravity(r_t)
            rot_t, _ = lvlh_frame(r_t, v_t)
            acc_rel = self._gravity(r_t + rho_) - g_t + a_lvlh @ rot_t.T
            return np.concatenate([v_t, g_t, y[6 + 3 * nb :], acc_rel.ravel()])

        atol = np.concatenate(
            [
                np.repeat(_ORB_ATOL_TARGET, 3),
                np.full(3 * nb, _ORB_ATOL_REL[0]),
                np.full(3 * nb, _ORB_ATOL_REL[1]),
            ]
        )
        sol = solve_ivp(rhs, (0.0, self.dt), y0, method="DOP853", rtol=_ORB_RTOL, atol=atol)
        if not sol.success:
            raise RuntimeError(f"orbit integration failed over dt={self.dt}: {sol.message}")
        y1 = sol.y[:, -1]
        self._target = y1[:6].copy()
        self.t += self.dt

        rot1, omega1 = self._target_frame()
        rho1 = y1[6 : 6 + 3 * nb].reshape(nb, 3) @ rot1
        rho_dot1 = y1[6 + 3 * nb :].reshape(nb, 3) @ rot1 - np.cross(omega1, rho1)
        out = np.concatenate([rho1, rho_dot1], axis=1)
        return out[0] if single else out


# --------------------------------------------------------------------------------------------
# attitude
# --------------------------------------------------------------------------------------------


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


# --------------------------------------------------------------------------------------------
# chaser propellant
# --------------------------------------------------------------------------------------------


def _thrust_magnitude(thrust: FloatArray, norm: Literal["l2", "l1"]) -> FloatArray:
    if norm == "l2":
        return np.linalg.norm(thrust, axis=-1)
    if norm == "l1":
        return np.sum(np.abs(thrust), axis=-1)
    raise ValueError(f"norm={norm!r} must be 'l2' or 'l1'")


def mass_flow_rate(
    thrust_N: npt.ArrayLike, isp: float, norm: Literal["l2", "l1"] = "l2"
) -> float | FloatArray:
    """Propellant mass flow ``|thrust| / (isp g0)`` [kg/s].

    Args:
        thrust_N: ``(3,)`` or ``(B, 3)`` thrust [N].
        isp: Specific impulse [s], > 0.
        norm: ``"l2"`` for one gimballed engine, ``"l1"`` for one thruster pair per axis.

    Returns:
        Mass flow [kg/s], a float or ``(B,)``.
    """
    thrust = _array("thrust_N", thrust_N, 3, batch=True)
    isp = _positive("isp", isp)
    flow = _thrust_magnitude(thrust, norm) / (isp * G0)
    return float(flow) if flow.ndim == 0 else flow


def propellant_used(
    thrust_N: npt.ArrayLike, dt: float, isp: float, norm: Literal["l2", "l1"] = "l2"
) -> float | FloatArray:
    """Propellant burnt holding ``thrust_N`` for ``dt`` [kg] (see :func:`mass_flow_rate`)."""
    dt = _non_negative("dt", dt)
    return mass_flow_rate(thrust_N, isp, norm) * dt


def saturate_thrust(thrust_N: npt.ArrayLike, max_thrust_N: npt.ArrayLike) -> FloatArray:
    """Clip each thrust axis to ``[-max, max]``.

    Args:
        thrust_N: ``(3,)`` or ``(B, 3)`` commanded thrust [N].
        max_thrust_N: Scalar or ``(3,)`` per-axis limit [N], >= 0.

    Returns:
        Saturated thrust, same shape as ``thrust_N``.
    """
    thrust = _array("thrust_N", thrust_N, 3, batch=True)
    limit = np.asarray(max_thrust_N, dtype=np.float64)
    if limit.shape not in ((), (3,)) or not np.all(np.isfinite(limit)) or np.any(limit < 0.0):
        raise ValueError(
            f"max_thrust_N={limit.tolist()} must be a finite scalar or (3,) array >= 0"
        )
    return np.clip(thrust, -limit, limit)


class ChaserMass:
    """Chaser mass bookkeeping: saturation, propellant use, thrust to acceleration.

    Args:
        dry_mass_kg: Mass without propellant [kg], > 0.
        propellant_kg: Initial propellant [kg], >= 0.
        isp: Specific impulse [s], > 0.
        max_thrust_N: Scalar or ``(3,)`` per-axis thrust limit [N].
        norm: How thrust maps to mass flow (see :func:`mass_flow_rate`).
    """

    def __init__(
        self,
        dry_mass_kg: float,
        propellant_kg: float,
        isp: float,
        max_thrust_N: npt.ArrayLike,
        norm: Literal["l2", "l1"] = "l2",
    ) -> None:
        self.dry_mass_kg = _positive("dry_mass_kg", dry_mass_kg)
        self.propellant_kg = _non_negative("propellant_kg", propellant_kg)
        self.isp = _positive("isp", isp)
        saturate_thrust(np.zeros(3), max_thrust_N)  # validates the limit
        self.max_thrust_N = np.asarray(max_thrust_N, dtype=np.float64)
        _thrust_magnitude(np.zeros(3), norm)
        self.norm: Literal["l2", "l1"] = norm
        # apply() runs every step: the limits and the flow constant are validated once, here.
        self._lo, self._hi = -self.max_thrust_N, self.max_thrust_N
        self._isp_g0 = self.isp * G0

    @property
    def mass_kg(self) -> float:
        """Current total mass [kg]."""
        return self.dry_mass_kg + self.propellant_kg

    def apply(self, thrust_N: npt.ArrayLike, dt: float) -> tuple[FloatArray, FloatArray]:
        """Saturate a command, burn propellant for ``dt`` and return the acceleration.

        If the tank cannot feed the whole step the thrust is scaled down so that the step
        burns exactly what is left. The acceleration uses the mass at the start of the step
        (the relative change over a step is ``mdot dt / m``, ~1e-5 for typical values).

        Args:
            thrust_N: ``(3,)`` commanded thrust in LVLH [N].
            dt: Step [s], >= 0.

        Returns:
            ``(accel, thrust)``: ``(3,)`` acceleration [m/s^2] and ``(3,)`` applied thrust [N].
        """
        # saturate_thrust + propellant_used, with the limit and isp validated at construction.
        thrust = np.minimum(np.maximum(_array("thrust_N", thrust_N, 3, batch=False), self._lo), self._hi)
        dt = _non_negative("dt", dt)
        t0, t1, t2 = thrust.tolist()
        if self.norm == "l2":
            magnitude = math.sqrt(t0 * t0 + t1 * t1 + t2 * t2)
        else:
            magnitude = abs(t0) + abs(t1) + abs(t2)
        need = magnitude / self._isp_g0 * dt
        if need > self.propellant_kg:
            thrust = thrust * (self.propellant_kg / need)
            need = self.propellant_kg
        accel = thrust / self.mass_kg
        self.propellant_kg = max(self.propellant_kg - need, 0.0)
        return accel, thrust
