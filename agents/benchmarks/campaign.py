"""Campaign throughput: runs/minute on a Dask LocalCluster against a serial loop.

The same runs (same campaign seed and dispersions) are flown twice: in a plain loop in this
process, then on an embedded LocalCluster with one single-threaded worker process per core. The
ratio should approach the number of workers when runs are long compared to Dask's per-task
overhead. The rows of both must be identical (the seed rule makes a run a function of
``(campaign seed, index)`` only); the table says so.
"""

from __future__ import annotations

import argparse
import os
import time

from agents.benchmarks.timing import format_table


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--runs", type=int, default=8, help="runs per executor (default 8)")
    p.add_argument("--workers", type=int, default=None, help="LocalCluster workers (default: cores)")
    p.add_argument("--env-id", default="TriDAR/FinalApproach-v0")
    p.add_argument("--perception", default="truth+noise", choices=["truth", "truth+noise", "tridar"])
    p.add_argument("--controller", default="glideslope")
    p.add_argument("--max-steps", type=int, default=400, help="cap on steps per run (default 400)")
    p.add_argument("--seed", type=int, default=0)


def _warm_up() -> None:
    import agents.controllers
    import agents.episode  # noqa: F401
    import tridar_env  # noqa: F401


def run(args: argparse.Namespace) -> int:
    import pandas as pd

    from agents.campaign import (
        CampaignConfig,
        build_specs,
        iter_results,
        open_client,
        validate_campaign,
    )

    if args.runs < 1:
        raise ValueError(f"--runs={args.runs}; expected >= 1")
    cfg = CampaignConfig(
        name="bench", env_id=args.env_id, perception=args.perception, controller=args.controller,
        runs=args.runs, seed=args.seed, max_steps=args.max_steps,
        dispersions={"env__initial__range_m": {"uniform": [10.0, 30.0]},
                     "env__initial__lateral_dispersion_m": {"uniform": [0.0, 1.0]}},
    )
    validate_campaign(cfg, "bench")
    specs = build_specs(cfg)
    workers = args.workers or os.cpu_count() or 1

    t0 = time.perf_counter()
    serial = list(iter_results(specs))
    t_serial = time.perf_counter() - t0

    t0 = time.perf_counter()
    with open_client(None, workers) as client:
        client.run(_warm_up)  # imports in every worker: start-up cost, not per-run throughput
        t_start = time.perf_counter() - t0
        t1 = time.perf_counter()
        dask_rows = list(iter_results(specs, client))
        t_dask = time.perf_counter() - t1

    def frame(rows: list[dict]) -> pd.DataFrame:
        return pd.DataFrame(rows).drop(columns=["wall_time_s"]).sort_values("index").reset_index(drop=True)

    same = frame(serial).equals(frame(dask_rows))
    steps = sum(int(r.get("steps", 0) or 0) for r in serial)
    # Sum of per-run times: equal in both columns on an idle machine; larger on the cluster when
    # other processes compete for the cores (then the ratio understates the scaling).
    busy_serial = sum(r["wall_time_s"] for r in serial)
    busy_dask = sum(r["wall_time_s"] for r in dask_rows)
    rows = [
        {"executor": "serial loop", "workers": 1, "runs": len(serial), "wall [s]": t_serial,
         "runs/min": 60.0 * len(serial) / t_serial, "ratio": 1.0, "run time sum [s]": busy_serial, "same rows": "-"},
        {"executor": "LocalCluster", "workers": workers, "runs": len(dask_rows), "wall [s]": t_dask,
         "runs/min": 60.0 * len(dask_rows) / t_dask, "ratio": t_serial / t_dask,
         "run time sum [s]": busy_dask, "same rows": "yes" if same else "NO"},
        {"executor": "LocalCluster incl. start-up", "workers": workers, "runs": len(dask_rows),
         "wall [s]": t_dask + t_start, "runs/min": 60.0 * len(dask_rows) / (t_dask + t_start),
         "ratio": t_serial / (t_dask + t_start), "run time sum [s]": busy_dask,
         "same rows": "yes" if same else "NO"},
    ]
    print(f"campaign throughput: {args.env_id}, perception={args.perception}, "
          f"controller={args.controller}, {len(specs)} runs, {steps} env steps, "
          f"max {args.max_steps} steps/run")
    print(format_table(rows))
    return 0 if same else 1
