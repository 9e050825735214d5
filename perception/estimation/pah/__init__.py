"""Polygonal aspect hashing (PAH): model-based acquisition of the target pose (seed 000 section 3.1).

Offline (:meth:`PAHDatabase.build`, section 3.1.1): a sparse, evenly spread set ``S`` of model
surface points (farthest-point subsampling of dense area-uniform samples) and every segment
``L(s_i, s_j)`` between them, stored in two tables:

- a *length table*: the undirected segments sorted by length, indexed by quantised length
  (``length_bin_m`` bins, CSR offsets), for the direct lookup of the first polygon edge;
- a *connectivity table*: the (M, M) lengths of all segments by end point, so that "the points
  at distance ``d_0k +- tol`` from the matched ``s_0`` and ``d_1k +- tol`` from ``s_1``..." is an
  AND of banded rows.

Runtime (:meth:`PAHDatabase.localize`, section 3.1.2): an N-point polygon (4-6 points) of large
area is picked from the scan by greedy farthest-point selection from a random seed point, among
the points that have scan neighbours (an isolated stray return would otherwise be picked first).
All model polygons whose pairwise distances match the scan polygon's within the tolerance are
enumerated by a partial tree traversal (first edge from the length table, each further vertex
from the connectivity rows of the vertices matched so far: vertex 0's distance band is a run of
its row sorted by length, the other vertices' rows test only that run), vectorised over the
partial matches.
Each match gives a pose ``p = R s + T`` (eq. 1) by a batched SVD; matches that are mirror images,
that show back faces to the sensor or (constrained search) that fall outside the approach corridor
are dropped before any fit check. The survivors are scored by a surface-fit precheck on a
decimated scan (an occupancy grid of the voxels near the model surface, O(1) per point), the best
few by the full O(n) check against the dense model's KD-tree, and the distinct best ones are
polished by a short ICP (one start per basin: a start near one already polished slides to the same
pose) and verified on the whole scan.

Verification (Figure 2's fit check, plus free space): besides the surface fit, every scan ray is
cast against the model under the hypothesis (one Embree call for all hypotheses); a point measured
behind the model surface along its ray (and along the rim of its beam footprint, which can
straddle an edge) is impossible under that pose. This is what tells a long
body such as CYGNSS from its half-turn flip, which fits the visible points as well. The leading
hypothesis is always verified against its near-symmetric alternatives (the turns that map the
model nearly onto itself, found once per target), so the flip competes even when no polygon
produced it (each alternative judged with the symmetry tolerance before its short ICP); a leader
whose short ICP had not settled is polished by a full ICP before more polygons are paid for.
More polygons are tried until a verified leader fits ``accept_fitness`` of the scan
with (almost) no free-space violation, or the polygon or time budget runs out (default budgets
:data:`DEFAULT_TIME_BUDGET_S` and :data:`DEFAULT_CONSTRAINED_TIME_BUDGET_S`; running out before a
hypothesis explained the scan gives ``converged=False`` and says so). The leader and runners-up in
other basins are refined by a full ICP along the measured rays (each point matched to the face its
ray crosses) and the best verified one is returned.

Several scans (:meth:`PAHDatabase.localize_scans`, section 3.1.2's "newly acquired point clouds
over time"): successive scans of one static relative pose are pooled and localized as one cloud
(in a corridor, the fit check of the matches and the short screening ICPs run on one scan's worth
of the pooled points; the verification of every hypothesis and the final ICP always on all of
them).
On sparse scans (100-300 points on a 1 m target, or on CYGNSS at tens of metres) one scan leaves
the final ICP noise-limited (Cramer-Rao bound up to 1-2 deg per axis), and leaves the small features that tell the
cubesat's bus from its quarter and half turns unsampled; two or three scans fix both.

Constrained search (section 5.3, the docking case): a :class:`PoseConstraint` bounds the attitude
about a nominal one and the position to a cone about the boresight and a range interval. The tree
is pruned as early as possible: every polygon edge must point, once rotated by the nominal
attitude, within the attitude tolerance of the scan edge (from the first edge on); from the first
triangle on, its pose must be admitted (attitude, and the implied target origin in the cone and
range) and the matched model normals must face the sensor; matches that differ only by
neighbouring model points are merged at the triangle; and each further vertex is the model point
nearest to where the triangle's pose puts it. The alternatives of a leader that the corridor
excludes are never tried. Constrained acquisition costs a small fraction of the unconstrained one.
"""

from __future__ import annotations

import dataclasses
import json
import math
import time
import zipfile
import zlib
from collections.abc import Callable, Sequence
from dataclasses import dataclass, fields
from pathlib import Path

import numpy as np
import numpy.typing as npt
from pydantic import ValidationError
from scipy import ndimage
from scipy.spatial import cKDTree

from perception.config import CorridorConfig, ICPConfig, PAHConfig
from perception.sensing.pointcloud import PointCloud
from perception.estimation.registration import (
    ModelCloud,
    RegistrationResult,
    icp,
    per_point_sigma,
    prepare_model,
    validate_points,
)
from perception.sensing.sensors.raycast import cast_rays
from perception.targets import TargetModel

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]

__all__ = [
    "DEFAULT_CONSTRAINED_TIME_BUDGET_S",
    "DEFAULT_TIME_BUDGET_S",
    "PAH_FORMAT_VERSION",
    "PAHDatabase",
    "PAHFileError",
    "PoseConstraint",
]

#: Version of the ``.npz`` layout written by :meth:`PAHDatabase.save`.
PAH_FORMAT_VERSION = 1

#: Default wall-clock budgets [s] of :meth:`PAHDatabase.localize`, unconstrained and in a corridor.
#: Seed 000 section 5.3: docking (corridor) acquisition took under a second on the flight
#: computer, unconstrained 5-10 s; a typical acquisition here takes a small fraction of either.
DEFAULT_TIME_BUDGET_S = 5.0
DEFAULT_CONSTRAINED_TIME_BUDGET_S = 1.0

# Dense samples the sparse set is drawn from (shared with ICP's prepared model).
_DENSE_POINTS = 20_000
# A matched model normal may face away from the scan ray by at most this cosine: the sparse point
# matched to a scan point can sit just round an edge, so the test is lenient.
_VISIBLE_COS = 0.35
# Voxels per metre are capped so the fit grid of a large target stays below ~16 M cells.
_MAX_GRID_CELLS = 16_000_000


# ---------------------------------------------------------------------------------------------
# Corridor constraint
# ---------------------------------------------------------------------------------------------
@dataclass
class PoseConstraint:
    """Admissible poses of the target for a constrained (docking-corridor) acquisition.

    A pose ``T_sensor_target`` is admitted when all of these hold:

    - attitude: the angle of ``R_sensor_target_nominal^T R`` is at most ``attitude_tol_rad``;
    - line of sight: the target origin lies inside the cone of half-angle
      ``boresight_half_angle_rad`` about the sensor +z (boresight) axis;
    - range: ``range_min_m <= |t| <= range_max_m``.

    Attributes:
        R_sensor_target_nominal: (3, 3) nominal attitude of the target in the sensor frame.
        attitude_tol_rad: attitude tolerance [rad], in (0, pi].
        boresight_half_angle_rad: half-angle of the line-of-sight cone [rad], in (0, pi].
        range_min_m: minimum range of the target origin [m], >= 0.
        range_max_m: maximum range [m], > range_min_m.
    """

    R_sensor_target_nominal: FloatArray
    attitude_tol_rad: float
    boresight_half_angle_rad: float
    range_min_m: float = 0.0
    range_max_m: float = math.inf

    def __post_init__(self) -> None:
        R = np.asarray(self.R_sensor_target_nominal, dtype=np.float64)
        if R.shape != (3, 3) or not np.all(np.isfinite(R)):
            raise ValueError(
                f"R_sensor_target_nominal has shape {R.shape}; expected a finite (3, 3) rotation"
            )
        if not (np.allclose(R.T @ R, np.eye(3), atol=1e-6) and abs(np.linalg.det(R) - 1) < 1e-6):
            raise ValueError("R_sensor_target_nominal is not a rotation (orthonormal, det +1)")
        self.R_sensor_target_nominal = R
        for name in ("attitude_tol_rad", "boresight_half_angle_rad"):
            v = float(getattr(self, name))
            if not (0.0 < v <= math.pi):
                raise ValueError(f"{name}={v}; expected an angle in (0, pi] [rad]")
            setattr(self, name, v)
        lo, hi = float(self.range_min_m), float(self.range_max_m)
        if not (lo >= 0.0 and hi > lo) or math.isnan(hi):
            raise ValueError(
                f"range_min_m={lo}, range_max_m={hi}; expected 0 <= range_min_m < range_max_m [m]"
            )
        self.range_min_m, self.range_max_m = lo, hi

    @classmethod
    def from_corridor(
        cls, cfg: CorridorConfig, R_sensor_target_nominal: npt.ArrayLike
    ) -> PoseConstraint:
        """The constraint of an approach corridor.

        ``cfg.half_angle_deg`` is the line-of-sight cone: the target origin must lie within that
        angle of the sensor boresight (+z); ``cfg.attitude_tolerance_deg`` bounds the attitude
        error about ``R_sensor_target_nominal``; the range limits are copied.
        """
        if not isinstance(cfg, CorridorConfig):
            raise ValueError(f"cfg is a {type(cfg).__name__}; expected a CorridorConfig")  # noqa: TRY004
        return cls(
            R_sensor_target_nominal=np.asarray(R_sensor_target_nominal, dtype=np.float64),
            attitude_tol_rad=math.radians(cfg.attitude_tolerance_deg),
            boresight_half_angle_rad=math.radians(cfg.half_angle_deg),
            range_min_m=float(cfg.min_range_m),
            range_max_m=float(cfg.max_range_m),
        )

    def attitude_ok(self, R: FloatArray, slack_rad: float = 0.0) -> npt.NDArray[np.bool_]:
        """(K,) True where the angle of ``R_nominal^T R_k`` is within tolerance (+ slack)."""
        # trace(Rn^T R) = sum of the element-wise product.
        tr = np.einsum("ij,kij->k", self.R_sensor_target_nominal, R)
        lim = math.cos(min(self.attitude_tol_rad + slack_rad, math.pi))
        return 0.5 * (tr - 1.0) >= lim - 1e-12

    def position_ok(self, t: FloatArray, slack_m: float = 0.0) -> npt.NDArray[np.bool_]:
        """(K,) True where positions (K, 3) [m] are in the cone and range interval (+ slack)."""
        r = np.linalg.norm(t, axis=1)
        in_range = (r >= self.range_min_m - slack_m) & (r <= self.range_max_m + slack_m)
        with np.errstate(invalid="ignore", divide="ignore"):
            cos_los = np.where(r > 0, t[:, 2] / r, 1.0)
            ang = np.arccos(np.clip(cos_los, -1.0, 1.0))
            ang_slack = np.where(r > 0, np.arcsin(np.clip(slack_m / r, 0.0, 1.0)), 0.0)
        return in_range & (ang <= self.boresight_half_angle_rad + ang_slack + 1e-12)

    def admits_batch(self, Ts: npt.ArrayLike) -> npt.NDArray[np.bool_]:
        """Vectorised :meth:`admits`: Ts (K, 4, 4) -> (K,) bool (non-finite poses are refused)."""
        T = np.asarray(Ts, dtype=np.float64)
        if T.ndim != 3 or T.shape[1:] != (4, 4):
            raise ValueError(f"Ts has shape {T.shape}; expected (K, 4, 4) transforms")
        finite = np.all(np.isfinite(T), axis=(1, 2))
        T = np.where(finite[:, None, None], T, np.eye(4))
        return finite & self.attitude_ok(T[:, :3, :3]) & self.position_ok(T[:, :3, 3])

    def admits(self, T: npt.ArrayLike) -> bool:
        """True when the pose ``T_sensor_target`` (4, 4) lies inside the corridor."""
        arr = np.asarray(T, dtype=np.float64)
        if arr.shape != (4, 4):
            raise ValueError(f"T has shape {arr.shape}; expected a (4, 4) transform")
        return bool(self.admits_batch(arr[None])[0])


# ---------------------------------------------------------------------------------------------
# Helpers
# ---------------------------------------------------------------------------------------------
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


def _ragged(starts: IntArray, ends: IntArray) -> tuple[IntArray, IntArray]:
    """Expand ranges ``[starts_k, ends_k)``: returns (owner k, index) of every element."""
    counts = np.maximum(ends - starts, 0)
    total = int(counts.sum())
    owner = np.repeat(np.arange(starts.shape[0]), counts)
    first = np.cumsum(counts) - counts
    pos = np.arange(total) - np.repeat(first, counts)
    return owner, starts[owner] + pos


def _kabsch_batch(
    S: FloatArray, Q: FloatArray | None, Qk: FloatArray | None = None
) -> tuple[FloatArray, FloatArray]:
    """Batched rigid fits ``Q ~= R S_k + t`` (eq. 1) of model polygons to one scan polygon.

    Args:
        S: (K, N, 3) model polygons [m], target frame.
        Q: (N, 3) scan polygon [m], sensor frame (or None with ``Qk``).
        Qk: (K, N, 3) one target point set per fit instead of ``Q``.

    Returns:
        R (K, 3, 3) proper rotations and t (K, 3) [m].
    """
    cs = S.mean(axis=1)
    if Qk is None:
        assert Q is not None
        Qk = np.broadcast_to(Q, S.shape)
    cq = Qk.mean(axis=1)
    H = np.einsum("kni,knj->kij", S - cs[:, None, :], Qk - cq[:, None, :])
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(np.einsum("kji,klj->kil", Vt, U)))
    d[d == 0] = 1.0
    Vt[:, 2, :] *= d[:, None]
    R = np.einsum("kji,klj->kil", Vt, U)
    t = cq - np.einsum("kij,kj->ki", R, cs)
    return R, t


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


# ---------------------------------------------------------------------------------------------
# Database
# ---------------------------------------------------------------------------------------------
_ARRAY_KEYS = ("points", "normals", "seg_i", "seg_j", "seg_len", "bin_ptr", "dist")


class PAHFileError(ValueError):
    """A PAH database file that cannot be used; the message is one line naming the file."""


@dataclass
class _Hypothesis:
    """A candidate pose after a short ICP, verified on the whole scan (:meth:`PAHDatabase._verify`).

    Attributes:
        T: (4, 4) pose ``T_sensor_target``.
        fitness: fraction of the scan points within their noise gate of the model surface.
        likelihood: mean Gaussian likelihood of the point-to-plane residuals (0 for outliers).
        free_space: fraction of the scan points measured behind the model surface along their
            ray (the ray would have been stopped by the model first): impossible under this pose.
        expanded: its near-symmetric alternatives have been verified too.
        settled: its short ICP converged (an unsettled pose, still sliding along a weakly
            observed direction, scores below what it would reach).
        polished: refined by a full ICP on every point (:meth:`PAHDatabase._polish`).
        free_space_beam: violation fraction judged over the beam footprint, once computed (it
            can only be lower than ``free_space``).
    """

    T: FloatArray
    fitness: float
    likelihood: float
    free_space: float
    expanded: bool = False
    settled: bool = True
    polished: bool = False
    free_space_beam: float | None = None

    @property
    def score(self) -> float:
        """Ranking score: likelihood, less a heavy price per unexplained or see-through point."""
        return self.likelihood - _UNEXPLAINED_PENALTY * ((1.0 - self.fitness) + self.free_space)

    def clean(self, accept_fitness: float, n_points: int) -> bool:
        """Explains the scan: ``accept_fitness`` of it fits and (almost) nothing sees through it.

        A few violations are tolerated (mixed returns at silhouettes): up to
        ``_FREE_SPACE_ACCEPT`` of the scan, and at least ``_FREE_SPACE_ACCEPT_POINTS`` points.
        """
        fs = self.free_space if self.free_space_beam is None else self.free_space_beam
        return self.fitness >= accept_fitness and fs <= _free_space_allowed(n_points)


class PAHDatabase:
    """PAH reference database of one target, and the runtime localization that uses it.

    Attributes:
        target: the target model (needed by :meth:`localize` for the fit check and ICP), or None
            for a database loaded without its target (see :meth:`attach`).
        config: the PAH settings it was built with.
        model_hash: the geometry hash of the target it was built on.
        target_name: the target's name.
        points: (M, 3) sparse model points ``S`` [m], target frame.
        normals: (M, 3) their unit outward normals.
        coverage_m: 90th percentile of the distance from a surface point to the nearest ``s_i``
            [m]: how far a scan point may be from its match in ``S``.
        seg_i, seg_j, seg_len: the length table: undirected segments (i < j) sorted by length [m].
        bin_ptr: (B + 1,) offsets into the sorted segments of each ``length_bin_m`` bin.
        dist: (M, M) the connectivity table: ``dist[i, j] = |s_i - s_j|`` [m].
    """

    def __init__(
        self,
        *,
        config: PAHConfig,
        model_hash: str,
        target_name: str,
        points: FloatArray,
        normals: FloatArray,
        coverage_m: float,
        seg_i: IntArray,
        seg_j: IntArray,
        seg_len: FloatArray,
        bin_ptr: IntArray,
        dist: FloatArray,
        target: TargetModel | None = None,
    ) -> None:
        self.config = config
        self.model_hash = model_hash
        self.target_name = target_name
        self.points = points
        self.normals = normals
        self.coverage_m = float(coverage_m)
        self.seg_i, self.seg_j, self.seg_len = seg_i, seg_j, seg_len
        self.bin_ptr = bin_ptr
        self.dist = dist
        self._cluster_cache: dict[float, tuple[IntArray, int]] = {}
        self._rows_cache: tuple[IntArray, FloatArray, FloatArray, float] | None = None
        self.max_length_m = float(seg_len[-1]) if seg_len.size else 0.0
        self.target: TargetModel | None = None
        if target is not None:
            self.attach(target)

    def __repr__(self) -> str:
        return (
            f"PAHDatabase(target={self.target_name!r}, points={self.points.shape[0]}, "
            f"segments={self.seg_len.shape[0]}, polygon_size={self.config.polygon_size})"
        )

    # -- offline --------------------------------------------------------------------------------
    @classmethod
    def build(
        cls, target: TargetModel, config: PAHConfig | None = None, seed: int = 0
    ) -> PAHDatabase:
        """Build the reference database of a target (seed 000 section 3.1.1).

        Args:
            target: the target model (library target or any loaded mesh).
            config: PAH settings; defaults when None.
            seed: seed of the deterministic surface sampling and subsampling.

        Returns:
            The database, holding a reference to ``target``.

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
        return cls(
            config=cfg, model_hash=target.model_hash, target_name=target.name, points=S,
            normals=N, coverage_m=coverage, seg_i=iu[order].astype(np.int64),
            seg_j=ju[order].astype(np.int64), seg_len=seg_len, bin_ptr=bin_ptr, dist=D,
            target=target,
        )

    def attach(self, target: TargetModel) -> None:
        """Attach the target the database was built on (its geometry hash must match).

        Raises:
            ValueError: not a TargetModel, or a target with different geometry.
        """
        if not isinstance(target, TargetModel):
            raise ValueError(f"target is a {type(target).__name__}; expected a TargetModel")  # noqa: TRY004
        if target.model_hash != self.model_hash:
            raise ValueError(
                f"target {target.name!r} has model hash {target.model_hash[:12]}...; this PAH "
                f"database was built on {self.target_name!r} ({self.model_hash[:12]}...)"
            )
        self.target = target

    def save(self, path: str | Path) -> Path:
        """Write the database to ``path`` (``.npz`` appended if missing; no pickles).

        Returns:
            The path written.
        """
        p = Path(path)
        if p.suffix != ".npz":
            p = p.with_name(p.name + ".npz")
        p.parent.mkdir(parents=True, exist_ok=True)
        arrays = {k: getattr(self, k) for k in _ARRAY_KEYS}
        np.savez(
            p,
            format_version=np.int64(PAH_FORMAT_VERSION),
            model_hash=np.str_(self.model_hash),
            target_name=np.str_(self.target_name),
            config_json=np.str_(self.config.model_dump_json()),
            coverage_m=np.float64(self.coverage_m),
            **arrays,
        )
        return p

    @classmethod
    def load(cls, path: str | Path, target: TargetModel | None = None) -> PAHDatabase:
        """Read a database written by :meth:`save`.

        Every entry is checked before use: each ``.npy`` header (dtype, shape, size against the
        archive) before its data is read, so a hostile header cannot make the loader allocate;
        then the values (finite, indices in range, the length table sorted and consistent with
        the connectivity table, ``bin_ptr`` the exact offsets of the length bins).

        Args:
            path: the ``.npz`` file.
            target: the target to attach; its geometry hash must match the database's.

        Raises:
            FileNotFoundError: no such file.
            PAHFileError: (a ValueError) not a PAH database, another format version, a corrupt
                file, or a target whose geometry differs from the one the database was built on.
                The message is one line naming the file (and the entry and its problem).
        """
        p = Path(path)
        if not p.is_file():
            raise FileNotFoundError(f"PAH database file {p} does not exist")
        meta, config, arrays = _read_database(p)
        db = cls(
            config=config, model_hash=meta["model_hash"], target_name=meta["target_name"],
            coverage_m=meta["coverage_m"], **arrays,
        )
        if target is not None:
            try:
                db.attach(target)
            except ValueError as exc:
                raise PAHFileError(f"PAH database {p}: {exc}") from None
        return db

    # -- runtime: polygon matching ---------------------------------------------------------------
    def match_polygon(
        self,
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
        (:meth:`_banded`).

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

        Args:
            Q: (N, 3) scan polygon [m], sensor frame.
            tolerance_m: distance tolerance per edge [m].
            rng: draws the subset kept when a level exceeds ``max_candidates``.
            R_nominal: (3, 3) nominal attitude for direction pruning (constrained search).
            direction_tol_rad: angle [rad] the rotated model edge ``R_nominal (s_k - s_0)`` may make
                with the scan edge ``q_k - q_0`` (the attitude tolerance; widened here by the length
                tolerance). Both or neither of ``R_nominal`` and this.
            constraint: approach corridor; implies the direction pruning with its nominal attitude
                and tolerance unless those are given.
            rays: (N, 3) unit ray directions of the scan vertices, sensor frame.
            merge_m: merge distance [m] of partial-match poses (None: no merging).

        Returns:
            (K, N) model-point indices, row k matching ``Q`` vertex by vertex.
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
        cap = int(self.config.max_candidates)
        S = self.points
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
            return np.einsum("kij,kj->ki", R, self.normals[idx]) @ ray_a[k] < _VISIBLE_COS

        # Level 1: the first edge, direct lookup by quantised length (both orientations).
        d = dq[0, 1]
        b = self.config.length_bin_m
        nb = self.bin_ptr.shape[0] - 1
        lo_b = min(int(max(d - tolerance_m, 0.0) // b), nb)
        hi_b = min(int((d + tolerance_m) // b), nb - 1)
        if hi_b < lo_b:
            return np.empty((0, n_poly), dtype=np.int64)
        sl = slice(int(self.bin_ptr[lo_b]), int(self.bin_ptr[hi_b + 1]))
        keep = np.abs(self.seg_len[sl] - d) <= tolerance_m
        a, c = self.seg_i[sl][keep], self.seg_j[sl][keep]
        cand = np.concatenate([np.stack([a, c], 1), np.stack([c, a], 1)])
        if proj is not None and cand.shape[0]:
            ln = np.concatenate([self.seg_len[sl][keep]] * 2)
            cand = cand[proj[cand[:, 1], 1] - proj[cand[:, 0], 1] >= lims[1] * ln]
        cand = self._cap(cand, cap, rng)
        # Further levels: AND of the banded connectivity rows of the matched vertices.
        for k in range(2, n_poly):
            if cand.shape[0] == 0:
                break
            owner, new = self._banded(cand, dq[:k, k], tolerance_m,
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
                cand = self._merge(cand, dq, merge_m)
            cand = self._cap(cand, cap, rng)
            if cand.shape[0] and (constraint is not None or ray_a is not None):
                cand = self._prune_partial(cand, Qa, dq, tolerance_m, constraint,
                                           visible if ray_a is not None else None)
        if cand.shape[0] == 0 or cand.shape[1] < n_poly:
            return np.empty((0, n_poly), dtype=np.int64)
        return cand

    def _banded(
        self, cand: IntArray, d: FloatArray, tol: float, proj: FloatArray | None = None,
        lim: float = 0.0,
    ) -> tuple[IntArray, IntArray]:
        """Next-vertex candidates of partial matches ``cand`` (K, k): the (owner o, point j) pairs
        with ``|dist[cand[o, v], j] - d[v]| <= tol`` for every matched vertex ``v`` and, with
        ``proj`` (M,) (the model points projected on the nominal edge direction), the edge from
        vertex 0 pointing that way: ``proj[j] - proj[cand[o, 0]] >= lim dist[cand[o, 0], j]``.
        Ordered by owner, then point (as ``np.nonzero`` over a dense (K, M) test).

        Vertex 0's band is a contiguous run of its row of the connectivity table sorted by length
        (:meth:`_sorted_rows`), found by one ``searchsorted`` for all partial matches; only those
        points are tested further. Cost O(K x band) instead of O(K x M).
        """
        order, sdist, keys, stride = self._sorted_rows()
        m = self.dist.shape[0]
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
            flat = self.dist.reshape(-1)
            ok = np.abs(flat[cand[owner, 1] * m + new] - d[1]) <= tol
            for v in range(2, d.shape[0]):
                ok &= np.abs(flat[cand[owner, v] * m + new] - d[v]) <= tol
            owner, new = owner[ok], new[ok]
        key = np.sort(owner * m + new)
        return key // m, key % m

    def _sorted_rows(self) -> tuple[IntArray, FloatArray, FloatArray, float]:
        """Rows of the connectivity table sorted by length, flattened: ``order`` (M * M,) point
        indices, ``sdist = dist[i, order]``, ``keys = i * stride + sdist`` (ascending) and
        ``stride`` [m]."""
        if self._rows_cache is None:
            m = self.dist.shape[0]
            srt = np.argsort(self.dist, axis=1, kind="stable")
            stride = 2.0 * float(self.dist.max()) + 1.0
            sdist = np.take_along_axis(self.dist, srt, axis=1)
            keys = sdist + stride * np.arange(m)[:, None]
            self._rows_cache = (srt.ravel().astype(np.int64), sdist.ravel(), keys.ravel(), stride)
        return self._rows_cache

    def _merge(self, cand: IntArray, dq: FloatArray, merge_m: float) -> IntArray:
        """One partial match (K, k) per tuple of model-point clusters: the best-fitting one."""
        k = cand.shape[1]
        cluster, n_clusters = self._clusters(merge_m)
        key = np.zeros(cand.shape[0], dtype=np.int64)
        for v in range(k):
            key = key * n_clusters + cluster[cand[:, v]]
        misfit = np.zeros(cand.shape[0])
        for i in range(k):
            for j in range(i + 1, k):
                misfit += np.abs(self.dist[cand[:, i], cand[:, j]] - dq[i, j])
        order = np.lexsort((misfit, key))
        ks = key[order]
        first = np.r_[True, ks[1:] != ks[:-1]]
        return cand[np.sort(order[first])]

    def _clusters(self, merge_m: float) -> tuple[IntArray, int]:
        """Model points grouped about farthest-point centres ``merge_m`` [m] apart: (M,) ids, count.

        Matches that differ only by neighbouring model points of one group give the same pose
        within the tolerance. Cached per merge distance (rounded to 1 cm).
        """
        key = max(round(merge_m, 2), 0.01)
        hit = self._cluster_cache.get(key)
        if hit is None:
            S = self.points
            centres = [0]
            d = np.linalg.norm(S - S[0], axis=1)
            while d.max() > key and len(centres) < S.shape[0]:
                centres.append(int(np.argmax(d)))
                d = np.minimum(d, np.linalg.norm(S - S[centres[-1]], axis=1))
            _, ids = cKDTree(S[centres]).query(S, k=1)
            hit = (ids.astype(np.int64), len(centres))
            self._cluster_cache[key] = hit
        return hit

    def _prune_partial(
        self,
        cand: IntArray,
        Q: FloatArray,
        dq: FloatArray,
        tol: float,
        constraint: PoseConstraint | None,
        visible: Callable[[int, IntArray, FloatArray], npt.NDArray[np.bool_]] | None,
    ) -> IntArray:
        """Corridor and visibility tests of partial matches (K, k >= 3) by their triangle poses."""
        k = cand.shape[1]
        Sk = self.points[cand]
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

    @staticmethod
    def _cap(cand: IntArray, cap: int, rng: np.random.Generator) -> IntArray:
        if cand.shape[0] <= cap:
            return cand
        return cand[np.sort(rng.choice(cand.shape[0], size=cap, replace=False))]

    def _fit_grid(self, threshold_m: float) -> _FitGrid:
        assert self.target is not None
        dense = prepare_model(self.target, _DENSE_POINTS)
        key = ("pah_fit_grid", round(threshold_m, 6), self.model_hash)
        return self.target.cached(key, lambda: _FitGrid.build(dense.points, threshold_m))

    # -- runtime: localization ---------------------------------------------------------------------
    def localize(
        self,
        points: npt.ArrayLike,
        rng: np.random.Generator,
        constraint: PoseConstraint | None = None,
        sigma: float | npt.ArrayLike | None = None,
        max_time_s: float | None = None,
        directions: npt.ArrayLike | None = None,
        *,
        search_points: int | None = None,
    ) -> RegistrationResult:
        """Find the target pose in a scan without an initial guess (seed 000 section 3.1.2).

        For each polygon: match it, fit a pose per match, drop mirror images, back-facing and
        (constrained) out-of-corridor poses, precheck the survivors on a decimated scan, check the
        best few on the whole scan (or the ``search_points`` subset), and polish the distinct
        best ones by a short ICP (one start per basin; on the subset, if any) scored on the
        whole scan, surface fit and free space (so that near-symmetric alternatives are
        compared, not the first one taken); the leader's near-symmetric alternatives are
        verified too. It stops when a verified leader scores ``accept_fitness`` with (almost) no
        free-space violation, or the polygon or time budget is spent; the best hypothesis, and
        runners-up in other basins, are then refined by a full ICP and the best verified one wins.

        Args:
            points: (N, 3) scan points [m], sensor frame (non-finite rows are ignored).
            rng: the only source of randomness (polygon seeds, decimation, candidate caps).
            constraint: approach corridor; candidates outside it are dropped before any fit check.
            sigma: range noise 1-sigma [m], a float or (N,) per point; default 0.01 m.
            max_time_s: wall-clock budget [s], checked before each polygon; when it runs out the
                best hypothesis so far is refined and returned with ``converged=False`` unless it
                explains the scan. None: :data:`DEFAULT_TIME_BUDGET_S` unconstrained,
                :data:`DEFAULT_CONSTRAINED_TIME_BUDGET_S` with a constraint; ``math.inf``: none.
                A budget makes the result depend on the machine's speed when it runs out.
            directions: (N, 3) measured ray directions [sensor frame] (``PointCloud.directions``);
                default: the lines of sight ``points / |points|``. Every ICP matches points to
                the face their ray crosses, and the free-space test casts these rays.
            search_points: when the scan has more points, the fit check of the best matches and
                the short screening ICPs (the stages whose cost grows with the scan) run on a
                random subset of this many points (drawn from ``rng``); polygons are picked from,
                and every hypothesis is verified and the final ICP run on, all the points. Meant
                for scans pooled in a corridor (:meth:`localize_scans`), where one scan's worth of
                points finds the candidates and the rest tell them apart and refine the winner.
                None: all points everywhere.

        Returns:
            The ICP-refined :class:`RegistrationResult` of the best hypothesis; ``iterations`` is
            the ICP's. ``reason`` is empty when its score reached ``accept_fitness`` (inside the
            corridor, if any), otherwise it says why not. A scan too small or degenerate to
            localize, or one no polygon matched, gives ``RegistrationResult.failure``.

        Raises:
            ValueError: points not (N, 3), ``rng`` not a Generator, a bad ``constraint``,
                ``sigma``, ``max_time_s``, ``directions`` or ``search_points``, or a database
                without a target.
        """
        t_start = time.perf_counter()
        P_all = validate_points(points, "points")
        if not isinstance(rng, np.random.Generator):
            raise ValueError(f"rng={rng!r}; expected a numpy.random.Generator")  # noqa: TRY004
        if constraint is not None and not isinstance(constraint, PoseConstraint):
            raise ValueError(f"constraint is a {type(constraint).__name__}; expected PoseConstraint")
        if max_time_s is None:
            max_time_s = (
                DEFAULT_TIME_BUDGET_S if constraint is None else DEFAULT_CONSTRAINED_TIME_BUDGET_S
            )
        if not (
            isinstance(max_time_s, (int, float)) and not math.isnan(max_time_s) and max_time_s > 0
        ):
            raise ValueError(
                f"max_time_s={max_time_s!r}; expected a budget > 0 [s] (math.inf: none) or None"
            )
        if search_points is not None and not (
            isinstance(search_points, (int, np.integer)) and not isinstance(search_points, bool)
            and search_points >= 1
        ):
            raise ValueError(f"search_points={search_points!r}; expected an int >= 1 or None")
        if self.target is None:
            raise ValueError(
                f"PAH database of {self.target_name!r} has no target; pass target= to load() or "
                "call attach(target)"
            )
        sig_all = per_point_sigma(sigma, P_all.shape[0])
        ok = np.all(np.isfinite(P_all), axis=1) & np.isfinite(sig_all)
        if directions is not None:
            D_all = np.asarray(directions, dtype=np.float64)
            if D_all.shape != P_all.shape:
                raise ValueError(
                    f"directions has shape {D_all.shape}; expected {P_all.shape} like points"
                )
            with np.errstate(invalid="ignore", divide="ignore"):
                D_all = D_all / np.linalg.norm(D_all, axis=1, keepdims=True)
            ok &= np.all(np.isfinite(D_all), axis=1)
        P = np.ascontiguousarray(P_all[ok])
        sig = sig_all[ok]
        n = P.shape[0]
        cfg = self.config
        n_poly = int(cfg.polygon_size)
        min_pts = max(2 * n_poly, 10)

        def elapsed() -> float:
            return time.perf_counter() - t_start

        if n < min_pts:
            return RegistrationResult.failure(
                f"{n} finite scan points (of {P_all.shape[0]}); PAH needs >= {min_pts}",
                n_points=n, time_s=elapsed(),
            )
        rng_norm = np.linalg.norm(P, axis=1)
        if float(np.ptp(P, axis=0).max()) < 1e-6 or np.any(rng_norm < 1e-9):
            return RegistrationResult.failure(
                "scan points coincide or sit on the sensor origin; PAH needs a spread-out cloud",
                n_points=n, time_s=elapsed(),
            )
        sig_med = float(np.median(sig))
        # A scan vertex lies up to `coverage` from its model point, plus range noise on each end.
        tol = max(float(cfg.length_tolerance_m), self.coverage_m) + 2.0 * sig_med
        fit_thr = max(float(cfg.fit_inlier_m), 3.0 * sig_med)
        grid = self._fit_grid(max(float(cfg.fit_inlier_m), self.coverage_m))
        mc = prepare_model(self.target, _DENSE_POINTS)
        pre = P[rng.choice(n, size=min(n, int(cfg.precheck_points)), replace=False)]
        pre_a = pre[: max(10, int(cfg.precheck_points) // 4)]
        # The measured rays when given, else the lines of sight: ICP matches each point to the
        # face its ray crosses, and the free-space test casts them. Per-point inlier distance of
        # the hypothesis score: noise plus model sampling.
        scan = _Scan.build(P, sig, None if directions is None else np.ascontiguousarray(D_all[ok]),
                           mc.spacing, ranges=rng_norm)
        rays = scan.rays
        search = scan
        if search_points is not None and search_points < n:
            # The O(n) stages of the search on a random subset (see search_points).
            sub = np.sort(rng.choice(n, size=max(int(search_points), min_pts), replace=False))
            search = scan.subset(sub)
        max_extent = self.max_length_m + 2.0 * tol
        screen_cfg = ICPConfig(max_iterations=_SCREEN_ICP_ITERATIONS)
        # Polygon vertices come from points with scan neighbours: a stray return floats alone,
        # and the far-apart vertex choice would otherwise pick it first (it is still scored).
        pool = _supported(P)
        if pool.size < n_poly:
            pool = np.arange(n)

        hyps: list[_Hypothesis] = []
        best: _Hypothesis | None = None
        n_cands = n_admitted = polygons = 0
        stop = ""
        for _ in range(int(cfg.max_polygons)):
            if elapsed() > max_time_s:
                stop = f"time budget {max_time_s:.3g} s spent after {polygons} polygons"
                break
            polygons += 1
            poly = _pick_polygon(P[pool], n_poly, max_extent, rng)
            if poly is None:
                continue
            poly = pool[poly]
            Q = P[poly]
            # Constrained, the corridor and visibility prune the tree and near-identical matches
            # merge at the first triangle; unconstrained, all poses are plausible, that pruning
            # costs more than it saves, and the fit checks below take the many matches in stride.
            if constraint is None:
                cand = self.match_polygon(Q, tol, rng)
            else:
                cand = self.match_polygon(Q, tol, rng, constraint=constraint, rays=rays[poly],
                                          merge_m=_MERGE_FRACTION * tol)
            n_cands += cand.shape[0]
            if cand.shape[0] == 0:
                continue
            # Cheap poses from the first triangle for pruning; SVD only for the survivors.
            R, t = _triangle_poses(self.points[cand], Q)
            keep = self._plausible(R, t, cand, Q, rays[poly], tol, constraint)
            cand, R, t = cand[keep], R[keep], t[keep]
            if cand.shape[0] == 0:
                continue
            score_a = grid.inside(_to_model(pre_a, R, t)).mean(axis=1)
            top = np.argsort(-score_a, kind="stable")[:_PRECHECK_KEEP]
            cand = cand[top]
            R, t = _kabsch_batch(self.points[cand], Q)
            resid = Q[None] - (np.einsum("kij,knj->kni", R, self.points[cand]) + t[:, None, :])
            keep = np.sqrt(np.mean(np.sum(resid**2, axis=2), axis=1)) <= tol
            keep &= self._plausible(R, t, cand, Q, rays[poly], tol, constraint)
            R, t = R[keep], t[keep]
            n_admitted += R.shape[0]
            if R.shape[0] == 0:
                continue
            score_b = grid.inside(_to_model(pre, R, t)).mean(axis=1)
            top = np.argsort(-score_b, kind="stable")[:_FULL_CHECK]
            # Full O(n) check of the best few on the dense model's KD-tree.
            dist, _ = mc.kdtree.query(_to_model(search.P, R[top], t[top]).reshape(-1, 3), k=1,
                                      distance_upper_bound=fit_thr)
            fit = np.isfinite(dist).reshape(top.size, search.P.shape[0]).mean(axis=1)
            order = np.argsort(-fit, kind="stable")
            starts = []
            for j in order[:_SCREEN_PER_POLYGON]:
                if fit[j] < 0.5 * fit[order[0]] or (best is not None and fit[j] < 0.5 * best.fitness):
                    break
                T0 = _pose(R[top[j]], t[top[j]])
                if not any(_same_pose(T0, h.T) for h in hyps):
                    starts.append(T0)
            new = self._screen(scan, starts, hyps, mc, screen_cfg, search)
            hyps += new
            best = _best(hyps, constraint)
            # Verify the leader against the poses it could be confused with (half turns of a
            # long body, quarter turns of a square one): one of them may be the truth.
            if best is not None and not best.expanded:
                best.expanded = True
                hyps += self._alternatives(best, scan, hyps, mc, screen_cfg, constraint, search)
                best = _best(hyps, constraint)
            if best is not None:
                self._beam_check(scan, best, mc)
            # A leader whose short ICP was still sliding may explain the scan once settled:
            # polish it on every point before paying for another polygon.
            if (best is not None and not best.settled and not best.polished
                    and not best.clean(cfg.accept_fitness, n)):
                self._polish(scan, best, mc)
                best = _best(hyps, constraint)  # None if polishing left the corridor
                if best is not None:
                    self._beam_check(scan, best, mc)
            if best is not None and best.expanded and best.clean(cfg.accept_fitness, n):
                break
        if best is None:
            why = (
                f"no admissible candidate in {polygons} polygons ({n_cands} matches, "
                f"{n_admitted} passed the pose checks)"
            )
            why = f"{stop}; {why}" if stop else why
            return RegistrationResult.failure(why, n_points=n, time_s=elapsed(),
                                              iterations=polygons)
        res, final_fit, final_fs = self._refine(scan, hyps, best, mc, constraint)
        notes = []
        if final_fit < cfg.accept_fitness:
            notes.append(f"fit score {final_fit:.2f} < accept_fitness {cfg.accept_fitness:.2f}")
        if final_fs > _free_space_allowed(n):
            notes.append(f"{100 * final_fs:.1f} % of the points lie behind the model surface")
        if constraint is not None and not constraint.admits(res.T_sensor_target):
            notes.append("refined pose outside the corridor")
        if notes:
            res.reason = "; ".join([*notes, *(s for s in (stop, res.reason) if s)])
            if stop:
                # Out of time before any hypothesis explained the scan: the pose is a best
                # guess, not an acquisition.
                res.converged = False
        elif not res.converged:
            res.reason = res.reason or "ICP refinement did not converge"
        res.time_s = elapsed()
        return res

    def localize_scans(
        self,
        scans: Sequence[PointCloud],
        rng: np.random.Generator,
        constraint: PoseConstraint | None = None,
        max_time_s: float | None = None,
    ) -> RegistrationResult:
        """Localize from several successive scans of the same relative pose (more data, one pose).

        Seed 000 section 3.1.2: "it is possible to repeat the process ... from newly acquired point
        clouds over time ... to increase the probability of success". The scans must see the
        target at one pose in one sensor frame (a station-keeping chaser and a target that does
        not turn appreciably over the scans, or scans already compensated for the motion): their
        points, noise and measured rays are pooled and localized as one cloud by
        :meth:`localize`: polygons are picked from the pooled cloud, and every hypothesis is
        verified (surface fit and free space) and the final ICP run on all of it. Two or three
        scans halve the pose noise of a sparse scan's ICP and sample more of the small features
        (antenna, port ring, nozzle) that tell a box-shaped body from its quarter and half turns.

        With a ``constraint``, the search's work per candidate, the fit check of the best matches
        and the short screening ICPs, runs on a random subset of the pooled points the size of
        the largest scan (``search_points`` of :meth:`localize`), so that K scans cost little more
        than one: the corridor leaves few candidates, all near the nominal attitude, and one
        scan's worth of points finds them; the pool then decides between them and refines the
        winner (acquisition benchmark, 3 scans, 200 cases per target: 100 % success either way;
        median 0.052 -> 0.038 s on the cubesat, 0.044 -> 0.033 s on CYGNSS). Unconstrained the
        whole pool is searched: there the screening ICPs on the subset ended in wrong basins (or
        the time budget ran out) more often, 97.5 % against 99.5 % success on the cubesat.

        Nothing here checks that the scans share one pose (the fit of a box turned by 15 deg
        between scans hardly drops): pool only scans the caller knows to be of one pose.

        Args:
            scans: one or more :class:`~perception.sensing.pointcloud.PointCloud` (``points``, ``sigma``,
                ``directions`` are used).
            rng, constraint, max_time_s: as for :meth:`localize` (the budget covers all scans).

        Returns:
            As :meth:`localize`; ``n_points`` counts the pooled points.

        Raises:
            ValueError: ``scans`` empty or not PointClouds, and everything :meth:`localize` raises.
        """
        if isinstance(scans, PointCloud):
            scans = [scans]
        if not isinstance(scans, Sequence) or len(scans) == 0:
            raise ValueError(f"scans is {type(scans).__name__}; expected a non-empty sequence of "
                             "PointCloud")
        for i, c in enumerate(scans):
            if not isinstance(c, PointCloud):
                raise ValueError(f"scans[{i}] is a {type(c).__name__}; expected a PointCloud")  # noqa: TRY004
        P = np.concatenate([c.points for c in scans])
        sig = np.concatenate([np.broadcast_to(np.asarray(c.sigma, dtype=np.float64), (len(c),))
                              for c in scans])
        D = np.concatenate([c.directions for c in scans])
        # In a corridor the search works on one scan's worth of the pooled points (verification
        # and the final ICP on all of them); unconstrained it searches them all (see above).
        search = max(len(c) for c in scans) if constraint is not None else None
        res = self.localize(P, rng, constraint=constraint, sigma=sig, max_time_s=max_time_s,
                            directions=D, search_points=search)
        return res

    def _refine(
        self,
        scan: _Scan,
        hyps: list[_Hypothesis],
        best: _Hypothesis,
        mc: ModelCloud,
        constraint: PoseConstraint | None,
    ) -> tuple[RegistrationResult, float, float]:
        """Full ICP from the leader and from runners-up in other basins; the best verified wins.

        After the short screening ICP a near-symmetric pose (the quarter turn of a square body,
        the flip of a long one) can trail the truth by a hair, or lead it; refined fully, the
        truth usually fits better. Runners-up at least ``_BASIN_RAD`` / ``_BASIN_M`` from every
        start are refined too (at most ``_FINAL_STARTS`` starts), and all results are verified in
        one batch. A runner-up is within ``_RUNNER_UP_MARGIN`` of the leader's score, or its short
        ICP did not settle and it fits ``_UNSETTLED_FIT`` of the leader's fit; those that fit more
        of the scan than the leader go first, then the unsettled ones, then by score.

        Returns:
            The winning ICP result, its fit score and its free-space violation fraction.
        """
        # A hypothesis that fits more of the scan than the leader, or nearly as much with its
        # short ICP still sliding along a weakly observed direction, trails only because its
        # pose is unpolished (that costs likelihood and free space); without priority the
        # leader's twins, which fit less, would take every start.
        ranked = sorted(
            (h for h in hyps if (constraint is None or constraint.admits(h.T))
             and (h.score >= best.score - _RUNNER_UP_MARGIN
                  or (not h.settled and h.fitness >= _UNSETTLED_FIT * best.fitness))),
            key=lambda h: (h.fitness <= best.fitness, h.settled, -h.score),
        )
        starts = [best]
        for h in ranked:
            if len(starts) >= _FINAL_STARTS:
                break
            if not any(_same_pose(h.T, u.T, _BASIN_M, _BASIN_RAD) for u in starts):
                starts.append(h)
        results = []
        for h in starts:
            r = icp(scan.P, mc, h.T, sigma=scan.sigma, directions=scan.rays, match_along_rays=True)
            if not r.converged:
                # Slow convergence along a weakly observed direction: one more pass.
                r = icp(scan.P, mc, r.T_sensor_target, sigma=scan.sigma, directions=scan.rays,
                        match_along_rays=True)
            results.append(r)
        Ts = np.stack([r.T_sensor_target for r in results])
        fit, like, fs = self._verify(scan, Ts, mc)
        score = like - _UNEXPLAINED_PENALTY * ((1.0 - fit) + fs)
        if constraint is not None:
            inside = constraint.admits_batch(Ts)
            if inside.any():
                score = np.where(inside, score, -np.inf)
        k = int(np.argmax(score))
        fs_k = float(fs[k])
        if fs_k > _free_space_allowed(scan.P.shape[0]):
            fs_k = float(self._verify(scan, Ts[k : k + 1], mc, footprint=True)[2][0])
        return results[k], float(fit[k]), fs_k

    def _screen(
        self,
        scan: _Scan,
        starts: list[FloatArray],
        known: list[_Hypothesis],
        mc: ModelCloud,
        icp_cfg: ICPConfig,
        icp_scan: _Scan | None = None,
    ) -> list[_Hypothesis]:
        """Short ICP from each start pose (on ``icp_scan``, default ``scan``), then one batched
        verification of the distinct results on ``scan``.

        A start within ``_BASIN_M`` / ``_BASIN_RAD`` of an earlier start or of its result is in
        that basin and is skipped (its ICP would slide to the same pose, a duplicate dropped
        anyway): the best few matches of a polygon are usually neighbouring model points.
        """
        Ts: list[FloatArray] = []
        settled: list[bool] = []
        sc = scan if icp_scan is None else icp_scan
        tried: list[FloatArray] = []
        for T0 in starts:
            # A start in the basin of one already polished (near it or its result) would only
            # slide to the same pose.
            if any(_same_pose(T0, U, _BASIN_M, _BASIN_RAD) for U in tried):
                continue
            r = icp(sc.P, mc, T0, sigma=sc.sigma, config=icp_cfg, directions=sc.rays,
                    match_along_rays=True)
            T = r.T_sensor_target
            tried += [T0, T]
            if not any(_same_pose(T, h.T) for h in known) and not any(_same_pose(T, U) for U in Ts):
                Ts.append(T)
                settled.append(r.converged)
        if not Ts:
            return []
        fit, like, fs = self._verify(scan, np.stack(Ts), mc)
        return [_Hypothesis(T, float(a), float(b), float(c), settled=ok)
                for T, a, b, c, ok in zip(Ts, fit, like, fs, settled)]

    def _beam_check(self, scan: _Scan, h: _Hypothesis, mc: ModelCloud) -> None:
        """Judge the violations of a hypothesis that fails acceptance on them over the footprint."""
        if h.free_space_beam is None and h.free_space > _free_space_allowed(scan.P.shape[0]):
            h.free_space_beam = float(self._verify(scan, h.T[None], mc, footprint=True)[2][0])

    def _polish(self, scan: _Scan, h: _Hypothesis, mc: ModelCloud) -> None:
        """Full ICP of a hypothesis on every scan point, verified; updates ``h`` in place.

        The short screening ICP (12 iterations) can leave a pose a few degrees short of its
        basin's bottom, where a tight noise gate (triangulation range) sees points behind the
        surface; settled, it may explain the scan outright.
        """
        r = icp(scan.P, mc, h.T, sigma=scan.sigma, directions=scan.rays, match_along_rays=True)
        fit, like, fs = self._verify(scan, r.T_sensor_target[None], mc)
        h.T = r.T_sensor_target
        h.fitness, h.likelihood, h.free_space = float(fit[0]), float(like[0]), float(fs[0])
        h.settled, h.polished, h.free_space_beam = bool(r.converged), True, None

    def _alternatives(
        self,
        h: _Hypothesis,
        scan: _Scan,
        known: list[_Hypothesis],
        mc: ModelCloud,
        icp_cfg: ICPConfig,
        constraint: PoseConstraint | None,
        icp_scan: _Scan | None = None,
    ) -> list[_Hypothesis]:
        """The near-symmetric alternatives of a hypothesis, polished and verified.

        Each alternative is ``h.T`` composed with a near-symmetry of the model; the raw poses are
        verified in one batch, and those that fit at least half as well as ``h`` are polished by
        the short ICP and verified again. They are not marked expanded: the alternatives of an
        alternative that takes the lead are verified in turn (duplicates of known hypotheses are
        dropped, so this ends).
        """
        G = self._near_symmetries()
        if G.shape[0] == 0:
            return []
        Ts = np.einsum("ij,kjl->kil", h.T, G)
        if constraint is not None:
            # Loose: the short ICP may still pull a nearly admitted alternative inside.
            Ts = Ts[constraint.attitude_ok(Ts[:, :3, :3], slack_rad=0.1)
                    & constraint.position_ok(Ts[:, :3, 3], slack_m=0.1)]
            if Ts.shape[0] == 0:
                return []
        # A near-symmetry maps the surface onto itself only to within _SYMMETRY_GATE_M (a turn
        # fitted to the whole model, wing and all, is a few cm and degrees off the turn of the
        # part the scan sees): judged with the plain gate, the alternative that is the truth can
        # fit a fifth of the scan before its short ICP and fit all of it after.
        loose = dataclasses.replace(scan, gate=scan.gate + _SYMMETRY_GATE_M)
        fit, _, _ = self._verify(loose, Ts, mc, free_space=False)
        order = np.argsort(-fit, kind="stable")[:_ALTERNATIVES_SCREENED]
        starts = [Ts[i] for i in order if fit[i] >= 0.5 * h.fitness]
        return self._screen(scan, starts, known, mc, icp_cfg, icp_scan)

    def _verify(
        self, scan: _Scan, Ts: FloatArray, mc: ModelCloud, free_space: bool = True,
        footprint: bool = False,
    ) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Surface fit and free-space test of K poses on the whole scan (vectorised).

        Surface fit: each point, moved into the model frame, is an inlier when within its gate
        ``scan.gate`` of a dense model sample; inliers add ``exp(-r^2 / 2 sigma^2)`` of their
        point-to-plane residual ``r`` to the likelihood (it sees small features that a noise-wide
        gate cannot). Free space: every scan ray is cast against the model under each pose (one
        Embree call for all K poses); a point measured more than ``scan.margin`` beyond the first
        model surface on its ray is impossible under that pose, since the surface would have
        returned the pulse (or, specular or dark, absorbed it) before it got there. The beam
        has a footprint: with ``footprint`` a point counts as a violation only when the rays on
        the footprint's rim (``_FOOTPRINT_HALF_ANGLE_RAD`` off its axis) all meet the model in
        front of it too (a footprint straddling an edge or a dark face echoes from behind). The
        ranking uses the centre ray (an edge a pose puts in a beam's way is weak evidence against
        it); whether a pose explains the scan is judged over the footprint
        (:meth:`_Hypothesis.clean`), so that beam effects never reject the truth.

        Args:
            scan: the scan bundle.
            Ts: (K, 4, 4) poses ``T_sensor_target``.
            mc: the dense model.
            free_space: run the ray test (else its column is zero).
            footprint: count a violation only when the whole beam footprint sees it (below).

        Returns:
            fitness (K,), likelihood (K,) and free-space violation fraction (K,).
        """
        assert self.target is not None
        n = scan.P.shape[0]
        k = Ts.shape[0]
        R, t = Ts[:, :3, :3], Ts[:, :3, 3]
        X = _to_model(scan.P, R, t)
        d, j = mc.kdtree.query(X.reshape(-1, 3), k=1, distance_upper_bound=float(scan.gate.max()))
        d, j = d.reshape(k, n), j.reshape(k, n)
        inl = d <= scan.gate
        jj = np.where(inl, j, 0)
        r = np.einsum("kni,kni->kn", X - mc.points[jj], mc.normals[jj])
        like = np.where(inl, np.exp(-0.5 * (r / scan.sigma) ** 2), 0.0).mean(axis=1)
        fs = np.zeros(k)
        if free_space:
            origins = -np.einsum("ki,kij->kj", t, R)
            dirs = np.einsum("ni,kij->knj", scan.rays, R).reshape(-1, 3)
            _, r_model, _ = cast_rays(self.target, np.repeat(origins, n, axis=0), dirs)
            r_model = r_model.reshape(k, n)
            with np.errstate(invalid="ignore"):
                behind = scan.ranges > r_model + scan.margin
            kk, ii = np.nonzero(behind)
            if footprint and kk.size and _FOOTPRINT_HALF_ANGLE_RAD > 0:
                # The beam is a footprint, not a line: where part of it passes an edge (or falls
                # on a dark or specular face that returns nothing) the first echo comes from
                # behind the surface the centre ray meets. A violation must hold for the whole
                # footprint: every rim ray meets the model in front of the measured range.
                rim = _rim_rays(scan.rays[ii], _FOOTPRINT_HALF_ANGLE_RAD)  # (m, F, 3)
                rim_t = np.einsum("mfi,mij->mfj", rim, R[kk]).reshape(-1, 3)
                f = rim.shape[1]
                _, r_rim, _ = cast_rays(self.target, np.repeat(origins[kk], f, axis=0), rim_t)
                with np.errstate(invalid="ignore"):
                    deep = scan.ranges[ii, None] > r_rim.reshape(-1, f) + scan.margin[ii, None]
                behind[kk, ii] = deep.all(axis=1)
            fs = behind.mean(axis=1)
        return inl.mean(axis=1), like, fs

    def verify_poses(
        self, points: FloatArray, sigma: float | FloatArray, Ts: FloatArray,
        directions: FloatArray | None = None,
    ) -> tuple[FloatArray, FloatArray]:
        """Fitness and score of K candidate poses on a scan, as PAH ranks its hypotheses.

        The score is the mean Gaussian likelihood of the point-to-plane residuals minus
        ``2 x`` (outlier fraction + free-space violation fraction): a point the pose leaves
        unexplained, or one measured behind the model's first surface on its ray, is evidence
        against it.

        Args:
            points: (n, 3) finite scan points [m], sensor frame.
            sigma: range noise, scalar or (n,) [m].
            Ts: (K, 4, 4) poses ``T_sensor_target``.
            directions: (n, 3) ray directions (default: the lines of sight).

        Returns:
            ``(fitness, score)``, each (K,).
        """
        if self.target is None:
            raise ValueError("verify_poses() needs the target: build() or load(path, target)")
        P = np.asarray(points, dtype=np.float64)
        sig = per_point_sigma(sigma, P.shape[0])
        mc = prepare_model(self.target, _DENSE_POINTS)
        rays = None if directions is None else np.asarray(directions, dtype=np.float64)
        scan = _Scan.build(P, sig, rays, mc.spacing)
        fit, like, fs = self._verify(scan, np.asarray(Ts, dtype=np.float64).reshape(-1, 4, 4), mc)
        return fit, like - _UNEXPLAINED_PENALTY * ((1.0 - fit) + fs)

    def near_symmetries(self) -> FloatArray:
        """(S, 4, 4) rigid motions ``G`` of the target frame that nearly map the model onto itself.

        ``T @ G`` is a pose that a partial scan may fit about as well as ``T`` (the half turn of a
        two-winged bus about its port axis). Needs the database's target; cached on it.
        """
        if self.target is None:
            raise ValueError("near_symmetries() needs the target: build() or load(path, target)")
        return self._near_symmetries()

    def _near_symmetries(self) -> FloatArray:
        """(S, 4, 4) rigid motions ``G`` of the target frame that nearly map the model onto itself.

        Candidates are the 23 turns of the cube group about the centroid (quarter and half turns
        about the axes, half turns about the face diagonals, third turns about the body
        diagonals), in the frame of the principal axes of the surface and in the body frame; a
        candidate is kept when it maps at least
        ``_SYMMETRY_OVERLAP`` of the surface to within ``_SYMMETRY_GATE_M`` of the surface
        (best first, at most ``_MAX_SYMMETRIES``). ``T @ G`` is then a pose a partial scan may
        fit as well as ``T``. Cached on the target.
        """
        assert self.target is not None
        mc = prepare_model(self.target, _DENSE_POINTS)

        def build() -> FloatArray:
            X = mc.points[:: max(1, mc.points.shape[0] // _SYMMETRY_SAMPLES)]
            c = X.mean(axis=0)
            _, V = np.linalg.eigh(np.cov((X - c).T))
            V[:, 2] *= np.sign(np.linalg.det(V))
            rots: list[FloatArray] = []
            for F in (V, np.eye(3)):
                for C in _CUBE_GROUP:
                    Rk = F @ C @ F.T
                    if np.trace(Rk) < _TURN_MIN_TRACE and all(
                        np.sum(Rk * Q) < _TURN_MIN_TRACE for Q in rots
                    ):
                        rots.append(Rk)
            G = np.stack([_pose(Rk, c - Rk @ c) for Rk in rots])
            # A few point-to-point ICP steps: the turn that fits best need not be about the
            # centroid (an off-centre wing moves it), nor exactly about the axis.
            for _ in range(_SYMMETRY_ICP_STEPS):
                Y = np.einsum("kij,nj->kni", G[:, :3, :3], X) + G[:, None, :3, 3]
                _, j = mc.kdtree.query(Y.reshape(-1, 3), k=1)
                Rs, ts = _kabsch_batch(np.broadcast_to(X, Y.shape), None,
                                       mc.points[j].reshape(Y.shape))
                G = np.stack([_pose(Ri, ti) for Ri, ti in zip(Rs, ts)])
            Y = np.einsum("kij,nj->kni", G[:, :3, :3], X) + G[:, None, :3, 3]
            d, _ = mc.kdtree.query(Y.reshape(-1, 3), k=1, distance_upper_bound=_SYMMETRY_GATE_M)
            overlap = np.isfinite(d).reshape(len(rots), -1).mean(axis=1)
            keep: list[int] = []
            for i in np.argsort(-overlap, kind="stable"):
                Ri = G[i, :3, :3]
                # Distinct turns only (the steps may have slid two onto one, or back to identity).
                if overlap[i] >= _SYMMETRY_OVERLAP and np.trace(Ri) < _TURN_MIN_TRACE and all(
                    np.sum(Ri * G[k, :3, :3]) < _TURN_MIN_TRACE for k in keep
                ):
                    keep.append(int(i))
            # With every turn its inverse: a leader a quarter turn off needs the opposite turn.
            turns: list[FloatArray] = []
            for Gi in G[keep[:_MAX_SYMMETRIES]]:
                for Gj in (Gi, np.linalg.inv(Gi)):
                    if all(np.sum(Gj[:3, :3] * U[:3, :3]) < _TURN_MIN_TRACE for U in turns):
                        turns.append(Gj)
            out = np.ascontiguousarray(np.stack(turns)) if turns else np.empty((0, 4, 4))
            out.setflags(write=False)
            return out

        return self.target.cached(("pah_near_symmetries", self.model_hash), build)  # type: ignore[no-any-return]

    def _plausible(
        self,
        R: FloatArray,
        t: FloatArray,
        cand: IntArray,
        Q: FloatArray,
        rays: FloatArray,
        tol: float,
        constraint: PoseConstraint | None,
    ) -> npt.NDArray[np.bool_]:
        """(K,) poses whose matched model normals face the sensor and that lie in the corridor."""
        nrm_s = np.einsum("kij,knj->kni", R, self.normals[cand])
        keep = np.all(np.einsum("kni,ni->kn", nrm_s, rays) < _VISIBLE_COS, axis=1)
        if constraint is not None:
            slack = math.atan(2.0 * tol / max(_diameter(Q), 1e-9))
            keep &= constraint.attitude_ok(R, slack_rad=slack)
            keep &= constraint.position_ok(t, slack_m=tol)
        return keep


# Partial polygon matches whose poses agree within this fraction of the length tolerance merge.
_MERGE_FRACTION = 1.0
# Candidates kept after the first (quarter-size) precheck, and sent on to the full check.
_PRECHECK_KEEP = 256
_FULL_CHECK = 16
# Distinct hypotheses per polygon polished by a short ICP, and that ICP's iterations.
_SCREEN_PER_POLYGON = 3
_SCREEN_ICP_ITERATIONS = 12
# Free-space test: a point further than 3 sigma + this [m] behind the model surface along its
# ray is a violation (the margin absorbs mixed returns of the beam footprint at silhouettes).
_FREE_SPACE_MARGIN_M = 0.02
# ... and only if the rays about it on the rim of the beam footprint, this far off its axis
# [rad], all see it behind the surface too (TriDAR beam: 0.5 mrad full divergence, plus
# pointing quantisation and jitter); _FOOTPRINT_RAYS of them.
_FOOTPRINT_HALF_ANGLE_RAD = 3e-4
_FOOTPRINT_RAYS = 6
# A hypothesis with more violations than this fraction of the scan is not accepted outright.
_FREE_SPACE_ACCEPT = 0.02
_FREE_SPACE_ACCEPT_POINTS = 3.5
# Score price of an outlier or a free-space violation, in units of one point's likelihood (<= 1):
# a missing or see-through point is evidence against the pose, not just a poorer fit.
_UNEXPLAINED_PENALTY = 2.0
# Near-symmetries: rotations of the model about its centroid that map at least this fraction of
# its surface to within _SYMMETRY_GATE_M of itself; at most _MAX_SYMMETRIES are kept.
_SYMMETRY_OVERLAP = 0.6
_SYMMETRY_GATE_M = 0.05
_MAX_SYMMETRIES = 10
_SYMMETRY_SAMPLES = 600
# Two rotations closer than ~25 deg (trace of R_a^T R_b above this) count as one turn.
_TURN_MIN_TRACE = 1.0 + 2.0 * math.cos(math.radians(25.0))
_SYMMETRY_ICP_STEPS = 6
# Final refinement: runners-up within this score of the leader, in another basin (farther than
# _BASIN_M or _BASIN_RAD from every start), get the full ICP too; at most _FINAL_STARTS starts.
_RUNNER_UP_MARGIN = 0.15
_BASIN_M = 0.1
_BASIN_RAD = math.radians(10.0)
_FINAL_STARTS = 3
# An unsettled hypothesis fitting this fraction of the leader's fit gets a final full ICP.
_UNSETTLED_FIT = 0.95
# Alternatives of a leader that get the short ICP (best raw fit first).
_ALTERNATIVES_SCREENED = 8
# Polygon vertices: points whose 3rd nearest neighbour is within 4x the scan's median such
# distance (1% stray returns at 2-60 m: ~90% of them excluded, <= 2% of the target's points).
_ISOLATION_K = 3
_ISOLATION_FACTOR = 4.0


@dataclass(eq=False)
class _Scan:
    """The finite scan points of one :meth:`PAHDatabase.localize` call and what verification needs.

    Attributes:
        P: (n, 3) points [m], sensor frame.
        sigma: (n,) range noise [m].
        ranges: (n,) ``|P|`` [m].
        rays: (n, 3) unit ray directions.
        gate: (n,) inlier distance to the model surface [m] (noise plus model sampling).
        margin: (n,) depth behind the model surface beyond which a point violates free space [m].
    """

    P: FloatArray
    sigma: FloatArray
    ranges: FloatArray
    rays: FloatArray
    gate: FloatArray
    margin: FloatArray

    @classmethod
    def build(cls, P: FloatArray, sigma: FloatArray, rays: FloatArray | None, spacing: float,
              ranges: FloatArray | None = None) -> _Scan:
        """The scan of points ``P`` with range noise ``sigma``: gate ``3 sigma + spacing`` (the
        model's sample spacing), free-space margin ``3 sigma + _FREE_SPACE_MARGIN_M``; rays are
        the lines of sight when None."""
        r = np.linalg.norm(P, axis=1) if ranges is None else ranges
        d = P / r[:, None] if rays is None else rays
        return cls(P, sigma, r, d, 3.0 * sigma + spacing, 3.0 * sigma + _FREE_SPACE_MARGIN_M)

    def subset(self, idx: IntArray) -> _Scan:
        """The points ``idx`` of this scan, with their gates and margins."""
        return _Scan(*(getattr(self, f.name)[idx] for f in fields(self)))


def _free_space_allowed(n_points: int) -> float:
    """Violation fraction a pose that explains a scan of ``n_points`` may show (silhouettes)."""
    return max(_FREE_SPACE_ACCEPT, _FREE_SPACE_ACCEPT_POINTS / max(n_points, 1))


def _rim_rays(d: FloatArray, half_angle_rad: float) -> FloatArray:
    """(m, F, 3) unit rays at ``half_angle_rad`` about each unit ray of d (m, 3), F around."""
    a = np.where(np.abs(d[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    u = np.cross(d, a)
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    v = np.cross(d, u)
    phi = 2.0 * np.pi * np.arange(_FOOTPRINT_RAYS) / _FOOTPRINT_RAYS
    off = math.tan(half_angle_rad) * (np.cos(phi)[None, :, None] * u[:, None, :]
                                      + np.sin(phi)[None, :, None] * v[:, None, :])
    r = d[:, None, :] + off
    return r / np.linalg.norm(r, axis=2, keepdims=True)


def _cube_group() -> FloatArray:
    """(24, 3, 3) the rotations mapping a cube onto itself (signed permutations, det +1)."""
    out = []
    for perm in ((0, 1, 2), (0, 2, 1), (1, 0, 2), (1, 2, 0), (2, 0, 1), (2, 1, 0)):
        for signs in np.ndindex(2, 2, 2):
            M = np.zeros((3, 3))
            M[np.arange(3), perm] = 1.0 - 2.0 * np.asarray(signs)
            if np.linalg.det(M) > 0:
                out.append(M)
    return np.stack(out)


_CUBE_GROUP = _cube_group()


def _pose(R: FloatArray, t: FloatArray) -> FloatArray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


def _best(hyps: list[_Hypothesis], constraint: PoseConstraint | None) -> _Hypothesis | None:
    """Highest-scoring hypothesis (inside the corridor, if any); the first one on ties."""
    best = None
    for h in hyps:
        if constraint is not None and not constraint.admits(h.T):
            continue
        if best is None or h.score > best.score:
            best = h
    return best


def _to_model(P: FloatArray, R: FloatArray, t: FloatArray) -> FloatArray:
    """Scan points (m, 3) into the model frame under K poses: (K, m, 3) = R_k^T (p - t_k)."""
    return np.matmul(P[None] - t[:, None, :], R)  # (einsum is ~3x slower here)


def _triangle_poses(S: FloatArray, Q: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Poses from orthonormal frames on the first three vertices (cheap, for pruning).

    Args:
        S: (K, N, 3) model polygons [m]; Q: (N, 3) scan polygon [m].

    Returns:
        R (K, 3, 3), t (K, 3) with ``Q ~= R S_k + t`` (centroids aligned).
    """

    def frames(a: FloatArray, b: FloatArray, c: FloatArray) -> FloatArray:
        x = b - a
        x = x / np.linalg.norm(x, axis=-1, keepdims=True).clip(1e-12)
        z = np.cross(b - a, c - a)
        z = z / np.linalg.norm(z, axis=-1, keepdims=True).clip(1e-12)
        y = np.cross(z, x)
        return np.stack([x, y, z], axis=-1)

    Fs = frames(S[:, 0], S[:, 1], S[:, 2])
    Fq = frames(Q[0], Q[1], Q[2])
    # R_k = Fq Fs_k^T, as one (3K, 3) x (3, 3) product (einsum is ~20x slower here).
    K = Fs.shape[0]
    R = np.ascontiguousarray((Fs.reshape(-1, 3) @ Fq.T).reshape(K, 3, 3).transpose(0, 2, 1))
    t = Q.mean(axis=0) - np.einsum("kij,kj->ki", R, S.mean(axis=1))
    return R, t


def _same_pose(A: FloatArray, B: FloatArray, tol_m: float = 0.05, tol_rad: float = 0.1) -> bool:
    if np.linalg.norm(A[:3, 3] - B[:3, 3]) > tol_m:
        return False
    c = 0.5 * (float(np.sum(A[:3, :3] * B[:3, :3])) - 1.0)
    return c >= math.cos(tol_rad)


def _diameter(Q: FloatArray) -> float:
    """Largest pairwise distance of a small point set (N, 3) [m]."""
    return float(np.linalg.norm(Q[:, None, :] - Q[None, :, :], axis=-1).max())


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


# ---------------------------------------------------------------------------------------------
# Database files: every entry checked before use
# ---------------------------------------------------------------------------------------------
#: Entries of a database file: name -> (accepted dtype kinds, number of dimensions).
_ENTRIES: dict[str, tuple[str, int]] = {
    "format_version": ("iu", 0), "model_hash": ("U", 0), "target_name": ("U", 0),
    "config_json": ("U", 0), "coverage_m": ("f", 0),
    "points": ("f", 2), "normals": ("f", 2), "seg_i": ("iu", 1), "seg_j": ("iu", 1),
    "seg_len": ("f", 1), "bin_ptr": ("iu", 1), "dist": ("f", 2),
}
_KIND_NAMES = {"iu": "an integer", "U": "a string", "f": "a float"}
# A deflated entry (``np.savez_compressed``) may claim at most this multiple of the archive's size
# once inflated: float tables compress less than 2x, a zip bomb claims 1000x.
_MAX_INFLATION = 64
_MAX_TEXT_CHARS = 1_000_000  # config JSON, target name, model hash


class _Archive:
    """The entries of an open ``.npz``; an entry's data is read only after its header passed."""

    def __init__(self, path: Path, zf: zipfile.ZipFile) -> None:
        self.path, self.zf = path, zf
        self.size = path.stat().st_size
        self.infos = {i.filename: i for i in zf.infolist()}

    def fail(self, name: str, problem: str) -> PAHFileError:
        return PAHFileError(f"PAH database {self.path} is corrupt: {name}: {problem}")

    def header(self, name: str) -> tuple[int, ...]:
        """The entry's shape, after its dtype, dimensions and size against the archive passed."""
        info = self.infos.get(f"{name}.npy")
        if info is None:
            raise self.fail(name, "no such entry")
        if info.flag_bits & 0x1:
            raise self.fail(name, "encrypted entry")
        if info.compress_type == zipfile.ZIP_STORED:
            if info.compress_size != info.file_size or info.file_size > self.size:
                raise self.fail(name, f"entry claims {info.file_size} bytes; the file has {self.size}")
        elif info.compress_type == zipfile.ZIP_DEFLATED:
            if info.file_size > _MAX_INFLATION * self.size:
                raise self.fail(name, f"entry claims {info.file_size} bytes inflated from a "
                                      f"{self.size}-byte file")
        else:
            raise self.fail(name, f"zip compression method {info.compress_type} not supported")
        try:
            with self.zf.open(info) as f:
                version = np.lib.format.read_magic(f)
                if version == (1, 0):
                    shape, _, dtype = np.lib.format.read_array_header_1_0(f)
                elif version == (2, 0):
                    shape, _, dtype = np.lib.format.read_array_header_2_0(f)
                else:
                    raise ValueError(f".npy format version {version} not supported")
                data_bytes = info.file_size - f.tell()
        except (ValueError, EOFError, OSError, zipfile.BadZipFile, zlib.error) as exc:
            raise self.fail(name, f"unreadable .npy header ({_one_line(exc)})") from None
        kinds, ndim = _ENTRIES[name]
        if dtype.kind not in kinds or dtype.hasobject or dtype.fields or dtype.subdtype:
            raise self.fail(name, f"dtype {dtype}; expected {_KIND_NAMES[kinds]} dtype")
        if len(shape) != ndim:
            raise self.fail(name, f"shape {shape}; expected {ndim} dimensions")
        nbytes = math.prod(shape) * dtype.itemsize
        if nbytes > data_bytes:
            raise self.fail(name, f"header claims shape {shape} of {dtype} ({nbytes} bytes); the "
                                  f"entry holds {data_bytes} bytes")
        return shape

    def read(self, name: str) -> np.ndarray:
        """The entry's array (call :meth:`header` first)."""
        try:
            with self.zf.open(self.infos[f"{name}.npy"]) as f:
                return np.lib.format.read_array(f, allow_pickle=False)
        except (ValueError, EOFError, OSError, zipfile.BadZipFile, zlib.error) as exc:
            raise self.fail(name, f"unreadable data ({_one_line(exc)})") from None

    def scalar(self, name: str) -> np.generic:
        self.header(name)
        return self.read(name)[()]


def _one_line(exc: BaseException) -> str:
    """An exception's message on one line (pydantic's errors as ``field: message; ...``)."""
    if isinstance(exc, ValidationError):
        return "; ".join(
            f"{'.'.join(map(str, e['loc'])) or 'config'}: {e['msg']}" for e in exc.errors()
        )
    return " ".join(str(exc).split()) or type(exc).__name__


def _read_database(p: Path) -> tuple[dict, PAHConfig, dict[str, np.ndarray]]:
    """Metadata, settings and arrays of a database file, every one checked (PAHFileError)."""
    try:
        zf = zipfile.ZipFile(p)
    except (zipfile.BadZipFile, EOFError, ValueError) as exc:  # OSError (permissions) propagates
        raise PAHFileError(f"PAH database {p} is not a .npz archive ({_one_line(exc)})") from None
    with zf:
        ar = _Archive(p, zf)
        if "format_version.npy" not in ar.infos:
            raise PAHFileError(f"PAH database {p}: no format_version entry; not a PAH database")
        version = int(ar.scalar("format_version"))
        if version != PAH_FORMAT_VERSION:
            raise PAHFileError(
                f"PAH database {p}: format version {version}; this code reads version "
                f"{PAH_FORMAT_VERSION}"
            )
        meta: dict = {}
        for k in ("model_hash", "target_name", "config_json"):
            text = str(ar.scalar(k))
            if len(text) > _MAX_TEXT_CHARS:
                raise ar.fail(k, f"{len(text)} characters; expected <= {_MAX_TEXT_CHARS}")
            if k != "config_json" and not text.isprintable():
                raise ar.fail(k, f"{text!r} has non-printable characters")
            meta[k] = text
        try:
            config = PAHConfig.model_validate(json.loads(meta.pop("config_json")))
        except (ValueError, RecursionError) as exc:  # bad JSON, pydantic's ValidationError
            raise ar.fail("config_json", _one_line(exc)) from None
        meta["coverage_m"] = float(ar.scalar("coverage_m"))
        shapes = {k: ar.header(k) for k in _ARRAY_KEYS}
        m = shapes["points"][0]
        n = m * (m - 1) // 2
        expected = {"points": (m, 3), "normals": (m, 3), "seg_i": (n,), "seg_j": (n,),
                    "seg_len": (n,), "dist": (m, m)}
        if m < 3:
            raise ar.fail("points", f"{m} points; a database has >= 3")
        for k, shape in expected.items():
            if shapes[k] != shape:
                raise ar.fail(k, f"shape {shapes[k]}; expected {shape} for {m} points")
        if shapes["bin_ptr"][0] < 2:
            raise ar.fail("bin_ptr", f"{shapes['bin_ptr'][0]} offsets; expected >= 2")
        arrays = {k: ar.read(k) for k in _ARRAY_KEYS}
    _check_values(ar, arrays, config, meta["coverage_m"])
    return meta, config, arrays


def _first(mask: npt.NDArray[np.bool_]) -> int:
    return int(np.flatnonzero(mask.reshape(-1))[0])


def _check_values(
    ar: _Archive, a: dict[str, np.ndarray], config: PAHConfig, coverage_m: float
) -> None:
    """Ranges, order and consistency of the arrays (shapes and dtypes already checked); converts
    the index arrays to int64 and the tables to C-ordered float64 in place (no-ops on a file
    :meth:`PAHDatabase.save` wrote)."""
    m, n = a["points"].shape[0], a["seg_len"].shape[0]
    for k in ("points", "normals", "seg_len", "dist"):
        bad = ~np.isfinite(a[k])
        if bad.any():
            raise ar.fail(k, f"non-finite value at flat index {_first(bad)}")
        a[k] = np.ascontiguousarray(a[k], dtype=np.float64)
    for k, hi in (("seg_i", m), ("seg_j", m), ("bin_ptr", n + 1)):
        bad = (a[k] < 0) | (a[k] >= hi)
        if bad.any():
            i = _first(bad)
            raise ar.fail(k, f"{k}[{i}]={a[k][i]} out of range [0, {hi})")
        a[k] = np.ascontiguousarray(a[k], dtype=np.int64)
    si, sj, seg_len, dist, bp = a["seg_i"], a["seg_j"], a["seg_len"], a["dist"], a["bin_ptr"]
    if np.any(si >= sj):
        i = _first(si >= sj)
        raise ar.fail("seg_j", f"segment {i} has j={sj[i]} <= i={si[i]}; expected i < j")
    if np.unique(si * m + sj).size != n:
        raise ar.fail("seg_i", "a segment appears twice; expected every pair of points once")
    if np.any(dist < 0) or np.any(np.diagonal(dist) != 0) or not np.array_equal(dist, dist.T):
        raise ar.fail("dist", "not a distance table (negative, non-zero diagonal or asymmetric)")
    down = np.diff(seg_len) < 0
    if down.any():
        i = _first(down)
        raise ar.fail("seg_len", f"not sorted: seg_len[{i}]={seg_len[i]:.6g} > "
                                 f"seg_len[{i + 1}]={seg_len[i + 1]:.6g}")
    if not np.allclose(seg_len, dist[si, sj]):
        raise ar.fail("seg_len", "length table inconsistent with the connectivity table dist")
    if bp[0] != 0 or bp[-1] != n:
        raise ar.fail("bin_ptr", f"runs from {bp[0]} to {bp[-1]}; expected 0 to {n} (segments)")
    down = np.diff(bp) < 0
    if down.any():
        i = _first(down)
        raise ar.fail("bin_ptr", f"decreasing: bin_ptr[{i}]={bp[i]} > bin_ptr[{i + 1}]={bp[i + 1]}")
    b = config.length_bin_m
    with np.errstate(over="ignore"):
        n_bins = seg_len[-1] / b
    if not (math.isfinite(n_bins) and math.floor(n_bins) + 2 == bp.size):
        raise ar.fail("bin_ptr", f"{bp.size} offsets; {seg_len[-1]:.6g} m in bins of {b} m "
                                 f"needs {n_bins + 2:.0f}")
    # The offsets exactly as build computes them from the sorted lengths.
    want = np.searchsorted(seg_len, np.arange(bp.size) * b, side="left")
    want[-1] = n
    if not np.array_equal(bp, want):
        i = _first(bp != want)
        raise ar.fail("bin_ptr", f"bin_ptr[{i}]={bp[i]}; the segment lengths put {want[i]} there")
    if not 0.0 <= coverage_m <= seg_len[-1]:
        raise ar.fail("coverage_m", f"{coverage_m}; expected 0 to the longest segment "
                                    f"{seg_len[-1]:.6g} m")
