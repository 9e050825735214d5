"""Relative motion of the target during a frame: one pose per sample time, vectorised.

A scanning sensor collects its samples one after the other, so a moving target is seen at a
different pose by every sample (the distortion of scanning LiDARs, seed 003 section 1.1). The
motion is given as:

- :class:`RelativeMotion`: constant linear and angular velocity of the target in the sensor frame
  (poses in closed form for any number of times);
- any object with a ``poses(times) -> (N, 4, 4)`` method;
- a callable ``t -> (4, 4) T_sensor_target`` (absolute time). It is called at a few knots across
  the frame and interpolated (slerp for rotation, linear for translation), so the number of Python
  calls does not grow with the number of samples.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt
from scipy.spatial.transform import Rotation, Slerp

from perception.geometry import check_rigid, skew

FloatArray = npt.NDArray[np.float64]

__all__ = ["Motion", "RelativeMotion", "sample_poses"]


@dataclass(frozen=True)
class RelativeMotion:
    """Target moving at constant velocity and spinning at a constant rate, seen from the sensor.

    Attributes:
        T_sensor_target_start: (4, 4) pose at ``t_ref``.
        v_sensor: (3,) velocity of the target origin (centre of mass) [m/s], sensor frame.
        omega_sensor: (3,) angular velocity of the target [rad/s], sensor frame; the target turns
            about its own origin.
        t_ref: time [s] of ``T_sensor_target_start``; None means the start of the scan (``t0``).
    """

    T_sensor_target_start: FloatArray
    v_sensor: FloatArray
    omega_sensor: FloatArray
    t_ref: float | None = None

    def __post_init__(self) -> None:
        T = check_rigid(self.T_sensor_target_start, "T_sensor_target_start")
        v = np.asarray(self.v_sensor, dtype=np.float64).reshape(-1)
        w = np.asarray(self.omega_sensor, dtype=np.float64).reshape(-1)
        if v.shape != (3,) or not np.all(np.isfinite(v)):
            raise ValueError(f"v_sensor={self.v_sensor!r}; expected a finite (3,) velocity [m/s]")
        if w.shape != (3,) or not np.all(np.isfinite(w)):
            raise ValueError(
                f"omega_sensor={self.omega_sensor!r}; expected a finite (3,) rate [rad/s]"
            )
        if self.t_ref is not None and not math.isfinite(self.t_ref):
            raise ValueError(f"t_ref={self.t_ref!r}; expected a finite time [s]")
        object.__setattr__(self, "T_sensor_target_start", T)
        object.__setattr__(self, "v_sensor", v)
        object.__setattr__(self, "omega_sensor", w)

    def poses(self, times: npt.ArrayLike, t_ref: float | None = None) -> FloatArray:
        """(N, 4, 4) ``T_sensor_target`` at absolute ``times`` (N,) [s].

        ``t_ref`` is used when the motion's own ``t_ref`` is None (the scan passes its ``t0``).
        """
        t = np.asarray(times, dtype=np.float64).reshape(-1)
        ref = self.t_ref if self.t_ref is not None else (0.0 if t_ref is None else t_ref)
        dt = t - ref
        R0 = self.T_sensor_target_start[:3, :3]
        p0 = self.T_sensor_target_start[:3, 3]
        out = np.zeros((t.size, 4, 4))
        # A constant rate turns about one fixed axis u by theta = |omega| dt, so by Rodrigues
        # R(dt) R0 = R0 + sin(theta) K R0 + 2 sin^2(theta / 2) K^2 R0 (K = [u]x): two products
        # computed once, then per-sample scalars.
        w = float(np.linalg.norm(self.omega_sensor))
        if w > 0.0:
            K = skew(self.omega_sensor / w)
            KR = K @ R0
            basis = np.stack([R0, KR, K @ KR]).reshape(3, 9)
            th = w * dt
            coef = np.empty((t.size, 3))
            coef[:, 0] = 1.0
            coef[:, 1] = np.sin(th)
            coef[:, 2] = 2.0 * np.sin(0.5 * th) ** 2
            out[:, :3, :3] = (coef @ basis).reshape(-1, 3, 3)
        else:
            out[:, :3, :3] = R0
        out[:, :3, 3] = p0 + dt[:, None] * self.v_sensor
        out[:, 3, 3] = 1.0
        return out


Motion = RelativeMotion | Callable[[float], Any] | Any


def sample_poses(motion: Motion, times: FloatArray, t0: float, knots: int = 16) -> FloatArray:
    """Poses ``T_sensor_target`` (N, 4, 4) of a motion at the absolute sample ``times`` [s].

    Raises:
        ValueError: naming ``motion`` when it yields non-finite or non-rigid poses.
    """
    t = np.asarray(times, dtype=np.float64).reshape(-1)
    if isinstance(motion, RelativeMotion):
        Ts = motion.poses(t, t_ref=t0)
    elif hasattr(motion, "poses"):
        Ts = np.asarray(motion.poses(t), dtype=np.float64)
    elif callable(motion):
        Ts = _interpolated(motion, t, knots)
    else:
        raise ValueError(
            f"motion={motion!r}; expected None, RelativeMotion, an object with poses(times) "
            "or a callable t -> (4, 4) T_sensor_target"
        )
    if Ts.shape != (t.size, 4, 4) or not np.all(np.isfinite(Ts)):
        raise ValueError(
            f"motion gave poses of shape {Ts.shape} or non-finite entries; expected finite "
            f"({t.size}, 4, 4) T_sensor_target"
        )
    # Rigidity spot check on the extremes (all poses of a smooth motion lie between them); a
    # RelativeMotion's poses are exact rotations of its checked start pose.
    if not isinstance(motion, RelativeMotion):
        for k in {0, t.size - 1}:
            check_rigid(Ts[k], "motion pose")
    return Ts


def _interpolated(fn: Callable[[float], Any], t: FloatArray, knots: int) -> FloatArray:
    if t.size == 0:
        return np.zeros((0, 4, 4))
    lo, hi = float(t.min()), float(t.max())
    if hi <= lo:
        T = check_rigid(fn(lo), "motion(t)")
        return np.broadcast_to(T, (t.size, 4, 4)).copy()
    kt = np.linspace(lo, hi, max(2, min(int(knots), t.size)))
    KT = np.stack([check_rigid(fn(float(x)), "motion(t)") for x in kt])
    rot = Slerp(kt, Rotation.from_matrix(KT[:, :3, :3]))(t).as_matrix()
    out = np.zeros((t.size, 4, 4))
    out[:, :3, :3] = rot
    for i in range(3):
        out[:, i, 3] = np.interp(t, kt, KT[:, i, 3])
    out[:, 3, 3] = 1.0
    return out
