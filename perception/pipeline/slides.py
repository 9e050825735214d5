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
not, ICP runs once more from twice the push on the side that was left further off (offset ``o``
from ``d``, ``o2`` from ``2 d``). With ``rho = (o2 - o) / d`` the fraction of the extra push not
recovered, the direction is uncertain by about ``o / (1 - rho)`` (capped at 10 o). A slide, where
ICP stops where it starts, keeps the fraction (``o2 = 2 o``: the bound extrapolates it); a second
basin next to the answer catches both pushes at the same place (``o2 = o``: the uncertainty is the
basin's offset, not more: at 20 m on the ISS-like port a twin basin 1.6 cm along the port face
caught every push from 2 to 10 cm, and extrapolating from one push made it 0.5 m and held a
healthy approach degraded). That variance is added along ``e`` (kept in the target frame, turning with it) to every registration, so the filter weighs them
as they deserve, its covariance and the protection level grow, and the pose turns degraded rather
than wrong-but-valid.

**A slide keeps the filter's velocity along it uncertain** (``integrity.slide_velocity_time_s``
= tau): its error persists from frame to frame, so a filter that averages the deweighted
registrations as independent noise grows sure of a velocity along the slide that the scans never
observed, and then ignores the registrations that would correct it (a fly-around track kept a
velocity 4-11 cm/s wrong along the ISS-like truss for 100 s and drifted 1-25 m under a 0.7 m
protection level). While a slide of sigma ``s`` is on, the velocity variance along it is raised to
``(s / tau)**2`` before each prediction (a consider-style floor, injected as process noise): the
prediction then carries that uncertainty into the position, the registrations pull the track
back, and the protection level covers what they cannot settle.

**The published position along a slide can be kept uncertain too**
(``integrity.slide_position_floor``): the registrations of one slide share one offset, and after
a filter restart on four of them, averaged as independent, a fly-around pose was 1.49 m off along
the truss under a 1.14 m protection level while the slide was held at 2.78 m sigma. The state a
frame publishes has its position variance along each held slide raised to at least ``s**2`` (a
consider covariance): the bound covers the shared offset, and the live filter's gain is left
alone. (Flooring the live filter instead made it follow each registration at half gain along the
truss: in the first 6 runs of a campaign, 3 wandered 1-15 m off, degraded, and one took 3.3 times
as long to fly round.)

**A slide can be held** (``integrity.slide_hold_s``, default 0: until the next probe) after the
last probe that found it, whatever the probes in between say, kept in the target frame across a
new track (a planned restart looks at the same aspect); slides along nearly the same axis
(within 20 deg) merge at the larger sigma. On a weak aspect the probes flicker (ICP comes back
from one pair of pushes and not from the next), and a registration 0.25 m off along the truss
claimed 2 cm in a frame whose probe "held". Holding for 30 s without the velocity floor was
measured on the fly-around campaign and made it worse: with its registrations deweighted along the
truss for half a minute the filter kept a wrong velocity there unchallenged, and ICP from the
drifted prediction then settled in another bay (4 runs in 100 valid-but-wrong, 4 stalled, against
1 with no hold). With the floor on, the velocity stays uncertain while the slide is held, and
``fly_around`` holds for the floor's time (10 s): a run whose probes swung between 1.5 cm and
0.6 m went 1 m off under its protection level with no hold, and 8 cm off with it.
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
    from perception.pipeline.filter import PoseFilter
    from perception.pipeline.tridar import TriDAR

FloatArray = npt.NDArray[np.float64]

__all__ = ["SlideMonitor"]

#: Slides whose axes are within 20 deg of each other are one slide.
_MERGE_COS = math.cos(math.radians(20.0))


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
        #: Held slides: ``[axis_target (3,), sigma_m, time found]`` (module docstring).
        self.held: list[tuple[FloatArray, float, float]] = []

    def start(self) -> None:
        """A new track: probe its first registrations; the held slides stay (they belong to
        the aspect, which a restart does not change)."""
        self.checked_t = -np.inf

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
            if ig.slide_hold_s <= 0.0:
                self.held = []  # no hold: a slide lasts until the next probe
            if self.axis_target is not None:
                self.hold(self.axis_target, self.sigma_m, t_ref)
        if ig.slide_hold_s > 0.0:
            self.held = [h for h in self.held if t_ref - h[2] <= ig.slide_hold_s + 1e-9]
        return self.inflate(res)

    def hold(self, axis_target: FloatArray, sigma_m: float, t: float) -> None:
        """Hold a slide found at ``t`` [s]; one along a held axis (within 20 deg) merges into it
        at the larger sigma."""
        for i, (a, s, _) in enumerate(self.held):
            if abs(float(a @ axis_target)) >= _MERGE_COS:
                keep = (a, s, t) if s >= sigma_m else (axis_target, sigma_m, t)
                self.held[i] = keep
                return
        self.held.append((axis_target, sigma_m, t))

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

        def left(push: float) -> float:
            """How far along ``e`` ICP stops from the answer pushed by ``push`` [m]."""
            T0 = T.copy()
            T0[:3, 3] += push * e
            alt = icp(pts, self.tri.model, T0, sigma=cloud.sigma, directions=cloud.directions,
                      config=icp_cfg, coarse=False)
            return abs(float((alt.T_sensor_target[:3, 3] - T[:3, 3]) @ e)) if alt.converged else abs(push)

        offsets = [left(d), left(-d)]
        o = max(offsets)
        if o <= 3.0 * sigma:
            self.axis_target, self.sigma_m = None, 0.0
            return
        self.slides += 1
        o2 = left(2.0 * d if offsets[0] >= offsets[1] else -2.0 * d)
        rho = min(max((o2 - o) / d, 0.0), 1.0)
        self.sigma_m = min(o / max(1.0 - rho, 0.1), 10.0 * o)
        self.axis_target = T[:3, :3].T @ e

    def loosen(self, f: PoseFilter) -> None:
        """Before ``f`` predicts to its next registration: keep its velocity along each slide
        uncertain by ``sigma / slide_velocity_time_s`` (module docstring), so the prediction
        carries that uncertainty into the position the registration is weighed against."""
        tau = self.tri.pc.integrity.slide_velocity_time_s
        if tau is None or not self.held or not f.initialized:
            return
        for a, s, _ in self.held:
            f.floor_velocity(f.R @ a, s / tau)

    def pin(self, f: PoseFilter) -> PoseFilter:
        """``f`` (the copy of the filter a frame publishes) with its position along each held
        slide uncertain by at least the slide's sigma (``integrity.slide_position_floor``;
        module docstring); the live filter's gain is left alone."""
        if self.tri.pc.integrity.slide_position_floor and self.held and f.initialized:
            for a, s, _ in self.held:
                f.floor_position(f.R @ a, s)
        return f

    def inflate(self, res: RegistrationResult) -> RegistrationResult:
        """``res`` with each held slide's ``sigma**2`` added along its axis (none: ``res`` itself)."""
        if not self.held:
            return res
        R = res.T_sensor_target[:3, :3]
        cov = res.covariance.copy()
        for a, s, _ in self.held:
            e = R @ a
            cov[:3, :3] += s * s * np.outer(e, e)
        return dataclasses.replace(res, covariance=cov)
