"""Voxel-grid simplification of point clouds, with the adaptive grid size of seed 003 eq. (16).

A voxel grid replaces all points that fall into one cubic cell of edge ``voxel_size`` by their
centroid (the PCL ``VoxelGrid`` filter the seed uses). Seed 003 makes the edge grow as the chaser
closes in, so that the simplified cloud stays near a constant size while the raw flash cloud grows
with 1 / range^2::

    d_k = d_m * exp((X_init - X_{k-1}) / X_init)                                    (16)

with ``d_m`` the model cloud's grid size, ``X_init`` the range at initialisation and ``X_{k-1}`` the
range estimated on the previous frame (the seed's X axis is our boresight, +z).
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]

__all__ = ["adaptive_voxel_size", "voxel_downsample"]


def adaptive_voxel_size(d_model: float, x_init: float, x_prev: float) -> float:
    """Grid size of seed 003 eq. (16).

    Args:
        d_model: grid size of the model point cloud ``d_m`` [m], > 0.
        x_init: range along the boresight at initialisation ``X_init`` [m], > 0.
        x_prev: range along the boresight estimated on the previous frame ``X_{k-1}`` [m], > 0.

    Returns:
        The voxel edge ``d_k`` [m]; equals ``d_model`` at ``x_prev == x_init`` and grows as the
        range shrinks (``d_model * e`` at zero range).
    """
    for name, value in (("d_model", d_model), ("x_init", x_init), ("x_prev", x_prev)):
        if not (math.isfinite(value) and value > 0):
            raise ValueError(f"adaptive_voxel_size {name}={value}; expected a finite value > 0 [m]")
    return float(d_model * math.exp((x_init - x_prev) / x_init))


def voxel_downsample(points: npt.ArrayLike, voxel_size: float) -> FloatArray:
    """Replace the points of each occupied voxel by their centroid.

    The grid is anchored at the origin of the points' frame (cell ``i`` spans
    ``[i d, (i + 1) d)`` on each axis), so the same scene gives the same cells frame after frame.

    Args:
        points: (N, 3) float64 [m], any frame.
        voxel_size: voxel edge [m], > 0.

    Returns:
        (M, 3) float64 [m] centroids, M <= N, ordered by voxel index (deterministic).
    """
    if not (math.isfinite(voxel_size) and voxel_size > 0):
        raise ValueError(f"voxel_downsample voxel_size={voxel_size}; expected a finite value > 0 [m]")
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"voxel_downsample points has shape {p.shape}; expected (N, 3)")
    if p.shape[0] == 0:
        return np.zeros((0, 3))
    if not np.all(np.isfinite(p)):
        raise ValueError("voxel_downsample points has non-finite entries; expected finite [m]")
    cells = np.floor(p / voxel_size).astype(np.int64)
    # Pack the three integer cell indices into one int64 key: np.unique on a 1-D array is a
    # plain sort, several times faster than np.unique(axis=0) on rows.
    lo = cells.min(axis=0)
    cells -= lo
    span = cells.max(axis=0) + 1
    if float(span[0]) * float(span[1]) * float(span[2]) >= 2.0**62:
        raise ValueError(
            f"voxel_downsample voxel_size={voxel_size} is too small for a cloud spanning "
            f"{np.ptp(p, axis=0)} m; expected fewer than 2**62 cells"
        )
    keys = (cells[:, 0] * span[1] + cells[:, 1]) * span[2] + cells[:, 2]
    _, inverse, counts = np.unique(keys, return_inverse=True, return_counts=True)
    m = counts.shape[0]
    out = np.empty((m, 3))
    for axis in range(3):  # three bincounts, one per coordinate (not a loop over points)
        out[:, axis] = np.bincount(inverse, weights=p[:, axis], minlength=m)
    out /= counts[:, None]
    return out
