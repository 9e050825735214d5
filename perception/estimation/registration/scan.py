"""The scan side of ICP: checking the points, their range noise and their ray directions, and
keeping the rows on which all three are finite."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]


def validate_points(points: npt.ArrayLike, name: str = "points") -> FloatArray:
    """Return ``points`` as a (N, 3) float64 array or raise ``ValueError`` naming ``name``.

    Non-finite rows are kept (callers drop them and count what is left).
    """
    try:
        P = np.asarray(points, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name} could not be read as a float array: {exc}") from None
    if P.ndim == 1 and P.size == 0:
        P = P.reshape(0, 3)
    if P.ndim != 2 or P.shape[1] != 3:
        raise ValueError(f"{name} has shape {P.shape}; expected (N, 3) [m]")
    return P


def per_point_sigma(sigma: float | npt.ArrayLike | None, n: int) -> FloatArray:
    """(n,) range-noise sigmas [m] from None (1 cm), a float or an (n,) array; ValueError if bad."""
    if sigma is None:
        return np.full(n, 0.01)
    try:
        s = np.asarray(sigma, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"sigma={sigma!r}; expected a float or (N,) array [m]") from None
    if s.ndim == 0:
        if not (np.isfinite(s) and s > 0):
            raise ValueError(f"sigma={float(s)}; expected a finite range noise > 0 [m]")
        return np.full(n, float(s))
    s = s.reshape(-1)
    if s.shape[0] != n:
        raise ValueError(f"sigma has {s.shape[0]} values for {n} points; expected a float or (N,)")
    if np.any(s[np.isfinite(s)] <= 0):
        raise ValueError("sigma has values <= 0; expected per-point range noise > 0 [m]")
    return s


def ray_directions(directions: npt.ArrayLike | None, P: FloatArray) -> FloatArray:
    """(N, 3) unit ray directions: ``directions`` normalised, or ``P / |P|`` (rays from the sensor
    origin) when None; ValueError if the shape differs from ``P``'s."""
    if directions is None:
        r = np.linalg.norm(P, axis=1, keepdims=True)
        with np.errstate(invalid="ignore", divide="ignore"):
            return P / r
    D = np.asarray(directions, dtype=np.float64)
    if D.shape != P.shape:
        raise ValueError(f"directions has shape {D.shape}; expected {P.shape} like points")
    n = np.linalg.norm(D, axis=1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        return D / n


def usable_scan(
    points: npt.ArrayLike,
    sigma: float | npt.ArrayLike | None,
    directions: npt.ArrayLike | None,
) -> tuple[FloatArray, FloatArray, FloatArray, int]:
    """The scan rows whose point, sigma and ray direction are all finite.

    Returns:
        (K, 3) points [m], (K,) range sigmas [m], (K, 3) unit ray directions (sensor frame), and
        the number of rows given.

    Raises:
        ValueError: as :func:`validate_points`, :func:`per_point_sigma`, :func:`ray_directions`.
    """
    P_all = validate_points(points, "points")
    sig_all = per_point_sigma(sigma, P_all.shape[0])
    D_all = ray_directions(directions, P_all)
    ok = (
        np.all(np.isfinite(P_all), axis=1)
        & np.all(np.isfinite(D_all), axis=1)
        & np.isfinite(sig_all)
    )
    P = np.ascontiguousarray(P_all[ok])
    sig = sig_all[ok]
    D = D_all[ok]
    return P, sig, D, P_all.shape[0]
