"""Outline (silhouette) constraints of a flash LiDAR frame, and a pose refinement that uses them.

Why: seen face-on, a target made of flat plates (the CYGNSS-like bus and wings of seed 003) gives
point-to-plane ICP no information about its in-plane position and its roll about the boresight:
every point's residual is along the plate normal. The Cramer-Rao bound of
:func:`perception.estimation.registration.icp` flags ``tx, ty, rz`` as degenerate on most seed-003 frames,
and the tracker's in-plane error is whatever the prediction left (a few mm, spikes of 5-8 mm and
0.24 deg). What does fix them is the outline: a flash frame says, pixel by pixel, where the target
is *not*.

How: for every pair of 4-neighbour pixels with a valid return at ``a`` and none at ``b`` (both
inside the image), the target's outline crosses the segment between the two pixel rays. A pixel is
valid exactly when its ray's first hit is a face seen at less than the sensor's grazing limit and
within its range window, so the model's outline at a pose is found the same way: cast rays along
the pair's line (``d(u) = normalise(d_a + u (d_b - d_a))``, a few pixels either side), take the
valid -> invalid flip nearest to the pair and bisect it. The flip lies on an edge of the hit facet;
that edge and the sensor origin span the *silhouette plane*, and the residual is the distance of
the pair's midpoint ray (``u = 1/2``, at the crossing's range) from that plane. Its error is the
pixel quantisation only: the true crossing is uniform over the pair, so the variance is
``w^2 / 12 (n . u_pair)^2`` with ``w`` the pair's footprint [m]. The residual has the form of a
point-to-plane residual (normal ``n``, point ``s`` on the edge), so surface and outline rows share
one Gauss-Newton step on the pose.

:func:`refine_pose` runs that joint step from an ICP result: surface rows from the faces the
measured rays cross (:meth:`perception.estimation.registration.FaceGrid.nearest`), outline rows from the
pairs, re-matched each iteration; its covariance is the inverse of the joint information.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from perception.config import FlashLidarConfig
from perception.geometry import check_rigid
from perception.sensing.pointcloud import PointCloud
from perception.estimation.registration import (
    ModelCloud,
    RegistrationResult,
    covariance_from_information,
)
from perception.sensing.scan_patterns import angles_to_directions
from perception.sensing.sensors.raycast import cast_rays
from perception.targets import TargetModel

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.intp]

__all__ = [
    "FlashGeometry",
    "OutlineRows",
    "model_crossings",
    "outline_pairs",
    "outline_rows",
    "refine_pose",
    "refine_with_outline",
    "scan_outline_pairs",
]


#: A surface match counts when the point's ray crosses the face within this of its edges [m].
_CROSSING_TOL_M = 1e-3

#: Outline rows whose image-plane normals agree to this [rad] are one group of parallel edges.
_PARALLEL_TOLERANCE_RAD = math.radians(1.0)


@dataclass(frozen=True)
class FlashGeometry:
    """What the estimator knows of a flash LiDAR: its pixel rays and when a pixel returns.

    Attributes:
        directions: (rows * cols, 3) unit ray of every pixel, row-major, sensor frame.
        rows: pixel rows.
        cols: pixel columns.
        cos_grazing: a face seen at a larger incidence (smaller cosine) gives no return.
        min_range_m: nearest valid range [m].
        max_range_m: farthest valid range [m].
    """

    directions: FloatArray
    rows: int
    cols: int
    cos_grazing: float
    min_range_m: float
    max_range_m: float

    @classmethod
    def from_config(cls, config: FlashLidarConfig | None = None) -> FlashGeometry:
        """The geometry of :class:`perception.sensing.sensors.FlashLidar` for ``config`` (same pixel
        angles: equal angular steps, pixel centres)."""
        c = config or FlashLidarConfig()
        fov_h, fov_v = (math.radians(v) for v in c.fov_deg)
        az = ((np.arange(c.cols) + 0.5) / c.cols - 0.5) * fov_h
        down = ((np.arange(c.rows) + 0.5) / c.rows - 0.5) * fov_v
        AZ, DOWN = np.meshgrid(az, down)
        d = np.ascontiguousarray(angles_to_directions(AZ, -DOWN).reshape(-1, 3))
        d.setflags(write=False)
        return cls(d, c.rows, c.cols, math.cos(math.radians(c.grazing_limit_deg)),
                   float(c.min_range_m), float(c.max_range_m))


def outline_pairs(valid_mask: npt.ArrayLike) -> tuple[IntArray, IntArray]:
    """4-neighbour pixel pairs across the outline of a flash frame.

    Args:
        valid_mask: (rows, cols) bool, pixels with a return.

    Returns:
        ``(a, b)`` row-major flat indices (K,): ``a`` valid, ``b`` its invalid right, left, lower
        or upper neighbour. Pairs leaving the image are not outline (the target may go on).
    """
    v = np.asarray(valid_mask, dtype=bool)
    if v.ndim != 2:
        raise ValueError(f"valid_mask has shape {v.shape}; expected (rows, cols)")
    rows, cols = v.shape
    idx = np.arange(rows * cols).reshape(rows, cols)
    a_l, b_l = [], []
    for va, vb, ia, ib in (
        (v[:, :-1], v[:, 1:], idx[:, :-1], idx[:, 1:]),
        (v[:-1, :], v[1:, :], idx[:-1, :], idx[1:, :]),
    ):
        m = va & ~vb
        a_l += [ia[m], ib[~va & vb]]
        b_l += [ib[m], ia[~va & vb]]
    return np.concatenate(a_l).astype(np.intp), np.concatenate(b_l).astype(np.intp)


def scan_outline_pairs(
    directions: npt.ArrayLike, returned: npt.ArrayLike, max_step_factor: float = 3.0
) -> tuple[IntArray, IntArray]:
    """Consecutive samples of a scan pattern across the target's outline.

    A scanning LIDAR draws a continuous curve; where one sample returns and the next does not (or
    the reverse), the target's outline crosses the short arc between the two rays, just as
    between two flash pixels. Steps much longer than the pattern's typical step (a raster's line
    return, a jump between petals) are not pairs.

    Args:
        directions: (N, 3) unit rays of the pattern's samples in time order, sensor frame.
        returned: (N,) bool, which samples gave a return.
        max_step_factor: longest step, in median steps, that still makes a pair.

    Returns:
        ``(a, b)`` sample indices (K,): ``a`` returned, ``b`` its neighbour that did not.
    """
    d = np.asarray(directions, dtype=np.float64)
    ok = np.asarray(returned, dtype=bool)
    if d.ndim != 2 or d.shape[1] != 3 or ok.shape != (d.shape[0],):
        raise ValueError(f"directions {d.shape} and returned {ok.shape}; expected (N, 3) and (N,)")
    if d.shape[0] < 2:
        return np.zeros(0, dtype=np.intp), np.zeros(0, dtype=np.intp)
    step = np.linalg.norm(np.diff(d, axis=0), axis=1)
    short = step <= max_step_factor * float(np.median(step))
    k = np.arange(d.shape[0] - 1)
    fwd = ok[:-1] & ~ok[1:] & short
    bwd = ~ok[:-1] & ok[1:] & short
    a = np.concatenate([k[fwd], k[bwd] + 1]).astype(np.intp)
    b = np.concatenate([k[fwd] + 1, k[bwd]]).astype(np.intp)
    return a, b


def _valid_hits(target: TargetModel, T: FloatArray, d_sensor: FloatArray, geom: FlashGeometry
                ) -> tuple[npt.NDArray[np.bool_], npt.NDArray[np.int64], FloatArray]:
    """Which rays (sensor frame, from the sensor origin) return at pose ``T``: (valid, face, range)."""
    R, t = T[:3, :3], T[:3, 3]
    face, rng, cos_inc = cast_rays(target, -(R.T @ t), d_sensor @ R)
    with np.errstate(invalid="ignore"):
        ok = (face >= 0) & (cos_inc >= geom.cos_grazing) & (rng >= geom.min_range_m) & (
            rng <= geom.max_range_m)
    return ok, face, rng


def _line_dirs(da: FloatArray, db: FloatArray, u: FloatArray) -> FloatArray:
    d = da + u[:, None] * (db - da)
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def model_crossings(
    target: TargetModel,
    T_sensor_target: npt.ArrayLike,
    da: FloatArray,
    db: FloatArray,
    geom: FlashGeometry,
    *,
    reach_px: int = 3,
    bisections: int = 6,
) -> tuple[npt.NDArray[np.bool_], FloatArray, npt.NDArray[np.int64], FloatArray]:
    """Where the model's outline at a pose crosses each pair's line of rays.

    Args:
        target: the model.
        T_sensor_target: (4, 4) pose.
        da: (K, 3) unit rays of the valid pixels, sensor frame.
        db: (K, 3) unit rays of their invalid neighbours.
        geom: the sensor's validity rule.
        reach_px: search ``u`` in ``[-reach_px, reach_px + 1]`` (pixels along the pair).
        bisections: halvings of the bracketing pixel step (1/64 px with 6).

    Returns:
        ``(ok, s, face, u)``: pairs with a valid -> invalid flip in reach (K,) bool; for those,
        the model point at the flip on the valid side (K, 3) [m, sensor frame], its face (K,) and
        the flip's ``u`` (K,).
    """
    T = check_rigid(T_sensor_target, "T_sensor_target")
    k = da.shape[0]
    us = np.arange(-int(reach_px), int(reach_px) + 2, dtype=np.float64)
    n_u = us.size
    uu = np.tile(us, k)
    kk = np.repeat(np.arange(k), n_u)
    ok, face, rng = _valid_hits(target, T, _line_dirs(da[kk], db[kk], uu), geom)
    S = ok.reshape(k, n_u)
    flip = S[:, :-1] & ~S[:, 1:]
    # Nearest flip to the pair itself (bracket [0, 1]).
    cost = np.where(flip, np.abs(us[:-1]), np.inf)
    j = np.argmin(cost, axis=1)
    found = np.isfinite(cost[np.arange(k), j])
    rows = np.flatnonzero(found)
    lo = us[j[rows]]
    hi = lo + 1.0
    at = rows * n_u + j[rows]
    f_lo = face[at].copy()
    r_lo = rng[at].copy()
    dA, dB = da[rows], db[rows]
    for _ in range(int(bisections)):
        mid = 0.5 * (lo + hi)
        v, fm, rm = _valid_hits(target, T, _line_dirs(dA, dB, mid), geom)
        lo = np.where(v, mid, lo)
        hi = np.where(v, hi, mid)
        f_lo = np.where(v, fm, f_lo)
        r_lo = np.where(v, rm, r_lo)
    s = np.zeros((k, 3))
    fc = np.full(k, -1, dtype=np.int64)
    u = np.full(k, np.nan)
    s[rows] = _line_dirs(dA, dB, lo) * r_lo[:, None]
    fc[rows] = f_lo
    u[rows] = lo
    return found, s, fc, u


@dataclass
class OutlineRows:
    """Linearised outline residuals ``r(xi) ~= r - A xi`` in the twist of
    :attr:`RegistrationResult.covariance` (pivot: the target origin, sensor axes).

    Attributes:
        A: (K, 6) rows ``[n, (s - t) x n]``.
        r: (K,) distance of the pair's midpoint ray from the silhouette plane [m] (positive:
            the measured outline lies beyond the model's, on the invalid side).
        var: (K,) quantisation variance [m^2].
        s: (K, 3) model outline points [m], sensor frame.
        normal: (K, 3) silhouette-plane normals, sensor frame.
    """

    A: FloatArray
    r: FloatArray
    var: FloatArray
    s: FloatArray
    normal: FloatArray


def outline_rows(
    target: TargetModel,
    model: ModelCloud,
    T_sensor_target: npt.ArrayLike,
    da: FloatArray,
    db: FloatArray,
    geom: FlashGeometry,
    *,
    reach_px: int = 3,
    bisections: int = 6,
) -> OutlineRows:
    """Outline residuals of the pairs ``(da, db)`` at a pose (pairs with no model flip in reach are
    left out).

    Args:
        target: the model (ray casting).
        model: its prepared :class:`ModelCloud` (the facet edges of its :class:`FaceGrid`).
        T_sensor_target: (4, 4) pose.
        da, db: (K, 3) rays of the valid pixels and of their invalid neighbours, sensor frame.
        geom: sensor validity rule.
        reach_px, bisections: see :func:`model_crossings`.
    """
    if model.grid is None:
        raise ValueError("model has no FaceGrid (built from bare samples); outline rows need faces")
    T = check_rigid(T_sensor_target, "T_sensor_target")
    R, t = T[:3, :3], T[:3, 3]
    ok, s, face, u = model_crossings(target, T, da, db, geom, reach_px=reach_px,
                                     bisections=bisections)
    s, face, dA, dB = s[ok], face[ok], da[ok], db[ok]
    if s.shape[0] == 0:
        z = np.zeros((0, 3))
        return OutlineRows(np.zeros((0, 6)), np.zeros(0), np.zeros(0), z, z.copy())
    pl = model.grid.planes[face]
    st = (s - t) @ R
    v = np.einsum("kij,kj->ki", pl[:, 1:, :3], st) + pl[:, 1:, 3]
    e_row = np.argmax(v, axis=1)  # the facet edge the flip lies on (interior edges never win)
    m_edge = pl[np.arange(face.size), 1 + e_row, :3]
    e = np.cross(pl[:, 0, :3], m_edge) @ R.T
    n = np.cross(s, e)
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
    step = dB - dA
    n *= np.sign(np.einsum("ij,ij->i", n, step))[:, None]
    rng = np.linalg.norm(s, axis=1)
    mid = dA + 0.5 * step
    mid /= np.linalg.norm(mid, axis=1, keepdims=True)
    r = np.einsum("ij,ij->i", n, mid) * rng
    w_px = np.linalg.norm(step, axis=1) * rng
    proj = np.abs(np.einsum("ij,ij->i", n, step)) / np.linalg.norm(step, axis=1)
    period = w_px * np.maximum(proj, 0.05 ** 0.5)
    # Parallel edges move together: a shift of the target along their normal moves every
    # crossing's phase by the same amount, so they are one group (signed by their side).
    theta = np.arctan2(n[:, 1], n[:, 0])
    n_bins = round(math.pi / _PARALLEL_TOLERANCE_RAD)
    direction = np.mod(np.rint(np.mod(theta, math.pi) / _PARALLEL_TOLERANCE_RAD), n_bins)
    side = np.where(np.cos(theta - direction * _PARALLEL_TOLERANCE_RAD) >= 0.0, 1.0, -1.0)
    var = _edge_quantisation_variance(direction.astype(np.int64), u[ok], period, side)
    A = np.hstack([n, np.cross(s - t, n)])
    return OutlineRows(A, r, var, s, n)


def _edge_quantisation_variance(group: npt.NDArray[np.int64], u: FloatArray, period: FloatArray,
                                side: FloatArray | None = None, n_offsets: int = 32
                                ) -> FloatArray:
    """Per-row variance [m^2] that gives each group of parallel edges the information its pairs
    really carry.

    A pair's error is its crossing's position between the two pixels (period ``period`` [m],
    normal to the edge), uniform over the period: variance ``period^2 / 12`` if the pairs were
    independent. They are not: along an edge, the crossing phases ``u`` follow the edge's slope
    over the pixel grid, and an edge that runs with the grid (or at 45 deg) puts every pair at the
    same phase; parallel edges of a rigid body keep their phase differences. Shifting the target
    by an unknown offset ``c`` (uniform over a period) along the group's normal moves every
    phase by ``side c / period`` (``side`` +-1: which way each row's normal points); the variance
    over ``c`` of the group's mean error is what the group tells. Each of its ``n`` rows gets
    ``n`` times that (never less than its own ``period^2 / 12``), so that the rows of one group
    together weigh as much as that one mean.
    """
    if group.size == 0:
        return np.zeros(0)
    sd = np.ones_like(u) if side is None else side
    _, g = np.unique(group, return_inverse=True)
    n_g = np.bincount(g).astype(np.float64)
    p_max = np.zeros(n_g.size)
    np.maximum.at(p_max, g, period)
    c = (np.arange(n_offsets) + 0.5) / n_offsets * p_max[g][:, None]  # (K, n_offsets) [m]
    err = sd[:, None] * (np.mod(u[:, None] + sd[:, None] * c / period[:, None], 1.0) - 0.5)
    err *= period[:, None]
    mean = np.zeros((n_g.size, n_offsets))
    np.add.at(mean, g, err)
    mean /= n_g[:, None]
    v_group = np.var(mean, axis=1)
    return np.maximum(n_g[g] * v_group[g], period**2 / 12.0)


def _exp_so3(phi: FloatArray) -> FloatArray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_rotvec(phi).as_matrix()


def refine_pose(
    cloud: PointCloud,
    target: TargetModel,
    model: ModelCloud,
    T_init: npt.ArrayLike,
    geom: FlashGeometry,
    *,
    sigma: float,
    surface_idx: npt.ArrayLike | None = None,
    max_pairs: int = 1500,
    iterations: int = 4,
    gate_m: float = 0.05,
    kernel_scale: float = 2.5,
    noise_floor_fraction: float = 0.2,
    back_facing_cos: float = 0.3,
    step_tol_sigma: float = 0.2,
    outline_axes: tuple[int, ...] = (0, 1, 5),
    reach_px: int = 3,
) -> RegistrationResult:
    """Gauss-Newton on the pose with surface rows and outline rows together.

    Surface rows: each measured point on the face its ray crosses (exact planes of the model's
    :class:`FaceGrid`), residual variance ``sigma^2 ((n . d)^2 + f^2)``, Huber kernel at
    ``kernel_scale`` sigmas. Outline rows: :func:`outline_rows` on the frame's outline pairs
    (an even stride over them when there are more than ``max_pairs``), Huber too. Both are
    re-matched every iteration.

    Args:
        cloud: the flash frame (``organized``/``valid_mask`` and ``directions`` needed).
        target: the model.
        model: its prepared :class:`ModelCloud` (with a face grid).
        T_init: (4, 4) starting pose (an ICP result: within a pixel or two).
        geom: the sensor's pixel rays and validity rule.
        sigma: range noise 1-sigma [m].
        surface_idx: indices of the cloud's points for the surface rows (default all).
        max_pairs: cap on outline pairs per frame.
        iterations: Gauss-Newton iterations at most.
        gate_m: surface matches farther than this are dropped [m].
        kernel_scale: Huber threshold [sigmas].
        noise_floor_fraction: ``f`` above.
        back_facing_cos: faces whose normal . ray exceeds this are not matched.
        step_tol_sigma: stop once a step is below this many sigmas (Mahalanobis length; the
            outline pairs are re-matched each step, which leaves a jitter of ~0.1 sigma).
        outline_axes: twist components (of ``tx, ty, tz, rx, ry, rz``) the outline rows inform;
            default the image-plane ones (``tx, ty, rz``). The outline's error is pixel
            quantisation, the same for every pair along an edge that runs with the pixel grid
            (roll 0, +-45, +-90 deg on a box-shaped target); with all six axes, two such edges at
            different depths (bus face and wing, 0.19 m apart) would tilt the pose by their
            quantisation difference over that depth, overriding the surface's far better pitch
            and yaw.
        reach_px: pixels either side of a pair searched for the model's outline on the first
            iteration (one pixel afterwards).

    Returns:
        :class:`RegistrationResult` with the refined pose and the joint covariance.
    """
    t_start = time.perf_counter()
    if cloud.valid_mask is None:
        raise ValueError("cloud has no valid_mask; outline refinement needs an organised flash frame")
    if model.grid is None:
        raise ValueError("model has no FaceGrid; refine_pose needs the model's faces")
    T = check_rigid(T_init, "T_init").copy()
    if cloud.valid_mask.shape != (geom.rows, geom.cols):
        raise ValueError(f"cloud grid {cloud.valid_mask.shape} != sensor {(geom.rows, geom.cols)}")
    a, b = outline_pairs(cloud.valid_mask)
    idx = np.arange(len(cloud)) if surface_idx is None else np.asarray(surface_idx)
    return refine_with_outline(
        cloud.points[idx], cloud.directions[idx], sigma, geom.directions[a], geom.directions[b],
        target, model, T, geom, max_pairs=max_pairs, iterations=iterations, gate_m=gate_m,
        kernel_scale=kernel_scale, noise_floor_fraction=noise_floor_fraction,
        back_facing_cos=back_facing_cos, step_tol_sigma=step_tol_sigma, outline_axes=outline_axes,
        reach_px=reach_px, t_start=t_start,
    )


def refine_with_outline(
    P: FloatArray,
    D: FloatArray,
    sigma: float | npt.ArrayLike,
    da: FloatArray,
    db: FloatArray,
    target: TargetModel,
    model: ModelCloud,
    T_init: npt.ArrayLike,
    geom: FlashGeometry,
    *,
    max_pairs: int = 1500,
    iterations: int = 4,
    gate_m: float = 0.05,
    kernel_scale: float = 2.5,
    noise_floor_fraction: float = 0.2,
    back_facing_cos: float = 0.3,
    step_tol_sigma: float = 0.2,
    outline_axes: tuple[int, ...] = (0, 1, 5),
    reach_px: int = 3,
    t_start: float | None = None,
) -> RegistrationResult:
    """The Gauss-Newton of :func:`refine_pose` on given surface points and outline pairs (any
    sensor: a flash frame's pixel pairs, or consecutive samples of a scan across the outline,
    :func:`scan_outline_pairs`).

    Args:
        P: (N, 3) measured points [m], sensor frame (de-skewed to the pose's time).
        D: (N, 3) their unit rays.
        sigma: range noise 1-sigma [m], scalar or (N,).
        da, db: (K, 3) rays of the returning samples and of their non-returning neighbours.
        target, model, T_init, geom: as in :func:`refine_pose` (only ``geom``'s validity rule is
            used here, not its pixel grid).
        max_pairs ... reach_px: as in :func:`refine_pose`.
        t_start: the caller's start time (``time.perf_counter``) for ``time_s``.
    """
    if t_start is None:
        t_start = time.perf_counter()
    if model.grid is None:
        raise ValueError("model has no FaceGrid; refine_with_outline needs the model's faces")
    T = check_rigid(T_init, "T_init").copy()
    P = np.asarray(P, dtype=np.float64)
    D = np.asarray(D, dtype=np.float64)
    sig_all = np.broadcast_to(np.asarray(sigma, dtype=np.float64), (P.shape[0],))
    if da.shape[0] > max_pairs:
        stride = -(-da.shape[0] // max_pairs)
        da, db = da[::stride], db[::stride]
    n_pts = P.shape[0]
    grid = model.grid
    axis_mask = np.zeros(6)
    axis_mask[list(outline_axes)] = 1.0
    H = np.zeros((6, 6))
    n_surf = n_out = 0
    converged = False
    it = 0
    for it in range(1, int(iterations) + 1):
        R, t = T[:3, :3], T[:3, 3]
        q = (P - t) @ R
        found, dist, face, v = grid.nearest(q, D @ R, back_facing_cos, True)
        pl = grid.planes[face]
        nt = pl[:, 0, :3]
        dt_ = D[found] @ R
        cos = np.einsum("ij,ij->i", nt, dt_)
        # A point whose ray does not cross its face inside the face's edges lies beyond the
        # model's outline at this pose (nearest-face fallback); and a return never comes from a
        # face seen beyond the grazing limit. Such a point just past a face-on plate's edge would
        # be matched to the edge-on side face, whose plane would pin the in-plane position with
        # a sigma the noise floor makes far too small. The outline rows carry what it knows.
        with np.errstate(divide="ignore", invalid="ignore"):
            lam = -v[:, 0] / cos
        edge_at_crossing = v[:, 1:] + lam[:, None] * np.einsum("kij,kj->ki", pl[:, 1:, :3], dt_)
        crosses = np.max(edge_at_crossing, axis=1) <= _CROSSING_TOL_M
        keep = (dist <= gate_m) & (-cos >= geom.cos_grazing) & crosses
        found, v, nt, cos = found[keep], v[keep], nt[keep], cos[keep]
        ns = nt @ R.T
        rs = v[:, 0]
        foot = (q[found] - rs[:, None] * nt) @ R.T + t
        var_s = sig_all[found] ** 2 * (cos * cos + noise_floor_fraction**2)
        As = np.hstack([ns, np.cross(foot - t, ns)])
        # After the first step the model's outline is within a pixel of where it will end.
        orow = outline_rows(target, model, T, da, db, geom, reach_px=reach_px if it == 1 else 1)
        A = np.vstack([As, orow.A * axis_mask])
        r = np.concatenate([rs, orow.r])
        var = np.concatenate([var_s, orow.var])
        z = r / np.sqrt(var)
        w = np.minimum(1.0, kernel_scale / np.maximum(np.abs(z), 1e-12)) / var
        Aw = A * w[:, None]
        H = Aw.T @ A
        g = Aw.T @ r
        n_surf, n_out = int(found.size), int(orow.r.size)
        if n_surf + n_out < 6:
            return RegistrationResult.failure(
                f"{n_surf} surface and {n_out} outline rows; refinement needs >= 6",
                T_init, n_points=n_pts, time_s=time.perf_counter() - t_start, iterations=it)
        damp = 1e-9 * float(np.max(np.diag(H))) + 1e-12
        xi = np.linalg.solve(H + damp * np.eye(6), g)
        T_new = np.eye(4)
        T_new[:3, :3] = _exp_so3(xi[3:]) @ R
        T_new[:3, 3] = t + xi[:3]
        T = T_new
        if float(xi @ H @ xi) < step_tol_sigma**2:
            converged = True
            break
    radius = float(model.radius)
    cov, degenerate = covariance_from_information(H, radius)
    return RegistrationResult(
        T_sensor_target=T,
        fitness=n_surf / max(n_pts, 1),
        inlier_rmse=0.0,
        converged=converged,
        iterations=it,
        covariance=cov,
        degenerate_axes=degenerate,
        reason="" if converged else f"not converged after {iterations} iterations",
        n_points=n_pts,
        n_inliers=n_surf,
        time_s=time.perf_counter() - t_start,
    )
