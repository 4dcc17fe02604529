"""MCAP recordings: raw station packets with receive time, the arena config, outputs, truth.

One file holds everything needed to re-run the pipeline offline (`visionpos replay`)
or to calibrate: every received station packet exactly as it arrived (raw bytes,
log_time = receive time on the server's monotonic clock, the sender's address in
the channel metadata), the arena config as YAML, the fused BodyStates, simulator
ground truth and any JSON side channel (events, stats, camera truth).

Layout (MCAP profile "visionpos"):
    metadata "visionpos.config"   {"yaml": arena config}
    metadata "visionpos.meta"     {"json": free-form meta: start times, host, version, ...}
    /station/packets   message_encoding "visionpos.station", no schema, one channel per sender
                       (channel metadata: host, port); data = the UDP payload, untouched
    /fusion/states     json, schema visionpos.BodyState
    /fusion/markers    json {"points": [[x, y, z], ...], "residual_px": [...]}: loose markers (no body)
    /sim/truth         json, schema visionpos.Truth
    /foxglove/...      protobuf, schemas foxglove.* (visionpos/foxglove/channels.py): the 3-D scene, the
                       cameras' blobs and health as Foxglove and Lichtblick show them, at a bounded rate
    any other topic    json, no schema (write_json)

Crash safety: the file is written *unchunked* (every record goes straight to the data
section) and a background thread moves what was written to the OS every
FLUSH_INTERVAL_S, each time followed by a provisional end: DataEnd, a Footer with no
summary (summary_start 0) and the closing magic, which the next flush overwrites with
new data and a new provisional end, in one write. A writer killed with SIGKILL therefore
leaves a complete MCAP file without a summary, ending at its last flush: any MCAP reader
(mcap's own `make_reader(f).iter_messages()`, Foxglove) reads it linearly, losing at most
the last FLUSH_INTERVAL_S of data. close() replaces the provisional end with the summary,
its indexes and the real footer. A kill landing inside a flush's write, or a power cut, can
leave a torn end: visionpos's reader still reads everything before it, and
`visionpos recover` (recover()) rewrites any damaged file as a clean, indexed one.

A write error (disk full) stops the recording, not the caller: the provisional end is put
back after the last complete flush (its bytes were already on disk, so this needs no new
space), one error is logged, and later writes are counted as dropped.

Bounded state: packets get one channel per sender (host, port) for the first
max_sources senders (MAX_PACKET_SOURCES); packets from any further sender share one
overflow channel (metadata overflow: "true", no address), so spoofed source ports
cannot grow the channel table. A cleanly closed file ends its data with metadata
"visionpos.end" {"json": counts per topic, sources, overflow, dropped, error}.

The writer's calling thread never touches the disk: records are appended to an
in-memory spool under a lock.
"""

from __future__ import annotations

import atexit
import errno
import io
import json
import logging
import math
import mmap
import os
import socket
import struct
import threading
import time
import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from mcap.data_stream import ReadDataStream, RecordBuilder
from mcap.exceptions import McapError
from mcap.opcode import Opcode
from mcap.reader import make_reader
from mcap.records import Channel, Chunk, DataEnd, Footer, Header, Message, Metadata, Schema
from mcap.stream_reader import breakup_chunk
from mcap.writer import CompressionType, IndexType, Writer

from visionpos import __version__
from visionpos.config.arena import parse_arena
from visionpos.errors import VisionposError
from visionpos.foxglove.channels import DEFAULT_RATE_HZ, TOPIC_PREFIX, FoxgloveChannels
from visionpos.foxglove.protobuf import file_descriptor_set
from visionpos.messages import BodyState

log = logging.getLogger(__name__)

PROFILE = "visionpos"
FORMAT_VERSION = 1
TOPIC_PACKETS = "/station/packets"
TOPIC_STATES = "/fusion/states"
TOPIC_TRUTH = "/sim/truth"
TOPIC_MARKERS = "/fusion/markers"
TOPIC_HEALTH = "/server/health"
TOPIC_EVENTS = "/server/events"
PACKET_ENCODING = "visionpos.station"
FLUSH_INTERVAL_S = 0.25
# senders with their own packet channel; the rest share one. Far above any arena's station
# count (and their reconnects, each from a new port), far below what a flood of spoofed
# ports would make
MAX_PACKET_SOURCES = 64
_OVERFLOW_SOURCES_COUNTED = 1024  # distinct overflow senders counted exactly up to this many
META_END = "visionpos.end"
_MAX_RECORD = 64 * 2**20  # a corrupted length field must not make the reader allocate GiB
_MAGIC = b"\x89MCAP0\r\n"
_RECORD_HEAD = struct.Struct("<BQ")  # opcode, content length
_MESSAGE_HEAD = struct.Struct("<HIQQ")  # channel id, sequence, log time, publish time


def _provisional_end() -> bytes:
    b = RecordBuilder()
    DataEnd(0).write(b)  # crc 0: not computed
    Footer(0, 0, 0).write(b)  # summary_start 0: no summary, readers read the data section linearly
    b.write(_MAGIC)
    return b.end()


_PROVISIONAL_END = _provisional_end()
# the records the reader uses, parsed by mcap's classes (messages are parsed in _records)
_RECORD_TYPES = {Opcode.HEADER: Header, Opcode.SCHEMA: Schema, Opcode.CHANNEL: Channel, Opcode.METADATA: Metadata,
                 Opcode.CHUNK: Chunk, Opcode.FOOTER: Footer}

_STATE_SCHEMA = {
    "title": "visionpos.BodyState",
    "type": "object",
    "description": "Filtered rigid-body pose (SI units, world z up, quaternion x,y,z,w body->world).",
    "properties": {
        "name": {"type": "string"},
        "body_id": {"type": "integer"},
        "time_ns": {"type": "integer"},
        "capture_ns": {"type": "integer"},
        "position": {"type": "array", "items": {"type": ["number", "null"]}},
        "quaternion": {"type": "array", "items": {"type": ["number", "null"]}},
        "velocity": {"type": "array", "items": {"type": ["number", "null"]}},
        "angular_velocity": {"type": "array", "items": {"type": ["number", "null"]}},
        "covariance": {"type": "array", "items": {"type": ["number", "null"]}, "description": "6x6 row-major"},
        "velocity_covariance": {"type": "array", "items": {"type": ["number", "null"]},
                                "description": "3x3 row-major"},
        "tracked": {"type": "boolean"},
        "n_markers": {"type": "integer"},
        "n_cameras": {"type": "integer"},
        "residual_mm": {"type": ["number", "null"]},
        "reset_counter": {"type": "integer"},
        "update_kind": {"type": "string", "enum": ["", "pose", "views"],
                        "description": "last measurement that kept the body tracked: triangulated pose or "
                                       "single-camera views"},
    },
}
_TRUTH_SCHEMA = {
    "title": "visionpos.Truth",
    "type": "object",
    "description": "Simulator ground truth of one body (m, quaternion x,y,z,w body->world).",
    "properties": {
        "name": {"type": "string"},
        "position": {"type": "array", "items": {"type": "number"}},
        "quaternion": {"type": "array", "items": {"type": "number"}},
    },
}


class RecordingError(VisionposError, ValueError):
    """A recording that cannot be read. str() names the file and what is wrong."""


class RecordingDamagedWarning(UserWarning):
    """The recording ends early (writer killed, disk full) or is corrupt part-way; data before it was read."""


# ---------------------------------------------------------------- encoding helpers


def _plain(obj: Any) -> Any:
    """numpy scalars/arrays -> plain Python, NaN/inf -> None, so YAML/JSON can hold them."""
    if isinstance(obj, dict):
        return {k: _plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_plain(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _plain(obj.tolist())
    if isinstance(obj, np.generic):
        obj = obj.item()
    if isinstance(obj, float) and not math.isfinite(obj):
        return None  # strict JSON (Foxglove) has no NaN/inf
    return obj


def _num(x: float) -> float | None:
    return None if not math.isfinite(x) else x


def _list(a: Any) -> list[float | None]:
    """Flat list of floats; NaN/inf -> null (an untracked state's pose is NaN by design)."""
    v = np.asarray(a, dtype=np.float64).ravel()
    if np.isfinite(v).all():
        return v.tolist()
    return [x if math.isfinite(x) else None for x in v.tolist()]


def state_to_dict(s: BodyState) -> dict[str, Any]:
    """BodyState -> JSON-able dict (arrays flattened row-major; NaN -> null)."""
    return {
        "name": s.name,
        "body_id": int(s.body_id),
        "time_ns": int(s.time_ns),
        "capture_ns": int(s.capture_ns),
        "position": _list(s.position),
        "quaternion": _list(s.quaternion),
        "velocity": _list(s.velocity),
        "angular_velocity": _list(s.angular_velocity),
        "covariance": _list(s.covariance),
        "velocity_covariance": _list(s.velocity_covariance),
        "tracked": bool(s.tracked),
        "n_markers": int(s.n_markers),
        "n_cameras": int(s.n_cameras),
        "residual_mm": _num(float(s.residual_mm)),
        "reset_counter": int(s.reset_counter),
        "update_kind": str(s.update_kind),
    }


def state_from_dict(d: dict[str, Any]) -> BodyState:
    """Inverse of state_to_dict. Raises KeyError/ValueError on a malformed dict."""

    def arr(key: str, shape: tuple[int, ...]) -> np.ndarray:
        return np.asarray(d[key], dtype=np.float64).reshape(shape)  # null -> NaN

    res = d.get("residual_mm")
    return BodyState(
        name=str(d["name"]),
        body_id=int(d["body_id"]),
        time_ns=int(d["time_ns"]),
        capture_ns=int(d["capture_ns"]),
        position=arr("position", (3,)),
        quaternion=arr("quaternion", (4,)),
        velocity=arr("velocity", (3,)),
        angular_velocity=arr("angular_velocity", (3,)),
        covariance=arr("covariance", (6, 6)),
        velocity_covariance=arr("velocity_covariance", (3, 3)),
        tracked=bool(d["tracked"]),
        n_markers=int(d.get("n_markers", 0)),
        n_cameras=int(d.get("n_cameras", 0)),
        residual_mm=float("nan") if res is None else float(res),
        reset_counter=int(d.get("reset_counter", 0)),
        update_kind=str(d.get("update_kind", "")),  # recordings before issue 15 have none
    )


def _dumps(obj: Any) -> bytes:
    # allow_nan=False: a NaN would make the file unreadable for strict JSON tools (Foxglove)
    return json.dumps(obj, separators=(",", ":"), allow_nan=False).encode()


def _realtime_minus_monotonic(meta: dict[str, Any]) -> int | None:
    """The recording host's CLOCK_REALTIME - monotonic difference at the start, from its meta."""
    wall, mono = meta.get("wall_start_unix_ns"), meta.get("monotonic_start_ns")
    return wall - mono if isinstance(wall, int) and isinstance(mono, int) else None


def _arena_cameras(config: Any) -> tuple[Any, ...]:
    """The calibrated cameras of a recording's config: an ArenaConfig's, or parsed from the raw mapping
    (a mapping that is no valid arena, as some tools record, has none)."""
    cams = getattr(config, "cameras", None)
    if cams is not None:
        return tuple(cams)
    try:
        return parse_arena(getattr(config, "raw", config)).cameras
    except (VisionposError, TypeError, ValueError) as e:
        log.debug("recording config is no arena (%s): Foxglove channels without cameras", e)
        return ()


# ---------------------------------------------------------------- writer


class _Spool:
    """File-like sink for mcap.Writer: appends to memory; a flusher thread moves it to disk.

    Only tell() and write() are needed by the writer (unchunked mode). tell() is the
    offset in the file, which the writer's summary indexes rely on.
    """

    def __init__(self) -> None:
        self.parts: list[bytes] = []
        self.pos = 0
        self.messages = 0  # messages in parts

    def write(self, b: bytes) -> int:
        self.parts.append(b)
        self.pos += len(b)
        return len(b)

    def tell(self) -> int:
        return self.pos

    def flush(self) -> None:  # the flusher thread owns disk writes
        pass


class RecordingWriter:
    """Write a visionpos MCAP recording. Cheap to call from an event loop; crash-safe.

    config: the arena config mapping (ArenaConfig.raw; an object with `.raw` is accepted).
    meta: free-form JSON-able facts (scenario, seed, command line ...). The writer adds
    version, host, wall-clock and monotonic start times.
    max_sources: senders that get their own packet channel; later ones share one.
    foxglove_rate_hz: the Foxglove channels' update rate (visionpos/foxglove/channels.py); 0 or None:
    no Foxglove channels. Cameras for them come from the config (an ArenaConfig, or a raw mapping
    that parses as an arena; one that does not gets the channels without cameras).
    realtime_minus_monotonic_ns: for the Foxglove blobs of realtime-stamped stations (None: the meta's
    wall_start_unix_ns - monotonic_start_ns, this host's at the start unless meta gives them).

    All write_* methods are thread-safe; none does disk I/O on the caller's thread, and
    none raises because of the disk: after a write error they only count what they drop.
    """

    def __init__(self, path: str | Path, config: dict[str, Any] | Any, meta: dict[str, Any] | None = None,
                 flush_interval_s: float = FLUSH_INTERVAL_S, max_sources: int = MAX_PACKET_SOURCES,
                 foxglove_rate_hz: float | None = DEFAULT_RATE_HZ, realtime_minus_monotonic_ns: int | None = None):
        self.path = Path(path)
        raw = getattr(config, "raw", config)
        if not isinstance(raw, dict):
            raise TypeError(f"RecordingWriter: config must be a mapping (arena YAML), got {type(raw).__name__}")
        if max_sources < 1:
            raise ValueError(f"RecordingWriter: max_sources must be >= 1, got {max_sources}")
        try:
            self._fd = os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC | getattr(os, "O_CLOEXEC", 0), 0o644)
        except OSError as e:
            raise RecordingError(f"{self.path}: cannot create recording: {e.strerror or e}") from None
        self._lock = threading.Lock()  # the spool and the mcap writer
        self._io_lock = threading.Lock()  # the file: one flush at a time
        self._spool = _Spool()
        self._closed = False
        self._flush_interval = float(flush_interval_s)
        self._write_error: OSError | None = None
        self._data_end = 0  # file offset of the provisional end: where the next flush writes
        self.counts: dict[str, int] = {}
        self.bytes_written = 0
        self.messages_on_disk = 0
        self.dropped = 0  # messages not recorded because of a write error
        self._max_sources = int(max_sources)
        self._overflow_channel: int | None = None
        self._overflow_sources: set[tuple[str, int]] = set()
        self.overflow_packets = 0
        self._w = Writer(
            self._spool,
            compression=CompressionType.NONE,
            use_chunking=False,
            index_types=IndexType.METADATA,
            enable_crcs=True,
        )
        self._w.start(profile=PROFILE, library=f"visionpos {__version__}")
        full_meta = {
            "format_version": FORMAT_VERSION,
            "visionpos_version": __version__,
            "host": socket.gethostname(),
            "wall_start_unix_ns": time.time_ns(),
            "monotonic_start_ns": time.monotonic_ns(),
            **_plain(meta or {}),
        }
        self._w.add_metadata("visionpos.config", {"yaml": yaml.safe_dump(_plain(raw), sort_keys=False)})
        self._w.add_metadata("visionpos.meta", {"json": json.dumps(full_meta)})
        self._state_schema = self._w.register_schema("visionpos.BodyState", "jsonschema", _dumps(_STATE_SCHEMA))
        self._truth_schema = self._w.register_schema("visionpos.Truth", "jsonschema", _dumps(_TRUTH_SCHEMA))
        self._packet_channels: dict[tuple[str, int] | None, int] = {}
        self._topic_channels: dict[str, int] = {}
        self._seq = 0
        self._fox_schemas: dict[str, int] = {}
        self.foxglove: FoxgloveChannels | None = None
        if foxglove_rate_hz:
            rt = realtime_minus_monotonic_ns
            if rt is None:  # the difference the recording states, as replay and foxglove_copy use it
                rt = _realtime_minus_monotonic(full_meta)
            self.foxglove = FoxgloveChannels(_arena_cameras(config), foxglove_rate_hz, rt)
        self._flush_to_disk()  # header + config on disk before any data arrives
        if self._write_error is not None:
            os.close(self._fd)
            err = self._write_error
            raise RecordingError(f"{self.path}: cannot write recording: {err.strerror or err}")
        self._stop = threading.Event()
        self._flusher = threading.Thread(target=self._flush_loop, name=f"mcap-flush:{self.path.name}", daemon=True)
        self._flusher.start()
        # an interpreter exiting without close() (an exception in the server) still ends the file cleanly
        atexit.register(self.close)

    # -- context manager
    def __enter__(self) -> "RecordingWriter":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    # -- writes (all under self._lock)
    def _channel_for(self, topic: str, encoding: str, schema_id: int) -> int:
        ch = self._topic_channels.get(topic)
        if ch is None:
            ch = self._w.register_channel(topic, encoding, schema_id)
            self._topic_channels[topic] = ch
        return ch

    def _recording(self) -> bool:
        """False once closed (raises) or stopped by a write error (counts the drop)."""
        if self._closed:
            raise RuntimeError(f"{self.path}: recording is closed")
        if self._write_error is not None:
            self.dropped += 1
            return False
        return True

    def _add(self, channel: int, log_ns: int, data: bytes, topic: str) -> None:
        self._seq += 1
        self._w.add_message(channel, log_ns, data, log_ns, self._seq & 0xFFFFFFFF)
        self._spool.messages += 1
        self.counts[topic] = self.counts.get(topic, 0) + 1

    def _source_channel(self, source: tuple[str, int] | None) -> int:
        """A new sender's channel: its own while there are fewer than max_sources, else the shared one."""
        if len(self._packet_channels) < self._max_sources:
            md = {} if source is None else {"host": str(source[0]), "port": str(int(source[1]))}
            ch = self._packet_channels[source] = self._w.register_channel(TOPIC_PACKETS, PACKET_ENCODING, 0, md)
            return ch
        self.overflow_packets += 1
        if len(self._overflow_sources) < _OVERFLOW_SOURCES_COUNTED and source is not None:
            self._overflow_sources.add(source)
        if self._overflow_channel is None:
            self._overflow_channel = self._w.register_channel(TOPIC_PACKETS, PACKET_ENCODING, 0,
                                                              {"overflow": "true"})
            log.warning("%s: more than %d packet senders; the packets of later ones share one channel without "
                        "their address", self.path, self._max_sources)
        return self._overflow_channel

    def _add_foxglove(self, out: list[tuple[str, str, int, bytes]]) -> None:
        """Foxglove messages (topic, schema name, log time, protobuf bytes); lock held."""
        for topic, schema, t, data in out:
            ch = self._topic_channels.get(topic)
            if ch is None:
                ch = self._channel_for(topic, "protobuf", _protobuf_schema(self._w, self._fox_schemas, schema))
            self._add(ch, t, data, topic)

    def _foxglove_out(self, out: list[tuple[str, str, int, bytes]]) -> None:
        if out:
            with self._lock:
                if self._recording():
                    self._add_foxglove(out)

    def write_packet(self, recv_ns: int, data: bytes, source: tuple[str, int] | None = None) -> None:
        """One received UDP payload, untouched, stamped with its receive time (server monotonic ns)."""
        fox = self.foxglove.packet(recv_ns, data) if self.foxglove is not None else None
        with self._lock:
            if self._closed or self._write_error is not None:  # inline: this runs for every packet
                self._recording()
                return
            ch = self._packet_channels.get(source)
            if ch is None:
                ch = self._source_channel(source)
            self._add(ch, int(recv_ns), bytes(data), TOPIC_PACKETS)
            if fox:
                self._add_foxglove(fox)

    def write_state(self, state: BodyState) -> None:
        """One fused BodyState, logged at its time_ns."""
        data = _dumps(state_to_dict(state))
        with self._lock:
            if self._recording():
                ch = self._channel_for(TOPIC_STATES, "json", self._state_schema)
                self._add(ch, int(state.time_ns), data, TOPIC_STATES)

    def write_states(self, states: list[BodyState]) -> None:
        """One output tick's states (the Foxglove bodies are updated from ticks, so give them together)."""
        for s in states:
            self.write_state(s)
        if self.foxglove is not None:
            self._foxglove_out(self.foxglove.states(states))

    def publish(self, states: list[BodyState]) -> None:
        """Sink interface (server output tick): record the outputs."""
        self.write_states(states)

    def publish_markers(self, lp) -> None:
        """Sink interface: a new set of loose markers (LoosePoints), logged at its time_ns."""
        data = _dumps({"points": _plain(lp.points), "residual_px": _plain(lp.residual_px)})
        fox = self.foxglove.markers(int(lp.time_ns), lp.points) if self.foxglove is not None else None
        with self._lock:
            if self._recording():
                ch = self._channel_for(TOPIC_MARKERS, "json", 0)
                self._add(ch, int(lp.time_ns), data, TOPIC_MARKERS)
                if fox:
                    self._add_foxglove(fox)

    def write_truth(self, time_ns: int, name: str, position: np.ndarray, quaternion: np.ndarray) -> None:
        """Simulator ground truth of body `name`: position (3,) m, quaternion (4,) xyzw."""
        p = np.asarray(position, dtype=float).ravel()
        q = np.asarray(quaternion, dtype=float).ravel()
        if p.shape != (3,) or q.shape != (4,):
            raise ValueError(f"write_truth: position must be (3,) and quaternion (4,), got {p.shape}, {q.shape}")
        data = _dumps({"name": str(name), "position": p.tolist(), "quaternion": q.tolist()})
        with self._lock:
            if self._recording():
                ch = self._channel_for(TOPIC_TRUTH, "json", self._truth_schema)
                self._add(ch, int(time_ns), data, TOPIC_TRUTH)

    def write_json(self, topic: str, time_ns: int, obj: dict[str, Any]) -> None:
        """Any JSON-able mapping on its own topic (events, camera truth, stats).

        /server/health and /server/events also go to the Foxglove log.
        """
        if topic in (TOPIC_PACKETS, TOPIC_STATES, TOPIC_TRUTH, TOPIC_MARKERS) or topic.startswith(TOPIC_PREFIX):
            raise ValueError(
                f"write_json: topic {topic!r} is reserved; use write_packet/write_state/write_truth/publish_markers"
            )
        data = _dumps(_plain(obj))
        fox = None
        if self.foxglove is not None and topic in (TOPIC_HEALTH, TOPIC_EVENTS):
            fox = (self.foxglove.health if topic == TOPIC_HEALTH else self.foxglove.event)(int(time_ns), obj)
        with self._lock:
            if self._recording():
                ch = self._channel_for(topic, "json", 0)
                self._add(ch, int(time_ns), data, topic)
                if fox:
                    self._add_foxglove(fox)

    # -- disk
    def _pwrite_all(self, data: bytes, offset: int) -> None:
        view = memoryview(data)
        while view:
            n = os.pwrite(self._fd, view, offset)
            if n <= 0:  # a regular file accepts nothing more only when the disk is full
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
            view = view[n:]
            offset += n

    def _flush_to_disk(self, final: bool = False) -> None:
        """Write the spool at the provisional end, followed by a new one (by the summary when final).

        One write per flush: a file cut anywhere but inside it is a complete MCAP file.
        """
        with self._io_lock:
            with self._lock:
                parts, self._spool.parts = self._spool.parts, []
                n_messages, self._spool.messages = self._spool.messages, 0
                failed = self._write_error is not None
                if failed:  # written between the failed flush and the stop: lost too
                    self.dropped += n_messages
            if failed or (not parts and not final):
                return
            data = b"".join(parts)
            buf = data if final else data + _PROVISIONAL_END
            try:
                self._pwrite_all(buf, self._data_end)
                if final:  # the summary is longer than the provisional end, but make sure
                    os.ftruncate(self._fd, self._data_end + len(buf))
            except OSError as e:
                self._stop_on_error(e, n_messages)
                return
            self._data_end += len(data)
            self.messages_on_disk += n_messages
            self.bytes_written = self._data_end + len(buf) - len(data)

    def _stop_on_error(self, err: OSError, lost: int) -> None:
        """Stop recording after a failed write; end the file after the last complete flush."""
        with self._lock:
            self._write_error = err
            self.dropped += lost
        if self._data_end == 0:  # nothing on disk yet: __init__ reports it
            return
        try:
            # these bytes were on disk before the failed write: rewriting them needs no new space
            self._pwrite_all(_PROVISIONAL_END, self._data_end)
            os.ftruncate(self._fd, self._data_end + len(_PROVISIONAL_END))
            readable = "a complete MCAP file without a summary, readable by any MCAP reader"
            self.bytes_written = self._data_end + len(_PROVISIONAL_END)
        except OSError:
            try:
                os.ftruncate(self._fd, self._data_end)
                self.bytes_written = self._data_end
            except OSError:
                pass
            readable = f"readable by visionpos; `visionpos recover {self.path}` makes it a clean MCAP file"
        log.error("%s: recording stopped, writing failed (%s). The file keeps the %d messages (%d bytes) recorded "
                  "before the error: %s. The server goes on without recording.", self.path,
                  err.strerror or err, self.messages_on_disk, self.bytes_written, readable)

    def _flush_loop(self) -> None:
        while not self._stop.wait(self._flush_interval):
            try:
                self._flush_to_disk()
            except Exception:  # keep flushing: a dead flusher would let the spool grow without bound
                log.exception("%s: flushing the recording failed", self.path)

    def flush(self) -> None:
        """Move everything written so far to the OS now."""
        self._flush_to_disk()

    def _end_meta(self) -> dict[str, Any]:
        return {
            "messages": dict(self.counts),
            "packet_sources": len(self._packet_channels),
            "max_sources": self._max_sources,
            "overflow_sources": len(self._overflow_sources),
            "overflow_sources_counted_up_to": _OVERFLOW_SOURCES_COUNTED,
            "overflow_packets": self.overflow_packets,
            "wall_end_unix_ns": time.time_ns(),
            "monotonic_end_ns": time.monotonic_ns(),
        }

    def close(self) -> None:
        """Write the summary and footer and close. Idempotent; nothing already written is lost.

        After a write error the file keeps its provisional end (no summary).
        """
        if self._closed:
            return
        atexit.unregister(self.close)
        self._stop.set()
        self._flusher.join()
        with self._lock:
            self._closed = True
            if self._write_error is None:
                self._w.add_metadata(META_END, {"json": json.dumps(self._end_meta())})
                self._w.finish()
        self._flush_to_disk(final=True)
        try:
            os.fsync(self._fd)
        except OSError:
            pass
        os.close(self._fd)

    def stats(self) -> dict[str, Any]:
        """messages: handed to the recorder per topic; recorded: messages on disk; dropped: messages
        lost to a write error (the failed write's and every later one)."""
        return {"path": str(self.path), "messages": dict(self.counts), "bytes": self.bytes_written,
                "recorded": self.messages_on_disk,
                "packet_sources": len(self._packet_channels), "overflow_sources": len(self._overflow_sources),
                "overflow_packets": self.overflow_packets, "dropped": self.dropped,
                "error": None if self._write_error is None else str(self._write_error)}


# ---------------------------------------------------------------- reader


class RecordingReader:
    """Read a visionpos recording, tolerating a missing footer and a truncated last record.

    .config -> dict, .meta -> dict; packets()/states()/truth()/json(topic)/messages() stream
    from the file each time they are called. .complete is True for a cleanly closed file (with
    its summary); end() returns the writer's closing counts. A damaged tail emits one RecordingDamagedWarning
    per reader and `.damage` names it; everything before it is returned.
    """

    def __init__(self, path: str | Path):
        self.path = Path(path)
        if not self.path.is_file():
            raise RecordingError(f"{self.path}: no such recording file")
        with open(self.path, "rb") as f:
            magic = f.read(8)
            f.seek(0, os.SEEK_END)
            size = f.tell()
            f.seek(max(0, size - len(_PROVISIONAL_END)))
            tail = f.read(len(_PROVISIONAL_END))
        if magic != _MAGIC:
            raise RecordingError(
                f"{self.path}: not an MCAP file (starts with {magic[:8]!r}); "
                "expected a recording written by `visionpos serve --record` or `visionpos record`"
            )
        self.damage: str | None = None
        self._warned = False
        # a cleanly closed file ends with its summary, footer and magic; a writer killed or stopped by
        # a write error leaves its provisional end (no summary), or a torn end if killed mid-write
        unclosed = tail == _PROVISIONAL_END
        self.complete = size > 16 and tail[-len(_MAGIC):] == magic and not unclosed
        config = meta = None
        header_seen = False
        for rec in self._records(stop_at_message=True):
            if isinstance(rec, Header):
                header_seen = True
                if rec.profile != PROFILE:
                    raise RecordingError(
                        f"{self.path}: MCAP profile is {rec.profile!r}, not {PROFILE!r}: "
                        "this is not a visionpos recording"
                    )
            elif isinstance(rec, Metadata) and rec.name == "visionpos.config":
                config = self._parse_config(rec.metadata.get("yaml", ""))
            elif isinstance(rec, Metadata) and rec.name == "visionpos.meta":
                try:
                    meta = json.loads(rec.metadata.get("json", "{}"))
                except json.JSONDecodeError as e:
                    raise RecordingError(f"{self.path}: metadata 'visionpos.meta' is not valid JSON: {e}") from None
            if config is not None and meta is not None:
                break
        if not header_seen:
            raise RecordingError(f"{self.path}: MCAP file has no header record (truncated right after the magic?)")
        if config is None:
            raise RecordingError(f"{self.path}: no 'visionpos.config' metadata: not a visionpos recording, "
                                 "or it was cut off before the config was written")
        self.config: dict[str, Any] = config
        self.meta: dict[str, Any] = meta or {}
        if int(self.meta.get("format_version", FORMAT_VERSION)) > FORMAT_VERSION:
            raise RecordingError(f"{self.path}: recording format {self.meta['format_version']} is newer than this "
                                 f"visionpos ({FORMAT_VERSION}); upgrade visionpos")
        if unclosed:
            self._damaged("recording was not closed (its writer was killed or stopped by a write error such as a "
                          "full disk): it ends at the writer's last flush, without a summary")

    def end(self) -> dict[str, Any] | None:
        """The writer's closing counts (metadata "visionpos.end": messages per topic, packet_sources,
        overflow_sources, overflow_packets, ...), or None when it never closed (killed, disk full)."""
        if not self.complete:
            return None
        try:
            with open(self.path, "rb") as f:
                for md in make_reader(f).iter_metadata():  # through the summary's metadata index
                    if md.name == META_END:
                        return json.loads(md.metadata.get("json", "{}"))
        except (McapError, struct.error, EOFError, ValueError) as e:
            raise RecordingError(f"{self.path}: summary is damaged ({type(e).__name__}: {e})") from None
        return None

    def _parse_config(self, text: str) -> dict[str, Any]:
        try:
            cfg = yaml.safe_load(text)
        except yaml.YAMLError as e:
            raise RecordingError(f"{self.path}: recorded config is not valid YAML: {e}") from None
        if not isinstance(cfg, dict):
            raise RecordingError(f"{self.path}: recorded config is not a mapping")
        return cfg

    def _damaged(self, what: str) -> None:
        self.damage = what
        if not self._warned:
            self._warned = True
            warnings.warn(RecordingDamagedWarning(f"{self.path}: {what}; using everything before it"), stacklevel=3)

    def _records(self, stop_at_message: bool = False, message_records: bool = False) -> Iterator[Any]:
        """The data records in file order: a message as a tuple (channel id, log time ns, data),
        or as mcap's Message when message_records, the others the reader uses (Header, Schema,
        Channel, Metadata) as mcap's record objects.

        Messages are parsed here, straight from the mapped file: mcap's StreamReader takes
        about ten reads and calls per record, which made reading the log a tenth of a
        replay. Chunks (files from other MCAP writers) are unpacked by mcap. Stops at the
        footer; anything damaged before it ends the stream with one warning.
        """
        with open(self.path, "rb") as f, mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as mm:
            size = len(mm)
            pos = len(_MAGIC)
            n = 0
            while True:
                if pos + _RECORD_HEAD.size > size:
                    what = "ends inside a record header" if pos < size else "ends without a footer"
                    self._damaged(f"recording {what} after {n} records (byte {pos}); the writer was probably killed")
                    return
                op, length = _RECORD_HEAD.unpack_from(mm, pos)
                start = pos + _RECORD_HEAD.size
                pos = start + length
                if length > _MAX_RECORD or pos > size:
                    kind = "is corrupt" if length > _MAX_RECORD else "ends"
                    self._damaged(f"recording {kind} after {n} records (record at byte {start - 9} says it is "
                                  f"{length} bytes, {size - start} left); the writer was probably killed")
                    return
                n += 1
                if op == Opcode.MESSAGE:
                    if length < _MESSAGE_HEAD.size:
                        self._damaged(f"recording is corrupt after {n - 1} records (a {length}-byte message at "
                                      f"byte {start - 9})")
                        return
                    if stop_at_message:
                        return
                    cid, seq, log_time, pub_time = _MESSAGE_HEAD.unpack_from(mm, start)
                    if message_records:
                        yield Message(cid, log_time, mm[start + _MESSAGE_HEAD.size:pos], pub_time, seq)
                    else:
                        yield cid, log_time, mm[start + _MESSAGE_HEAD.size:pos]
                    continue
                kind = _RECORD_TYPES.get(op)
                if kind is None:  # indexes, statistics, attachments, data end: not needed
                    continue
                try:
                    rec = kind.read(ReadDataStream(io.BytesIO(mm[start:pos])))
                    inner = breakup_chunk(rec) if kind is Chunk else [rec]
                except (McapError, struct.error, EOFError, UnicodeDecodeError, ValueError, MemoryError) as e:
                    self._damaged(f"recording is corrupt after {n - 1} records (near byte {start - 9}, "
                                  f"{type(e).__name__}: {e or 'truncated'})")
                    return
                if kind is Footer:
                    return
                for r in inner:
                    if isinstance(r, Message):
                        if stop_at_message:
                            return
                        yield r if message_records else (r.channel_id, r.log_time, r.data)
                    else:
                        yield r

    def messages(self, topics: set[str] | None = None) -> Iterator[tuple[str, int, bytes, Channel]]:
        """(topic, log_time_ns, data, channel) for every message in file order."""
        channels: dict[int, Channel] = {}
        schemas: dict[int, Schema] = {}
        wanted: dict[int, bool] = {}  # channel id -> its topic is asked for
        for rec in self._records():
            if type(rec) is tuple:
                cid, t, data = rec
                ok = wanted.get(cid)
                if ok is None:
                    if cid not in channels:
                        self._damaged(f"message on unknown channel {cid}")
                        continue
                    ok = wanted[cid] = topics is None or channels[cid].topic in topics
                if ok:
                    ch = channels[cid]
                    yield ch.topic, t, data, ch
            elif isinstance(rec, Schema):
                schemas[rec.id] = rec
            elif isinstance(rec, Channel):
                self._check_channel(rec, schemas)
                channels[rec.id] = rec
                wanted.pop(rec.id, None)

    def _check_channel(self, ch: Channel, schemas: dict[int, Schema]) -> None:
        if ch.topic == TOPIC_PACKETS and ch.message_encoding != PACKET_ENCODING:
            raise RecordingError(f"{self.path}: channel {ch.topic} has message encoding {ch.message_encoding!r}, "
                                 f"expected {PACKET_ENCODING!r}")
        expect = {TOPIC_STATES: "visionpos.BodyState", TOPIC_TRUTH: "visionpos.Truth"}.get(ch.topic)
        if expect is not None:
            sc = schemas.get(ch.schema_id)
            if ch.message_encoding != "json" or sc is None or sc.name != expect:
                got = sc.name if sc is not None else f"schema id {ch.schema_id}"
                raise RecordingError(f"{self.path}: channel {ch.topic} has encoding {ch.message_encoding!r} "
                                     f"and schema {got!r}, expected json with schema {expect!r}")

    def packets(self) -> Iterator[tuple[int, bytes]]:
        """(recv_ns, raw packet bytes) in log order."""
        for _, t, data, _ in self.messages({TOPIC_PACKETS}):
            yield t, data

    def packets_with_source(self) -> Iterator[tuple[int, bytes, tuple[str, int] | None]]:
        """(recv_ns, raw bytes, (host, port) or None) in log order."""
        sources: dict[int, tuple[str, int] | None] = {}
        for _, t, data, ch in self.messages({TOPIC_PACKETS}):
            src = sources.get(ch.id, 0)
            if src == 0:
                md = ch.metadata
                src = sources[ch.id] = (md["host"], int(md["port"])) if "host" in md and "port" in md else None
            yield t, data, src

    def _json(self, topic: str) -> Iterator[tuple[int, dict[str, Any]]]:
        for _, t, data, _ in self.messages({topic}):
            try:
                obj = json.loads(data)
            except (json.JSONDecodeError, UnicodeDecodeError) as e:
                self._damaged(f"message on {topic} at {t} ns is not valid JSON ({e})")
                continue
            yield t, obj

    def states(self) -> Iterator[BodyState]:
        """Recorded BodyStates in log order."""
        for t, d in self._json(TOPIC_STATES):
            try:
                yield state_from_dict(d)
            except (KeyError, ValueError, TypeError) as e:
                self._damaged(f"BodyState at {t} ns is malformed ({type(e).__name__}: {e})")

    def truth(self) -> dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """name -> (times_ns (T,) int64, positions (T, 3), quaternions (T, 4) xyzw), time-sorted."""
        acc: dict[str, tuple[list[int], list[list[float]], list[list[float]]]] = {}
        for t, d in self._json(TOPIC_TRUTH):
            ts, ps, qs = acc.setdefault(str(d.get("name")), ([], [], []))
            ts.append(t)
            ps.append(d["position"])
            qs.append(d["quaternion"])
        out = {}
        for name, (ts, ps, qs) in acc.items():
            t = np.asarray(ts, dtype=np.int64)
            order = np.argsort(t, kind="stable")
            out[name] = (t[order], np.asarray(ps, dtype=float)[order].reshape(-1, 3),
                         np.asarray(qs, dtype=float)[order].reshape(-1, 4))
        return out

    def json(self, topic: str) -> Iterator[tuple[int, dict[str, Any]]]:
        """(log_time_ns, object) for a write_json topic, in log order."""
        return self._json(topic)

    def topics(self) -> dict[str, int]:
        """topic -> message count (reads the whole file)."""
        counts: dict[str, int] = {}
        for topic, _, _, _ in self.messages():
            counts[topic] = counts.get(topic, 0) + 1
        return counts


# ---------------------------------------------------------------- recover

META_RECOVERED = "visionpos.recovered"


def recover(src: str | Path, dst: str | Path) -> dict[str, Any]:
    """Rewrite the recording `src` as a clean MCAP file `dst`: every record before any damage,
    then a summary with statistics, channels and the metadata index, as a cleanly closed
    recording has. Works on a killed writer's file (provisional or torn end), one stopped by
    a full disk, or a complete one. Writes `dst` through a temporary file, never `src`.

    Returns what was done (also stored in dst as metadata "visionpos.recovered"):
    {"from", "messages", "messages_by_topic", "damage" (None or what ended the read), "was_complete"}.
    """
    return _rewrite_file(src, dst, "recover writes a new file", "the recovered recording", None)


def _rewrite_file(src: str | Path, dst: str | Path, same_file: str, what: str,
                  fox_rate_hz: float | None) -> dict[str, Any]:
    """_rewrite of the recording src into dst through dst.part (src never written; a failed write leaves
    no dst). same_file, what: the error wording (dst is src; writing dst failed); fox_rate_hz: build the
    Foxglove channels at this rate (None: copy the records only)."""
    src, dst = Path(src), Path(dst)
    if dst.exists() and dst.resolve() == src.resolve():
        raise RecordingError(f"{dst}: {same_file}; give another output than the input")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RecordingDamagedWarning)  # reported in the result instead
        reader = RecordingReader(src)
        fox = (None if fox_rate_hz is None else
               FoxgloveChannels(_arena_cameras(reader.config), fox_rate_hz, _realtime_minus_monotonic(reader.meta)))
        tmp = dst.with_name(dst.name + ".part")
        try:
            with open(tmp, "wb") as f:
                report = _rewrite(reader, f, fox)
            os.replace(tmp, dst)
        except OSError as e:
            tmp.unlink(missing_ok=True)
            raise RecordingError(f"{dst}: cannot write {what}: {e.strerror or e}") from None
        except BaseException:
            tmp.unlink(missing_ok=True)
            raise
    return report


META_FOXGLOVE_COPY = "visionpos.foxglove_copy"


def foxglove_copy(src: str | Path, dst: str | Path, rate_hz: float = DEFAULT_RATE_HZ) -> dict[str, Any]:
    """Write `dst`: the recording `src` with Foxglove channels (visionpos/foxglove/channels.py) built
    from what it recorded (station packets, outputs, loose markers, health, events), so a recording
    made before them opens in Foxglove or Lichtblick as a 3-D scene. Every record of src is kept;
    Foxglove channels src already has are replaced. A damaged src is copied up to the damage.

    Returns (and stores in dst as metadata "visionpos.foxglove_copy") {"from", "messages",
    "messages_by_topic", "foxglove_messages", "damage", "was_complete"}.
    """
    return _rewrite_file(src, dst, "the Foxglove copy is a new file", "the Foxglove copy", rate_hz)


def _protobuf_schema(w: Writer, registered: dict[str, int], schema: str) -> int:
    """The id of a Foxglove protobuf schema in writer w, registered on first use (registered: name -> id)."""
    sid = registered.get(schema)
    if sid is None:
        sid = registered[schema] = w.register_schema(schema, "protobuf", file_descriptor_set(schema))
    return sid


class _FoxgloveFeed:
    """Feeds a recording's messages, in file order, to FoxgloveChannels; writes what they return."""

    def __init__(self, w: Writer, fox: FoxgloveChannels) -> None:
        self.w, self.fox = w, fox
        self.schemas: dict[str, int] = {}
        self.channels: dict[str, int] = {}
        self.tick: list[BodyState] = []  # the states of one output tick (recorded together, one time_ns)
        self.count = 0

    def _emit(self, out: list[tuple[str, str, int, bytes]]) -> None:
        for topic, schema, t, data in out:
            ch = self.channels.get(topic)
            if ch is None:
                ch = self.channels[topic] = self.w.register_channel(topic, "protobuf",
                                                                    _protobuf_schema(self.w, self.schemas, schema))
            self.w.add_message(ch, t, data, t, 0)
            self.count += 1

    def _end_tick(self) -> None:
        if self.tick:
            self._emit(self.fox.states(self.tick))
            self.tick = []

    def message(self, topic: str, t: int, data: bytes) -> None:
        if topic != TOPIC_STATES:  # the live writer updates the bodies right after the tick's states
            self._end_tick()
        if topic == TOPIC_PACKETS:
            self._emit(self.fox.packet(t, data))
            return
        if topic not in (TOPIC_STATES, TOPIC_MARKERS, TOPIC_HEALTH, TOPIC_EVENTS):
            return
        try:
            obj = json.loads(data)
            if topic == TOPIC_STATES:
                s = state_from_dict(obj)
                if self.tick and self.tick[-1].time_ns != s.time_ns:
                    self._end_tick()
                self.tick.append(s)
            elif topic == TOPIC_MARKERS:
                pts = np.asarray(obj["points"], dtype=np.float64).reshape(-1, 3)  # null -> NaN
                self._emit(self.fox.markers(t, pts[np.isfinite(pts).all(axis=1)]))
            elif topic == TOPIC_HEALTH:
                self._emit(self.fox.health(t, obj))
            else:
                self._emit(self.fox.event(t, obj))
        except (json.JSONDecodeError, UnicodeDecodeError, KeyError, ValueError, TypeError):
            return  # a malformed side-channel message: nothing to show for it

    def finish(self) -> None:
        self._end_tick()


def _rewrite(reader: RecordingReader, f: Any, fox: FoxgloveChannels | None = None) -> dict[str, Any]:
    """Copy every record of reader to f with a summary; with fox, also the Foxglove channels (a
    Foxglove copy: src's own /foxglove/ channels are left out, fox writes them anew)."""
    w = Writer(f, compression=CompressionType.NONE, use_chunking=False, index_types=IndexType.METADATA,
               enable_crcs=True)
    schemas: dict[int, int] = {}  # id in the input -> id in the output
    channels: dict[int, tuple[int, str]] = {}  # id in the input -> (id in the output, topic)
    by_topic: dict[str, int] = {}
    started = False
    feed = None
    for rec in reader._records(message_records=True):
        if isinstance(rec, Message):
            ch = channels.get(rec.channel_id)
            if ch is None:  # the reader has flagged it (damage) or it is a replaced Foxglove channel
                continue
            w.add_message(ch[0], rec.log_time, rec.data, rec.publish_time, rec.sequence)
            by_topic[ch[1]] = by_topic.get(ch[1], 0) + 1
            if feed is not None:
                feed.message(ch[1], rec.log_time, rec.data)
        elif isinstance(rec, Header):
            if not started:
                w.start(profile=rec.profile, library=rec.library)
                started = True
                feed = None if fox is None else _FoxgloveFeed(w, fox)
        elif isinstance(rec, Schema):
            if rec.id not in schemas:  # a complete file repeats schemas and channels in its summary
                schemas[rec.id] = w.register_schema(rec.name, rec.encoding, rec.data)
        elif isinstance(rec, Channel):
            if fox is not None and rec.topic.startswith(TOPIC_PREFIX):
                continue
            if rec.id not in channels:
                sid = schemas.get(rec.schema_id, 0)
                channels[rec.id] = (w.register_channel(rec.topic, rec.message_encoding, sid, dict(rec.metadata)),
                                    rec.topic)
        elif isinstance(rec, Metadata) and rec.name not in (META_RECOVERED, META_FOXGLOVE_COPY):
            w.add_metadata(rec.name, dict(rec.metadata))
    report = {"from": str(reader.path), "messages": sum(by_topic.values()), "messages_by_topic": by_topic,
              "damage": reader.damage, "was_complete": reader.complete}
    if feed is not None:
        feed.finish()
        report["foxglove_messages"] = feed.count
    w.add_metadata(META_FOXGLOVE_COPY if fox is not None else META_RECOVERED, {"json": json.dumps(report)})
    w.finish()
    return report
