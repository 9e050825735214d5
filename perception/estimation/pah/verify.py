"""Verification of PAH pose hypotheses: surface fit, free space, and the ICPs that settle them.

:func:`_verify` scores K poses on the whole scan: the surface fit (inliers within a noise gate of
the dense model, and the likelihood of their point-to-plane residuals) and free space (every scan
ray cast against the model under each pose; a point measured behind the first model surface on
its ray is impossible under that pose, judged over the beam footprint where acceptance hangs on
it). :func:`_screen` polishes start poses by a short ICP (one per basin) and verifies them,
:func:`_polish` settles a hypothesis by a full ICP, and :func:`_refine` refines the leader and
runners-up in other basins and picks the best verified one. Every ICP of a PAH search runs here.
"""

from __future__ import annotations

import math

import numpy as np

from perception.config import ICPConfig
from perception.estimation.registration import (
    ModelCloud,
    RegistrationResult,
    icp,
    per_point_sigma,
    prepare_model,
)
from perception.sensing.sensors.raycast import cast_rays
from perception.targets import TargetModel

from .constraint import PoseConstraint
from .hypotheses import _UNEXPLAINED_PENALTY, _free_space_allowed, _Hypothesis, _Scan
from .model import _DENSE_POINTS
from .poses import FloatArray, _same_pose, _to_model

# ... and only if the rays about it on the rim of the beam footprint, this far off its axis
# [rad], all see it behind the surface too (TriDAR beam: 0.5 mrad full divergence, plus
# pointing quantisation and jitter); _FOOTPRINT_RAYS of them.
_FOOTPRINT_HALF_ANGLE_RAD = 3e-4
_FOOTPRINT_RAYS = 6
# Final refinement: runners-up within this score of the leader, in another basin (farther than
# _BASIN_M or _BASIN_RAD from every start), get the full ICP too; at most _FINAL_STARTS starts.
_RUNNER_UP_MARGIN = 0.15
_BASIN_M = 0.1
_BASIN_RAD = math.radians(10.0)
_FINAL_STARTS = 3
# An unsettled hypothesis fitting this fraction of the leader's fit gets a final full ICP.
_UNSETTLED_FIT = 0.95


def _verify(
    target: TargetModel, scan: _Scan, Ts: FloatArray, mc: ModelCloud, free_space: bool = True,
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
        target: the target model.
        scan: the scan bundle.
        Ts: (K, 4, 4) poses ``T_sensor_target``.
        mc: the dense model.
        free_space: run the ray test (else its column is zero).
        footprint: count a violation only when the whole beam footprint sees it (below).

    Returns:
        fitness (K,), likelihood (K,) and free-space violation fraction (K,).
    """
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
        _, r_model, _ = cast_rays(target, np.repeat(origins, n, axis=0), dirs)
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
            _, r_rim, _ = cast_rays(target, np.repeat(origins[kk], f, axis=0), rim_t)
            with np.errstate(invalid="ignore"):
                deep = scan.ranges[ii, None] > r_rim.reshape(-1, f) + scan.margin[ii, None]
            behind[kk, ii] = deep.all(axis=1)
        fs = behind.mean(axis=1)
    return inl.mean(axis=1), like, fs


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


def _screen(
    target: TargetModel,
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
    fit, like, fs = _verify(target, scan, np.stack(Ts), mc)
    return [_Hypothesis(T, float(a), float(b), float(c), settled=ok)
            for T, a, b, c, ok in zip(Ts, fit, like, fs, settled)]


def _beam_check(target: TargetModel, scan: _Scan, h: _Hypothesis, mc: ModelCloud) -> None:
    """Judge the violations of a hypothesis that fails acceptance on them over the footprint."""
    if h.free_space_beam is None and h.free_space > _free_space_allowed(scan.P.shape[0]):
        h.free_space_beam = float(_verify(target, scan, h.T[None], mc, footprint=True)[2][0])


def _polish(target: TargetModel, scan: _Scan, h: _Hypothesis, mc: ModelCloud) -> None:
    """Full ICP of a hypothesis on every scan point, verified; updates ``h`` in place.

    The short screening ICP (12 iterations) can leave a pose a few degrees short of its
    basin's bottom, where a tight noise gate (triangulation range) sees points behind the
    surface; settled, it may explain the scan outright.
    """
    r = icp(scan.P, mc, h.T, sigma=scan.sigma, directions=scan.rays, match_along_rays=True)
    fit, like, fs = _verify(target, scan, r.T_sensor_target[None], mc)
    h.T = r.T_sensor_target
    h.fitness, h.likelihood, h.free_space = float(fit[0]), float(like[0]), float(fs[0])
    h.settled, h.polished, h.free_space_beam = bool(r.converged), True, None


def _refine(
    target: TargetModel,
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
    fit, like, fs = _verify(target, scan, Ts, mc)
    score = like - _UNEXPLAINED_PENALTY * ((1.0 - fit) + fs)
    if constraint is not None:
        inside = constraint.admits_batch(Ts)
        if inside.any():
            score = np.where(inside, score, -np.inf)
    k = int(np.argmax(score))
    fs_k = float(fs[k])
    if fs_k > _free_space_allowed(scan.P.shape[0]):
        fs_k = float(_verify(target, scan, Ts[k : k + 1], mc, footprint=True)[2][0])
    return results[k], float(fit[k]), fs_k


def verify_poses(
    target: TargetModel, points: FloatArray, sigma: float | FloatArray, Ts: FloatArray,
    directions: FloatArray | None = None,
) -> tuple[FloatArray, FloatArray]:
    """(fitness, score) of K poses on a scan (see :meth:`PAHDatabase.verify_poses`)."""
    P = np.asarray(points, dtype=np.float64)
    sig = per_point_sigma(sigma, P.shape[0])
    mc = prepare_model(target, _DENSE_POINTS)
    rays = None if directions is None else np.asarray(directions, dtype=np.float64)
    scan = _Scan.build(P, sig, rays, mc.spacing)
    fit, like, fs = _verify(target, scan, np.asarray(Ts, dtype=np.float64).reshape(-1, 4, 4), mc)
    return fit, like - _UNEXPLAINED_PENALTY * ((1.0 - fit) + fs)
