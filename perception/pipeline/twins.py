"""The ambiguity monitor of a track: does a near-symmetric turn of the tracked pose (a twin)
explain the scan as well, or better?

ICP runs from ``T @ G`` for each near-symmetry ``G`` of the model (PAH's near-symmetry search) and
the converged alternatives are scored as PAH ranks hypotheses
(:meth:`~perception.estimation.pah.PAHDatabase.verify_poses`). Two uses, on their own schedules:

- integrity (``integrity.ambiguity_check_period_s``, and on every new track's first
  ``confirm_frames`` frames): while a twin scores within ``ambiguity_margin`` of the tracked pose,
  or above it, the scan cannot tell them apart and the port may be where the twin puts it: the
  protection level grows by the port's offset between the two poses (a roll twin of a nearly
  symmetric bus, locked at acquisition, was 0.45 m off at 10-15 m under a 3 cm protection level);
- switching (``symmetry_check_period_s``): a twin whose score beats the tracked pose's by
  ``symmetry_margin`` gets a vote, and ``symmetry_switch_checks`` votes in a row for the same turn
  move the track there (the filter restarts on it, keeping its rates). A track that locked onto
  the flipped twin of a nearly symmetric target at 60 m, where the features that tell them apart
  are a few noisy points, is put right once they are resolved.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

from perception.config import ICPConfig
from perception.estimation.registration import RegistrationResult, icp
from perception.pipeline.publish import tof_share
from perception.pipeline.tracking import measurement_cov
from perception.sensing.pointcloud import PointCloud

if TYPE_CHECKING:
    from perception.pipeline.tridar import TriDAR

FloatArray = npt.NDArray[np.float64]

__all__ = ["TwinMonitor"]

#: ``(turn index, registration, PAH score)`` of a converged near-symmetric alternative.
Alternative = tuple[int, RegistrationResult, float]


class TwinMonitor:
    """The ambiguity monitor of the pipeline's track (see the module docstring).

    Attributes:
        twins_open: indices of the near-symmetric turns the scans have not yet ruled out: None,
            all of them (a track that PAH started from nothing); empty for a track that carries a
            prior.
        ambiguity_m: the port's largest offset [m] to an open twin (added to the protection level).

    Args:
        tri: the pipeline (configuration, model, PAH database, filter, track bookkeeping).
    """

    def __init__(self, tri: TriDAR) -> None:
        self.tri = tri
        self.reset()

    def reset(self) -> None:
        self.sym_checked_t = -np.inf
        self.amb_checked_t = -np.inf
        self.ambiguity_m = 0.0
        self.twins_open: set[int] | None = set()
        self.sym_votes = 0
        self.sym_candidate = -1
        self.lost: tuple[set[int] | None, float] = (set(), 0.0)

    def track_lost(self) -> None:
        """The track was lost: keep the twins it had not ruled out (and their port offset) for a
        reacquisition from its prediction."""
        self.lost = (None if self.twins_open is None else set(self.twins_open), self.ambiguity_m)

    def start(self, all_open: bool, continues_lost: bool = False) -> None:
        """A new track: all twins open (PAH's answer may be a twin of the truth); those the lost
        track had left open (``continues_lost``: a reacquisition from its prediction continues it,
        twin and all: a PAH track lost before its twins were ruled out, reacquired from its
        prediction, was published valid a half turn off, 0.26 m at the port under a 0.06 m
        protection level); or none (a seed)."""
        if all_open:
            self.twins_open, self.ambiguity_m = None, 0.0
        elif continues_lost:
            twins, amb = self.lost
            self.twins_open, self.ambiguity_m = (None if twins is None else set(twins)), amb
        else:
            self.twins_open, self.ambiguity_m = set(), 0.0

    def monitor(self, pts: FloatArray, cloud: PointCloud, res: RegistrationResult,
                t_ref: float, icp_cfg: ICPConfig) -> None:
        """Check a tracking frame's registration ``res`` of the de-skewed points ``pts`` (N, 3)
        [m] for twins, where a check is due at ``t_ref`` [s]."""
        tri = self.tri
        pc = tri.pc
        ig = pc.integrity
        amb_due = ig.ambiguity_check_period_s is not None and self.twins_open != set() and (
            tri.n_updates <= ig.confirm_frames
            or t_ref - self.amb_checked_t >= ig.ambiguity_check_period_s - 1e-9)
        sym_due = pc.symmetry_check_period_s is not None and \
            t_ref - self.sym_checked_t >= pc.symmetry_check_period_s - 1e-9
        if not (amb_due or sym_due):
            return
        G = tri.pah.near_symmetries()
        if amb_due:
            self.amb_checked_t = t_ref
        if sym_due:
            self.sym_checked_t = t_ref
        if len(G) == 0:
            self.twins_open, self.ambiguity_m = set(), 0.0
            return
        tri.stats.symmetry_checks += 1
        score0, alts, unsettled = self.alternatives(pts, cloud, res, icp_cfg, G)
        if amb_due:
            self._rule_out(res.T_sensor_target, score0, alts, unsettled, len(G))
        if sym_due:
            self._vote(pts, cloud, t_ref, score0, alts)

    def _rule_out(self, T: FloatArray, score0: float, alts: list[Alternative],
                  unsettled: dict[int, FloatArray], n_turns: int) -> None:
        """Integrity: keep open the twins that explain the scan about as well as the tracked pose
        ``T`` (or that ICP could not settle: ``unsettled``, turn index -> its unpolished pose),
        and the port's largest offset to them."""
        tri = self.tri
        ig = tri.pc.integrity
        # A twin stays open while it explains the scan about as well (or better); one that
        # explains it clearly worse, or that explains less than half of what the tracked pose
        # does before ICP, is ruled out for this track. One that ICP did not settle in its capped
        # iterations is not evidence either way and stays open at its unpolished pose: ruling
        # it out let a track locked on the flipped twin of a tumbling CYGNSS-like bus (the truth
        # scoring 0.75-0.78 against its 0.50-0.73 at every check before) publish 0.58 m port
        # error under a 0.31 m protection level, the one check where the true turn's ICP stopped
        # short having closed every twin at once.
        # The mission's approach corridor, where configured, rules out a twin as PAH's search
        # does (a plate flipped about an in-plane axis is the same solid, port behind it).
        corridor = tri.corridor
        close = {i: a.T_sensor_target for i, a, s_alt in alts if s_alt >= score0 - ig.ambiguity_margin}
        close.update(unsettled)
        close = {i: Ti for i, Ti in close.items() if corridor is None or corridor.admits(Ti)}
        prev = set(range(n_turns)) if self.twins_open is None else self.twins_open
        self.twins_open = prev & set(close)
        r = tri.model_target.T_target_port[:3, 3]
        port = T[:3, :3] @ r + T[:3, 3]
        self.ambiguity_m = max(
            (float(np.linalg.norm(close[i][:3, :3] @ r + close[i][:3, 3] - port))
             for i in self.twins_open), default=0.0)

    def _vote(self, pts: FloatArray, cloud: PointCloud, t_ref: float, score0: float,
              alts: list[Alternative]) -> None:
        """Switching: a vote for a twin that clearly beats the tracked pose; enough in a row for
        the same one move the track there."""
        tri = self.tri
        pc = tri.pc
        best = max(alts, key=lambda a: a[2], default=None)
        if best is None or best[2] <= score0 + pc.symmetry_margin:
            self.sym_votes, self.sym_candidate = 0, -1
            return
        best_i, best_res, _ = best
        self.sym_votes = self.sym_votes + 1 if best_i == self.sym_candidate else 1
        self.sym_candidate = best_i
        if self.sym_votes < pc.symmetry_switch_checks:
            return
        self.move_track(best_res, pts, cloud, t_ref)
        self.sym_votes, self.sym_candidate = 0, -1

    def move_track(self, best_res: RegistrationResult, pts: FloatArray, cloud: PointCloud,
                   t_ref: float) -> None:
        """Move the track to ``best_res`` (a turn that clearly explains the scans better): the
        filter restarts on it at ``t_ref`` [s], keeping its velocity and rates."""
        tri = self.tri
        best_res = tri.tracking.outline_refine(best_res, pts, cloud)
        f = tri.filter
        v_origin = f.target_state()[1]
        r_port = tri.target.T_target_port[:3, 3]
        f.initialize(t_ref, best_res.T_sensor_target, measurement_cov(best_res, r_port, tri.pc),
                     velocity=v_origin, omega=f.w,
                     cov_acc=measurement_cov(best_res, r_port, tri.pc, floors=False),
                     tof_share=tof_share(cloud.subsystem))
        tri.last_result = best_res
        tri.stats.symmetry_switches += 1
        tri.n_updates = max(tri.n_updates, 3)
        # The old pose is now a twin (clearly worse); the others are judged again from here.
        self.twins_open, self.amb_checked_t = None, -np.inf

    def alternatives(self, pts: FloatArray, cloud: PointCloud, res: RegistrationResult,
                     icp_cfg: ICPConfig, G: FloatArray
                     ) -> tuple[float, list[Alternative], dict[int, FloatArray]]:
        """The tracked pose's PAH score, the converged near-symmetric alternatives
        ``(turn index, registration, score)`` for the turns ``G`` (K, 4, 4), and the turns
        polished but not converged (turn index -> unpolished pose ``T @ G[i]``)."""
        tri = self.tri
        pah = tri.pah
        T = res.T_sensor_target
        sigma, dirs = cloud.sigma, cloud.directions
        fit, score = pah.verify_poses(pts, sigma, np.concatenate([T[None], T @ G]), dirs)
        # Turns that show the sensor another side of the target explain little even before ICP:
        # only the near-fits are polished (with capped work: a turn that is not a better basin
        # need not converge) and scored again.
        cfg = icp_cfg.model_copy(update={"max_iterations": min(icp_cfg.max_iterations, 10)})
        alts: list[tuple[int, RegistrationResult]] = []
        unsettled: dict[int, FloatArray] = {}
        for i in np.flatnonzero(fit[1:] >= 0.5 * fit[0]):
            alt = icp(pts, tri.model, T @ G[i], sigma=sigma, directions=dirs, config=cfg)
            if alt.converged:
                alts.append((int(i), alt))
            else:
                unsettled[int(i)] = T @ G[i]
        if not alts:
            return float(score[0]), [], unsettled
        _, s_alt = pah.verify_poses(pts, sigma, np.stack([a.T_sensor_target for _, a in alts]), dirs)
        return float(score[0]), [(i, a, float(s)) for (i, a), s in zip(alts, s_alt)], unsettled
