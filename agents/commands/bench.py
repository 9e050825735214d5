"""``tridar-env bench NAME``: run one benchmark script and print its table."""

from __future__ import annotations

import argparse
import importlib
import pkgutil

from agents.cli import command


def _benchmarks() -> list[str]:
    from agents import benchmarks

    return sorted(
        m.name for m in pkgutil.iter_modules(benchmarks.__path__) if m.name not in {"timing"}
    )


@command("bench", "run a benchmark (prints median, p90 and ratio to a peer in the same process)")
def add(p: argparse.ArgumentParser) -> None:
    sub = p.add_subparsers(dest="bench", metavar="NAME")
    for name in _benchmarks():
        mod = importlib.import_module(f"agents.benchmarks.{name}")
        sp = sub.add_parser(name, help=(mod.__doc__ or name).strip().splitlines()[0])
        mod.add_arguments(sp)
        sp.set_defaults(handler=mod.run)
    p.set_defaults(handler=lambda a: (p.print_help(), 0)[1])
