"""RecordingReader: reads a recording written by RecordingWriter (or any MCAP file of the visionpos
profile), tolerating a missing footer and a truncated or corrupt tail."""

from __future__ import annotations

import io
import json
import mmap
import os
import struct
import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from mcap.data_stream import ReadDataStream
from mcap.exceptions import McapError
from mcap.opcode import Opcode
from mcap.reader import make_reader
from mcap.records import Channel, Chunk, Footer, Header, Message, Metadata, Schema
from mcap.stream_reader import breakup_chunk

from visionpos.messages import BodyState
from visionpos.recording.codec import (
    FORMAT_VERSION,
    MCAP_MAGIC,
    META_END,
    PACKET_ENCODING,
    PROFILE,
    PROVISIONAL_END,
    TOPIC_IMU,
    TOPIC_PACKETS,
    TOPIC_STATES,
    TOPIC_TRUTH,
    ImuRecord,
    RecordingDamagedWarning,
    RecordingError,
    imu_from_dict,
    state_from_dict,
)
from visionpos.recording.writer import drop_redacted

_MAX_RECORD = 64 * 2**20  # a corrupted length field must not make the reader allocate GiB
_RECORD_HEAD = struct.Struct("<BQ")  # opcode, content length
_MESSAGE_HEAD = struct.Struct("<HIQQ")  # channel id, sequence, log time, publish time
# the records the reader uses, parsed by mcap's classes (messages are parsed in _records)
_RECORD_TYPES = {Opcode.HEADER: Header, Opcode.SCHEMA: Schema, Opcode.CHANNEL: Channel, Opcode.METADATA: Metadata,
                 Opcode.CHUNK: Chunk, Opcode.FOOTER: Footer}


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
            f.seek(max(0, size - len(PROVISIONAL_END)))
            tail = f.read(len(PROVISIONAL_END))
        if magic != MCAP_MAGIC:
            raise RecordingError(
                f"{self.path}: not an MCAP file (starts with {magic[:8]!r}); "
                "expected a recording written by `visionpos serve --record` or `visionpos record`"
            )
        self.damage: str | None = None
        self._warned = False
        # a cleanly closed file ends with its summary, footer and magic; a writer killed or stopped by
        # a write error leaves its provisional end (no summary), or a torn end if killed mid-write
        unclosed = tail == PROVISIONAL_END
        self.complete = size > 16 and tail[-len(MCAP_MAGIC):] == magic and not unclosed
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
        return drop_redacted(cfg)  # the secrets the writer left out take their defaults

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
            pos = len(MCAP_MAGIC)
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
        expect = {TOPIC_STATES: "visionpos.BodyState", TOPIC_TRUTH: "visionpos.Truth",
                  TOPIC_IMU: "visionpos.ImuSample"}.get(ch.topic)
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

    def inputs(self) -> Iterator[tuple]:
        """The pipeline's recorded inputs in file order (its input order): station packets as packets_with_source
        gives them, (recv_ns, raw bytes, (host, port) or None), and IMU samples as ImuRecord."""
        sources: dict[int, tuple[str, int] | None] = {}
        for topic, t, data, ch in self.messages({TOPIC_PACKETS, TOPIC_IMU}):
            if topic == TOPIC_IMU:
                try:
                    yield ImuRecord(t, *imu_from_dict(json.loads(data)))
                except (json.JSONDecodeError, UnicodeDecodeError, KeyError, ValueError, TypeError) as e:
                    self._damaged(f"IMU sample at {t} ns is malformed ({type(e).__name__}: {e})")
                continue
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
