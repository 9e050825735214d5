"""Publishing: frame outputs queued until the processor is done with them, and the state vector at
the call time with its integrity (protection level, correlated-error terms, degraded flag).

A frame's result (:class:`FrameOutput`) becomes available ``latency`` seconds after its scan ends;
:meth:`Publisher.publish` returns the newest available one with the filter state propagated from its
measurement time to the call time (what a navigation filter publishes). A pose older than
``max_pose_age`` is no longer published as valid.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from perception.config import PipelineConfig
from perception.geometry import fast_matrix_to_quat
from perception.pipeline.filter import EgoMotion, PoseFilter
from perception.pipeline.integrity import (
    alert_limit,
    integrity_factor,
    port_covariance,
    protection_level,
    turn_about,
)
from perception.pipeline.state import INVALID_VARIANCE, Mode, StateVector, Validity
from perception.sensing.pointcloud import Subsystem

FloatArray = npt.NDArray[np.float64]

__all__ = ["FrameOutput", "Publisher", "lever", "tof_share"]


@dataclass
class FrameOutput:
    """A frame's result, published once the processor is done with it."""

    available_t: float
    mode: Mode
    kind: str  # "bearing" | "pose" | "none"
    t_meas: float
    n_points: int
    fitness: float = 0.0
    bearing: FloatArray | None = None
    range_m: float = 0.0
    range_sigma: float = 0.0
    range_rate: float | None = None
    range_valid: bool = True  # False: a bearing without a range (thermal, no coarse range yet)
    bearing_source: str = ""  # "lidar" | "thermal" for a bearing fix
    filt: PoseFilter | None = None
    n_updates: int = 0
    ambiguity_m: float = 0.0  # port offset to a twin pose the scan cannot rule out [m]
    lever_m: float = math.inf  # RMS distance of the frame's points from their centroid [m]
    tof_share: float = 0.0  # fraction of the frame's points the time-of-flight ranged
    consistency: float = 1.0  # variance scale from the registrations' disagreement with the filter
    turn_confirmed: bool = True  # the turn monitor has judged the track (SlideMonitor.turn_confirmed)
    rival_m: float = 0.0  # port offset to a rejected registration not yet ruled out [m] (RivalMonitor)
    bias_cov: FloatArray | None = None  # (3, 3) [m^2] the registrations' predicted bias at the port (TrackingMode.bias_covariance)


def tof_share(subsystem: npt.NDArray[np.int8]) -> float:
    """Fraction of a frame's points (``PointCloud.subsystem``) ranged by the time of flight."""
    return float(np.mean(subsystem == Subsystem.TOF)) if len(subsystem) else 0.0


def _with_bias(P: FloatArray, sigma: float, range_bias: float, los: FloatArray) -> FloatArray:
    """A copy of the (12, 12) ``P`` with a correlated position error of ``sigma`` [m] per axis,
    at least ``range_bias`` [m] along the line of sight (``los``: (3, 3) projector onto it)."""
    Q = P.copy()
    Q.flat[0:36:13] += sigma**2
    Q[0:3, 0:3] += max(range_bias**2 - sigma**2, 0.0) * los
    return Q


def lever(points: FloatArray) -> float:
    """RMS distance [m] of ``points`` (N, 3) from their centroid (inf for none)."""
    if len(points) == 0:
        return math.inf
    return float(np.sqrt(np.mean(np.sum((points - points.mean(axis=0)) ** 2, axis=1))))


class Publisher:
    """The queue of frame outputs and the state vector published from the newest available one.

    Args:
        pc: the pipeline configuration (its ``integrity`` section).
        r_port: (3,) the docking port's position in the target frame [m].
        max_pose_age: age [s] beyond which a measurement is no longer published as valid.
        tof_bias_m: the time of flight's configured range bias [m] (``sensor.tof.bias_m``): a
            frame whose points it ranged is off along the line of sight by up to its share of
            it, the same every frame (the filter cannot average it away): the protection
            level's allowance along the line of sight (the published covariance has it from the
            filter's accuracy covariance, ``PoseFilter``'s ``range_bias_m``).
        accuracy: ``range -> (across, along)`` [m], the correlated position error at the port
            calibrated on the target's model (``integrity.accuracy_calibration``), called at the
            first published pose; None: the static ``integrity.accuracy_*`` figures.
    """

    def __init__(self, pc: PipelineConfig, r_port: FloatArray, max_pose_age: float,
                 tof_bias_m: float = 0.0,
                 accuracy: Callable[[float], tuple[float, float]] | None = None) -> None:
        self.pc = pc
        self.r_port = r_port
        self.max_pose_age = max_pose_age
        self.tof_bias_m = abs(float(tof_bias_m))
        self.accuracy = accuracy
        self.reset()

    def reset(self) -> None:
        self.pending: list[FrameOutput] = []
        self.published: FrameOutput | None = None

    def append(self, out: FrameOutput) -> None:
        """Queue a frame's output (published from ``out.available_t`` on)."""
        self.pending.append(out)

    def publish(self, t: float, mode: Mode, ego: EgoMotion | None) -> StateVector:
        """The state vector at ``t`` [s] from the newest output available then.

        Args:
            t: call time [s].
            mode: the pipeline's mode now.
            ego: the host's latest rates, which carry the filter state to ``t`` (None: none).
        """
        ready = [o for o in self.pending if o.available_t <= t + 1e-9]
        if ready:
            self.published = ready[-1]
            self.pending = [o for o in self.pending if o.available_t > t + 1e-9]
        out = self.published
        if out is None:
            return StateVector.invalid(t, mode)
        bearing_ok = out.bearing is not None and (t - out.t_meas) <= self.max_pose_age
        valid_kw: dict[str, bool] = {}
        kw: dict[str, Any] = {}
        if bearing_ok:
            ranged = out.range_valid
            valid_kw.update(bearing=True, range=ranged, range_rate=ranged and out.range_rate is not None)
            kw.update(bearing=out.bearing, range=out.range_m if ranged else 0.0,
                      range_rate=out.range_rate if ranged and out.range_rate is not None else 0.0,
                      bearing_source=out.bearing_source)
        cov = np.eye(12) * INVALID_VARIANCE
        pose_fresh = out.kind == "pose" and out.filt is not None and (t - out.t_meas) <= self.max_pose_age
        if pose_fresh and mode == Mode.TRACKING and out.filt is not None:
            self._pose(out, out.filt, t, ego, cov, valid_kw, kw)
        return StateVector(
            t=t, mode=mode, valid=Validity(**valid_kw), covariance=cov, fitness=out.fitness,
            n_points=out.n_points, latency=max(t - out.t_meas, 0.0), **kw,
        )

    def _pose(self, out: FrameOutput, filt: PoseFilter, t: float, ego: EgoMotion | None,
              cov: FloatArray, valid_kw: dict[str, bool], kw: dict[str, Any]) -> None:
        """The tracked pose, rates and covariance at ``t``, with their integrity (in place)."""
        f = filt.copy()
        if ego is not None:
            f.set_ego(ego)  # the host's latest rates carry the state to now
        if t > f.t:
            f.predict(t)
        fp, fv, fR, fw, fP = f.target_state()
        rates_ok = out.n_updates >= 3
        valid_kw.update(position=True, attitude=True, velocity=rates_ok, angular_velocity=rates_ok)
        rng_m = float(np.linalg.norm(fp))
        kw.update(position=fp, quaternion=fast_matrix_to_quat(fR), range=rng_m,
                  bearing=np.array([np.arctan2(fp[0], fp[2]), np.arctan2(-fp[1], np.hypot(fp[0], fp[2]))]))
        kw["bearing_source"] = ""
        valid_kw.update(bearing=True, range=True)
        blocks = [slice(0, 3), slice(6, 9)]
        if rates_ok:
            kw.update(velocity=fv, angular_velocity=fw, range_rate=float(fp @ fv / max(rng_m, 1e-9)))
            valid_kw["range_rate"] = True
            blocks += [slice(3, 6), slice(9, 12)]
        # The registrations' correlated error does not average down. Two covariances, as ARAIM
        # keeps them: the published one adds the typical correlated error (accuracy_*: the state
        # vector's NEES stays near 3), the protection level the worst shapes' allowance (bias_*,
        # along the line of sight at least the time of flight's range bias), on position and,
        # over the scan's lever arm, on attitude as a turn about the port (the origin moves with
        # it; the port's bound does not). bias_* >= accuracy_* (config) and the published line of
        # sight is clipped to the allowance there, so the bound covers the published covariance.
        ig = self.pc.integrity
        r_port = self.r_port
        port = fp + fR @ r_port
        port_rng = float(np.linalg.norm(port))
        los = np.outer(port, port) / max(port_rng, 1e-9) ** 2
        acc = max(ig.accuracy_bias_m, ig.accuracy_bias_rad * port_rng)
        bias = max(ig.bias_m, ig.bias_rad * port_rng)
        rb = out.tof_share * self.tof_bias_m
        # The filter's accuracy covariance carries the time of flight's range bias as the
        # registrations put it into the state, frame by frame (PoseFilter's range_bias_m). On
        # top of it, along the line of sight: ICP's range offset on the shape (never beyond the
        # integrity allowance there), and over the scan's lever arm a differential depth
        # error's tilt, turned about the port.
        share = out.tof_share
        offset = share * ig.accuracy_tof_range_bias_m + (1.0 - share) * ig.accuracy_range_bias_m
        P_f = f.accuracy_covariance()
        if self.accuracy is None:
            P_f = _with_bias(P_f, acc, min(offset, bias), los)
        else:
            # The model's own calibration (on a sensor without the range bias the filter
            # carries), over the generic floor, within the allowance as the static figures are.
            across, along = self.accuracy(port_rng)
            across = min(math.hypot(across, ig.accuracy_bias_m), bias)
            along = min(math.hypot(along, ig.accuracy_bias_m), bias)
            P_f = P_f.copy()
            P_f[0:3, 0:3] += across**2 * (np.eye(3) - los) + along**2 * los
        if out.bias_cov is not None:
            # The sensor model's prediction of the registrations' bias there, the same frame
            # after frame (TrackingMode.predict_bias): carried, not corrected, and within the
            # protection level's allowance as the static figures are.
            B = out.bias_cov
            tr = float(np.trace(B))
            if tr > bias * bias:
                B = B * (bias * bias / tr)
            P_f = P_f.copy()
            P_f[0:3, 0:3] += B
        P_acc = turn_about(P_f, fR, r_port, (ig.accuracy_lever_bias_m / max(out.lever_m, 1e-3)) ** 2)
        P_int = turn_about(_with_bias(fP, bias, rb, los), fR, r_port,
                           (bias / max(out.lever_m, 1e-3)) ** 2)
        for a in blocks:
            for b in blocks:
                cov[a, b] = P_acc[a, b]
        # Integrity: the port's error bound from the filter's full pose covariance (the
        # unobservable directions of the registrations grow there, not in the floors).
        pl = protection_level(port_covariance(P_int, fR, r_port), integrity_factor(ig.risk))
        pl *= math.sqrt(out.consistency)  # registrations that keep disagreeing with the filter
        pl += out.ambiguity_m  # the port may be where a twin the scan allows puts it
        pl += out.rival_m  # or where a registration the filter rejected puts it
        al = alert_limit(port_rng, ig.alert_limit_m, ig.alert_limit_range_m)
        kw.update(protection_level=pl, alert_limit=al)
        # A track is trusted once confirmed by a few accepted frames (its rates estimated; an
        # acquisition's transient is not yet inside the filter's covariance) and, with the turn
        # monitor on, by its turn probes.
        # A registration that leaves many returns unexplained is not a pose to close in on.
        valid_kw["degraded"] = (pl > al or out.n_updates < ig.confirm_frames
                                or out.fitness < ig.min_valid_fitness or not out.turn_confirmed)
