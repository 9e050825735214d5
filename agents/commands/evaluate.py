"""``tridar-env evaluate MODEL``: fly a saved policy for N episodes and print the summary table.

``tridar-env evaluate --table SPEC``: the baseline table of :mod:`agents.baseline_table` (every row
of SPEC on each of its perceptions, one Markdown table).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from agents.cli import command

#: Marker kind of an ``evaluate --out`` folder (:mod:`agents.outputs`).
KIND = "evaluate"
# The model form's defaults (None in the parser: with --table, a given value overrides the spec).
_PERCEPTION, _EPISODES, _SEED = "tridar", 20, 0


@command("evaluate", "run a saved SB3 policy for N episodes on any id and perception mode")
def add(p: argparse.ArgumentParser) -> None:
    p.add_argument("model", nargs="?", default=None,
                   help="model.zip written by 'tridar-env train', or its run folder (or --table SPEC)")
    p.add_argument("--table", type=Path, default=None, metavar="SPEC",
                   help="instead of MODEL: the baseline table of a spec YAML (e.g. "
                        "configs/baselines.yaml), every row on each of its perceptions")
    p.add_argument("--only", type=int, action="append", default=None, metavar="ROW",
                   help="with --table: only row ROW of the spec (counted from 0; repeatable)")
    p.add_argument("--env-id", default=None,
                   help="Gymnasium id (default: the one the policy was trained on)")
    p.add_argument("--perception", choices=["truth", "truth+noise", "tridar", "flash"], default=None,
                   help="perception mode to evaluate on (default: the full TriDAR pipeline; with "
                        "--table: only this one of the rows' perceptions)")
    p.add_argument("--episodes", type=int, default=None,
                   help=f"number of episodes (default {_EPISODES}; with --table: replaces the spec's)")
    p.add_argument("--seed", type=int, default=None,
                   help=f"evaluation seed (episode i: campaign seed rule; default {_SEED}; with "
                        "--table: replaces the spec's)")
    p.add_argument("--max-steps", type=int, default=None, help="cap on steps per episode")
    p.add_argument("--workers", type=int, default=None,
                   help="run episodes on a Dask LocalCluster with this many processes")
    p.add_argument("--scheduler", default=None, help="or on a running Dask scheduler tcp://host:port")
    p.add_argument("--out", type=Path, default=None,
                   help="also write results.parquet and summary.json (--table: table.md and "
                        "rows.json) into this folder (new, empty or written by evaluate before)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    if args.model is not None and args.table is not None:
        raise ValueError(f"got MODEL {args.model!r} and --table {str(args.table)!r}; expected one "
                         "of them: a policy to evaluate, or a baseline spec")
    if args.model is None and args.table is None:
        raise ValueError("no MODEL and no --table; expected a model.zip (or its run folder) or "
                         "--table SPEC (e.g. configs/baselines.yaml)")
    if args.table is not None:
        return run_table(args)
    if args.only is not None:
        raise ValueError(f"--only {args.only[0]} selects rows of a --table spec; expected it with "
                         "--table SPEC, not with MODEL")
    return run_model(args)


def run_model(args: argparse.Namespace) -> int:
    from agents.campaign import format_summary
    from agents.outputs import check_folder
    from agents.training import evaluate

    perception = args.perception or _PERCEPTION
    seed = _SEED if args.seed is None else args.seed
    if args.out is not None:
        check_folder(args.out, KIND)  # refuse before the episodes are flown
    table, summary = evaluate(
        args.model, env_id=args.env_id, perception=perception,
        episodes=_EPISODES if args.episodes is None else args.episodes, seed=seed,
        max_steps=args.max_steps, progress=not args.no_progress, workers=args.workers,
        scheduler=args.scheduler,
    )
    print(format_summary(summary, f"evaluate {args.model} on {args.env_id or 'its training id'} "
                                  f"(perception={perception}, seed={seed})"))
    if args.out is not None:
        write_results(args.out, table, summary)
        print(f"results: {args.out / 'results.parquet'}")
    return 0


def run_table(args: argparse.Namespace) -> int:
    from agents import baseline_table as bt
    from agents.outputs import check_folder

    if args.env_id is not None:
        raise ValueError(f"--env-id {args.env_id!r} with --table; expected the env ids in the spec "
                         "(select rows with --only ROW)")
    for flag, value in (("--episodes", args.episodes), ("--max-steps", args.max_steps)):
        if value is not None and value < 1:
            raise ValueError(f"{flag}={value}; expected >= 1")
    if args.seed is not None and args.seed < 0:
        raise ValueError(f"--seed={args.seed}; expected >= 0")
    spec = bt.load_spec(args.table)
    bt.select(spec, args.only, args.perception)  # refuse a bad selection before anything runs
    if args.out is not None:
        check_folder(args.out, KIND)
    lines = bt.run_table(
        spec, args.table, only=args.only, perception=args.perception, episodes=args.episodes,
        seed=args.seed, max_steps=args.max_steps, progress=not args.no_progress,
        workers=args.workers, scheduler=args.scheduler,
    )
    markdown = bt.format_markdown(lines)
    print(markdown)
    if args.out is not None:
        bt.write_table(args.out, KIND, markdown, bt.rows_document(lines, spec, args.table))
        print(f"table: {args.out / 'table.md'}; rows: {args.out / 'rows.json'}")
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
