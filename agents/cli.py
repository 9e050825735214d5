"""The ``tridar-env`` command line.

Each subcommand lives in its own module under :mod:`agents.commands` and registers itself with
:func:`command`; heavy imports happen inside the handlers so that ``tridar-env --help`` stays fast.
"""

from __future__ import annotations

import argparse
import importlib
import pkgutil
import sys
from collections.abc import Callable, Sequence

from perception.config import ConfigError

AddFn = Callable[[argparse.ArgumentParser], None]

#: name -> (help text, function adding arguments and ``set_defaults(handler=...)``)
COMMANDS: dict[str, tuple[str, AddFn]] = {}


def command(name: str, help_text: str) -> Callable[[AddFn], AddFn]:
    """Register ``add(parser)`` as subcommand ``name``; ``add`` sets ``handler`` via set_defaults."""

    def wrap(add: AddFn) -> AddFn:
        COMMANDS[name] = (help_text, add)
        return add

    return wrap


def build_parser() -> argparse.ArgumentParser:
    from agents import commands

    for info in sorted(pkgutil.iter_modules(commands.__path__), key=lambda m: m.name):
        importlib.import_module(f"{commands.__name__}.{info.name}")
    parser = argparse.ArgumentParser(
        prog="tridar-env",
        description="Spacecraft rendezvous and docking through a simulated TriDAR 3D vision system.",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, (help_text, add) in COMMANDS.items():
        add(sub.add_parser(name, help=help_text, description=help_text))
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the console script; returns the process exit code."""
    parser = build_parser()
    args = parser.parse_args(argv)
    handler: Callable[[argparse.Namespace], int] | None = getattr(args, "handler", None)
    if handler is None:
        parser.print_help()
        return 0
    try:
        return int(handler(args) or 0)
    except (ConfigError, FileNotFoundError, ValueError) as exc:
        print(f"tridar-env {args.command}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":  # pragma: no cover
    # Run the registry of the importable module (subcommands register on ``agents.cli``,
    # not on ``__main__``), so ``python -m agents.cli`` sees every command.
    from agents.cli import main as _main

    raise SystemExit(_main())
