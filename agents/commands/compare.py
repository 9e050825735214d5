"""``tridar-env compare DIR DIR [...]``: campaigns side by side, run for run."""

from __future__ import annotations

import argparse
from pathlib import Path

from agents.cli import command


@command("compare", "campaigns side by side on the same dispersed runs (e.g. TriDAR vs flash): "
                    "docked, error by range, cost, runs on which they disagree")
def add(p: argparse.ArgumentParser) -> None:
    p.add_argument("folders", nargs="+", type=Path, help="campaign result folders (two or more)")
    p.add_argument("--labels", nargs="+", default=None, help="a name for each folder (default: its name)")
    p.add_argument("--bins", nargs="+", type=float, default=None,
                   help="range bin edges [m] of the error table (default 0 5 10 20 40 80)")
    p.add_argument("--plot", type=Path, default=None, metavar="FILE.png",
                   help="also draw the position error against range to a new PNG file")
    p.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from agents.campaign_compare import DEFAULT_BINS, compare, plot_error_vs_range, read_campaign

    if args.labels is not None and len(args.labels) != len(args.folders):
        raise ValueError(f"--labels: {len(args.labels)} names for {len(args.folders)} folders; "
                         "expected one per folder")
    labels = args.labels or [None] * len(args.folders)
    if args.plot is not None and args.plot.exists():
        raise ValueError(f"--plot {args.plot}: exists; expected a new file (nothing is overwritten)")
    runs = [read_campaign(f, lab) for f, lab in zip(args.folders, labels)]
    result = compare(runs, args.bins if args.bins is not None else DEFAULT_BINS)
    print(result.format())
    if args.plot is not None:
        print(f"plot: {plot_error_vs_range(runs, args.plot)}")
    return 0
