"""Rigid-pose helpers of PAH: batched Kabsch fits, triangle frames, pose comparison.

Shared by the table traversal (:mod:`.polygons`), the search (:mod:`.search`), verification
(:mod:`.verify`) and the near-symmetry search (:mod:`.symmetry`). Also the array type aliases.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]


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


def _pose(R: FloatArray, t: FloatArray) -> FloatArray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


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
