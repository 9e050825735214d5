"""Offline building of a PAH database's tables (seed 000 section 3.1.1).

A sparse, evenly spread set ``S`` of model surface points (farthest-point subsampling of dense
area-uniform samples), the length table of every segment ``L(s_i, s_j)`` (sorted by length,
indexed by quantised length) and the (M, M) connectivity table of all segment lengths. The
:class:`~perception.estimation.pah.database.PAHDatabase` holding them is made by its ``build``.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from perception.config import PAHConfig
from perception.targets import TargetModel

from .model import _DENSE_POINTS
from .poses import FloatArray, IntArray


def _farthest_point_indices(points: FloatArray, n: int, start: int) -> IntArray:
    """Greedy farthest-point subsampling: ``n`` indices of ``points`` spread evenly."""
    m = points.shape[0]
    n = min(n, m)
    idx = np.empty(n, dtype=np.int64)
    idx[0] = start
    d = np.linalg.norm(points - points[start], axis=1)
    for k in range(1, n):
        idx[k] = int(np.argmax(d))
        d = np.minimum(d, np.linalg.norm(points - points[idx[k]], axis=1))
    return idx


def build_tables(target: TargetModel, config: PAHConfig | None, seed: int) -> dict[str, Any]:
    """The constructor arguments of the database of ``target`` (all but ``target``).

    Raises:
        ValueError: ``target`` is not a TargetModel, ``config`` not a PAHConfig, or the mesh has
            no surface.
    """
    if not isinstance(target, TargetModel):
        raise ValueError(f"target is a {type(target).__name__}; expected a TargetModel")  # noqa: TRY004
    cfg = PAHConfig() if config is None else config
    if not isinstance(cfg, PAHConfig):
        raise ValueError(f"config is a {type(cfg).__name__}; expected a PAHConfig")  # noqa: TRY004
    if len(target.mesh.faces) == 0 or not float(target.mesh.area) > 0:
        raise ValueError(f"target {target.name!r} has no surface; PAH needs a mesh with area")
    dense_pts, dense_nrm = target.sample_surface(_DENSE_POINTS, seed=int(seed))
    dense = np.asarray(dense_pts)
    start = int(np.random.default_rng(seed).integers(dense.shape[0]))
    idx = _farthest_point_indices(dense, int(cfg.model_points), start)
    S = np.ascontiguousarray(dense[idx], dtype=np.float64)
    N = np.ascontiguousarray(dense_nrm[idx], dtype=np.float64)
    m = S.shape[0]
    d_cover, _ = cKDTree(S).query(dense, k=1)
    coverage = float(np.percentile(d_cover, 90))

    D = np.linalg.norm(S[:, None, :] - S[None, :, :], axis=-1)
    iu, ju = np.triu_indices(m, k=1)
    lengths = D[iu, ju]
    order = np.argsort(lengths, kind="stable")
    seg_len = lengths[order]
    n_bins = math.floor(seg_len[-1] / cfg.length_bin_m) + 1
    edges = np.arange(n_bins + 1) * cfg.length_bin_m
    bin_ptr = np.searchsorted(seg_len, edges, side="left").astype(np.int64)
    bin_ptr[-1] = seg_len.shape[0]
    return {
        "config": cfg, "model_hash": target.model_hash, "target_name": target.name, "points": S,
        "normals": N, "coverage_m": coverage, "seg_i": iu[order].astype(np.int64),
        "seg_j": ju[order].astype(np.int64), "seg_len": seg_len, "bin_ptr": bin_ptr, "dist": D,
    }
