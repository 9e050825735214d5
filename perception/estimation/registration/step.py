"""One ICP step: the Gauss-Newton point-to-plane step on SE(3) (with the point-to-point term of
the coarse phase and a trust region), or the closed-form point-to-point (Kabsch) step of the
seed-003 baseline; and the residual's Jacobian rows, which the covariance shares.

The twist ``xi = (rho, phi)`` is a translation of the target origin and a rotation about it, in
the target frame: the model point ``x`` moves to ``x + rho + phi x x``.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

from perception.config import ICPConfig
from perception.estimation.registration.correspondence import Matches
from perception.estimation.registration.weights import kernel_weights
from perception.geometry import cross_rows, fast_rotvec_to_matrix, kabsch, se3_log, skew

FloatArray = npt.NDArray[np.float64]


def jacobian_rows(s_rel: FloatArray, n_sensor: FloatArray) -> FloatArray:
    """Rows ``A_i = [n_i, s_i x n_i]`` with ``r_i(xi) ~= r_i - A_i xi``, ``s_i`` about the pivot."""
    A = np.empty((n_sensor.shape[0], 6))
    A[:, :3] = n_sensor
    A[:, 3:] = cross_rows(s_rel, n_sensor)
    return A


def gauss_newton_step(
    q: FloatArray, m: Matches, w: FloatArray, fine: bool, trust: float, radius: float
) -> tuple[FloatArray, FloatArray]:
    """The weighted point-to-plane Gauss-Newton step of the matches ``m``.

    Args:
        q: (N, 3) scan points, target frame.
        m: the matches kept.
        w: (K,) their weights.
        fine: fine phase; otherwise (coarse) the point-to-point residual is added.
        trust: longest step [m] at the model's ``radius`` [m]; a longer one is scaled down.

    Returns:
        The twist ``xi`` (6,) and the information ``H`` (6, 6) of the step's linear system.
    """
    r = m.r
    # Linearised about the target origin, not the sensor origin: a finite rotation step
    # then does not swing the target about a lever arm of the full range.
    c = m.foot
    A = jacobian_rows(c, m.normal)
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
    x0, x1, x2, x3, x4, x5 = xi_t.tolist()
    reach = math.hypot(x0, x1, x2) + radius * math.hypot(x3, x4, x5)
    if reach > trust:
        xi_t = xi_t * (trust / reach)
    return xi_t, Hm


def apply_step(
    R: FloatArray, t: FloatArray, xi_t: FloatArray
) -> tuple[FloatArray, FloatArray, float, float]:
    """The pose ``(R, t)`` (sensor from target) moved by the twist ``xi_t``, and the step's
    translation [m] and rotation [rad]."""
    # In the target frame the model point x moves to x + rho + phi x x; in the sensor
    # frame that is t += R rho, R <- R exp(phi) (= exp(R phi) R about the target origin).
    t = t + R @ xi_t[:3]
    R = R @ fast_rotvec_to_matrix(xi_t[3:])
    x0, x1, x2, x3, x4, x5 = xi_t.tolist()
    step_t = math.hypot(x0, x1, x2)
    step_r = math.hypot(x3, x4, x5)
    return R, t, step_t, step_r


def kabsch_step(
    P: FloatArray, q: FloatArray, sig: FloatArray, m: Matches, w: FloatArray, fine: bool,
    cfg: ICPConfig, R: FloatArray, t: FloatArray,
) -> tuple[FloatArray, FloatArray, float, float]:
    """Closed-form step on point pairs, weighted by the same noise model (in the fine phase the
    kernel acts on the point-to-point distance): the new pose ``(R, t)`` and the step's
    translation [m] and rotation [rad].

    Args:
        P: (N, 3) scan points, sensor frame; ``q`` the same in the target frame.
        sig: (N,) range sigmas [m].
        m: the matches kept; ``w`` their weights.
        fine: fine phase.
        cfg: the kernel's kind and scale.
        R, t: the current pose.
    """
    sv = sig[m.sel]
    p = P[m.sel]
    wp = w.copy() if not fine else 1.0 / sv**2
    if fine:
        e_n = np.linalg.norm(q[m.sel] - m.foot, axis=1)
        wp = wp * kernel_weights(e_n / sv, cfg.robust_kernel, float(cfg.kernel_scale))
    T_old = np.eye(4)
    T_old[:3, :3], T_old[:3, 3] = R, t
    T_new = kabsch(m.foot, p, weights=wp)
    xi = centered_step(T_new, T_old)
    R, t = T_new[:3, :3].copy(), T_new[:3, 3].copy()
    step_t = float(np.linalg.norm(xi[:3]))
    step_r = float(np.linalg.norm(xi[3:]))
    return R, t, step_t, step_r


def centered_step(T_new: FloatArray, T_old: FloatArray) -> FloatArray:
    """Twist ``xi`` with ``T_new ~= Tr(t) exp(xi) Tr(-t) T_old`` (translation and rotation parts)."""
    dR = T_new[:3, :3] @ T_old[:3, :3].T
    phi = se3_log(np.block([[dR, np.zeros((3, 1))], [np.zeros((1, 3)), np.ones((1, 1))]]))[3:]
    return np.concatenate([T_new[:3, 3] - T_old[:3, 3], phi])
