"""Chaser mass: thrust saturation, propellant use and thrust-to-acceleration.

Thrusts are in LVLH [N], held over a step like the accelerations of :mod:`.orbit`.
"""

from __future__ import annotations

import math
from typing import Literal

import numpy as np
import numpy.typing as npt

from tridar_env.dynamics._checks import _array, _non_negative, _positive
from tridar_env.dynamics.constants import G0

__all__ = ["ChaserMass", "mass_flow_rate", "propellant_used", "saturate_thrust"]

FloatArray = npt.NDArray[np.float64]


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
