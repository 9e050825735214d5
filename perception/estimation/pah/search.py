"""The runtime PAH search of one (possibly pooled) scan: :func:`localize` (seed 000 section 3.1.2).

For each polygon picked from the scan (:mod:`.polygons`): match it in the tables, fit a pose per
match, drop mirror images, back-facing and (constrained) out-of-corridor poses, precheck the
survivors on a decimated scan (the fit grid of :mod:`.model`), check the best few on the whole
scan (or the ``search_points`` subset), and screen the distinct best ones by a short ICP
(:mod:`.verify`); the leader's near-symmetric alternatives are verified too (:mod:`.symmetry`).
It stops when a verified leader explains the scan, or the polygon or time budget is spent; the
best hypothesis, and runners-up in other basins, are then refined and the best verified one wins.

The screening and polishing ICPs are reached through the database (``db._screen``,
``db._polish``), so that a stage replaced on :class:`PAHDatabase` is the one the search uses.
"""

from __future__ import annotations

import math
import time
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

from perception.config import ICPConfig
from perception.estimation.registration import (
    RegistrationResult,
    per_point_sigma,
    prepare_model,
    validate_points,
)

from .constraint import PoseConstraint
from .hypotheses import _best, _free_space_allowed, _Hypothesis, _Scan
from .model import _DENSE_POINTS, fit_grid
from .polygons import _pick_polygon, _plausible, _supported, match_polygon
from .poses import _kabsch_batch, _pose, _same_pose, _to_model, _triangle_poses
from .symmetry import _alternatives
from .verify import _beam_check, _refine

if TYPE_CHECKING:
    from .database import PAHDatabase

#: Default wall-clock budgets [s] of :meth:`PAHDatabase.localize`, unconstrained and in a corridor.
#: Seed 000 section 5.3: docking (corridor) acquisition took under a second on the flight
#: computer, unconstrained 5-10 s; a typical acquisition here takes a small fraction of either.
DEFAULT_TIME_BUDGET_S = 5.0
DEFAULT_CONSTRAINED_TIME_BUDGET_S = 1.0

# Partial polygon matches whose poses agree within this fraction of the length tolerance merge.
_MERGE_FRACTION = 1.0
# Candidates kept after the first (quarter-size) precheck, and sent on to the full check.
_PRECHECK_KEEP = 256
_FULL_CHECK = 16
# Distinct hypotheses per polygon polished by a short ICP, and that ICP's iterations.
_SCREEN_PER_POLYGON = 3
_SCREEN_ICP_ITERATIONS = 12


def localize(
    db: PAHDatabase,
    points: npt.ArrayLike,
    rng: np.random.Generator,
    constraint: PoseConstraint | None = None,
    sigma: float | npt.ArrayLike | None = None,
    max_time_s: float | None = None,
    directions: npt.ArrayLike | None = None,
    *,
    search_points: int | None = None,
) -> RegistrationResult:
    """The pose of the target in a scan, without an initial guess (see
    :meth:`PAHDatabase.localize` for the arguments, result and errors)."""
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
    if db.target is None:
        raise ValueError(
            f"PAH database of {db.target_name!r} has no target; pass target= to load() or "
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
    cfg = db.config
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
    tol = max(float(cfg.length_tolerance_m), db.coverage_m) + 2.0 * sig_med
    fit_thr = max(float(cfg.fit_inlier_m), 3.0 * sig_med)
    grid = fit_grid(db.target, db.model_hash, max(float(cfg.fit_inlier_m), db.coverage_m))
    mc = prepare_model(db.target, _DENSE_POINTS)
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
    max_extent = db.max_length_m + 2.0 * tol
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
            cand = match_polygon(db, Q, tol, rng)
        else:
            cand = match_polygon(db, Q, tol, rng, constraint=constraint, rays=rays[poly],
                                      merge_m=_MERGE_FRACTION * tol)
        n_cands += cand.shape[0]
        if cand.shape[0] == 0:
            continue
        # Cheap poses from the first triangle for pruning; SVD only for the survivors.
        R, t = _triangle_poses(db.points[cand], Q)
        keep = _plausible(db, R, t, cand, Q, rays[poly], tol, constraint)
        cand, R, t = cand[keep], R[keep], t[keep]
        if cand.shape[0] == 0:
            continue
        score_a = grid.inside(_to_model(pre_a, R, t)).mean(axis=1)
        top = np.argsort(-score_a, kind="stable")[:_PRECHECK_KEEP]
        cand = cand[top]
        R, t = _kabsch_batch(db.points[cand], Q)
        resid = Q[None] - (np.einsum("kij,knj->kni", R, db.points[cand]) + t[:, None, :])
        keep = np.sqrt(np.mean(np.sum(resid**2, axis=2), axis=1)) <= tol
        keep &= _plausible(db, R, t, cand, Q, rays[poly], tol, constraint)
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
        new = db._screen(scan, starts, hyps, mc, screen_cfg, search)
        hyps += new
        best = _best(hyps, constraint)
        # Verify the leader against the poses it could be confused with (half turns of a
        # long body, quarter turns of a square one): one of them may be the truth.
        if best is not None and not best.expanded:
            best.expanded = True
            hyps += _alternatives(db, best, scan, hyps, mc, screen_cfg, constraint, search)
            best = _best(hyps, constraint)
        if best is not None:
            _beam_check(db.target, scan, best, mc)
        # A leader whose short ICP was still sliding may explain the scan once settled:
        # polish it on every point before paying for another polygon.
        if (best is not None and not best.settled and not best.polished
                and not best.clean(cfg.accept_fitness, n)):
            db._polish(scan, best, mc)
            best = _best(hyps, constraint)  # None if polishing left the corridor
            if best is not None:
                _beam_check(db.target, scan, best, mc)
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
    res, final_fit, final_fs = _refine(db.target, scan, hyps, best, mc, constraint)
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
