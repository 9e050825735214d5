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

**A turn can be uncertain too** (``integrity.turn_check_period_s``): a cylinder bus's roll about
its axis is pinned only by what breaks the symmetry (a thin boom, 0-3 of ~250 points a frame), and
the registration's information, from a handful of points or the rim's 32 facets, still claimed
0.2-8 deg; ICP from the prediction stopped where it started or in the next facet's basin, the
filter took the roll the prediction carried and a rate of 3 deg/s the target never had, and the
off-axis port was published valid 0.83 m away under a 9 cm protection level. The turn probe is the
slide probe for the weakest rotation ``e`` of the registration's covariance, near and far: the pose
is turned about the line through the pivot ``q`` the covariance couples with ``e`` (``q = o - g x
e``, ``g = C_tr C_rr^-1 e``: a roll about a bus's axis moves no point of that axis). Near: by ``a =
max(3 sigma, turn_probe_rad)`` both ways, ICP (capped at 10 iterations, as the twin monitor's) from
each. Far: every ``turn_grid_deg`` round the circle (beyond ``2 a``) is scored as it stands, PAH's
way (:meth:`~perception.estimation.pah.PAHDatabase.verify_poses`, one batch), and the
``turn_candidates`` best local maxima are polished by the capped ICP (a coarse sweep of 30/90/180
deg polished by ICP never reached the true roll: with a boom's few returns ICP barely turns, and
the rim's facets hold it in the basin it starts in). A stop more than ``3 sigma`` from the answer
about ``e`` that explains the scan about as well (its score within ``ambiguity_margin`` of the
tracked pose's, as the twin monitor judges twins) is another answer the scan allows: the turn is
uncertain by its offset. The near pushes and the best far turn are judged on their mean lead over
the last ``symmetry_switch_checks`` probes: the boom's returns vary from frame to frame, and single
frames with none of them made turns that the others had ruled out by 0.3-2.7 look alike, holding
the bus degraded at 12 m with its roll right to 1 deg. A far turn that lost to the tracked pose at
each of the last ``turn_rule_out_probes`` probes is ruled out however small each loss (a sign
test: a turn the scans truly cannot tell apart loses six in a row with probability 1/64; close to
the bus's flat end face a turn 7-14 deg off lost every probe by 0.01-0.05, inside the margin, and
held right tracks degraded at 4-5 m until 9 approaches of 10 timed out; a wrong track's far turn
wins some probes and stays alike). Far turns that the last probes all ruled out
by a wide margin (ten ``ambiguity_margin``), with no turn held, are looked at every
``turn_far_every`` probes only: on a healthy track they score 1-3 below it, and they are most of a
probe's cost. Where a near push stays off (ICP settled there, explaining the scan as well), ICP
runs once more from ``2 a``: a valley that slides on (``rho > 0.9``) is free, uniform on the circle
(sigma ``pi / sqrt(3)``, also the cap); a bounded one of a few degrees is not held (a generated
assembly's roll 1-3 m from the port sat in such a 3-7 deg valley, which the filter, averaging over
a moving aspect, flew inside its bound; held, it stopped the docking), nor is a push the iteration
cap stopped on its way back (a weak slope, not a valley). A stop that explains the scan clearly
worse is not evidence (a 30 deg turn of a well-pinned target may not come back, and need not). The
turn is held, added to the registrations along ``[e x (o - q), e]`` and floored in the published
attitude (``slide_position_floor``) as a slide is. Its rate is not floored: the deweighted
registrations teach the filter no rate about it, and ``sigma / tau`` of a free turn (10 deg/s) spun
the estimate 90 deg in 2 s. The mission's approach corridor, where configured, rules a turn out as
it rules out a twin (a box-like assembly flipped about an in-plane axis fits its front face as
well, port behind it: held at 104 deg, it kept a docking degraded at 3-8 m). A rotation the
registration already reports degenerate (sigma over 0.5 rad) is not probed: the frame says so
itself, and the filter's continuity carries the turn through it.

**A new track waits for its turn probes**: it is probed at every frame until
``symmetry_switch_checks`` probes have run on it (frames that leave the turn degenerate do not
count), and its pose is published degraded until then. A track PAH started 60 deg off in roll on a
generated cylinder bus at 28 m took three frames that left the roll degenerate, then one that
claimed it to 0.26 deg; that frame's probe found a far turn of only 8 deg alike (the turn it
probes about is the registration's weakest, not yet the bus's axis), and the next frames were
published valid 0.38 m off under a 0.32 m protection level, until the probe four frames later
found the 55 deg turn. The judgement over several probes (below) is what rules a turn in or out;
one probe is not a judgement.

**A held turn lapses only on evidence that it is pinned**: ``slide_hold_s`` after it was last
found, and once ``symmetry_switch_checks`` probes in a row that ran found no turn, or one far
tighter (under a third of its sigma; a tighter finding does not renew it). Frames that leave the
turn degenerate are no evidence either way: with a plain hold, a track PAH started 90 deg off in
roll at 11 m let its turn lapse over such frames and was published valid 0.69 m off under a
0.15 m protection level.

**A lapsing turn hands its doubt on**: the registrations are deweighted about a held turn and the
published attitude is floored, but the live filter is not, and it keeps turning at the rate it
had: on the generated cylinder bus (shape seed 41, reset seed 701) a track sure of a false
0.55 deg/s roll rate turned 10 -> 18 deg off in 14 s, and when the hold lapsed it was published
valid up to 0.15 m off at the port. When a turn lapses, the live filter's attitude about it is floored at the hold's
sigma (the filter learnt nothing about it while it lasted), and the registrations that pin it
now, as the probes found, set it: that run docked with no hazardous frame. (Freeing the filter's
rate about a held turn instead, floored at the target's rate prior, or a held target's rate
relaxing to zero as a Gauss-Markov process, ran the bus's other seeds worse: timeouts and
hazardous frames where there were none.)

**A turn the scans stop seeing is carried** (``Held.carried``): a free turn found on a track
whose probes had pinned it (``symmetry_switch_checks`` probes in a row on this track, with no
turn held) is the scans no longer seeing what pins it, not evidence that it is wrong. It is held
as any turn (the registrations are deweighted about it, so they teach the filter nothing there),
but neither the published attitude nor, when it lapses, the live filter is floored at it: the
filter's continuity carries it, as through frames that report the turn degenerate themselves,
its covariance growing with its rate's. A generated cylinder bus (shape seed 9595) whose boom
had pinned its roll for 300 s showed only its end face inside 4 m; held free, the off-axis port's
bound went to 2-10 m, 2 mm off, and 0 of 4 approaches docked. Found again while carried, it stays
carried; on a track the probes had not pinned (a new one, or one that had just found a turn), it
is held and floored as above.

**A turn that explains the scans better moves the track** (the twin monitor's switch, with its
``symmetry_margin`` and ``symmetry_switch_checks``): once the features that pin the turn come into
the scans (the bus's boom at 10-15 m), the probe's far turn scores clearly above the tracked pose
at probe after probe, and the track restarts there (keeping its rates) rather than wait for a
prediction that never carries ICP into the right basin. While a turn is held the scan planner
(:mod:`perception.pipeline.observability`) steers the scan onto the features that pin it (its
``pin``): its regions' own bounds take the rim's facets for roll information and kept the boom
out of the scans at 10 m.
"""

from __future__ import annotations

import dataclasses
import math
from typing import TYPE_CHECKING, NamedTuple

import numpy as np
import numpy.typing as npt

from perception.config import ICPConfig
from perception.estimation.registration import RegistrationResult, icp
from perception.geometry import fast_matrix_to_rotvec, fast_rotvec_to_matrix
from perception.sensing.pointcloud import PointCloud

if TYPE_CHECKING:
    from perception.pipeline.filter import PoseFilter
    from perception.pipeline.tridar import TriDAR

FloatArray = npt.NDArray[np.float64]

__all__ = ["SlideMonitor"]

#: Slides whose axes are within 20 deg of each other are one slide.
_MERGE_COS = math.cos(math.radians(20.0))
#: A turn the registration already reports this uncertain [rad] is not probed.
_TURN_PROBED_BELOW_RAD = 0.5
#: Two turns within 20 deg of each other are the same turn (trace of their difference).
_SAME_TURN_TRACE = 1.0 + 2.0 * math.cos(math.radians(20.0))
#: 1-sigma of a turn uniform on the circle [rad].
_FREE_TURN_RAD = math.pi / math.sqrt(3.0)


class Held(NamedTuple):
    """A held slide: ``axis`` (3,) unit [target frame], ``sigma`` (1-sigma [m], or [rad] for a
    turn), ``t`` the time it was found [s], and for a turn the ``pivot`` (3,) its axis passes
    through [target frame, m] (None: a slide of the position). ``carried``: a free turn found on
    a track whose probes had pinned it (module doc, "A turn the scans stop seeing"): the
    registrations are deweighted about it, and the filter's continuity carries it."""

    axis: FloatArray
    sigma: float
    t: float
    pivot: FloatArray | None = None
    carried: bool = False


def _turn_twist(R: FloatArray, h: Held) -> FloatArray:
    """(6,) twist about the target origin ``o`` (sensor axes) of a unit turn about held turn
    ``h`` at attitude ``R``: ``[e x (o - q), e]``, with ``o - q = -R pivot``."""
    assert h.pivot is not None
    e = R @ h.axis
    return np.concatenate([np.cross(e, -(R @ h.pivot)), e])


class SlideMonitor:
    """The slide monitor of the pipeline's track (module docstring).

    Attributes:
        axis_target: (3,) unit direction [target frame] of the last probe's slide, or None.
        sigma_m: 1-sigma [m] added along it to the registrations (0: none).
        turn_axis_target, turn_pivot_target, turn_sigma_rad: the last turn probe's slide (its
            axis [target frame], a point on it [target frame, m], 1-sigma [rad]), or None / 0.
        probes: probes run; ``slides``: those that found a slide; ``turn_probes``, ``turns``: the
            same for turns; ``turn_switches``: tracks moved to a better turn.
    """

    def __init__(self, tri: TriDAR) -> None:
        self.tri = tri
        self.probes = 0
        self.slides = 0
        self.turns = 0
        self.turn_probes = 0
        self.turn_switches = 0
        self.reset()

    def reset(self) -> None:
        self.checked_t = -np.inf
        self.turn_checked_t = -np.inf
        self.turn_votes = 0
        self.turn_candidate: FloatArray | None = None
        self.pending_switch: RegistrationResult | None = None
        self.turn_leads = np.empty((0, 3))  # the last probes' leads: near pushes, best far turn
        self.turn_quiet = 0  # probes in a row that ran and found no turn
        self.track_quiet = 0  # the same on this track (since its start or its last move)
        self._far_wait = 0  # probes before the far turns are looked at again
        self.axis_target: FloatArray | None = None
        self.sigma_m = 0.0
        self.turn_axis_target: FloatArray | None = None
        self.turn_pivot_target: FloatArray | None = None
        self.turn_sigma_rad = 0.0
        #: Held slides and turns (module docstring).
        self.held: list[Held] = []

    def start(self) -> None:
        """A new track: probe its first registrations; the held slides stay (they belong to
        the aspect, which a restart does not change)."""
        self.checked_t = self.turn_checked_t = -np.inf
        self.turn_leads = np.empty((0, 3))
        self.track_quiet = 0

    @property
    def turn_confirmed(self) -> bool:
        """Whether the turn monitor has judged the track (since its start or its last move) at
        ``symmetry_switch_checks`` probes that ran; True with the monitor off. Until then its
        pose is published degraded (module doc, "A new track waits for its turn probes")."""
        return (self.tri.pc.integrity.turn_check_period_s is None
                or len(self.turn_leads) >= self.tri.pc.symmetry_switch_checks)

    @property
    def enabled(self) -> bool:
        ig = self.tri.pc.integrity
        return ig.slide_check_period_s is not None or ig.turn_check_period_s is not None

    def apply(self, pts: FloatArray, cloud: PointCloud, res: RegistrationResult, t_ref: float,
              icp_cfg: ICPConfig, n_updates: int) -> RegistrationResult:
        """``res`` with the slide's variance added (probing first when a probe is due at
        ``t_ref`` [s], the track having ``n_updates`` accepted registrations)."""
        ig = self.tri.pc.integrity
        self.pending_switch = None  # a switch is this frame's, or none
        if not self.enabled or not res.converged:
            return res

        def due(period: float | None, checked: float) -> bool:
            return period is not None and (n_updates < ig.confirm_frames or t_ref - checked >= period - 1e-9)

        if due(ig.slide_check_period_s, self.checked_t):
            self.checked_t = t_ref
            self.probe(pts, cloud, res, icp_cfg)
            if ig.slide_hold_s <= 0.0:  # no hold: a slide lasts until the next probe
                self.held = [h for h in self.held if h.pivot is not None]
            if self.axis_target is not None:
                self.hold(self.axis_target, self.sigma_m, t_ref)
        # A new track is probed at every frame until it is confirmed (turn_confirmed).
        if due(ig.turn_check_period_s, self.turn_checked_t) or not self.turn_confirmed:
            # A frame that leaves the turn degenerate is not probed; the next one is (probing
            # on schedule only, a track PAH started 60 deg off in roll met a degenerate frame at
            # every probe while the frames between claimed the roll, and was published wrong).
            if self.probe_turn(pts, cloud, res, icp_cfg):
                self.turn_checked_t = t_ref
            if ig.slide_hold_s <= 0.0:
                self.held = [h for h in self.held if h.pivot is None]
            if self.turn_axis_target is not None:
                held = self._held_turn(self.turn_axis_target)
                if held is not None and self.turn_sigma_rad < held.sigma / 3.0:
                    self.turn_quiet += 1  # pinned far tighter than held: evidence it is pinned
                    self.track_quiet += 1
                else:
                    # A free turn on a track the probes had pinned (a carried hold goes on
                    # being carried): the scans stopped seeing what pins it (module doc).
                    carried = self.turn_sigma_rad >= _FREE_TURN_RAD and (
                        held.carried if held is not None else (
                            self.track_quiet >= self.tri.pc.symmetry_switch_checks and not self.turn_held()))
                    self.turn_quiet = self.track_quiet = 0
                    self.hold(self.turn_axis_target, self.turn_sigma_rad, t_ref, self.turn_pivot_target,
                              carried=carried)
        if ig.slide_hold_s > 0.0:
            self.expire(t_ref)
        return self.inflate(res)

    def expire(self, t_ref: float) -> None:
        """Drop the holds that lapse at ``t_ref`` [s]: a slide ``slide_hold_s`` after it was last
        found; a turn then too, but only once ``symmetry_switch_checks`` probes in a row that ran
        found it pinned (no turn, or one far tighter than held): frames that leave it unobserved
        are no evidence either way. A lapsing turn leaves the live filter's attitude about it as
        uncertain as the hold said (module docstring, "A lapsing turn hands its doubt on")."""
        quiet = self.turn_quiet >= self.tri.pc.symmetry_switch_checks
        hold_s = self.tri.pc.integrity.slide_hold_s
        kept, lapsed = [], []
        for h in self.held:
            stays = t_ref - h.t <= hold_s + 1e-9 or (h.pivot is not None and not quiet)
            (kept if stays else lapsed).append(h)
        f = self.tri.filter
        for h in lapsed:
            if h.pivot is not None and f.initialized and not h.carried:
                f.floor_turn(f.R @ h.axis, self._pivot(f, h.pivot), h.sigma)
        self.held = kept

    def hold(self, axis_target: FloatArray, sigma: float, t: float, pivot: FloatArray | None = None,
             carried: bool = False) -> None:
        """Hold a slide (a turn, given its ``pivot``) found at ``t`` [s]; one of the same kind
        along a held axis (within 20 deg) merges into it at the larger sigma, carried only if
        both are."""
        new = Held(axis_target, sigma, t, pivot, carried)
        for i, h in enumerate(self.held):
            if (h.pivot is None) == (pivot is None) and abs(float(h.axis @ axis_target)) >= _MERGE_COS:
                kept = h._replace(t=t) if h.sigma >= sigma else new
                self.held[i] = kept._replace(carried=h.carried and carried)
                return
        self.held.append(new)

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

    def probe_turn(self, pts: FloatArray, cloud: PointCloud, res: RegistrationResult,
                   icp_cfg: ICPConfig) -> bool:
        """Turn ``res`` about its weakest rotation, near and far; set the turn (module doc).
        False when the registration leaves that rotation degenerate (nothing probed)."""
        ig = self.tri.pc.integrity
        self.turn_axis_target = self.turn_pivot_target = None
        self.turn_sigma_rad = 0.0
        self.turn_probes += 1
        T = res.T_sensor_target
        C = 0.5 * (res.covariance + res.covariance.T)
        lam, V = np.linalg.eigh(C[3:, 3:])
        e = V[:, -1]
        sigma = math.sqrt(max(float(lam[-1]), 0.0))
        if not sigma < _TURN_PROBED_BELOW_RAD:
            # The frame says itself that it does not pin the turn: nothing to probe, and no
            # evidence either way (a held turn neither renews nor counts towards lapsing).
            return False
        # The translation the covariance couples with a unit turn about e, and the line it turns
        # about: e x (o - q) = g, taken perpendicular to e.
        g = C[:3, 3:] @ np.linalg.lstsq(C[3:, 3:], e, rcond=1e-12)[0]
        o = T[:3, 3]
        q = o - np.cross(g, e)
        R = T[:3, :3]
        a = max(3.0 * sigma, ig.turn_probe_rad)
        cfg = icp_cfg.model_copy(update={"max_iterations": min(icp_cfg.max_iterations, 10)})

        def turned(angle: float) -> FloatArray:
            Rq = fast_rotvec_to_matrix(angle * e)
            T0 = T.copy()
            T0[:3, :3] = Rq @ T[:3, :3]
            T0[:3, 3] = q + Rq @ (o - q)
            return T0

        verify = self.tri.pah.verify_poses
        # The far turns: every turn_grid_deg round the circle scored as it stands, and the
        # turn_candidates best local maxima (beyond 2 a) polished by ICP.
        step = math.radians(ig.turn_grid_deg)
        grid = np.arange(1, round(2.0 * math.pi / step)) * step
        grid = np.where(grid > math.pi, grid - 2.0 * math.pi, grid)
        grid = np.sort(grid[np.abs(grid) > 2.0 * a])
        # The mission's approach corridor, where configured, rules a turn out as it rules out a
        # twin (a box-like assembly flipped about an in-plane axis fits its front face as well,
        # port behind it: held at 104 deg, it kept a docking degraded at 3-8 m).
        corridor = self.tri.corridor
        if corridor is not None and grid.size:
            grid = grid[corridor.admits_batch(np.stack([turned(float(x)) for x in grid]))]
        far: list[float] = []
        # Far turns the last probes all ruled out by a wide margin (10 ambiguity_margin), with
        # no turn held, are looked at again every turn_far_every probes only (most of a probe's
        # cost; a healthy track's far turns score 1-3 below it).
        n = self.tri.pc.symmetry_switch_checks
        wide = (len(self.turn_leads) >= n and not self.turn_held()
                and float(self.turn_leads[-n:, 2].max()) < -10.0 * ig.ambiguity_margin)
        skip_far = wide and self._far_wait > 0
        self._far_wait = (self._far_wait - 1 if skip_far else ig.turn_far_every - 1) if wide else 0
        if grid.size and not skip_far:
            _, gs = verify(pts, cloud.sigma, np.stack([turned(float(x)) for x in grid]), cloud.directions)
            peak = (gs >= np.roll(gs, 1)) & (gs >= np.roll(gs, -1))
            order = np.argsort(-np.where(peak, gs, -np.inf), kind="stable")[: ig.turn_candidates]
            far = [float(grid[k]) for k in order if peak[k]]

        def run(angles: list[float]) -> tuple[FloatArray, FloatArray, list[RegistrationResult]]:
            """Offsets about ``e`` [rad] where ICP stops from the turned poses, their PAH score
            leads over ``res``, and the registrations."""
            # Each stop refined as the tracked registration was (the scan's outline, where ICP
            # leaves axes unobserved): plain ICP slid along a flat port face's roll that the
            # outline pins, and the false free turns held generated flat faces degraded.
            alts = [self.tri.tracking.outline_refine(
                icp(pts, self.tri.model, turned(x), sigma=cloud.sigma, directions=cloud.directions,
                    config=cfg, coarse=False), pts, cloud) for x in angles]
            ends = [alt.T_sensor_target for alt in alts]
            off = np.array([abs(float(fast_matrix_to_rotvec(Te[:3, :3] @ T[:3, :3].T) @ e)) for Te in ends])
            _, score = verify(pts, cloud.sigma, np.stack([T, *ends]), cloud.directions)
            lead = score[1:] - score[0]
            if corridor is not None:
                lead = np.where(corridor.admits_batch(np.stack(ends)), lead, -np.inf)
            return off, lead, alts

        off, lead, alts = run([a, -a, *far])
        k_best = int(np.argmax(lead))
        self._vote_turn(T, float(lead[k_best]), alts[k_best])
        # A far turn that ICP brought back within 2 a is the tracked pose's own basin (the near
        # pushes probe it); one still on its way back, capped, was taken for another answer on
        # the ISS-like port at 16 m (held 3-6 deg, degraded, and the approach stalled).
        far_ok = off[2:] > max(3.0 * sigma, 2.0 * a)
        k_far = 2 + int(np.argmax(np.where(far_ok, lead[2:], -np.inf))) if np.any(far_ok) else -1
        # The near pushes and the best far turn are judged on their mean lead over the last
        # symmetry_switch_checks probes: the few returns that pin the turn (a boom's) vary from
        # frame to frame, and single frames with none of them made turns the others had ruled
        # out by 0.3-2.7 look alike. Skipped far turns stand as last judged; leads are floored
        # at -1, so one probe with no far turn does not outweigh the others.
        far_lead = self.turn_leads[-1, 2] if skip_far else (lead[k_far] if k_far >= 0 else -1.0)
        judged = np.maximum([lead[0], lead[1], far_lead], -1.0)
        m = ig.turn_rule_out_probes or 0
        self.turn_leads = np.vstack([self.turn_leads.reshape(-1, 3), judged])[-max(n, m):]
        mean_lead = self.turn_leads[-n:].mean(axis=0)
        alike = mean_lead >= -ig.ambiguity_margin
        # A far turn that lost at each of the last m probes is ruled out (a sign test; module doc).
        if m and len(self.turn_leads) >= m and bool(np.all(self.turn_leads[-m:, 2] < 0.0)):
            alike[2] = False
        # A near push counts where ICP settled: one the iteration cap stopped on its way back
        # (a weak slope, not a valley) held a generated assembly's roll at 3-5 deg and its pose
        # degraded in the last metres of a docking it had flown within its bound.
        found = np.array([off[0] > 3.0 * sigma and alts[0].converged,
                          off[1] > 3.0 * sigma and alts[1].converged, k_far >= 0])
        # A far turn alike is another basin: the turn is uncertain by its offset. The near pushes
        # count only where the valley is free (the second push slides on, rho > 0.9): a bounded
        # valley of a few degrees (a generated assembly's roll at 1-3 m from the port, 3-7 deg)
        # is the same at every aspect only if the aspect stands still, and the filter that
        # averaged it flew that docking inside its bound; held, it stopped the docking.
        s_turn = float(off[k_far]) if found[2] and alike[2] else 0.0
        near = found[:2] & alike[:2]
        if np.any(near):  # the near pushes did not come back: a flat valley or a basin next door
            k = int(np.argmax(np.where(near, off[:2], -1.0)))
            off2, lead2, _ = run([2.0 * a if k == 0 else -2.0 * a])
            rho = min(max((float(off2[0]) - float(off[k])) / a, 0.0), 1.0) if lead2[0] >= -ig.ambiguity_margin else 0.0
            if rho > 0.9:
                s_turn = _FREE_TURN_RAD
        if s_turn <= 0.0:
            self.turn_quiet += 1
            self.track_quiet += 1
            return True
        self.turns += 1
        if s_turn < _FREE_TURN_RAD and alts[k_far].converged:
            # Another basin ICP settled in: the line the pose turns about is the screw axis of
            # that move, not the covariance's coupling (unreliable along a direction this weak:
            # a square plate's quarter-turn twin about its port's own axis was put a metre off
            # and held the pose degraded at 0.74 m).
            Ta = alts[k_far].T_sensor_target
            Rm = Ta[:3, :3] @ R.T
            q = np.linalg.lstsq(np.eye(3) - Rm, Ta[:3, 3] - Rm @ o, rcond=1e-9)[0]
            q = q - float((q - o) @ e) * e  # the point of the line nearest the target origin
        self.turn_axis_target, self.turn_pivot_target = R.T @ e, R.T @ (q - o)
        self.turn_sigma_rad = min(s_turn, _FREE_TURN_RAD)
        return True

    def _vote_turn(self, T: FloatArray, lead: float, alt: RegistrationResult) -> None:
        """A vote for the turned pose ``alt`` when it explains the scan better than the tracked
        pose ``T`` by ``symmetry_margin`` (its PAH score's ``lead``); ``symmetry_switch_checks``
        votes in a row for the same turn (within 20 deg, in the target frame) make it the
        pending switch (:meth:`switch`)."""
        pc = self.tri.pc
        if not (lead > pc.symmetry_margin and alt.converged):
            self.turn_votes, self.turn_candidate = 0, None
            return
        D = T[:3, :3].T @ alt.T_sensor_target[:3, :3]  # the turn, in the target frame
        same = self.turn_candidate is not None and float(np.trace(self.turn_candidate.T @ D)) >= _SAME_TURN_TRACE
        self.turn_votes = self.turn_votes + 1 if same else 1
        self.turn_candidate = D
        if self.turn_votes >= pc.symmetry_switch_checks:
            self.pending_switch = alt
            self.turn_votes, self.turn_candidate = 0, None

    def switch(self, pts: FloatArray, cloud: PointCloud, t_ref: float) -> bool:
        """Move the track to the turn the probes preferred (after the frame's filter update, as
        the twin monitor's switch): True when it did."""
        alt, self.pending_switch = self.pending_switch, None
        if alt is None:
            return False
        self.tri.twins.move_track(alt, pts, cloud, t_ref)
        self.turn_switches += 1
        self.turn_leads = np.empty((0, 3))  # judged again from the new pose
        self.track_quiet = 0
        return True

    def loosen(self, f: PoseFilter) -> None:
        """Before ``f`` predicts to its next registration: keep its velocity along each slide
        uncertain by ``sigma / slide_velocity_time_s`` (module docstring), so the prediction
        carries that uncertainty into the position the registration is weighed against."""
        tau = self.tri.pc.integrity.slide_velocity_time_s
        if tau is None or not self.held or not f.initialized:
            return
        for h in self.held:
            if h.pivot is None:  # a turn's rate is left alone (module docstring)
                f.floor_velocity(f.R @ h.axis, h.sigma / tau)

    def pin(self, f: PoseFilter) -> PoseFilter:
        """``f`` (the copy of the filter a frame publishes) with its position along each held
        slide uncertain by at least the slide's sigma (``integrity.slide_position_floor``;
        module docstring); the live filter's gain is left alone."""
        if self.tri.pc.integrity.slide_position_floor and self.held and f.initialized:
            for h in self.held:
                if h.pivot is None:
                    f.floor_position(f.R @ h.axis, h.sigma)
                elif not h.carried:
                    f.floor_turn(f.R @ h.axis, self._pivot(f, h.pivot), h.sigma)
        return f

    def turn_held(self) -> bool:
        """A turn is held."""
        return any(h.pivot is not None for h in self.held)

    def _held_turn(self, axis_target: FloatArray) -> Held | None:
        """The held turn about ``axis_target`` (within 20 deg), if any."""
        return next((h for h in self.held if h.pivot is not None
                     and abs(float(h.axis @ axis_target)) >= _MERGE_COS), None)

    def turn_direction(self, T: FloatArray) -> FloatArray | None:
        """The widest held turn at pose ``T`` as a twist about the target origin (sensor axes,
        ``[e x (o - q), e]``), for the scan planner to pin; None with no turn held."""
        turns = [h for h in self.held if h.pivot is not None]
        if not turns:
            return None
        return _turn_twist(T[:3, :3], max(turns, key=lambda h: h.sigma))

    @staticmethod
    def _pivot(f: PoseFilter, pivot_target: FloatArray) -> FloatArray:
        """A target-frame point in the sensor frame at the filter's pose."""
        T = f.T_sensor_target
        return T[:3, :3] @ pivot_target + T[:3, 3]

    def inflate(self, res: RegistrationResult) -> RegistrationResult:
        """``res`` with each held slide's ``sigma**2`` added along its axis, each held turn's along
        its turn (none: ``res`` itself)."""
        if not self.held:
            return res
        R = res.T_sensor_target[:3, :3]
        cov = res.covariance.copy()
        for h in self.held:
            e = R @ h.axis
            if h.pivot is None:
                cov[:3, :3] += h.sigma**2 * np.outer(e, e)
            else:
                u = _turn_twist(R, h)
                cov += h.sigma**2 * np.outer(u, u)
        return dataclasses.replace(res, covariance=cov)
