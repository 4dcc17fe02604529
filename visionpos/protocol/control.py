"""The control messages (HELLO, HELLO_ACK, HEARTBEAT, SYNC_REQUEST, SYNC_REPLY, BYE), each reading and writing
itself, and the server-side helpers that build replies (pure, no I/O).

Version 2 binds every message to its station session and makes every one fresh: station -> server control
messages (HELLO, HEARTBEAT, SYNC_REQUEST, BYE) carry a per-session counter that must strictly increase; HELLO
carries the server's cookie (a stateless challenge); replies echo the session and the counter they answer.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from visionpos.protocol.wire import (
    CAMERA_KINDS,
    HEADER_BYTES,
    I64_MAX,
    I64_MIN,
    MAX_FPS,
    NO_COOKIE,
    TEMPERATURE_UNKNOWN,
    U16,
    U32,
    UNCERTAINTY_UNKNOWN,
    AckStatus,
    MsgType,
    ProtocolError,
    Timebase,
    WireMessage,
    check_body_size,
    check_cookie,
    check_range,
    pack_text,
    unpack_text,
)

# Every body starts with session u32 and a u32 counter (control counter, or the echoed counter).
_HELLO = struct.Struct("<IIHHfBB2x16s32s16s")  # 84 bytes
_HELLO_ACK = struct.Struct("<IIB7xqqq16s")  # 56 bytes
_HEARTBEAT = struct.Struct("<IIHhIIIi4xqqq")  # 56 bytes
_SYNC_REQUEST = struct.Struct("<IIq")  # 16 bytes
_SYNC_REPLY = struct.Struct("<IIqqq")  # 32 bytes
_BYE = struct.Struct("<II")  # 8 bytes


def check_hello(w: int, h: int, fps: float, kind: int) -> None:
    """A HELLO's camera must be possible: a resolution, a frame rate in (0, MAX_FPS], a known kind."""
    if not w or not h:
        raise ProtocolError(f"hello resolution {w}x{h}: width and height must be > 0")
    if not (0.0 < fps <= MAX_FPS):  # false for NaN too
        raise ProtocolError(f"hello fps {fps} out of range (0, {MAX_FPS:g}]")
    if kind >= len(CAMERA_KINDS):
        raise ProtocolError(f"hello camera kind {kind} unknown (expected 0..{len(CAMERA_KINDS) - 1})")


def temperature_field(temperature_c: float | None) -> int:
    """Heartbeat.temperature_c -> the wire's i16 of centi-degrees (TEMPERATURE_UNKNOWN for None)."""
    if temperature_c is None:
        return TEMPERATURE_UNKNOWN
    return int(np.clip(round(temperature_c * 100.0), -32767, 32767))


def temperature_c(field: int) -> float | None:
    return None if field == TEMPERATURE_UNKNOWN else field / 100.0


@dataclass(frozen=True, slots=True)
class Hello(WireMessage):
    """Station registration, sent until a HelloAck with the same session arrives.

    session: random non-zero u32 chosen at agent start; it tells the server
    that a station restarted (new session) and echoes back in HelloAck.
    fps: nominal frame rate, in (0, MAX_FPS]. camera_kind: one of CAMERA_KINDS.
    counter: the session's control counter (strictly increasing over Hello,
    Heartbeat, SyncRequest, Bye). cookie: NO_COOKIE, or the cookie of the
    server's CHALLENGE answer.
    """

    TYPE: ClassVar[MsgType] = MsgType.HELLO

    station_id: int
    camera_id: int
    session: int
    width: int
    height: int
    fps: float
    camera_kind: str = "unknown"
    camera_name: str = ""
    software: str = ""
    timebase: int = Timebase.SERVER
    counter: int = 0
    cookie: bytes = NO_COOKIE

    def write_body(self) -> bytes:
        if self.camera_kind not in CAMERA_KINDS:
            raise ProtocolError(f"camera_kind {self.camera_kind!r} is not one of {CAMERA_KINDS}")
        return _HELLO.pack(
            check_range("session", self.session, 0, U32),
            check_range("counter", self.counter, 0, U32),
            check_range("width", self.width, 0, U16),
            check_range("height", self.height, 0, U16),
            float(self.fps),
            CAMERA_KINDS.index(self.camera_kind),
            check_range("timebase", self.timebase, 0, 255),
            check_cookie("cookie", self.cookie),
            pack_text("camera_name", self.camera_name, 32),
            pack_text("software", self.software, 16),
        )

    @classmethod
    def read_body(cls, data: bytes, station_id: int, camera_id: int, body_len: int) -> Hello:
        check_body_size(cls.TYPE, body_len, _HELLO.size)
        session, counter, w, h, fps, kind, timebase, cookie, name, sw = _HELLO.unpack_from(data, HEADER_BYTES)
        check_hello(w, h, fps, kind)
        return cls(station_id, camera_id, session, w, h, fps, CAMERA_KINDS[kind], unpack_text(name),
                   unpack_text(sw), timebase, counter, cookie)


@dataclass(frozen=True, slots=True)
class HelloAck(WireMessage):
    """Server answer to Hello and to each Heartbeat.

    start_ns: capture start (trigger) time on the server clock; stations send
    no frames captured before it. server_ns: server clock when sent.
    duration_ns: recording length after start_ns, 0 = until stopped.
    status: an AckStatus. echo: the counter of the Hello/Heartbeat answered.
    cookie: with CHALLENGE, what the next Hello must carry (else NO_COOKIE).
    """

    TYPE: ClassVar[MsgType] = MsgType.HELLO_ACK

    station_id: int
    camera_id: int
    session: int
    start_ns: int
    server_ns: int
    status: int = AckStatus.OK
    duration_ns: int = 0
    echo: int = 0
    cookie: bytes = NO_COOKIE

    def write_body(self) -> bytes:
        return _HELLO_ACK.pack(
            check_range("session", self.session, 0, U32),
            check_range("echo", self.echo, 0, U32),
            check_range("status", self.status, 0, 255),
            check_range("start_ns", self.start_ns, I64_MIN, I64_MAX),
            check_range("server_ns", self.server_ns, I64_MIN, I64_MAX),
            check_range("duration_ns", self.duration_ns, 0, I64_MAX),
            check_cookie("cookie", self.cookie),
        )

    @classmethod
    def read_body(cls, data: bytes, station_id: int, camera_id: int, body_len: int) -> HelloAck:
        check_body_size(cls.TYPE, body_len, _HELLO_ACK.size)
        session, echo, status, start, server, dur, cookie = _HELLO_ACK.unpack_from(data, HEADER_BYTES)
        return cls(station_id, camera_id, session, start, server, status, dur, echo, cookie)


@dataclass(frozen=True, slots=True)
class Heartbeat(WireMessage):
    """Station health, about once a second. Counters are since agent start (mod 2^32).

    status: HeartbeatStatus bits. clock_offset_ns: server clock - station clock estimate;
    clock_uncertainty_ns its 1-sigma uncertainty (-1 = unknown). drift_ppb: station clock rate
    error (server - station) in parts per billion. temperature_c: None = no sensor.
    station_ns: station local clock when sent. counter: the session's control counter.
    """

    TYPE: ClassVar[MsgType] = MsgType.HEARTBEAT

    station_id: int
    camera_id: int
    counter: int
    session: int = 0
    status: int = 0
    frames_captured: int = 0
    frames_dropped: int = 0
    send_errors: int = 0
    clock_offset_ns: int = 0
    clock_uncertainty_ns: int = UNCERTAINTY_UNKNOWN
    drift_ppb: int = 0
    temperature_c: float | None = None
    station_ns: int = 0

    def write_body(self) -> bytes:
        return _HEARTBEAT.pack(
            check_range("session", self.session, 0, U32),
            check_range("counter", self.counter, 0, U32),
            check_range("status", self.status, 0, U16),
            temperature_field(self.temperature_c),
            int(self.frames_captured) & U32,
            int(self.frames_dropped) & U32,
            int(self.send_errors) & U32,
            int(np.clip(self.drift_ppb, -(1 << 31), (1 << 31) - 1)),
            check_range("clock_offset_ns", self.clock_offset_ns, I64_MIN, I64_MAX),
            check_range("clock_uncertainty_ns", self.clock_uncertainty_ns, -1, I64_MAX),
            check_range("station_ns", self.station_ns, I64_MIN, I64_MAX),
        )

    @classmethod
    def read_body(cls, data: bytes, station_id: int, camera_id: int, body_len: int) -> Heartbeat:
        check_body_size(cls.TYPE, body_len, _HEARTBEAT.size)
        (session, counter, status, temp, cap, drop, err, drift, off, unc, st_ns) = _HEARTBEAT.unpack_from(
            data, HEADER_BYTES
        )
        return cls(station_id, camera_id, counter, session, status, cap, drop, err, off, unc, drift,
                   temperature_c(temp), st_ns)


@dataclass(frozen=True, slots=True)
class SyncRequest(WireMessage):
    """Clock-sync request: t1_ns = station clock at send; counter: the session's control counter."""

    TYPE: ClassVar[MsgType] = MsgType.SYNC_REQUEST

    station_id: int
    camera_id: int
    t1_ns: int
    counter: int = 0
    session: int = 0

    def write_body(self) -> bytes:
        return _SYNC_REQUEST.pack(
            check_range("session", self.session, 0, U32),
            check_range("counter", self.counter, 0, U32),
            check_range("t1_ns", self.t1_ns, I64_MIN, I64_MAX),
        )

    @classmethod
    def read_body(cls, data: bytes, station_id: int, camera_id: int, body_len: int) -> SyncRequest:
        check_body_size(cls.TYPE, body_len, _SYNC_REQUEST.size)
        session, counter, t1 = _SYNC_REQUEST.unpack_from(data, HEADER_BYTES)
        return cls(station_id, camera_id, t1, counter, session)


@dataclass(frozen=True, slots=True)
class SyncReply(WireMessage):
    """Clock-sync reply: t1 echoed, t2 = server clock at receive, t3 = server clock at send;
    echo and session: the request's counter and session."""

    TYPE: ClassVar[MsgType] = MsgType.SYNC_REPLY

    station_id: int
    camera_id: int
    t1_ns: int
    t2_ns: int
    t3_ns: int
    echo: int = 0
    session: int = 0

    def write_body(self) -> bytes:
        return _SYNC_REPLY.pack(
            check_range("session", self.session, 0, U32),
            check_range("echo", self.echo, 0, U32),
            check_range("t1_ns", self.t1_ns, I64_MIN, I64_MAX),
            check_range("t2_ns", self.t2_ns, I64_MIN, I64_MAX),
            check_range("t3_ns", self.t3_ns, I64_MIN, I64_MAX),
        )

    @classmethod
    def read_body(cls, data: bytes, station_id: int, camera_id: int, body_len: int) -> SyncReply:
        check_body_size(cls.TYPE, body_len, _SYNC_REPLY.size)
        session, echo, t1, t2, t3 = _SYNC_REPLY.unpack_from(data, HEADER_BYTES)
        return cls(station_id, camera_id, t1, t2, t3, echo, session)


@dataclass(frozen=True, slots=True)
class Bye(WireMessage):
    """Station shutting down cleanly; the server may mark it offline at once."""

    TYPE: ClassVar[MsgType] = MsgType.BYE

    station_id: int
    camera_id: int
    session: int = 0
    counter: int = 0

    def write_body(self) -> bytes:
        return _BYE.pack(check_range("session", self.session, 0, U32), check_range("counter", self.counter, 0, U32))

    @classmethod
    def read_body(cls, data: bytes, station_id: int, camera_id: int, body_len: int) -> Bye:
        check_body_size(cls.TYPE, body_len, _BYE.size)
        session, counter = _BYE.unpack_from(data, HEADER_BYTES)
        return cls(station_id, camera_id, session, counter)


# ---------------------------------------------------------------- server-side helpers


def make_sync_reply(req: SyncRequest, t2_ns: int, t3_ns: int) -> SyncReply:
    """Server answer to a SyncRequest. t2_ns: server clock when the request
    was received (take it as early as possible, e.g. the datagram's receive
    time); t3_ns: server clock just before sending the reply."""
    return SyncReply(req.station_id, req.camera_id, req.t1_ns, int(t2_ns), int(t3_ns), req.counter, req.session)


def make_hello_ack(
    hello: Hello | Heartbeat,
    start_ns: int,
    server_ns: int,
    status: int = AckStatus.OK,
    duration_ns: int = 0,
    cookie: bytes = NO_COOKIE,
) -> HelloAck:
    """Server answer to a Hello (registration) or a Heartbeat (keep-alive).

    start_ns: the capture start (trigger) time on the server clock, the same
    for every station of a session; server_ns: server clock now. Answer a
    Heartbeat whose session the server does not know with
    status=AckStatus.UNKNOWN_SESSION so the station registers again at once. The
    ack echoes the request's session and counter (the station checks both).
    """
    return HelloAck(hello.station_id, hello.camera_id, hello.session, int(start_ns), int(server_ns), status,
                    duration_ns, hello.counter, cookie)


def seq_delta(new: int, old: int) -> int:
    """Signed difference new - old of two u32 sequence numbers, wrap-around aware.

    > 0: new is later (1 = next frame, k = k - 1 frames lost);
    <= 0: duplicate or replayed/reordered packet (drop it).
    """
    d = (int(new) - int(old)) & U32
    return d - (1 << 32) if d >= (1 << 31) else d


def server_time_from_realtime(capture_realtime_ns: int, server_realtime_ns: int, server_clock_ns: int) -> int:
    """Convert a Timebase.REALTIME capture stamp to the server clock.

    server_realtime_ns / server_clock_ns: the server's CLOCK_REALTIME and its
    own (monotonic) clock read back to back; valid when both hosts'
    realtime clocks are disciplined to the same reference (PTP/chrony).
    """
    return int(capture_realtime_ns) - (int(server_realtime_ns) - int(server_clock_ns))
