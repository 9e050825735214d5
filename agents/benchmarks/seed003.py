"""Seed 003 experiments 1 and 2: the line-roll tracker against plain ICP and our point-to-plane ICP.

Long module: its tracker classes (~240 lines) wait for issue 20, which moves them into
perception; a sibling file would be listed by ``tridar-env bench`` as a benchmark of its own.

Zhao, Xu and Bo (Sensors 2018) section 3: a CYGNSS-like target (3.55 x 1.10 x 0.47 m) seen by a
500 x 500 pixel, 20 x 20 deg flash LiDAR with a uniform +-10 mm range error, 51 frames from 60 m to
10 m (1 m per frame) while the target rolls from 125 to -125 deg (5 deg per frame). Experiment 2
adds a pitch from 10 to 0 deg and a lateral offset y from 10 to 0 m (0.2 per frame). Poses are
written in the seed's frames (X toward the target, Y right, Z down; roll about X) and converted
with :func:`perception.estimation.linetrack.T_from_seed_pose`; errors are reported back in those frames.

Trackers, each initialised on frame 1 from truth plus a small random error (the seed uses its own
global method there) and then run frame to frame from its previous estimate:

- ``ICP``: point-to-point ICP on the full cloud (the seed's baseline), seed ICP settings;
- ``Proposed``: :class:`perception.estimation.linetrack.LineRollTracker` (line roll prior, adaptive voxel
  grid, point-to-point ICP);
- ``P2Plane``: our default ICP (point-to-plane, :class:`~perception.config.ICPConfig` defaults) on
  a uniform random subset of the flash cloud (``--plane-points``, TriDAR-like sparse sensing);
- ``Lines+P2Plane`` (extra row): the seed tracker's roll prior and voxel grid with our
  point-to-plane ICP (its gate widened to 2 m) in place of point-to-point;
- ``P2Plane+CV+rays`` (extra row): our ICP as the tumbling-target mission runs it on this target —
  each point matched to the face its measured ray crosses (``match_along_rays``) — from a
  constant-velocity prediction (the last frame-to-frame motion repeated, what the pipeline's
  filter supplies) on the same uniform subset as ``P2Plane``;
- ``P2Plane+CV+outline`` (extra row): ``P2Plane+CV+rays``, then
  :func:`perception.estimation.silhouette.refine_pose`: one Gauss-Newton on the surface rows of the same
  subset and on the flash frame's *outline* (every valid pixel next to an invalid one: the model's
  outline, found by casting rays along the pair, must cross between them). The CYGNSS bus and
  wings are plates seen nearly face-on, so point-to-plane ICP has next to no information about
  the in-plane position and the roll (its Cramer-Rao bound flags ``tx, ty, rz`` degenerate on most
  frames; they were the 5-8 mm and 0.24 deg spikes of ``P2Plane+CV+rays``); the outline fixes
  them, to the pixel quantisation of the edges (``--outline-points``, ``--outline-pairs``);
- ``P2Plane+EKF+outline`` (extra row): the same refinement (from the prediction, no ICP first)
  inside the pipeline's :class:`perception.pipeline.filter.PoseFilter` (the pipeline's default process
  noise), which
  fuses each frame's pose with the refinement's covariance. That covariance counts an edge
  running with the pixel grid (roll 0, +-45, +-90 deg: all edges of a box) once, not once per
  pixel, so on those frames (one flash frame places each such edge only to a pixel: 37 mm at
  53 m) the filter leans on its prediction.

Seed 003's figures: < 0.5 deg and ~1 cm, ~200 ms per frame on ~5,000 points.
Our goals: max rotation error <= 0.2 deg, max position error <= 5 mm, <= 50 ms per frame.
Plots mirroring the seed's Figs. 7-12 go to ``--out`` (default ``reports/seed003``).
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]

GOAL_ROT_DEG = 0.2
GOAL_POS_M = 0.005
GOAL_TIME_S = 0.050
METHODS = ("ICP", "Proposed", "P2Plane", "Lines+P2Plane", "P2Plane+CV+rays", "P2Plane+CV+outline",
           "P2Plane+EKF+outline")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", type=Path, default=Path("reports/seed003"),
                        help="folder for the table, per-frame CSV, config and PNG plots")
    parser.add_argument("--experiments", type=int, nargs="+", choices=(1, 2), default=[1, 2])
    parser.add_argument("--methods", nargs="+", choices=METHODS, default=list(METHODS))
    parser.add_argument("--frames", type=int, default=51, help="frames per experiment (seed: 51)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--init-error-deg", type=float, default=0.5,
                        help="attitude error of the frame-1 initial pose [deg]")
    parser.add_argument("--init-error-m", type=float, default=0.02,
                        help="position error of the frame-1 initial pose [m]")
    parser.add_argument("--d-model", type=float, default=0.03, help="d_m of eq. (16) [m]")
    parser.add_argument("--q-lines", type=int, default=10, help="Q, longest lines matched")
    parser.add_argument("--plane-points", type=int, default=2000,
                        help="points per frame for the point-to-plane tracker")
    parser.add_argument("--outline-points", type=int, default=2000,
                        help="points per frame for the surface rows of the outline tracker")
    parser.add_argument("--outline-pairs", type=int, default=1500,
                        help="outline pixel pairs per frame for the outline tracker")
    parser.add_argument("--no-plots", action="store_true")


# ---------------------------------------------------------------------------------------------
# Scenario
# ---------------------------------------------------------------------------------------------
def seed_trajectory(experiment: int, frames: int = 51) -> tuple[FloatArray, FloatArray]:
    """Truth of seed 003 section 3.2 (experiment 1) or 3.3 (experiment 2), in the seed's frames.

    Returns:
        positions (frames, 3) [m] (x toward the target, y right, z down) and roll/pitch/yaw
        (frames, 3) [rad].
    """
    if experiment not in (1, 2):
        raise ValueError(f"experiment={experiment}; expected 1 or 2")
    if frames < 2:
        raise ValueError(f"frames={frames}; expected >= 2")
    k = np.arange(frames, dtype=np.float64)
    pos = np.zeros((frames, 3))
    rpy = np.zeros((frames, 3))
    pos[:, 0] = 60.0 - 1.0 * k
    rpy[:, 0] = np.radians(125.0 - 5.0 * k)
    if experiment == 2:
        pos[:, 1] = 10.0 - 0.2 * k
        rpy[:, 1] = np.radians(10.0 - 0.2 * k)
    return pos, rpy


def seed_errors(T_est: FloatArray, T_true: FloatArray) -> tuple[FloatArray, FloatArray, float]:
    """Errors as the seed reports them: estimate minus truth in its frames.

    Returns:
        position error (3,) [m] along seed x, y, z; roll/pitch/yaw error (3,) [deg] (wrapped
        Euler differences); and the total rotation angle between the two attitudes [deg].
    """
    from perception.estimation.linetrack import seed_pose_from_T
    from perception.geometry import pose_error

    p_e, a_e = seed_pose_from_T(T_est)
    p_t, a_t = seed_pose_from_T(T_true)
    d_ang = (a_e - a_t + np.pi) % (2.0 * np.pi) - np.pi
    _, rot_deg = pose_error(T_est, T_true)
    return p_e - p_t, np.degrees(d_ang), float(rot_deg)


def perturb(T: FloatArray, rng: np.random.Generator, rot_deg: float, pos_m: float) -> FloatArray:
    """``T`` turned by ``rot_deg`` about a random axis through the target origin and moved by
    ``pos_m`` in a random direction."""
    from scipy.spatial.transform import Rotation

    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    shift = rng.normal(size=3)
    shift /= np.linalg.norm(shift)
    out = T.copy()
    out[:3, :3] = Rotation.from_rotvec(math.radians(rot_deg) * axis).as_matrix() @ T[:3, :3]
    out[:3, 3] = T[:3, 3] + pos_m * shift
    return out


# ---------------------------------------------------------------------------------------------
# Trackers
# ---------------------------------------------------------------------------------------------
@dataclass
class Step:
    """One tracked frame: the pose, the points the estimator used, the grid size, the time."""

    T: FloatArray
    n_used: int
    voxel_m: float
    time_s: float
    converged: bool


class Tracker(Protocol):
    def init(self, cloud: Any, T: FloatArray) -> Step: ...
    def update(self, cloud: Any) -> Step: ...


class PlainICP:
    """The seed's baseline: point-to-point ICP on the whole cloud from the previous estimate."""

    def __init__(self, model: Any, sigma: float, config: Any) -> None:
        self.model, self.sigma, self.config = model, sigma, config
        self.T: FloatArray | None = None
        self.directions: FloatArray | None = None  # measured rays of the points being run

    def _run(self, points: FloatArray, T0: FloatArray) -> Step:
        from perception.estimation.registration import icp

        t0 = time.perf_counter()
        res = icp(points, self.model, T0, sigma=self.sigma, config=self.config,
                  directions=self.directions)
        dt = time.perf_counter() - t0
        self.T = res.T_sensor_target
        return Step(res.T_sensor_target, res.n_points, float("nan"), dt, res.converged)

    def init(self, cloud: Any, T: FloatArray) -> Step:
        return self._run(cloud.points, T)

    def update(self, cloud: Any) -> Step:
        assert self.T is not None
        return self._run(cloud.points, self.T)


class SparsePlaneICP(PlainICP):
    """Our default tracker: point-to-plane ICP on a fixed-size uniform random subset, from the
    previous pose moved by the shift of the cloud's centroid (the flash frames close in by 1 m per
    frame, twice the default gate; the pipeline's filter would predict that motion)."""

    def __init__(self, model: Any, sigma: float, config: Any, n_points: int,
                 rng: np.random.Generator) -> None:
        super().__init__(model, sigma, config)
        self.n_points, self.rng = int(n_points), rng
        self.centroid: FloatArray | None = None

    def _indices(self, cloud: Any) -> npt.NDArray[np.intp] | None:
        """The random subset's indices, or None when the cloud is no larger than it."""
        n = len(cloud)
        return None if n <= self.n_points else self.rng.choice(n, self.n_points, replace=False)

    def _subset(self, cloud: Any) -> FloatArray:
        idx = self._indices(cloud)
        return cloud.points if idx is None else cloud.points[idx]

    def init(self, cloud: Any, T: FloatArray) -> Step:
        t0 = time.perf_counter()
        self.centroid = cloud.points.mean(axis=0)
        step = self._run(self._subset(cloud), T)
        step.time_s = time.perf_counter() - t0
        return step

    def update(self, cloud: Any) -> Step:
        assert self.T is not None and self.centroid is not None
        t0 = time.perf_counter()
        centroid = cloud.points.mean(axis=0)
        T0 = self.T.copy()
        T0[:3, 3] += centroid - self.centroid
        self.centroid = centroid
        step = self._run(self._subset(cloud), T0)
        step.time_s = time.perf_counter() - t0
        return step


class PredictedRayPlaneICP(SparsePlaneICP):
    """Point-to-plane ICP matched along the measured rays, from a constant-velocity prediction.

    The first update has no velocity yet and uses the centroid shift like :class:`SparsePlaneICP`;
    later ones repeat the last frame-to-frame motion in the target's frame,
    ``T_k = T_{k-1} (T_{k-2}^-1 T_{k-1})`` (a constant roll rate and closing speed are predicted
    exactly; the pipeline's filter does the same from its rate estimates).
    """

    def __init__(self, model: Any, sigma: float, config: Any, n_points: int,
                 rng: np.random.Generator) -> None:
        super().__init__(model, sigma, config, n_points, rng)
        self.prev: FloatArray | None = None

    def _subset(self, cloud: Any) -> FloatArray:
        idx = self._indices(cloud)
        self.directions = cloud.directions if idx is None else cloud.directions[idx]
        return cloud.points if idx is None else cloud.points[idx]

    def update(self, cloud: Any) -> Step:
        assert self.T is not None
        if self.prev is None:
            self.prev = self.T.copy()
            return super().update(cloud)
        t0 = time.perf_counter()
        T_pred = self.T @ np.linalg.solve(self.prev, self.T)
        self.prev = self.T.copy()
        step = self._run(self._subset(cloud), T_pred)
        step.time_s = time.perf_counter() - t0
        return step


class OutlineRayPlaneICP(PredictedRayPlaneICP):
    """:class:`PredictedRayPlaneICP`, then a joint refinement with the frame's outline.

    ICP's pose is refined by :func:`perception.estimation.silhouette.refine_pose`: surface rows on the same
    subset (each point on the face its ray crosses) and outline rows from the flash frame's
    valid/invalid pixel pairs, which fix the in-plane position and the roll that the plates of a
    face-on target leave unconstrained in point-to-plane ICP.
    """

    def __init__(self, target: Any, model: Any, sigma: float, config: Any, n_points: int,
                 rng: np.random.Generator, geometry: Any, max_pairs: int) -> None:
        super().__init__(model, sigma, config, n_points, rng)
        self.target, self.geometry, self.max_pairs = target, geometry, int(max_pairs)
        self._cloud: Any = None
        self._idx: npt.NDArray[np.intp] | None = None
        self.skip_icp = False  # refine straight from the prediction (FilteredOutlineICP)

    def _subset(self, cloud: Any) -> FloatArray:
        idx = self._indices(cloud)
        self._cloud = cloud
        self._idx = np.arange(len(cloud)) if idx is None else idx
        self.directions = cloud.directions[self._idx]
        return cloud.points[self._idx]

    def _run(self, points: FloatArray, T0: FloatArray) -> Step:
        from perception.estimation.registration import icp
        from perception.estimation.silhouette import refine_pose

        t0 = time.perf_counter()
        converged = True
        if not self.skip_icp:
            res = icp(points, self.model, T0, sigma=self.sigma, config=self.config,
                      directions=self.directions)
            T0, converged = res.T_sensor_target, res.converged
        ref = refine_pose(self._cloud, self.target, self.model, T0, self.geometry,
                          sigma=self.sigma, surface_idx=self._idx, max_pairs=self.max_pairs)
        dt = time.perf_counter() - t0
        self.T = ref.T_sensor_target
        self.result = ref
        return Step(ref.T_sensor_target, ref.n_points, float("nan"), dt,
                    converged and ref.converged)


class FilteredOutlineICP(OutlineRayPlaneICP):
    """:class:`OutlineRayPlaneICP` inside the pipeline's pose filter.

    A single frame cannot place an edge that runs with the pixel grid better than its pixel
    pitch (every pair along it has the same sub-pixel phase; at 53 m that is +-19 mm per edge,
    and a box-shaped target at roll 0, +-45 or +-90 deg has only such edges).
    :class:`perception.pipeline.filter.PoseFilter` (constant velocity and rate, the pipeline's default
    process noise from :class:`~perception.config.PipelineConfig`) fuses each frame's refined
    pose with the refinement's covariance, which counts such a group of parallel edges once; the
    filter's posterior is the estimate and its prediction starts the next frame (no ICP: the
    refinement's surface rows take it from there). The filter starts on frame 2 from the two
    first poses (their difference as velocity and rate); frame 2 is predicted like
    :class:`SparsePlaneICP`. The result leans on that prediction at the grid-aligned frames:
    experiment 2's max position error is 1.8 mm with a tenth of the pipeline's acceleration
    noise density, 4.6 mm with it and 8 mm with four times it (single frames: ~12 mm).
    """

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        from perception.config import PipelineConfig
        from perception.pipeline.filter import PoseFilter

        super().__init__(*args, **kwargs)
        pc = PipelineConfig()
        self.filter = PoseFilter(pc.process_noise_accel**2, pc.process_noise_angacc**2)
        self.t_prev = 0.0
        self.rejected = 0

    def init(self, cloud: Any, T: FloatArray) -> Step:
        self.t_prev = float(cloud.t_start)
        return super().init(cloud, T)

    def update(self, cloud: Any) -> Step:
        from scipy.spatial.transform import Rotation

        assert self.T is not None
        t = float(cloud.t_start)
        if not self.filter.initialized:
            T_prev = self.T.copy()
            step = SparsePlaneICP.update(self, cloud)
            dt = max(t - self.t_prev, 1e-9)
            t0 = time.perf_counter()
            omega = Rotation.from_matrix(step.T[:3, :3] @ T_prev[:3, :3].T).as_rotvec() / dt
            self.filter.initialize(t, step.T, self.result.covariance,
                                   velocity=(step.T[:3, 3] - T_prev[:3, 3]) / dt, omega=omega)
            step.time_s += time.perf_counter() - t0
            self.t_prev = t
            return step
        t0 = time.perf_counter()
        self.skip_icp = True
        step = self._run(self._subset(cloud), self.filter.pose_at(t))
        if not self.filter.update(t, step.T, self.result.covariance).accepted:
            self.rejected += 1
        self.T = self.filter.T_sensor_target
        self.t_prev = t
        step.T = self.T
        step.time_s = time.perf_counter() - t0
        return step


class Proposed:
    """Adapter of :class:`perception.estimation.linetrack.LineRollTracker` to :class:`Step`."""

    def __init__(self, tracker: Any) -> None:
        self.tracker = tracker

    def _step(self, res: Any) -> Step:
        info = self.tracker.last
        return Step(res.T_sensor_target, info.n_points_used, info.voxel_size_m, res.time_s,
                    res.converged)

    def init(self, cloud: Any, T: FloatArray) -> Step:
        return self._step(self.tracker.init(cloud, T))

    def update(self, cloud: Any) -> Step:
        return self._step(self.tracker.update(cloud))


# ---------------------------------------------------------------------------------------------
# Runs
# ---------------------------------------------------------------------------------------------
@dataclass
class Run:
    """Per-frame record of one method on one experiment."""

    method: str
    experiment: int
    distance: FloatArray
    pos_err: list[FloatArray] = field(default_factory=list)
    ang_err: list[FloatArray] = field(default_factory=list)
    rot_err: list[float] = field(default_factory=list)
    time_s: list[float] = field(default_factory=list)
    n_raw: list[int] = field(default_factory=list)
    n_used: list[int] = field(default_factory=list)
    voxel_m: list[float] = field(default_factory=list)
    converged: list[bool] = field(default_factory=list)

    def add(self, step: Step, T_true: FloatArray, n_raw: int) -> None:
        pe, ae, re = seed_errors(step.T, T_true)
        self.pos_err.append(pe)
        self.ang_err.append(ae)
        self.rot_err.append(re)
        self.time_s.append(step.time_s)
        self.n_raw.append(n_raw)
        self.n_used.append(step.n_used)
        self.voxel_m.append(step.voxel_m)
        self.converged.append(step.converged)

    def arrays(self) -> tuple[FloatArray, FloatArray]:
        return np.asarray(self.pos_err), np.asarray(self.ang_err)


def _make_trackers(names: list[str], target: Any, flash_cfg: Any, args: argparse.Namespace,
                   experiment: int) -> dict[str, Tracker]:
    """The trackers of ``names``, each drawing its point subsets from its own generator, seeded by
    ``(seed, experiment, method)``: a row's numbers do not depend on which other rows run."""
    from perception.config import ICPConfig
    from perception.estimation.linetrack import LineRollTracker, seed003_icp_config
    from perception.estimation.registration import prepare_model

    sigma = flash_cfg.range_error_m / math.sqrt(3.0)
    out: dict[str, Tracker] = {}
    for name in names:
        rng = np.random.default_rng([args.seed, experiment, METHODS.index(name)])
        if name == "ICP":
            cfg = seed003_icp_config(sigma)
            out[name] = PlainICP(prepare_model(target, cfg.model_points), sigma, cfg)
        elif name == "Proposed":
            out[name] = Proposed(LineRollTracker(target, q_lines=args.q_lines,
                                                 d_model=args.d_model, flash=flash_cfg))
        elif name == "Lines+P2Plane":
            out[name] = Proposed(LineRollTracker(
                target, q_lines=args.q_lines, d_model=args.d_model, flash=flash_cfg,
                icp_config=ICPConfig(max_correspondence_m=2.0)))
        elif name in ("P2Plane+CV+outline", "P2Plane+EKF+outline"):
            from perception.estimation.silhouette import FlashGeometry

            cfg = ICPConfig(match_along_rays=True)
            cls = OutlineRayPlaneICP if name == "P2Plane+CV+outline" else FilteredOutlineICP
            out[name] = cls(
                target, prepare_model(target, cfg.model_points), sigma, cfg, args.outline_points,
                rng, FlashGeometry.from_config(flash_cfg), args.outline_pairs)
        elif name == "P2Plane+CV+rays":
            cfg = ICPConfig(match_along_rays=True)
            out[name] = PredictedRayPlaneICP(prepare_model(target, cfg.model_points), sigma, cfg,
                                             args.plane_points, rng)
        else:
            cfg = ICPConfig()
            out[name] = SparsePlaneICP(prepare_model(target, cfg.model_points), sigma, cfg,
                                       args.plane_points, rng)
    return out


def run_experiment(experiment: int, args: argparse.Namespace) -> dict[str, Run]:
    """Simulate one experiment's frames and track them with every requested method."""
    from perception.config import FlashLidarConfig
    from perception.estimation.linetrack import T_from_seed_pose
    from perception.sensing.sensors import FlashLidar
    from perception.targets import load_target

    target = load_target("cygnss")
    flash_cfg = FlashLidarConfig()
    lidar = FlashLidar(flash_cfg)
    rng = np.random.default_rng([args.seed, experiment])
    pos, rpy = seed_trajectory(experiment, args.frames)
    truth = [T_from_seed_pose(p, a) for p, a in zip(pos, rpy)]
    clouds = [lidar.capture(target, T, rng, t=0.2 * k) for k, T in enumerate(truth)]
    T_init = perturb(truth[0], rng, args.init_error_deg, args.init_error_m)
    trackers = _make_trackers(args.methods, target, flash_cfg, args, experiment)
    runs: dict[str, Run] = {}
    for name, tracker in trackers.items():
        run = Run(name, experiment, pos[:, 0].copy())
        run.add(tracker.init(clouds[0], T_init), truth[0], len(clouds[0]))
        for cloud, T_true in zip(clouds[1:], truth[1:]):
            run.add(tracker.update(cloud), T_true, len(cloud))
        runs[name] = run
    return runs


# ---------------------------------------------------------------------------------------------
# Report
# ---------------------------------------------------------------------------------------------
def error_rows(runs: dict[str, Run]) -> list[dict[str, Any]]:
    """Max and RMS of each seed axis error per method (the seed's Figs. 7/8, 10/11 in numbers)."""
    rows = []
    for name, r in runs.items():
        pe, ae = r.arrays()
        for stat, fn in (("max", lambda a: np.max(np.abs(a), axis=0)),
                         ("rms", lambda a: np.sqrt(np.mean(a * a, axis=0)))):
            a, p = fn(ae), fn(pe) * 1e3
            rows.append({
                "exp": r.experiment, "method": name, "stat": stat,
                "roll_deg": float(a[0]), "pitch_deg": float(a[1]), "yaw_deg": float(a[2]),
                "x_mm": float(p[0]), "y_mm": float(p[1]), "z_mm": float(p[2]),
            })
    return rows


def summary_rows(runs: dict[str, Run]) -> list[dict[str, Any]]:
    """Totals against our goals, time per frame and points used."""
    rows = []
    for name, r in runs.items():
        pe, _ = r.arrays()
        rot = float(np.max(r.rot_err))
        posn = float(np.max(np.linalg.norm(pe, axis=1)))
        t = np.asarray(r.time_s)
        used = np.asarray(r.n_used)
        raw = np.asarray(r.n_raw)
        ok = rot <= GOAL_ROT_DEG and posn <= GOAL_POS_M and float(np.median(t)) <= GOAL_TIME_S
        rows.append({
            "exp": r.experiment, "method": name,
            "max_rot_deg": rot, "max_pos_mm": posn * 1e3,
            "median_ms": float(np.median(t)) * 1e3, "p90_ms": float(np.percentile(t, 90)) * 1e3,
            "points_used": f"{int(np.median(used))} ({int(used.min())}-{int(used.max())})",
            "points_raw": f"{int(np.median(raw))} ({int(raw.min())}-{int(raw.max())})",
            "converged": f"{int(np.sum(r.converged))}/{len(r.converged)}",
            "goals_met": "yes" if ok else "no",
        })
    return rows


def write_csv(path: Path, runs: dict[str, Run]) -> None:
    with path.open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["method", "frame", "distance_m", "roll_err_deg", "pitch_err_deg", "yaw_err_deg",
                    "x_err_m", "y_err_m", "z_err_m", "rot_err_deg", "time_s", "points_raw",
                    "points_used", "voxel_m", "converged"])
        for name, r in runs.items():
            pe, ae = r.arrays()
            for k in range(len(r.time_s)):
                w.writerow([name, k + 1, f"{r.distance[k]:.3f}", *(f"{v:.6g}" for v in ae[k]),
                            *(f"{v:.6g}" for v in pe[k]), f"{r.rot_err[k]:.6g}",
                            f"{r.time_s[k]:.6g}", r.n_raw[k], r.n_used[k],
                            f"{r.voxel_m[k]:.6g}", int(r.converged[k])])


def _symlog_if_wide(ax: Any, runs: dict[str, Run], values_of: Any, linthresh: float) -> None:
    """Linear axis, unless a diverging method would flatten the others: then linear within
    +-linthresh and logarithmic beyond."""
    vmax = max(float(np.max(np.abs(values_of(r)))) for r in runs.values())
    if vmax > 5.0 * linthresh:
        ax.set_yscale("symlog", linthresh=linthresh)


def plot_experiment(out: Path, experiment: int, runs: dict[str, Run]) -> list[Path]:
    """Three PNGs mirroring seed 003 Figs. 7-9 (experiment 1) or 10-12 (experiment 2)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figs = {1: (7, 8, 9), 2: (10, 11, 12)}[experiment]
    styles = {"ICP": ("tab:red", "s"), "Proposed": ("tab:blue", "o"), "P2Plane": ("tab:green", "^"),
              "Lines+P2Plane": ("tab:purple", "d"), "P2Plane+CV+rays": ("tab:orange", "v"),
              "P2Plane+CV+outline": ("tab:brown", "P"), "P2Plane+EKF+outline": ("tab:gray", "X")}
    paths = []

    def axes_of(title: str, n: int) -> tuple[Any, Any]:
        fig, axs = plt.subplots(n, 1, figsize=(7, 2.6 * n), sharex=True, constrained_layout=True)
        fig.suptitle(title)
        return fig, axs

    def series(ax: Any, values_of: Any, label: str, unit: str) -> None:
        for name, r in runs.items():
            c, m = styles.get(name, ("k", "."))
            ax.plot(-r.distance, values_of(r), color=c, marker=m, ms=3, lw=1, label=name)
        ax.set_ylabel(f"{label} [{unit}]")
        ax.grid(alpha=0.3)

    fig, axs = axes_of(f"Experiment {experiment}: attitude error (seed 003 Fig. {figs[0]})", 3)
    for i, (ax, lab) in enumerate(zip(axs, ("roll", "pitch", "yaw"))):
        series(ax, lambda r, i=i: r.arrays()[1][:, i], f"{lab} error", "deg")
        _symlog_if_wide(ax, runs, lambda r, i=i: r.arrays()[1][:, i], 0.5)
    axs[0].legend(loc="upper right", fontsize=8)
    axs[-1].set_xlabel("approach distance [m] (negative: closing along X)")
    paths.append(out / f"exp{experiment}_attitude_error.png")
    fig.savefig(paths[-1], dpi=110)
    plt.close(fig)

    fig, axs = axes_of(f"Experiment {experiment}: position error (seed 003 Fig. {figs[1]})", 3)
    for i, (ax, lab) in enumerate(zip(axs, ("X", "Y", "Z"))):
        series(ax, lambda r, i=i: r.arrays()[0][:, i] * 1e3, f"{lab} error", "mm")
        _symlog_if_wide(ax, runs, lambda r, i=i: r.arrays()[0][:, i] * 1e3, 10.0)
    axs[0].legend(loc="upper right", fontsize=8)
    axs[-1].set_xlabel("approach distance [m] (negative: closing along X)")
    paths.append(out / f"exp{experiment}_position_error.png")
    fig.savefig(paths[-1], dpi=110)
    plt.close(fig)

    fig, axs = axes_of(f"Experiment {experiment}: runtime (seed 003 Fig. {figs[2]})", 3)
    series(axs[0], lambda r: np.asarray(r.time_s) * 1e3, "time per frame", "ms")
    axs[0].axhline(GOAL_TIME_S * 1e3, color="k", ls=":", lw=1, label="goal")
    axs[0].set_yscale("log")
    series(axs[1], lambda r: np.asarray(r.n_used), "points used", "-")
    any_run = next(iter(runs.values()))
    axs[1].plot(-any_run.distance, any_run.n_raw, color="k", lw=1, ls="--", label="sensor cloud")
    axs[1].set_yscale("log")
    axs[0].legend(loc="upper left", fontsize=8)
    axs[1].legend(loc="upper left", fontsize=8)
    if "Proposed" in runs:
        r = runs["Proposed"]
        axs[2].plot(-r.distance, np.asarray(r.voxel_m) * 1e3, color="tab:blue", marker="o", ms=3)
    axs[2].set_ylabel("grid size d_k [mm]")
    axs[2].grid(alpha=0.3)
    axs[-1].set_xlabel("approach distance [m] (negative: closing along X)")
    paths.append(out / f"exp{experiment}_runtime.png")
    fig.savefig(paths[-1], dpi=110)
    plt.close(fig)
    return paths


def run(args: argparse.Namespace) -> int:
    import yaml

    from agents.benchmarks.timing import format_table
    from agents.outputs import check_folder, claim_folder
    from perception.config import FlashLidarConfig, ICPConfig
    from perception.estimation.linetrack import seed003_icp_config

    out: Path = args.out
    check_folder(out, "bench-seed003")  # before the work: its own files only
    claim_folder(out, "bench-seed003")
    all_runs: dict[int, dict[str, Run]] = {}
    for e in args.experiments:
        t0 = time.perf_counter()
        all_runs[e] = run_experiment(e, args)
        print(f"experiment {e}: {args.frames} frames, {time.perf_counter() - t0:.1f} s")
    err = [row for e in all_runs for row in error_rows(all_runs[e])]
    summ = [row for e in all_runs for row in summary_rows(all_runs[e])]
    head = (
        "seed 003 (CYGNSS-like, flash 500x500, 20x20 deg, +-10 mm; 60 m -> 10 m, roll 125 -> "
        "-125 deg)\npaper: < 0.5 deg, ~1 cm, ~200 ms/frame, ~5,000 points. goals: max rotation "
        f"<= {GOAL_ROT_DEG} deg, max position <= {GOAL_POS_M * 1e3:.0f} mm, <= "
        f"{GOAL_TIME_S * 1e3:.0f} ms/frame"
    )
    text = "\n".join([head, "", "errors (estimate - truth, seed axes: x boresight, y right, z down)",
                      format_table(err, ".3f"), "", "summary", format_table(summ, ".3g")])
    print(text)
    (out / "seed003_table.md").write_text(text + "\n")
    for e, runs in all_runs.items():
        write_csv(out / f"exp{e}_frames.csv", runs)
        if not args.no_plots:
            for p in plot_experiment(out, e, runs):
                print(f"wrote {p}")
    flash = FlashLidarConfig()
    resolved = {
        "args": {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()
                 if k != "handler"},
        "flash": flash.model_dump(mode="json"),
        "icp_point_to_point": seed003_icp_config(flash.range_error_m / math.sqrt(3.0)).model_dump(
            mode="json"),
        "icp_point_to_plane": ICPConfig().model_dump(mode="json"),
    }
    (out / "config.yaml").write_text(yaml.safe_dump(json.loads(json.dumps(resolved)),
                                                    sort_keys=False))
    return 0
