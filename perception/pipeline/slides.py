"""The slide monitor of a track: does ICP come back when the pose is pushed along the direction
its registration constrains least?

The registration's covariance is computed at its answer from the frame's own information; it says
nothing of how far from that answer ICP would have stopped had it started elsewhere. Along a
direction the scan constrains weakly (a long truss seen side-on, 85 m out, with its ends at the
edge of the field), ICP that starts from a prediction a few centimetres off stops about where it
started, and still claims millimetres: a filter that took a wrong first velocity then drags the
track along (a fly-around run went 1.9 m off under a 0.5 m protection level).

The probe (``integrity.slide_check_period_s``, and on every new track's first
``confirm_frames`` registrations): ICP from the answer pushed by ``d = max(3 sigma,
slide_probe_fraction * range)`` both ways along the largest-variance axis ``e`` of its position
covariance. If ICP brings the pose back to within 3 sigma of the answer, the direction holds. If
not, with ``o`` the larger offset left and ``rho = o / d`` the fraction not recovered, the
direction is uncertain by about ``o / (1 - rho)`` (capped at 10 o): that variance is added along
``e`` (kept in the target frame, turning with it) to every registration until the next probe, so
the filter weighs them as they deserve, its covariance and the protection level grow, and the
pose turns degraded rather than wrong-but-valid.
"""

from __future__ import annotations

import dataclasses
import math
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

from perception.config import ICPConfig
from perception.estimation.registration import RegistrationResult, icp
from perception.sensing.pointcloud import PointCloud

if TYPE_CHECKING:
    from perception.pipeline.tridar import TriDAR

FloatArray = npt.NDArray[np.float64]

__all__ = ["SlideMonitor"]


class SlideMonitor:
    """The slide monitor of the pipeline's track (module docstring).

    Attributes:
        axis_target: (3,) unit direction [target frame] of the last probe's slide, or None.
        sigma_m: 1-sigma [m] added along it to the registrations (0: none).
        probes: probes run; ``slides``: those that found a slide.
    """

    def __init__(self, tri: TriDAR) -> None:
        self.tri = tri
        self.probes = 0
        self.slides = 0
        self.reset()

    def reset(self) -> None:
        self.checked_t = -np.inf
        self.axis_target: FloatArray | None = None
        self.sigma_m = 0.0

    def start(self) -> None:
        """A new track: probe its first registrations; nothing carried over."""
        self.reset()

    @property
    def enabled(self) -> bool:
        return self.tri.pc.integrity.slide_check_period_s is not None

    def apply(self, pts: FloatArray, cloud: PointCloud, res: RegistrationResult, t_ref: float,
              icp_cfg: ICPConfig, n_updates: int) -> RegistrationResult:
        """``res`` with the slide's variance added (probing first when a probe is due at
        ``t_ref`` [s], the track having ``n_updates`` accepted registrations)."""
        ig = self.tri.pc.integrity
        if ig.slide_check_period_s is None or not res.converged:
            return res
        if n_updates < ig.confirm_frames or t_ref - self.checked_t >= ig.slide_check_period_s - 1e-9:
            self.checked_t = t_ref
            self.probe(pts, cloud, res, icp_cfg)
        return self.inflate(res)

    def probe(self, pts: FloatArray, cloud: PointCloud, res: RegistrationResult, icp_cfg: ICPConfig) -> None:
        """Push ``res`` both ways along its weakest position axis; set the slide (module doc)."""
        self.probes += 1
        T = res.T_sensor_target
        C = 0.5 * (res.covariance[:3, :3] + res.covariance[:3, :3].T)
        lam, V = np.linalg.eigh(C)
        e = V[:, -1]
        sigma = math.sqrt(max(float(lam[-1]), 0.0))
        rng = float(np.linalg.norm(T[:3, 3]))
        d = max(3.0 * sigma, self.tri.pc.integrity.slide_probe_fraction * rng)
        offsets = []
        for sgn in (1.0, -1.0):
            T0 = T.copy()
            T0[:3, 3] += sgn * d * e
            alt = icp(pts, self.tri.model, T0, sigma=cloud.sigma, directions=cloud.directions,
                      config=icp_cfg, coarse=False)
            offsets.append(abs(float((alt.T_sensor_target[:3, 3] - T[:3, 3]) @ e)) if alt.converged else d)
        o = max(offsets)
        if o <= 3.0 * sigma:
            self.axis_target, self.sigma_m = None, 0.0
            return
        self.slides += 1
        rho = min(o / d, 1.0)
        self.sigma_m = min(o / max(1.0 - rho, 0.1), 10.0 * o)
        self.axis_target = T[:3, :3].T @ e

    def inflate(self, res: RegistrationResult) -> RegistrationResult:
        """``res`` with ``sigma_m**2`` added along the slide's axis (none: ``res`` itself)."""
        if self.axis_target is None or self.sigma_m <= 0.0:
            return res
        e = res.T_sensor_target[:3, :3] @ self.axis_target
        cov = res.covariance.copy()
        cov[:3, :3] += self.sigma_m**2 * np.outer(e, e)
        return dataclasses.replace(res, covariance=cov)
