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
    /fusion/imu        json, schema visionpos.ImuSample: the vehicles' IMU samples the pipeline took
                       (FusionPipeline.push_imu), an input a replay hands over again at the same point
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

Modules: codec.py (the format's names, the provisional end, the JSON codec of BodyState), writer.py
(RecordingWriter), reader.py (RecordingReader), repair.py (recover, foxglove_copy).
"""

from visionpos.recording.codec import (
    FORMAT_VERSION,
    META_END,
    PACKET_ENCODING,
    PROFILE,
    TOPIC_EVENTS,
    TOPIC_HEALTH,
    TOPIC_IMU,
    TOPIC_MARKERS,
    TOPIC_PACKETS,
    TOPIC_STATES,
    TOPIC_TRUTH,
    ImuRecord,
    RecordingDamagedWarning,
    RecordingError,
    state_from_dict,
    state_to_dict,
)
from visionpos.recording.reader import RecordingReader
from visionpos.recording.repair import META_FOXGLOVE_COPY, META_RECOVERED, foxglove_copy, recover
from visionpos.recording.writer import FLUSH_INTERVAL_S, MAX_PACKET_SOURCES, RecordingWriter

__all__ = [
    "FLUSH_INTERVAL_S", "FORMAT_VERSION", "MAX_PACKET_SOURCES", "META_END", "META_FOXGLOVE_COPY", "META_RECOVERED",
    "PACKET_ENCODING", "PROFILE", "TOPIC_EVENTS", "TOPIC_HEALTH", "TOPIC_IMU", "TOPIC_MARKERS", "TOPIC_PACKETS",
    "TOPIC_STATES", "TOPIC_TRUTH", "ImuRecord", "RecordingDamagedWarning", "RecordingError", "RecordingReader",
    "RecordingWriter",
    "foxglove_copy", "recover", "state_from_dict", "state_to_dict",
]
