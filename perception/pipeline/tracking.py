"""Tracking mode: scan a region of interest around the predicted pose, de-skew, register from the
prediction, refine by the outline where ICP leaves axes unobserved, and update the filter.

A registration the filter's innovation gate rejects is kept; a few in a row that agree with one
another restart the filter on them (keeping its rates) rather than dropping a good track. The
ambiguity monitor (:class:`~perception.pipeline.twins.TwinMonitor`) runs on the accepted frames.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections import deque
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt

from perception.config import PipelineConfig
from perception.estimation.registration import RegistrationResult, icp
from perception.geometry import cross_rows, fast_matrix_to_rotvec, pose_error, skew
from perception.numeric import median
from perception.pipeline.modes import FrameVerdict
from perception.pipeline.publish import FrameOutput, lever, tof_share
from perception.pipeline.state import Mode, TruthScene
from perception.sensing.pointcloud import PointCloud, Subsystem
from perception.sensing.scan_patterns import angles_to_directions

if TYPE_CHECKING:
    from perception.pipeline.filter import PoseFilter
    from perception.pipeline.tridar import TriDAR

FloatArray = npt.NDArray[np.float64]

__all__ = ["MIN_REGISTRATION_POINTS", "TrackingMode", "deskew", "measurement_cov"]

#: Points a frame needs for a registration.
MIN_REGISTRATION_POINTS = 12
#: The predicted bias (TrackingMode.predict_bias) is the mean of the track's last this many probes.
BIAS_PROBES = 10

#: A registration's normalised innovation squared counts at most this much in the consistency
#: monitor's mean (a singular innovation covariance reports inf).
NIS_CAP = 1.0e4


@functools.lru_cache(maxsize=64)
def _nis_mean_bound(n: int) -> float:
    """99.9 % quantile of the mean of ``n`` chi-square(6) values."""
    from scipy.stats import chi2

    return float(chi2.ppf(0.999, 6 * n)) / n


def deskew(cloud: PointCloud, motion_T: Any, t_ref: float) -> FloatArray:
    """Move every point to where it would be at ``t_ref`` under a constant-rate motion estimate.

    Args:
        cloud: points with their sample times.
        motion_T: an object with ``p``, ``v``, ``R``, ``w``, ``t`` (a :class:`PoseFilter` state).
        t_ref: reference time [s].

    Returns:
        (N, 3) de-skewed points [m], sensor frame.
    """
    if len(cloud) == 0:
        return cloud.points.copy()
    f = motion_T
    tau_i = cloud.times - f.t
    tau_r = t_ref - f.t
    p_i = f.p + np.outer(tau_i, f.v)
    p_r = f.p + f.v * tau_r
    x = cloud.points - p_i
    w = np.asarray(f.w, dtype=np.float64)
    rate = float(np.sqrt(w @ w))
    if rate == 0.0:
        return x + p_r
    # Rodrigues about the one axis w / |w|, by the angle rate (tau_r - tau_i) of each point.
    k = w / rate
    ang = rate * (tau_r - tau_i)
    c, s = np.cos(ang)[:, None], np.sin(ang)[:, None]
    kx = cross_rows(np.broadcast_to(k, x.shape), x)
    return x * c + kx * s + np.outer(x @ k, k) * (1.0 - c) + p_r


def measurement_cov(res: RegistrationResult, r_port: FloatArray, pc: PipelineConfig,
                    floors: bool = True) -> FloatArray:
    """Registration covariance plus the configured floors (what the bound leaves out); without
    ``floors``, the registration's own (the filter's accuracy covariance takes that: the floors
    are errors that repeat from frame to frame, which the publisher carries instead).

    The floors are added about the filter's reference point (the docking port, ``r_port`` (3,)
    [m] in the target frame), where the scan looks and where they were measured: added about a
    centre of mass 12 m behind the port, the attitude floor alone would put 0.3 deg x 12 m = 6 cm
    of position error on a port whose position is known to a few millimetres.
    """
    if not floors:
        return 0.5 * (res.covariance + res.covariance.T)
    a = res.T_sensor_target[:3, :3] @ r_port
    J = np.eye(6)
    J[:3, 3:] = -skew(a)  # origin -> port: dp_port = dp - [a]x dtheta
    cov = J @ res.covariance @ J.T
    cov.flat[0:21:7] += pc.measurement_floor_m**2
    cov.flat[21::7] += math.radians(pc.measurement_floor_deg) ** 2
    J[:3, 3:] = skew(a)  # and back
    cov = J @ cov @ J.T
    return 0.5 * (cov + cov.T)


class TrackingMode:
    """Tracking mode's frames, the filter's gate-reject handling and the outline refinement.

    State: the gate's rejections in a row and their registrations, and the frame's scan pattern
    (for the outline refinement).

    Args:
        tri: the pipeline (sensor, model, filter, mode logic, planner, track bookkeeping).
    """

    def __init__(self, tri: TriDAR) -> None:
        self.tri = tri
        self.reset()

    def reset(self) -> None:
        self.clear_rejects()
        self.frame_pattern: tuple[Any, float] | None = None  # (pattern, start time) of the frame
        self.nis: deque[float] = deque(maxlen=self.tri.pc.integrity.consistency_window_frames or 1)
        # The registrations' predicted bias at the port (sensor frame [m]), the track's last
        # probes (predict_bias); a tuple, rebound, so a frame's output may keep it.
        self.bias_probes: tuple[FloatArray, ...] = ()
        self.bias_frames = 0  # good frames since the last probe

    def consistency(self) -> float:
        """The variance scale the registrations' disagreement with the filter asks for
        (``integrity.consistency_window_frames``): the mean normalised innovation squared of the
        window over 6 when it is beyond chi-square(6)'s 99.9 % band for its mean, else 1."""
        n = len(self.nis)  # empty with the monitor off: nothing is appended
        if n < 2:
            return 1.0
        m = sum(self.nis) / n
        return m / 6.0 if m > _nis_mean_bound(n) else 1.0

    def clear_rejects(self) -> None:
        """Forget the gate's rejections (an accepted update, a new track or filter)."""
        self.gate_rejects = 0
        self.rejected: list[tuple[float, FloatArray, FloatArray, FloatArray]] = []  # since the last update

    # ------------------------------------------------------------------ the scan
    def pattern(self, T_pred: FloatArray, t: float = 0.0) -> tuple[Any, str]:
        """The scan pattern around the predicted pose ``T_pred`` and the name of its region."""
        tri = self.tri
        rng_m = float(np.linalg.norm(T_pred[:3, 3]))
        region = tri.logic.region_for_range(rng_m)
        roi = tri.target.regions.get(region) or tri.target.regions["whole"]
        if tri.planner is not None:
            weak = tri.last_result is not None and bool(tri.last_result.degenerate_axes)
            roi, _ = tri.planner.choose(T_pred, region, tri.frame_index, t, weak,
                                        pin=tri.slides.turn_direction(T_pred))
            region = roi.name
        try:
            pattern = tri.sensor.make_scan_pattern(tri.frame_index, T_pred, roi)
        except ValueError:
            pattern = tri.bearing.full_field()
        return pattern, region

    # ------------------------------------------------------------------ the frame
    def frame(self, scene: TruthScene | PointCloud, t: float) -> None:
        """One tracking frame at ``t`` [s]."""
        tri = self.tri
        f = tri.filter
        T_start = f.pose_at(t)
        pattern, _ = self.pattern(T_start, t)
        cloud = self.take(scene, t, pattern)
        if cloud is None:
            return
        t_ref = float(0.5 * (cloud.t_start + cloud.t_end))
        pts = deskew(cloud, f, t_ref)
        T_pred = f.pose_at(t_ref)
        # On an established track (rates estimated, the last frames accepted) the prediction is
        # within a few sigma of the answer: ICP starts in its fine phase.
        settled = (tri.pc.fine_only_tracking and tri.n_updates >= 3
                   and tri.logic.bad_frames == 0 and self.gate_rejects == 0)
        icp_cfg = tri.logic.icp_config_for(cloud.subsystem)
        res = icp(pts, tri.model, T_pred, sigma=cloud.sigma, directions=cloud.directions,
                  config=icp_cfg, coarse=not settled)
        self.frame_pattern = None if isinstance(scene, PointCloud) else (pattern, t)
        res = self.outline_refine(res, pts, cloud)
        res = tri.slides.apply(pts, cloud, res, t_ref, icp_cfg, tri.n_updates)
        tri.last_result = res
        tri.stats.registration_time_s.append(res.time_s)
        expected = max(median(cloud.sigma), tri.pc.measurement_floor_m)
        share = tof_share(cloud.subsystem)
        # With a running filter the consistency test is its innovation gate, which weighs each
        # direction by the registration's covariance: a pose that slides along a direction the
        # geometry leaves unobservable (degenerate_axes) is not a jump, it is uninformative.
        verdict = tri.logic.judge(res.converged, res.fitness, res.inlier_rmse, expected,
                                  res.T_sensor_target, None)
        if verdict.good:
            verdict = self._update(t_ref, res, expected, verdict, share)
        if verdict.good and tri.n_updates > 0:
            tri.twins.monitor(pts, cloud, res, t_ref, icp_cfg)
            tri.slides.switch(pts, cloud, t_ref)
            if settled:
                self.predict_bias(res, icp_cfg)
        outside = self.outside_corridor(t_ref)
        if outside is not None:
            verdict = FrameVerdict(False, outside)
            self.drop(t, outside)
        self.conclude(cloud, pts, t, t_ref, res, verdict, share)

    def outside_corridor(self, t_ref: float) -> str | None:
        """Why the track's pose at ``t_ref`` [s] is outside the mission's approach corridor (its
        attitude further from the nominal than ``corridor.attitude_tolerance_deg``), or None.

        The corridor is the mission's statement of where the target can be; search acquires
        only inside it, and a track that has drifted out of it is wrong by at least its distance
        to the corridor, whatever its covariance says. On a generated cylinder bus whose roll only
        a thin boom pins, the filter took a roll rate of 2 deg/s the target never had and the roll
        left the 20 deg corridor for 50-160 deg, published valid 0.3-0.88 m off at the port
        between the turn monitor's holds. Only the attitude is judged: close in, the line of
        sight to the target origin of a large target can leave the cone while the port is on
        the axis. A confirmed track turning faster than ``corridor.max_rate_deg_s`` is judged
        outside it too.
        """
        tri = self.tri
        corridor = tri.corridor
        if corridor is None or not tri.filter.initialized or tri.logic.mode != Mode.TRACKING:
            return None
        R = tri.filter.pose_at(t_ref)[:3, :3]
        if not corridor.attitude_ok(R[None])[0]:
            off = math.degrees(float(np.linalg.norm(fast_matrix_to_rotvec(corridor.R_sensor_target_nominal.T @ R))))
            return (f"tracked attitude {off:.1f} deg from the nominal, outside the approach corridor "
                    f"(corridor.attitude_tolerance_deg={tri.pc.corridor.attitude_tolerance_deg:g})")
        # The same for the turn rate: a restarted filter on the bus took a false roll rate of
        # 4 deg/s from registrations whose scans its own prediction steered, and was published
        # valid up to 0.14 m off at 7 m before the roll had left the 20 deg corridor.
        limit = tri.pc.corridor.max_rate_deg_s
        if limit is None or tri.n_updates < tri.pc.integrity.confirm_frames:
            return None
        rate = math.degrees(float(np.linalg.norm(tri.filter.W)))
        if rate <= limit:
            return None
        return (f"tracked turn rate {rate:.2f} deg/s, outside the approach corridor "
                f"(corridor.max_rate_deg_s={limit:g})")

    def drop(self, t: float, reason: str) -> None:
        """Lose the track now, for ``reason``, and forget it: a wrong track is no prediction to
        reacquire from (search starts afresh, inside the corridor)."""
        tri = self.tri
        tri.logic.go(t, Mode.SEARCH, f"loss of track: {reason}")
        self.after_loss(True, t)
        tri.lost_track = None
        tri.stats.corridor_exits += 1

    def take(self, scene: TruthScene | PointCloud, t: float, pattern: Any) -> PointCloud | None:
        """The frame's cloud, or None after recording a frame with too few points to register
        (a bad frame towards loss of track, nothing published)."""
        tri = self.tri
        cloud = tri.scan(scene, t, pattern)
        tri.last_cloud = cloud
        tri.busy_until = cloud.t_end + tri.pc.tracking_latency_s
        n = len(cloud)
        if n >= MIN_REGISTRATION_POINTS:
            return cloud
        reason = f"{n} points; tracking needs >= {MIN_REGISTRATION_POINTS}"
        lost = tri.logic.record(t, FrameVerdict(False, reason))
        self.after_loss(lost, t)
        tri.publisher.append(FrameOutput(tri.busy_until, tri.logic.mode, "none", t, n))
        return None

    def conclude(self, cloud: PointCloud, pts: FloatArray, t: float, t_ref: float,
                 res: RegistrationResult, verdict: FrameVerdict, share: float) -> bool:
        """Record the frame's verdict (loss of track), queue its output (the pose, with the
        frame's bearing fix; ``share``: of its points the time of flight ranged); True when the
        track was lost."""
        tri = self.tri
        lost = tri.logic.record(t, verdict)
        self.after_loss(lost, t)
        out = FrameOutput(tri.busy_until, tri.logic.mode, "pose" if tri.logic.mode == Mode.TRACKING else "none",
                          t_ref, len(cloud), fitness=res.fitness, filt=tri.slides.pin(tri.filter.copy()),
                          bias_cov=self.bias_covariance(),
                          n_updates=tri.n_updates, ambiguity_m=tri.twins.ambiguity_m, lever_m=lever(pts),
                          consistency=self.consistency(), turn_confirmed=tri.slides.turn_confirmed,
                          tof_share=share, rival_m=tri.rivals.offset_m(tri.filter))
        bfix = tri.bearing.fix(cloud, t)
        out.bearing, out.range_m, out.range_rate = bfix.bearing, bfix.range_m, bfix.range_rate
        out.bearing_source = bfix.bearing_source
        tri.publisher.append(out)
        return lost

    def _update(self, t_ref: float, res: RegistrationResult, expected: float,
                verdict: FrameVerdict, share: float) -> FrameVerdict:
        """The filter's update on a good registration (``share``: of its points the time of
        flight ranged); the frame's verdict after it."""
        tri = self.tri
        cov = measurement_cov(res, tri.target.T_target_port[:3, 3], tri.pc)
        cov_acc = measurement_cov(res, tri.target.T_target_port[:3, 3], tri.pc, floors=False)
        tri.slides.loosen(tri.filter)
        upd = tri.filter.update(t_ref, res.T_sensor_target, cov, cov_acc, tof_share=share)
        if tri.pc.integrity.consistency_window_frames is not None:
            self.nis.append(min(upd.mahalanobis2, NIS_CAP))
        if upd.accepted:
            tri.rivals.accepted(t_ref, res.T_sensor_target, cov)
            self.clear_rejects()
            tri.n_updates += 1
            tri.last_pose_t = t_ref
            tri.accepted_fitness = res.fitness
            return verdict
        # The registration is sound but the filter disagrees: an unmodelled manoeuvre or an
        # overconfident filter. After a few such frames that agree with one another,
        # restart the filter on them (keeping the rates) rather than dropping a good track.
        # Rejected registrations that disagree with one another as well (ICP in another
        # basin each frame: the roll of a near-cylindrical bus 20-40 deg off under a 2 deg
        # sigma) are not a track to restart on: they count towards loss of track.
        self.gate_rejects += 1
        tri.rivals.rejected(tri.filter, res.T_sensor_target, cov)
        self.rejected = [*self.rejected, (t_ref, res.T_sensor_target, cov, cov_acc, share)]
        self.rejected = self.rejected[-tri.pc.filter_reinit_frames:]
        restart = None
        if self.gate_rejects >= tri.pc.filter_reinit_frames and not res.degenerate_axes:
            restart = self._restart_on_rejected(tri.filter)
        if restart is None:
            return tri.logic.judge(True, res.fitness, res.inlier_rmse, expected,
                                   res.T_sensor_target, None, filter_accepted=False)
        tri.rivals.replaced(tri.filter)
        tri.filter = restart
        self.clear_rejects()
        tri.stats.filter_reinits += 1
        tri.n_updates = 1
        # A restarted filter is a new track to the monitors: probed from its first frames and
        # confirmed by its turn probes (slides.turn_confirmed) before it is trusted.
        tri.slides.start()
        tri.last_pose_t = t_ref
        tri.accepted_fitness = res.fitness
        return verdict

    def _restart_on_rejected(self, f: PoseFilter) -> PoseFilter | None:
        """A filter restarted on the registrations the gate rejected in a row (keeping ``f``'s
        rates: the motion between the frames is the track's; their covariance grown by the rate
        error that alone would explain the rejection), if each of them passes the gate of the
        one restarted on those before it; else None."""
        v_origin = f.target_state()[1]
        g = f.copy()
        (t0, T0, C0, A0, s0), *rest = self.rejected
        # The rates are kept, but not as sure as before: a wrong rate is one reason the gate
        # rejects (a cylinder bus's track took a 1.5 deg/s false roll rate from a slow basin
        # change; five restarts that kept it with its small covariance each drifted the roll
        # off again, published valid 20 deg off). Their covariance grows by the rate error that
        # alone would explain the newest rejected registration since the last accepted one.
        # (After the rejected registrations have been checked against one another with the
        # rates as they were: doubted first, any two would pass.)
        doubt = f.rate_doubt(self.rejected[-1][1], self.tri.last_pose_t)
        g.initialize(t0, T0, C0, velocity=v_origin, omega=f.w, cov_acc=A0, tof_share=s0)
        P, P_acc = g.P.copy(), g.P_acc.copy()
        for rates in (slice(3, 6), slice(9, 12)):
            P[rates, rates] = f.P[rates, rates]
            P_acc[rates, rates] = f.P_acc[rates, rates]
        g.P, g.P_acc = P, P_acc
        for t_k, T_k, C_k, A_k, s_k in rest:
            if not g.update(t_k, T_k, C_k, A_k, tof_share=s_k).accepted:
                return None
        for name in ("P", "P_acc"):
            M = getattr(g, name).copy()
            M[3:6, 3:6] += np.outer(doubt[:3], doubt[:3])
            M[9:12, 9:12] += np.outer(doubt[3:], doubt[3:])
            setattr(g, name, M)
        return g

    def after_loss(self, lost: bool, t: float) -> None:
        """On loss of track: keep the track's filter for reacquisition and reset the live one."""
        if lost:
            tri = self.tri
            tri.stats.losses += 1
            # A track whose last accepted registrations left many returns unexplained was
            # sliding off: reacquiring from its prediction would continue the slide.
            if tri.filter.initialized:
                sound = tri.accepted_fitness >= tri.pc.integrity.min_valid_fitness
                tri.lost_track = tri.filter.copy() if sound else None
                tri.twins.track_lost()
            tri.filter.reset()
            tri.rivals.reset()
            tri.n_updates = 0
            tri.search_started = t

    # ------------------------------------------------------------------ bias prediction
    def bias_covariance(self) -> FloatArray | None:
        """(3, 3) the outer product of the registrations' predicted bias at the port with itself
        [m^2], sensor frame, from the track's last probes of :meth:`predict_bias`, or None (fewer
        than two, or the predictor off). The probes scatter with the pattern's phase (1-2 mm on
        a boxes-and-booms target at 20 m), so the outer product of their mean holds their
        scatter over their count too: that is taken out (the unbiased estimate of the mean's
        outer product, its negative directions cut), or a shape without a bias would be given
        one of the phases' scatter."""
        n = len(self.bias_probes)
        if n < 2:
            return None
        b = np.asarray(self.bias_probes)
        m = b.mean(axis=0)
        M = np.outer(m, m) - np.cov(b.T, ddof=1) / n
        lam, V = np.linalg.eigh(0.5 * (M + M.T))
        return (V * np.maximum(lam, 0.0)) @ V.T

    def predict_bias(self, res: RegistrationResult, icp_cfg: Any) -> None:
        """The frame's registration bias at the port as the sensor model predicts it
        (``integrity.bias_prediction_frames``): the frame's scan pattern taken again on the
        pipeline's own model at the registered pose, by the same sensor without its noise,
        jitter, faults or range offset (which the filter carries), and registered from that
        pose as the frame was. Where the result lands off the pose is where the frame's
        registration lands off the truth, whatever the noise: the beam's footprint, whose first
        echo dilates the near surface at every edge it straddles (0.5 mrad is 1 cm at 20 m),
        and the samples a region's edges cut. On a generated boxes-and-booms target at 19-25 m
        the scans of its 'port_x2' region registered 3-7 mm off across the line of sight every
        frame (truth poses of a flight, 12 noisy scans each; none with a footprint of nil) and
        this predicted 3-5 mm of it, in the same direction; in flight the ISS-like port's
        registrations sat 1.6-2.1 mm off at 20-30 m where it predicted 1.5-1.9 mm. Only the
        published covariance takes it (:class:`~perception.pipeline.publish.Publisher`), and only
        when configured: on top of the static figures it made the library's shapes conservative
        (iss_port NEES 2.4 -> 1.3 on new seeds) while it took the worst overconfident ones from
        6.4 to 2.8 (boxes and booms) and 6.0 to 4.7 (a flat face).
        """
        tri = self.tri
        every = tri.pc.integrity.bias_prediction_frames
        if every is None or self.frame_pattern is None or not res.converged or res.degenerate_axes:
            return
        self.bias_frames += 1
        if self.bias_frames < every:
            return
        self.bias_frames = 0
        T = res.T_sensor_target
        quiet = self.quiet_sensor
        # Its own generator: the quiet sensor's draws change nothing, and the pipeline's stay as
        # they were (the closed loop is the same with the probe or without).
        cloud = quiet.scan(tri.model_target, T, self.frame_pattern[0], np.random.default_rng(0))
        if len(cloud) < MIN_REGISTRATION_POINTS:
            return
        # Weighted with the noise the real sensor reports for each point.
        rng_p = np.linalg.norm(cloud.points, axis=1)
        sig = np.where(cloud.subsystem == Subsystem.TOF, tri.sensor.range_sigma(rng_p, Subsystem.TOF),
                       tri.sensor.range_sigma(rng_p, Subsystem.TRIANGULATION))
        ref = icp(cloud.points, tri.model, T, sigma=sig, directions=cloud.directions,
                  config=icp_cfg, coarse=False)
        if not ref.converged:
            return
        r_port = tri.target.T_target_port[:3, 3]
        Te = ref.T_sensor_target
        b = Te[:3, :3] @ r_port + Te[:3, 3] - (T[:3, :3] @ r_port + T[:3, 3])
        self.bias_probes = (*self.bias_probes[-(BIAS_PROBES - 1):], b)

    @functools.cached_property
    def quiet_sensor(self) -> Any:
        """The pipeline's sensor without its noise, pointing jitter, faults and range offset,
        switching between its subsystems where the real one does (the default switch is
        derived from the noise models, which it no longer has)."""
        from perception.sensing.sensors.tridar import TriDARSensor

        real = self.tri.sensor
        c = real.config
        return TriDARSensor(c.model_copy(update={
            "tof": c.tof.model_copy(update={"noise_sigma_m": 0.0, "bias_m": 0.0}),
            "triangulation": c.triangulation.model_copy(update={"noise_k_per_m": 0.0}),
            "pointing": c.pointing.model_copy(update={"jitter_rad": 0.0}),
            "faults": type(c.faults)(),
            "transition_range_m": real.transition_range_m,
        }))

    # ------------------------------------------------------------------ outline refinement
    def outline_refine(self, res: RegistrationResult, pts: FloatArray, cloud: PointCloud) -> RegistrationResult:
        """Where ICP left axes unobserved, add what the scan says about the outline.

        The samples of the frame's pattern that gave no return bound the target as much as the
        returns locate its surface: where the scan's curve crosses the outline, the model's
        outline must cross the same short arc (:func:`perception.estimation.silhouette.scan_outline_pairs`,
        the scanning form of seed 003's depth-map outline). A flat face seen head-on, which
        point-to-plane ICP cannot place in its plane, is placed by its edges. The refinement is
        kept when it converges, observes more axes than ICP did and stays within a frame's jump of
        ICP's pose; its covariance is the joint information's.
        """
        tri = self.tri
        if not (res.degenerate_axes and tri.pc.outline_refinement and self.frame_pattern is not None):
            return res
        from perception.estimation.silhouette import (
            FlashGeometry,
            refine_with_outline,
            scan_outline_pairs,
        )

        pattern, t0 = self.frame_pattern
        dirs = angles_to_directions(pattern.az, pattern.el)
        returned = np.isin(t0 + pattern.times, cloud.times)
        a, b = scan_outline_pairs(dirs, returned)
        if a.size < 3:
            return res
        geom = FlashGeometry(dirs, 1, dirs.shape[0], 0.05, 0.0, math.inf)
        icp_cfg = tri.logic.icp_config_for(cloud.subsystem)
        ref = refine_with_outline(
            pts, cloud.directions, cloud.sigma, dirs[a], dirs[b], tri.model_target, tri.model,
            res.T_sensor_target, geom, noise_floor_fraction=icp_cfg.noise_floor_fraction,
            back_facing_cos=icp_cfg.back_facing_cos, gate_m=max(3.0 * res.inlier_rmse, 0.05),
        )
        tri.stats.outline_refinements += 1
        if not ref.converged or len(ref.degenerate_axes) >= len(res.degenerate_axes):
            return res
        # A refinement that turns or moves the pose further than a frame may jump has found
        # another basin of the outline (a near-symmetric twin), not the slide it is there for.
        dt, dr = pose_error(ref.T_sensor_target, res.T_sensor_target)
        if dt > tri.pc.max_jump_m or dr > tri.pc.max_jump_deg:
            return res
        tri.stats.outline_accepted += 1
        return dataclasses.replace(ref, fitness=res.fitness, inlier_rmse=res.inlier_rmse,
                                   n_inliers=res.n_inliers, time_s=res.time_s + ref.time_s)
