"""``tridar-env replay SOURCE``: the perception pipeline run again, offline, on recorded clouds.

SOURCE is a tridar-env recording (``--record`` of ``demo`` / ``run``), a folder of PLY/PCD frames,
or any MCAP / ROS 2 bag with ``sensor_msgs/PointCloud2`` on ``--topic``. With a recording and no
``--set`` the pipeline is rebuilt from the recorded settings and its state vectors are compared
with the live ones (bitwise); ``--set`` replays the same clouds with other settings. Errors are
against the recorded truth (or ``--truth`` CSV for real data); ``--plot`` and ``--csv`` write them.
Conventions for real data: :mod:`agents.replay_sources`.
"""

from __future__ import annotations

import argparse
import csv
from pathlib import Path

from agents.cli import command


@command("replay", "rerun the TriDAR pipeline offline on a recording, a PLY/PCD folder or a bag topic")
def add(p: argparse.ArgumentParser) -> None:
    p.add_argument("source", type=Path, help="recording .mcap, folder of .ply/.pcd frames, or MCAP/bag")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="pipeline/mission override on the recorded config (pipeline.icp.max_iterations=10); "
                        "repeatable")
    p.add_argument("--mission", default=None,
                   help="mission YAML or name for real data (default: the recording's, else final_approach)")
    p.add_argument("--target", default=None, help="target library name or mesh file (real data)")
    p.add_argument("--topic", default=None, help="PointCloud2 topic of a foreign MCAP / ROS 2 bag")
    p.add_argument("--truth", type=Path, default=None, help="truth CSV t,x,y,z,qw,qx,qy,qz (T_sensor_target)")
    p.add_argument("--times", type=Path, default=None, help="timestamps CSV file,t for a folder")
    p.add_argument("--rate", type=float, default=None, metavar="HZ", help="frame rate when files carry no times")
    p.add_argument("--axes", choices=["optical", "ros"], default="optical",
                   help="point axes of real data: optical (+z boresight, +y down) or ros (+x forward, +z up)")
    p.add_argument("--seed-from-truth", action="store_true",
                   help="seed the first acquisition with the first truth pose (real data)")
    p.add_argument("--plot", type=Path, default=None, help="write errors, protection level and mode (PNG)")
    p.add_argument("--csv", type=Path, default=None, help="write per-frame errors (CSV)")
    p.add_argument("--force", action="store_true", help="replace existing --plot / --csv files")
    p.set_defaults(handler=run)


def _real_source(args: argparse.Namespace, overrides: dict) -> tuple:
    from agents.replay import real_data_items, resolve_replay_config
    from agents.replay_sources import clouds_from_mcap, load_folder, load_truth_csv, to_cloud
    from perception.sensing.sensors.tridar import TriDARSensor

    if args.target:
        overrides = {**overrides, "target__name": args.target}
    cfg = resolve_replay_config(None, args.mission or "final_approach",
                                {"env__perception": "tridar", **overrides})
    if args.source.is_dir():
        frames = load_folder(args.source, times=args.times, rate_hz=args.rate)
    else:
        frames = clouds_from_mcap(args.source, args.topic)
    if not frames:
        raise ValueError(f"{args.source}: no readable frames")
    sensor = TriDARSensor(cfg.sensor)
    clouds = [to_cloud(f, sensor, axes=args.axes) for f in frames]
    truth = load_truth_csv(args.truth) if args.truth else None
    seed = truth.at(frames[0].t, tol=1e9) if truth is not None and args.seed_from_truth else None
    if args.seed_from_truth and seed is None:
        raise ValueError("--seed-from-truth needs --truth")
    return real_data_items(clouds, [f.t for f in frames], truth, seed), cfg, False


def run(args: argparse.Namespace) -> int:
    import numpy as np
    from tqdm import tqdm

    from agents.benchmarks.timing import format_table
    from agents.commands.demo import parse_overrides
    from agents.replay import (
        load_recording,
        plot_errors,
        replay,
        resolve_replay_config,
        summary_rows,
    )
    from tridar_env.mcap_log import refuse_existing

    for out in (args.plot, args.csv):
        if out is not None:
            refuse_existing(out, args.force)
    overrides = parse_overrides(args.overrides)
    src = args.source
    if not src.exists():
        raise ValueError(f"{src}: no such file or folder")
    if src.is_dir() or args.topic:
        items, cfg, exact = _real_source(args, overrides)
    else:
        rec = load_recording(src)
        cfg = resolve_replay_config(rec.cfg, args.mission, overrides)
        items = rec.items
        exact = rec.cfg is not None and cfg.model_dump_json() == rec.cfg.model_dump_json()
    n = sum(1 for it in items if it.kind == "frame")
    with tqdm(total=n, unit="frame", desc=f"replay {src.name}", disable=n < 50) as bar:
        res = replay(items, cfg, exact=exact, on_frame=lambda i: bar.update(1))
    print(f"replay of {src}: {res.frames_offered} frames offered, {res.frames_processed} processed by "
          f"the pipeline ({'recorded settings' if exact else 'settings given here'})")
    if res.exact:
        print(f"state vectors bitwise equal to the live run: {res.bitwise_equal} of {res.compared}")
    e = res.errors()
    modes = np.bincount(e["mode"], minlength=3) if len(e["mode"]) else np.zeros(3, int)
    print(f"frames by published mode: bearing {modes[0]}, search {modes[1]}, tracking {modes[2]}; "
          f"valid pose {int(e['pose_valid'].sum())}")
    if any(T is not None for T in res.truth):
        print(format_table(summary_rows(res)))
        ok = np.isfinite(e["pos_err_m"]) & e["pose_valid"]
        over = int(np.sum(e["pos_err_m"][ok] > e["protection_level_m"][ok]))
        print(f"valid poses whose position error exceeds the protection level: {over} of {int(ok.sum())}")
    if args.plot is not None:
        print(f"plot: {plot_errors(res, args.plot, title=f'replay of {src.name}')}")
    if args.csv is not None:
        with open(args.csv, "w", newline="") as fh:
            w = csv.writer(fh)
            w.writerow(["t", "mode", "pose_valid", "pos_err_m", "att_err_deg", "protection_level_m"])
            for row in zip(e["t"], e["mode"], e["pose_valid"], e["pos_err_m"], e["att_err_deg"],
                           e["protection_level_m"]):
                w.writerow([repr(float(row[0])), int(row[1]), int(row[2]), *(repr(float(v)) for v in row[3:])])
        print(f"csv: {args.csv}")
    if res.exact and res.bitwise_equal != res.compared:
        return 1
    return 0
