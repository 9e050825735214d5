"""MCAP files of a recorded run: a writer with ROS 2 (CDR) and JSON channels, and a tolerant reader.

Needs the ``record`` extra (``mcap``, ``mcap-ros2-support``); no ROS install. The file's profile
is ``ros2``: ROS 2 (``ros2 bag play``, with the MCAP storage plugin) and Foxglove open it as it is.

Topics (``t`` below is simulation time [s] from the episode start; a message's log time is
``t`` plus the episode's offset in the file, so several episodes follow each other):

=========================  ==========================================  =======================================
topic                      schema                                      content
=========================  ==========================================  =======================================
``/tridar/points``         ``sensor_msgs/msg/PointCloud2``             every scanned frame (see ``ros2msgs``)
``/tridar/estimate``       ``geometry_msgs/msg/PoseWithCovarianceStamped``  the published pose (when it has one)
``/truth/pose``            ``geometry_msgs/msg/PoseStamped``           true ``T_sensor_target``
``/tridar/state``          JSON ``tridar/State``                       mode, validity, protection level, ...
``/tridar/scan_region``    JSON ``tridar/ScanRegion``                  the scan pattern's angular window
``/tridar/frame``          JSON ``tridar/Frame``                       the pipeline's inputs and output of one
                                                                       call (what replay feeds back)
``/tridar/event``          JSON ``tridar/Event``                       pipeline reset and external pose seeds
``/env/step``              JSON ``tridar/EnvStep``                     action, reward and its terms, truth
=========================  ==========================================  =======================================

The resolved mission config is an attachment (``mission_config.json``, JSON text) and the
recording's provenance a metadata record (``tridar-env``). Nothing is pickled.
"""

from __future__ import annotations

import json
import sys
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any, Self

__all__ = ["LoggedMessage", "McapContents", "McapLog", "read_mcap", "refuse_existing", "time_ns"]

#: Topic -> JSON schema name of the JSON channels.
JSON_TOPICS = {
    "/tridar/state": "tridar/State",
    "/tridar/scan_region": "tridar/ScanRegion",
    "/tridar/frame": "tridar/Frame",
    "/tridar/event": "tridar/Event",
    "/env/step": "tridar/EnvStep",
}
_NUM, _STR, _BOOL = {"type": "number"}, {"type": "string"}, {"type": "boolean"}
_VEC = {"type": "array", "items": _NUM}
_OPT_NUM = {"type": ["number", "null"]}
#: Schema name -> JSON-schema properties (what Foxglove offers for plots and message paths).
JSON_PROPERTIES: dict[str, dict[str, Any]] = {
    "tridar/State": {
        "t": _NUM, "mode": _STR, "pose_valid": _BOOL, "protection_level": _NUM, "alert_limit": _NUM,
        "range": _NUM, "range_rate": _NUM, "fitness": _NUM, "n_points": _NUM, "latency": _NUM,
        "bearing": _VEC, "bearing_source": _STR,
        "valid": {"type": "object", "additionalProperties": _BOOL},
    },
    "tridar/ScanRegion": {"t": _NUM, "mode": _STR, "pattern": _STR, "az_min": _NUM, "az_max": _NUM,
                          "el_min": _NUM, "el_max": _NUM, "samples": _NUM},
    "tridar/Frame": {"t": _NUM, "rng": {"type": "object"}, "scans": {"type": "array"},
                     "ego": {"type": "object"}, "truth": {"type": "object"}, "state": {"type": "object"}},
    "tridar/Event": {"kind": _STR, "t": _NUM},
    "tridar/EnvStep": {
        "episode": _NUM, "step": _NUM, "t": _NUM, "action": {"type": ["array", "null"], "items": _NUM},
        "reward": _OPT_NUM, "reward_terms": {"type": "object", "additionalProperties": _OPT_NUM},
        "terminated": _BOOL, "truncated": _BOOL, "termination": _STR, "mode": _STR,
        "r_lvlh": _VEC, "v_lvlh": _VEC, "pos_err_m": _OPT_NUM, "att_err_deg": _OPT_NUM,
        "propellant_kg": _OPT_NUM,
    },
}
CONFIG_ATTACHMENT = "mission_config.json"
METADATA_NAME = "tridar-env"


def time_ns(t: float) -> int:
    """A log time [ns] (>= 0) of ``t`` [s]."""
    return max(round(t * 1e9), 0)


def refuse_existing(path: str | Path, force: bool) -> Path:
    """``path`` as a Path; a ``ValueError`` (one line) when it exists and ``force`` is not set."""
    p = Path(path)
    if p.exists() and not force:
        raise ValueError(f"{p} exists; refusing to overwrite it (pass --force to replace it)")
    if p.is_dir():
        raise ValueError(f"{p} is a folder; expected a file name ending in .mcap")
    return p


def _json_default(o: Any) -> Any:
    tolist = getattr(o, "tolist", None)
    if tolist is not None:
        return tolist()
    raise TypeError(f"{type(o).__name__} is not JSON serialisable")


class McapLog:
    """Writes one recording. ``close()`` (or the context manager) finishes the file.

    Args:
        path: the ``.mcap`` file to create.
        force: replace an existing file (otherwise an existing file is refused).
        chunk_size: bytes per compressed chunk.
        compression: ``lz4`` (default: a quarter of zstd's time per chunk, which at a cloud per
            frame is most of what recording costs), ``zstd`` (files about a sixth smaller) or
            ``none``.
    """

    def __init__(self, path: str | Path, *, force: bool = False, chunk_size: int = 1024 * 1024,
                 compression: str = "lz4") -> None:
        try:
            from mcap.writer import CompressionType
            from mcap_ros2.writer import Writer
        except ImportError as exc:  # pragma: no cover - depends on the install
            raise ValueError(f"recording needs the 'record' extra ({exc}); pip install "
                             "'tridar-env[record]'") from None
        from tridar_env.ros2msgs import MSG_TEXT

        kinds = {"lz4": CompressionType.LZ4, "zstd": CompressionType.ZSTD, "none": CompressionType.NONE}
        if compression not in kinds:
            raise ValueError(f"compression={compression!r}; expected one of {sorted(kinds)}")
        self.path = refuse_existing(path, force)
        self._fh: IO[bytes] = open(self.path, "wb" if force else "xb")  # noqa: SIM115
        self._w = Writer(self._fh, chunk_size=chunk_size, compression=kinds[compression])
        self._schemas = {name: self._w.register_msgdef(name, text) for name, text in MSG_TEXT.items()}
        # mcap-ros2-support writes CDR channels only; the JSON channels go on its MCAP writer.
        self._raw = self._w._writer
        self._json_channels: dict[str, int] = {}
        self._cdr_channels: dict[str, int] = {}
        self._seq: dict[str, int] = {}
        self.closed = False
        #: CPU time [s] the recorder spent on its own work (its callers add to it; ``close``
        #: adds the last chunk's): what recording costs, without an A/B run.
        self.busy_s = 0.0

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def next_seq(self, topic: str) -> int:
        s = self._seq.get(topic, 0)
        self._seq[topic] = s + 1
        return s

    def ros(self, topic: str, schema: str, msg: dict[str, Any], t_ns: int, seq: int | None = None) -> int:
        """Write a ROS 2 message (``schema`` a ``pkg/msg/Type``); returns its sequence number.

        The types of :data:`~tridar_env.ros2msgs.ENCODERS` are encoded here (the same CDR bytes as
        mcap-ros2-support's encoder, faster); others go through mcap-ros2-support."""
        from tridar_env.ros2msgs import ENCODERS

        s = self.next_seq(topic) if seq is None else seq
        enc = ENCODERS.get(schema)
        if enc is None:
            self._w.write_message(topic, self._schemas[schema], msg, log_time=t_ns, publish_time=t_ns, sequence=s)
            return s
        ch = self._cdr_channels.get(topic)
        if ch is None:
            ch = self._cdr_channels[topic] = self._raw.register_channel(topic, "cdr", self._schemas[schema].id)
        self._raw.add_message(ch, log_time=t_ns, publish_time=t_ns, sequence=s, data=enc(msg))
        return s

    def json(self, topic: str, obj: dict[str, Any], t_ns: int) -> None:
        """Write a JSON message on one of :data:`JSON_TOPICS`."""
        ch = self._json_channels.get(topic)
        if ch is None:
            name = JSON_TOPICS[topic]
            schema = json.dumps({"title": name, "type": "object",
                                 "properties": JSON_PROPERTIES.get(name, {})}).encode()
            sid = self._raw.register_schema(name, "jsonschema", schema)
            ch = self._json_channels[topic] = self._raw.register_channel(topic, "json", sid)
        data = json.dumps(obj, separators=(",", ":"), default=_json_default, allow_nan=False).encode()
        self._raw.add_message(ch, log_time=t_ns, publish_time=t_ns, sequence=self.next_seq(topic), data=data)

    def metadata(self, name: str, data: dict[str, str]) -> None:
        self._w.add_metadata(name, data)

    def attachment(self, name: str, media_type: str, text: str) -> None:
        self._w.add_attachment(create_time=0, log_time=0, name=name, media_type=media_type, data=text.encode())

    def close(self) -> None:
        if self.closed:
            return
        self.closed = True
        t0 = time.process_time()
        try:
            self._w.finish()
        finally:
            self._fh.close()
            self.busy_s += time.process_time() - t0


@dataclass
class LoggedMessage:
    """One decoded message: ``topic``, ``schema`` name, ``log_time`` [ns], ``sequence`` and
    ``data`` (a decoded ROS 2 message object or a JSON dict)."""

    topic: str
    schema: str
    log_time: int
    sequence: int
    data: Any


@dataclass
class McapContents:
    """What :func:`read_mcap` found: messages in file order, metadata, attachments (text) and the
    problems met (one line each; the messages before a problem are kept)."""

    path: Path
    messages: list[LoggedMessage] = field(default_factory=list)
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)
    attachments: dict[str, str] = field(default_factory=dict)
    problems: list[str] = field(default_factory=list)

    def topic(self, name: str) -> list[LoggedMessage]:
        return [m for m in self.messages if m.topic == name]

    def topics(self) -> dict[str, str]:
        """Topic -> schema name."""
        return {m.topic: m.schema for m in self.messages}


def _decoder(schema: Any, encoding: str) -> Callable[[bytes], Any]:
    if encoding == "json":
        return lambda data: json.loads(data)
    if encoding == "cdr" and schema is not None and schema.encoding == "ros2msg":
        from mcap_ros2.decoder import DecoderFactory

        dec = DecoderFactory().decoder_for(encoding, schema)
        if dec is None:
            raise ValueError(f"no decoder for schema {schema.name!r}")
        return dec
    return lambda data: data  # unknown encodings stay bytes


def _records(fh: IO[bytes]) -> Iterator[Any]:
    from mcap.stream_reader import StreamReader

    yield from StreamReader(fh, validate_crcs=True).records


def read_mcap(path: str | Path, topics: set[str] | None = None,
              warn: Callable[[str], None] | None = None) -> McapContents:
    """Read a recording (or any MCAP) record by record, decoding CDR and JSON messages.

    A truncated or corrupt file keeps what was read before the damage; a message that does not
    decode is skipped. Each problem is one line in ``problems`` (and passed to ``warn``).

    Args:
        path: the ``.mcap`` file.
        topics: only these topics (None: all).
        warn: called with each problem line (default: print to stderr).
    """
    from mcap.records import Attachment, Channel, Message, Metadata, Schema

    p = Path(path)
    out = McapContents(p)
    say = warn or (lambda line: print(line, file=sys.stderr))
    schemas: dict[int, Any] = {}
    channels: dict[int, Any] = {}
    decoders: dict[int, Callable[[bytes], Any] | None] = {}
    bad: dict[str, int] = {}
    with open(p, "rb") as fh:
        try:
            for rec in _records(fh):
                if isinstance(rec, Schema):
                    schemas[rec.id] = rec
                elif isinstance(rec, Channel):
                    channels[rec.id] = rec
                elif isinstance(rec, Message):
                    ch = channels.get(rec.channel_id)
                    if ch is None or (topics is not None and ch.topic not in topics):
                        continue
                    if rec.channel_id not in decoders:
                        try:
                            decoders[rec.channel_id] = _decoder(schemas.get(ch.schema_id), ch.message_encoding)
                        except Exception as exc:  # noqa: BLE001  (an unknown schema: skip the topic)
                            decoders[rec.channel_id] = None
                            bad[ch.topic] = bad.get(ch.topic, 0) + 1
                            out.problems.append(f"{p}: topic {ch.topic}: cannot decode ({exc}); skipped")
                    dec = decoders[rec.channel_id]
                    if dec is None:
                        continue
                    try:
                        data = dec(rec.data)
                    except Exception:  # noqa: BLE001  (one bad message; count it, keep going)
                        bad[ch.topic] = bad.get(ch.topic, 0) + 1
                        continue
                    sch = schemas.get(ch.schema_id)
                    out.messages.append(LoggedMessage(ch.topic, sch.name if sch else "", rec.log_time,
                                                      rec.sequence, data))
                elif isinstance(rec, Metadata):
                    out.metadata[rec.name] = dict(rec.metadata)
                elif isinstance(rec, Attachment):
                    try:
                        out.attachments[rec.name] = rec.data.decode()
                    except UnicodeDecodeError:
                        pass
        except Exception as exc:  # noqa: BLE001  (damage: keep what came before)
            reason = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
            out.problems.append(f"{p}: damaged or truncated after {len(out.messages)} messages "
                                f"({type(exc).__name__}: {reason}); kept those")
    for topic, n in bad.items():
        out.problems.append(f"{p}: topic {topic}: {n} messages did not decode; skipped them")
    for line in out.problems:
        say(line)
    return out
