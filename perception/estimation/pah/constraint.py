"""The approach-corridor constraint of a PAH search: :class:`PoseConstraint`."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from perception.config import CorridorConfig

from .poses import FloatArray


@dataclass
class PoseConstraint:
    """Admissible poses of the target for a constrained (docking-corridor) acquisition.

    A pose ``T_sensor_target`` is admitted when all of these hold:

    - attitude: the angle of ``R_sensor_target_nominal^T R`` is at most ``attitude_tol_rad``;
    - line of sight: the target origin lies inside the cone of half-angle
      ``boresight_half_angle_rad`` about the sensor +z (boresight) axis;
    - range: ``range_min_m <= |t| <= range_max_m``.

    Attributes:
        R_sensor_target_nominal: (3, 3) nominal attitude of the target in the sensor frame.
        attitude_tol_rad: attitude tolerance [rad], in (0, pi].
        boresight_half_angle_rad: half-angle of the line-of-sight cone [rad], in (0, pi].
        range_min_m: minimum range of the target origin [m], >= 0.
        range_max_m: maximum range [m], > range_min_m.
    """

    R_sensor_target_nominal: FloatArray
    attitude_tol_rad: float
    boresight_half_angle_rad: float
    range_min_m: float = 0.0
    range_max_m: float = math.inf

    def __post_init__(self) -> None:
        R = np.asarray(self.R_sensor_target_nominal, dtype=np.float64)
        if R.shape != (3, 3) or not np.all(np.isfinite(R)):
            raise ValueError(
                f"R_sensor_target_nominal has shape {R.shape}; expected a finite (3, 3) rotation"
            )
        if not (np.allclose(R.T @ R, np.eye(3), atol=1e-6) and abs(np.linalg.det(R) - 1) < 1e-6):
            raise ValueError("R_sensor_target_nominal is not a rotation (orthonormal, det +1)")
        self.R_sensor_target_nominal = R
        for name in ("attitude_tol_rad", "boresight_half_angle_rad"):
            v = float(getattr(self, name))
            if not (0.0 < v <= math.pi):
                raise ValueError(f"{name}={v}; expected an angle in (0, pi] [rad]")
            setattr(self, name, v)
        lo, hi = float(self.range_min_m), float(self.range_max_m)
        if not (lo >= 0.0 and hi > lo) or math.isnan(hi):
            raise ValueError(
                f"range_min_m={lo}, range_max_m={hi}; expected 0 <= range_min_m < range_max_m [m]"
            )
        self.range_min_m, self.range_max_m = lo, hi

    @classmethod
    def from_corridor(
        cls, cfg: CorridorConfig, R_sensor_target_nominal: npt.ArrayLike
    ) -> PoseConstraint:
        """The constraint of an approach corridor.

        ``cfg.half_angle_deg`` is the line-of-sight cone: the target origin must lie within that
        angle of the sensor boresight (+z); ``cfg.attitude_tolerance_deg`` bounds the attitude
        error about ``R_sensor_target_nominal``; the range limits are copied.
        """
        if not isinstance(cfg, CorridorConfig):
            raise ValueError(f"cfg is a {type(cfg).__name__}; expected a CorridorConfig")  # noqa: TRY004
        return cls(
            R_sensor_target_nominal=np.asarray(R_sensor_target_nominal, dtype=np.float64),
            attitude_tol_rad=math.radians(cfg.attitude_tolerance_deg),
            boresight_half_angle_rad=math.radians(cfg.half_angle_deg),
            range_min_m=float(cfg.min_range_m),
            range_max_m=float(cfg.max_range_m),
        )

    def attitude_ok(self, R: FloatArray, slack_rad: float = 0.0) -> npt.NDArray[np.bool_]:
        """(K,) True where the angle of ``R_nominal^T R_k`` is within tolerance (+ slack)."""
        # trace(Rn^T R) = sum of the element-wise product.
        tr = np.einsum("ij,kij->k", self.R_sensor_target_nominal, R)
        lim = math.cos(min(self.attitude_tol_rad + slack_rad, math.pi))
        return 0.5 * (tr - 1.0) >= lim - 1e-12

    def position_ok(self, t: FloatArray, slack_m: float = 0.0) -> npt.NDArray[np.bool_]:
        """(K,) True where positions (K, 3) [m] are in the cone and range interval (+ slack)."""
        r = np.linalg.norm(t, axis=1)
        in_range = (r >= self.range_min_m - slack_m) & (r <= self.range_max_m + slack_m)
        with np.errstate(invalid="ignore", divide="ignore"):
            cos_los = np.where(r > 0, t[:, 2] / r, 1.0)
            ang = np.arccos(np.clip(cos_los, -1.0, 1.0))
            ang_slack = np.where(r > 0, np.arcsin(np.clip(slack_m / r, 0.0, 1.0)), 0.0)
        return in_range & (ang <= self.boresight_half_angle_rad + ang_slack + 1e-12)

    def admits_batch(self, Ts: npt.ArrayLike) -> npt.NDArray[np.bool_]:
        """Vectorised :meth:`admits`: Ts (K, 4, 4) -> (K,) bool (non-finite poses are refused)."""
        T = np.asarray(Ts, dtype=np.float64)
        if T.ndim != 3 or T.shape[1:] != (4, 4):
            raise ValueError(f"Ts has shape {T.shape}; expected (K, 4, 4) transforms")
        finite = np.all(np.isfinite(T), axis=(1, 2))
        T = np.where(finite[:, None, None], T, np.eye(4))
        return finite & self.attitude_ok(T[:, :3, :3]) & self.position_ok(T[:, :3, 3])

    def admits(self, T: npt.ArrayLike) -> bool:
        """True when the pose ``T_sensor_target`` (4, 4) lies inside the corridor."""
        arr = np.asarray(T, dtype=np.float64)
        if arr.shape != (4, 4):
            raise ValueError(f"T has shape {arr.shape}; expected a (4, 4) transform")
        return bool(self.admits_batch(arr[None])[0])
