"""Which correspondences count and how much: the correspondence gate, trimming, the front-face
test, the noise variance of each point-to-plane residual and the robust kernels.

Outlier rejection is tuned for space, where there is no clutter but there are returns from parts
that were removed from the model (solar arrays, radiators, arms; seed 000 section 5.3):

- a correspondence gate on the point-to-model distance that starts at ``max_correspondence_m`` and
  shrinks each iteration to three times the median distance, never below a floor set by the
  sensor noise, the model sampling and ``min_correspondence_m`` (:class:`Gates`);
- trimming of the worst ``trim_fraction`` correspondences, applied only to those beyond that floor
  (so a converged, clean frame keeps all its points and its full information);
- a robust kernel (Huber by default) on the noise-normalised point-to-plane residual
  (:func:`robust_weights`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from perception.config import ICPConfig
from perception.estimation.registration.correspondence import Matches
from perception.estimation.registration.model import ModelCloud
from perception.numeric import median

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]


@dataclass
class Gates:
    """The correspondence gate of one scan and its limits.

    Attributes:
        gate: current gate on the point-to-model distance [m].
        floor: the gate never shrinks below this [m]:
            ``max(min_correspondence_m, 4 sigma, 1.5 model spacing)``.
        median_floor: floor of the median gate [m] (with exact faces the model spacing is no
            error source, so it may go down to the noise).
        median_factor: the median gate is this many median match distances (0: off).
        trim: fraction of the worst matches trimmed (those beyond ``floor`` only).
    """

    gate: float
    floor: float
    median_floor: float
    median_factor: float
    trim: float

    @classmethod
    def start(cls, cfg: ICPConfig, mc: ModelCloud, sig: FloatArray) -> Gates:
        """The initial gate ``max_correspondence_m`` (at least the floor), range sigmas ``sig``."""
        gate_floor = max(cfg.min_correspondence_m, 4.0 * median(sig), 1.5 * mc.spacing)
        gate = max(cfg.max_correspondence_m, gate_floor)
        trim = float(cfg.trim_fraction)
        gate_k = float(cfg.gate_median_factor)
        # With exact face distances the model spacing is no error source: the median gate may go
        # down to the noise (strays a few cm off a face are then still rejected).
        median_floor = (max(cfg.min_correspondence_m, 4.0 * median(sig))
                        if mc.grid is not None else gate_floor)
        return cls(gate, gate_floor, median_floor, gate_k, trim)

    def select(
        self, m: Matches, d_all: FloatArray, back_cos: float, min_pts: int, match_scale: float
    ) -> tuple[BoolArray, FloatArray]:
        """One mask over the matches: median gate, then trim, then front faces.

        Args:
            m: the matches of this iteration.
            d_all: (N, 3) unit rays of all scan points, target frame.
            back_cos: matches whose normal has ``n . d`` at or above this face away from the sensor.
            min_pts: the median gate is skipped when it would leave fewer matches.
            match_scale: median match distance of this iteration [m] (or the last one known).

        Returns:
            The mask of the matches kept, and ``n . d`` of every match.
        """
        dist = m.dist
        kept = None  # None: all
        n_kept = int(m.sel.size)
        if self.median_factor > 0.0 and n_kept > min_pts:
            # Adaptive gate on the median match distance: once the pose is close, a stray
            # return 0.1-1 m off every surface is no longer a correspondence (trimming alone
            # keeps it while fewer than trim_fraction of the points are strays).
            thr = max(self.median_floor, self.median_factor * match_scale)
            if thr < self.gate:
                near = dist <= thr
                n_near = int(np.count_nonzero(near))
                if n_near < n_kept and n_near >= min_pts:
                    kept, n_kept = near, n_near
        if self.trim > 0.0 and n_kept > min_pts:
            kth = int((1.0 - self.trim) * (n_kept - 1))
            thr = float(np.partition(dist if kept is None else dist[kept], kth)[kth])
            if thr > self.floor:
                kept = dist <= thr if kept is None else kept & (dist <= thr)
        cos = np.einsum("ij,ij->i", m.normal, d_all[m.sel])
        front = cos < back_cos
        kept = front if kept is None else kept & front
        return kept, cos

    def to_fine(self, match_scale: float) -> None:
        """The fine gate from the coarse phase's last matches (the step that follows them is a
        fraction of the gate floor), so the first fine iteration already works at its own scale."""
        self.gate = max(self.floor, min(self.gate, 3.0 * match_scale))

    def shrink(self, dist: FloatArray) -> bool:
        """Fine phase: the gate to three times the median of the kept match distances ``dist``
        (never above the gate before, nor below the floor); True when it has settled."""
        new_gate = max(self.floor, min(self.gate, 3.0 * median(dist)))
        gate_settled = new_gate >= 0.98 * self.gate
        self.gate = new_gate
        return gate_settled


def noise_variance(
    sv: FloatArray, cos: FloatArray, floor_frac: float, model_sig: float
) -> FloatArray:
    """Noise variance [m^2] of point-to-plane residuals: range sigmas ``sv`` projected on the
    normals (``cos = n . d``), a floor ``floor_frac sigma`` for grazing points, and the model's
    error ``model_sig`` (as in
    :func:`~perception.estimation.registration.covariance.information_matrix`)."""
    return sv * sv * (cos * cos + floor_frac**2) + model_sig**2


def robust_weights(
    m: Matches, var: FloatArray, fine: bool, cfg: ICPConfig, gate_floor: float
) -> FloatArray:
    """Weights of the matches ``m``: inverse noise variance times a robust kernel.

    Fine phase: the configured kernel on the noise-normalised residual. Coarse phase: soft
    (Cauchy) down-weighting on the distance, scaled by the current spread: parts missing from the
    model cannot drag the coarse solution, a misaligned face still pulls.
    """
    w = 1.0 / var
    r = m.r
    if fine:
        w = w * kernel_weights(r / np.sqrt(var), cfg.robust_kernel, float(cfg.kernel_scale))
    else:
        w = w * kernel_weights(
            m.dist / max(gate_floor, 1.5 * median(m.dist)), "cauchy", 1.0
        )
    return w


def kernel_weights(z: FloatArray, kind: str, k: float) -> FloatArray:
    """Weights of normalised residuals ``z`` under the kernel ``kind`` ("huber", "tukey",
    "cauchy"; anything else: 1) of scale ``k``."""
    a = np.abs(z)
    if kind == "huber":
        return np.minimum(1.0, k / np.maximum(a, 1e-12))
    if kind == "tukey":
        u = a / k
        return np.where(u < 1.0, (1.0 - u * u) ** 2, 0.0)
    if kind == "cauchy":
        return 1.0 / (1.0 + (a / k) ** 2)
    return np.ones_like(a)

