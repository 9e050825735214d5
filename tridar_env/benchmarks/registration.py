"""ICP tracking on TriDAR frames: time, error and ratio to the Cramer-Rao bound, next to peers.

Frames are 1,000-point rosette scans from :class:`perception.sensors.TriDARSensor`, steered onto
the target (the pattern's field of view sized to the target's angular extent). The target drifts
and turns a little between frames and each frame is tracked from the previous frame's estimate.
Open3D point-to-plane ICP and small_gicp (when importable; benchmark-only extras) run on the same
clouds from the same initial poses in the same process.

PAH acquisition is not benchmarked here yet (perception.pah is not written).
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


def _peers(model_pts: np.ndarray, model_nrm: np.ndarray) -> dict[str, Any]:
    """Callables ``(points, T_init) -> T`` for the peers that are importable."""
    peers: dict[str, Any] = {}
    try:
        import open3d as o3d

        tgt = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(model_pts))
        tgt.normals = o3d.utility.Vector3dVector(model_nrm)
        reg = o3d.pipelines.registration

        def o3d_icp(P: np.ndarray, T0: np.ndarray) -> np.ndarray:
            # Open3D aligns source to target: source = scan (sensor), target = model, so it
            # estimates T_target_sensor.
            src = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(P))
            r = reg.registration_icp(
                src, tgt, 0.05, np.linalg.inv(T0),
                reg.TransformationEstimationPointToPlane(),
                reg.ICPConvergenceCriteria(max_iteration=30),
            )
            return np.linalg.inv(np.asarray(r.transformation))

        peers["open3d p2plane"] = o3d_icp
    except Exception:  # noqa: BLE001 - optional peer, any import/runtime failure skips it
        pass
    try:
        import small_gicp

        tgt_cloud, tgt_tree = small_gicp.preprocess_points(model_pts, downsampling_resolution=0.01)

        def sg_icp(P: np.ndarray, T0: np.ndarray) -> np.ndarray:
            r = small_gicp.align(
                tgt_cloud, small_gicp.PointCloud(P), tgt_tree,
                init_T_target_source=np.linalg.inv(T0), registration_type="GICP",
                max_correspondence_distance=0.05, num_threads=1,
            )
            return np.linalg.inv(np.asarray(r.T_target_source))

        peers["small_gicp"] = sg_icp
    except Exception:  # noqa: BLE001
        pass
    return peers


def run(args: argparse.Namespace) -> int:
    from scipy.spatial.transform import Rotation

    from perception.config import SensorConfig
    from perception.geometry import make_T, pose_error
    from perception.registration import icp, prepare_model
    from perception.scan_patterns import rosette
    from perception.sensors import TriDARSensor
    from perception.targets import load_target

    from tridar_env.benchmarks.timing import Timing, format_table

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
        est = {"tridar icp": T_true.copy(), **{k: T_true.copy() for k in peers}}
        stats: dict[str, dict[str, list[float]]] = {k: {"t": [], "e_m": [], "e_deg": []} for k in est}
        crlb_pos, crlb_rot, err_vec = [], [], []
        for f in range(frames):
            # Small relative motion between frames: ~1 cm and ~0.3 deg.
            step = Rotation.from_rotvec(rng.normal(scale=np.radians(0.2), size=3))
            T_true = T_true @ make_T(step.as_matrix())
            T_true[:3, 3] += rng.normal(scale=0.006, size=3)
            pattern = rosette(1000, fov, phase=0.37 * f)
            cloud = sensor.scan(target, T_true, pattern, rng)
            if len(cloud.points) < 20:
                continue
            t0 = time.perf_counter()
            res = icp(cloud.points, model, est["tridar icp"], sigma=cloud.sigma,
                      directions=cloud.directions)
            dt = time.perf_counter() - t0
            est["tridar icp"] = res.T_sensor_target
            e = pose_error(res.T_sensor_target, T_true)
            s = stats["tridar icp"]
            s["t"].append(dt)
            s["e_m"].append(e[0])
            s["e_deg"].append(e[1])
            crlb_pos.append(np.trace(res.covariance[:3, :3]))
            crlb_rot.append(np.trace(res.covariance[3:, 3:]))
            dphi = Rotation.from_matrix(T_true[:3, :3] @ res.T_sensor_target[:3, :3].T).as_rotvec()
            err_vec.append(np.r_[T_true[:3, 3] - res.T_sensor_target[:3, 3], dphi])
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
        E = np.array(err_vec)
        ratio_pos = float(np.sqrt(np.mean(np.sum(E[:, :3] ** 2, 1)) / np.mean(crlb_pos))) if len(E) else float("nan")
        ratio_rot = float(np.sqrt(np.mean(np.sum(E[:, 3:] ** 2, 1)) / np.mean(crlb_rot))) if len(E) else float("nan")
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
                "rms/crlb pos": ratio_pos if k == "tridar icp" else "",
                "rms/crlb rot": ratio_rot if k == "tridar icp" else "",
            }
            rows.append(row)
    print("ICP tracking, 1,000-point rosette frames, tracked from the previous estimate")
    print(GOALS)
    print(format_table(rows))
    print("acquisition (PAH): not benchmarked - perception.pah not implemented yet")
    return 0
