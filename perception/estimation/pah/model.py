"""The dense target model PAH checks against, and its occupancy grid for the cheap fit precheck.

:data:`_DENSE_POINTS` is the size of the dense area-uniform sample shared by the database build
(:mod:`.build`) and by ICP's prepared model; :class:`_FitGrid` is the boolean voxel grid of the
region near the model surface (an O(1) per-point fit test), cached on the target by
:func:`fit_grid`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from scipy import ndimage

from perception.estimation.registration import prepare_model
from perception.targets import TargetModel

from .poses import FloatArray

# Dense samples the sparse set is drawn from (shared with ICP's prepared model).
_DENSE_POINTS = 20_000
# Voxels per metre are capped so the fit grid of a large target stays below ~16 M cells.
_MAX_GRID_CELLS = 16_000_000


@dataclass(eq=False)
class _FitGrid:
    """Boolean voxel grid of the region within ``threshold_m`` of the model surface."""

    occupied: npt.NDArray[np.bool_]
    origin: FloatArray
    voxel_m: float
    threshold_m: float

    @classmethod
    def build(cls, dense: FloatArray, threshold_m: float) -> _FitGrid:
        lo = dense.min(axis=0) - threshold_m - 1e-6
        hi = dense.max(axis=0) + threshold_m + 1e-6
        voxel = 0.5 * threshold_m
        size = hi - lo
        if np.prod(np.ceil(size / voxel)) > _MAX_GRID_CELLS:
            voxel = float(np.cbrt(np.prod(size) / _MAX_GRID_CELLS)) * 1.01
        shape = np.maximum(np.ceil(size / voxel).astype(np.int64), 1)
        grid = np.zeros(tuple(shape), dtype=bool)
        ijk = np.clip(np.floor((dense - lo) / voxel).astype(np.int64), 0, shape - 1)
        grid[ijk[:, 0], ijk[:, 1], ijk[:, 2]] = True
        r = max(round(threshold_m / voxel), 0)
        if r > 0:
            ax = np.arange(-r, r + 1)
            ball = (ax[:, None, None] ** 2 + ax[None, :, None] ** 2 + ax[None, None, :] ** 2) <= (
                r * r
            )
            grid = ndimage.binary_dilation(grid, structure=ball)
        return cls(grid, lo, float(voxel), float(threshold_m))

    def inside(self, X: FloatArray) -> npt.NDArray[np.bool_]:
        """(...,) True where points (..., 3) [m, target frame] are near the surface."""
        shape = np.asarray(self.occupied.shape)
        ijk = np.floor((X - self.origin) / self.voxel_m).astype(np.int64)
        ok = np.all((ijk >= 0) & (ijk < shape), axis=-1)
        ijk = np.where(ok[..., None], ijk, 0)
        flat = (ijk[..., 0] * shape[1] + ijk[..., 1]) * shape[2] + ijk[..., 2]
        return ok & self.occupied.reshape(-1)[flat]


def fit_grid(target: TargetModel, model_hash: str, threshold_m: float) -> _FitGrid:
    """The fit grid of ``target`` at ``threshold_m`` [m], cached on the target."""
    dense = prepare_model(target, _DENSE_POINTS)
    key = ("pah_fit_grid", round(threshold_m, 6), model_hash)
    return target.cached(key, lambda: _FitGrid.build(dense.points, threshold_m))
