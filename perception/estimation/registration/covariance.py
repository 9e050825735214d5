"""The pose covariance of a frame: the point-to-plane information matrix, its inverse with the
unobservable directions flagged (degenerate axes), and the change of pivot to the sensor origin.

The covariance is the inverse of the point-to-plane information matrix
``H = sum_i A_i^T A_i / var_i`` over the inliers at the final pose, where ``A_i`` is the residual's
Jacobian and ``var_i`` its noise variance from the sensor's range noise projected on the surface
normal. That is the Cramer-Rao bound of the frame: what the pose can be known to from this geometry
and this noise, whatever the solver. Directions in which ``H`` is (nearly) singular are reported in
``degenerate_axes`` rather than hidden.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from perception.estimation.registration.result import (
    AXIS_NAMES,
    FAILURE_VARIANCE,
    RegistrationResult,
)
from perception.estimation.registration.step import jacobian_rows
from perception.estimation.registration.weights import noise_variance
from perception.geometry import skew

FloatArray = npt.NDArray[np.float64]


def _residual_variance(
    sig: FloatArray,
    n_sensor: FloatArray,
    d_sensor: FloatArray,
    floor_fraction: float,
    model_sigma: float = 0.0,
) -> FloatArray:
    cos = np.einsum("ij,ij->i", n_sensor, d_sensor)
    return noise_variance(sig, cos, floor_fraction, model_sigma)


def information_rows(
    points_model_sensor: npt.ArrayLike,
    normals_sensor: npt.ArrayLike,
    sigma: float | npt.ArrayLike,
    directions: npt.ArrayLike,
    center: npt.ArrayLike,
    floor_fraction: float = 0.2,
    model_sigma_m: float = 0.0,
) -> FloatArray:
    """(K, 6) rows ``A_i / sqrt(var_i)`` whose ``rows^T rows`` is :func:`information_matrix`."""
    S = np.asarray(points_model_sensor, dtype=np.float64)
    Nn = np.asarray(normals_sensor, dtype=np.float64)
    D = np.asarray(directions, dtype=np.float64)
    c = np.asarray(center, dtype=np.float64).reshape(3)
    sig = np.broadcast_to(np.asarray(sigma, dtype=np.float64), (S.shape[0],))
    A = jacobian_rows(S - c, Nn)
    return A / np.sqrt(_residual_variance(sig, Nn, D, floor_fraction, model_sigma_m))[:, None]


def information_matrix(
    points_model_sensor: npt.ArrayLike,
    normals_sensor: npt.ArrayLike,
    sigma: float | npt.ArrayLike,
    directions: npt.ArrayLike,
    center: npt.ArrayLike,
    floor_fraction: float = 0.2,
    model_sigma_m: float = 0.0,
) -> FloatArray:
    """Point-to-plane Fisher information ``sum_i A_i^T A_i / var_i`` of a set of surface points.

    The twist is the one of :attr:`RegistrationResult.covariance`: a translation ``rho`` of the
    target origin and a rotation ``phi`` about it, both along sensor axes.
    ``A_i = [n_i, (s_i - c) x n_i]`` is the derivative of the point-to-plane residual with respect
    to it; the residual's noise variance is
    ``var_i = sigma_i^2 ((n_i . d_i)^2 + f^2) + sigma_model^2``: the range noise along the ray
    ``d_i`` projected on the normal, plus a floor ``f sigma_i`` so grazing points (where the
    projection vanishes but the beam footprint does not) are not given unbounded weight, plus the
    model's own resolution error (a match on a neighbouring facet of a discrete model).

    Args:
        points_model_sensor: (K, 3) matched model surface points [m], sensor frame.
        normals_sensor: (K, 3) unit normals, sensor frame.
        sigma: float or (K,) range noise 1-sigma [m].
        directions: (K, 3) unit ray directions, sensor frame.
        center: (3,) target origin in the sensor frame [m] (the pivot ``c``).
        floor_fraction: ``f`` above.
        model_sigma_m: ``sigma_model`` above [m].

    Returns:
        (6, 6) information matrix [1/m^2, 1/(m rad), 1/rad^2].
    """
    rows = information_rows(points_model_sensor, normals_sensor, sigma, directions, center,
                            floor_fraction, model_sigma_m)
    return rows.T @ rows


#: Components of an unobservable direction below this (unit eigenvector) are round-off mixing.
_MIX_TOL = 0.05


def covariance_from_information(
    H: npt.ArrayLike, length_scale_m: float, degeneracy_ratio: float = 1e-4,
    rows: npt.ArrayLike | None = None, min_support: float = 0.0,
) -> tuple[FloatArray, list[str]]:
    """Invert an information matrix, flagging and capping unobservable directions.

    Rotations are scaled by ``length_scale_m`` (a rotation ``phi`` moves the target's points by
    ~``L phi``) so translation and rotation information compare fairly. A direction (eigenvector
    of the scaled information) is unobservable when its eigenvalue is below ``degeneracy_ratio``
    times the largest, or, given the per-point ``rows``, when fewer than ``min_support`` points
    effectively carry it: with contributions ``c_i = w_i (A_i v)^2`` the effective count is
    ``(sum c)^2 / sum c^2``. Two grazing points that matched the side of an appendage do not
    observe a flat face's in-plane motion, however much weight the noise model gives them: a
    mis-association of a few points must not turn into a confident direction. Unobservable
    directions get :data:`FAILURE_VARIANCE` along themselves (not along the nearest axis, which
    would leave part of them overconfident), and the dominant component of each is named.

    Args:
        H: (6, 6) information matrix in the twist of :attr:`RegistrationResult.covariance`.
        length_scale_m: characteristic size of the target [m] (its radius).
        degeneracy_ratio: relative eigenvalue threshold.
        rows: (K, 6) per-point rows ``sqrt(w_i) A_i`` whose ``rows^T rows`` is ``H`` (optional).
        min_support: effective number of points a direction needs (with ``rows``).

    Returns:
        (6, 6) covariance and the list of degenerate axis names (ordered as :data:`AXIS_NAMES`).
    """
    H = np.asarray(H, dtype=np.float64)
    L = max(float(length_scale_m), 1e-6)
    sc = np.array([1.0, 1.0, 1.0, 1.0 / L, 1.0 / L, 1.0 / L])
    scale = np.multiply.outer(sc, sc)
    Hs = (0.5 * (H + H.T)) * scale
    if not np.isfinite(Hs).all():
        return FAILURE_VARIANCE * np.eye(6), list(AXIS_NAMES)
    lam, V = np.linalg.eigh(Hs)
    lam_max = float(lam[-1])
    if lam_max <= 0:
        return FAILURE_VARIANCE * np.eye(6), list(AXIS_NAMES)
    weak = lam < degeneracy_ratio * lam_max
    if rows is not None and min_support > 0:
        c = np.square(np.asarray(rows, dtype=np.float64) @ (sc[:, None] * V))  # (K, 6)
        tot = c.sum(axis=0)
        sq = np.einsum("ij,ij->j", c, c)
        n_eff = np.where(sq > 0, tot * tot / np.where(sq > 0, sq, 1.0), 0.0)
        weak |= n_eff < min_support
    inv = np.where(weak, 0.0, 1.0 / np.where(weak, 1.0, lam))
    Vs = sc[:, None] * V  # back to the unscaled twist
    cov = (Vs * inv) @ Vs.T
    names: set[str] = set()
    for k in np.flatnonzero(weak):
        names.add(AXIS_NAMES[int(np.argmax(np.abs(V[:, k])))])
        # Unknown along the direction itself (finite, so nothing downstream meets inf); its
        # small components (round-off mixing with well-observed axes, which a variance of 1e6
        # would turn into metres) are dropped.
        v = np.where(np.abs(V[:, k]) < _MIX_TOL, 0.0, V[:, k])
        u = sc * v
        cov += FAILURE_VARIANCE * np.outer(u, u) / float(u @ u)
    cov = 0.5 * (cov + cov.T)
    return cov, [a for a in AXIS_NAMES if a in names]


def covariance_about_sensor_origin(result: RegistrationResult) -> FloatArray:
    """The result's covariance re-expressed for ``T_true = se3_exp(xi) @ T_est`` (twist about the
    sensor origin): ``Ad cov Ad^T`` with ``Ad = [[I, t^], [0, I]]``, ``t`` the target position.

    At range its translation block is dominated by the rotation lever arm ``phi x t``; use the
    result's own covariance for the target position.
    """
    Ad = np.eye(6)
    Ad[:3, 3:] = skew(result.T_sensor_target[:3, 3])
    cov = Ad @ result.covariance @ Ad.T
    return 0.5 * (cov + cov.T)
