"""ICP's final pass at the returned pose: its correspondences, fitness and inlier RMSE, and the
Cramer-Rao covariance of the frame (edge-ambiguous matches left out), as a
:class:`RegistrationResult`."""

from __future__ import annotations

import math
import time

import numpy as np
import numpy.typing as npt

from perception.config import ICPConfig
from perception.estimation.registration.correspondence import Matches, correspond, edge_ambiguous
from perception.estimation.registration.covariance import (
    covariance_from_information,
    information_rows,
)
from perception.estimation.registration.model import ModelCloud, model_sigma
from perception.estimation.registration.result import RegistrationResult
from perception.geometry import skew

FloatArray = npt.NDArray[np.float64]


def final_pass(
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
    reuse: Matches | None = None,
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
        m = correspond(mc, (P - t) @ R, gate, int(cfg.plane_candidates), d_all,
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
        model_sigma(mc, cfg),
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
