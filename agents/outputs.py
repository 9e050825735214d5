"""Output folders: a tool deletes or overwrites only what it created.

Every command that writes a results folder (``train``, ``campaign``, ``evaluate --out``, ``demo``,
``run``, ``check-target``) claims it with :func:`claim_folder`, which writes a marker file
(``.tridar-env-output``: the kind of folder, the time, host and pid that created it). A folder
without the marker is somebody else's: the commands refuse to write into it unless it is empty,
and ``--force`` / ``--fresh`` refuse to delete anything in it. Inside a marked folder, deletions
name the files the tool writes itself; nothing is removed by pattern-free ``rmtree``.

Also here: the plain-name check for a config ``name`` that becomes a folder name
(:func:`check_name`), an exclusive lock held while a process writes the folder
(:func:`lock_folder`), an atomic write that survives a crash (:func:`atomic_write`: temporary
file, fsync, rename, fsync of the folder) and the clean-up of temporary files left by dead
processes only (:func:`remove_stale_tmp`).
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import json
import math
import os
import re
import socket
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np

__all__ = [
    "LOCK_FILE",
    "MARKER_FILE",
    "OutputFolderError",
    "atomic_write",
    "check_folder",
    "check_name",
    "claim_folder",
    "fsync_dir",
    "is_marked",
    "json_safe",
    "lock_folder",
    "pid_alive",
    "read_marker",
    "remove_stale_tmp",
    "tmp_path",
]

MARKER_FILE = ".tridar-env-output"
LOCK_FILE = ".lock"
_NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,99}$")
# Temporary names written by atomic_write: ".<name>.<pid>.tmp" plus an optional extension.
_TMP_RE = re.compile(r"^\..+\.(\d+)\.tmp(\.[A-Za-z0-9]+)?$")


class OutputFolderError(ValueError):
    """An output folder the tool may not write, delete in, or share (one-line message)."""


def check_name(value: str, field: str = "name") -> str:
    """Refuse a config ``name`` that would not be a single plain folder name.

    Accepted: 1-100 characters, letters, digits, ``.``, ``_`` and ``-``, starting with a letter or
    digit (so no path separator, no ``..``, nothing absolute, nothing hidden).

    Raises:
        OutputFolderError: naming the field and the value.
    """
    if not isinstance(value, str) or not _NAME_RE.match(value):
        raise OutputFolderError(
            f"{field}={value!r} is not a plain folder name; expected 1-100 letters, digits, '.', "
            "'_' or '-' starting with a letter or digit (no '/', '..' or absolute path); "
            "pass --out DIR to write elsewhere"
        )
    return value


def read_marker(folder: str | Path) -> dict[str, Any] | None:
    """The marker of ``folder`` (a dict with at least ``kind``), or None when it has none."""
    p = Path(folder) / MARKER_FILE
    try:
        data = json.loads(p.read_text())
    except (OSError, ValueError):
        return None
    if not isinstance(data, dict) or data.get("tool") != "tridar-env" or "kind" not in data:
        return None
    return data


def is_marked(folder: str | Path) -> bool:
    """``folder`` was created by a tridar-env command."""
    return read_marker(folder) is not None


def check_folder(
    folder: str | Path, kind: str, *, destroy: str | None = None, new: bool = False
) -> bool:
    """Check, without writing anything, that a ``kind`` command may use ``folder``.

    Args:
        folder: the output folder (it need not exist).
        kind: what writes it (``campaign``, ``train``, ``evaluate``, ``report``, ...).
        destroy: the flag about to delete earlier results (``--fresh``, ``--force``), if any.
        new: the folder must not exist yet (a time-stamped report folder).

    Returns:
        True when ``folder`` exists and carries a ``kind`` marker.

    Raises:
        OutputFolderError: ``folder`` is a file, exists when ``new``, is a tridar-env folder of
            another kind, or is a non-empty folder that tridar-env did not create.
    """
    out = Path(folder)
    if not out.exists():
        return False
    if new:
        raise OutputFolderError(f"{out} already exists; wait a second or pass --out DIR")
    if not out.is_dir():
        raise OutputFolderError(f"{out} is not a folder; expected a {kind} output folder")
    marker = read_marker(out)
    if marker is not None:
        if marker["kind"] != kind:
            raise OutputFolderError(
                f"{out} is a tridar-env {marker['kind']} folder; expected a {kind} folder "
                "(choose another --out)"
            )
        return True
    if any(out.iterdir()):
        if destroy:
            raise OutputFolderError(
                f"{out} was not created by tridar-env (no {MARKER_FILE}); {destroy} deletes only "
                "in folders tridar-env created: choose another --out"
            )
        raise OutputFolderError(
            f"{out} is not empty and was not created by tridar-env (no {MARKER_FILE}); "
            "choose a new or empty folder with --out"
        )
    return False


def claim_folder(folder: str | Path, kind: str, *, new: bool = False) -> Path:
    """Create ``folder`` (or adopt an empty one) for ``kind`` and write its marker.

    A folder already marked for ``kind`` is returned as is.

    Raises:
        OutputFolderError: as :func:`check_folder` (``new``: it appeared meanwhile).
    """
    out = Path(folder)
    if check_folder(out, kind, new=new):
        return out
    try:
        out.mkdir(parents=True, exist_ok=not new)
    except FileExistsError:
        raise OutputFolderError(f"{out} already exists; wait a second or pass --out DIR") from None
    marker = {
        "tool": "tridar-env", "kind": kind, "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        "host": socket.gethostname(), "pid": os.getpid(), "version": _version(),
    }
    atomic_write(out / MARKER_FILE, lambda p: p.write_text(json.dumps(marker, indent=2) + "\n"))
    return out


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("tridar-env")
    except PackageNotFoundError:
        return "unknown"


@contextlib.contextmanager
def lock_folder(folder: str | Path) -> Iterator[Path]:
    """Hold an exclusive ``flock`` on ``folder/.lock`` for the duration of the block.

    The lock file stays (removing it would let two processes lock two different files); the
    lock itself dies with the process.

    Raises:
        OutputFolderError: another process holds the lock (its pid is named when known).
    """
    path = Path(folder) / LOCK_FILE
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as exc:
            if exc.errno not in (errno.EAGAIN, errno.EACCES, errno.EWOULDBLOCK):
                raise
            holder = os.pread(fd, 32, 0).decode(errors="replace").strip() or "unknown"
            raise OutputFolderError(
                f"{folder} is in use by another tridar-env process (pid {holder}); wait for it "
                "to finish or choose another --out"
            ) from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        yield path
    finally:
        os.close(fd)  # releases the lock


def tmp_path(path: Path, suffix: str = "") -> Path:
    """The temporary name of ``path`` for this process (``.<name>.<pid>.tmp<suffix>``)."""
    return path.with_name(f".{path.name}.{os.getpid()}.tmp{suffix}")


def fsync_dir(folder: str | Path) -> None:
    """Make the entries of ``folder`` (a rename, a new file) durable."""
    fd = os.open(folder, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def atomic_write(path: str | Path, write: Callable[[Path], Any], suffix: str = "") -> Path:
    """Write ``path`` through ``write(tmp)``: a crash leaves the old file or the new one.

    The temporary file (named by :func:`tmp_path`, ``suffix`` kept for writers that append an
    extension) is fsynced, renamed over ``path``, and the folder is fsynced.
    """
    p = Path(path)
    tmp = tmp_path(p, suffix)
    try:
        write(tmp)
        with open(tmp, "rb+") as f:
            os.fsync(f.fileno())
        os.replace(tmp, p)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    fsync_dir(p.parent)
    return p


def pid_alive(pid: int) -> bool:
    """A process with this id exists on this host."""
    if pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True  # somebody else's process
    return True


def remove_stale_tmp(folder: str | Path) -> list[Path]:
    """Delete the temporary files of :func:`atomic_write` in ``folder`` that this process wrote or
    whose process is gone; another live process's are left alone. Returns what was removed."""
    out = Path(folder)
    removed = []
    if not out.is_dir():
        return removed
    for p in out.iterdir():
        m = _TMP_RE.match(p.name)
        if m is None or not p.is_file():
            continue
        pid = int(m.group(1))
        if pid == os.getpid() or not pid_alive(pid):
            p.unlink(missing_ok=True)
            removed.append(p)
    return removed


def json_safe(o: Any) -> Any:
    """Plain JSON: numpy scalars to Python, NaN/inf to null (dicts, lists and tuples walked)."""
    if isinstance(o, dict):
        return {k: json_safe(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [json_safe(v) for v in o]
    if isinstance(o, np.generic):
        o = o.item()
    if isinstance(o, float) and not math.isfinite(o):
        return None
    return o
