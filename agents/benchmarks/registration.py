"""ICP tracking on TriDAR frames: time, error and ratio to the Cramer-Rao bound, next to peers.

Frames are 1,000-point rosette scans from :class:`perception.sensing.sensors.TriDARSensor`, steered onto
the target (the pattern's field of view sized to the target's angular extent). The target drifts
and turns a little between frames and each frame is tracked from the previous frame's estimate.
Open3D point-to-plane ICP and small_gicp (when importable; benchmark-only extras) run on the same
clouds from the same initial poses in the same process. Our tracker runs twice: as the pipeline
runs it (closest face) and matching each point to the face its measured ray crosses. The ratios to
the Cramer-Rao bound are taken over the frames whose information matrix has full rank (see
:class:`_BoundStats`).

PAH acquisition (``--no-acquisition`` to skip; ``--no-tracking`` runs it alone): random attitudes
at the ranges of issue 4 (``cubesat`` 2-10 m, ``cygnss`` 5-50 m), the same clouds localized
unconstrained and in a docking corridor (with the cloud's ray directions), success judged on the
returned pose; Open3D RANSAC + FPFH global registration (refined by Open3D ICP) on the same clouds
is the peer row. Each case draws its scene and each localization its randomness from its own
seeded generator, so a change to PAH leaves the cases unchanged. Times are wall clock
(``t_*``, what a caller waits) and process CPU time (``cpu_med_s``, robust to other load on the
machine).
"""

from __future__ import annotations

import argparse
import time
from typing import Any

import numpy as np

GOALS = "goals: <= 5 ms/frame; <= 1 cm / 0.1 deg under 10 m; RMS error <= 1.5x CRLB"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--quick", action="store_true", help="fewer frames (about a minute)")
    parser.add_argument("--frames", type=int, default=40, help="frames per range")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--no-peers", action="store_true", help="skip Open3D and small_gicp")
    parser.add_argument("--acq-cases", type=int, default=200, help="acquisition cases per target")
    parser.add_argument("--no-acquisition", action="store_true", help="skip the PAH benchmark")
    parser.add_argument("--no-tracking", action="store_true", help="skip the ICP tracking benchmark")
    parser.add_argument("--acq-scans", type=int, default=3, metavar="K",
                        help="also localize from K successive scans of each case's static pose "
                        "(PAHDatabase.localize_scans; 1: single-scan rows only)")
    parser.add_argument("--acq-log", default=None, metavar="PATH",
                        help="write one JSON line per acquisition case and method (errors, reason)")
    parser.add_argument("--acq-only", default=None, metavar="CASES",
                        help="run only these acquisition case numbers (comma-separated)")


def _peers(model_pts: np.ndarray, model_nrm: np.ndarray) -> dict[str, Any]:
    """Callables ``(points, T_init) -> T_sensor_target`` for the peers that are importable.

    Both peers align a source cloud to a target cloud and return ``T_target_source``; with the
    model as target and the scan (sensor frame) as source that is ``T_target_sensor``, so the
    initial guess is ``inv(T_sensor_target)`` and the answer is inverted back.
    """
    peers: dict[str, Any] = {}
    # Peers need writable, contiguous float64 copies (the model arrays are read-only caches).
    model_pts = np.array(model_pts, dtype=np.float64, order="C")
    model_nrm = np.array(model_nrm, dtype=np.float64, order="C")
    try:
        import open3d as o3d

        tgt = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(model_pts))
        tgt.normals = o3d.utility.Vector3dVector(model_nrm)
        reg = o3d.pipelines.registration

        def o3d_icp(P: np.ndarray, T0: np.ndarray) -> np.ndarray:
            src = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.array(P, dtype=np.float64)))
            r = reg.registration_icp(
                src, tgt, 0.05, np.linalg.inv(T0),
                reg.TransformationEstimationPointToPlane(),
                reg.ICPConvergenceCriteria(max_iteration=30),
            )
            return np.linalg.inv(np.asarray(r.transformation))

        peers["open3d p2plane"] = o3d_icp
    except Exception:  # noqa: BLE001, S110 - optional peer, any import/runtime failure skips it
        pass
    try:
        import small_gicp

        # Model: downsampled to ~1 cm, covariances from 10 neighbours, KD-tree, built once.
        tgt_cloud, tgt_tree = small_gicp.preprocess_points(
            model_pts, downsampling_resolution=0.01, num_neighbors=10, num_threads=1
        )

        def sg_icp(P: np.ndarray, T0: np.ndarray) -> np.ndarray:
            # The scan needs its own covariances (GICP) too: preprocessing is part of the frame's
            # time. A fine voxel keeps all of a sparse 1,000-point scan.
            src_cloud, _ = small_gicp.preprocess_points(
                np.array(P, dtype=np.float64), downsampling_resolution=0.005, num_neighbors=10,
                num_threads=1,
            )
            r = small_gicp.align(
                tgt_cloud, src_cloud, tgt_tree,
                init_T_target_source=np.linalg.inv(T0), registration_type="GICP",
                max_correspondence_distance=0.05, num_threads=1,
            )
            return np.linalg.inv(np.asarray(r.T_target_source))

        peers["small_gicp"] = sg_icp
    except Exception:  # noqa: BLE001, S110 - optional peer
        pass
    return peers


#: Our tracker, as the pipeline runs it (closest face) and matching each point to the face its
#: measured ray crosses (``match_along_rays``, PAH's refinement).
OURS = {"tridar icp": False, "tridar icp (rays)": True}


class _BoundStats:
    """Error against the Cramer-Rao covariance of the frames whose information has full rank.

    ``rms/crlb`` is ``sqrt(mean |e|^2 / mean trace(C))``; ``std/crlb`` the same with the mean error
    (a sensor bias such as the TOF ``bias_m``, which no estimator removes) taken out; ``bias_mm``
    that mean. Frames with an unobservable direction carry a placeholder variance and are counted
    in ``degenerate`` instead (one of them would swamp the mean).
    """

    COLUMNS = ("rms/crlb pos", "std/crlb pos", "rms/crlb rot", "bias_mm", "degenerate")

    def __init__(self) -> None:
        self.err: list[np.ndarray] = []
        self.tr_pos: list[float] = []
        self.tr_rot: list[float] = []
        self.degenerate = 0

    def add(self, res: Any, T_true: np.ndarray) -> None:
        from scipy.spatial.transform import Rotation

        if res.degenerate_axes:
            self.degenerate += 1
            return
        self.tr_pos.append(float(np.trace(res.covariance[:3, :3])))
        self.tr_rot.append(float(np.trace(res.covariance[3:, 3:])))
        dphi = Rotation.from_matrix(T_true[:3, :3] @ res.T_sensor_target[:3, :3].T).as_rotvec()
        self.err.append(np.r_[T_true[:3, 3] - res.T_sensor_target[:3, 3], dphi])

    def columns(self) -> dict[str, Any]:
        if not self.err:
            return {**dict.fromkeys(self.COLUMNS[:-1], float("nan")), "degenerate": self.degenerate}
        E = np.array(self.err)
        bias = E[:, :3].mean(axis=0)
        cp, cr = float(np.mean(self.tr_pos)), float(np.mean(self.tr_rot))
        return {
            "rms/crlb pos": float(np.sqrt(np.mean(np.sum(E[:, :3] ** 2, axis=1)) / cp)),
            "std/crlb pos": float(np.sqrt(np.mean(np.sum((E[:, :3] - bias) ** 2, axis=1)) / cp)),
            "rms/crlb rot": float(np.sqrt(np.mean(np.sum(E[:, 3:] ** 2, axis=1)) / cr)),
            "bias_mm": 1e3 * float(np.linalg.norm(bias)),
            "degenerate": self.degenerate,
        }


def run(args: argparse.Namespace) -> int:
    from scipy.spatial.transform import Rotation

    from agents.benchmarks.timing import Timing, format_table
    from perception.config import SensorConfig
    from perception.geometry import make_T, pose_error
    from perception.estimation.registration import icp, prepare_model
    from perception.sensing.scan_patterns import rosette
    from perception.sensing.sensors import TriDARSensor
    from perception.targets import load_target

    if getattr(args, "no_tracking", False):
        if not args.no_acquisition:
            run_acquisition(args)
        return 0
    frames = 10 if args.quick else int(args.frames)
    cases = [("cubesat", r) for r in (2.0, 5.0, 10.0)] + [("cygnss", r) for r in (5.0, 20.0, 50.0)]
    rng = np.random.default_rng(args.seed)
    sensor = TriDARSensor(SensorConfig())
    fov_max = np.radians(min(SensorConfig().fov_deg)) * 0.99
    rows = []
    for name, range_m in cases:
        target = load_target(name)
        model = prepare_model(target)
        peers = {} if args.no_peers else _peers(model.points, model.normals)
        R0 = Rotation.random(random_state=int(rng.integers(1 << 31)))
        T_true = make_T(R0.as_matrix(), [0.0, 0.0, range_m])
        fov = min(fov_max, 2.4 * np.arctan(target.radius / range_m))
        est = {**{k: T_true.copy() for k in OURS}, **{k: T_true.copy() for k in peers}}
        stats: dict[str, dict[str, list[float]]] = {k: {"t": [], "e_m": [], "e_deg": []} for k in est}
        bound = {k: _BoundStats() for k in OURS}
        for f in range(frames):
            # Small relative motion between frames: ~1 cm and ~0.3 deg.
            step = Rotation.from_rotvec(rng.normal(scale=np.radians(0.2), size=3))
            T_true = T_true @ make_T(step.as_matrix())
            T_true[:3, 3] += rng.normal(scale=0.006, size=3)
            pattern = rosette(1000, fov, phase=0.37 * f)
            cloud = sensor.scan(target, T_true, pattern, rng)
            if len(cloud.points) < 20:
                continue
            for k, along_rays in OURS.items():
                t0 = time.perf_counter()
                res = icp(cloud.points, model, est[k], sigma=cloud.sigma,
                          directions=cloud.directions, match_along_rays=along_rays)
                dt = time.perf_counter() - t0
                est[k] = res.T_sensor_target
                e = pose_error(res.T_sensor_target, T_true)
                stats[k]["t"].append(dt)
                stats[k]["e_m"].append(e[0])
                stats[k]["e_deg"].append(e[1])
                bound[k].add(res, T_true)
            for k, fn in peers.items():
                t0 = time.perf_counter()
                try:
                    Tk = fn(cloud.points, est[k])
                except Exception:  # noqa: BLE001 - a peer failing a frame is recorded as lost
                    Tk = est[k]
                dtk = time.perf_counter() - t0
                est[k] = Tk
                ek = pose_error(Tk, T_true)
                stats[k]["t"].append(dtk)
                stats[k]["e_m"].append(ek[0])
                stats[k]["e_deg"].append(ek[1])
        base = None
        for k, s in stats.items():
            if not s["t"]:
                continue
            tm = Timing.of(s["t"])
            base = tm.median if k == "tridar icp" else base
            row = {
                "target": name,
                "range_m": range_m,
                "method": k,
                "frames": tm.n,
                "t_med_ms": 1e3 * tm.median,
                "t_p90_ms": 1e3 * tm.p90,
                "t_vs_ours": tm.median / base if base else float("nan"),
                "err_med_mm": 1e3 * float(np.median(s["e_m"])),
                "err_p90_mm": 1e3 * float(np.percentile(s["e_m"], 90)),
                "rot_med_deg": float(np.median(s["e_deg"])),
                "rot_p90_deg": float(np.percentile(s["e_deg"], 90)),
                **(bound[k].columns() if k in bound else dict.fromkeys(_BoundStats.COLUMNS, "")),
            }
            rows.append(row)
    print("ICP tracking, 1,000-point rosette frames, tracked from the previous estimate")
    print(GOALS)
    print(format_table(rows))
    if not args.no_acquisition:
        run_acquisition(args)
    return 0


ACQ_GOALS = "goals: >= 99% success; median <= 0.5 s unconstrained, <= 0.05 s constrained"
#: Acquisition ranges [m] per target (issue 4).
ACQ_RANGES_M = {"cubesat": (2.0, 10.0), "cygnss": (5.0, 50.0)}


def _add_s(target: Any, T_est: np.ndarray, T_true: np.ndarray, n: int = 2000) -> float:
    """ADD-S [m]: mean distance from model points under T_est to the nearest under T_true."""
    from scipy.spatial import cKDTree

    from perception.geometry import transform_points

    pts, _ = target.sample_surface(n, seed=7)
    d, _ = cKDTree(transform_points(T_true, pts)).query(transform_points(T_est, pts))
    return float(np.mean(d))


def _acq_success(target: Any, T_est: np.ndarray, T_true: np.ndarray) -> bool:
    from perception.geometry import pose_error

    if target.symmetries:
        return _add_s(target, T_est, T_true) < 0.05
    e_m, e_deg = pose_error(T_est, T_true)
    return e_m < 0.05 and e_deg < 2.0


def _o3d_global(model_pts: np.ndarray, voxel: float) -> Any:
    """Open3D RANSAC + FPFH + point-to-plane ICP: callable ``points -> T_sensor_target``."""
    import open3d as o3d

    reg = o3d.pipelines.registration
    geo = o3d.geometry

    def features(P: np.ndarray) -> tuple[Any, Any]:
        pc = geo.PointCloud(o3d.utility.Vector3dVector(np.array(P))).voxel_down_sample(voxel)
        pc.estimate_normals(geo.KDTreeSearchParamHybrid(radius=2.5 * voxel, max_nn=30))
        f = reg.compute_fpfh_feature(pc, geo.KDTreeSearchParamHybrid(radius=5 * voxel, max_nn=100))
        return pc, f

    tgt, tgt_f = features(model_pts)
    tgt_full = geo.PointCloud(o3d.utility.Vector3dVector(np.array(model_pts)))
    tgt_full.estimate_normals(geo.KDTreeSearchParamHybrid(radius=2.5 * voxel, max_nn=30))

    def solve(P: np.ndarray) -> np.ndarray:
        src, src_f = features(P)
        r = reg.registration_ransac_based_on_feature_matching(
            src, tgt, src_f, tgt_f, True, 1.5 * voxel,
            reg.TransformationEstimationPointToPoint(False), 3,
            [reg.CorrespondenceCheckerBasedOnEdgeLength(0.9),
             reg.CorrespondenceCheckerBasedOnDistance(1.5 * voxel)],
            reg.RANSACConvergenceCriteria(100_000, 0.999),
        )
        src_full = geo.PointCloud(o3d.utility.Vector3dVector(P))
        r = reg.registration_icp(src_full, tgt_full, 0.05, r.transformation,
                                 reg.TransformationEstimationPointToPlane())
        # Open3D estimates T_target_sensor (scan -> model).
        return np.linalg.inv(np.asarray(r.transformation))

    return solve


def run_acquisition(args: argparse.Namespace) -> None:
    """PAH acquisition: success rate and time, unconstrained and constrained, next to Open3D."""
    import json

    from scipy.spatial.transform import Rotation

    from agents.benchmarks.timing import Timing, format_table
    from perception.config import SensorConfig
    from perception.geometry import make_T, pose_error
    from perception.estimation.pah import PAHDatabase, PoseConstraint
    from perception.estimation.registration import prepare_model
    from perception.sensing.sensors import TriDARSensor
    from perception.targets import load_target

    n_cases = 20 if args.quick else int(args.acq_cases)
    n_scans = int(getattr(args, "acq_scans", 1))
    if n_scans < 1:
        raise ValueError(f"--acq-scans={n_scans}; expected >= 1")
    only = getattr(args, "acq_only", None)
    case_ids = (
        [int(c) for c in str(only).split(",") if c.strip()] if only else list(range(n_cases))
    )
    log_path = getattr(args, "acq_log", None)
    log = open(log_path, "w") if log_path else None  # noqa: SIM115 - closed at the end
    sensor = TriDARSensor(SensorConfig())
    # The further scans' own sensor: the first scan's frame counter runs as it always has.
    more_sensor = TriDARSensor(SensorConfig())
    rows = []
    for name in ("cubesat", "cygnss"):
        target = load_target(name)
        range_lo, range_hi = ACQ_RANGES_M[name]
        db = PAHDatabase.build(target)
        peer = None
        if not args.no_peers:
            try:
                peer = _o3d_global(prepare_model(target).points, 0.05)
            except Exception:  # noqa: BLE001 - optional peer
                peer = None
        multi = [f"pah unconstrained, {n_scans} scans", f"pah constrained, {n_scans} scans"]
        methods = ["pah unconstrained", "pah constrained", *(multi if n_scans > 1 else []),
                   "open3d ransac+fpfh"]
        stats: dict[str, tuple[list[float], list[float], list[bool]]] = {
            k: ([], [], []) for k in methods
        }
        for case in case_ids:
            rng = np.random.default_rng([args.seed + 1000, case])
            R = Rotation.random(random_state=int(rng.integers(1 << 31))).as_matrix()
            T_true = make_T(R, [0.0, 0.0, rng.uniform(range_lo, range_hi)])
            cloud = sensor.scan(target, T_true, sensor.make_scan_pattern(0, T_true, target.regions["whole"]), rng)
            R_nom = Rotation.from_rotvec(rng.normal(scale=np.radians(5.0), size=3)).as_matrix() @ R
            corridor = PoseConstraint(R_nom, np.radians(20.0), np.radians(15.0), 1.0, 100.0)
            # Further scans of the same static pose (the pattern's phase advanced frame by frame),
            # from their own generator: the single-scan case above is unchanged by them.
            scans = [cloud]
            more_rng = np.random.default_rng([args.seed + 1000, case, 100])
            for f in range(1, n_scans):
                pattern = sensor.make_scan_pattern(f, T_true, target.regions["whole"])
                scans.append(more_sensor.scan(target, T_true, pattern, more_rng, frame_index=f))
            runs = [("pah unconstrained", None, 1), ("pah constrained", corridor, 2)]
            if n_scans > 1:
                runs += [(multi[0], None, 1), (multi[1], corridor, 2)]
            for key, con, j in runs:
                pah_rng = np.random.default_rng([args.seed + 1000, case, j])
                c0 = time.process_time()
                if key in multi:
                    res = db.localize_scans(scans, pah_rng, constraint=con)
                else:
                    res = db.localize(cloud.points, pah_rng, constraint=con, sigma=cloud.sigma,
                                      directions=cloud.directions)
                stats[key][1].append(time.process_time() - c0)
                stats[key][0].append(res.time_s)
                stats[key][2].append(_acq_success(target, res.T_sensor_target, T_true))
                if log is not None:
                    e_m, e_deg = pose_error(res.T_sensor_target, T_true)
                    log.write(json.dumps({
                        "target": name, "case": case, "method": key, "ok": stats[key][2][-1],
                        "e_m": float(e_m), "e_deg": float(e_deg), "t_s": res.time_s,
                        "range_m": float(T_true[2, 3]), "n_points": res.n_points,
                        "fitness": float(res.fitness), "converged": bool(res.converged),
                        "iterations": int(res.iterations), "reason": res.reason,
                    }) + "\n")
                    log.flush()
            if peer is not None:
                t0, c0 = time.perf_counter(), time.process_time()
                try:
                    T_peer = peer(cloud.points)
                except Exception:  # noqa: BLE001 - a peer failure counts as a miss
                    T_peer = np.eye(4)
                stats["open3d ransac+fpfh"][0].append(time.perf_counter() - t0)
                stats["open3d ransac+fpfh"][1].append(time.process_time() - c0)
                stats["open3d ransac+fpfh"][2].append(_acq_success(target, T_peer, T_true))
        base = Timing.of(stats["pah unconstrained"][0]).median
        for key, (times, cpu, ok) in stats.items():
            if not times:
                continue
            tm = Timing.of(times)
            rows.append({
                "target": name,
                "range_m": f"{range_lo:g}-{range_hi:g}",
                "method": key,
                "scans": n_scans if key in multi else 1,
                "cases": tm.n,
                "success_%": 100.0 * float(np.mean(ok)),
                "t_med_s": tm.median,
                "t_p90_s": tm.p90,
                "t_max_s": float(np.max(times)),
                "cpu_med_s": float(np.median(cpu)),
                "t_vs_pah": tm.median / base,
            })
    if log is not None:
        log.close()
    print()
    print("Acquisition (PAH), random attitudes (cubesat 2-10 m, cygnss 5-50 m), TriDAR scans steered"
          " on the whole target; success: < 5 cm and < 2 deg (ADD-S < 5 cm for symmetric targets)")
    if n_scans > 1:
        print(f"'{n_scans} scans': PAHDatabase.localize_scans on {n_scans} successive 0.1 s scans of"
              " the same static pose (times: localization only, not the extra scans' acquisition)")
    print(ACQ_GOALS)
    print(format_table(rows))
