"""Argument checks shared by the dynamics modules.

Each raises ``ValueError`` naming the offending argument, so that a bad configuration value is
reported by its field name (the tests match on it).
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]


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
