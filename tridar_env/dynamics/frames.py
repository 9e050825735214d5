"""Frames: the target's LVLH frame and exact ECI <-> LVLH relative states, and quaternions.

* ECI: Earth-centred inertial, z along the Earth's pole (the J2 axis).
* LVLH / Hill of the target: x radial (away from Earth), y along-track (+V-bar), z orbit normal
  (``r x v``). For a circular orbit it rotates relative to inertial space at ``+n`` about its z.
* Relative states are ``(6,)`` ``[x, y, z, vx, vy, vz]`` of the chaser with respect to the
  target, in LVLH with velocities taken in the rotating frame [m, m/s].
* Attitudes at the API edge are scalar-first Hamilton quaternions ``(w, x, y, z)``, ``w >= 0``;
  :func:`_rotation_from_wxyz` and :func:`_wxyz` convert to and from SciPy's scalar-last
  ``Rotation`` for the other dynamics modules.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt
from scipy.spatial.transform import Rotation

__all__ = ["eci_from_relative_lvlh", "lvlh_frame", "relative_lvlh_from_eci"]

FloatArray = npt.NDArray[np.float64]


def _rotation_from_wxyz(q_wxyz: FloatArray) -> Rotation:
    # Explicit reorder rather than ``scalar_first=`` (SciPy >= 1.14 only).
    return Rotation.from_quat(np.asarray(q_wxyz, dtype=np.float64)[..., [1, 2, 3, 0]])


def _wxyz(rotation: Rotation) -> FloatArray:
    """Scalar-first unit quaternion(s) with ``w >= 0``."""
    q = np.asarray(rotation.as_quat(), dtype=np.float64)[..., [3, 0, 1, 2]]
    return np.where(q[..., :1] < 0.0, -q, q)


def lvlh_frame(
    r_eci: npt.ArrayLike, v_eci: npt.ArrayLike, a_eci: npt.ArrayLike | None = None
) -> tuple[FloatArray, FloatArray]:
    """LVLH axes of an orbiting body and the angular velocity of the LVLH frame.

    Args:
        r_eci: ``(3,)`` target position [m].
        v_eci: ``(3,)`` target velocity [m/s].
        a_eci: ``(3,)`` target total acceleration [m/s^2]; only its orbit-normal component
            matters (it tilts the orbit plane). ``None`` for Keplerian motion.

    Returns:
        ``(R_eci_lvlh, omega_lvlh)``: ``(3, 3)`` rotation whose columns are the LVLH axes in
        ECI (maps LVLH coordinates to ECI), and ``(3,)`` angular velocity of LVLH relative to
        ECI expressed in LVLH [rad/s]: ``[r a_z / |h|, 0, |h| / r^2]``.
    """
    r = np.asarray(r_eci, dtype=np.float64)
    v = np.asarray(v_eci, dtype=np.float64)
    h = np.cross(r, v)
    rn = float(np.linalg.norm(r))
    hn = float(np.linalg.norm(h))
    if rn == 0.0 or hn == 0.0:
        raise ValueError(f"r_eci={r.tolist()}, v_eci={v.tolist()} do not define an orbit plane")
    x = r / rn
    z = h / hn
    y = np.cross(z, x)
    rot = np.column_stack([x, y, z])
    a_normal = 0.0 if a_eci is None else float(np.dot(np.asarray(a_eci, dtype=np.float64), z))
    omega = np.array([rn * a_normal / hn, 0.0, hn / rn**2])
    return rot, omega


def relative_lvlh_from_eci(
    target_eci: npt.ArrayLike,
    chaser_eci: npt.ArrayLike,
    target_accel_eci: npt.ArrayLike | None = None,
) -> FloatArray:
    """Chaser state relative to the target, in the target's rotating LVLH frame.

    ``rho = R^T (r_c - r_t)``, ``rho_dot = R^T (v_c - v_t) - omega x rho``.

    Args:
        target_eci: ``(6,)`` target position and velocity in ECI [m, m/s].
        chaser_eci: ``(6,)`` or ``(B, 6)`` chaser position and velocity in ECI [m, m/s].
        target_accel_eci: ``(3,)`` target acceleration [m/s^2] (see :func:`lvlh_frame`).

    Returns:
        Relative LVLH state(s), same shape as ``chaser_eci``.
    """
    t = np.asarray(target_eci, dtype=np.float64)
    c = np.asarray(chaser_eci, dtype=np.float64)
    rot, omega = lvlh_frame(t[:3], t[3:], target_accel_eci)
    rho = (c[..., :3] - t[:3]) @ rot
    rho_dot = (c[..., 3:] - t[3:]) @ rot - np.cross(omega, rho)
    return np.concatenate([rho, rho_dot], axis=-1)


def eci_from_relative_lvlh(
    target_eci: npt.ArrayLike,
    relative_lvlh: npt.ArrayLike,
    target_accel_eci: npt.ArrayLike | None = None,
) -> FloatArray:
    """Inverse of :func:`relative_lvlh_from_eci`: chaser ECI state(s) ``(6,)`` or ``(B, 6)``."""
    t = np.asarray(target_eci, dtype=np.float64)
    x = np.asarray(relative_lvlh, dtype=np.float64)
    rot, omega = lvlh_frame(t[:3], t[3:], target_accel_eci)
    rho, rho_dot = x[..., :3], x[..., 3:]
    r_c = t[:3] + rho @ rot.T
    v_c = t[3:] + (rho_dot + np.cross(omega, rho)) @ rot.T
    return np.concatenate([r_c, v_c], axis=-1)
