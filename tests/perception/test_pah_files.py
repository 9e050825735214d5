"""PAH database files from careless or hostile hands (issue 17).

Every damaged file is refused with one line naming the file (:class:`PAHFileError`, a ValueError),
never an IndexError, TypeError or MemoryError, and never loaded as valid; harmless changes (narrower
integer dtypes, compression, extra entries) still load, to the same tables.
"""

from __future__ import annotations

import io
import json
import warnings
import zipfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st

from perception.config import PAHConfig
from perception.estimation.pah import PAHDatabase, PAHFileError
from perception.targets import load_target

ARRAYS = ("points", "normals", "seg_i", "seg_j", "seg_len", "bin_ptr", "dist")
ENTRIES = (*ARRAYS, "format_version", "model_hash", "target_name", "config_json", "coverage_m")


@pytest.fixture(scope="module")
def saved(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict[str, np.ndarray]]:
    """A small real database (30 points, 435 segments) saved once, and its entries."""
    db = PAHDatabase.build(load_target("cubesat"), PAHConfig(model_points=30))
    path = db.save(tmp_path_factory.mktemp("pah") / "db.npz")
    with np.load(path, allow_pickle=False) as z:
        return path, {k: z[k] for k in z.files}


def write(path: Path, data: dict[str, np.ndarray], compressed: bool = False) -> Path:
    (np.savez_compressed if compressed else np.savez)(path, **data)
    return path


def refused(path: Path, *words: str) -> str:
    """Load ``path``; it must be refused with one line naming the file (and ``words``)."""
    with pytest.raises(PAHFileError) as info:
        PAHDatabase.load(path)
    msg = str(info.value)
    assert "\n" not in msg and str(path) in msg, msg
    for w in words:
        assert w in msg, msg
    return msg


def with_header(path: Path, entry: str, header: dict, data: bytes) -> Path:
    """Rewrite ``path`` with ``entry``'s .npy replaced by the given header and raw data."""
    buf = io.BytesIO()
    np.lib.format.write_array_header_1_0(buf, header)
    src = path.read_bytes()
    out = path.with_name(f"{path.stem}_{entry}_hdr.npz")
    with zipfile.ZipFile(io.BytesIO(src)) as zin, zipfile.ZipFile(out, "w") as zout:
        for info in zin.infolist():
            body = buf.getvalue() + data if info.filename == f"{entry}.npy" else zin.read(info)
            zout.writestr(info.filename, body)
    return out


# ---------------------------------------------------------------------------------------------
# The cases the tester found
# ---------------------------------------------------------------------------------------------
def test_shuffled_or_negative_bin_ptr_is_refused(saved, tmp_path: Path) -> None:
    _, data = saved
    bp = data["bin_ptr"]
    shuffled = bp.copy()
    shuffled[1:-1] = np.random.default_rng(0).permutation(bp[1:-1])
    assert not np.array_equal(shuffled, bp)
    refused(write(tmp_path / "shuffled.npz", {**data, "bin_ptr": shuffled}), "bin_ptr")
    negative = bp.copy()
    negative[1] = -5
    refused(write(tmp_path / "negative.npz", {**data, "bin_ptr": negative}), "bin_ptr", "-5")
    # Sorted, in range, right ends, but not the offsets of the length bins.
    shifted = bp.copy()
    k = int(np.flatnonzero(np.diff(bp) > 0)[0]) + 1
    shifted[k] -= 1
    refused(write(tmp_path / "shifted.npz", {**data, "bin_ptr": shifted}), "bin_ptr")
    refused(write(tmp_path / "start.npz", {**data, "bin_ptr": bp + 1}), "bin_ptr")


@pytest.mark.parametrize(
    ("entry", "value"),
    [
        ("seg_i", lambda d: d["seg_i"].astype(np.float64)),  # was IndexError
        ("seg_j", lambda d: d["seg_j"].astype(str)),  # was TypeError (UFuncTypeError)
        ("bin_ptr", lambda d: d["bin_ptr"].astype(np.complex128)),
        ("dist", lambda d: d["dist"].astype(str)),
        ("points", lambda d: d["points"] > 0),
        ("format_version", lambda d: np.arange(3)),  # was TypeError
        ("format_version", lambda d: np.str_("1")),
        ("coverage_m", lambda d: np.str_("0.05")),
        ("target_name", lambda d: np.float64(1.0)),
        ("model_hash", lambda d: np.array(["a", "b"])),
    ],
)
def test_wrong_dtype_or_rank_is_refused(saved, tmp_path: Path, entry: str, value) -> None:
    _, data = saved
    refused(write(tmp_path / "bad.npz", {**data, entry: value(data)}), entry)


def test_huge_header_count_is_refused_before_allocating(saved) -> None:
    path, _ = saved
    for entry, shape in (("seg_len", (10**12,)), ("points", (10**12, 3)), ("dist", (10**6, 10**6))):
        header = {"descr": "<f8", "fortran_order": False, "shape": shape}
        refused(with_header(path, entry, header, b"\0" * 64), entry, "claims")  # was MemoryError
    # A compressed entry whose zip record claims ~4 GB once inflated (a zip bomb's claim).
    compressed = write(path.with_name("compressed.npz"), saved[1], compressed=True)
    refused(claim_size(compressed, "dist", 2**32 - 16), "dist", "inflated")
    stored = claim_size(path, "dist", 2**32 - 16)  # stored: sizes that disagree
    refused(stored, "dist", "claims")


def claim_size(path: Path, entry: str, size: int) -> Path:
    """A copy of ``path`` whose central directory claims ``size`` uncompressed bytes for ``entry``."""
    raw = bytearray(path.read_bytes())
    name = f"{entry}.npy".encode()
    pos = raw.find(b"PK\x01\x02")
    while raw[pos + 46: pos + 46 + len(name)] != name:
        pos = raw.find(b"PK\x01\x02", pos + 4)
        assert pos > 0
    raw[pos + 24: pos + 28] = size.to_bytes(4, "little")
    out = path.with_name(f"{path.stem}_{entry}_claims.npz")
    out.write_bytes(bytes(raw))
    return out


def test_non_finite_values_are_refused(saved, tmp_path: Path) -> None:
    _, data = saved
    for entry in ("points", "normals", "seg_len", "dist"):
        a = data[entry].copy()
        a.reshape(-1)[3] = np.nan
        refused(write(tmp_path / f"nan_{entry}.npz", {**data, entry: a}), entry, "non-finite")
    refused(write(tmp_path / "inf.npz", {**data, "coverage_m": np.float64(np.inf)}), "coverage_m")


def test_hostile_config_and_text_entries_are_refused(saved, tmp_path: Path) -> None:
    _, data = saved
    deep = np.str_("[" * 100_000)  # was RecursionError
    refused(write(tmp_path / "deep.npz", {**data, "config_json": deep}), "config_json")
    cfg = json.loads(str(data["config_json"]))
    bad = np.str_(json.dumps({**cfg, "model_points": -1, "length_bin_m": 0}))
    msg = refused(write(tmp_path / "cfg.npz", {**data, "config_json": bad}), "config_json")
    assert "model_points" in msg and "length_bin_m" in msg  # every field, still one line
    # A bin width that makes the number of bins overflow.
    tiny = np.str_(json.dumps({**cfg, "length_bin_m": 1e-320}))
    refused(write(tmp_path / "tiny.npz", {**data, "config_json": tiny}), "bin_ptr")
    name = np.str_("cubesat\nINFO: all good")
    refused(write(tmp_path / "name.npz", {**data, "target_name": name}), "target_name")


def test_structurally_wrong_tables_are_refused(saved, tmp_path: Path) -> None:
    _, data = saved
    m = data["points"].shape[0]
    cases = {
        "seg_i": data["seg_i"] + m,  # index out of range (was IndexError in the check itself)
        "seg_j": data["seg_i"],  # j == i
        "dist": -data["dist"],
        "coverage_m": np.float64(-1.0),
    }
    for entry, value in cases.items():
        refused(write(tmp_path / f"{entry}.npz", {**data, entry: value}), entry)
    swapped = {**data, "seg_i": data["seg_j"], "seg_j": data["seg_i"]}
    refused(write(tmp_path / "swapped.npz", swapped), "seg_j")
    twice = data["seg_i"].copy(), data["seg_j"].copy()
    twice[0][1], twice[1][1] = twice[0][0], twice[1][0]
    refused(write(tmp_path / "twice.npz", {**data, "seg_i": twice[0], "seg_j": twice[1]}))
    refused(write(tmp_path / "short.npz", {**data, "dist": data["dist"][:-1]}), "dist", "shape")
    missing = {k: v for k, v in data.items() if k != "normals"}
    refused(write(tmp_path / "missing.npz", missing), "normals")


def test_not_an_archive_and_truncated_files_are_refused(saved, tmp_path: Path) -> None:
    path, _ = saved
    for name, body in (("empty", b""), ("text", b"hello\n"), ("half", path.read_bytes()[:3000])):
        (tmp_path / f"{name}.npz").write_bytes(body)
        refused(tmp_path / f"{name}.npz")
    pickled = tmp_path / "pickled.npz"
    np.savez(pickled, **{**saved[1], "points": np.array([{"a": 1}], dtype=object)})
    refused(pickled, "points", "dtype object")


def test_harmless_changes_still_load_the_same_tables(saved, tmp_path: Path) -> None:
    path, data = saved
    db = PAHDatabase.load(path)
    variants = {
        "compressed": (data, True),
        "int32": ({**data, **{k: data[k].astype(np.int32) for k in ("seg_i", "seg_j", "bin_ptr")}},
                  False),
        "bigendian": ({**data, **{k: data[k].astype(">f8") for k in ("points", "dist")}}, False),
        "extra": ({**data, "notes": np.str_("hand-edited")}, False),
        "renamed": ({**data, "target_name": np.str_("my cubesat")}, False),
    }
    for name, (d, compressed) in variants.items():
        db2 = PAHDatabase.load(write(tmp_path / f"{name}.npz", d, compressed))
        for k in ARRAYS:
            a, b = getattr(db2, k), getattr(db, k)
            np.testing.assert_array_equal(a, b)
            assert a.dtype == b.dtype and a.flags.c_contiguous, (name, k)


# ---------------------------------------------------------------------------------------------
# Fuzzing
# ---------------------------------------------------------------------------------------------
def _mutate(a: np.ndarray, op: str, i: int, x: float, rng: np.random.Generator) -> np.ndarray:
    flat = np.array(a).reshape(-1).copy()
    if op == "shuffle":
        return rng.permutation(flat).reshape(a.shape)
    if op == "set" and flat.size:
        try:
            flat[i % flat.size] = x
        except (ValueError, OverflowError, TypeError):
            return flat.reshape(a.shape)
        return flat.reshape(a.shape)
    if op == "truncate":
        return flat[: i % max(flat.size, 1)]
    if op == "extend":
        return np.concatenate([flat, flat[:1]]) if flat.size else flat
    if op == "reshape":
        return flat.reshape(-1, 1) if a.ndim != 2 else flat
    dtypes = {"f32": np.float32, "f16": np.float16, "i8": np.int8, "u64": np.uint64,
              "bool": np.bool_, "c128": np.complex128, "str": str}
    if op in dtypes:
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")  # complex to real, overflow: the point here
                return np.asarray(a).astype(dtypes[op])
        except (ValueError, OverflowError, TypeError):
            return np.asarray(a)
    return np.asarray(a)


OPS = ("shuffle", "set", "truncate", "extend", "reshape", "f32", "f16", "i8", "u64", "bool", "c128",
       "str", "drop")
VALUES = st.sampled_from([np.nan, np.inf, -np.inf, -1.0, 0.0, 1e300, -(2.0**62), 2.0**40, 7.0])


def _check_outcome(path: Path) -> None:
    """Either a one-line refusal naming the file, or a database whose tables are consistent."""
    try:
        db = PAHDatabase.load(path)
    except PAHFileError as exc:
        assert "\n" not in str(exc) and str(path) in str(exc), str(exc)
        event("refused")
        return
    event("loaded")
    m, n = db.points.shape[0], db.seg_len.shape[0]
    assert db.bin_ptr[0] == 0 and db.bin_ptr[-1] == n and np.all(np.diff(db.bin_ptr) >= 0)
    assert 0 <= db.seg_i.min() and db.seg_j.max() < m and np.all(np.isfinite(db.dist))
    assert db.seg_i.dtype == db.bin_ptr.dtype == np.int64 and db.dist.dtype == np.float64


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    mutations=st.lists(
        st.tuples(st.sampled_from(ENTRIES), st.sampled_from(OPS), st.integers(0, 10**6), VALUES),
        min_size=1, max_size=3,
    ),
    seed=st.integers(0, 2**32 - 1),
    compressed=st.booleans(),
)
def test_fuzzed_entries_are_refused_in_one_line_or_load_consistently(
    saved, tmp_path_factory: pytest.TempPathFactory, mutations, seed: int, compressed: bool
) -> None:
    _, data = saved
    rng = np.random.default_rng(seed)
    d = dict(data)
    for entry, op, i, x in mutations:
        if op == "drop":
            d.pop(entry, None)
        elif entry in d:
            d[entry] = _mutate(d[entry], op, i, x, rng)
    _check_outcome(write(tmp_path_factory.mktemp("fuzz") / "db.npz", d, compressed))


@settings(max_examples=100, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    flips=st.lists(st.tuples(st.integers(0, 10**7), st.integers(1, 255)), min_size=1, max_size=8),
    cut=st.none() | st.integers(0, 10**7),
)
def test_fuzzed_bytes_are_refused_in_one_line_or_load_consistently(
    saved, tmp_path_factory: pytest.TempPathFactory, flips, cut: int | None
) -> None:
    path, _ = saved
    raw = bytearray(path.read_bytes())
    for pos, xor in flips:
        raw[pos % len(raw)] ^= xor
    if cut is not None:
        raw = raw[: cut % len(raw)]
    out = tmp_path_factory.mktemp("bytes") / "db.npz"
    out.write_bytes(bytes(raw))
    _check_outcome(out)


@settings(max_examples=100, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    entry=st.sampled_from(ENTRIES),
    shape=st.lists(st.integers(0, 10**13), min_size=0, max_size=3).map(tuple),
    descr=st.sampled_from(["<f8", "<i8", "<u4", "|b1", "<c16", "<U4", "|O", "|V8", ">f8"]),
    fortran=st.booleans(),
)
def test_fuzzed_npy_headers_never_allocate_what_the_file_does_not_hold(
    saved, entry: str, shape: tuple[int, ...], descr: str, fortran: bool
) -> None:
    path, _ = saved
    header = {"descr": descr, "fortran_order": fortran, "shape": shape}
    _check_outcome(with_header(path, entry, header, b"\0" * 256))
