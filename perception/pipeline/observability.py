"""Observability-aware tracking scans: choose the region whose scan pins all six axes at the port.

Seed 000 steers the scan by range (whole structure far out, docking area closer, the port only at
short range, Fig. 9). On a target the strategy was not tuned for, the port region can be a flat
patch: three of six axes unobserved, and an estimate that slides along the face. The
:class:`ScanPlanner` predicts, for candidate regions, the scan the sensor will make (the same
steered pattern and the same rays, cast on the model at the predicted pose), forms the
registration's information ``sum A_i^T A_i / var_i``
(:func:`perception.estimation.registration.information_rows`, the ``J^T J / sigma^2`` behind the Cramer-Rao
bound), and scores each region by the bound it gives
at the docking port: ``sqrt(lambda_max)`` of the port-position covariance plus the attitude bound
times ``attitude_lever_m``. Directions carried by grazing matches that another face explains as
well (edge mixing) or by fewer than ``min_support`` effective points count as unobserved, so a
region must be observable in a way that survives a few centimetres of prediction error.

With ``outline`` the prediction also counts what the pipeline's outline refinement adds where
ICP leaves axes unobserved: consecutive samples of the predicted scan across the target's outline
(:func:`perception.estimation.silhouette.scan_outline_pairs`), so a region that shows a flat face's edges
scores better than one inside the face.

Candidates: the target's own regions (``whole``, ``docking_area``, ``port`` and any others), boxes
centred on the port growing by factors of two up to the whole target, and a "feature" region: the
port plus the model points that carry the most information along the weakest direction of the
range strategy's region, found in the prediction of the whole target. The range strategy's region
is used as long as its registrations observe every axis, and is kept after a prediction unless
another candidate's bound is smaller by ``switch_factor``: the seed's strategies stay the frame,
the prediction overrides them where they leave an axis unobserved.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from perception.config import ScanPlanConfig
from perception.geometry import skew
from perception.pipeline.integrity import port_covariance
from perception.sensing.pointcloud import Subsystem
from perception.estimation.registration import (
    FAILURE_VARIANCE,
    ModelCloud,
    covariance_from_information,
    edge_ambiguous,
    information_rows,
)
from perception.sensing.scan_patterns import angles_to_directions
from perception.sensing.sensors.raycast import cast_rays, face_planes
from perception.targets import RegionOfInterest, TargetModel

FloatArray = npt.NDArray[np.float64]

__all__ = ["Prediction", "ScanPlanner", "predict_information"]


@dataclass
class Prediction:
    """What a scan of a region is predicted to tell about the pose.

    Attributes:
        region: the region predicted.
        information: (6, 6) information of the predicted scan (twist about the target origin,
            sensor axes; the layout of
            :attr:`~perception.estimation.registration.RegistrationResult.covariance`), scaled to the
            frame's sample count.
        covariance: (6, 6) its covariance, unobserved directions at ``FAILURE_VARIANCE``.
        port_bound_m: ``sqrt(lambda_max)`` of the port position covariance [m].
        attitude_bound_rad: ``sqrt(lambda_max)`` of the attitude covariance [rad].
        degenerate_axes: unobserved axes (names of :data:`~perception.estimation.registration.AXIS_NAMES`).
        n_hits: predicted returns (of the predicted rays).
        score: ``port_bound_m + attitude_lever_m * attitude_bound_rad`` [m].
    """

    region: RegionOfInterest
    information: FloatArray
    covariance: FloatArray
    port_bound_m: float
    attitude_bound_rad: float
    degenerate_axes: list[str] = field(default_factory=list)
    n_hits: int = 0
    score: float = math.inf


def _bound(C: FloatArray) -> float:
    return math.sqrt(max(float(np.linalg.eigvalsh(0.5 * (C + C.T))[-1]), 0.0))


def predict_information(
    target: TargetModel,
    sensor: object,
    model: ModelCloud,
    T_sensor_target: npt.ArrayLike,
    region: RegionOfInterest,
    frame_index: int = 0,
    n_rays: int = 300,
    config: ScanPlanConfig | None = None,
    floor_fraction: float = 0.2,
) -> Prediction:
    """Predict the information of a steered scan of ``region`` from the model at a pose.

    Args:
        target: the target model.
        sensor: a :class:`~perception.sensing.sensors.tridar.TriDARSensor` (pattern, noise model).
        model: the prepared model cloud (:func:`~perception.estimation.registration.prepare_model`).
        T_sensor_target: (4, 4) predicted pose.
        region: region of interest to steer onto.
        frame_index: frame index (pattern phase).
        n_rays: rays to predict with; the information is scaled to ``scan.n_points``.
        config: planner settings (ambiguity, support, lever).
        floor_fraction: ICP's residual noise floor (``icp.noise_floor_fraction``).
    """
    cfg = config or ScanPlanConfig()
    T = np.asarray(T_sensor_target, dtype=np.float64)
    R, t = T[:3, :3], T[:3, 3]
    n_frame = int(sensor.config.scan.n_points)  # type: ignore[attr-defined]
    fail = Prediction(
        region,
        np.zeros((6, 6)),
        FAILURE_VARIANCE * np.eye(6),
        math.sqrt(FAILURE_VARIANCE),
        math.sqrt(FAILURE_VARIANCE),
        ["tx", "ty", "tz", "rx", "ry", "rz"],
        0,
        math.inf,
    )
    try:
        pattern = sensor.make_scan_pattern(frame_index, T, region, n_points=n_rays)  # type: ignore[attr-defined]
    except ValueError:
        return fail
    d_s = angles_to_directions(pattern.az, pattern.el)
    face, rng, cos_inc = cast_rays(target, -R.T @ t, d_s @ R)
    hit = face >= 0
    n_hit = int(np.count_nonzero(hit))
    if n_hit < 6:
        return fail
    d_all = d_s
    d_s, rng, f = d_s[hit], rng[hit], face[hit]
    normals_t = face_planes(target)[0][f]
    pts_s = d_s * rng[:, None]
    tri = rng < float(sensor.transition_range_m)  # type: ignore[attr-defined]
    sig = np.where(
        tri,
        sensor.range_sigma(rng, Subsystem.TRIANGULATION),  # type: ignore[attr-defined]
        sensor.range_sigma(rng, Subsystem.TOF),
    )  # type: ignore[attr-defined]
    c = pts_s.mean(axis=0)
    rows = information_rows(pts_s, normals_t @ R.T, sig, d_s, c, floor_fraction)
    if cfg.edge_ambiguity_sigmas > 0:
        foot_t = (pts_s - t) @ R
        amb = edge_ambiguous(
            model, foot_t, normals_t, sig, -cos_inc[hit], cfg.edge_ambiguity_sigmas, d_s @ R
        )
        rows[amb] = 0.0
    scale = n_frame / max(n_rays, 1)
    rows = rows * math.sqrt(scale)
    if cfg.outline:
        rows = np.vstack([rows, _outline_information_rows(target, model, T, d_all, hit, c) * scale])
    H = rows.T @ rows
    dc = (pts_s - c).ravel()
    patch = max(math.sqrt(float(dc @ dc) / n_hit), 0.05)
    # The support threshold counts points of the predicted ray set: scale it to the frame.
    cov_c, degenerate = covariance_from_information(H, patch, 1e-4, rows, cfg.min_support / scale)
    J = np.eye(6)
    J[:3, 3:] = -skew(t - c)  # as in ICP: the bound about the patch centre moved to the origin
    cov = J @ cov_c @ J.T
    cov = 0.5 * (cov + cov.T)
    Jinv = np.linalg.inv(J)
    info = Jinv.T @ H @ Jinv
    P12 = np.zeros((12, 12))
    P12[0:3, 0:3], P12[0:3, 6:9], P12[6:9, 0:3], P12[6:9, 6:9] = (
        cov[:3, :3],
        cov[:3, 3:],
        cov[3:, :3],
        cov[3:, 3:],
    )
    port_b = _bound(port_covariance(P12, R, target.T_target_port[:3, 3]))
    att_b = _bound(cov[3:, 3:])
    return Prediction(
        region, info, cov, port_b, att_b, degenerate, n_hit, port_b + cfg.attitude_lever_m * att_b
    )


def _outline_information_rows(
    target: TargetModel,
    model: ModelCloud,
    T: FloatArray,
    d_all: FloatArray,
    hit: npt.NDArray[np.bool_],
    c: FloatArray,
) -> FloatArray:
    """Rows of the outline information of a predicted scan (what the pipeline's outline
    refinement adds): pairs of consecutive samples across the outline, their silhouette-plane
    normals and quantisation variances, on the in-plane axes (tx, ty, rz) about ``c``."""
    from perception.estimation.silhouette import FlashGeometry, outline_rows, scan_outline_pairs

    a, b = scan_outline_pairs(d_all, hit)
    if a.size == 0:
        return np.zeros((0, 6))
    geom = FlashGeometry(d_all, 1, d_all.shape[0], 0.05, 0.0, math.inf)
    o = outline_rows(target, model, T, d_all[a], d_all[b], geom)
    if o.r.size == 0:
        return np.zeros((0, 6))
    A = np.hstack([o.normal, np.cross(o.s - c, o.normal)])
    A[:, 2:5] = 0.0  # the refinement's outline rows inform the image-plane axes only
    return A / np.sqrt(o.var)[:, None]


class ScanPlanner:
    """Chooses the tracking region by the predicted bound at the port (see the module docstring).

    Args:
        target: the target model.
        sensor: the TriDAR sensor.
        model: the prepared model cloud.
        config: planner settings.
        floor_fraction: ICP's residual noise floor.
    """

    def __init__(
        self,
        target: TargetModel,
        sensor: object,
        model: ModelCloud,
        config: ScanPlanConfig | None = None,
        floor_fraction: float = 0.2,
    ) -> None:
        self.target = target
        self.sensor = sensor
        self.model = model
        self.cfg = config or ScanPlanConfig()
        self.floor = float(floor_fraction)
        self._fixed = self._port_boxes()
        self.reset()

    def reset(self) -> None:
        """Forget the current choice (a new track)."""
        self.region: RegionOfInterest | None = None
        self.prediction: Prediction | None = None
        self._t_plan = -math.inf
        self._default = ""
        self.plans = 0

    def _port_boxes(self) -> list[RegionOfInterest]:
        regs = self.target.regions
        whole = regs["whole"]
        port = regs.get("port") or whole
        out = list(regs.values())
        p = np.asarray(self.target.T_target_port[:3, 3], dtype=np.float64)
        h = float(max(port.half_extents))
        size = float(max(whole.half_extents))
        k = 1
        while h * 2**k < size and k <= 4:
            hk = h * 2**k
            out.append(RegionOfInterest(f"port_x{2**k}", tuple(p), (hk, hk, hk)))
            k += 1
        return out

    def _predict(
        self, T: FloatArray, region: RegionOfInterest, frame_index: int
    ) -> Prediction:
        return predict_information(
            self.target, self.sensor, self.model, T, region, frame_index, self.cfg.rays,
            self.cfg, self.floor,
        )

    def candidates(
        self, T_pred: FloatArray, default: RegionOfInterest, frame_index: int
    ) -> list[RegionOfInterest]:
        """The fixed candidates plus a feature region built for the weak axes at this pose."""
        base = self._predict(T_pred, default, frame_index)
        feat = self._feature_region(T_pred, base.information, frame_index)
        return list(self._fixed) + ([feat] if feat is not None else [])

    def _feature_region(
        self, T_pred: FloatArray, information: FloatArray | None, frame_index: int,
        direction: FloatArray | None = None,
    ) -> RegionOfInterest | None:
        """The port plus the visible model points that best pin the weakest axis of
        ``information`` (the range strategy's region's predicted information), or ``direction``
        (a twist about the target origin, sensor axes) when given."""
        if direction is not None:
            weak = np.asarray(direction, dtype=np.float64)
        else:
            assert information is not None
            _, V = np.linalg.eigh(information + 1e-12 * np.eye(6))
            weak = V[:, 0]
        whole = self.target.regions["whole"]
        R, t = T_pred[:3, :3], T_pred[:3, 3]
        try:
            pattern = self.sensor.make_scan_pattern(
                frame_index, T_pred, whole, n_points=self.cfg.rays
            )  # type: ignore[attr-defined]
        except ValueError:
            return None
        d_s = angles_to_directions(pattern.az, pattern.el)
        face, rng, _ = cast_rays(self.target, -R.T @ t, d_s @ R)
        hit = face >= 0
        if np.count_nonzero(hit) < 6:
            return None
        pts_s = d_s[hit] * rng[hit, None]
        n_s = face_planes(self.target)[0][face[hit]] @ R.T
        rows = information_rows(pts_s, n_s, 1.0, d_s[hit], t, self.floor)
        gain = np.square(rows @ weak)
        top = np.argsort(-gain)[: max(8, int(0.1 * gain.size))]
        pts_t = (pts_s[top] - t) @ R
        p = np.asarray(self.target.T_target_port[:3, 3], dtype=np.float64)
        lo = np.minimum(pts_t.min(axis=0), p) - 0.05
        hi = np.maximum(pts_t.max(axis=0), p) + 0.05
        return RegionOfInterest("features", tuple(0.5 * (lo + hi)), tuple(0.5 * (hi - lo)))

    def due(self, t: float, weak: bool) -> bool:
        """A prediction is due: the current region left axes unobserved (``weak``) and the last
        plan is older than ``period_s``, or a region other than the default is in use and its
        period elapsed (the default may serve again)."""
        if t - self._t_plan < self.cfg.period_s - 1e-9:
            return False
        return weak or (self.region is not None and self.region.name != self._default)

    def choose(
        self,
        T_pred: npt.ArrayLike,
        default_name: str,
        frame_index: int = 0,
        t: float = 0.0,
        weak: bool = False,
        pin: npt.ArrayLike | None = None,
    ) -> tuple[RegionOfInterest, Prediction | None]:
        """The region to scan now.

        The range strategy's region (seed 000 Fig. 9) serves as long as the registrations on it
        observe every axis: predicting costs a few ray casts per candidate, spent only where the
        strategy falls short. When ``weak`` (the last registration left axes unobserved), the
        candidates are predicted (at most every ``period_s``) and the best is kept until the
        next plan.

        Args:
            T_pred: (4, 4) predicted pose of the frame.
            default_name: the range strategy's region.
            frame_index: frame index (pattern phase).
            t: time [s].
            weak: the last registration had unobserved axes.
            pin: a direction the scans must pin (a twist about the target origin, sensor
                axes: a turn the turn monitor holds, :mod:`perception.pipeline.slides`). The
                regions' own bounds do not see it (a cylinder bus's rim facets claim its roll
                locally, whatever the turn), so the feature region built for it is scanned
                outright, at most every ``period_s``.

        Returns:
            The region and its prediction (None when the default serves unpredicted).
        """
        regs = self.target.regions
        default = regs.get(default_name) or regs["whole"]
        if default_name != self._default:
            self.region, self.prediction, self._default = None, None, default_name
            self._t_plan = -math.inf
        if not self.due(t, weak or pin is not None):
            return (self.region, self.prediction) if self.region is not None else (default, None)
        T = np.asarray(T_pred, dtype=np.float64)
        if pin is not None:
            feat = self._feature_region(T, None, frame_index, np.asarray(pin, dtype=np.float64))
            if feat is not None:
                self.region, self.prediction = feat, None
                self._t_plan = float(t)
                self.plans += 1
                return feat, None
        # The fixed candidates include the default region: its prediction also seeds the
        # feature region (predicted once, not again for it).
        preds = [self._predict(T, r, frame_index) for r in self._fixed]
        base = next(p for p in preds if p.region is default)
        feat = self._feature_region(T, base.information, frame_index)
        if feat is not None:
            preds.append(self._predict(T, feat, frame_index))
        best = min(preds, key=lambda p: p.score)
        choice = best if best.score * self.cfg.switch_factor < base.score else base
        self.region, self.prediction = choice.region, choice
        self._t_plan = float(t)
        self.plans += 1
        return choice.region, choice
