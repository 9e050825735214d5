"""Seed 003's frames versus ours, and the roll prior as a pose change: :data:`SEED_FROM_OURS`,
:func:`T_from_seed_pose` / :func:`seed_pose_from_T` (conversions, derived in the docstring of
:mod:`perception.estimation.linetrack`) and :func:`roll_about_boresight` (eqs. 15 and 17).
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt
from scipy.spatial.transform import Rotation

from perception.geometry import check_rigid

FloatArray = npt.NDArray[np.float64]

#: ``p_seed = SEED_FROM_OURS @ p_ours``: seed (X, Y, Z) = our (z, x, y). Used for both the sensor
#: and the target frame.
SEED_FROM_OURS: FloatArray = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
SEED_FROM_OURS.setflags(write=False)


def T_from_seed_pose(position_seed: npt.ArrayLike, rpy_seed_rad: npt.ArrayLike) -> FloatArray:
    """``T_sensor_target`` (our axes) from a pose written in seed 003's frames.

    Args:
        position_seed: (3,) target origin in the seed's sensor frame (X toward the target, Y
            right, Z down) [m]; seed 003's (x, y, z) of sections 3.2 / 3.3.
        rpy_seed_rad: (3,) roll, pitch, yaw (phi, theta, psi) [rad] of eq. (2).

    Returns:
        (4, 4) pose mapping target-body coordinates into our sensor frame.
    """
    pos = np.asarray(position_seed, dtype=np.float64).reshape(-1)
    rpy = np.asarray(rpy_seed_rad, dtype=np.float64).reshape(-1)
    if pos.shape != (3,) or not np.all(np.isfinite(pos)):
        raise ValueError(f"position_seed={pos}; expected 3 finite values [m]")
    if rpy.shape != (3,) or not np.all(np.isfinite(rpy)):
        raise ValueError(f"rpy_seed_rad={rpy}; expected 3 finite angles [rad]")
    P = SEED_FROM_OURS
    R_seed = Rotation.from_euler("XYZ", rpy).as_matrix()
    T = np.eye(4)
    T[:3, :3] = P.T @ R_seed @ P
    T[:3, 3] = P.T @ pos
    return T


def seed_pose_from_T(T_sensor_target: npt.ArrayLike) -> tuple[FloatArray, FloatArray]:
    """Inverse of :func:`T_from_seed_pose`: (position_seed (3,) [m], rpy (3,) [rad]).

    Roll and yaw are in (-pi, pi], pitch in [-pi/2, pi/2].
    """
    T = check_rigid(T_sensor_target, "T_sensor_target")
    P = SEED_FROM_OURS
    R_seed = P @ T[:3, :3] @ P.T
    return P @ T[:3, 3], Rotation.from_matrix(R_seed).as_euler("XYZ")


def roll_about_boresight(T_sensor_target: npt.ArrayLike, delta_roll: float) -> FloatArray:
    """The roll prior of eqs. (15) and (17): turn the target by ``delta_roll`` [rad] about the
    boresight direction through its own origin (``R <- Rz(delta_roll) R``, position unchanged)."""
    T = check_rigid(T_sensor_target, "T_sensor_target").copy()
    if not math.isfinite(delta_roll):
        raise ValueError(f"delta_roll={delta_roll}; expected a finite angle [rad]")
    c, s = math.cos(delta_roll), math.sin(delta_roll)
    Rz = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    T[:3, :3] = Rz @ T[:3, :3]
    return T
