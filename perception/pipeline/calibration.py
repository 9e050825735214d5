"""Calibration of the registrations' correlated error on the target's own model (pre-flight).

The registrations' correlated error, the part that is the same frame after frame at one aspect and
that a filter therefore cannot average away, depends on the shape: at 10-20 m the time of
flight's first echo over a footprint on slopes and edges put the ISS-like port +12 mm off along
the line of sight in closed loop, a cubesat +7 mm, hubble -9 mm. A TriDAR team characterises its
sensor on the target's model before flight; :func:`calibrate_accuracy` does the same with the
simulated sensor, and ``tridar-env check-target`` sets it beside the protection level's
allowance (``integrity.bias_m``, ``bias_rad``): a shape whose registrations are further off than
that, every frame, is one the bound may not cover.

At sensor-to-port ranges along the approach, at ``poses`` aspects each (the port dispersed across
the line of sight by 5 % of the range, at most 0.5 m, and the attitude by 1 deg), the tracking
scan the pipeline would plan there is taken ``repeats`` times with independent sensor noise and
registered as a settled track registers (fine ICP from a start a registration's noise off, the
outline refinement), after one scan that only stands for the track's previous frame (a
registration that leaves axes unobserved moves the next scan where the scan planner looks). The
mean error of the repeats at one aspect is its correlated error plus the white noise over the
repeats, which their scatter removes; over the aspects of one range it gives three 1-sigma
figures: along and across the line of sight at the port and the attitude. A component a
registration leaves unobserved (a flat port face's in-plane position) is left out of that aspect
(the filter's covariance carries it, along the directions it reports).

What it is not: the published covariance's correlated-error term. Measured on the six generated
kinds (shape seed 9090, 12 closed-loop runs, the same runs with and without it), publishing these
figures in place of the static ``integrity.accuracy_*`` ones made the position NEES 5.1 (3.6-7.0
per shape; 1.6 with the static figures) and the attitude NEES 1.0 (1.6): the closed loop's
correlated error held more than a static aspect's registration bias. Much of that was the
filter's lag behind the tide (:mod:`perception.pipeline.filter`, now modelled). Since then, on
ten shapes' tuning runs (the library's four, six generated kinds; the same frames re-scored),
a table of 48 aspects by 4 scans across and along the line of sight, over a 0.5 mm floor, gave
position NEES 1.5-4.2 per shape against 1.3-6.8 with the refitted static figures: closer to
honest per shape, not inside every band, and 12-25 s a target; still a diagnostic.

Each scan of an aspect is the track's next frame, its pattern's phase a step on: scanned at one
phase, where that phase's samples fell on the shape was the same for every repeat and counted as
correlated, though a track's next frame samples elsewhere. Across the line of sight, where the
shapes differ most, the published 2-dof NEES on ten shapes' tuning runs (reset seeds 960-962; the
library's four, six generated kinds of shape seed 9494) was 0.3-1.8 with one phase, 0.7-3.0 with
the phase stepping on (hubble 3.7; static figures 0.95-13.8); the position NEES per shape 1.0-3.0,
hubble 6.8 (static figures 1.3-14.4). What is left is mostly the filter's own accuracy
covariance, conservative on most shapes: along the line of sight the time of flight's range
offset, a consider parameter of the sensor's configured size, is the largest part of it.

The calibration draws from its own generator (the caller's; ``check-target`` seeds it with
:data:`CALIBRATION_SEED`): the same model, sensor and settings give the same table.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt

from perception.estimation.registration import icp
from perception.geometry import fast_matrix_to_rotvec, fast_rotvec_to_matrix, los_basis, skew

if TYPE_CHECKING:
    from perception.pipeline.tridar import TriDAR

FloatArray = npt.NDArray[np.float64]

__all__ = ["CALIBRATION_SEED", "AccuracyTable", "approach_ranges", "calibrate_accuracy",
           "calibration_ranges"]

#: Seed of the calibration's own generator (the calibration is the model's, not an episode's).
CALIBRATION_SEED = 20261205
#: Aspects a calibrated range, scans an aspect, calibrated ranges (geometric from
#: MIN_RANGE_M to 1.25 times the approach's farthest start): what ``TriDAR.accuracy_table`` takes.
#: With 12 aspects by 3 scans the figures of one range scattered by a factor 2 between seeds.
POSES, REPEATS, RANGES, MIN_RANGE_M = 48, 4, 8, 1.5
#: Lateral dispersion of the port across the line of sight: this fraction of the range [-].
LATERAL_FRACTION = 0.05
#: ... and at most this [m].
LATERAL_MAX_M = 0.5
#: Attitude dispersion of the aspects, 1-sigma per axis [deg].
ATTITUDE_DISPERSION_DEG = 1.0
#: A settled track's ICP starts this far from the answer (1-sigma per axis): the filter's
#: prediction, a registration's noise off [m] (or this fraction of the range, if more) and [deg].
START_OFFSET_M = 0.003
START_OFFSET_FRACTION = 0.0003
START_OFFSET_DEG = 0.1
#: A direction of a registration's covariance beyond this [m^2 or rad^2] is one it leaves
#: unobserved (they carry FAILURE_VARIANCE, 1e6).
UNOBSERVED_VARIANCE = 1.0e2


@dataclass(frozen=True)
class AccuracyTable:
    """The target's correlated registration error by sensor-to-port range.

    Attributes:
        range_m: (K,) increasing sensor-to-port ranges [m].
        across_m: (K,) 1-sigma per axis across the line of sight at the port [m].
        along_m: (K,) 1-sigma along the line of sight at the port [m] (on a sensor without
            the time of flight's configured range bias, which the filter's accuracy covariance
            carries: ``TriDAR.accuracy_table``).
        attitude_rad: (K,) 1-sigma per axis of the attitude, turned about the port [rad].
            Each NaN at a range where no aspect's registrations observed it.
        samples: (K, 3) aspects that observed the line of sight, an axis across it (the more
            observed one) and an attitude axis, at each range.
    """

    range_m: FloatArray
    across_m: FloatArray
    along_m: FloatArray
    attitude_rad: FloatArray
    samples: npt.NDArray[np.int64]

    def at(self, range_m: float) -> tuple[float, float, float]:
        """(across [m], along [m], attitude [rad]) at ``range_m``: each linear in range between
        the ranges where it was observed, the nearest one's beyond them (0 where never)."""
        r = float(range_m)

        def one(v: FloatArray) -> float:
            ok = np.isfinite(v)
            return float(np.interp(r, self.range_m[ok], v[ok])) if ok.any() else 0.0

        return one(self.across_m), one(self.along_m), one(self.attitude_rad)


def calibration_ranges(min_range_m: float, max_range_m: float, n: int) -> FloatArray:
    """``n`` sensor-to-port ranges [m], geometric from ``min_range_m`` to ``max_range_m``."""
    if not (0.0 < min_range_m < max_range_m) or n < 2:
        raise ValueError(f"calibration ranges {min_range_m}..{max_range_m} m in {n} steps; expected "
                         "0 < min < max and at least 2 steps")
    return np.geomspace(min_range_m, max_range_m, int(n))


def _turn(rng: np.random.Generator, sigma_rad: float) -> FloatArray:
    return fast_rotvec_to_matrix(rng.normal(0.0, sigma_rad, 3))


def _observed(cov: FloatArray, a: FloatArray, B: FloatArray) -> npt.NDArray[np.bool_]:
    """Which of the six components (the port's position along the rows of ``B``, the attitude
    about the sensor axes) a registration of covariance ``cov`` (origin twist) observes, ``a``
    (3,) being the port's offset from the target origin in the sensor frame: none of the
    directions it leaves unobserved (variance beyond :data:`UNOBSERVED_VARIANCE`) leans on it."""
    J = np.eye(6)
    J[:3, 3:] = -skew(a)  # origin -> port
    Cp = J @ (0.5 * (cov + cov.T)) @ J.T
    out = np.ones(6, dtype=bool)
    for blk, axes in ((slice(0, 3), B), (slice(3, 6), np.eye(3))):
        lam, V = np.linalg.eigh(Cp[blk, blk])
        U = V[:, lam > UNOBSERVED_VARIANCE]
        out[blk] = np.all(np.abs(axes @ U) < 0.3, axis=1) if U.size else True
    return out


def calibrate_accuracy(tri: TriDAR, ranges_m: FloatArray, poses: int, repeats: int,
                       rng: np.random.Generator) -> AccuracyTable:
    """The correlated error of ``tri``'s tracking registrations on its target (module doc).

    Args:
        tri: a pipeline built for the mission and target (its sensor, model, scan strategy and
            ICP settings are used; its state is not: the caller passes one of its own).
        ranges_m: (K,) sensor-to-port ranges [m].
        poses: aspects per range.
        repeats: scans per aspect (>= 2: their scatter separates the white noise).
        rng: the calibration's generator.

    Returns:
        The table (a figure no aspect of a range observed is NaN there: :meth:`AccuracyTable.at`
        takes it from the ranges that did).
    """
    if poses < 1 or repeats < 2:
        raise ValueError(f"calibration poses={poses}, repeats={repeats}; expected >= 1 and >= 2")
    target = tri.target
    r_port = target.T_target_port[:3, 3]
    R0 = tri.R_nominal  # the docking frame facing the port (perception.pipeline.approach_pose)
    rows = []
    for r in np.asarray(ranges_m, dtype=np.float64):
        lat = min(LATERAL_FRACTION * r, LATERAL_MAX_M)
        # Per component (along, two across, three attitude axes): sums of the aspects' squared
        # correlated errors and how many aspects observed it.
        tot, cnt = np.zeros(6), np.zeros(6, dtype=np.int64)
        for _ in range(poses):
            R = _turn(rng, math.radians(ATTITUDE_DISPERSION_DEG)) @ R0
            port = np.array([*rng.normal(0.0, lat, 2), r])
            T = np.eye(4)
            T[:3, :3] = R
            T[:3, 3] = port - R @ r_port
            B = los_basis(port)
            comps, seen = [], np.ones(6, dtype=bool)
            tri.last_result = None
            for k in range(repeats + 1):  # the first one only sets the planner's last registration
                T0 = T.copy()
                T0[:3, :3] = _turn(rng, math.radians(START_OFFSET_DEG)) @ R
                T0[:3, 3] += rng.normal(0.0, max(START_OFFSET_M, START_OFFSET_FRACTION * r), 3)
                # Each scan is the track's next frame: the pattern's phase steps on (the sensor's
                # scan.phase_step), so the error of where one phase's samples fall on the shape
                # is noise over the repeats, as it is over a track's frames.
                tri.frame_index += 1
                pattern, _ = tri.tracking.pattern(T0)
                cloud = tri.sensor.scan(target, T, pattern, rng)
                if len(cloud) < 12:
                    break
                tri.tracking.frame_pattern = (pattern, 0.0)
                res = icp(cloud.points, tri.model, T0, sigma=cloud.sigma, directions=cloud.directions,
                          config=tri.logic.icp_config_for(cloud.subsystem), coarse=False)
                res = tri.tracking.outline_refine(res, cloud.points, cloud)
                tri.last_result = res  # a weak one moves the next scan, as on a track
                if k == 0:
                    continue
                if not res.converged:
                    break
                Te = res.T_sensor_target
                e = Te[:3, :3] @ r_port + Te[:3, 3] - port
                th = fast_matrix_to_rotvec(Te[:3, :3] @ R.T)
                comps.append(np.concatenate([B @ e, th]))
                seen &= _observed(res.covariance, Te[:3, :3] @ r_port, B)
            if len(comps) < repeats or not seen.any():
                continue
            C = np.asarray(comps)
            # The mean of the repeats carries the white noise over the repeats; their scatter
            # (unbiased) estimates it.
            c2 = C.mean(axis=0) ** 2 - C.var(axis=0, ddof=1) / repeats
            tot += np.where(seen, c2, 0.0)
            cnt += seen
        rows.append((r, tot, cnt))
    def sig(tot: FloatArray, cnt: npt.NDArray[np.int64]) -> float:
        n = int(cnt.sum())
        return math.sqrt(max(float(tot.sum()) / n, 0.0)) if n else math.nan

    return AccuracyTable(
        range_m=np.array([r for r, _, _ in rows]),
        along_m=np.array([sig(t[:1], c[:1]) for _, t, c in rows]),
        across_m=np.array([sig(t[1:3], c[1:3]) for _, t, c in rows]),
        attitude_rad=np.array([sig(t[3:], c[3:]) for _, t, c in rows]),
        samples=np.array([[c[0], c[1:3].max(), c[3:].max()] for _, _, c in rows], dtype=np.int64),
    )



def approach_ranges(cfg: Any) -> FloatArray:
    """The ranges a target is calibrated at for ``cfg``'s mission: :data:`RANGES` of them,
    geometric from :data:`MIN_RANGE_M` to 1.25 times the approach's farthest start."""
    ini = cfg.env.initial
    far = 1.25 * (ini.range_m + 2.0 * ini.range_dispersion_m)
    return calibration_ranges(MIN_RANGE_M, max(far, 2.0 * MIN_RANGE_M), RANGES)
