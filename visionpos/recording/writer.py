"""RecordingWriter: a crash-safe, unchunked MCAP writer whose caller never touches the disk (see the package
docstring: the provisional end, write errors, bounded packet channels)."""

from __future__ import annotations

import atexit
import errno
import json
import logging
import os
import socket
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from mcap.writer import CompressionType, IndexType, Writer

from visionpos import __version__
from visionpos.foxglove.channels import DEFAULT_RATE_HZ, TOPIC_PREFIX, FoxgloveChannels
from visionpos.messages import BodyState
from visionpos.recording.codec import (
    FORMAT_VERSION,
    IMU_SCHEMA,
    META_END,
    PACKET_ENCODING,
    PROFILE,
    PROVISIONAL_END,
    STATE_SCHEMA,
    TOPIC_EVENTS,
    TOPIC_HEALTH,
    TOPIC_IMU,
    TOPIC_MARKERS,
    TOPIC_PACKETS,
    TOPIC_STATES,
    TOPIC_TRUTH,
    TRUTH_SCHEMA,
    RecordingError,
    arena_cameras,
    imu_to_dict,
    json_bytes,
    plain,
    protobuf_schema,
    realtime_minus_monotonic,
    state_to_dict,
)

log = logging.getLogger(__name__)

FLUSH_INTERVAL_S = 0.25
# senders with their own packet channel; the rest share one. Far above any arena's station
# count (and their reconnects, each from a new port), far below what a flood of spoofed
# ports would make
MAX_PACKET_SOURCES = 64
_OVERFLOW_SOURCES_COUNTED = 1024  # distinct overflow senders counted exactly up to this many
# keys of the arena file whose value is a secret itself (console.token), wherever they appear: a recording's
# copy of the arena holds REDACTED instead. Key material lives in files (server.key_file,
# vehicles[i].signing.key_file): only their paths are recorded, never read into the recording.
SECRET_KEYS = frozenset({"token", "secret", "password", "passphrase", "key"})
REDACTED = "<redacted>"


def redact_secrets(value: Any) -> Any:
    """A copy of an arena mapping with the value of every SECRET_KEYS key (at any depth) replaced by REDACTED."""
    if isinstance(value, dict):
        return {k: (REDACTED if k in SECRET_KEYS and v is not None else redact_secrets(v)) for k, v in value.items()}
    if isinstance(value, list):
        return [redact_secrets(v) for v in value]
    return value


def drop_redacted(value: Any) -> Any:
    """A recorded arena mapping with the REDACTED values left out, so their settings take their defaults on
    replay (a replay's console makes a fresh token where it needs one)."""
    if isinstance(value, dict):
        return {k: drop_redacted(v) for k, v in value.items() if not (k in SECRET_KEYS and v == REDACTED)}
    if isinstance(value, list):
        return [drop_redacted(v) for v in value]
    return value


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
        self.opened_monotonic_ns = time.monotonic_ns()  # for the console's "recording for N s"
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
            **plain(meta or {}),
        }
        self._w.add_metadata("visionpos.config", {"yaml": yaml.safe_dump(redact_secrets(plain(raw)),
                                                                         sort_keys=False)})
        self._w.add_metadata("visionpos.meta", {"json": json.dumps(full_meta)})
        self._state_schema = self._w.register_schema("visionpos.BodyState", "jsonschema", json_bytes(STATE_SCHEMA))
        self._truth_schema = self._w.register_schema("visionpos.Truth", "jsonschema", json_bytes(TRUTH_SCHEMA))
        self._imu_schema = self._w.register_schema("visionpos.ImuSample", "jsonschema", json_bytes(IMU_SCHEMA))
        self._packet_channels: dict[tuple[str, int] | None, int] = {}
        self._topic_channels: dict[str, int] = {}
        self._seq = 0
        self._fox_schemas: dict[str, int] = {}
        self.foxglove: FoxgloveChannels | None = None
        if foxglove_rate_hz:
            rt = realtime_minus_monotonic_ns
            if rt is None:  # the difference the recording states, as replay and foxglove_copy use it
                rt = realtime_minus_monotonic(full_meta)
            self.foxglove = FoxgloveChannels(arena_cameras(config), foxglove_rate_hz, rt)
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
                ch = self._channel_for(topic, "protobuf", protobuf_schema(self._w, self._fox_schemas, schema))
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
        data = json_bytes(state_to_dict(state))
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
        data = json_bytes({"points": plain(lp.points), "residual_px": plain(lp.residual_px)})
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
        data = json_bytes({"name": str(name), "position": p.tolist(), "quaternion": q.tolist()})
        with self._lock:
            if self._recording():
                ch = self._channel_for(TOPIC_TRUTH, "json", self._truth_schema)
                self._add(ch, int(time_ns), data, TOPIC_TRUTH)

    def write_imu(self, log_ns: int, body: str, t_ns: int, accel, gyro, lever_arm, at: str) -> None:
        """One IMU sample handed to the pipeline (FusionPipeline.push_imu; IMU_SCHEMA), logged at log_ns: the
        receive time of the frame whose push took it (at "frame") or the tick's time (at "tick")."""
        data = json_bytes(imu_to_dict(body, t_ns, accel, gyro, lever_arm, at))
        with self._lock:
            if self._recording():
                ch = self._channel_for(TOPIC_IMU, "json", self._imu_schema)
                self._add(ch, int(log_ns), data, TOPIC_IMU)

    def write_json(self, topic: str, time_ns: int, obj: dict[str, Any]) -> None:
        """Any JSON-able mapping on its own topic (events, camera truth, stats).

        /server/health and /server/events also go to the Foxglove log.
        """
        reserved = (TOPIC_PACKETS, TOPIC_STATES, TOPIC_TRUTH, TOPIC_MARKERS, TOPIC_IMU)
        if topic in reserved or topic.startswith(TOPIC_PREFIX):
            raise ValueError(f"write_json: topic {topic!r} is reserved; use write_packet/write_state/write_truth/"
                             "publish_markers/write_imu")
        data = json_bytes(plain(obj))
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
            buf = data if final else data + PROVISIONAL_END
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
            self._pwrite_all(PROVISIONAL_END, self._data_end)
            os.ftruncate(self._fd, self._data_end + len(PROVISIONAL_END))
            readable = "a complete MCAP file without a summary, readable by any MCAP reader"
            self.bytes_written = self._data_end + len(PROVISIONAL_END)
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
