"""ROS 2 message definitions and conversions for recordings (``sensor_msgs``, ``geometry_msgs``).

The definitions are the upstream ROS 2 ``.msg`` texts (comments dropped), concatenated with their
dependencies as the ``ros2msg`` schema encoding expects (one ``=====`` line and ``MSG: pkg/Type``
per dependency), so that ROS 2 tools and Foxglove decode a recording without a ROS install.

Time stamps are simulation time [s] from the episode start, written as ``builtin_interfaces/Time``.
The sensor frame is ``tridar`` (+z boresight, +x right, +y down, the camera convention of
``REP 103``'s optical frames); the target frame is ``target``.

Point clouds keep every per-point field the pipeline reads, at full precision (``FLOAT64``), so a
replay is bitwise: ``x y z`` [m], ``t`` [s] (absolute sample time), ``intensity``, ``sigma`` [m]
(1-sigma range noise), ``subsystem`` (0 triangulation, 1 time of flight, 2 flash),
``dx dy dz`` (the reported ray direction) and ``spurious`` (evaluation only).
"""

from __future__ import annotations

import math
import struct
from collections.abc import Callable
from typing import Any

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]

__all__ = [
    "ENCODERS", "MSG_TEXT", "POINT_FIELDS", "cloud_arrays", "msgdef", "pointcloud2", "pose_stamped",
    "pose_with_covariance_stamped", "stamp", "stamp_to_s",
]

_DEFS: dict[str, str] = {
    "builtin_interfaces/Time": "int32 sec\nuint32 nanosec\n",
    "std_msgs/Header": "builtin_interfaces/Time stamp\nstring frame_id\n",
    "sensor_msgs/PointField": (
        "uint8 INT8    = 1\nuint8 UINT8   = 2\nuint8 INT16   = 3\nuint8 UINT16  = 4\n"
        "uint8 INT32   = 5\nuint8 UINT32  = 6\nuint8 FLOAT32 = 7\nuint8 FLOAT64 = 8\n"
        "string name\nuint32 offset\nuint8  datatype\nuint32 count\n"
    ),
    "sensor_msgs/PointCloud2": (
        "std_msgs/Header header\nuint32 height\nuint32 width\nPointField[] fields\n"
        "bool    is_bigendian\nuint32  point_step\nuint32  row_step\nuint8[] data\nbool is_dense\n"
    ),
    "geometry_msgs/Point": "float64 x\nfloat64 y\nfloat64 z\n",
    "geometry_msgs/Quaternion": "float64 x 0\nfloat64 y 0\nfloat64 z 0\nfloat64 w 1\n",
    "geometry_msgs/Pose": "Point position\nQuaternion orientation\n",
    "geometry_msgs/PoseWithCovariance": "Pose pose\nfloat64[36] covariance\n",
    "geometry_msgs/PoseWithCovarianceStamped": "std_msgs/Header header\nPoseWithCovariance pose\n",
    "geometry_msgs/PoseStamped": "std_msgs/Header header\nPose pose\n",
}
_DEPS: dict[str, tuple[str, ...]] = {
    "std_msgs/Header": ("builtin_interfaces/Time",),
    "sensor_msgs/PointCloud2": ("std_msgs/Header", "builtin_interfaces/Time", "sensor_msgs/PointField"),
    "geometry_msgs/Pose": ("geometry_msgs/Point", "geometry_msgs/Quaternion"),
    "geometry_msgs/PoseWithCovariance": ("geometry_msgs/Pose", "geometry_msgs/Point", "geometry_msgs/Quaternion"),
    "geometry_msgs/PoseWithCovarianceStamped": (
        "std_msgs/Header", "builtin_interfaces/Time", "geometry_msgs/PoseWithCovariance",
        "geometry_msgs/Pose", "geometry_msgs/Point", "geometry_msgs/Quaternion",
    ),
    "geometry_msgs/PoseStamped": (
        "std_msgs/Header", "builtin_interfaces/Time", "geometry_msgs/Pose", "geometry_msgs/Point",
        "geometry_msgs/Quaternion",
    ),
}
_SEP = "=" * 80


def msgdef(name: str) -> str:
    """The ``ros2msg`` schema text of ``pkg/msg/Type`` (or ``pkg/Type``) with its dependencies."""
    short = name.replace("/msg/", "/")
    if short not in _DEFS:
        raise ValueError(f"message type {name!r}; expected one of {sorted(_DEFS)}")
    parts = [_DEFS[short]]
    for dep in _DEPS.get(short, ()):
        parts.append(f"{_SEP}\nMSG: {dep}\n{_DEFS[dep]}")
    return "\n".join(parts)


#: ``pkg/msg/Type`` -> its schema text.
MSG_TEXT = {
    full: msgdef(full) for full in (
        "sensor_msgs/msg/PointCloud2", "geometry_msgs/msg/PoseWithCovarianceStamped",
        "geometry_msgs/msg/PoseStamped",
    )
}

_INT8, _UINT8, _INT16, _UINT16, _INT32, _UINT32, _FLOAT32, _FLOAT64 = range(1, 9)
_NUMPY_OF = {_INT8: "i1", _UINT8: "u1", _INT16: "i2", _UINT16: "u2", _INT32: "i4", _UINT32: "u4",
             _FLOAT32: "f4", _FLOAT64: "f8"}

#: (name, datatype) of the recorded cloud's fields, in order (packed, little-endian).
POINT_FIELDS: tuple[tuple[str, int], ...] = (
    ("x", _FLOAT64), ("y", _FLOAT64), ("z", _FLOAT64), ("t", _FLOAT64), ("intensity", _FLOAT64),
    ("sigma", _FLOAT64), ("dx", _FLOAT64), ("dy", _FLOAT64), ("dz", _FLOAT64),
    ("subsystem", _INT8), ("spurious", _UINT8),
)
_CLOUD_DTYPE = np.dtype([(n, "<" + _NUMPY_OF[d]) for n, d in POINT_FIELDS])
_FIELD_MSGS = []
_off = 0
for _n, _d in POINT_FIELDS:
    _FIELD_MSGS.append({"name": _n, "offset": _off, "datatype": _d, "count": 1})
    _off += np.dtype(_NUMPY_OF[_d]).itemsize


def stamp(t: float) -> dict[str, int]:
    """``builtin_interfaces/Time`` of ``t`` [s] (negative times clamp to 0)."""
    ns = max(round(t * 1e9), 0)
    return {"sec": ns // 1_000_000_000, "nanosec": ns % 1_000_000_000}


def stamp_to_s(st: Any) -> float:
    """Seconds of a decoded ``builtin_interfaces/Time``."""
    return float(st.sec) + 1e-9 * float(st.nanosec)


def pointcloud2(
    points: FloatArray, times: FloatArray, intensity: FloatArray, sigma: FloatArray,
    directions: FloatArray, subsystem: npt.NDArray[np.int8], spurious: npt.NDArray[np.bool_],
    t: float, frame_id: str = "tridar",
) -> dict[str, Any]:
    """A ``sensor_msgs/PointCloud2`` (as a dict for the CDR encoder) of one frame's points."""
    n = points.shape[0]
    rec = np.empty(n, dtype=_CLOUD_DTYPE)
    rec["x"], rec["y"], rec["z"] = points[:, 0], points[:, 1], points[:, 2]
    rec["t"], rec["intensity"], rec["sigma"] = times, intensity, sigma
    rec["dx"], rec["dy"], rec["dz"] = directions[:, 0], directions[:, 1], directions[:, 2]
    rec["subsystem"], rec["spurious"] = subsystem, spurious
    return {
        "header": {"stamp": stamp(t), "frame_id": frame_id},
        "height": 1, "width": n, "fields": _FIELD_MSGS, "is_bigendian": False,
        "point_step": _CLOUD_DTYPE.itemsize, "row_step": _CLOUD_DTYPE.itemsize * n,
        "data": rec.tobytes(), "is_dense": True,
    }


def cloud_arrays(msg: Any) -> dict[str, npt.NDArray[Any]]:
    """Field name -> (N,) array of a decoded ``PointCloud2`` (any field layout, either byte
    order; fields with ``count > 1`` are skipped). Raises ``ValueError`` on an inconsistent one."""
    n = int(msg.height) * int(msg.width)
    step = int(msg.point_step)
    data = bytes(msg.data)
    if n * step > len(data) or (n and step <= 0):
        raise ValueError(f"PointCloud2 of {msg.height}x{msg.width} points of {step} bytes needs "
                         f"{n * step} bytes of data; it has {len(data)}")
    order = ">" if msg.is_bigendian else "<"
    names, formats, offsets = [], [], []
    for f in msg.fields:
        if int(f.datatype) not in _NUMPY_OF or int(f.count) != 1 or f.name in names:
            continue
        size = np.dtype(_NUMPY_OF[int(f.datatype)]).itemsize
        if int(f.offset) + size > step:
            raise ValueError(f"PointCloud2 field {f.name!r} at offset {f.offset} overruns the "
                             f"{step}-byte point")
        names.append(f.name)
        formats.append(order + _NUMPY_OF[int(f.datatype)])
        offsets.append(int(f.offset))
    dt = np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": max(step, 1)})
    rec = np.frombuffer(data, dtype=dt, count=n)
    return {name: rec[name].copy() for name in names}


def _quat_xyzw(q_wxyz: FloatArray) -> dict[str, float]:
    w, x, y, z = (float(v) for v in q_wxyz)
    return {"x": x, "y": y, "z": z, "w": w}


def pose_stamped(t: float, position: FloatArray, q_wxyz: FloatArray, frame_id: str = "tridar") -> dict[str, Any]:
    """A ``geometry_msgs/PoseStamped``: the target's pose in ``frame_id``."""
    px, py, pz = (float(v) for v in position)
    return {"header": {"stamp": stamp(t), "frame_id": frame_id},
            "pose": {"position": {"x": px, "y": py, "z": pz}, "orientation": _quat_xyzw(q_wxyz)}}


def pose_with_covariance_stamped(
    t: float, position: FloatArray, q_wxyz: FloatArray, covariance12: FloatArray, frame_id: str = "tridar"
) -> dict[str, Any]:
    """A ``geometry_msgs/PoseWithCovarianceStamped`` from a ``StateVector``'s pose and its
    (12, 12) covariance (position and attitude blocks: ``x y z rx ry rz``, sensor frame)."""
    cov6 = np.asarray(covariance12, dtype=np.float64).reshape(-1)[_POSE_COV_INDEX]
    msg = pose_stamped(t, position, q_wxyz, frame_id)
    return {"header": msg["header"], "pose": {"pose": msg["pose"], "covariance": cov6.tolist()}}


# Flat indices of the (6, 6) position-attitude block of a (12, 12) state covariance.
_POSE_COV_INDEX = np.ravel_multi_index(np.ix_(np.r_[0:3, 6:9], np.r_[0:3, 6:9]), (12, 12)).reshape(-1)


def finite_or_zero(x: float) -> float:
    """JSON has no NaN: non-finite numbers become 0."""
    return x if math.isfinite(x) else 0.0


# ---------------------------------------------------------------------------------- CDR encoding
# The three message types a recording writes, encoded directly (XCDR1, little endian). The same
# bytes as mcap-ros2-support's generic encoder (a test compares them), at a fraction of its cost
# per message: that encoder walks the definition field by field in Python, which for a point
# cloud's eleven PointFields is most of a recording's overhead.
_CDR_LE = b"\x00\x01\x00\x00"


class _Cdr:
    __slots__ = ("buf",)

    def __init__(self) -> None:
        self.buf = bytearray(_CDR_LE)

    def align(self, n: int) -> None:
        pad = -(len(self.buf) - 4) % n
        if pad:
            self.buf += bytes(pad)

    def u32(self, v: int) -> None:
        self.align(4)
        self.buf += struct.pack("<I", v)

    def string(self, s: str) -> None:
        b = s.encode()
        self.u32(len(b) + 1)
        self.buf += b + b"\0"

    def f64s(self, values: list[float]) -> None:
        self.align(8)
        self.buf += struct.pack(f"<{len(values)}d", *values)

    def header(self, h: dict[str, Any]) -> None:
        self.align(4)
        self.buf += struct.pack("<iI", h["stamp"]["sec"], h["stamp"]["nanosec"])
        self.string(h["frame_id"])

    def pose(self, p: dict[str, Any]) -> None:
        pos, q = p["position"], p["orientation"]
        self.f64s([pos["x"], pos["y"], pos["z"], q["x"], q["y"], q["z"], q["w"]])


def _fields_block(fields: list[dict[str, Any]]) -> bytes:
    """The CDR bytes of a ``PointField[]`` starting at a 4-byte aligned offset (they do not
    depend on where: every member aligns to at most 4)."""
    c = _Cdr()
    c.u32(len(fields))
    for f in fields:
        c.string(f["name"])
        c.u32(f["offset"])
        c.buf.append(f["datatype"])
        c.u32(f["count"])
    return bytes(c.buf[4:])


def _encode_pointcloud2(m: dict[str, Any]) -> bytes:
    c = _Cdr()
    c.header(m["header"])
    c.u32(m["height"])
    c.u32(m["width"])
    fields = m["fields"]
    c.buf += _FIELDS_BYTES if fields is _FIELD_MSGS else _fields_block(fields)
    c.buf.append(1 if m["is_bigendian"] else 0)
    c.u32(m["point_step"])
    c.u32(m["row_step"])
    c.u32(len(m["data"]))
    c.buf += m["data"]
    c.buf.append(1 if m["is_dense"] else 0)
    return bytes(c.buf)


def _encode_pose_stamped(m: dict[str, Any]) -> bytes:
    c = _Cdr()
    c.header(m["header"])
    c.pose(m["pose"])
    return bytes(c.buf)


def _encode_pose_with_covariance_stamped(m: dict[str, Any]) -> bytes:
    c = _Cdr()
    c.header(m["header"])
    c.pose(m["pose"]["pose"])
    c.f64s(m["pose"]["covariance"])
    return bytes(c.buf)


_FIELDS_BYTES = _fields_block(_FIELD_MSGS)

#: ``pkg/msg/Type`` -> CDR encoder of its message dict.
ENCODERS: dict[str, Callable[[dict[str, Any]], bytes]] = {
    "sensor_msgs/msg/PointCloud2": _encode_pointcloud2,
    "geometry_msgs/msg/PoseStamped": _encode_pose_stamped,
    "geometry_msgs/msg/PoseWithCovarianceStamped": _encode_pose_with_covariance_stamped,
}
