"""Rewrites of a recording: recover (a clean, indexed copy of a damaged file) and foxglove_copy (the same
with Foxglove channels built from what it recorded)."""

from __future__ import annotations

import json
import os
import warnings
from pathlib import Path
from typing import Any

import numpy as np
from mcap.records import Channel, Header, Message, Metadata, Schema
from mcap.writer import CompressionType, IndexType, Writer

from visionpos.foxglove.channels import DEFAULT_RATE_HZ, TOPIC_PREFIX, FoxgloveChannels
from visionpos.messages import BodyState
from visionpos.recording.codec import (
    TOPIC_EVENTS,
    TOPIC_HEALTH,
    TOPIC_MARKERS,
    TOPIC_PACKETS,
    TOPIC_STATES,
    RecordingDamagedWarning,
    RecordingError,
    arena_cameras,
    protobuf_schema,
    realtime_minus_monotonic,
    state_from_dict,
)
from visionpos.recording.reader import RecordingReader

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
               FoxgloveChannels(arena_cameras(reader.config), fox_rate_hz, realtime_minus_monotonic(reader.meta)))
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
                                                                    protobuf_schema(self.w, self.schemas, schema))
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
