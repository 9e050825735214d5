"""Near-symmetries of a target, and the alternatives of a PAH hypothesis that they give.

A near-symmetry is a rigid motion ``G`` of the target frame that maps the model nearly onto
itself (the half turn of a two-winged bus about its port axis, the quarter turns of a square
one): ``T @ G`` is a pose a partial scan may fit about as well as ``T``. They are found once per
target (:func:`_near_symmetries`, cached on it), and the leading hypothesis of a search is always
verified against its alternatives (:func:`_alternatives`), so the flip competes even when no
polygon produced it.
"""

from __future__ import annotations

import dataclasses
import math
from typing import TYPE_CHECKING

import numpy as np

from perception.config import ICPConfig
from perception.estimation.registration import ModelCloud, prepare_model
from perception.targets import TargetModel

from .constraint import PoseConstraint
from .hypotheses import _Hypothesis, _Scan
from .model import _DENSE_POINTS
from .poses import FloatArray, _kabsch_batch, _pose
from .verify import _verify

if TYPE_CHECKING:
    from .database import PAHDatabase

# Near-symmetries: rotations of the model about its centroid that map at least this fraction of
# its surface to within _SYMMETRY_GATE_M of itself; at most _MAX_SYMMETRIES are kept.
_SYMMETRY_OVERLAP = 0.6
_SYMMETRY_GATE_M = 0.05
_MAX_SYMMETRIES = 10
_SYMMETRY_SAMPLES = 600
# Two rotations closer than ~25 deg (trace of R_a^T R_b above this) count as one turn.
_TURN_MIN_TRACE = 1.0 + 2.0 * math.cos(math.radians(25.0))
_SYMMETRY_ICP_STEPS = 6
# Alternatives of a leader that get the short ICP (best raw fit first).
_ALTERNATIVES_SCREENED = 8


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


def _near_symmetries(target: TargetModel, model_hash: str) -> FloatArray:
    """(S, 4, 4) rigid motions ``G`` of the target frame that nearly map the model onto itself.

    Candidates are the 23 turns of the cube group about the centroid (quarter and half turns
    about the axes, half turns about the face diagonals, third turns about the body
    diagonals), in the frame of the principal axes of the surface and in the body frame; a
    candidate is kept when it maps at least
    ``_SYMMETRY_OVERLAP`` of the surface to within ``_SYMMETRY_GATE_M`` of the surface
    (best first, at most ``_MAX_SYMMETRIES``). ``T @ G`` is then a pose a partial scan may
    fit as well as ``T``. Cached on the target.
    """
    mc = prepare_model(target, _DENSE_POINTS)

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

    return target.cached(("pah_near_symmetries", model_hash), build)  # type: ignore[no-any-return]


def _alternatives(
    db: PAHDatabase,
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
    assert db.target is not None
    G = _near_symmetries(db.target, db.model_hash)
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
    fit, _, _ = _verify(db.target, loose, Ts, mc, free_space=False)
    order = np.argsort(-fit, kind="stable")[:_ALTERNATIVES_SCREENED]
    starts = [Ts[i] for i in order if fit[i] >= 0.5 * h.fitness]
    return db._screen(scan, starts, known, mc, icp_cfg, icp_scan)
