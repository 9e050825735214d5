"""``tridar-env evaluate MODEL``: fly a saved policy for N episodes and print the summary table."""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path

from agents.cli import command


@command("evaluate", "run a saved SB3 policy for N episodes on any id and perception mode")
def add(p: argparse.ArgumentParser) -> None:
    p.add_argument("model", help="model.zip written by 'tridar-env train', or its run folder")
    p.add_argument("--env-id", default=None,
                   help="Gymnasium id (default: the one the policy was trained on)")
    p.add_argument("--perception", choices=["truth", "truth+noise", "tridar"], default="tridar",
                   help="perception mode to evaluate on (default: the full TriDAR pipeline)")
    p.add_argument("--episodes", type=int, default=20, help="number of episodes (default 20)")
    p.add_argument("--seed", type=int, default=0, help="evaluation seed (episode i: campaign seed rule)")
    p.add_argument("--max-steps", type=int, default=None, help="cap on steps per episode")
    p.add_argument("--workers", type=int, default=None,
                   help="run episodes on a Dask LocalCluster with this many processes")
    p.add_argument("--scheduler", default=None, help="or on a running Dask scheduler tcp://host:port")
    p.add_argument("--out", type=Path, default=None,
                   help="also write results.parquet and summary.json into this folder")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from agents.campaign import format_summary
    from agents.training import evaluate

    table, summary = evaluate(
        args.model, env_id=args.env_id, perception=args.perception, episodes=args.episodes,
        seed=args.seed, max_steps=args.max_steps, progress=not args.no_progress,
        workers=args.workers, scheduler=args.scheduler,
    )
    print(format_summary(summary, f"evaluate {args.model} on {args.env_id or 'its training id'} "
                                  f"(perception={args.perception}, seed={args.seed})"))
    if args.out is not None:
        args.out.mkdir(parents=True, exist_ok=True)
        tmp = args.out / f".results.parquet.{os.getpid()}.tmp"
        table.to_parquet(tmp, index=False)
        os.replace(tmp, args.out / "results.parquet")
        (args.out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
        print(f"results: {args.out / 'results.parquet'}")
    return 0
