"""TriDAR operating modes: the bearing / search / tracking state machine and strategies by range.

This is the control logic of seed 000 section 3.3 (Fig. 4) and the "mission configuration
database" of section 5.3, kept free of sensors and estimators so it can be tested on its own:

* **bearing** at start-up and whenever geometry tracking is impossible: full-field scans, centroid
  bearing and filtered range / closing rate; hands over to search inside
  ``bearing_to_search_range_m`` with enough returns;
* **search** computes and *validates* an initial pose (fit quality and, when configured, the
  approach corridor) before tracking may start; falls back to bearing beyond
  ``search_to_bearing_range_m``;
* **tracking** steers the scan onto a region of interest chosen by range (whole structure far out,
  docking area closer, the port only at short range — seed 000 Fig. 9), judges every frame
  (fitness, inlier RMSE against the expected noise, jump against the prediction, filter gate) and
  declares loss of track after ``loss_of_track_frames`` bad frames in a row;
* **planned restarts** every ``restart_period_s`` (300 s in the flights) drop to search (or bearing
  when far) and must reacquire.

Tracker settings differ on triangulation data, as the seed notes: ``icp_triangulation`` (when
given) for a scan whose points came mostly from the triangulation subsystem, else ``icp``. The
scan's own points decide, not the distance to the target's origin: on a large target the port the
sensor looks at can be inside the transition range while the origin is well outside it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from perception.config import ICPConfig, PipelineConfig
from perception.geometry import pose_error
from perception.sensing.pointcloud import Subsystem
from perception.pipeline.state import Mode

__all__ = ["ModeEvent", "FrameVerdict", "ModeLogic", "corridor_constraint"]


@dataclass(frozen=True)
class ModeEvent:
    """A mode transition: when, from, to and why."""

    t: float
    source: Mode
    target: Mode
    reason: str


@dataclass(frozen=True)
class FrameVerdict:
    """Judgement of one tracking frame."""

    good: bool
    reason: str = ""


class ModeLogic:
    """Mode state, transitions and per-range strategies.

    Args:
        config: the pipeline section of the mission configuration.
        transition_range_m: the sensor's triangulation/TOF transition range [m].
    """

    def __init__(self, config: PipelineConfig, transition_range_m: float) -> None:
        if config.search_to_bearing_range_m < config.bearing_to_search_range_m:
            raise ValueError(
                f"search_to_bearing_range_m={config.search_to_bearing_range_m} is below "
                f"bearing_to_search_range_m={config.bearing_to_search_range_m}; expected hysteresis >= 0"
            )
        self.cfg = config
        self.transition_range_m = float(transition_range_m)
        self.mode = Mode.BEARING
        self.bad_frames = 0
        self.last_restart_t = 0.0
        self.events: list[ModeEvent] = []

    def reset(self, t: float = 0.0) -> None:
        """Start-up: bearing mode (seed 000 Fig. 4)."""
        self.mode = Mode.BEARING
        self.bad_frames = 0
        self.last_restart_t = float(t)
        self.events = []

    def go(self, t: float, mode: Mode, reason: str) -> None:
        """Record and enter a new mode (no-op when already there)."""
        if mode == self.mode:
            return
        self.events.append(ModeEvent(float(t), self.mode, mode, reason))
        self.mode = mode
        self.bad_frames = 0

    # ------------------------------------------------------------------ strategies by range
    def region_for_range(self, range_m: float) -> str:
        """Region of interest to scan while tracking at this range (seed 000 Fig. 9)."""
        if range_m > self.cfg.roi_whole_above_m:
            return "whole"
        if range_m > self.cfg.roi_port_below_m:
            return "docking_area"
        return "port"

    def icp_config_for(self, subsystem: npt.ArrayLike) -> ICPConfig:
        """Tracker settings for the subsystem that produced most of a scan's points.

        Args:
            subsystem: the scan's per-point :class:`~perception.sensing.pointcloud.Subsystem` codes
                (``PointCloud.subsystem``).
        """
        s = np.asarray(subsystem)
        tri = self.cfg.icp_triangulation
        if tri is not None and 2 * np.count_nonzero(s == int(Subsystem.TRIANGULATION)) > s.size:
            return tri
        return self.cfg.icp

    # ------------------------------------------------------------------ transitions
    def after_bearing(self, t: float, range_m: float | None, n_points: int, min_points: int) -> None:
        """Bearing -> search once close enough with enough returns."""
        if range_m is not None and n_points >= min_points and range_m <= self.cfg.bearing_to_search_range_m:
            self.go(t, Mode.SEARCH, f"range {range_m:.1f} m <= {self.cfg.bearing_to_search_range_m:.1f} m")

    def search_too_far(self, t: float, range_m: float | None) -> bool:
        """Search -> bearing when the target is (again) too far for geometry."""
        if range_m is not None and range_m > self.cfg.search_to_bearing_range_m:
            self.go(t, Mode.BEARING, f"range {range_m:.1f} m > {self.cfg.search_to_bearing_range_m:.1f} m")
            return True
        return False

    def restart_due(self, t: float) -> bool:
        """A planned restart (``restart_period_s``) is due."""
        period = self.cfg.restart_period_s
        return period is not None and (t - self.last_restart_t) >= period - 1e-9

    def restart(self, t: float, range_m: float | None) -> None:
        """Planned restart: drop the track; reacquire by search (bearing when far)."""
        self.last_restart_t = float(t)
        far = range_m is not None and range_m > self.cfg.bearing_to_search_range_m
        self.go(t, Mode.BEARING if far else Mode.SEARCH, "planned restart")

    # ------------------------------------------------------------------ frame quality
    def judge(
        self,
        converged: bool,
        fitness: float,
        inlier_rmse: float,
        expected_sigma: float,
        T_est: np.ndarray,
        T_pred: np.ndarray | None,
        filter_accepted: bool = True,
        acquisition: bool = False,
    ) -> FrameVerdict:
        """Is a tracking frame good? (Fitness, RMSE vs noise, jump vs prediction, filter gate.)

        ``acquisition``: the pose of a search (PAH, external seed or reacquisition), validated
        before it may start a track (seed 000 section 5.3): it must fit ``acquire_min_fitness``
        of the scan, not only the tracking floor ``min_fitness``.
        """
        c = self.cfg
        min_fit = max(c.min_fitness, c.acquire_min_fitness) if acquisition else c.min_fitness
        if not converged and fitness < min_fit:
            # Running out of iterations with a good fit is a slow convergence, not a bad frame;
            # the fit, noise and jump checks below still apply.
            return FrameVerdict(False, "registration did not converge")
        if fitness < min_fit:
            what = "acquisition fitness" if acquisition else "fitness"
            return FrameVerdict(False, f"{what} {fitness:.2f} < {min_fit:.2f}")
        limit = c.max_inlier_rmse_factor * max(expected_sigma, 1e-3)
        if inlier_rmse > limit:
            return FrameVerdict(False, f"inlier RMSE {inlier_rmse:.4f} m > {limit:.4f} m")
        if T_pred is not None:
            dt, dr = pose_error(T_est, T_pred)
            if dt > c.max_jump_m or dr > c.max_jump_deg:
                return FrameVerdict(False, f"jump {dt:.3f} m / {dr:.2f} deg from the prediction")
        if not filter_accepted:
            return FrameVerdict(False, "rejected by the filter's innovation gate")
        return FrameVerdict(True)

    def record(self, t: float, verdict: FrameVerdict) -> bool:
        """Count bad frames; after ``loss_of_track_frames`` in a row go to search. True on loss."""
        if verdict.good:
            self.bad_frames = 0
            return False
        self.bad_frames += 1
        if self.bad_frames >= self.cfg.loss_of_track_frames:
            self.go(t, Mode.SEARCH, f"loss of track: {verdict.reason}")
            return True
        return False


def corridor_constraint(pc: PipelineConfig, R_nominal: npt.NDArray[np.float64]) -> Any:
    """The mission's approach corridor as a PAH pose constraint (search acquires only inside it,
    a track that leaves it is lost), or None when ``pipeline.use_corridor`` is off."""
    if not pc.use_corridor:
        return None
    from perception.estimation.pah import PoseConstraint

    return PoseConstraint.from_corridor(pc.corridor, R_nominal)
