"""When ICP stops: the coarse phase's hand-over to the fine phase, the fine phase's stop rule and
its limit-cycle check, as :class:`StopRule`, which carries what they remember between iterations.

The coarse phase hands over once its steps are a fraction of the gate floor. The fine phase stops
once its gate has settled and the correction left is below ``step_tol_sigma`` of the frame's own
information: the last step, or, while the steps contract, their geometric tail (a step of ``s``
sigmas after one of ``s / rho`` leaves about ``s rho / (1 - rho)``); or once the cost no longer
changes, or the steps cycle.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from perception.config import ICPConfig

FloatArray = npt.NDArray[np.float64]


@dataclass
class StopRule:
    """Stop criteria of one ICP call and their state across iterations.

    Attributes:
        coarse_tol_t, coarse_tol_r: the coarse phase hands over below these steps [m, rad].
        translation_tol_m, rotation_tol_rad: a fine step below both is small.
        step_tol2: a fine step below this squared Mahalanobis length [sigma^2] is small.
        residual_tol: relative cost change below which the fine phase has converged.
        step_sigma2: squared Mahalanobis length of the last fine step.
        prev_step_sigma: Mahalanobis length of the fine step before.
        prev_xi: the last fine step (before any halving).
        reversals: fine steps running that undid the one before.
        stalled: the last fine step was a limit cycle (and was halved).
        prev_cost: cost of the previous fine iteration (inf at the start of the phase).
    """

    coarse_tol_t: float
    coarse_tol_r: float
    translation_tol_m: float
    rotation_tol_rad: float
    step_tol2: float
    residual_tol: float
    step_sigma2: float = np.inf
    prev_step_sigma: float = np.inf
    prev_xi: FloatArray | None = None
    reversals: int = 0
    stalled: bool = False
    prev_cost: float = np.inf

    @classmethod
    def start(cls, cfg: ICPConfig, gate_floor: float, radius: float) -> StopRule:
        """Criteria for a scan of gate floor ``gate_floor`` [m] on a model of ``radius`` [m]."""
        # The coarse phase hands over once its steps are a fraction of the gate floor.
        coarse_tol_t = max(10.0 * cfg.translation_tol_m, 0.25 * gate_floor)
        coarse_tol_r = max(10.0 * cfg.rotation_tol_rad, 0.25 * gate_floor / radius)
        step_tol2 = float(cfg.step_tol_sigma) ** 2
        return cls(coarse_tol_t, coarse_tol_r, cfg.translation_tol_m, cfg.rotation_tol_rad,
                   step_tol2, cfg.residual_tol)

    def coarse_done(self, step_t: float, step_r: float) -> bool:
        """True when the coarse phase hands over; the fine phase's cost history then starts."""
        if step_t < self.coarse_tol_t and step_r < self.coarse_tol_r:
            self.prev_cost = np.inf
            return True
        return False

    def limit_cycle(self, xi_t: FloatArray, H: FloatArray, cost: float) -> FloatArray:
        """A fine Gauss-Newton step ``xi_t`` of information ``H`` at ``cost``, halved when it is
        part of a limit cycle.

        A sub-sigma step that no longer lowers the cost is a limit cycle (points near an edge
        trading faces), and so is a run of steps each undoing the one before (to within a third
        of its length) for two steps running: the matches flip between two sets, each pulling
        back to the other pose. Stop half-way.
        """
        # The step against the frame's own uncertainty (Mahalanobis length squared).
        self.step_sigma2 = float(xi_t @ H @ xi_t)
        back = None if self.prev_xi is None else xi_t + self.prev_xi
        undo = back is not None and self.step_sigma2 > 0.0 and float(
            back @ H @ back) < self.step_sigma2 / 9.0
        self.reversals = self.reversals + 1 if undo else 0
        self.stalled = (self.step_sigma2 < 1.0 and cost >= self.prev_cost) or self.reversals >= 2
        self.prev_xi = xi_t
        if self.stalled:
            xi_t = 0.5 * xi_t
        return xi_t

    def done(
        self, step_t: float, step_r: float, cost: float, gate_settled: bool
    ) -> tuple[bool, bool]:
        """After a fine step of ``step_t`` [m] and ``step_r`` [rad] at ``cost``: whether ICP has
        converged, and whether the step was small (below tolerance)."""
        small_step = step_t < self.translation_tol_m and step_r < self.rotation_tol_rad
        # Once a step is a small fraction of a sigma in every direction, further iterations
        # cannot change the answer. Gauss-Newton on the plane metric contracts about linearly
        # (each step a fraction rho of the one before), so after a step of s sigmas about
        # s rho / (1 - rho) remains: when that is below the tolerance, confirming it by another
        # iteration is not needed.
        s_k = math.sqrt(self.step_sigma2)
        prev = self.prev_step_sigma
        rho = s_k / prev if 0.0 < prev < math.inf else math.inf
        small_step = small_step or self.step_sigma2 < self.step_tol2 or (
            rho < 0.5 and (s_k * rho / (1.0 - rho)) ** 2 < self.step_tol2
        )
        self.prev_step_sigma = s_k
        small_change = abs(self.prev_cost - cost) <= self.residual_tol * max(cost, 1e-12)
        self.prev_cost = cost
        return gate_settled and (small_step or small_change or self.stalled), small_step
