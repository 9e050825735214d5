"""Search mode: acquire the target's pose on the scans steered onto the bearing fix.

Three sources of an initial pose, tried in this order: the prediction of a track lost within
``reacquire_window_s`` (one ICP run), an external seed (:meth:`~perception.pipeline.tridar.TriDAR.seed_pose`),
and PAH's search over the whole database. An answer the mode logic judges good (and the mission's
approach corridor admits, where configured) starts the filter and hands over to tracking.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any

import numpy as np

from perception.estimation.registration import RegistrationResult, icp
from perception.numeric import median
from perception.pipeline.modes import FrameVerdict
from perception.pipeline.publish import FrameOutput, lever, tof_share
from perception.pipeline.state import Mode, TruthScene
from perception.pipeline.tracking import MIN_REGISTRATION_POINTS, measurement_cov
from perception.sensing.pointcloud import PointCloud

if TYPE_CHECKING:
    from perception.pipeline.filter import PoseFilter
    from perception.pipeline.tridar import TriDAR

__all__ = ["SearchMode"]


class SearchMode:
    """Search mode's frames (acquisition).

    Args:
        tri: the pipeline (sensor, model, PAH database, filter, mode logic, track bookkeeping).
    """

    def __init__(self, tri: TriDAR) -> None:
        self.tri = tri

    def reset(self) -> None:
        """Nothing of its own: search's state is the pipeline's (external seed, lost track)."""

    def frame(self, scene: TruthScene | PointCloud, t: float) -> None:
        """One search frame at ``t`` [s]: scan the bearing box, register, and acquire if good."""
        tri = self.tri
        if tri.search_started is None:
            tri.search_started = t
        cloud = tri.scan(scene, t, tri.bearing.steered())
        tri.last_cloud = cloud
        out = tri.bearing.fix(cloud, t)
        tri.busy_until = cloud.t_end + tri.pc.search_latency_s
        out.available_t = tri.busy_until
        if tri.logic.search_too_far(t, out.range_m if out.kind == "bearing" else None):
            tri.publisher.append(out)
            return
        if len(cloud) < MIN_REGISTRATION_POINTS:
            tri.publisher.append(out)
            return
        t_ref = float(np.mean(cloud.times))
        constraint = tri.corridor
        res, verdict, admitted, from_track, from_pah = self._register(cloud, t_ref, constraint)
        tri.last_result = res
        tri.stats.registration_time_s.append(res.time_s)
        if verdict.good and admitted:
            out = self._acquire(cloud, t, t_ref, res, out, from_track, from_pah)
        elif not admitted:
            tri.stats.rejected_candidates += 1
        tri.publisher.append(out)

    def _register(self, cloud: PointCloud, t_ref: float, constraint: Any
                  ) -> tuple[RegistrationResult, FrameVerdict, bool, PoseFilter | None, bool]:
        """The frame's candidate pose: ``(registration, verdict, admitted by the corridor,
        the lost track it continues or None, whether PAH found it)``."""
        tri = self.tri
        sigma = cloud.sigma
        icp_cfg = tri.logic.icp_config_for(cloud.subsystem)
        expected = max(median(sigma), tri.pc.measurement_floor_m)
        res, admitted, verdict, from_track, from_pah = None, False, None, None, False
        lost = tri.lost_track
        if lost is not None and t_ref - lost.t <= tri.pc.reacquire_window_s:
            # Reacquisition from the lost track's prediction (cheap); PAH only if that fails.
            res = icp(cloud.points, tri.model, lost.pose_at(t_ref), sigma=sigma,
                      directions=cloud.directions, config=icp_cfg)
            verdict = tri.logic.judge(res.converged, res.fitness, res.inlier_rmse, expected,
                                      res.T_sensor_target, lost.pose_at(t_ref), acquisition=True)
            admitted = constraint is None or bool(constraint.admits(res.T_sensor_target))
            from_track = lost if (verdict.good and admitted) else None
        if from_track is None:
            if tri.external_seed is not None:
                res = icp(cloud.points, tri.model, tri.external_seed[1], sigma=sigma,
                          directions=cloud.directions, config=icp_cfg)
                tri.external_seed = None
            else:
                # No wall-clock budget: the polygon budget bounds the work, and a run must not
                # depend on how busy the machine is (its latency is simulated, not measured).
                res = tri.pah.localize(cloud.points, tri.rng, constraint=constraint,
                                       sigma=sigma, max_time_s=math.inf)
                from_pah = True
            verdict = tri.logic.judge(res.converged, res.fitness, res.inlier_rmse, expected,
                                      res.T_sensor_target, None, acquisition=True)
            if verdict.good and from_pah and res.reason:
                # PAH validates its own answer (its score reached accept_fitness with almost no
                # point seen through the model) and says why not otherwise; ICP's fitness alone
                # is lenient (a pose 11 deg off on the iss_port cone fits 100 % within its gate
                # with 3 % of the points behind the surface). Search again on the next scan.
                verdict = FrameVerdict(False, f"PAH: {res.reason}")
            admitted = constraint is None or bool(constraint.admits(res.T_sensor_target))
        assert res is not None and verdict is not None
        return res, verdict, admitted, from_track, from_pah

    def _acquire(self, cloud: PointCloud, t: float, t_ref: float, res: RegistrationResult,
                 out: FrameOutput, from_track: PoseFilter | None, from_pah: bool) -> FrameOutput:
        """Start the track on ``res``: the filter, the track's bookkeeping, the twin monitor, and
        tracking mode; returns the frame's output (the pose, with ``out``'s bearing fix)."""
        tri = self.tri
        # The slide monitor probes a new track's first registrations (this one included), on
        # this search frame: no tracking frame's pattern to refine an outline on.
        tri.tracking.frame_pattern = None
        tri.slides.start()
        res = tri.slides.apply(cloud.points, cloud, res, t_ref, tri.logic.icp_config_for(cloud.subsystem), 0)
        cov = measurement_cov(res, tri.target.T_target_port[:3, 3], tri.pc)
        cov_acc = measurement_cov(res, tri.target.T_target_port[:3, 3], tri.pc, floors=False)
        floor = tri.pc.integrity.acquisition_floor_fraction
        if from_pah and from_track is None and floor > 0.0:
            # PAH's answer is good to its basin, not to ICP's noise: a first pose taken at its
            # claimed millimetres gave the filter a wrong velocity from the next frame.
            s = floor * float(np.linalg.norm(res.T_sensor_target[:3, 3]))
            cov = cov + np.diag([s * s] * 3 + [0.0] * 3)
            cov_acc = cov_acc + np.diag([s * s] * 3 + [0.0] * 3)
        share = tof_share(cloud.subsystem)
        if from_track is not None:
            tri.stats.reacquired_from_track += 1
            tri.filter.initialize(t_ref, res.T_sensor_target, cov,
                                  velocity=from_track.target_state()[1], omega=from_track.w,
                                  cov_acc=cov_acc, tof_share=share)
        else:
            tri.filter.initialize(t_ref, res.T_sensor_target, cov, cov_acc=cov_acc, tof_share=share)
        tri.lost_track = None
        tri.rivals.reset()  # a new track: its own registrations judge it
        tri.tracking.clear_rejects()
        tri.tracking.nis.clear()  # a new track: its own registrations judge it
        tri.n_updates = 1
        tri.accepted_fitness = res.fitness
        # PAH's answer may be a twin of the truth until the scans rule the twins out; a seed has
        # (so has a lost track's prediction, as far as that track had: continuity carries on what
        # it had ruled out, and no more).
        tri.twins.start(all_open=from_pah, continues_lost=from_track is not None)
        tri.last_pose_t = t_ref
        tri.stats.acquisitions.append((tri.search_started, t))
        tri.search_started = None
        tri.logic.go(t, Mode.TRACKING, f"acquired (fitness {res.fitness:.2f})")
        return FrameOutput(tri.busy_until, Mode.TRACKING, "pose", t_ref, len(cloud), fitness=res.fitness,
                           lever_m=lever(cloud.points), tof_share=share,
                           bearing=out.bearing, range_m=out.range_m, range_rate=out.range_rate,
                           filt=tri.filter.copy(), n_updates=tri.n_updates,
                           ambiguity_m=tri.twins.ambiguity_m)
