"""Where a replay's frames come from: a tridar-env recording, a folder of PLY/PCD frames, or any
MCAP / ROS 2 bag with ``sensor_msgs/PointCloud2`` on a topic.

Conventions for data from elsewhere (a lab scanner, a bag from a robot):

* points are in the **sensor frame**, metres: +z boresight, +x right, +y down (the optical
  convention). ``axes="ros"`` converts from the ROS body convention (x forward, y left, z up).
* the frame time [s] is, in order of preference: the ``t`` column of a ``timestamps.csv`` (columns
  ``file,t``) in the folder or given with ``times``; the earliest per-point time (a PLY/PCD field
  ``t``, absolute seconds); the frame index over ``rate_hz``. A bag's frame time is the message's
  ``header.stamp``; a FLOAT64 field ``t`` gives per-point times.
* per-point ``intensity`` is read when present (else 1); the range noise ``sigma`` and the ranging
  subsystem come from the mission's sensor model at each point's range.
* truth, when a user has it, is a CSV with columns ``t,x,y,z,qw,qx,qy,qz``: ``T_sensor_target``,
  the target body origin in the sensor frame and the scalar-first quaternion of the target's
  attitude in the sensor frame (target -> sensor), at the frame times (nearest row is used).

A file that cannot be read, or whose points are unusable, is one line on stderr naming the file and
the problem; the frames that were good are kept.
"""

from __future__ import annotations

import csv
import math
import re
import sys
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from perception.sensing.pointcloud import PointCloud, Subsystem

FloatArray = npt.NDArray[np.float64]

__all__ = ["RawFrame", "Truth", "clouds_from_mcap", "load_folder", "load_truth_csv", "read_pcd",
           "read_ply", "to_cloud"]

_R_OPTICAL_ROS = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])


@dataclass
class RawFrame:
    """One frame from outside: ``t`` [s], ``fields`` name -> (N,) arrays (``x y z`` at least), and
    where it came from."""

    t: float
    fields: dict[str, npt.NDArray[Any]]
    source: str


@dataclass
class Truth:
    """Truth poses ``T_sensor_target`` (M, 4, 4) at times ``t`` (M,) [s]."""

    t: FloatArray
    T: npt.NDArray[np.float64]
    problems: list[str] = field(default_factory=list)

    def at(self, t: float, tol: float = 1e-3) -> FloatArray | None:
        """The pose at ``t`` (the nearest row within ``tol`` [s]), or None."""
        if not len(self.t):
            return None
        i = int(np.argmin(np.abs(self.t - t)))
        return self.T[i] if abs(self.t[i] - t) <= tol else None


def _say(line: str) -> None:
    print(line, file=sys.stderr)


# ---------------------------------------------------------------------------------- file formats
_PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
              "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
              "float": "f4", "float32": "f4", "double": "f8", "float64": "f8"}


def read_ply(path: str | Path) -> dict[str, npt.NDArray[Any]]:
    """The vertex properties of a PLY file (ascii or binary), name -> (N,) array.

    Raises:
        ValueError: not a PLY, an unsupported layout, or fewer bytes than the header promises.
    """
    raw = Path(path).read_bytes()
    end = raw.find(b"end_header")
    if not raw.startswith(b"ply") or end < 0:
        raise ValueError("not a PLY file (no 'ply' magic or no end_header)")
    body_start = raw.index(b"\n", end) + 1
    header = raw[:end].decode("ascii", "replace").splitlines()
    fmt, elements, current = "", [], None
    for line in header:
        parts = line.split()
        if not parts:
            continue
        if parts[0] == "format":
            fmt = parts[1]
        elif parts[0] == "element":
            current = [parts[1], int(parts[2]), []]
            elements.append(current)
        elif parts[0] == "property" and current is not None:
            if parts[1] == "list":
                if current[0] == "vertex":
                    raise ValueError("list properties on vertices are not supported")
                current[2].append((parts[-1], None))
            else:
                if parts[1] not in _PLY_TYPES:
                    raise ValueError(f"PLY property type {parts[1]!r} is not supported")
                current[2].append((parts[2], _PLY_TYPES[parts[1]]))
    if not elements or elements[0][0] != "vertex":
        raise ValueError("PLY has no vertex element first; expected a point cloud")
    _, n, props = elements[0]
    names = [p for p, _ in props]
    if fmt == "ascii":
        lines = raw[body_start:].decode("ascii", "replace").split("\n")
        rows = [ln.split() for ln in lines[:n] if ln.strip()]
        if len(rows) < n:
            raise ValueError(f"PLY promises {n} vertices; the file holds {len(rows)}")
        arr = np.array(rows, dtype=np.float64)
        return {name: arr[:, i] for i, name in enumerate(names)}
    if fmt not in ("binary_little_endian", "binary_big_endian"):
        raise ValueError(f"PLY format {fmt!r}; expected ascii or binary")
    order = "<" if fmt == "binary_little_endian" else ">"
    dt = np.dtype([(name, order + t) for name, t in props])
    need = dt.itemsize * n
    if len(raw) - body_start < need:
        raise ValueError(f"PLY promises {n} vertices ({need} bytes); the file holds "
                         f"{len(raw) - body_start} bytes after the header (truncated?)")
    rec = np.frombuffer(raw, dtype=dt, count=n, offset=body_start)
    return {name: rec[name].astype(np.float64) for name in names}


_PCD_TYPES = {("F", 4): "f4", ("F", 8): "f8", ("I", 1): "i1", ("I", 2): "i2", ("I", 4): "i4",
              ("I", 8): "i8", ("U", 1): "u1", ("U", 2): "u2", ("U", 4): "u4", ("U", 8): "u8"}


def read_pcd(path: str | Path) -> dict[str, npt.NDArray[Any]]:
    """The fields of a PCD file (``DATA ascii`` or ``binary``), name -> (N,) array.

    Raises:
        ValueError: not a PCD, ``binary_compressed``, or fewer points than the header says.
    """
    raw = Path(path).read_bytes()
    head: dict[str, list[str]] = {}
    pos = 0
    while pos < len(raw):
        nl = raw.find(b"\n", pos)
        nl = len(raw) if nl < 0 else nl
        line = raw[pos:nl].decode("ascii", "replace").strip()
        pos = nl + 1
        if not line or line.startswith("#"):
            continue
        key, *vals = line.split()
        head[key.upper()] = vals
        if key.upper() == "DATA":
            break
    if "FIELDS" not in head or "DATA" not in head:
        raise ValueError("not a PCD file (no FIELDS or DATA line)")
    names = head["FIELDS"]
    sizes = [int(s) for s in head.get("SIZE", ["4"] * len(names))]
    types = head.get("TYPE", ["F"] * len(names))
    counts = [int(c) for c in head.get("COUNT", ["1"] * len(names))]
    n = int(head.get("POINTS", head.get("WIDTH", ["0"]))[0])
    data = head["DATA"][0].lower()
    if data == "ascii":
        rows = [ln.split() for ln in raw[pos:].decode("ascii", "replace").splitlines() if ln.strip()]
        if len(rows) < n:
            raise ValueError(f"PCD promises {n} points; the file holds {len(rows)}")
        arr = np.array(rows[:n], dtype=np.float64)
        out, col = {}, 0
        for name, c in zip(names, counts):
            out[name] = arr[:, col]
            col += c
        return out
    if data != "binary":
        raise ValueError(f"PCD DATA {data!r}; expected ascii or binary")
    fmts = []
    for name, s, t, c in zip(names, sizes, types, counts):
        if (t, s) not in _PCD_TYPES:
            raise ValueError(f"PCD field {name!r} of type {t}{s} is not supported")
        fmts.append((name, "<" + _PCD_TYPES[(t, s)], (c,)) if c > 1 else (name, "<" + _PCD_TYPES[(t, s)]))
    dt = np.dtype(fmts)
    if len(raw) - pos < dt.itemsize * n:
        raise ValueError(f"PCD promises {n} points ({dt.itemsize * n} bytes); the file holds "
                         f"{len(raw) - pos} bytes of data (truncated?)")
    rec = np.frombuffer(raw, dtype=dt, count=n, offset=pos)
    return {name: rec[name].astype(np.float64) for name, c in zip(names, counts) if c == 1}


# ---------------------------------------------------------------------------------- frames
def _read_times(path: Path) -> dict[str, float]:
    out: dict[str, float] = {}
    with open(path, newline="") as fh:
        for row in csv.DictReader(fh):
            try:
                out[Path(row["file"]).name] = float(row["t"])
            except (KeyError, TypeError, ValueError):
                raise ValueError(f"{path}: a row {row!r}; expected columns file,t") from None
    return out


def _natural_key(p: Path) -> list[Any]:
    return [int(s) if s.isdigit() else s for s in re.split(r"(\d+)", p.name)]


def load_folder(
    folder: str | Path, *, times: str | Path | None = None, rate_hz: float | None = None,
    warn: Callable[[str], None] = _say,
) -> list[RawFrame]:
    """The PLY/PCD frames of ``folder`` in natural name order (see the module docstring for times).

    A file that does not read is one ``warn`` line and is left out."""
    root = Path(folder)
    files = sorted((p for p in root.iterdir() if p.suffix.lower() in (".ply", ".pcd")), key=_natural_key)
    if not files:
        raise ValueError(f"{root}: no .ply or .pcd files; expected a folder of point-cloud frames")
    tfile = Path(times) if times is not None else root / "timestamps.csv"
    table = _read_times(tfile) if tfile.exists() else {}
    if times is not None and not tfile.exists():
        raise ValueError(f"{tfile}: no such timestamps file")
    frames = []
    for i, f in enumerate(files):
        try:
            fields = read_ply(f) if f.suffix.lower() == ".ply" else read_pcd(f)
            if not {"x", "y", "z"} <= set(fields):
                raise ValueError(f"fields {sorted(fields)}; expected x, y, z")
        except (OSError, ValueError) as exc:
            warn(f"{f}: {exc}; frame skipped")
            continue
        if f.name in table:
            t = table[f.name]
        elif "t" in fields and len(fields["t"]) and np.isfinite(fields["t"]).any():
            t = float(np.nanmin(fields["t"]))
        elif rate_hz:
            t = i / rate_hz
        elif table:
            warn(f"{f}: not in {tfile.name}; frame skipped")
            continue
        else:
            raise ValueError(f"{root}: no frame times (no timestamps.csv, no per-point 't' field); "
                             "pass --rate HZ")
        frames.append(RawFrame(t, fields, str(f)))
    frames.sort(key=lambda fr: fr.t)
    return frames


def clouds_from_mcap(path: str | Path, topic: str, warn: Callable[[str], None] = _say) -> list[RawFrame]:
    """The ``PointCloud2`` messages on ``topic`` of any MCAP (a ROS 2 bag included)."""
    from tridar_env.mcap_log import read_mcap
    from tridar_env.ros2msgs import cloud_arrays, stamp_to_s

    contents = read_mcap(path, topics={topic}, warn=warn)
    msgs = contents.topic(topic)
    if not msgs:
        raise ValueError(f"{path}: no messages on topic {topic!r}")
    frames = []
    for m in msgs:
        if not m.schema.endswith("PointCloud2"):
            raise ValueError(f"{path}: topic {topic} carries {m.schema or 'unknown'}; expected "
                             "sensor_msgs/msg/PointCloud2")
        try:
            fields = cloud_arrays(m.data)
            if not {"x", "y", "z"} <= set(fields):
                raise ValueError(f"fields {sorted(fields)}; expected x, y, z")
        except ValueError as exc:
            warn(f"{path}: {topic} message {m.sequence}: {exc}; frame skipped")
            continue
        frames.append(RawFrame(stamp_to_s(m.data.header.stamp), fields, f"{path}#{m.sequence}"))
    return frames


def to_cloud(frame: RawFrame, sensor: Any, axes: str = "optical",
             warn: Callable[[str], None] = _say) -> PointCloud:
    """A pipeline ``PointCloud`` of a raw frame (sigma and subsystem from ``sensor``'s model)."""
    f = frame.fields
    pts = np.column_stack([f["x"], f["y"], f["z"]]).astype(np.float64)
    if axes == "ros":
        pts = pts @ _R_OPTICAL_ROS.T
    elif axes != "optical":
        raise ValueError(f"axes={axes!r}; expected optical or ros")
    n0 = len(pts)
    r = np.linalg.norm(pts, axis=1)
    keep = np.isfinite(r) & (r > 1e-6)
    times = np.asarray(f["t"], dtype=np.float64) if "t" in f and f["t"].dtype.kind == "f" else None
    if times is not None:
        keep &= np.isfinite(times)
    if not keep.all():
        warn(f"{frame.source}: {n0 - int(keep.sum())} of {n0} points not finite or at the origin; dropped")
    pts, r = pts[keep], r[keep]
    t = frame.t
    times = np.full(len(pts), t) if times is None else times[keep]
    inten = np.asarray(f["intensity"], dtype=np.float64)[keep] if "intensity" in f else np.ones(len(pts))
    inten = np.clip(np.nan_to_num(inten, nan=0.0), 0.0, None)
    tri = r < float(getattr(sensor, "transition_range_m", math.inf))
    sub = np.where(tri, Subsystem.TRIANGULATION, Subsystem.TOF).astype(np.int8)
    sigma = np.empty(len(pts))
    if hasattr(sensor, "range_sigma"):
        sigma[tri] = sensor.range_sigma(r[tri], Subsystem.TRIANGULATION)
        sigma[~tri] = sensor.range_sigma(r[~tri], Subsystem.TOF)
    else:
        sigma[:] = 0.01
    t_end = float(times.max()) if len(times) else t
    return PointCloud(points=pts, times=times, subsystem=sub, intensity=inten, sigma=sigma,
                      directions=pts / r[:, None], t_start=float(min(t, times.min() if len(times) else t)),
                      t_end=max(t_end, t))


def load_truth_csv(path: str | Path, warn: Callable[[str], None] = _say) -> Truth:
    """Truth poses from a CSV ``t,x,y,z,qw,qx,qy,qz`` (bad rows: one line each, skipped)."""
    from perception.geometry import T_from_quat_pos

    ts, Ts, problems = [], [], []
    with open(path, newline="") as fh:
        for i, row in enumerate(csv.DictReader(fh), start=2):
            try:
                vals = [float(row[k]) for k in ("t", "x", "y", "z", "qw", "qx", "qy", "qz")]
                if not all(math.isfinite(v) for v in vals):
                    raise ValueError("non-finite value")
                q = np.array(vals[4:])
                nq = float(np.linalg.norm(q))
                if abs(nq - 1.0) > 1e-3:
                    raise ValueError(f"quaternion norm {nq:.4f}")
                Ts.append(T_from_quat_pos(q / nq, np.array(vals[1:4])))
                ts.append(vals[0])
            except (KeyError, TypeError, ValueError) as exc:
                problems.append(f"line {i}: {exc}")
    if problems:
        line = (f"{path}: {len(problems)} rows skipped (first: {problems[0]}); expected columns "
                "t,x,y,z,qw,qx,qy,qz")
        warn(line)
        problems = [line]
    return Truth(np.array(ts), np.array(Ts).reshape(-1, 4, 4), problems)
