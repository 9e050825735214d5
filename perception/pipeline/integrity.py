"""Integrity of a published pose: protection level, alert limit and the degraded flag.

A navigation sensor is judged by whether it knows when it is wrong (DESIGN.md, "Integrity"). The
state vector therefore carries, with every pose, a **protection level** (PL): a bound on the error
of the docking port's position that holds with probability ``1 - risk`` if the published
covariance is right. For a Gaussian error ``e ~ N(0, P)`` in 3-D, ``e^T P^-1 e`` is chi-square
with 3 degrees of freedom, and ``|e|^2 <= lambda_max(P) e^T P^-1 e``, so

    PL = sqrt(lambda_max(P_port) * chi2_3.isf(risk))

bounds ``|e|`` at that risk whatever the shape of the error ellipsoid (a flat face seen head-on
gives one long in-plane axis: the PL is then set by it). The **alert limit** (AL) is the error the
mission can tolerate at the current range: ``alert_limit_m`` inside ``alert_limit_range_m`` of the
port, growing in proportion to the range beyond it. A pose whose PL exceeds the AL is published
**degraded**: its numbers and covariance are still there (a controller may use them to back away),
but it is not valid for closing in.
"""

from __future__ import annotations

import functools
import math

import numpy as np
import numpy.typing as npt
from scipy.stats import chi2

from perception.geometry import skew

FloatArray = npt.NDArray[np.float64]

__all__ = ["alert_limit", "integrity_factor", "port_covariance", "protection_level", "turn_about"]


@functools.lru_cache(maxsize=16)
def integrity_factor(risk: float, dof: int = 3) -> float:
    """``sqrt(chi2_dof.isf(risk))``: protection level per unit of the largest 1-sigma axis.

    Args:
        risk: probability that the error exceeds the protection level (0 < risk < 1).
        dof: dimension of the error (3 for a position).
    """
    if not (0.0 < risk < 1.0):
        raise ValueError(f"risk={risk}; expected a probability in (0, 1)")
    return math.sqrt(float(chi2.isf(risk, dof)))


def port_covariance(
    cov12: npt.ArrayLike, R_sensor_target: npt.ArrayLike, r_port_target: npt.ArrayLike
) -> FloatArray:
    """(3, 3) covariance [m^2] of the port position from a state covariance about the target origin.

    Args:
        cov12: (12, 12) covariance over ``[position, velocity, attitude, angular velocity]`` (the
            :class:`~perception.pipeline.state.StateVector` layout; attitude a left perturbation about the
            sensor axes).
        R_sensor_target: (3, 3) estimated attitude.
        r_port_target: (3,) port position in the target frame [m].

    The port sits at ``p + R r``; a left rotation ``theta`` moves it by ``theta x (R r)``, so
    ``d_port = dp - [R r]x theta``.
    """
    P = np.asarray(cov12, dtype=np.float64)
    a = np.asarray(R_sensor_target, dtype=np.float64) @ np.asarray(r_port_target, dtype=np.float64)
    A = -skew(a)
    C = P[0:3, 0:3] + A @ P[6:9, 0:3] + P[0:3, 6:9] @ A.T + A @ P[6:9, 6:9] @ A.T
    return 0.5 * (C + C.T)


def turn_about(
    cov12: npt.ArrayLike, R_sensor_target: npt.ArrayLike, r_point_target: npt.ArrayLike,
    variance: float,
) -> FloatArray:
    """``cov12`` plus an isotropic attitude error of ``variance`` [rad^2] that turns the target
    about a body point (the port) rather than about its origin.

    The origin moves with such a turn (``dp = [R r]x theta``), the point does not: the result's
    :func:`port_covariance` at ``r_point_target`` equals the input's.

    Args:
        cov12: (12, 12) covariance, layout as :func:`port_covariance`.
        R_sensor_target: (3, 3) estimated attitude.
        r_point_target: (3,) the pivot in the target frame [m].
        variance: added attitude variance per axis [rad^2] (>= 0).
    """
    P = np.array(cov12, dtype=np.float64)
    S = skew(np.asarray(R_sensor_target, dtype=np.float64) @ np.asarray(r_point_target, dtype=np.float64))
    v = float(variance)
    P[0:3, 0:3] += v * (S @ S.T)
    P[0:3, 6:9] += v * S
    P[6:9, 0:3] += v * S.T
    P[6:9, 6:9] += v * np.eye(3)
    return P


def protection_level(cov3: npt.ArrayLike, factor: float) -> float:
    """Protection level [m]: ``factor * sqrt(lambda_max(cov3))`` (see the module docstring)."""
    C = np.asarray(cov3, dtype=np.float64)
    lam = float(np.linalg.eigvalsh(0.5 * (C + C.T))[-1])
    return factor * math.sqrt(max(lam, 0.0))


def alert_limit(range_m: float, limit_m: float, limit_range_m: float) -> float:
    """Alert limit [m] at ``range_m`` from the port: ``limit_m`` inside ``limit_range_m``, then
    proportional to the range (the same angular accuracy further out)."""
    return float(limit_m) * max(1.0, float(range_m) / float(limit_range_m))
