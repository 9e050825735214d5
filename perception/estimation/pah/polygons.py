"""Polygons of a scan, and the model polygons that match them (seed 000 section 3.1.2).

Polygon selection: an N-point polygon (4-6 points) of large area is picked from the scan by
greedy farthest-point selection from a random seed point, among the points that have scan
neighbours (:func:`_supported`, :func:`_pick_polygon`).

Table traversal (:func:`match_polygon`): all model polygons whose pairwise distances match the
scan polygon's within the tolerance, enumerated by a partial tree traversal of the database's
tables: the first edge from the length table, each further vertex from the banded connectivity
rows of the vertices matched so far (:func:`_banded`), vectorised over the partial matches and
pruned as early as they can be judged (direction, corridor, visibility, merging). Then the poses
of full matches are checked for visibility and the corridor (:func:`_plausible`).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt
from scipy.spatial import cKDTree

from .constraint import PoseConstraint
from .poses import FloatArray, IntArray, _diameter, _triangle_poses

if TYPE_CHECKING:
    from .database import PAHDatabase

# A matched model normal may face away from the scan ray by at most this cosine: the sparse point
# matched to a scan point can sit just round an edge, so the test is lenient.
_VISIBLE_COS = 0.35
# Polygon vertices: points whose 3rd nearest neighbour is within 4x the scan's median such
# distance (1% stray returns at 2-60 m: ~90% of them excluded, <= 2% of the target's points).
_ISOLATION_K = 3
_ISOLATION_FACTOR = 4.0


def _supported(P: FloatArray) -> IntArray:
    """Indices of the scan points that are not isolated: their ``_ISOLATION_K``-th nearest
    neighbour lies within ``_ISOLATION_FACTOR`` times the scan's median such distance.

    Stray-light returns land at random ranges along their rays, metres from any other point;
    points on the target have neighbours along and across the scan lines.
    """
    k = min(_ISOLATION_K, P.shape[0] - 1)
    d, _ = cKDTree(P).query(P, k=k + 1)
    dk = d[:, -1]
    return np.flatnonzero(dk <= _ISOLATION_FACTOR * np.median(dk))


def _pick_polygon(
    P: FloatArray, n_poly: int, max_extent: float, rng: np.random.Generator
) -> IntArray | None:
    """A large-area polygon of the scan: greedy farthest points from a random seed point.

    Each next vertex is drawn at random among the points whose distance to the chosen ones is at
    least 80 % of the largest such distance (so repeated draws give different polygons), and no
    farther than ``max_extent`` from any chosen vertex (the longest model segment). The longest
    edge is put first: it is looked up in the length table, where long lengths are rare.
    """
    n = P.shape[0]
    chosen = [int(rng.integers(n))]
    dmin = np.linalg.norm(P - P[chosen[0]], axis=1)
    dmax = dmin.copy()
    for _ in range(1, n_poly):
        score = np.where(dmax <= max_extent, dmin, -1.0)
        if not score.max() > 0:
            return None
        pool = np.flatnonzero(score >= 0.8 * score.max())
        nxt = int(pool[rng.integers(pool.size)])
        chosen.append(nxt)
        dn = np.linalg.norm(P - P[nxt], axis=1)
        dmin = np.minimum(dmin, dn)
        dmax = np.maximum(dmax, dn)
    idx = np.asarray(chosen, dtype=np.int64)
    d = np.linalg.norm(P[idx][:, None] - P[idx][None], axis=-1)
    a, b = np.unravel_index(int(np.argmax(d)), d.shape)
    rest = [i for i in range(n_poly) if i not in (a, b)]
    return idx[[a, b, *rest]]


def match_polygon(
    db: PAHDatabase,
    Q: npt.ArrayLike,
    tolerance_m: float,
    rng: np.random.Generator,
    R_nominal: npt.ArrayLike | None = None,
    direction_tol_rad: float | None = None,
    *,
    constraint: PoseConstraint | None = None,
    rays: npt.ArrayLike | None = None,
    merge_m: float | None = None,
) -> IntArray:
    """All model polygons whose pairwise distances match a scan polygon's (partial traversal).

    The first edge comes from the length table; each further vertex ``k`` is the set of model
    points whose distances to the already matched vertices all match, the AND of rows of the
    connectivity table banded at ``|dist - d_vk| <= tol``, vectorised over the partial
    matches: vertex 0's band is a run of its row sorted by length (one ``searchsorted`` for
    all partial matches), and only the points of that run are tested against the others
    (:func:`_banded`).

    Partial matches are pruned as early as they can be judged, so that the tree stays small:

    - direction (``R_nominal``): each rotated model edge ``R_nominal (s_k - s_0)`` must point
      within the tolerance of the scan edge ``q_k - q_0``, from the first edge on;
    - corridor (``constraint``): from the first triangle on, its pose (frames on the three
      vertices) must have an admitted attitude and put the target origin in the corridor's
      cone and range, both widened by what the length tolerance allows;
    - visibility (``rays``): the matched model normals must not face away from the rays;
    - merging (``merge_m``): partial matches whose triangle poses put the model within about
      ``merge_m`` of each other are one match (the scan vertex lies between several sparse
      model points, each of which matches within the tolerance); the one whose edge lengths
      match best is kept. Without it the candidates multiply by the number of model points
      within the tolerance at every level.

    Arguments and result: :meth:`PAHDatabase.match_polygon`.
    """
    Qa = np.asarray(Q, dtype=np.float64)
    if Qa.ndim != 2 or Qa.shape[1] != 3 or Qa.shape[0] < 3:
        raise ValueError(f"Q has shape {Qa.shape}; expected an (N, 3) polygon with N >= 3")
    if (R_nominal is None) != (direction_tol_rad is None):
        raise ValueError("R_nominal and direction_tol_rad go together; got only one of them")
    if constraint is not None and R_nominal is None:
        R_nominal = constraint.R_sensor_target_nominal
        direction_tol_rad = constraint.attitude_tol_rad
    n_poly = Qa.shape[0]
    ray_a = None if rays is None else np.asarray(rays, dtype=np.float64)
    if ray_a is not None and ray_a.shape != Qa.shape:
        raise ValueError(f"rays has shape {ray_a.shape}; expected {Qa.shape} like Q")
    dq = np.linalg.norm(Qa[:, None, :] - Qa[None, :, :], axis=-1)
    cap = int(db.config.max_candidates)
    S = db.points
    use_dir = R_nominal is not None
    # Direction test of an edge (s_0, s_k): (s_k - s_0) . e_k >= cos(angle) |s_k - s_0| |e_k|
    # with e_k = R_nominal^T (q_k - q_0); the projections s . e_k of all model points once.
    proj: FloatArray | None = None
    lims = np.zeros(n_poly)
    if use_dir:
        assert direction_tol_rad is not None
        E = (Qa - Qa[0]) @ np.asarray(R_nominal, dtype=np.float64)
        proj = S @ E.T
        for k in range(1, n_poly):
            slack = math.asin(min(1.0, 2.0 * tolerance_m / max(dq[0, k], 1e-9)))
            lims[k] = math.cos(min(math.pi, float(direction_tol_rad) + slack)) * dq[0, k]

    def visible(k: int, idx: IntArray, R: FloatArray) -> npt.NDArray[np.bool_]:
        assert ray_a is not None
        return np.einsum("kij,kj->ki", R, db.normals[idx]) @ ray_a[k] < _VISIBLE_COS

    # Level 1: the first edge, direct lookup by quantised length (both orientations).
    d = dq[0, 1]
    b = db.config.length_bin_m
    nb = db.bin_ptr.shape[0] - 1
    lo_b = min(int(max(d - tolerance_m, 0.0) // b), nb)
    hi_b = min(int((d + tolerance_m) // b), nb - 1)
    if hi_b < lo_b:
        return np.empty((0, n_poly), dtype=np.int64)
    sl = slice(int(db.bin_ptr[lo_b]), int(db.bin_ptr[hi_b + 1]))
    keep = np.abs(db.seg_len[sl] - d) <= tolerance_m
    a, c = db.seg_i[sl][keep], db.seg_j[sl][keep]
    cand = np.concatenate([np.stack([a, c], 1), np.stack([c, a], 1)])
    if proj is not None and cand.shape[0]:
        ln = np.concatenate([db.seg_len[sl][keep]] * 2)
        cand = cand[proj[cand[:, 1], 1] - proj[cand[:, 0], 1] >= lims[1] * ln]
    cand = _cap(cand, cap, rng)
    # Further levels: AND of the banded connectivity rows of the matched vertices.
    for k in range(2, n_poly):
        if cand.shape[0] == 0:
            break
        owner, new = _banded(db, cand, dq[:k, k], tolerance_m,
                             None if proj is None else proj[:, k], lims[k])
        if k >= 3 and new.shape[0]:
            # Past the first triangle its pose predicts where the vertex lies on the model:
            # of the points in the distance bands (about that spot and its mirror image
            # through the triangle's plane), keep the nearest to the prediction.
            R, t = _triangle_poses(S[cand[:, :3]], Qa[:3])
            s_pred = np.einsum("kji,kj->ki", R, Qa[k] - t)
            miss = np.linalg.norm(S[new] - s_pred[owner], axis=1)
            order = np.lexsort((miss, owner))
            first = np.r_[True, owner[order][1:] != owner[order][:-1]]
            sel = order[first]
            owner, new = owner[sel], new[sel]
        cand = np.concatenate([cand[owner], new[:, None]], axis=1)
        if merge_m and k == 2 and cand.shape[0] > 1:
            cand = _merge(db, cand, dq, merge_m)
        cand = _cap(cand, cap, rng)
        if cand.shape[0] and (constraint is not None or ray_a is not None):
            cand = _prune_partial(db, cand, Qa, dq, tolerance_m, constraint,
                                  visible if ray_a is not None else None)
    if cand.shape[0] == 0 or cand.shape[1] < n_poly:
        return np.empty((0, n_poly), dtype=np.int64)
    return cand


def _banded(
    db: PAHDatabase, cand: IntArray, d: FloatArray, tol: float, proj: FloatArray | None = None,
    lim: float = 0.0,
) -> tuple[IntArray, IntArray]:
    """Next-vertex candidates of partial matches ``cand`` (K, k): the (owner o, point j) pairs
    with ``|dist[cand[o, v], j] - d[v]| <= tol`` for every matched vertex ``v`` and, with
    ``proj`` (M,) (the model points projected on the nominal edge direction), the edge from
    vertex 0 pointing that way: ``proj[j] - proj[cand[o, 0]] >= lim dist[cand[o, 0], j]``.
    Ordered by owner, then point (as ``np.nonzero`` over a dense (K, M) test).

    Vertex 0's band is a contiguous run of its row of the connectivity table sorted by length
    (:func:`_sorted_rows`), found by one ``searchsorted`` for all partial matches; only those
    points are tested further. Cost O(K x band) instead of O(K x M).
    """
    order, sdist, keys, stride = _sorted_rows(db)
    m = db.dist.shape[0]
    c0 = cand[:, 0]
    base = c0.astype(np.float64) * stride
    row0 = c0 * m
    # Slightly wide bounds; the exact tests below decide.
    lo = np.clip(np.searchsorted(keys, base + (d[0] - tol - 1e-9), side="left"), row0, row0 + m)
    hi = np.clip(np.searchsorted(keys, base + (d[0] + tol + 1e-9), side="right"), lo, row0 + m)
    owner, pos = _ragged(lo, hi)
    new = order[pos]
    d0 = sdist[pos]
    ok = np.abs(d0 - d[0]) <= tol
    if proj is not None:
        ok &= proj[new] - proj[c0[owner]] >= lim * d0
    owner, new = owner[ok], new[ok]
    if d.shape[0] > 1:
        flat = db.dist.reshape(-1)
        ok = np.abs(flat[cand[owner, 1] * m + new] - d[1]) <= tol
        for v in range(2, d.shape[0]):
            ok &= np.abs(flat[cand[owner, v] * m + new] - d[v]) <= tol
        owner, new = owner[ok], new[ok]
    key = np.sort(owner * m + new)
    return key // m, key % m


def _sorted_rows(db: PAHDatabase) -> tuple[IntArray, FloatArray, FloatArray, float]:
    """Rows of the connectivity table sorted by length, flattened: ``order`` (M * M,) point
    indices, ``sdist = dist[i, order]``, ``keys = i * stride + sdist`` (ascending) and
    ``stride`` [m]."""
    if db._rows_cache is None:
        m = db.dist.shape[0]
        srt = np.argsort(db.dist, axis=1, kind="stable")
        stride = 2.0 * float(db.dist.max()) + 1.0
        sdist = np.take_along_axis(db.dist, srt, axis=1)
        keys = sdist + stride * np.arange(m)[:, None]
        db._rows_cache = (srt.ravel().astype(np.int64), sdist.ravel(), keys.ravel(), stride)
    return db._rows_cache


def _merge(db: PAHDatabase, cand: IntArray, dq: FloatArray, merge_m: float) -> IntArray:
    """One partial match (K, k) per tuple of model-point clusters: the best-fitting one."""
    k = cand.shape[1]
    cluster, n_clusters = _clusters(db, merge_m)
    key = np.zeros(cand.shape[0], dtype=np.int64)
    for v in range(k):
        key = key * n_clusters + cluster[cand[:, v]]
    misfit = np.zeros(cand.shape[0])
    for i in range(k):
        for j in range(i + 1, k):
            misfit += np.abs(db.dist[cand[:, i], cand[:, j]] - dq[i, j])
    order = np.lexsort((misfit, key))
    ks = key[order]
    first = np.r_[True, ks[1:] != ks[:-1]]
    return cand[np.sort(order[first])]


def _clusters(db: PAHDatabase, merge_m: float) -> tuple[IntArray, int]:
    """Model points grouped about farthest-point centres ``merge_m`` [m] apart: (M,) ids, count.

    Matches that differ only by neighbouring model points of one group give the same pose
    within the tolerance. Cached per merge distance (rounded to 1 cm).
    """
    key = max(round(merge_m, 2), 0.01)
    hit = db._cluster_cache.get(key)
    if hit is None:
        S = db.points
        centres = [0]
        d = np.linalg.norm(S - S[0], axis=1)
        while d.max() > key and len(centres) < S.shape[0]:
            centres.append(int(np.argmax(d)))
            d = np.minimum(d, np.linalg.norm(S - S[centres[-1]], axis=1))
        _, ids = cKDTree(S[centres]).query(S, k=1)
        hit = (ids.astype(np.int64), len(centres))
        db._cluster_cache[key] = hit
    return hit


def _prune_partial(
    db: PAHDatabase,
    cand: IntArray,
    Q: FloatArray,
    dq: FloatArray,
    tol: float,
    constraint: PoseConstraint | None,
    visible: Callable[[int, IntArray, FloatArray], npt.NDArray[np.bool_]] | None,
) -> IntArray:
    """Corridor and visibility tests of partial matches (K, k >= 3) by their triangle poses."""
    k = cand.shape[1]
    Sk = db.points[cand]
    R, _ = _triangle_poses(Sk[:, :3], Q[:3])
    keep = np.ones(cand.shape[0], dtype=bool)
    if constraint is not None:
        # A vertex may sit up to ~tol from its model point: the frame's axes then turn by up
        # to asin(2 tol / edge) about each of two axes.
        h = np.linalg.norm(np.cross(Q[1] - Q[0], Q[2] - Q[0])) / max(dq[0, 1], 1e-9)
        slack = sum(math.asin(min(1.0, 2.0 * tol / max(x, 1e-9))) for x in (dq[0, 1], h))
        keep &= constraint.attitude_ok(R, slack_rad=slack)
        # Target origin, from the centroid of the matched vertices; its lever arm turns by
        # the attitude slack.
        sc = Sk.mean(axis=1)
        t = Q[:k].mean(axis=0) - np.einsum("kij,kj->ki", R, sc)
        lever = np.linalg.norm(sc, axis=1).max()
        keep &= constraint.position_ok(t, slack_m=tol + float(lever) * min(slack, 2.0))
    if visible is not None:
        # The first triangle's pose serves every level: check each vertex once.
        for v in range(k) if k == 3 else (k - 1,):
            keep[keep] &= visible(v, cand[keep, v], R[keep])
    return cand[keep]


def _cap(cand: IntArray, cap: int, rng: np.random.Generator) -> IntArray:
    if cand.shape[0] <= cap:
        return cand
    return cand[np.sort(rng.choice(cand.shape[0], size=cap, replace=False))]


def _ragged(starts: IntArray, ends: IntArray) -> tuple[IntArray, IntArray]:
    """Expand ranges ``[starts_k, ends_k)``: returns (owner k, index) of every element."""
    counts = np.maximum(ends - starts, 0)
    total = int(counts.sum())
    owner = np.repeat(np.arange(starts.shape[0]), counts)
    first = np.cumsum(counts) - counts
    pos = np.arange(total) - np.repeat(first, counts)
    return owner, starts[owner] + pos


def _plausible(
    db: PAHDatabase,
    R: FloatArray,
    t: FloatArray,
    cand: IntArray,
    Q: FloatArray,
    rays: FloatArray,
    tol: float,
    constraint: PoseConstraint | None,
) -> npt.NDArray[np.bool_]:
    """(K,) poses whose matched model normals face the sensor and that lie in the corridor."""
    nrm_s = np.einsum("kij,knj->kni", R, db.normals[cand])
    keep = np.all(np.einsum("kni,ni->kn", nrm_s, rays) < _VISIBLE_COS, axis=1)
    if constraint is not None:
        slack = math.atan(2.0 * tol / max(_diameter(Q), 1e-9))
        keep &= constraint.attitude_ok(R, slack_rad=slack)
        keep &= constraint.position_ok(t, slack_m=tol)
    return keep
