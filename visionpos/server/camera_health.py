"""What ingest knows and counts: per-camera health (CameraHealth: registration, sequence and clock state,
counters, rates, the station's heartbeat), the server's packet counters (IngestCounters), and the named
reasons and events (Refusal, ClockJump, IngestEvent). Pure data and its snapshots; the checks that change
it are in ingest.py."""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from enum import StrEnum
from typing import Any

from visionpos import protocol as P

Addr = tuple[Any, ...]
RETIRED_SESSIONS = 4  # replaced sessions kept per camera: a HELLO for one of them is a replay
LOW_RATE_FRACTION = 0.8  # a camera delivering less than this fraction of its configured fps ...
LOW_RATE_AFTER_S = 3.0  # ... for this long gets a health warning
OUTAGE_MIN_S = 1.0  # a gap in accepted frames longer than this (and the vanish timeout) is an outage, not a rate


class ClockJump(StrEnum):
    """Why a frame's capture time was refused; the value is the log's wording."""

    FUTURE = "in the future"  # counted in clock_jumps_future
    STALE = "too old"  # clock_jumps_stale
    BACKWARDS = "going backwards"  # clock_jumps_backwards


class Refusal(StrEnum):
    """Why a packet that decoded was not accepted: counters.not_recorded keys, cameras' drop reasons."""

    UNKNOWN_CAMERA = "unknown camera"
    NOT_REGISTERED = "not registered"
    WRONG_SESSION = "wrong session"
    WRONG_ADDRESS = "wrong address"
    STALE_COUNTER = "stale counter"  # control message replayed (or reordered)
    RETIRED_SESSION = "retired session"  # HELLO of a session already replaced on this camera
    CHALLENGED = "no valid cookie"
    REJECTED = "rejected"  # resolution mismatch, camera of another station
    DUPLICATE = "duplicate seq"
    REORDERED = "reordered"
    REPLAYED = "replayed seq"
    BEFORE_START = "before start"
    WRONG_DIRECTION = "server message"


class IngestEvent(StrEnum):
    """Kinds handed to the `events` observer; the value is the "kind" recorded on /server/events."""

    REGISTERED = "registered"
    CAMERA_LOST = "camera_lost"
    CAMERA_BACK = "camera_back"
    RESYNC_REQUEST = "resync_request"


@dataclass
class CameraHealth:
    """Everything the server knows about one configured camera's station."""

    camera_id: int
    name: str
    fps_nominal: float  # announced by the station (its HELLO); the arena's fps until then
    width: int
    height: int
    required_station: int | None = None
    fps_configured: float = 0.0  # the arena's cameras[i].fps, which the fusion was set up for
    config_key: str = ""  # where fps_configured comes from, for messages ("cameras[1].fps")
    station_id: int | None = None
    session: int | None = None
    addr: Addr | None = None
    timebase: int = P.Timebase.SERVER
    registered: bool = False
    software: str = ""
    last_counter: int = 0  # the registered session's newest control counter
    retired: deque = field(default_factory=lambda: deque(maxlen=RETIRED_SESSIONS))
    resync_pending: bool = False  # tell the station at its next heartbeat
    # sequence / time state
    last_seq: int | None = None
    last_capture_ns: int | None = None
    last_seen_ns: int = 0  # any accepted packet
    last_frame_ns: int = 0  # accepted frame (receive time)
    online: bool = False
    jump_run: int = 0  # clock-jumped frames in a row (restarts at a resync request)
    jumped_since_accepted: int = 0  # clock-jumped frames since the last accepted frame (for the log)
    # the newest refused frame: shows "dropping (reason)" while no frame gets through
    drop_reason: str = ""
    last_drop_ns: int = 0
    # counters since start
    frames: int = 0
    lost: int = 0
    duplicates: int = 0
    reordered: int = 0
    replayed: int = 0
    seq_restarts: int = 0
    clock_jumps: int = 0
    future: int = 0
    stale: int = 0
    backwards: int = 0
    before_start: int = 0
    unregistered: int = 0  # frames while no HELLO was accepted
    wrong_session: int = 0  # frames or control messages of another session / station
    wrong_address: int = 0  # ... of the registered session from another address
    stale_control: int = 0  # control messages whose counter was not newer (replays)
    shed: int = 0  # accepted but not fused: it queued too long in the server (load shedding)
    resync_requests: int = 0
    vanished: int = 0
    # latency (recv - capture) running stats, ns
    latency_ewma_ns: float = 0.0
    latency_min_ns: int = 0
    latency_max_ns: int = 0
    # rates over the last ~1 s
    fps: float = 0.0
    loss_rate: float = 0.0
    low_rate_since_ns: int = 0  # start of the run of 1 s buckets below LOW_RATE_FRACTION (0: none)
    low_rate: bool = False  # that run is LOW_RATE_AFTER_S long: warned
    _bucket_start: int = 0
    _bucket_frames: int = 0
    _bucket_lost: int = 0
    # from heartbeats
    clock_offset_ns: int | None = None
    clock_uncertainty_ns: int | None = None
    drift_ppb: int | None = None
    station_status: int = 0
    station_frames_captured: int = 0
    station_frames_dropped: int = 0
    station_send_errors: int = 0
    temperature_c: float | None = None

    def reset_sequence(self) -> None:
        self.last_seq = None
        self.last_capture_ns = None
        self.jump_run = 0

    def low_rate_message(self) -> str:
        """What a camera that delivers too few frames is told (plain words, what to do)."""
        return (f"camera {self.camera_id} ({self.name}) delivers {self.fps:.0f} fps but {self.config_key} says "
                f"{self.fps_configured:g}: lower {self.config_key} to what the station can deliver, or reduce the "
                "station's load (a lower resolution or frame rate in its source, fewer processes on its host); "
                "fusion follows the measured rate meanwhile")

    def warnings(self) -> list[dict[str, Any]]:
        """Structured health warnings (for consoles): kind, the numbers, and the plain-language message."""
        if not self.low_rate:
            return []
        return [{"kind": "low_frame_rate", "measured_fps": round(self.fps, 2), "configured_fps": self.fps_configured,
                 "since_ns": self.low_rate_since_ns, "message": self.low_rate_message()}]

    def state(self, now_ns: int, timeout_ns: int) -> str:
        """streaming / dropping (frames arrive, none accepted) / gone / waiting."""
        if self.online:
            return "streaming"
        if self.last_drop_ns and now_ns - self.last_drop_ns <= timeout_ns:
            return "dropping"
        return "gone" if self.vanished else "waiting"

    def snapshot(self, now_ns: int, timeout_ns: int) -> dict[str, Any]:
        total = self.frames + self.lost
        state = self.state(now_ns, timeout_ns)
        return {
            "camera_id": self.camera_id,
            "name": self.name,
            "station_id": self.station_id,
            "addr": None if self.addr is None else f"{self.addr[0]}:{self.addr[1]}",
            "registered": self.registered,
            "online": self.online,
            "state": state,
            "dropping": self.drop_reason if state == "dropping" else None,
            "last_drop_reason": self.drop_reason or None,
            "fps": round(self.fps, 2),
            "fps_nominal": self.fps_nominal,
            "fps_configured": self.fps_configured,
            "low_frame_rate": self.low_rate,
            "warnings": self.warnings(),
            "frames": self.frames,
            "lost": self.lost,
            "loss": (self.lost / total) if total else 0.0,
            "loss_recent": round(self.loss_rate, 4),
            "duplicates": self.duplicates,
            "reordered": self.reordered,
            "replayed": self.replayed,
            "seq_restarts": self.seq_restarts,
            "clock_jumps": self.clock_jumps,
            "clock_jumps_future": self.future,
            "clock_jumps_stale": self.stale,
            "clock_jumps_backwards": self.backwards,
            "before_start": self.before_start,
            "unregistered": self.unregistered,
            "wrong_session": self.wrong_session,
            "wrong_address": self.wrong_address,
            "stale_control": self.stale_control,
            "shed": self.shed,
            "resync_requests": self.resync_requests,
            "vanished": self.vanished,
            "latency_ms": self.latency_ewma_ns * 1e-6 if self.frames else None,
            "latency_min_ms": self.latency_min_ns * 1e-6 if self.frames else None,
            "latency_max_ms": self.latency_max_ns * 1e-6 if self.frames else None,
            "last_seen_s_ago": (now_ns - self.last_seen_ns) * 1e-9 if self.last_seen_ns else None,
            "clock_offset_ms": None if self.clock_offset_ns is None else self.clock_offset_ns * 1e-6,
            "clock_uncertainty_us": (None if self.clock_uncertainty_ns is None or self.clock_uncertainty_ns < 0
                                     else self.clock_uncertainty_ns * 1e-3),
            "drift_ppb": self.drift_ppb,
            "station_frames_captured": self.station_frames_captured,
            "station_frames_dropped": self.station_frames_dropped,
            "station_send_errors": self.station_send_errors,
            "temperature_c": self.temperature_c,
            "timebase": "realtime" if self.timebase == P.Timebase.REALTIME else "server",
        }


@dataclass
class IngestCounters:
    packets: int = 0
    bytes: int = 0
    frames_accepted: int = 0
    frames_shed: int = 0
    frames_without_view_updates: int = 0  # fused while the view updates were paused (server/load.py)
    malformed: int = 0
    auth_failed: int = 0
    unknown: int = 0
    unknown_sources_evicted: int = 0
    rejected_hello: int = 0
    challenges: int = 0
    pipeline_errors: int = 0
    replies: int = 0
    send_errors: int = 0
    by_type: dict[str, int] = field(default_factory=dict)
    malformed_reasons: dict[str, int] = field(default_factory=dict)
    not_recorded: dict[str, int] = field(default_factory=dict)  # with a recorder: packets refused, by reason
    tap_errors: int = 0  # packet taps (live outputs) that raised



def fmt_addr(addr: Addr | None) -> str:
    """host:port for messages ("?" when unknown)."""
    if not addr:
        return "?"
    return f"{addr[0]}:{addr[1]}"
