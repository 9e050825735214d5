"""The outcome of a registration (:class:`RegistrationResult`) and the terms its covariance is
stated in: the axis names of the twist and the variance that means "unknown"."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]

#: Names of the six twist components of the covariance, in order: translation along the sensor
#: x, y, z axes, then rotation about them.
AXIS_NAMES: tuple[str, ...] = ("tx", "ty", "tz", "rx", "ry", "rz")

#: Variance [m^2 or rad^2] reported along unobservable directions and for failed registrations:
#: large enough to mean "unknown", finite so that no inf or NaN ever leaves an estimator.
FAILURE_VARIANCE = 1.0e6


@dataclass
class RegistrationResult:
    """Outcome of a registration (ICP tracking or PAH acquisition).

    Attributes:
        T_sensor_target: (4, 4) estimated pose; maps target-body coordinates into the sensor frame.
            Always a finite rigid transform (the initial guess on failure).
        fitness: inlier fraction of the finite scan points, 0..1.
        inlier_rmse: RMS point-to-plane residual of the inliers [m].
        converged: True when a stop criterion on the step or the residual was met.
        iterations: iterations run.
        covariance: (6, 6) covariance of a LEFT perturbation along the sensor axes, pivoting on
            the target origin: ``xi = (rho [m], phi [rad])`` with
            ``T_true = Tr(t) @ se3_exp(xi) @ Tr(-t) @ T_sensor_target`` (``t`` the estimated target
            position), i.e. to first order ``t_true = t + rho`` and
            ``R_true = exp(phi^) R``. So the top-left 3x3 block is the position covariance
            [m^2] of the target origin in the sensor frame and the bottom-right 3x3 the attitude
            covariance [rad^2] about the sensor axes. (Pivoting on the sensor origin instead,
            ``T_true = se3_exp(xi) @ T``, mixes ``phi x t`` into the translation block; see
            :func:`covariance_about_sensor_origin`.) Unobservable directions and failures carry
            ``FAILURE_VARIANCE``.
        degenerate_axes: names from :data:`AXIS_NAMES` of the directions the geometry does not
            constrain (e.g. ``["tx", "ty", "rz"]`` for a flat panel seen face-on).
        reason: empty when fine; otherwise why the registration failed or stopped early.
        n_points: finite scan points used.
        n_inliers: scan points inside the final correspondence gate.
        time_s: wall-clock time of the call [s].
    """

    T_sensor_target: FloatArray
    fitness: float = 0.0
    inlier_rmse: float = 0.0
    converged: bool = False
    iterations: int = 0
    covariance: FloatArray = field(default_factory=lambda: FAILURE_VARIANCE * np.eye(6))
    degenerate_axes: list[str] = field(default_factory=list)
    reason: str = ""
    n_points: int = 0
    n_inliers: int = 0
    time_s: float = 0.0

    @classmethod
    def failure(
        cls,
        reason: str,
        T: npt.ArrayLike | None = None,
        n_points: int = 0,
        time_s: float = 0.0,
        iterations: int = 0,
    ) -> RegistrationResult:
        """A non-converged result with a finite pose (``T`` or identity) and a huge finite covariance."""
        T_out = np.eye(4)
        if T is not None:
            arr = np.asarray(T, dtype=np.float64)
            if arr.shape == (4, 4) and np.all(np.isfinite(arr)):
                T_out = arr.copy()
        return cls(
            T_sensor_target=T_out,
            converged=False,
            iterations=int(iterations),
            covariance=FAILURE_VARIANCE * np.eye(6),
            degenerate_axes=list(AXIS_NAMES),
            reason=reason,
            n_points=int(n_points),
            time_s=float(time_s),
        )

    @property
    def position_sigma_m(self) -> float:
        """Root of the trace of the position covariance [m] (1-sigma, all axes together)."""
        return float(np.sqrt(max(np.trace(self.covariance[:3, :3]), 0.0)))

    @property
    def attitude_sigma_rad(self) -> float:
        """Root of the trace of the attitude covariance [rad]."""
        return float(np.sqrt(max(np.trace(self.covariance[3:, 3:]), 0.0)))
