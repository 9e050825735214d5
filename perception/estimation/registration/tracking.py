"""ICP tracking (seed 000 section 3.2): :func:`icp`, the loop that runs the phases in order.

Each iteration: correspondences (:mod:`.correspondence`), gates and weights (:mod:`.weights`), one
step (:mod:`.step`) and the stop rule (:mod:`.stopping`); then the final pass at the returned pose
(:mod:`.final`) with the covariance of :mod:`.covariance`.
"""

from __future__ import annotations

import time
from typing import Literal

import numpy as np
import numpy.typing as npt

from perception.config import ICPConfig
from perception.estimation.registration.correspondence import Matches, correspond
from perception.estimation.registration.final import final_pass
from perception.estimation.registration.model import ModelCloud, model_sigma, prepare_model
from perception.estimation.registration.result import RegistrationResult
from perception.estimation.registration.scan import usable_scan
from perception.estimation.registration.step import apply_step, gauss_newton_step, kabsch_step
from perception.estimation.registration.stopping import StopRule
from perception.estimation.registration.weights import Gates, noise_variance, robust_weights
from perception.geometry import check_rigid
from perception.numeric import median
from perception.targets import TargetModel

Method = Literal["point_to_plane", "point_to_point"]


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
        # ValueError (not TypeError): the documented error of every bad argument here.
        raise ValueError(  # noqa: TRY004
            f"model is a {type(model).__name__}; expected a TargetModel or ModelCloud")
    T = check_rigid(init_T_sensor_target, "init_T_sensor_target").copy()
    P, sig, D, n_given = usable_scan(points, sigma, directions)
    n = int(P.shape[0])
    min_pts = max(int(cfg.min_points), 6)
    if n < min_pts:
        return RegistrationResult.failure(
            f"{n} finite scan points (of {n_given}); ICP needs >= {min_pts}",
            T, n_points=n, time_s=time.perf_counter() - t_start,
        )

    floor_frac = float(cfg.noise_floor_fraction)
    model_sig = model_sigma(mc, cfg)
    gates = Gates.start(cfg, mc, sig)
    stop = StopRule.start(cfg, gates.floor, mc.radius)
    back_cos = float(cfg.back_facing_cos)
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
    fine = not coarse
    converged = False
    reason = ""
    it = 0
    reuse: Matches | None = None
    for it in range(1, cfg.max_iterations + 1):
        # Correspondences. Everything per point is in the target frame; only the step is rotated.
        q = (P - t) @ R
        d_all = D @ R
        cross_max = (np.maximum(cross_base, 3.0 * match_scale)
                     if cross_base is not None and fine else None)
        m = m_raw = correspond(
            mc, q, gates.gate, n_candidates if fine else 1, d_all, back_cos,
            meth == "point_to_point", along_rays, cross_max,
        )
        if m.dist.size:
            match_scale = median(m.dist)
        # Gates, trimming and front faces: one mask over the matches, applied once.
        kept, cos = gates.select(m, d_all, back_cos, min_pts, match_scale)
        nv = int(np.count_nonzero(kept))
        if nv < min_pts:
            return RegistrationResult.failure(
                f"{nv} correspondences within {gates.gate:.3g} m at iteration {it}; "
                f"ICP needs >= {min_pts}",
                T, n_points=n, time_s=time.perf_counter() - t_start, iterations=it,
            )
        if nv < m.sel.size:
            m = m.keep(kept)
            cos = cos[kept]
        # Weights.
        var = noise_variance(sig[m.sel], cos, floor_frac, model_sig)
        w = robust_weights(m, var, fine, cfg, gates.floor)
        cost = float(((w * m.r) @ m.r) / (w @ var))
        # One step.
        if meth == "point_to_plane":
            trust = gates.floor if fine else gates.gate
            xi_t, H = gauss_newton_step(q, m, w, fine, trust, mc.radius)
            if fine:
                xi_t = stop.limit_cycle(xi_t, H, cost)
            R, t, step_t, step_r = apply_step(R, t, xi_t)
        else:
            R, t, step_t, step_r = kabsch_step(P, q, sig, m, w, fine, cfg, R, t)
        # Stop rule.
        if not fine:
            if stop.coarse_done(step_t, step_r):
                fine = True
                gates.to_fine(match_scale)
            continue
        gate_settled = gates.shrink(m.dist)
        done, small_step = stop.done(step_t, step_r, cost, gate_settled)
        if done:
            converged = True
            # After a sub-tolerance step the matches of this iteration are the final pose's
            # (same faces; residuals are recomputed), so the final pass need not search again.
            if small_step and not stop.stalled and meth == "point_to_plane":
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
    return final_pass(P, sig, D, mc, T, gates.gate, cfg, converged, reason, it, t_start,
                      along_rays, reuse, cross_max)
