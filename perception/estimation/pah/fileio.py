"""PAH database files: the ``.npz`` format, writing it, and reading files from untrusted hands.

Every entry of a file is checked before use (:func:`load_database`): each ``.npy`` header
(dtype, shape, size against the archive) before its data is read, so a hostile header cannot
make the loader allocate; then the values (finite, indices in range, the length table sorted and
consistent with the connectivity table, ``bin_ptr`` the exact offsets of the length bins). A file
that cannot be used raises :class:`PAHFileError` with one line naming the file.
"""

from __future__ import annotations

import json
import math
import zipfile
import zlib
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt
from pydantic import ValidationError

from perception.config import PAHConfig
from perception.targets import TargetModel

if TYPE_CHECKING:
    from .database import PAHDatabase

#: Version of the ``.npz`` layout written by :meth:`PAHDatabase.save`.
PAH_FORMAT_VERSION = 1

_ARRAY_KEYS = ("points", "normals", "seg_i", "seg_j", "seg_len", "bin_ptr", "dist")


class PAHFileError(ValueError):
    """A PAH database file that cannot be used; the message is one line naming the file."""


def save_database(db: PAHDatabase, path: str | Path) -> Path:
    """Write ``db`` to ``path`` (``.npz`` appended if missing; no pickles); returns the path."""
    p = Path(path)
    if p.suffix != ".npz":
        p = p.with_name(p.name + ".npz")
    p.parent.mkdir(parents=True, exist_ok=True)
    arrays = {k: getattr(db, k) for k in _ARRAY_KEYS}
    np.savez(
        p,
        format_version=np.int64(PAH_FORMAT_VERSION),
        model_hash=np.str_(db.model_hash),
        target_name=np.str_(db.target_name),
        config_json=np.str_(db.config.model_dump_json()),
        coverage_m=np.float64(db.coverage_m),
        **arrays,
    )
    return p


def load_database(
    cls: type[PAHDatabase], path: str | Path, target: TargetModel | None = None
) -> PAHDatabase:
    """Read a database written by :func:`save_database` (see :meth:`PAHDatabase.load`)."""
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"PAH database file {p} does not exist")
    meta, config, arrays = _read_database(p)
    db = cls(
        config=config, model_hash=meta["model_hash"], target_name=meta["target_name"],
        coverage_m=meta["coverage_m"], **arrays,
    )
    if target is not None:
        try:
            db.attach(target)
        except ValueError as exc:
            raise PAHFileError(f"PAH database {p}: {exc}") from None
    return db


#: Entries of a database file: name -> (accepted dtype kinds, number of dimensions).
_ENTRIES: dict[str, tuple[str, int]] = {
    "format_version": ("iu", 0), "model_hash": ("U", 0), "target_name": ("U", 0),
    "config_json": ("U", 0), "coverage_m": ("f", 0),
    "points": ("f", 2), "normals": ("f", 2), "seg_i": ("iu", 1), "seg_j": ("iu", 1),
    "seg_len": ("f", 1), "bin_ptr": ("iu", 1), "dist": ("f", 2),
}
_KIND_NAMES = {"iu": "an integer", "U": "a string", "f": "a float"}
# A deflated entry (``np.savez_compressed``) may claim at most this multiple of the archive's size
# once inflated: float tables compress less than 2x, a zip bomb claims 1000x.
_MAX_INFLATION = 64
_MAX_TEXT_CHARS = 1_000_000  # config JSON, target name, model hash


class _Archive:
    """The entries of an open ``.npz``; an entry's data is read only after its header passed."""

    def __init__(self, path: Path, zf: zipfile.ZipFile) -> None:
        self.path, self.zf = path, zf
        self.size = path.stat().st_size
        self.infos = {i.filename: i for i in zf.infolist()}

    def fail(self, name: str, problem: str) -> PAHFileError:
        return PAHFileError(f"PAH database {self.path} is corrupt: {name}: {problem}")

    def header(self, name: str) -> tuple[int, ...]:
        """The entry's shape, after its dtype, dimensions and size against the archive passed."""
        info = self.infos.get(f"{name}.npy")
        if info is None:
            raise self.fail(name, "no such entry")
        if info.flag_bits & 0x1:
            raise self.fail(name, "encrypted entry")
        if info.compress_type == zipfile.ZIP_STORED:
            if info.compress_size != info.file_size or info.file_size > self.size:
                raise self.fail(name, f"entry claims {info.file_size} bytes; the file has {self.size}")
        elif info.compress_type == zipfile.ZIP_DEFLATED:
            if info.file_size > _MAX_INFLATION * self.size:
                raise self.fail(name, f"entry claims {info.file_size} bytes inflated from a "
                                      f"{self.size}-byte file")
        else:
            raise self.fail(name, f"zip compression method {info.compress_type} not supported")
        try:
            with self.zf.open(info) as f:
                version = np.lib.format.read_magic(f)
                if version == (1, 0):
                    shape, _, dtype = np.lib.format.read_array_header_1_0(f)
                elif version == (2, 0):
                    shape, _, dtype = np.lib.format.read_array_header_2_0(f)
                else:
                    raise ValueError(f".npy format version {version} not supported")
                data_bytes = info.file_size - f.tell()
        except (ValueError, EOFError, OSError, zipfile.BadZipFile, zlib.error) as exc:
            raise self.fail(name, f"unreadable .npy header ({_one_line(exc)})") from None
        kinds, ndim = _ENTRIES[name]
        if dtype.kind not in kinds or dtype.hasobject or dtype.fields or dtype.subdtype:
            raise self.fail(name, f"dtype {dtype}; expected {_KIND_NAMES[kinds]} dtype")
        if len(shape) != ndim:
            raise self.fail(name, f"shape {shape}; expected {ndim} dimensions")
        nbytes = math.prod(shape) * dtype.itemsize
        if nbytes > data_bytes:
            raise self.fail(name, f"header claims shape {shape} of {dtype} ({nbytes} bytes); the "
                                  f"entry holds {data_bytes} bytes")
        return shape

    def read(self, name: str) -> np.ndarray:
        """The entry's array (call :meth:`header` first)."""
        try:
            with self.zf.open(self.infos[f"{name}.npy"]) as f:
                return np.lib.format.read_array(f, allow_pickle=False)
        except (ValueError, EOFError, OSError, zipfile.BadZipFile, zlib.error) as exc:
            raise self.fail(name, f"unreadable data ({_one_line(exc)})") from None

    def scalar(self, name: str) -> np.generic:
        self.header(name)
        return self.read(name)[()]


def _one_line(exc: BaseException) -> str:
    """An exception's message on one line (pydantic's errors as ``field: message; ...``)."""
    if isinstance(exc, ValidationError):
        return "; ".join(
            f"{'.'.join(map(str, e['loc'])) or 'config'}: {e['msg']}" for e in exc.errors()
        )
    return " ".join(str(exc).split()) or type(exc).__name__


def _read_database(p: Path) -> tuple[dict, PAHConfig, dict[str, np.ndarray]]:
    """Metadata, settings and arrays of a database file, every one checked (PAHFileError)."""
    try:
        zf = zipfile.ZipFile(p)
    except (zipfile.BadZipFile, EOFError, ValueError) as exc:  # OSError (permissions) propagates
        raise PAHFileError(f"PAH database {p} is not a .npz archive ({_one_line(exc)})") from None
    with zf:
        ar = _Archive(p, zf)
        if "format_version.npy" not in ar.infos:
            raise PAHFileError(f"PAH database {p}: no format_version entry; not a PAH database")
        version = int(ar.scalar("format_version"))
        if version != PAH_FORMAT_VERSION:
            raise PAHFileError(
                f"PAH database {p}: format version {version}; this code reads version "
                f"{PAH_FORMAT_VERSION}"
            )
        meta: dict = {}
        for k in ("model_hash", "target_name", "config_json"):
            text = str(ar.scalar(k))
            if len(text) > _MAX_TEXT_CHARS:
                raise ar.fail(k, f"{len(text)} characters; expected <= {_MAX_TEXT_CHARS}")
            if k != "config_json" and not text.isprintable():
                raise ar.fail(k, f"{text!r} has non-printable characters")
            meta[k] = text
        try:
            config = PAHConfig.model_validate(json.loads(meta.pop("config_json")))
        except (ValueError, RecursionError) as exc:  # bad JSON, pydantic's ValidationError
            raise ar.fail("config_json", _one_line(exc)) from None
        meta["coverage_m"] = float(ar.scalar("coverage_m"))
        shapes = {k: ar.header(k) for k in _ARRAY_KEYS}
        m = shapes["points"][0]
        n = m * (m - 1) // 2
        expected = {"points": (m, 3), "normals": (m, 3), "seg_i": (n,), "seg_j": (n,),
                    "seg_len": (n,), "dist": (m, m)}
        if m < 3:
            raise ar.fail("points", f"{m} points; a database has >= 3")
        for k, shape in expected.items():
            if shapes[k] != shape:
                raise ar.fail(k, f"shape {shapes[k]}; expected {shape} for {m} points")
        if shapes["bin_ptr"][0] < 2:
            raise ar.fail("bin_ptr", f"{shapes['bin_ptr'][0]} offsets; expected >= 2")
        arrays = {k: ar.read(k) for k in _ARRAY_KEYS}
    _check_values(ar, arrays, config, meta["coverage_m"])
    return meta, config, arrays


def _first(mask: npt.NDArray[np.bool_]) -> int:
    return int(np.flatnonzero(mask.reshape(-1))[0])


def _check_values(
    ar: _Archive, a: dict[str, np.ndarray], config: PAHConfig, coverage_m: float
) -> None:
    """Ranges, order and consistency of the arrays (shapes and dtypes already checked); converts
    the index arrays to int64 and the tables to C-ordered float64 in place (no-ops on a file
    :meth:`PAHDatabase.save` wrote)."""
    m, n = a["points"].shape[0], a["seg_len"].shape[0]
    for k in ("points", "normals", "seg_len", "dist"):
        bad = ~np.isfinite(a[k])
        if bad.any():
            raise ar.fail(k, f"non-finite value at flat index {_first(bad)}")
        a[k] = np.ascontiguousarray(a[k], dtype=np.float64)
    for k, hi in (("seg_i", m), ("seg_j", m), ("bin_ptr", n + 1)):
        bad = (a[k] < 0) | (a[k] >= hi)
        if bad.any():
            i = _first(bad)
            raise ar.fail(k, f"{k}[{i}]={a[k][i]} out of range [0, {hi})")
        a[k] = np.ascontiguousarray(a[k], dtype=np.int64)
    si, sj, seg_len, dist, bp = a["seg_i"], a["seg_j"], a["seg_len"], a["dist"], a["bin_ptr"]
    if np.any(si >= sj):
        i = _first(si >= sj)
        raise ar.fail("seg_j", f"segment {i} has j={sj[i]} <= i={si[i]}; expected i < j")
    if np.unique(si * m + sj).size != n:
        raise ar.fail("seg_i", "a segment appears twice; expected every pair of points once")
    if np.any(dist < 0) or np.any(np.diagonal(dist) != 0) or not np.array_equal(dist, dist.T):
        raise ar.fail("dist", "not a distance table (negative, non-zero diagonal or asymmetric)")
    down = np.diff(seg_len) < 0
    if down.any():
        i = _first(down)
        raise ar.fail("seg_len", f"not sorted: seg_len[{i}]={seg_len[i]:.6g} > "
                                 f"seg_len[{i + 1}]={seg_len[i + 1]:.6g}")
    if not np.allclose(seg_len, dist[si, sj]):
        raise ar.fail("seg_len", "length table inconsistent with the connectivity table dist")
    if bp[0] != 0 or bp[-1] != n:
        raise ar.fail("bin_ptr", f"runs from {bp[0]} to {bp[-1]}; expected 0 to {n} (segments)")
    down = np.diff(bp) < 0
    if down.any():
        i = _first(down)
        raise ar.fail("bin_ptr", f"decreasing: bin_ptr[{i}]={bp[i]} > bin_ptr[{i + 1}]={bp[i + 1]}")
    b = config.length_bin_m
    with np.errstate(over="ignore"):
        n_bins = seg_len[-1] / b
    if not (math.isfinite(n_bins) and math.floor(n_bins) + 2 == bp.size):
        raise ar.fail("bin_ptr", f"{bp.size} offsets; {seg_len[-1]:.6g} m in bins of {b} m "
                                 f"needs {n_bins + 2:.0f}")
    # The offsets exactly as build computes them from the sorted lengths.
    want = np.searchsorted(seg_len, np.arange(bp.size) * b, side="left")
    want[-1] = n
    if not np.array_equal(bp, want):
        i = _first(bp != want)
        raise ar.fail("bin_ptr", f"bin_ptr[{i}]={bp[i]}; the segment lengths put {want[i]} there")
    if not 0.0 <= coverage_m <= seg_len[-1]:
        raise ar.fail("coverage_m", f"{coverage_m}; expected 0 to the longest segment "
                                    f"{seg_len[-1]:.6g} m")
