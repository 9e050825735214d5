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

import time
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
import numpy.typing as npt
from scipy.spatial import cKDTree

from perception.config import ICPConfig
from perception.geometry import check_rigid, invert, kabsch, se3_exp, se3_log, skew
from perception.targets import TargetModel

FloatArray = npt.NDArray[np.float64]

__all__ = [
    "AXIS_NAMES",
    "FAILURE_VARIANCE",
    "ModelCloud",
    "RegistrationResult",
    "prepare_model",
    "icp",
    "information_matrix",
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
    """

    points: FloatArray
    normals: FloatArray
    kdtree: cKDTree
    spacing: float
    radius: float
    name: str = ""
    model_hash: str = ""

    @classmethod
    def from_arrays(
        cls,
        points: npt.ArrayLike,
        normals: npt.ArrayLike,
        area_m2: float | None = None,
        name: str = "",
        model_hash: str = "",
    ) -> ModelCloud:
        """Build from surface samples and normals (target frame).

        Args:
            points: (M, 3) samples [m], M >= 3.
            normals: (M, 3) normals (normalised here).
            area_m2: surface area the samples cover [m^2]; estimated from nearest-neighbour
                distances when None.
            name: label.
            model_hash: geometry hash to carry along.
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
        )


def prepare_model(target: TargetModel, n_points: int = 20_000, seed: int = 0) -> ModelCloud:
    """Dense surface samples + normals + KD-tree of a target, built once and cached on it.

    Args:
        target: the target model (body frame, origin at the centre of mass).
        n_points: number of area-uniform samples (>= 100). 20,000 gives ~1 cm resolution on a
            1 m satellite, the 1-5 cm model resolution of seed 000 section 3.2.
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
            model_hash=target.model_hash,
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


def _per_point_sigma(sigma: float | npt.ArrayLike | None, n: int) -> FloatArray:
    if sigma is None:
        return np.full(n, 0.01)
    s = np.asarray(sigma, dtype=np.float64)
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
    return np.hstack([n_sensor, np.cross(s_rel, n_sensor)])


def _residual_variance(
    sig: FloatArray,
    n_sensor: FloatArray,
    d_sensor: FloatArray,
    floor_fraction: float,
    model_sigma: float = 0.0,
) -> FloatArray:
    cos = np.einsum("ij,ij->i", n_sensor, d_sensor)
    return sig**2 * (cos**2 + floor_fraction**2) + model_sigma**2


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
    S = np.asarray(points_model_sensor, dtype=np.float64)
    Nn = np.asarray(normals_sensor, dtype=np.float64)
    D = np.asarray(directions, dtype=np.float64)
    c = np.asarray(center, dtype=np.float64).reshape(3)
    sig = np.broadcast_to(np.asarray(sigma, dtype=np.float64), (S.shape[0],))
    A = _jacobian_rows(S - c, Nn)
    w = 1.0 / _residual_variance(sig, Nn, D, floor_fraction, model_sigma_m)
    return (A * w[:, None]).T @ A


def covariance_from_information(
    H: npt.ArrayLike, length_scale_m: float, degeneracy_ratio: float = 1e-4
) -> tuple[FloatArray, list[str]]:
    """Invert an information matrix, flagging and capping unobservable directions.

    Rotations are scaled by ``length_scale_m`` (a rotation ``phi`` moves the target's points by
    ~``L phi``) so translation and rotation information compare fairly. Eigenvalues below
    ``degeneracy_ratio`` times the largest are unobservable: their variance is
    :data:`FAILURE_VARIANCE` and the dominant component of each such eigenvector is named in the
    returned list.

    Args:
        H: (6, 6) information matrix in the twist of :attr:`RegistrationResult.covariance`.
        length_scale_m: characteristic size of the target [m] (its radius).
        degeneracy_ratio: relative eigenvalue threshold.

    Returns:
        (6, 6) covariance and the list of degenerate axis names (ordered as :data:`AXIS_NAMES`).
    """
    H = np.asarray(H, dtype=np.float64)
    L = max(float(length_scale_m), 1e-6)
    S = np.diag([1.0, 1.0, 1.0, 1.0 / L, 1.0 / L, 1.0 / L])
    Hs = S @ (0.5 * (H + H.T)) @ S
    if not np.all(np.isfinite(Hs)):
        return FAILURE_VARIANCE * np.eye(6), list(AXIS_NAMES)
    lam, V = np.linalg.eigh(Hs)
    lam_max = float(lam[-1])
    if lam_max <= 0:
        return FAILURE_VARIANCE * np.eye(6), list(AXIS_NAMES)
    weak = lam < degeneracy_ratio * lam_max
    inv = np.where(weak, 0.0, 1.0 / np.where(weak, 1.0, lam))
    cov = S @ ((V * inv) @ V.T) @ S
    names: set[str] = set()
    for k in np.flatnonzero(weak):
        names.add(AXIS_NAMES[int(np.argmax(np.abs(V[:, k])))])
    # The pseudo-inverse is blind along unobservable directions; the named axes get the huge
    # variance on their diagonal instead (other axes keep their bound).
    for a in names:
        i = AXIS_NAMES.index(a)
        cov[i, i] += FAILURE_VARIANCE
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
    the chosen sample (inf where none is within ``gate``) and its index.
    """
    dist, idx = mc.kdtree.query(q, k=k, distance_upper_bound=gate, workers=1)
    ok = np.isfinite(dist)
    safe = np.where(ok, idx, 0)
    r = np.abs(np.einsum("ijk,ijk->ij", mc.normals[safe], q[:, None, :] - mc.points[safe]))
    r = np.where(ok, r, np.inf)
    best = np.argmin(r, axis=1)
    rows = np.arange(q.shape[0])
    return dist[rows, best], idx[rows, best]


def _apply_centered(T: FloatArray, xi: FloatArray) -> FloatArray:
    """``T_new``: target translated by ``V rho`` and rotated by ``exp(phi)`` about its own origin."""
    dT = se3_exp(xi)
    out = T.copy()
    out[:3, :3] = dT[:3, :3] @ T[:3, :3]
    out[:3, 3] = T[:3, 3] + dT[:3, 3]
    return out


def _centered_step(T_new: FloatArray, T_old: FloatArray) -> FloatArray:
    """Twist ``xi`` with ``_apply_centered(T_old, xi) ~= T_new`` (translation and rotation parts)."""
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
    (the scan only sees front faces; this matters on thin panels).

    Args:
        points: (N, 3) scan points [m], sensor frame. Non-finite rows are ignored.
        model: a :class:`TargetModel` (prepared and cached with ``config.model_points`` samples)
            or a prepared :class:`ModelCloud`.
        init_T_sensor_target: (4, 4) initial guess (previous frame's pose or a prediction).
        sigma: range-noise 1-sigma [m], a float or (N,) per point; default 0.01 m.
        method: ``"point_to_plane"`` (Gauss-Newton on SE(3)) or ``"point_to_point"`` (Kabsch);
            default ``config.method``.
        config: tuning; defaults of :class:`~perception.config.ICPConfig` when None.
        directions: (N, 3) unit ray directions [sensor frame] along which each point's range
            noise acts. Default: ``points / |points|`` (rays from the sensor origin). They set the
            point-to-plane residual variance ``sigma_i^2 ((n_i . d_i)^2 + f^2) + sigma_model^2``
            used both to weight the solve and in the covariance, with
            ``f = config.noise_floor_fraction`` and ``sigma_model = config.model_noise_fraction *``
            the model spacing (see :func:`information_matrix`).

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
    sig_all = _per_point_sigma(sigma, P_all.shape[0])
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
    model_sig = float(cfg.model_noise_fraction) * mc.spacing
    gate_floor = max(cfg.min_correspondence_m, 4.0 * float(np.median(sig)), 1.5 * mc.spacing)
    gate = max(cfg.max_correspondence_m, gate_floor)
    trim = float(cfg.trim_fraction)
    kernel_k = float(cfg.kernel_scale)
    back_cos = float(cfg.back_facing_cos)
    # The coarse phase hands over once its steps are a fraction of the gate floor.
    coarse_tol_t = max(10.0 * cfg.translation_tol_m, 0.25 * gate_floor)
    coarse_tol_r = max(10.0 * cfg.rotation_tol_rad, 0.25 * gate_floor / mc.radius)
    n_candidates = int(cfg.plane_candidates)
    fine = False
    prev_cost = np.inf
    converged = False
    reason = ""
    it = 0
    for it in range(1, cfg.max_iterations + 1):
        R = T[:3, :3]
        t = T[:3, 3]
        q = (P - t) @ R  # scan points in the target frame
        if fine and n_candidates > 1:
            dist, idx = _best_plane_match(mc, q, gate, n_candidates)
        else:
            dist, idx = mc.kdtree.query(q, k=1, distance_upper_bound=gate, workers=1)
        valid = np.isfinite(dist)
        if trim > 0.0 and np.count_nonzero(valid) > min_pts:
            thr = float(np.quantile(dist[valid], 1.0 - trim))
            if thr > gate_floor:
                valid &= dist <= thr
        j = idx[valid]
        n_s = mc.normals[j] @ R.T
        front = np.einsum("ij,ij->i", n_s, D[valid]) < back_cos
        valid[valid] = front
        nv = int(np.count_nonzero(valid))
        if nv < min_pts:
            return RegistrationResult.failure(
                f"{nv} correspondences within {gate:.3g} m at iteration {it}; ICP needs >= {min_pts}",
                T, n_points=n, time_s=time.perf_counter() - t_start, iterations=it,
            )
        j = j[front]
        n_s = n_s[front]
        p = P[valid]
        s_s = mc.points[j] @ R.T + t
        r = np.einsum("ij,ij->i", n_s, p - s_s)
        var = _residual_variance(sig[valid], n_s, D[valid], floor_frac, model_sig)
        w = 1.0 / var
        if fine:
            w = w * _kernel_weights(r / np.sqrt(var), cfg.robust_kernel, kernel_k)
        else:
            # Soft (Cauchy) down-weighting on the distance, scaled by the current spread: parts
            # missing from the model cannot drag the coarse solution, a misaligned face still pulls.
            dv = dist[valid]
            w = w * _kernel_weights(dv / max(gate_floor, 1.5 * float(np.median(dv))), "cauchy", 1.0)
        cost = float(np.sum(w * r * r) / np.sum(w * var))
        if meth == "point_to_plane":
            # Linearised about the target origin, not the sensor origin: a finite rotation step
            # then does not swing the target about a lever arm of the full range.
            c = s_s - t
            A = _jacobian_rows(c, n_s)
            Aw = A * w[:, None]
            Hm = Aw.T @ A
            g = Aw.T @ r
            if not fine:
                # Coarse: add the point-to-point residual e = p - s, e(xi) ~= e - [I, -c^] xi,
                # which widens the basin of the plane metric (it cannot slide along faces).
                e = p - s_s
                ws = float(np.sum(w))
                Sc = (c * w[:, None]).sum(axis=0)
                Hpp = np.zeros((6, 6))
                Hpp[:3, :3] = ws * np.eye(3)
                Hpp[:3, 3:] = -skew(Sc)
                Hpp[3:, :3] = skew(Sc)
                cc = (c * w[:, None]).T @ c
                Hpp[3:, 3:] = np.trace(cc) * np.eye(3) - cc
                gpp = np.concatenate([(e * w[:, None]).sum(axis=0), (np.cross(c, e) * w[:, None]).sum(axis=0)])
                Hm = Hm + Hpp
                g = g + gpp
            damp = 1e-9 * float(np.max(np.diag(Hm))) + 1e-12
            try:
                xi = np.linalg.solve(Hm + damp * np.eye(6), g)
            except np.linalg.LinAlgError:
                xi = np.linalg.lstsq(Hm, g, rcond=None)[0]
            T = _apply_centered(T, xi)
        else:
            # Closed-form step on point pairs, weighted by the same noise model (the kernel acts on
            # the point-to-point distance).
            sv = sig[valid]
            wp = w.copy() if not fine else 1.0 / sv**2
            if fine:
                e = np.linalg.norm(p - s_s, axis=1)
                wp = wp * _kernel_weights(e / sv, cfg.robust_kernel, kernel_k)
            T_old = T
            T = kabsch(mc.points[j], p, weights=wp)
            xi = _centered_step(T, T_old)
        step_t = float(np.linalg.norm(xi[:3]))
        step_r = float(np.linalg.norm(xi[3:]))
        if not fine:
            if step_t < coarse_tol_t and step_r < coarse_tol_r:
                fine = True
                prev_cost = np.inf
            continue
        new_gate = max(gate_floor, min(gate, 3.0 * float(np.median(dist[valid]))))
        gate_settled = new_gate >= 0.98 * gate
        gate = new_gate
        small_step = step_t < cfg.translation_tol_m and step_r < cfg.rotation_tol_rad
        small_change = abs(prev_cost - cost) <= cfg.residual_tol * max(cost, 1e-12)
        prev_cost = cost
        if gate_settled and (small_step or small_change):
            converged = True
            break
        if cfg.time_budget_s is not None and time.perf_counter() - t_start > cfg.time_budget_s:
            reason = f"time budget {cfg.time_budget_s} s reached after {it} iterations"
            break
    if not converged and not reason:
        reason = f"not converged after {cfg.max_iterations} iterations"
    return _finish(P, sig, D, mc, T, gate, cfg, converged, reason, it, t_start)


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
) -> RegistrationResult:
    """Final correspondences, fitness and the Cramer-Rao covariance at the returned pose."""
    n = P.shape[0]
    R = T[:3, :3]
    t = T[:3, 3]
    if cfg.plane_candidates > 1:
        dist, idx = _best_plane_match(mc, (P - t) @ R, gate, int(cfg.plane_candidates))
    else:
        dist, idx = mc.kdtree.query((P - t) @ R, k=1, distance_upper_bound=gate, workers=1)
    inl = np.isfinite(dist)
    j = idx[inl]
    n_s = mc.normals[j] @ R.T
    front = np.einsum("ij,ij->i", n_s, D[inl]) < cfg.back_facing_cos
    inl[inl] = front
    n_in = int(np.count_nonzero(inl))
    min_pts = max(int(cfg.min_points), 6)
    if n_in < min_pts:
        res = RegistrationResult.failure(
            f"{n_in} inliers at the final pose; ICP needs >= {min_pts}",
            T, n_points=n, time_s=time.perf_counter() - t_start, iterations=iterations,
        )
        res.n_inliers = n_in
        res.fitness = n_in / max(n, 1)
        return res
    j = j[front]
    n_s = n_s[front]
    s_s = mc.points[j] @ R.T + t
    r = np.einsum("ij,ij->i", n_s, P[inl] - s_s)
    H = information_matrix(
        s_s, n_s, sig[inl], D[inl], t, cfg.noise_floor_fraction,
        cfg.model_noise_fraction * mc.spacing,
    )
    cov, degenerate = covariance_from_information(H, mc.radius, cfg.degeneracy_ratio)
    return RegistrationResult(
        T_sensor_target=T,
        fitness=n_in / n,
        inlier_rmse=float(np.sqrt(np.mean(r * r))),
        converged=converged,
        iterations=iterations,
        covariance=cov,
        degenerate_axes=degenerate,
        reason=reason,
        n_points=n,
        n_inliers=n_in,
        time_s=time.perf_counter() - t_start,
    )
