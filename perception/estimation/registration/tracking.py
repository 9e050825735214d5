# Long module: moved whole from perception/estimation/registration.py (history); split next.
"""ICP tracking (seed 000 section 3.2) and the pose covariance / Cramer-Rao bound of a frame.

The model side is prepared once per target (:func:`prepare_model`): dense area-uniform surface
samples with their face normals and a KD-tree, cached on the :class:`~perception.targets.TargetModel`
so every frame reuses them. :func:`icp` then aligns a sparse scan (sensor frame) to that model from
an initial ``T_sensor_target`` with Gauss-Newton point-to-plane steps on SE(3) (default) or
closed-form point-to-point (Kabsch) steps (the seed-003 baseline).

Outlier rejection is tuned for space, where there is no clutter but there are returns from parts
that were removed from the model (solar arrays, radiators, arms; seed 000 section 5.3):

- a correspondence gate on the point-to-model distance that starts at ``max_correspondence_m`` and
  shrinks each iteration to three times the median distance, never below a floor set by the
  sensor noise, the model sampling and ``min_correspondence_m``;
- trimming of the worst ``trim_fraction`` correspondences, applied only to those beyond that floor
  (so a converged, clean frame keeps all its points and its full information);
- a robust kernel (Huber by default) on the noise-normalised point-to-plane residual.

The covariance is the inverse of the point-to-plane information matrix
``H = sum_i A_i^T A_i / var_i`` over the inliers at the final pose, where ``A_i`` is the residual's
Jacobian and ``var_i`` its noise variance from the sensor's range noise projected on the surface
normal. That is the Cramer-Rao bound of the frame: what the pose can be known to from this geometry
and this noise, whatever the solver. Directions in which ``H`` is (nearly) singular are reported in
``degenerate_axes`` rather than hidden.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
import numpy.typing as npt
import trimesh
from scipy.spatial import cKDTree

from perception.config import ICPConfig
from perception.estimation.registration.facegrid import FaceGrid
from perception.geometry import (
    check_rigid,
    cross_rows,
    fast_rotvec_to_matrix,
    kabsch,
    se3_log,
    skew,
)
from perception.numeric import median
from perception.targets import TargetModel

FloatArray = npt.NDArray[np.float64]

__all__ = [
    "AXIS_NAMES",
    "FAILURE_VARIANCE",
    "FaceGrid",
    "ModelCloud",
    "RegistrationResult",
    "prepare_model",
    "icp",
    "information_matrix",
    "information_rows",
    "edge_ambiguous",
    "covariance_from_information",
    "covariance_about_sensor_origin",
    "validate_points",
]

#: Names of the six twist components of the covariance, in order: translation along the sensor
#: x, y, z axes, then rotation about them.
AXIS_NAMES: tuple[str, ...] = ("tx", "ty", "tz", "rx", "ry", "rz")

#: Variance [m^2 or rad^2] reported along unobservable directions and for failed registrations:
#: large enough to mean "unknown", finite so that no inf or NaN ever leaves an estimator.
FAILURE_VARIANCE = 1.0e6

Method = Literal["point_to_plane", "point_to_point"]


# ---------------------------------------------------------------------------------------------
# Result
# ---------------------------------------------------------------------------------------------
@dataclass
class RegistrationResult:
    """Outcome of a registration (ICP tracking or PAH acquisition).

    Attributes:
        T_sensor_target: (4, 4) estimated pose; maps target-body coordinates into the sensor frame.
            Always a finite rigid transform (the initial guess on failure).
        fitness: inlier fraction of the finite scan points, 0..1.
        inlier_rmse: RMS point-to-plane residual of the inliers [m].
        converged: True when a stop criterion on the step or the residual was met.
        iterations: iterations run.
        covariance: (6, 6) covariance of a LEFT perturbation along the sensor axes, pivoting on
            the target origin: ``xi = (rho [m], phi [rad])`` with
            ``T_true = Tr(t) @ se3_exp(xi) @ Tr(-t) @ T_sensor_target`` (``t`` the estimated target
            position), i.e. to first order ``t_true = t + rho`` and
            ``R_true = exp(phi^) R``. So the top-left 3x3 block is the position covariance
            [m^2] of the target origin in the sensor frame and the bottom-right 3x3 the attitude
            covariance [rad^2] about the sensor axes. (Pivoting on the sensor origin instead,
            ``T_true = se3_exp(xi) @ T``, mixes ``phi x t`` into the translation block; see
            :func:`covariance_about_sensor_origin`.) Unobservable directions and failures carry
            ``FAILURE_VARIANCE``.
        degenerate_axes: names from :data:`AXIS_NAMES` of the directions the geometry does not
            constrain (e.g. ``["tx", "ty", "rz"]`` for a flat panel seen face-on).
        reason: empty when fine; otherwise why the registration failed or stopped early.
        n_points: finite scan points used.
        n_inliers: scan points inside the final correspondence gate.
        time_s: wall-clock time of the call [s].
    """

    T_sensor_target: FloatArray
    fitness: float = 0.0
    inlier_rmse: float = 0.0
    converged: bool = False
    iterations: int = 0
    covariance: FloatArray = field(default_factory=lambda: FAILURE_VARIANCE * np.eye(6))
    degenerate_axes: list[str] = field(default_factory=list)
    reason: str = ""
    n_points: int = 0
    n_inliers: int = 0
    time_s: float = 0.0

    @classmethod
    def failure(
        cls,
        reason: str,
        T: npt.ArrayLike | None = None,
        n_points: int = 0,
        time_s: float = 0.0,
        iterations: int = 0,
    ) -> RegistrationResult:
        """A non-converged result with a finite pose (``T`` or identity) and a huge finite covariance."""
        T_out = np.eye(4)
        if T is not None:
            arr = np.asarray(T, dtype=np.float64)
            if arr.shape == (4, 4) and np.all(np.isfinite(arr)):
                T_out = arr.copy()
        return cls(
            T_sensor_target=T_out,
            converged=False,
            iterations=int(iterations),
            covariance=FAILURE_VARIANCE * np.eye(6),
            degenerate_axes=list(AXIS_NAMES),
            reason=reason,
            n_points=int(n_points),
            time_s=float(time_s),
        )

    @property
    def position_sigma_m(self) -> float:
        """Root of the trace of the position covariance [m] (1-sigma, all axes together)."""
        return float(np.sqrt(max(np.trace(self.covariance[:3, :3]), 0.0)))

    @property
    def attitude_sigma_rad(self) -> float:
        """Root of the trace of the attitude covariance [rad]."""
        return float(np.sqrt(max(np.trace(self.covariance[3:, 3:]), 0.0)))


# ---------------------------------------------------------------------------------------------
# Model side
# ---------------------------------------------------------------------------------------------
@dataclass(eq=False)
class ModelCloud:
    """Dense model surface samples prepared for correspondence search.

    Attributes:
        points: (M, 3) surface samples [m], target frame.
        normals: (M, 3) unit outward normals, target frame.
        kdtree: KD-tree over ``points``.
        spacing: mean sample spacing [m] (``sqrt(area / M)``), the model's resolution.
        radius: radius of the origin-centred sphere holding the samples [m].
        name: target name.
        model_hash: the target's geometry hash (empty for clouds built from bare arrays).
        grid: the mesh's exact faces indexed by voxel (None for clouds built from bare samples).
            With it, ICP measures point-to-plane residuals to the true faces, and the samples only
            serve points farther than ``grid.band`` from the surface.
    """

    points: FloatArray
    normals: FloatArray
    kdtree: cKDTree
    spacing: float
    radius: float
    name: str = ""
    model_hash: str = ""
    grid: FaceGrid | None = None

    @classmethod
    def from_arrays(
        cls,
        points: npt.ArrayLike,
        normals: npt.ArrayLike,
        area_m2: float | None = None,
        name: str = "",
        model_hash: str = "",
        mesh: trimesh.Trimesh | None = None,
    ) -> ModelCloud:
        """Build from surface samples and normals (target frame).

        Args:
            points: (M, 3) samples [m], M >= 3.
            normals: (M, 3) normals (normalised here).
            area_m2: surface area the samples cover [m^2]; estimated from nearest-neighbour
                distances when None.
            name: label.
            model_hash: geometry hash to carry along.
            mesh: the triangle mesh the samples were drawn from (target frame); when given, ICP
                matches against its exact faces (:class:`FaceGrid`).
        """
        P = np.ascontiguousarray(points, dtype=np.float64)
        N = np.asarray(normals, dtype=np.float64)
        if P.ndim != 2 or P.shape[1] != 3 or P.shape[0] < 3:
            raise ValueError(f"model points have shape {P.shape}; expected (M, 3) with M >= 3")
        if N.shape != P.shape:
            raise ValueError(f"model normals have shape {N.shape}; expected {P.shape}")
        if not (np.all(np.isfinite(P)) and np.all(np.isfinite(N))):
            raise ValueError("model points/normals contain non-finite values; expected finite")
        nn = np.linalg.norm(N, axis=1)
        if np.any(nn < 1e-12):
            raise ValueError("model normals contain zero vectors; expected unit normals")
        N = np.ascontiguousarray(N / nn[:, None])
        tree = cKDTree(P)
        if area_m2 is not None and area_m2 > 0:
            spacing = float(np.sqrt(area_m2 / P.shape[0]))
        else:
            d, _ = tree.query(P[: min(2000, P.shape[0])], k=2)
            spacing = float(np.median(d[:, 1]) * 1.2)
        return cls(
            points=P,
            normals=N,
            kdtree=tree,
            spacing=spacing,
            radius=float(np.linalg.norm(P, axis=1).max()),
            name=name,
            model_hash=model_hash,
            grid=FaceGrid.build(mesh) if mesh is not None else None,
        )


def prepare_model(target: TargetModel, n_points: int = 20_000, seed: int = 0) -> ModelCloud:
    """Dense surface samples + normals + KD-tree + exact face grid of a target, built once and
    cached on it.

    Args:
        target: the target model (body frame, origin at the centre of mass).
        n_points: number of area-uniform samples (>= 100). 20,000 gives ~1 cm resolution on a
            1 m satellite, the 1-5 cm model resolution of seed 000 section 3.2. ICP residuals are
            measured to the mesh's faces (:class:`FaceGrid`), so the samples only matter for
            points far from the surface (coarse alignment) and for acquisition.
        seed: seed of the deterministic sampling.

    Returns:
        The cached :class:`ModelCloud`.

    Raises:
        ValueError: a mesh with no faces or zero area, or ``n_points`` < 100.
    """
    if not isinstance(target, TargetModel):
        raise ValueError(f"target is a {type(target).__name__}; expected a TargetModel")
    if int(n_points) < 100:
        raise ValueError(f"n_points={n_points}; expected >= 100 model samples")
    if len(target.mesh.faces) == 0 or not float(target.mesh.area) > 0:
        raise ValueError(f"target {target.name!r} has no faces (or zero area); ICP needs a surface")

    def build() -> ModelCloud:
        pts, nrm = target.sample_surface(int(n_points), seed=int(seed))
        return ModelCloud.from_arrays(
            pts, nrm, area_m2=float(target.mesh.area), name=target.name,
            model_hash=target.model_hash, mesh=target.model_mesh,
        )

    return target.cached(("icp_model", int(n_points), int(seed)), build)


# ---------------------------------------------------------------------------------------------
# Input checking
# ---------------------------------------------------------------------------------------------
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


def _directions(directions: npt.ArrayLike | None, P: FloatArray) -> FloatArray:
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


# ---------------------------------------------------------------------------------------------
# Information matrix and covariance
# ---------------------------------------------------------------------------------------------
def _jacobian_rows(s_rel: FloatArray, n_sensor: FloatArray) -> FloatArray:
    """Rows ``A_i = [n_i, s_i x n_i]`` with ``r_i(xi) ~= r_i - A_i xi``, ``s_i`` about the pivot."""
    A = np.empty((n_sensor.shape[0], 6))
    A[:, :3] = n_sensor
    A[:, 3:] = cross_rows(s_rel, n_sensor)
    return A


def _residual_variance(
    sig: FloatArray,
    n_sensor: FloatArray,
    d_sensor: FloatArray,
    floor_fraction: float,
    model_sigma: float = 0.0,
) -> FloatArray:
    cos = np.einsum("ij,ij->i", n_sensor, d_sensor)
    return sig**2 * (cos**2 + floor_fraction**2) + model_sigma**2


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
    A = _jacobian_rows(S - c, Nn)
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


# ---------------------------------------------------------------------------------------------
# ICP
# ---------------------------------------------------------------------------------------------
def _kernel_weights(z: FloatArray, kind: str, k: float) -> FloatArray:
    a = np.abs(z)
    if kind == "huber":
        return np.minimum(1.0, k / np.maximum(a, 1e-12))
    if kind == "tukey":
        u = a / k
        return np.where(u < 1.0, (1.0 - u * u) ** 2, 0.0)
    if kind == "cauchy":
        return 1.0 / (1.0 + (a / k) ** 2)
    return np.ones_like(a)


def _best_plane_match(
    mc: ModelCloud, q: FloatArray, gate: float, k: int
) -> tuple[FloatArray, npt.NDArray[np.intp]]:
    """Among the ``k`` nearest samples, the one whose tangent plane passes closest to the point.

    Near an edge the nearest sample often lies on the neighbouring face; its plane is wrong for the
    point and biases the pose by a fraction of the model spacing. Returns the Euclidean distance to
    the chosen sample (inf where none is within ``gate``) and its index. Used for models without a
    :class:`FaceGrid`.
    """
    dist, idx = mc.kdtree.query(q, k=k, distance_upper_bound=gate, workers=1)
    ok = np.isfinite(dist)
    safe = np.where(ok, idx, 0)
    r = np.abs(np.einsum("ijk,ijk->ij", mc.normals[safe], q[:, None, :] - mc.points[safe]))
    r = np.where(ok, r, np.inf)
    best = np.argmin(r, axis=1)
    rows = np.arange(q.shape[0])
    return dist[rows, best], idx[rows, best]


@dataclass
class _Matches:
    """Correspondences of the scan points ``sel`` (target frame): distance to the model [m],
    unit normal, matched surface point and signed point-to-plane residual ``n . (q - foot)`` [m]."""

    sel: npt.NDArray[np.intp]
    dist: FloatArray
    normal: FloatArray
    foot: FloatArray
    r: FloatArray

    def keep(self, m: npt.NDArray[np.bool_]) -> _Matches:
        return _Matches(self.sel[m], self.dist[m], self.normal[m], self.foot[m], self.r[m])


def _samples_match(mc: ModelCloud, q: FloatArray, rows: npt.NDArray[np.intp], gate: float,
                   k: int) -> _Matches:
    """Nearest-sample matches of the points ``rows`` (best tangent plane of ``k`` when ``k`` > 1)."""
    if k > 1:
        dist, idx = _best_plane_match(mc, q[rows], gate, k)
    else:
        dist, idx = mc.kdtree.query(q[rows], k=1, distance_upper_bound=gate, workers=1)
    ok = np.isfinite(dist)
    j = idx[ok]
    sel = rows[ok]
    nrm = mc.normals[j]
    foot = mc.points[j]
    r = np.einsum("ij,ij->i", nrm, q[sel] - foot)
    return _Matches(sel, dist[ok], nrm, foot, r)


def _correspond(
    mc: ModelCloud,
    q: FloatArray,
    gate: float,
    k: int,
    rays: FloatArray,
    back_cos: float,
    samples: bool = False,
    along_rays: bool = False,
    max_cross: FloatArray | None = None,
) -> _Matches:
    """Matches of the points ``q`` (N, 3, target frame) within ``gate`` [m] of the model.

    With a :class:`FaceGrid`: the closest face (exact plane; the matched point is the closest
    point of the facet), and for points beyond the grid's band (only when ``gate`` reaches past
    it) the nearest sample, whose plane is its face's. Without one, or with ``samples`` (the
    point-to-point baseline pairs points with samples): the nearest sample, or the best tangent
    plane among the ``k`` nearest.
    """
    g = mc.grid
    if g is None or samples:
        return _samples_match(mc, q, np.arange(q.shape[0]), gate, k)
    found, dist, face, v = g.nearest(q, rays, back_cos, along_rays, max_cross)
    ok = dist <= gate
    sel = found[ok]
    pl = g.planes[face[ok]]
    v = v[ok]
    nrm = pl[:, 0, :3]
    r = v[:, 0]
    # Onto the plane, then back over the facet edges the point lies beyond.
    beyond = np.maximum(v[:, 1:], 0.0)
    foot = q[sel] - r[:, None] * nrm - np.einsum("ki,kij->kj", beyond, pl[:, 1:, :3])
    m = _Matches(sel, dist[ok], nrm, foot, r)
    if gate > g.band and found.size < q.shape[0]:
        missed = np.ones(q.shape[0], dtype=bool)
        missed[found] = False
        far = _samples_match(mc, q, np.flatnonzero(missed), gate, 1)
        if far.sel.size:
            m = _Matches(*(np.concatenate([a, b]) for a, b in zip(
                (m.sel, m.dist, m.normal, m.foot, m.r), (far.sel, far.dist, far.normal, far.foot, far.r))))
    return m


def _centered_step(T_new: FloatArray, T_old: FloatArray) -> FloatArray:
    """Twist ``xi`` with ``T_new ~= Tr(t) exp(xi) Tr(-t) T_old`` (translation and rotation parts)."""
    dR = T_new[:3, :3] @ T_old[:3, :3].T
    phi = se3_log(np.block([[dR, np.zeros((3, 1))], [np.zeros((1, 3)), np.ones((1, 1))]]))[3:]
    return np.concatenate([T_new[:3, 3] - T_old[:3, 3], phi])


def icp(
    points: npt.ArrayLike,
    model: TargetModel | ModelCloud,
    init_T_sensor_target: npt.ArrayLike,
    *,
    sigma: float | npt.ArrayLike | None = None,
    method: Method | None = None,
    config: ICPConfig | None = None,
    directions: npt.ArrayLike | None = None,
    match_along_rays: bool | None = None,
    coarse: bool = True,
) -> RegistrationResult:
    """Align a scan to the target model by ICP, from an initial pose.

    Two phases share the iteration budget. The *coarse* phase keeps the initial gate
    ``max_correspondence_m``, trims, down-weights far matches softly (Cauchy, scaled by 1.5 times
    the median distance), and adds the
    point-to-point residual to the plane residual (point-to-point method: Kabsch steps): its basin
    is wide, and a misaligned face seen by a minority of points still pulls the pose in. Once its steps are below a quarter of the gate floor, the
    *fine* phase (point-to-plane Gauss-Newton by default) shrinks the gate to three times the median correspondence distance
    (never below the floor ``max(min_correspondence_m, 4 sigma, 1.5 model spacing)``) and applies
    the robust kernel, which rejects returns from parts missing from the model. Correspondences
    whose model normal faces away from the sensor by more than ``back_facing_cos`` are dropped
    (the scan only sees front faces; this matters on thin panels). The fine phase stops once its
    gate has settled and the correction left is below ``step_tol_sigma`` of the frame's own
    information: the last step, or, while the steps contract, their geometric tail (a step of
    ``s`` sigmas after one of ``s / rho`` leaves about ``s rho / (1 - rho)``). After such a step
    the final fit keeps that iteration's matches and only re-evaluates their residuals.

    Args:
        points: (N, 3) scan points [m], sensor frame. Non-finite rows are ignored.
        model: a :class:`TargetModel` (prepared and cached with ``config.model_points`` samples)
            or a prepared :class:`ModelCloud`.
        init_T_sensor_target: (4, 4) initial guess (previous frame's pose or a prediction).
        sigma: range-noise 1-sigma [m], a float or (N,) per point; default 0.01 m.
        method: ``"point_to_plane"`` (Gauss-Newton on SE(3)) or ``"point_to_point"`` (Kabsch);
            default ``config.method``.
        config: tuning; defaults of :class:`~perception.config.ICPConfig` when None.
        match_along_rays: choose each point's face along its measured ray (needs
            ``directions``); in the fine phase only crossings within ``max(4 sigma_i,
            min_correspondence_m, 3 x`` the median match distance) of the point count (else its
            closest face). None: ``config.match_along_rays``.
        directions: (N, 3) unit ray directions [sensor frame] along which each point's range
            noise acts. Default: ``points / |points|`` (rays from the sensor origin). Given
            explicitly, and with ``match_along_rays``, they are taken as the measured rays and
            also choose each point's model face (the one its ray crosses,
            :meth:`FaceGrid.nearest`). They set the
            point-to-plane residual variance ``sigma_i^2 ((n_i . d_i)^2 + f^2) + sigma_model^2``
            used both to weight the solve and in the covariance, with
            ``f = config.noise_floor_fraction`` and ``sigma_model = config.model_noise_fraction *``
            the model spacing (see :func:`information_matrix`).
        coarse: start with the coarse phase. False goes straight to the fine phase: for an
            initial pose already within a few sigma of the answer (a tracking filter's
            prediction), where the coarse phase costs an iteration and changes nothing.

    Returns:
        A :class:`RegistrationResult`; ``converged=False`` with a ``reason`` (and the initial pose)
        when too few points are usable.

    Raises:
        ValueError: points not (N, 3), ``init_T_sensor_target`` not a rigid transform, a bad
            ``sigma``/``directions``/``method``, or a model without faces.
    """
    t_start = time.perf_counter()
    cfg = config if config is not None else ICPConfig()
    meth = cfg.method if method is None else method
    if meth not in ("point_to_plane", "point_to_point"):
        raise ValueError(f"method={meth!r}; expected 'point_to_plane' or 'point_to_point'")
    if isinstance(model, ModelCloud):
        mc = model
    elif isinstance(model, TargetModel):
        mc = prepare_model(model, cfg.model_points)
    else:
        raise ValueError(f"model is a {type(model).__name__}; expected a TargetModel or ModelCloud")
    T = check_rigid(init_T_sensor_target, "init_T_sensor_target").copy()
    P_all = validate_points(points, "points")
    sig_all = per_point_sigma(sigma, P_all.shape[0])
    D_all = _directions(directions, P_all)
    ok = (
        np.all(np.isfinite(P_all), axis=1)
        & np.all(np.isfinite(D_all), axis=1)
        & np.isfinite(sig_all)
    )
    P = np.ascontiguousarray(P_all[ok])
    sig = sig_all[ok]
    D = D_all[ok]
    n = int(P.shape[0])
    min_pts = max(int(cfg.min_points), 6)
    if n < min_pts:
        return RegistrationResult.failure(
            f"{n} finite scan points (of {P_all.shape[0]}); ICP needs >= {min_pts}",
            T, n_points=n, time_s=time.perf_counter() - t_start,
        )

    floor_frac = float(cfg.noise_floor_fraction)
    model_sig = _model_sigma(mc, cfg)
    gate_floor = max(cfg.min_correspondence_m, 4.0 * median(sig), 1.5 * mc.spacing)
    gate = max(cfg.max_correspondence_m, gate_floor)
    trim = float(cfg.trim_fraction)
    gate_k = float(cfg.gate_median_factor)
    # With exact face distances the model spacing is no error source: the median gate may go
    # down to the noise (strays a few cm off a face are then still rejected).
    median_floor = (max(cfg.min_correspondence_m, 4.0 * median(sig))
                    if mc.grid is not None else gate_floor)
    kernel_k = float(cfg.kernel_scale)
    back_cos = float(cfg.back_facing_cos)
    # The coarse phase hands over once its steps are a fraction of the gate floor.
    coarse_tol_t = max(10.0 * cfg.translation_tol_m, 0.25 * gate_floor)
    coarse_tol_r = max(10.0 * cfg.rotation_tol_rad, 0.25 * gate_floor / mc.radius)
    step_tol2 = float(cfg.step_tol_sigma) ** 2
    n_candidates = int(cfg.plane_candidates)
    # Faces are chosen by where each point's ray crosses them (FaceGrid.nearest) only when the
    # caller gave the measured rays: a direction derived from a point that was moved after the
    # measurement (de-skewed, merged) is not its ray.
    along_rays = directions is not None and (
        cfg.match_along_rays if match_along_rays is None else bool(match_along_rays)
    )
    # A ray crossing a face farther from the point than its noise and the pose error still being
    # corrected allow is not where the point came from. The pose error is gauged by three times
    # the median match distance of the previous iteration (none on the first: no limit); the
    # coarse phase, still far from the answer, is not limited.
    cross_base = np.maximum(4.0 * sig, cfg.min_correspondence_m) if along_rays else None
    match_scale = np.inf
    R = T[:3, :3].copy()
    t = T[:3, 3].copy()
    step_sigma2 = np.inf
    prev_step_sigma = np.inf
    prev_xi: FloatArray | None = None
    reversals = 0
    stalled = False
    fine = not coarse
    prev_cost = np.inf
    converged = False
    reason = ""
    it = 0
    reuse: _Matches | None = None
    for it in range(1, cfg.max_iterations + 1):
        # Everything per point is in the target frame; only the 6-vector step is rotated.
        q = (P - t) @ R
        d_all = D @ R
        cross_max = (np.maximum(cross_base, 3.0 * match_scale)
                     if cross_base is not None and fine else None)
        m = _correspond(
            mc, q, gate, n_candidates if fine else 1, d_all, back_cos, meth == "point_to_point",
            along_rays, cross_max,
        )
        m_raw = m
        # One mask over the matches (median gate, then trim, then front faces), applied once.
        dist = m.dist
        if dist.size:
            match_scale = median(dist)
        kept = None  # None: all
        n_kept = int(m.sel.size)
        if gate_k > 0.0 and n_kept > min_pts:
            # Adaptive gate on the median match distance: once the pose is close, a stray
            # return 0.1-1 m off every surface is no longer a correspondence (trimming alone
            # keeps it while fewer than trim_fraction of the points are strays).
            thr = max(median_floor, gate_k * match_scale)
            if thr < gate:
                near = dist <= thr
                n_near = int(np.count_nonzero(near))
                if n_near < n_kept and n_near >= min_pts:
                    kept, n_kept = near, n_near
        if trim > 0.0 and n_kept > min_pts:
            kth = int((1.0 - trim) * (n_kept - 1))
            thr = float(np.partition(dist if kept is None else dist[kept], kth)[kth])
            if thr > gate_floor:
                kept = dist <= thr if kept is None else kept & (dist <= thr)
        cos = np.einsum("ij,ij->i", m.normal, d_all[m.sel])
        front = cos < back_cos
        kept = front if kept is None else kept & front
        nv = int(np.count_nonzero(kept))
        if nv < min_pts:
            return RegistrationResult.failure(
                f"{nv} correspondences within {gate:.3g} m at iteration {it}; ICP needs >= {min_pts}",
                T, n_points=n, time_s=time.perf_counter() - t_start, iterations=it,
            )
        if nv < m.sel.size:
            m = m.keep(kept)
            cos = cos[kept]
        sv = sig[m.sel]
        var = sv * sv * (cos * cos + floor_frac**2) + model_sig**2
        w = 1.0 / var
        r = m.r
        if fine:
            w = w * _kernel_weights(r / np.sqrt(var), cfg.robust_kernel, kernel_k)
        else:
            # Soft (Cauchy) down-weighting on the distance, scaled by the current spread: parts
            # missing from the model cannot drag the coarse solution, a misaligned face still pulls.
            w = w * _kernel_weights(
                m.dist / max(gate_floor, 1.5 * median(m.dist)), "cauchy", 1.0
            )
        cost = float(((w * r) @ r) / (w @ var))
        Hm = None
        if meth == "point_to_plane":
            # Linearised about the target origin, not the sensor origin: a finite rotation step
            # then does not swing the target about a lever arm of the full range.
            c = m.foot
            A = _jacobian_rows(c, m.normal)
            Aw = A * w[:, None]
            Hm = Aw.T @ A
            g = Aw.T @ r
            if not fine:
                # Coarse: add the point-to-point residual e = q - s, e(xi) ~= e - [I, -c^] xi,
                # which widens the basin of the plane metric (it cannot slide along faces).
                e = q[m.sel] - c
                ws = float(np.sum(w))
                cw = c * w[:, None]
                Sc = cw.sum(axis=0)
                Hpp = np.zeros((6, 6))
                Hpp[:3, :3] = ws * np.eye(3)
                Hpp[:3, 3:] = -skew(Sc)
                Hpp[3:, :3] = skew(Sc)
                cc = cw.T @ c
                Hpp[3:, 3:] = np.trace(cc) * np.eye(3) - cc
                gpp = np.concatenate([w @ e, w @ cross_rows(c, e)])
                Hm = Hm + Hpp
                g = g + gpp
            Hd = Hm.copy()
            Hd.flat[::7] += 1e-9 * float(Hm.diagonal().max()) + 1e-12  # damping on the diagonal
            try:
                xi_t = np.linalg.solve(Hd, g)
            except np.linalg.LinAlgError:
                xi_t = np.linalg.lstsq(Hm, g, rcond=None)[0]
            # Trust region: the correspondences hold within the gate (in the fine phase, which
            # starts once the steps are well inside it, its floor); a longer step, along a
            # direction these points barely constrain, would leave it.
            trust = gate_floor if fine else gate
            x0, x1, x2, x3, x4, x5 = xi_t.tolist()
            reach = math.hypot(x0, x1, x2) + mc.radius * math.hypot(x3, x4, x5)
            if reach > trust:
                xi_t = xi_t * (trust / reach)
            if fine:
                # The step against the frame's own uncertainty (Mahalanobis length squared).
                step_sigma2 = float(xi_t @ Hm @ xi_t)
                # A sub-sigma step that no longer lowers the cost is a limit cycle (points near an
                # edge trading faces), and so is a run of steps each undoing the one before (to
                # within a third of its length) for two steps running: the matches flip between
                # two sets, each pulling back to the other pose. Stop half-way.
                back = None if prev_xi is None else xi_t + prev_xi
                undo = back is not None and step_sigma2 > 0.0 and float(
                    back @ Hm @ back) < step_sigma2 / 9.0
                reversals = reversals + 1 if undo else 0
                stalled = (step_sigma2 < 1.0 and cost >= prev_cost) or reversals >= 2
                prev_xi = xi_t
                if stalled:
                    xi_t = 0.5 * xi_t
            # In the target frame the model point x moves to x + rho + phi x x; in the sensor
            # frame that is t += R rho, R <- R exp(phi) (= exp(R phi) R about the target origin).
            t = t + R @ xi_t[:3]
            R = R @ fast_rotvec_to_matrix(xi_t[3:])
            x0, x1, x2, x3, x4, x5 = xi_t.tolist()
            step_t = math.hypot(x0, x1, x2)
            step_r = math.hypot(x3, x4, x5)
        else:
            # Closed-form step on point pairs, weighted by the same noise model (the kernel acts on
            # the point-to-point distance).
            p = P[m.sel]
            wp = w.copy() if not fine else 1.0 / sv**2
            if fine:
                e_n = np.linalg.norm(q[m.sel] - m.foot, axis=1)
                wp = wp * _kernel_weights(e_n / sv, cfg.robust_kernel, kernel_k)
            T_old = np.eye(4)
            T_old[:3, :3], T_old[:3, 3] = R, t
            T_new = kabsch(m.foot, p, weights=wp)
            xi = _centered_step(T_new, T_old)
            R, t = T_new[:3, :3].copy(), T_new[:3, 3].copy()
            step_t = float(np.linalg.norm(xi[:3]))
            step_r = float(np.linalg.norm(xi[3:]))
        if not fine:
            if step_t < coarse_tol_t and step_r < coarse_tol_r:
                fine = True
                prev_cost = np.inf
                # The fine gate from these matches (the step that follows them is a fraction of
                # the gate floor), so the first fine iteration already works at its own scale.
                gate = max(gate_floor, min(gate, 3.0 * match_scale))
            continue
        new_gate = max(gate_floor, min(gate, 3.0 * median(m.dist)))
        gate_settled = new_gate >= 0.98 * gate
        gate = new_gate
        small_step = step_t < cfg.translation_tol_m and step_r < cfg.rotation_tol_rad
        # Once a step is a small fraction of a sigma in every direction, further iterations
        # cannot change the answer. Gauss-Newton on the plane metric contracts about linearly
        # (each step a fraction rho of the one before), so after a step of s sigmas about
        # s rho / (1 - rho) remains: when that is below the tolerance, confirming it by another
        # iteration is not needed.
        s_k = math.sqrt(step_sigma2)
        rho = s_k / prev_step_sigma if 0.0 < prev_step_sigma < math.inf else math.inf
        small_step = small_step or step_sigma2 < step_tol2 or (
            rho < 0.5 and (s_k * rho / (1.0 - rho)) ** 2 < step_tol2
        )
        prev_step_sigma = s_k
        small_change = abs(prev_cost - cost) <= cfg.residual_tol * max(cost, 1e-12)
        prev_cost = cost
        if gate_settled and (small_step or small_change or stalled):
            converged = True
            # After a sub-tolerance step the matches of this iteration are the final pose's
            # (same faces; residuals are recomputed), so the final pass need not search again.
            if small_step and not stalled and meth == "point_to_plane":
                reuse = m_raw
            break
        if cfg.time_budget_s is not None and time.perf_counter() - t_start > cfg.time_budget_s:
            reason = f"time budget {cfg.time_budget_s} s reached after {it} iterations"
            break
    if not converged and not reason:
        reason = f"not converged after {cfg.max_iterations} iterations"
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    cross_max = None if cross_base is None else np.maximum(cross_base, 3.0 * match_scale)
    return _finish(P, sig, D, mc, T, gate, cfg, converged, reason, it, t_start, along_rays, reuse,
                   cross_max)


def _model_sigma(mc: ModelCloud, cfg: ICPConfig) -> float:
    """Model error [m] in the residual variance: the sampling error of a sample-based model; none
    for a model matched on its exact faces."""
    return 0.0 if mc.grid is not None else float(cfg.model_noise_fraction) * mc.spacing


#: A grazing match (``|n . d|`` below this) is checked for edge ambiguity before it counts.
_GRAZING_COS = 0.25
#: Model normals this far apart (cosine below) are different faces for the ambiguity test.
_OTHER_FACE_COS = 0.7
#: Points along the noise band of a grazing match at which the closest face is checked.
_AMBIGUITY_STEPS = 5


def edge_ambiguous(mc: ModelCloud, foot: FloatArray, normal: FloatArray, sig: FloatArray,
                   cos_ray: FloatArray, n_sigmas: float, rays: FloatArray | None = None) -> npt.NDArray[np.bool_]:
    """Grazing matches that another face of the model explains as well: edge mixing.

    A point whose ray meets its face at a grazing angle carries a large weight in the
    information (its range noise barely moves it off that face), but near an edge the same point
    lies within the noise of the neighbouring face too: a face-on point whose noise put it a few
    centimetres below a box's front face is "on" the side face. Which face it came from is not
    known, so it pins nothing: a wrong pose of a flat face held by a strip of such points would
    otherwise look confident. A grazing match is ambiguous when, along its ray within
    ``n_sigmas`` range sigmas of its foot, the model's closest face turns to one whose normal
    differs by more than ~45 deg (exact faces of the model's :class:`FaceGrid`; without one, a
    surface sample within that distance plus the sample spacing).

    Args:
        mc: the model.
        foot: (K, 3) matched surface points, target frame.
        normal: (K, 3) their unit normals, target frame.
        sig: (K,) range sigma of the points [m].
        cos_ray: (K,) ``normal . ray direction``.
        n_sigmas: the noise band [sigmas].
        rays: (K, 3) unit rays, target frame (needed for the face test).
    """
    out = np.zeros(foot.shape[0], dtype=bool)
    g = np.flatnonzero(np.abs(cos_ray) < _GRAZING_COS)
    if g.size == 0:
        return out
    if mc.grid is None or rays is None:
        r = n_sigmas * sig[g] + mc.spacing
        dist, idx = mc.kdtree.query(foot[g], k=12, distance_upper_bound=float(r.max()))
        near = (idx < mc.points.shape[0]) & (dist <= r[:, None])
        nb = mc.normals[np.minimum(idx, mc.points.shape[0] - 1)]
        other = np.einsum("ikj,ij->ik", nb, normal[g]) < _OTHER_FACE_COS
        out[g] = np.any(near & other, axis=1)
        return out
    steps = np.linspace(-1.0, 1.0, _AMBIGUITY_STEPS)
    band = n_sigmas * sig[g]
    q = (foot[g][None, :, :] + (steps[:, None] * band)[:, :, None] * rays[g][None, :, :]).reshape(-1, 3)
    tol = np.tile(np.maximum(0.2 * band, 1e-3), steps.size)
    found, dist, face, _ = mc.grid.nearest(q, along_rays=False)
    n_face = mc.grid.planes[face][:, 0, :3]
    k = found % g.size
    other = (np.einsum("ij,ij->i", n_face, normal[g][k]) < _OTHER_FACE_COS) & (dist <= tol[found])
    out[g[np.unique(k[other])]] = True
    return out


def _finish(
    P: FloatArray,
    sig: FloatArray,
    D: FloatArray,
    mc: ModelCloud,
    T: FloatArray,
    gate: float,
    cfg: ICPConfig,
    converged: bool,
    reason: str,
    iterations: int,
    t_start: float,
    along_rays: bool = False,
    reuse: _Matches | None = None,
    max_cross: FloatArray | None = None,
) -> RegistrationResult:
    """Final correspondences, fitness and the Cramer-Rao covariance at the returned pose.

    ``reuse``: the matches of the last iteration, whose step was below tolerance; their faces
    are kept (within ``gate``) and only the plane residuals are evaluated at ``T``. ``max_cross``:
    as in :meth:`FaceGrid.nearest`.
    """
    n = P.shape[0]
    R = T[:3, :3]
    t = T[:3, 3]
    d_all = D @ R
    if reuse is None:
        m = _correspond(mc, (P - t) @ R, gate, int(cfg.plane_candidates), d_all,
                        cfg.back_facing_cos, along_rays=along_rays, max_cross=max_cross)
    else:
        m = reuse.keep(reuse.dist <= gate)
        m.r = np.einsum("ij,ij->i", m.normal, (P[m.sel] - t) @ R - m.foot)
    front = np.einsum("ij,ij->i", m.normal, d_all[m.sel]) < cfg.back_facing_cos
    m = m.keep(front)
    n_in = int(m.sel.size)
    min_pts = max(int(cfg.min_points), 6)
    if n_in < min_pts:
        res = RegistrationResult.failure(
            f"{n_in} inliers at the final pose; ICP needs >= {min_pts}",
            T, n_points=n, time_s=time.perf_counter() - t_start, iterations=iterations,
        )
        res.n_inliers = n_in
        res.fitness = n_in / max(n, 1)
        return res
    # The bound is computed pivoting on the centre of the observed surface and judged against
    # that patch's own size, then moved to the target origin exactly. Judging observability about
    # a far origin (or against the whole target's size) would call a 1 m patch seen 12 m from
    # the centre of mass "rotation-degenerate" and, by capping axes at that pivot, throw away
    # the position information the patch does carry.
    foot_s = m.foot @ R.T + t
    c = foot_s.mean(axis=0)
    rows = information_rows(
        foot_s, m.normal @ R.T, sig[m.sel], D[m.sel], c, cfg.noise_floor_fraction,
        _model_sigma(mc, cfg),
    )
    if cfg.edge_ambiguity_sigmas > 0:
        # Edge mixing: grazing matches another face explains as well inform no direction.
        amb = edge_ambiguous(mc, m.foot, m.normal, sig[m.sel],
                             np.einsum("ij,ij->i", m.normal, d_all[m.sel]), cfg.edge_ambiguity_sigmas,
                             d_all[m.sel])
        rows[amb] = 0.0
    H = rows.T @ rows
    dc = (foot_s - c).ravel()
    patch = max(math.sqrt(float(dc @ dc) / n_in), 0.05)
    cov_c, degenerate = covariance_from_information(H, patch, cfg.degeneracy_ratio, rows,
                                                    cfg.min_direction_support)
    J = np.eye(6)
    J[:3, 3:] = -skew(t - c)  # origin shift of a rotation about c: rho_o = rho_c + phi x (t - c)
    cov = J @ cov_c @ J.T
    cov = 0.5 * (cov + cov.T)
    return RegistrationResult(
        T_sensor_target=T,
        fitness=n_in / n,
        inlier_rmse=math.sqrt(float(m.r @ m.r) / n_in),
        converged=converged,
        iterations=iterations,
        covariance=cov,
        degenerate_axes=degenerate,
        reason=reason,
        n_points=n,
        n_inliers=n_in,
        time_s=time.perf_counter() - t_start,
    )
