"""SE(3) and SO(3) helpers: homogeneous transforms, quaternions at the API edges, rigid fits.

Conventions (DESIGN.md): a pose ``T_a_b`` is a 4x4 homogeneous matrix that maps b-coordinates into
a-coordinates, ``p_a = T_a_b @ p_b``. Quaternions at API edges are scalar-first ``(w, x, y, z)``,
Hamilton, unit norm, with ``w >= 0``. Inside, rotations are ``scipy.spatial.transform.Rotation``.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt
from scipy.spatial.transform import Rotation

FloatArray = npt.NDArray[np.float64]

__all__ = [
    "make_T",
    "compose",
    "cross_rows",
    "fast_rotvec_to_matrix",
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
    "fast_cross",
    "los_basis",
    "fast_quat_to_matrix",
    "fast_matrix_to_quat",
    "fast_invert",
    "rotation_z",
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


_EYE3 = np.eye(3)
_EYE3_TOL = 1e-5 * _EYE3  # numpy.allclose's rtol on the reference's entries
_LAST_ROW = np.array([0.0, 0.0, 0.0, 1.0])
_LAST_ROW_TOL = 1e-5 * _LAST_ROW


def is_rigid(T: npt.ArrayLike, tol: float = 1e-6) -> bool:
    """True when ``T`` is a finite 4x4 proper rigid transform within ``tol``.

    ``R^T R`` and the last row are compared with the identity as ``numpy.allclose(atol=tol)``
    does (its default ``rtol`` of 1e-5 on the ones), and ``|det R - 1| < tol``; written out
    because this check guards every pose entering the sensor and ICP, several times a frame.
    """
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4) or not np.isfinite(T).all():
        return False
    R = T[:3, :3]
    if (np.abs(R.T @ R - _EYE3) > _EYE3_TOL + tol).any():
        return False
    if (np.abs(T[3] - _LAST_ROW) > _LAST_ROW_TOL + tol).any():
        return False
    (a, b, c), (d, e, f), (g, h, i) = R.tolist()
    det = a * (e * i - f * h) - b * (d * i - f * g) + c * (d * h - e * g)
    return abs(det - 1.0) < tol


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
    if v.shape == (3,):  # one vector (filters, ICP steps): a literal is ~10x the stacks' speed
        x, y, w = v.tolist()
        return np.array([[0.0, -w, y], [w, 0.0, -x], [-y, x, 0.0]])
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


# --------------------------------------------------------------------------------------------
# Single-item fast paths. The functions above accept batches and validate; a per-step simulation
# calls them on one 3-vector or one 3x3 matrix thousands of times a second, where numpy's generic
# machinery (np.cross, scipy Rotation construction) costs 10-50 us a call. These do the same math
# in plain floats for exactly one item and agree with the general functions to round-off (tests
# compare them on random inputs).
# --------------------------------------------------------------------------------------------


def cross_rows(a: FloatArray, b: FloatArray) -> FloatArray:
    """Row-wise ``a x b`` of (K, 3) arrays (``np.cross`` costs several times more at this size;
    pass ``np.broadcast_to(v, b.shape)`` for one vector against many)."""
    out = np.empty(np.broadcast_shapes(a.shape, b.shape))
    out[:, 0] = a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1]
    out[:, 1] = a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2]
    out[:, 2] = a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]
    return out


def fast_cross(a: FloatArray, b: FloatArray) -> FloatArray:
    """``np.cross(a, b)`` for two (3,) float vectors."""
    a0, a1, a2 = a.tolist()
    b0, b1, b2 = b.tolist()
    return np.array([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0])


def los_basis(port: FloatArray) -> FloatArray:
    """(3, 3) rows: the unit line of sight to ``port`` (3,) and two unit vectors across it."""
    u = port / np.linalg.norm(port)
    a = np.eye(3)[int(np.argmin(np.abs(u)))]
    b1 = np.cross(u, a)
    b1 /= np.linalg.norm(b1)
    return np.stack([u, b1, np.cross(u, b1)])


def fast_rotvec_to_matrix(v: FloatArray) -> FloatArray:
    """(3, 3) rotation matrix of one rotation vector [rad] (Rodrigues; series near zero), what
    ``Rotation.from_rotvec(v).as_matrix()`` returns."""
    x, y, z = v.tolist()
    th2 = x * x + y * y + z * z
    if th2 < 1e-8:  # sin(t)/t and (1 - cos t)/t^2 by their series: exact to double precision
        a = 1.0 - th2 / 6.0 + th2 * th2 / 120.0
        b = 0.5 - th2 / 24.0 + th2 * th2 / 720.0
    else:
        th = math.sqrt(th2)
        a = math.sin(th) / th
        b = (1.0 - math.cos(th)) / th2
    return np.array([
        [1.0 - b * (y * y + z * z), b * x * y - a * z, b * x * z + a * y],
        [b * x * y + a * z, 1.0 - b * (x * x + z * z), b * y * z - a * x],
        [b * x * z - a * y, b * y * z + a * x, 1.0 - b * (x * x + y * y)],
    ])


def fast_quat_to_matrix(q_wxyz: FloatArray) -> FloatArray:
    """(3, 3) rotation matrix of one scalar-first quaternion (normalised first, like
    :func:`quat_to_matrix`).

    Raises:
        ValueError: on a zero or non-finite quaternion.
    """
    w, x, y, z = np.asarray(q_wxyz, dtype=np.float64).reshape(4).tolist()
    n2 = w * w + x * x + y * y + z * z
    if not (n2 > 1e-24 and math.isfinite(n2)):
        raise ValueError(f"quaternion {[w, x, y, z]} has zero or non-finite norm; expected a unit (w, x, y, z)")
    s = 2.0 / n2
    xx, yy, zz = s * x * x, s * y * y, s * z * z
    xy, xz, yz = s * x * y, s * x * z, s * y * z
    wx, wy, wz = s * w * x, s * w * y, s * w * z
    return np.array([
        [1.0 - yy - zz, xy - wz, xz + wy],
        [xy + wz, 1.0 - xx - zz, yz - wx],
        [xz - wy, yz + wx, 1.0 - xx - yy],
    ])


def fast_matrix_to_quat(R: FloatArray) -> FloatArray:
    """Canonical scalar-first quaternion (4,) of one proper rotation matrix (3, 3).

    Shepperd's method (the branch SciPy's ``Rotation.from_matrix`` uses). Unlike SciPy it does not
    re-orthogonalise a matrix that is off SO(3) by more than 1e-12; callers pass products of
    rotations, orthonormal to round-off.
    """
    (r00, r01, r02), (r10, r11, r12), (r20, r21, r22) = R.tolist()
    tr = r00 + r11 + r22
    # Largest of (R00, R11, R22, trace), first one on ties (numpy argmax, as SciPy).
    if r00 >= r11 and r00 >= r22 and r00 >= tr:
        w, x, y, z = r21 - r12, 1.0 - tr + 2.0 * r00, r10 + r01, r20 + r02
    elif r11 >= r22 and r11 >= tr:
        w, x, y, z = r02 - r20, r01 + r10, 1.0 - tr + 2.0 * r11, r21 + r12
    elif r22 >= tr:
        w, x, y, z = r10 - r01, r02 + r20, r12 + r21, 1.0 - tr + 2.0 * r22
    else:
        w, x, y, z = 1.0 + tr, r21 - r12, r02 - r20, r10 - r01
    n = math.sqrt(w * w + x * x + y * y + z * z)
    if w < 0.0:
        n = -n
    return np.array([w / n, x / n, y / n, z / n])


def fast_matrix_to_rotvec(R: FloatArray) -> FloatArray:
    """Rotation vector (3,) [rad] of one proper rotation matrix (3, 3), angle in [0, pi]: what
    ``Rotation.from_matrix(R).as_rotvec()`` returns (through the canonical quaternion)."""
    w, x, y, z = fast_matrix_to_quat(R).tolist()
    s = math.sqrt(x * x + y * y + z * z)
    angle = 2.0 * math.atan2(s, w)
    # angle / sin(angle / 2); its series near zero (w >= 0, so angle <= pi)
    if angle <= 1e-3:
        a2 = angle * angle
        k = 2.0 + a2 / 12.0 + 7.0 * a2 * a2 / 2880.0
    else:
        k = angle / math.sin(0.5 * angle)
    return np.array([k * x, k * y, k * z])


def fast_invert(T: FloatArray) -> FloatArray:
    """Inverse of one rigid (4, 4) transform (:func:`invert` for a single pose)."""
    Rt = T[:3, :3].T
    out = np.zeros((4, 4))
    out[:3, :3] = Rt
    out[:3, 3] = -(Rt @ T[:3, 3])
    out[3, 3] = 1.0
    return out


def rotation_z(angle_rad: float) -> FloatArray:
    """(3, 3) rotation by ``angle_rad`` about +z (``Rotation.from_rotvec([0, 0, angle])``)."""
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
