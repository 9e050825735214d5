"""``tridar-env view FILE.mcap``: a recording in the rerun 3D viewer (the ``view`` extra).

Opens a viewer window, or with ``--save FILE.rrd`` writes the viewer's file without a window
(``rerun FILE.rrd`` shows it later). What is shown: :mod:`agents.viewer`.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from agents.cli import command


@command("view", "show a recording in the rerun 3D viewer (or --save FILE.rrd without a window)")
def add(p: argparse.ArgumentParser) -> None:
    p.add_argument("recording", type=Path, help="a tridar-env recording (.mcap)")
    p.add_argument("--save", type=Path, default=None, metavar="FILE.rrd",
                   help="write the viewer's file instead of opening a window")
    p.add_argument("--force", action="store_true", help="replace an existing --save file")
    p.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from agents.viewer import view

    if not args.recording.is_file():
        raise ValueError(f"{args.recording}: no such recording file")
    counts = view(args.recording, args.save, force=args.force)
    what = f"{sum(counts.values())} entries on {len(counts)} entities"
    print(f"{args.save}: {what}" if args.save else f"viewer: {what}")
    return 0
