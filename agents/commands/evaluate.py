"""``tridar-env evaluate MODEL``: fly a saved policy for N episodes and print the summary table."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from agents.cli import command

#: Marker kind of an ``evaluate --out`` folder (:mod:`agents.outputs`).
KIND = "evaluate"


@command("evaluate", "run a saved SB3 policy for N episodes on any id and perception mode")
def add(p: argparse.ArgumentParser) -> None:
    p.add_argument("model", help="model.zip written by 'tridar-env train', or its run folder")
    p.add_argument("--env-id", default=None,
                   help="Gymnasium id (default: the one the policy was trained on)")
    p.add_argument("--perception", choices=["truth", "truth+noise", "tridar", "flash"], default="tridar",
                   help="perception mode to evaluate on (default: the full TriDAR pipeline)")
    p.add_argument("--episodes", type=int, default=20, help="number of episodes (default 20)")
    p.add_argument("--seed", type=int, default=0, help="evaluation seed (episode i: campaign seed rule)")
    p.add_argument("--max-steps", type=int, default=None, help="cap on steps per episode")
    p.add_argument("--workers", type=int, default=None,
                   help="run episodes on a Dask LocalCluster with this many processes")
    p.add_argument("--scheduler", default=None, help="or on a running Dask scheduler tcp://host:port")
    p.add_argument("--out", type=Path, default=None,
                   help="also write results.parquet and summary.json into this folder (new, "
                        "empty or written by evaluate before)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from agents.campaign import format_summary
    from agents.outputs import check_folder
    from agents.training import evaluate

    if args.out is not None:
        check_folder(args.out, KIND)  # refuse before the episodes are flown
    table, summary = evaluate(
        args.model, env_id=args.env_id, perception=args.perception, episodes=args.episodes,
        seed=args.seed, max_steps=args.max_steps, progress=not args.no_progress,
        workers=args.workers, scheduler=args.scheduler,
    )
    print(format_summary(summary, f"evaluate {args.model} on {args.env_id or 'its training id'} "
                                  f"(perception={args.perception}, seed={args.seed})"))
    if args.out is not None:
        write_results(args.out, table, summary)
        print(f"results: {args.out / 'results.parquet'}")
    return 0


def write_results(out: Path, table: Any, summary: dict[str, Any]) -> None:
    """``results.parquet`` and ``summary.json`` in ``out``, a folder evaluate created (or an
    empty one), each written atomically."""
    from agents.outputs import atomic_write, claim_folder, lock_folder

    claim_folder(out, KIND)
    with lock_folder(out):
        atomic_write(out / "results.parquet", lambda p: table.to_parquet(p, index=False))
        atomic_write(out / "summary.json",
                     lambda p: p.write_text(json.dumps(summary, indent=2) + "\n"))
