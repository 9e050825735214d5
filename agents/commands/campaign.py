"""``tridar-env campaign CONFIG``: a Monte Carlo campaign on Dask (resumable)."""

from __future__ import annotations

import argparse
import contextlib
from collections.abc import Iterator
from pathlib import Path

from agents.cli import command


@command("campaign", "Monte Carlo campaign over dispersions on Dask (LocalCluster or --scheduler)")
def add(p: argparse.ArgumentParser) -> None:
    p.add_argument("config", help="campaign YAML (or a name in configs/campaigns)")
    p.add_argument("--out", type=Path, default=None,
                   help="results folder (default runs/campaigns/<name>); an existing one resumes "
                        "(a folder tridar-env did not create is refused unless empty)")
    p.add_argument("--scheduler", default=None,
                   help="address of a running Dask scheduler (tcp://host:port); "
                        "default: an embedded LocalCluster")
    p.add_argument("--workers", type=int, default=None,
                   help="LocalCluster worker processes (default: one per core)")
    p.add_argument("--serial", action="store_true", help="run in this process, no Dask")
    p.add_argument("--runs", type=int, default=None, help="override the number of runs")
    p.add_argument("--seed", type=int, default=None, help="override the campaign seed")
    p.add_argument("--perception", choices=["truth", "truth+noise", "tridar", "flash"], default=None,
                   help="override the perception mode")
    p.add_argument("--controller", default=None, help="override the controller name")
    p.add_argument("--max-steps", type=int, default=None, help="cap on steps per run")
    p.add_argument("--fresh", action="store_true",
                   help="discard results already in --out (only in a folder a campaign created)")
    p.add_argument("--retry-errors", action="store_true",
                   help="rerun runs whose stored outcome is 'error'")
    p.add_argument("--no-plots", action="store_true", help="skip the PNG plots")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--record", type=Path, default=None, metavar="DIR",
                   help="record every run to DIR/run-<index>.mcap (a new or empty folder, or one an "
                        "earlier --record made; with --serial or the embedded cluster)")
    p.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from agents.campaign import load_campaign, run_campaign

    overrides = {
        k: v for k, v in {
            "runs": args.runs, "seed": args.seed, "perception": args.perception,
            "controller": args.controller, "max_steps": args.max_steps,
        }.items() if v is not None
    }
    if args.workers is not None and args.workers < 1:
        raise ValueError(f"--workers={args.workers}; expected >= 1")
    cfg = load_campaign(args.config, **overrides)
    out = args.out or Path("runs") / "campaigns" / cfg.name
    with _recording(args.record, args.scheduler):
        res = run_campaign(
            cfg, out, scheduler=args.scheduler, workers=args.workers, serial=args.serial,
            fresh=args.fresh, retry_errors=args.retry_errors, progress=not args.no_progress,
            plots=not args.no_plots,
        )
    resumed = cfg.runs - len(res.ran) - res.failed_to_execute
    print(res.summary_table(
        f"campaign {cfg.name}: {len(res.ran)} runs now, {resumed} resumed from {out}"
    ))
    if not res.complete:
        print(f"{cfg.runs - len(res.table)} runs missing ({res.failed_to_execute} lost to failed "
              "workers); run the same command again to complete the campaign")
        return 1
    print(f"results: {out / 'results.parquet'}; plots: {', '.join(p.name for p in res.plots) or '-'}")
    return 0


_RECORD_MARKER = ".tridar-env-recordings"


@contextlib.contextmanager
def _recording(folder: Path | None, scheduler: str | None) -> Iterator[None]:
    """While inside, every run records into ``folder`` (None: no recording): the folder is
    claimed and named in an environment variable that this process's workers inherit; a folder
    tridar-env did not make is refused unless empty."""
    import os

    from agents.runner import RECORD_DIR_ENV

    if folder is None:
        yield
        return
    if scheduler:
        raise ValueError("--record writes on this machine; use it with --serial or the embedded "
                         "cluster, not --scheduler")
    if folder.exists() and not folder.is_dir():
        raise ValueError(f"--record {folder}: a file; expected a folder")
    if folder.is_dir() and any(folder.iterdir()) and not (folder / _RECORD_MARKER).exists():
        raise ValueError(f"--record {folder}: a folder tridar-env did not make and not empty; "
                         "expected a new or empty folder")
    folder.mkdir(parents=True, exist_ok=True)
    (folder / _RECORD_MARKER).touch()
    os.environ[RECORD_DIR_ENV] = str(folder.resolve())
    try:
        yield
    finally:
        os.environ.pop(RECORD_DIR_ENV, None)
