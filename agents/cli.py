"""The ``tridar-env`` command line.

Each subcommand lives in its own module under :mod:`agents.commands` and registers itself with
:func:`command`; heavy imports happen inside the handlers so that ``tridar-env --help`` stays fast.

Every failure a user can cause ends in one line on stderr and a non-zero exit code: 2 for bad
input (a config, a file, a value; a refused pickle, a broken zip, an unreadable path, memory
exhausted by what the input asked for), 130 for Ctrl-C, 143 for SIGTERM (raised in the main
thread as an interrupt, so worker pools shut down through their ``finally`` blocks), 1 with an
"internal error" line for anything else. ``--debug`` (anywhere on the line) shows the traceback.
A warning prints as one line too, ``tridar-env CMD: warning: ...``, not Python's two lines of
source path and code (``--debug`` keeps Python's format).
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import os
import pickle
import pkgutil
import signal
import sys
import threading
import traceback
import warnings
import zipfile
from collections.abc import Callable, Iterator, Sequence

from perception.config import ConfigError

AddFn = Callable[[argparse.ArgumentParser], None]

#: name -> (help text, function adding arguments and ``set_defaults(handler=...)``)
COMMANDS: dict[str, tuple[str, AddFn]] = {}

EXIT_BAD_INPUT = 2
EXIT_INTERRUPTED = 130
EXIT_TERMINATED = 128 + signal.SIGTERM
EXIT_BROKEN_PIPE = 128 + 13
# The longest error line printed; a message quoting a whole file is cut, not the user's screen.
_MAX_MESSAGE = 1000

#: Failures of the input, not of the program: (exception types, what the line says before the
#: message; "" when the message says it all).
_BAD_INPUT: tuple[tuple[tuple[type[BaseException], ...], str], ...] = (
    ((pickle.UnpicklingError,), "refused to unpickle"),
    ((zipfile.BadZipFile,), "not a valid zip file"),
    ((UnicodeError,), "not text in the expected encoding"),
    ((MemoryError,), "out of memory"),
    ((ConfigError, ValueError, OSError, EOFError), ""),
)


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised in the main thread: code that cleans up after Ctrl-C cleans up after it."""


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
    _add_debug_flag(parser, default=False, seen=set())
    return parser


def _add_debug_flag(parser: argparse.ArgumentParser, default: object, seen: set[int]) -> None:
    """``--debug`` on the parser and every subcommand's (nested ones too), so it may follow
    the command; the subparsers' default is SUPPRESS so they do not reset an earlier one."""
    if id(parser) in seen:
        return
    seen.add(id(parser))
    parser.add_argument("--debug", action="store_true", default=default,
                        help="on an error, show the full traceback instead of one line")
    for action in parser._actions:  # argparse has no public walk of its subparsers
        if isinstance(action, argparse._SubParsersAction):
            for sp in action.choices.values():
                _add_debug_flag(sp, argparse.SUPPRESS, seen)


def one_line(exc: BaseException) -> str:
    """The exception's message as one line: non-empty lines joined (a line ending in ':' by a
    space, others by ' | '), at most ``_MAX_MESSAGE`` characters; the type name if empty.

    A refused pickle keeps only the line naming what it tried to load (torch's message starts
    with advice on how to load the file anyway, the opposite of what this CLI wants).
    """
    lines = [ln.strip() for ln in str(exc).splitlines() if ln.strip()]
    if isinstance(exc, pickle.UnpicklingError):
        lines = _pickle_reason(lines)
    text = ""
    for ln in lines:
        text += ln if not text else (" " if text.endswith(":") else " | ") + ln
    if isinstance(exc, OSError) and not isinstance(exc, FileNotFoundError) and exc.filename:
        text = text if str(exc.filename) in text else f"{text}: {exc.filename}"
    if len(text) > _MAX_MESSAGE:
        text = text[: _MAX_MESSAGE - 3] + "..."
    return text or type(exc).__name__


def _pickle_reason(lines: list[str]) -> list[str]:
    named = [ln for ln in lines if "global" in ln.lower()]
    if named:
        return [f"the file holds pickled Python objects, not plain weights ({named[0]})"]
    if not lines or lines[0].startswith("Weights only load failed"):
        return ["the file holds pickled Python objects, not plain weights"]
    return lines[:1]


@contextlib.contextmanager
def _sigterm_as_interrupt() -> Iterator[list[bool]]:
    """While inside, SIGTERM raises :class:`Terminated` in the main thread (once: a second
    SIGTERM kills at once); yields a flag list that holds True once SIGTERM arrived."""
    got: list[bool] = []
    if threading.current_thread() is not threading.main_thread():
        yield got  # signals can only be handled in the main thread
        return

    def handler(signum: int, frame: object) -> None:
        got.append(True)
        signal.signal(signal.SIGTERM, signal.SIG_DFL)
        raise Terminated

    previous = signal.signal(signal.SIGTERM, handler)
    try:
        yield got
    finally:
        signal.signal(signal.SIGTERM, previous)


def _quiet_broken_pipe() -> None:
    """After stdout's reader went away (``| head``): no second error while Python flushes it."""
    with contextlib.suppress(OSError, ValueError):
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())


@contextlib.contextmanager
def _one_line_warnings(name: Callable[[], str], debug: bool) -> Iterator[None]:
    """While inside, a printed warning is one line naming the command (formatting only: code
    that records warnings, ``pytest.warns`` included, still gets the warning objects)."""
    if debug:
        yield
        return
    previous = warnings.formatwarning

    def fmt(message: Warning | str, category: type[Warning], filename: str, lineno: int,
            line: str | None = None) -> str:
        text = one_line(message if isinstance(message, Warning) else category(str(message)))
        return f"{name()}: warning: {text}\n"

    warnings.formatwarning = fmt
    try:
        yield
    finally:
        warnings.formatwarning = previous


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the console script; returns the process exit code."""
    argv = list(sys.argv[1:] if argv is None else argv)
    name, debug = "tridar-env", "--debug" in argv  # until the arguments are parsed
    with _sigterm_as_interrupt() as terminated, _one_line_warnings(lambda: name, debug):
        try:
            parser = build_parser()
            args = parser.parse_args(argv)
            name, debug = f"tridar-env {args.command}", bool(getattr(args, "debug", False))
            handler: Callable[[argparse.Namespace], int] | None = getattr(args, "handler", None)
            if handler is None:
                parser.print_help()
                return 0
            code = int(handler(args) or 0)
            if terminated:  # the handler caught the interrupt and wound up itself
                print(f"{name}: terminated (SIGTERM)", file=sys.stderr)
                return EXIT_TERMINATED
            return code
        except KeyboardInterrupt:
            if debug:
                traceback.print_exc()
            if terminated:
                print(f"{name}: terminated (SIGTERM)", file=sys.stderr)
                return EXIT_TERMINATED
            print(f"{name}: interrupted", file=sys.stderr)
            return EXIT_INTERRUPTED
        except SystemExit:
            raise  # argparse's usage errors and --help, and any handler's own exit
        except BrokenPipeError:
            _quiet_broken_pipe()
            return EXIT_BROKEN_PIPE
        except Exception as exc:  # noqa: BLE001  (each failure is one line; --debug for more)
            return _report(name, exc, debug)


def _report(name: str, exc: BaseException, debug: bool) -> int:
    """Print the failure (its traceback with ``--debug``, else one line); the exit code."""
    if debug:
        traceback.print_exc()
    for types, what in _BAD_INPUT:
        if isinstance(exc, types):
            if not debug:
                msg = one_line(exc)
                print(f"{name}: error: {what + ': ' if what else ''}{msg}", file=sys.stderr)
            return EXIT_BAD_INPUT
    if not debug:
        print(f"{name}: internal error: {type(exc).__name__}: {one_line(exc)} "
              "(rerun with --debug for the traceback)", file=sys.stderr)
    return 1


if __name__ == "__main__":  # pragma: no cover
    # Run the registry of the importable module (subcommands register on ``agents.cli``,
    # not on ``__main__``), so ``python -m agents.cli`` sees every command.
    from agents.cli import main as _main

    raise SystemExit(_main())
