"""Sensor simulation: TriDAR 1,000-sample scan and 500 x 500 flash frame vs the bare Embree call.

For each target, times a full TriDAR frame (1,000 samples, beam-divergence sub-rays, noise,
fusion) and a seed-003 flash frame, and in the same process a bare ``mesh.ray.intersects_location``
call (first hit only) with the same rays in the target frame: the Embree floor. Goals: TriDAR scan
<= 2 ms; flash frame <= 1.3x the bare Embree time.
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np

from agents.benchmarks.timing import Timing

if TYPE_CHECKING:
    from perception.sensing.sensors import FlashLidar, TriDARSensor
    from perception.targets import TargetModel


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--repeats", type=int, default=30, help="timed calls per row (default 30)")
    p.add_argument("--targets", nargs="+", default=["cygnss", "iss_port"])


def run(args: argparse.Namespace) -> int:
    from perception.config import FlashLidarConfig, SensorConfig
    from perception.sensing.sensors import FlashLidar, TriDARSensor
    from perception.targets import load_target
    from agents.benchmarks.timing import format_table

    sensor = TriDARSensor(SensorConfig())
    flash = FlashLidar(FlashLidarConfig())
    rows = []
    for name in args.targets:
        rows.extend(_target_rows(load_target(name), sensor, flash, args.repeats))
    print(format_table(rows))
    return 0


def _interleaved(a: Callable[[], object], b: Callable[[], object], repeats: int) -> tuple[Timing, Timing]:
    """Time ``a`` and ``b`` alternately so both see the same machine load (shared cores)."""
    for _ in range(2):
        a(), b()
    ta, tb = [], []
    for _ in range(repeats):
        t0 = time.perf_counter()
        a()
        t1 = time.perf_counter()
        b()
        ta.append(t1 - t0)
        tb.append(time.perf_counter() - t1)
    return Timing.of(ta), Timing.of(tb)


def _target_rows(
    target: TargetModel, sensor: TriDARSensor, flash: FlashLidar, repeats: int
) -> list[dict[str, object]]:
    from scipy.spatial.transform import Rotation

    from perception.geometry import make_T
    from perception.sensing.scan_patterns import angles_to_directions
    name = target.name
    rows: list[dict[str, object]] = []
    size = float(np.max(target.extents))
    R = Rotation.from_euler("xyz", [15.0, -20.0, 30.0], degrees=True)
    # TriDAR: steered on the whole target at ~5 sizes; flash: target filling ~half the frame.
    T_scan = make_T(R, [0.1, -0.1, 5.0 * size])
    T_flash = make_T(R, [0.0, 0.0, 2.2 * size])
    pattern = sensor.make_scan_pattern(0, T_scan, target.regions["whole"])
    rng = np.random.default_rng(0)
    cloud = sensor.scan(target, T_scan, pattern, rng, frame_index=0)
    # Same rays as the scan: every sub-ray of every sample, in the target frame.
    off = sensor.subray_offsets
    d_s = angles_to_directions(pattern.az[:, None] + off[:, 0],
                               pattern.el[:, None] + off[:, 1]).reshape(-1, 3)
    Rs = T_scan[:3, :3]
    o = np.broadcast_to(-(Rs.T @ T_scan[:3, 3]), d_s.shape)
    d_t = d_s @ Rs
    t_scan, t_bare = _interleaved(
        lambda: sensor.scan(target, T_scan, pattern, rng, frame_index=0),
        lambda: target.ray.intersects_location(o, d_t, multiple_hits=False),
        repeats,
    )
    rows.append({
        "target": name, "frame": f"tridar {len(pattern)}x{off.shape[0]} rays",
        "points": len(cloud), "median_ms": t_scan.median * 1e3, "p90_ms": t_scan.p90 * 1e3,
        "embree_ms": t_bare.median * 1e3, "ratio": t_scan.median / t_bare.median,
        "goal": "<= 2 ms", "met": "yes" if t_scan.median <= 2e-3 else "no",
    })

    frame = flash.capture(target, T_flash, rng)
    reps = max(5, repeats // 3)
    Rf = T_flash[:3, :3]
    d_f = flash.pixel_directions @ Rf
    o_f = np.broadcast_to(-(Rf.T @ T_flash[:3, 3]), d_f.shape)
    t_flash, t_fbare = _interleaved(
        lambda: flash.capture(target, T_flash, rng),
        lambda: target.ray.intersects_location(o_f, d_f, multiple_hits=False),
        reps,
    )
    ratio = t_flash.median / t_fbare.median
    rows.append({
        "target": name, "frame": f"flash {flash.shape[0]}x{flash.shape[1]}",
        "points": len(frame), "median_ms": t_flash.median * 1e3, "p90_ms": t_flash.p90 * 1e3,
        "embree_ms": t_fbare.median * 1e3, "ratio": ratio,
        "goal": "<= 1.3x embree", "met": "yes" if ratio <= 1.3 else "no",
    })
    return rows
