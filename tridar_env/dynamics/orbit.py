"""Relative orbital motion of the chaser about the target, in the target's LVLH frame.

Accelerations are chaser thrust accelerations in LVLH [m/s^2], held constant in LVLH over a step
(zero-order hold), the convention of the Clohessy-Wiltshire (CW) input matrix.

* :func:`mean_motion`, :func:`cw_stm`, :class:`CWPropagator`: CW with the exact closed-form
  state transition and zero-order-hold input matrix.
* :func:`gravity_acceleration`, :func:`circular_orbit_state`,
  :class:`NonlinearRelativePropagator`: both spacecraft under two-body gravity (+ optional J2)
  integrated in ECI, with the exact LVLH <-> ECI conversion of :mod:`.frames`.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt
from scipy.integrate import solve_ivp
from scipy.spatial.transform import Rotation

from tridar_env.dynamics._checks import _array, _finite_scalar, _non_negative, _positive
from tridar_env.dynamics.constants import J2_EARTH, MU_EARTH, R_EARTH
from tridar_env.dynamics.frames import eci_from_relative_lvlh, lvlh_frame, relative_lvlh_from_eci

__all__ = [
    "CWPropagator",
    "NonlinearRelativePropagator",
    "circular_orbit_state",
    "cw_stm",
    "gravity_acceleration",
    "mean_motion",
]

FloatArray = npt.NDArray[np.float64]

_DEFAULT_INCLINATION_RAD = float(np.deg2rad(51.6))

# Orbit integration: relative states are integrated directly (not as differences of two
# absolute states) so their absolute tolerance can sit far below the target's.
_ORB_RTOL = 1e-12
_ORB_ATOL_TARGET = (1e-6, 1e-9)  # [m], [m/s]
_ORB_ATOL_REL = (1e-9, 1e-12)  # [m], [m/s]


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


def cw_acceleration(n: float, r: npt.ArrayLike, v: npt.ArrayLike) -> FloatArray:
    """The CW model's natural acceleration at LVLH position ``r`` [m] and velocity ``v`` [m/s]:
    ``[3 n^2 x + 2 n y', -2 n x', -n^2 z]`` [m/s^2] (what a forced-motion law cancels)."""
    r = np.asarray(r, dtype=np.float64)
    v = np.asarray(v, dtype=np.float64)
    return np.array([3.0 * n * n * r[0] + 2.0 * n * v[1], -2.0 * n * v[0], -n * n * r[2]])


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
