"""SE(3) and SO(3) helpers: homogeneous transforms, quaternions at the API edges, rigid fits.

Conventions (DESIGN.md): a pose ``T_a_b`` is a 4x4 homogeneous matrix that maps b-coordinates into
a-coordinates, ``p_a = T_a_b @ p_b``. Quaternions at API edges are scalar-first ``(w, x, y, z)``,
Hamilton, unit norm, with ``w >= 0``. Inside, rotations are ``scipy.spatial.transform.Rotation``.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt
from scipy.spatial.transform import Rotation

FloatArray = npt.NDArray[np.float64]

__all__ = [
    "make_T",
    "compose",
    "invert",
    "transform_points",
    "transform_vectors",
    "is_rigid",
    "check_rigid",
    "quat_to_matrix",
    "matrix_to_quat",
    "quat_canonical",
    "rotation_from_quat",
    "quat_from_rotation",
    "T_from_quat_pos",
    "skew",
    "se3_exp",
    "se3_log",
    "kabsch",
    "pose_error",
    "rotation_angle",
]


def make_T(R: npt.ArrayLike | Rotation | None = None, t: npt.ArrayLike | None = None) -> FloatArray:
    """Build a 4x4 homogeneous transform from a rotation and a translation.

    Args:
        R: (3, 3) rotation matrix or a ``Rotation``; identity when None.
        t: (3,) translation [m]; zero when None.

    Returns:
        (4, 4) float64 transform.
    """
    T = np.eye(4)
    if R is not None:
        T[:3, :3] = R.as_matrix() if isinstance(R, Rotation) else np.asarray(R, dtype=np.float64)
    if t is not None:
        T[:3, 3] = np.asarray(t, dtype=np.float64).reshape(3)
    return T


def compose(*Ts: npt.ArrayLike) -> FloatArray:
    """Compose transforms left to right: ``compose(T_a_b, T_b_c) == T_a_c``. Batches broadcast."""
    if not Ts:
        return np.eye(4)
    out = np.asarray(Ts[0], dtype=np.float64)
    for T in Ts[1:]:
        out = out @ np.asarray(T, dtype=np.float64)
    return out


def invert(T: npt.ArrayLike) -> FloatArray:
    """Invert rigid transforms exactly (transpose rotation), shape (..., 4, 4)."""
    T = np.asarray(T, dtype=np.float64)
    R = T[..., :3, :3]
    t = T[..., :3, 3]
    Rt = np.swapaxes(R, -1, -2)
    out = np.zeros_like(T)
    out[..., :3, :3] = Rt
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", Rt, t)
    out[..., 3, 3] = 1.0
    return out


def transform_points(T: npt.ArrayLike, points: npt.ArrayLike) -> FloatArray:
    """Apply ``T`` (4, 4) to points (N, 3); returns (N, 3)."""
    T = np.asarray(T, dtype=np.float64)
    p = np.asarray(points, dtype=np.float64)
    return p @ T[:3, :3].T + T[:3, 3]


def transform_vectors(T: npt.ArrayLike, vectors: npt.ArrayLike) -> FloatArray:
    """Rotate direction vectors (N, 3) by the rotation part of ``T`` (no translation)."""
    T = np.asarray(T, dtype=np.float64)
    return np.asarray(vectors, dtype=np.float64) @ T[:3, :3].T


def is_rigid(T: npt.ArrayLike, tol: float = 1e-6) -> bool:
    """True when ``T`` is a finite 4x4 proper rigid transform within ``tol``."""
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        return False
    R = T[:3, :3]
    return bool(
        np.allclose(R.T @ R, np.eye(3), atol=tol)
        and abs(np.linalg.det(R) - 1.0) < tol
        and np.allclose(T[3], [0.0, 0.0, 0.0, 1.0], atol=tol)
    )


def check_rigid(T: npt.ArrayLike, name: str = "T", tol: float = 1e-6) -> FloatArray:
    """Return ``T`` as float64 or raise ``ValueError`` naming ``name`` when it is not rigid."""
    arr = np.asarray(T, dtype=np.float64)
    if arr.shape != (4, 4):
        raise ValueError(f"{name} has shape {arr.shape}; expected a (4, 4) homogeneous transform")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} has non-finite entries; expected a finite rigid transform")
    if not is_rigid(arr, tol):
        raise ValueError(f"{name} is not a rigid transform (rotation not orthonormal with det +1)")
    return arr


def quat_canonical(q: npt.ArrayLike) -> FloatArray:
    """Normalise scalar-first quaternions (..., 4) and flip sign so that ``w >= 0``."""
    q = np.asarray(q, dtype=np.float64)
    n = np.linalg.norm(q, axis=-1, keepdims=True)
    if np.any(~np.isfinite(n)) or np.any(n < 1e-12):
        raise ValueError("quaternion has zero or non-finite norm; expected a unit (w, x, y, z)")
    q = q / n
    return np.where(q[..., :1] < 0.0, -q, q)


def rotation_from_quat(q_wxyz: npt.ArrayLike) -> Rotation:
    """``Rotation`` from scalar-first quaternion(s) (..., 4)."""
    q = quat_canonical(q_wxyz)
    return Rotation.from_quat(q[..., [1, 2, 3, 0]])


def quat_from_rotation(rot: Rotation) -> FloatArray:
    """Scalar-first canonical quaternion(s) from a ``Rotation``."""
    q = rot.as_quat()
    return quat_canonical(q[..., [3, 0, 1, 2]])


def quat_to_matrix(q_wxyz: npt.ArrayLike) -> FloatArray:
    """(..., 3, 3) rotation matrices from scalar-first quaternions (..., 4)."""
    return rotation_from_quat(q_wxyz).as_matrix()


def matrix_to_quat(R: npt.ArrayLike) -> FloatArray:
    """Scalar-first canonical quaternions (..., 4) from rotation matrices (..., 3, 3)."""
    return quat_from_rotation(Rotation.from_matrix(np.asarray(R, dtype=np.float64)))


def T_from_quat_pos(q_wxyz: npt.ArrayLike, position: npt.ArrayLike) -> FloatArray:
    """4x4 transform from a scalar-first quaternion and a position [m]."""
    return make_T(quat_to_matrix(q_wxyz), position)


def skew(v: npt.ArrayLike) -> FloatArray:
    """Cross-product matrices (..., 3, 3) of vectors (..., 3): ``skew(a) @ b == cross(a, b)``."""
    v = np.asarray(v, dtype=np.float64)
    z = np.zeros(v.shape[:-1])
    return np.stack(
        [
            np.stack([z, -v[..., 2], v[..., 1]], axis=-1),
            np.stack([v[..., 2], z, -v[..., 0]], axis=-1),
            np.stack([-v[..., 1], v[..., 0], z], axis=-1),
        ],
        axis=-2,
    )


def se3_exp(xi: npt.ArrayLike) -> FloatArray:
    """Exponential map of a twist ``xi = (rho (3), phi (3))`` [m, rad] to a 4x4 transform.

    The rotation is ``exp(phi^)`` and the translation ``V(phi) rho`` (the SE(3) left Jacobian),
    so that ``se3_log(se3_exp(xi)) == xi``.
    """
    xi = np.asarray(xi, dtype=np.float64).reshape(6)
    rho, phi = xi[:3], xi[3:]
    theta = float(np.linalg.norm(phi))
    K = skew(phi)
    if theta < 1e-8:
        V = np.eye(3) + 0.5 * K + K @ K / 6.0
    else:
        V = (
            np.eye(3)
            + (1.0 - np.cos(theta)) / theta**2 * K
            + (theta - np.sin(theta)) / theta**3 * (K @ K)
        )
    return make_T(Rotation.from_rotvec(phi), V @ rho)


def se3_log(T: npt.ArrayLike) -> FloatArray:
    """Logarithm of a rigid transform: twist ``(rho, phi)`` with ``se3_exp(se3_log(T)) == T``."""
    T = np.asarray(T, dtype=np.float64)
    phi = Rotation.from_matrix(T[:3, :3]).as_rotvec()
    theta = float(np.linalg.norm(phi))
    K = skew(phi)
    if theta < 1e-8:
        V_inv = np.eye(3) - 0.5 * K + K @ K / 12.0
    else:
        half = 0.5 * theta
        V_inv = np.eye(3) - 0.5 * K + (1.0 - half / np.tan(half)) / theta**2 * (K @ K)
    return np.concatenate([V_inv @ T[:3, 3], phi])


def kabsch(
    source: npt.ArrayLike,
    target: npt.ArrayLike,
    weights: npt.ArrayLike | None = None,
) -> FloatArray:
    """Least-squares rigid transform ``T`` with ``target ~= T @ source`` (weighted Kabsch / SVD).

    Reflection-safe: the determinant correction guarantees a proper rotation even for planar or
    noisy correspondences.

    Args:
        source: (N, 3) points [m].
        target: (N, 3) corresponding points [m].
        weights: (N,) non-negative weights; uniform when None.

    Returns:
        (4, 4) transform mapping source coordinates into target coordinates.

    Raises:
        ValueError: on mismatched shapes, fewer than 3 points, non-finite input or zero weights.
    """
    P = np.asarray(source, dtype=np.float64)
    Q = np.asarray(target, dtype=np.float64)
    if P.ndim != 2 or P.shape[1] != 3 or P.shape != Q.shape:
        raise ValueError(
            f"source {P.shape} and target {Q.shape} must be matching (N, 3) arrays"
        )
    if P.shape[0] < 3:
        raise ValueError(f"kabsch got {P.shape[0]} correspondences; it needs >= 3")
    if not (np.all(np.isfinite(P)) and np.all(np.isfinite(Q))):
        raise ValueError("kabsch got non-finite points; expected finite (N, 3) arrays")
    if weights is None:
        w = np.full(P.shape[0], 1.0 / P.shape[0])
    else:
        w = np.asarray(weights, dtype=np.float64).reshape(-1)
        if w.shape[0] != P.shape[0] or np.any(w < 0) or not np.all(np.isfinite(w)):
            raise ValueError("weights must be (N,) finite and non-negative")
        s = w.sum()
        if s <= 0:
            raise ValueError("weights sum to zero; expected at least one positive weight")
        w = w / s
    mu_p = w @ P
    mu_q = w @ Q
    H = (P - mu_p).T @ ((Q - mu_q) * w[:, None])
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(Vt.T @ U.T))
    D = np.diag([1.0, 1.0, d if d != 0 else 1.0])
    R = Vt.T @ D @ U.T
    return make_T(R, mu_q - R @ mu_p)


def rotation_angle(R: npt.ArrayLike) -> npt.NDArray[np.float64] | float:
    """Rotation angle [rad] of rotation matrices (..., 3, 3), numerically safe near 0 and pi."""
    R = np.asarray(R, dtype=np.float64)
    ang = np.linalg.norm(Rotation.from_matrix(R).as_rotvec(), axis=-1)
    return float(ang) if np.ndim(ang) == 0 else ang


def pose_error(T_est: npt.ArrayLike, T_true: npt.ArrayLike) -> tuple[float, float]:
    """Translation error [m] and rotation error [deg] between two poses of the same frame pair.

    Translation error is ``|t_est - t_true|``; rotation error is the angle of ``R_true^T R_est``.
    """
    A = np.asarray(T_est, dtype=np.float64)
    B = np.asarray(T_true, dtype=np.float64)
    dt = float(np.linalg.norm(A[:3, 3] - B[:3, 3]))
    dR = B[:3, :3].T @ A[:3, :3]
    return dt, float(np.degrees(rotation_angle(dR)))
