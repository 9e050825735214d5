"""Small numeric helpers for the per-frame hot path (same values as numpy, less call overhead)."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

__all__ = ["median"]


def median(x: npt.NDArray[np.float64]) -> float:
    """``np.median`` of a non-empty 1-D array, bit for bit, without its per-call overhead.

    Raises:
        ValueError: ``x`` is empty (``np.median`` would return NaN).
    """
    n = x.size
    if n == 0:
        raise ValueError("median of an empty array; expected at least one value")
    k = n // 2
    if n % 2:
        return float(np.partition(x, k)[k])
    part = np.partition(x, (k - 1, k))
    return float((part[k - 1] + part[k]) / 2.0)
