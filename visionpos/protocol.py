"""The station <-> server wire protocol (UDP, binary, little-endian, versioned).

docs/protocol.md specifies every byte; this module is the reference
implementation used by stations, the fusion server, the simulator and replay.

Every packet is one UDP datagram:

    common header (16 bytes) | body (body_len bytes) | optional HMAC tag (16 bytes)

Frames decode to `visionpos.messages.BlobFrame`; the other messages decode to
the small frozen dataclasses below. `decode` raises `ProtocolError` with a
message naming what was wrong, so a server can count and drop bad packets.

Version 2 binds every message to its station session and makes every one
fresh: frames carry the session and their own seq; station -> server control
messages (HELLO, HEARTBEAT, SYNC_REQUEST, BYE) carry a per-session counter
that must strictly increase; HELLO carries the server's cookie (a stateless
challenge); replies echo the session and the counter they answer. All of it
is inside the HMAC. On request only, the server asks a station for a still image (IMAGE_REQUEST,
answered by IMAGE_CHUNKs of the JPEG) or sets its mask (MASK_UPDATE, answered by MASK_ACK);
stations/still.py and visionpos/server/images.py are the two sides. `decode_v1` reads version-1 packets (recordings made
before version 2) for replay only.

Server-side helpers (pure, no I/O): `make_hello_ack`, `make_sync_reply`,
`seq_delta`, `server_time_from_realtime`.
"""

from __future__ import annotations

import hashlib
import hmac
import struct
from dataclasses import dataclass
from enum import IntEnum, IntFlag

import numpy as np

from visionpos.errors import VisionposError
from visionpos.messages import BlobFrame

PROTOCOL_VERSION = 2
MAGIC = b"VPOS"
DEFAULT_PORT = 5600

# Largest UDP payload that crosses a 1500-byte Ethernet MTU unfragmented
# (1500 - 20 IPv4 - 8 UDP). Every packet of this protocol fits in it.
MAX_PACKET_BYTES = 1472
HEADER_BYTES = 16
FRAME_FIXED_BYTES = 24  # session, seq, capture_ns, flags, count, reserved
BLOB_BYTES = 16  # x, y, area, peak: 4 x float32
TAG_BYTES = 16  # HMAC-SHA256 truncated to its first 16 bytes
COOKIE_BYTES = 16
NO_COOKIE = bytes(COOKIE_BYTES)  # Hello.cookie before the server has challenged
# 40 + 88 * 16 + 16 = 1464 <= 1472: a signed full frame still fits one datagram.
MAX_BLOBS_PER_PACKET = 88
MAX_FPS = 1000.0


class MsgType(IntEnum):
    """Message type, header byte 5."""

    FRAME = 1
    HELLO = 2
    HELLO_ACK = 3
    HEARTBEAT = 4
    SYNC_REQUEST = 5
    SYNC_REPLY = 6
    BYE = 7
    IMAGE_REQUEST = 8
    IMAGE_CHUNK = 9
    MASK_UPDATE = 10
    MASK_ACK = 11


class HeaderFlag(IntFlag):
    """Header flag bits, header byte 6."""

    SIGNED = 0x01  # a 16-byte HMAC tag follows the body


class AckStatus(IntEnum):
    """HelloAck.status."""

    OK = 0
    UNKNOWN_SESSION = 1  # server does not know this station/session (it restarted): send Hello again
    REJECTED = 2  # camera id not configured on the server, or resolution mismatch: fix config
    CHALLENGE = 3  # Hello without a valid cookie: send it again carrying HelloAck.cookie
    RESYNC = 4  # heartbeat accepted, but the frames' capture times are off: restart clock sync


class MaskStatus(IntEnum):
    """MaskAck.status."""

    SAVED = 0  # applied to the running detector and written to the station's config file
    APPLIED = 1  # applied, but not saved (the station has no config file, or writing it failed: see text)
    REFUSED = 2  # not applied: a rectangle outside the image, or nothing to set (see text)


class MaskFlag(IntFlag):
    """MaskUpdate.flags: which lists the update replaces."""

    IGNORE = 0x01  # detector.ignore := the update's ignore rectangles
    ROIS = 0x02  # detector.rois := the update's rois


class Timebase(IntEnum):
    """Hello.timebase: which clock Frame.capture_ns is on."""

    SERVER = 0  # converted to the server clock with the built-in sync exchange
    REALTIME = 1  # station CLOCK_REALTIME, disciplined by PTP/chrony (server converts)


class CameraKind(IntEnum):
    """Hello.camera_kind on the wire; Hello carries its lower-case name."""

    UNKNOWN = 0
    PINHOLE = 1
    FISHEYE = 2


class HeartbeatStatus(IntFlag):
    """Heartbeat.status bits."""

    CAMERA_OK = 0x01  # the last capture attempt produced a frame
    CLOCK_SYNCED = 0x02  # clock offset estimate is valid (or the clock is external)
    CLOCK_EXTERNAL = 0x04  # built-in sync is off: host clock disciplined by PTP/chrony
    STREAMING = 0x08  # trigger time reached, frames are being sent


# The names before the enums, kept for their users. Enum values are the members (int comparisons cost
# nothing extra); flag bits stay plain ints: `int & IntFlag` builds a new IntFlag (~1 us a packet)
# and `~IntFlag` is not the int complement.
MSG_FRAME = MsgType.FRAME
MSG_HELLO = MsgType.HELLO
MSG_HELLO_ACK = MsgType.HELLO_ACK
MSG_HEARTBEAT = MsgType.HEARTBEAT
MSG_SYNC_REQUEST = MsgType.SYNC_REQUEST
MSG_SYNC_REPLY = MsgType.SYNC_REPLY
MSG_BYE = MsgType.BYE
MSG_IMAGE_REQUEST = MsgType.IMAGE_REQUEST
MSG_IMAGE_CHUNK = MsgType.IMAGE_CHUNK
MSG_MASK_UPDATE = MsgType.MASK_UPDATE
MSG_MASK_ACK = MsgType.MASK_ACK
HF_SIGNED = HeaderFlag.SIGNED.value
ACK_OK = AckStatus.OK
ACK_UNKNOWN_SESSION = AckStatus.UNKNOWN_SESSION
ACK_REJECTED = AckStatus.REJECTED
ACK_CHALLENGE = AckStatus.CHALLENGE
ACK_RESYNC = AckStatus.RESYNC
ACK_STATUS_NAMES = {s: s.name.lower().replace("_", " ") for s in AckStatus}  # "ok", "unknown session", ...
TIMEBASE_SERVER = Timebase.SERVER
TIMEBASE_REALTIME = Timebase.REALTIME
CAMERA_KINDS = tuple(k.name.lower() for k in CameraKind)  # Hello.camera_kind values, in wire order
HB_CAMERA_OK = HeartbeatStatus.CAMERA_OK.value
HB_CLOCK_SYNCED = HeartbeatStatus.CLOCK_SYNCED.value
HB_CLOCK_EXTERNAL = HeartbeatStatus.CLOCK_EXTERNAL.value
HB_STREAMING = HeartbeatStatus.STREAMING.value

TEMPERATURE_UNKNOWN = -32768  # Heartbeat temperature field value for "no sensor"
UNCERTAINTY_UNKNOWN = -1

# Every body starts with session u32 and a u32 counter (frame seq, control counter, or the echoed counter).
_HEADER = struct.Struct("<4sBBBBHHHH")
_FRAME_HEAD = struct.Struct("<4sBBBBHHHHIIqHH4x")  # header + fixed frame part, 40 bytes
_HELLO = struct.Struct("<IIHHfBB2x16s32s16s")  # 84 bytes
_HELLO_ACK = struct.Struct("<IIB7xqqq16s")  # 56 bytes
_HEARTBEAT = struct.Struct("<IIHhIIIi4xqqq")  # 56 bytes
_SYNC_REQUEST = struct.Struct("<IIq")  # 16 bytes
_SYNC_REPLY = struct.Struct("<IIqqq")  # 32 bytes
_BYE = struct.Struct("<II")  # 8 bytes
_IMAGE_REQUEST = struct.Struct("<IIIHBx")  # 16 bytes
_IMAGE_CHUNK = struct.Struct("<IIHHIqHHf")  # 32 bytes, then the chunk's JPEG bytes
_MASK_UPDATE = struct.Struct("<IIIHBB")  # 16 bytes, then (n_ignore + n_rois) x 4 x u16
_MASK_RECT = struct.Struct("<HHHH")
_MASK_ACK = struct.Struct("<IIB3x64s")  # 76 bytes
_BLOB_DTYPE = np.dtype("<f4")
_BLOB0 = HEADER_BYTES + FRAME_FIXED_BYTES

assert _HEADER.size == HEADER_BYTES and _FRAME_HEAD.size == _BLOB0
assert HEADER_BYTES + FRAME_FIXED_BYTES + MAX_BLOBS_PER_PACKET * BLOB_BYTES + TAG_BYTES <= MAX_PACKET_BYTES

# Still images (IMAGE_CHUNK): every chunk but the last carries exactly IMAGE_CHUNK_BYTES of the JPEG, so a
# signed chunk is one datagram; an image is at most MAX_IMAGE_BYTES (count <= MAX_IMAGE_CHUNKS).
IMAGE_CHUNK_BYTES = MAX_PACKET_BYTES - HEADER_BYTES - 32 - TAG_BYTES  # 1408
MAX_IMAGE_BYTES = 512 * 1024
MAX_IMAGE_CHUNKS = -(-MAX_IMAGE_BYTES // IMAGE_CHUNK_BYTES)
MAX_MASK_RECTS = 64  # per list in a MASK_UPDATE: 16 + 16 + 128 x 8 + 16 <= 1472
MASK_TEXT_BYTES = 64

_U16 = 0xFFFF
_U32 = 0xFFFFFFFF
_I64_MIN, _I64_MAX = -(1 << 63), (1 << 63) - 1


class ProtocolError(VisionposError, ValueError):  # ValueError: callers that catch it still do
    """A packet that cannot be encoded or decoded; the message says why and what to do."""


@dataclass(frozen=True, slots=True)
class Hello:
    """Station registration, sent until a HelloAck with the same session arrives.

    session: random non-zero u32 chosen at agent start; it tells the server
    that a station restarted (new session) and echoes back in HelloAck.
    fps: nominal frame rate, in (0, MAX_FPS]. camera_kind: one of CAMERA_KINDS.
    counter: the session's control counter (strictly increasing over Hello,
    Heartbeat, SyncRequest, Bye). cookie: NO_COOKIE, or the cookie of the
    server's CHALLENGE answer.
    """

    station_id: int
    camera_id: int
    session: int
    width: int
    height: int
    fps: float
    camera_kind: str = "unknown"
    camera_name: str = ""
    software: str = ""
    timebase: int = TIMEBASE_SERVER
    counter: int = 0
    cookie: bytes = NO_COOKIE


@dataclass(frozen=True, slots=True)
class HelloAck:
    """Server answer to Hello and to each Heartbeat.

    start_ns: capture start (trigger) time on the server clock; stations send
    no frames captured before it. server_ns: server clock when sent.
    duration_ns: recording length after start_ns, 0 = until stopped.
    status: an AckStatus. echo: the counter of the Hello/Heartbeat answered.
    cookie: with CHALLENGE, what the next Hello must carry (else NO_COOKIE).
    """

    station_id: int
    camera_id: int
    session: int
    start_ns: int
    server_ns: int
    status: int = ACK_OK
    duration_ns: int = 0
    echo: int = 0
    cookie: bytes = NO_COOKIE


@dataclass(frozen=True, slots=True)
class Heartbeat:
    """Station health, about once a second. Counters are since agent start (mod 2^32).

    clock_offset_ns: server clock - station clock estimate; clock_uncertainty_ns
    its 1-sigma uncertainty (-1 = unknown). drift_ppb: station clock rate
    error (server - station) in parts per billion. temperature_c: None = no sensor.
    station_ns: station local clock when sent. counter: the session's control counter.
    """

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


@dataclass(frozen=True, slots=True)
class SyncRequest:
    """Clock-sync request: t1_ns = station clock at send; counter: the session's control counter."""

    station_id: int
    camera_id: int
    t1_ns: int
    counter: int = 0
    session: int = 0


@dataclass(frozen=True, slots=True)
class SyncReply:
    """Clock-sync reply: t1 echoed, t2 = server clock at receive, t3 = server clock at send;
    echo and session: the request's counter and session."""

    station_id: int
    camera_id: int
    t1_ns: int
    t2_ns: int
    t3_ns: int
    echo: int = 0
    session: int = 0


@dataclass(frozen=True, slots=True)
class Bye:
    """Station shutting down cleanly; the server may mark it offline at once."""

    station_id: int
    camera_id: int
    session: int = 0
    counter: int = 0


@dataclass(frozen=True, slots=True)
class ImageRequest:
    """Server -> station: send one still image of the camera (docs/protocol.md, "Still images").

    session: the station's session. echo: the newest control counter the server accepted from it (the
    station believes only an echo of a counter it sent recently). request_id: the server's, increasing
    (with echo, the station's replay guard). max_width: downscale the image to at most this many pixels
    wide (0 = full size). quality: JPEG quality 1..100.
    """

    station_id: int
    camera_id: int
    session: int
    echo: int
    request_id: int
    max_width: int = 640
    quality: int = 80


@dataclass(frozen=True, slots=True)
class ImageChunk:
    """Station -> server: one slice of the JPEG answering ImageRequest request_id.

    index/count: this chunk and how many make the image; total_bytes: the JPEG's length. capture_ns: the
    frame's capture time (station clock converted to the server's when synced, else the station clock).
    width/height: the JPEG's size in pixels. background: the station's background level of that frame
    (grey levels 0..255, see stations/still.py). data: bytes [index * IMAGE_CHUNK_BYTES, ...) of the JPEG.
    """

    station_id: int
    camera_id: int
    session: int
    request_id: int
    index: int
    count: int
    total_bytes: int
    capture_ns: int
    width: int
    height: int
    background: float
    data: bytes


@dataclass(frozen=True, slots=True)
class MaskUpdate:
    """Server -> station: replace the detector's ignore rectangles and/or rois ([x0, y0, x1, y1] px, x1 > x0,
    y1 > y0) and save them to the station's config. flags: MaskFlag bits saying which list is set (an empty
    list with its flag clears it). session/echo/request_id: as ImageRequest."""

    station_id: int
    camera_id: int
    session: int
    echo: int
    request_id: int
    flags: int
    ignore: tuple[tuple[int, int, int, int], ...] = ()
    rois: tuple[tuple[int, int, int, int], ...] = ()


@dataclass(frozen=True, slots=True)
class MaskAck:
    """Station -> server: the answer to MaskUpdate request_id; status a MaskStatus, text why (UTF-8, 64 bytes)."""

    station_id: int
    camera_id: int
    session: int
    request_id: int
    status: int
    text: str = ""


Message = (BlobFrame | Hello | HelloAck | Heartbeat | SyncRequest | SyncReply | Bye | ImageRequest | ImageChunk
           | MaskUpdate | MaskAck)


# ---------------------------------------------------------------- helpers


def _check_range(name: str, v: int, lo: int, hi: int) -> int:
    v = int(v)
    if not lo <= v <= hi:
        raise ProtocolError(f"{name}={v} out of range [{lo}, {hi}] for the wire format")
    return v


def _tag(key: bytes, data: bytes | memoryview) -> bytes:
    return hmac.new(key, data, hashlib.sha256).digest()[:TAG_BYTES]


def _finish(mtype: int, station_id: int, camera_id: int, body: bytes, key: bytes | None) -> bytes:
    """Prefix the common header and append the tag when a key is given."""
    sid = _check_range("station_id", station_id, 0, _U16)
    cid = _check_range("camera_id", camera_id, 0, _U16)
    flags = HF_SIGNED if key is not None else 0
    packet = _HEADER.pack(MAGIC, PROTOCOL_VERSION, mtype, flags, 0, sid, cid, len(body), 0) + body
    if key is not None:
        packet += _tag(key, packet)
    return packet


def _text(name: str, s: str, size: int) -> bytes:
    b = s.encode("utf-8")
    if len(b) > size:
        raise ProtocolError(f"{name} {s!r} is {len(b)} bytes UTF-8; the wire field holds {size}")
    return b


def _untext(b: bytes) -> str:
    return b.rstrip(b"\0").decode("utf-8", errors="replace")


# ---------------------------------------------------------------- encode


def encode_frame(frame: BlobFrame, key: bytes | None = None) -> bytes:
    """BlobFrame -> one datagram. recv_ns is not sent.

    frame.blobs: (N, 4) x, y, area, peak; N <= MAX_BLOBS_PER_PACKET (the
    station caps and sets FLAG_TRUNCATED before encoding).
    """
    blobs = np.asarray(frame.blobs)
    if blobs.ndim != 2 or blobs.shape[1] != 4:
        if blobs.size == 0:
            blobs = np.zeros((0, 4), _BLOB_DTYPE)
        else:
            raise ProtocolError(f"frame blobs must have shape (N, 4), got {blobs.shape}")
    n = blobs.shape[0]
    if n > MAX_BLOBS_PER_PACKET:
        raise ProtocolError(
            f"frame has {n} blobs; at most {MAX_BLOBS_PER_PACKET} fit one packet "
            "(cap them and set FLAG_TRUNCATED)"
        )
    sid = _check_range("station_id", frame.station_id, 0, _U16)
    cid = _check_range("camera_id", frame.camera_id, 0, _U16)
    session = _check_range("session", frame.session, 0, _U32)
    seq = _check_range("seq", frame.seq, 0, _U32)
    flags = _check_range("flags", frame.flags, 0, _U16)
    cap = _check_range("capture_ns", frame.capture_ns, _I64_MIN, _I64_MAX)
    hflags = HF_SIGNED if key is not None else 0
    body_len = FRAME_FIXED_BYTES + n * BLOB_BYTES
    packet = _FRAME_HEAD.pack(
        MAGIC, PROTOCOL_VERSION, MSG_FRAME, hflags, 0, sid, cid, body_len, 0, session, seq, cap, flags, n
    ) + np.ascontiguousarray(blobs, dtype=_BLOB_DTYPE).tobytes()
    if key is not None:
        packet += _tag(key, packet)
    return packet


def _cookie(name: str, c: bytes) -> bytes:
    if type(c) is not bytes or len(c) != COOKIE_BYTES:
        raise ProtocolError(f"{name} must be {COOKIE_BYTES} bytes, got {c!r}")
    return c


def encode(msg: Message, key: bytes | None = None) -> bytes:
    """Any protocol message -> one datagram (signed with HMAC-SHA256 when key is given)."""
    if isinstance(msg, BlobFrame):
        return encode_frame(msg, key)
    if isinstance(msg, Hello):
        if msg.camera_kind not in CAMERA_KINDS:
            raise ProtocolError(f"camera_kind {msg.camera_kind!r} is not one of {CAMERA_KINDS}")
        body = _HELLO.pack(
            _check_range("session", msg.session, 0, _U32),
            _check_range("counter", msg.counter, 0, _U32),
            _check_range("width", msg.width, 0, _U16),
            _check_range("height", msg.height, 0, _U16),
            float(msg.fps),
            CAMERA_KINDS.index(msg.camera_kind),
            _check_range("timebase", msg.timebase, 0, 255),
            _cookie("cookie", msg.cookie),
            _text("camera_name", msg.camera_name, 32),
            _text("software", msg.software, 16),
        )
        return _finish(MSG_HELLO, msg.station_id, msg.camera_id, body, key)
    if isinstance(msg, HelloAck):
        body = _HELLO_ACK.pack(
            _check_range("session", msg.session, 0, _U32),
            _check_range("echo", msg.echo, 0, _U32),
            _check_range("status", msg.status, 0, 255),
            _check_range("start_ns", msg.start_ns, _I64_MIN, _I64_MAX),
            _check_range("server_ns", msg.server_ns, _I64_MIN, _I64_MAX),
            _check_range("duration_ns", msg.duration_ns, 0, _I64_MAX),
            _cookie("cookie", msg.cookie),
        )
        return _finish(MSG_HELLO_ACK, msg.station_id, msg.camera_id, body, key)
    if isinstance(msg, Heartbeat):
        if msg.temperature_c is None:
            temp = TEMPERATURE_UNKNOWN
        else:
            temp = int(np.clip(round(msg.temperature_c * 100.0), -32767, 32767))
        body = _HEARTBEAT.pack(
            _check_range("session", msg.session, 0, _U32),
            _check_range("counter", msg.counter, 0, _U32),
            _check_range("status", msg.status, 0, _U16),
            temp,
            int(msg.frames_captured) & _U32,
            int(msg.frames_dropped) & _U32,
            int(msg.send_errors) & _U32,
            int(np.clip(msg.drift_ppb, -(1 << 31), (1 << 31) - 1)),
            _check_range("clock_offset_ns", msg.clock_offset_ns, _I64_MIN, _I64_MAX),
            _check_range("clock_uncertainty_ns", msg.clock_uncertainty_ns, -1, _I64_MAX),
            _check_range("station_ns", msg.station_ns, _I64_MIN, _I64_MAX),
        )
        return _finish(MSG_HEARTBEAT, msg.station_id, msg.camera_id, body, key)
    if isinstance(msg, SyncRequest):
        body = _SYNC_REQUEST.pack(
            _check_range("session", msg.session, 0, _U32),
            _check_range("counter", msg.counter, 0, _U32),
            _check_range("t1_ns", msg.t1_ns, _I64_MIN, _I64_MAX),
        )
        return _finish(MSG_SYNC_REQUEST, msg.station_id, msg.camera_id, body, key)
    if isinstance(msg, SyncReply):
        body = _SYNC_REPLY.pack(
            _check_range("session", msg.session, 0, _U32),
            _check_range("echo", msg.echo, 0, _U32),
            _check_range("t1_ns", msg.t1_ns, _I64_MIN, _I64_MAX),
            _check_range("t2_ns", msg.t2_ns, _I64_MIN, _I64_MAX),
            _check_range("t3_ns", msg.t3_ns, _I64_MIN, _I64_MAX),
        )
        return _finish(MSG_SYNC_REPLY, msg.station_id, msg.camera_id, body, key)
    if isinstance(msg, Bye):
        body = _BYE.pack(_check_range("session", msg.session, 0, _U32), _check_range("counter", msg.counter, 0, _U32))
        return _finish(MSG_BYE, msg.station_id, msg.camera_id, body, key)
    if isinstance(msg, ImageRequest):
        body = _IMAGE_REQUEST.pack(
            _check_range("session", msg.session, 0, _U32),
            _check_range("echo", msg.echo, 0, _U32),
            _check_range("request_id", msg.request_id, 0, _U32),
            _check_range("max_width", msg.max_width, 0, _U16),
            _check_range("quality", msg.quality, 1, 100),
        )
        return _finish(MSG_IMAGE_REQUEST, msg.station_id, msg.camera_id, body, key)
    if isinstance(msg, ImageChunk):
        data = bytes(msg.data)
        _check_chunk(msg.index, msg.count, msg.total_bytes, len(data), msg.width, msg.height, msg.background)
        body = _IMAGE_CHUNK.pack(
            _check_range("session", msg.session, 0, _U32),
            _check_range("request_id", msg.request_id, 0, _U32),
            msg.index, msg.count, msg.total_bytes,
            _check_range("capture_ns", msg.capture_ns, _I64_MIN, _I64_MAX),
            msg.width, msg.height, float(msg.background),
        ) + data
        return _finish(MSG_IMAGE_CHUNK, msg.station_id, msg.camera_id, body, key)
    if isinstance(msg, MaskUpdate):
        flags = _check_range("flags", msg.flags, 0, int(MaskFlag.IGNORE | MaskFlag.ROIS))
        rects = []
        for name, lst in (("ignore", msg.ignore), ("rois", msg.rois)):
            if len(lst) > MAX_MASK_RECTS:
                raise ProtocolError(f"mask update has {len(lst)} {name} rectangles; at most {MAX_MASK_RECTS} fit")
            for r in lst:
                rects.append(_MASK_RECT.pack(*_check_rect(name, r)))
        body = _MASK_UPDATE.pack(
            _check_range("session", msg.session, 0, _U32),
            _check_range("echo", msg.echo, 0, _U32),
            _check_range("request_id", msg.request_id, 0, _U32),
            flags, len(msg.ignore), len(msg.rois),
        ) + b"".join(rects)
        return _finish(MSG_MASK_UPDATE, msg.station_id, msg.camera_id, body, key)
    if isinstance(msg, MaskAck):
        text = msg.text.encode("utf-8")[:MASK_TEXT_BYTES].decode("utf-8", errors="ignore").encode("utf-8")
        body = _MASK_ACK.pack(
            _check_range("session", msg.session, 0, _U32),
            _check_range("request_id", msg.request_id, 0, _U32),
            _check_range("status", msg.status, 0, len(MaskStatus) - 1),
            text,
        )
        return _finish(MSG_MASK_ACK, msg.station_id, msg.camera_id, body, key)
    raise ProtocolError(f"cannot encode {type(msg).__name__}: not a protocol message")


def _check_chunk(index: int, count: int, total: int, n: int, width: int, height: int, background: float) -> None:
    """The chunking rule (every chunk but the last is IMAGE_CHUNK_BYTES long) and the header's ranges."""
    if not 0 < total <= MAX_IMAGE_BYTES:
        raise ProtocolError(f"image chunk total_bytes {total} out of range (0, {MAX_IMAGE_BYTES}]")
    if count != -(-total // IMAGE_CHUNK_BYTES):
        raise ProtocolError(f"image chunk count {count} does not fit total_bytes {total} "
                            f"({IMAGE_CHUNK_BYTES} bytes a chunk)")
    if not 0 <= index < count:
        raise ProtocolError(f"image chunk index {index} out of range [0, {count})")
    want = IMAGE_CHUNK_BYTES if index < count - 1 else total - index * IMAGE_CHUNK_BYTES
    if n != want:
        raise ProtocolError(f"image chunk {index} of {count} carries {n} bytes, expected {want}")
    if not (0 < width <= _U16 and 0 < height <= _U16):
        raise ProtocolError(f"image chunk size {width}x{height}: width and height must be in 1..65535")
    if not 0.0 <= background <= 255.0:  # false for NaN too
        raise ProtocolError(f"image chunk background {background} out of range [0, 255]")


def _check_rect(name: str, r: object) -> tuple[int, int, int, int]:
    try:
        x0, y0, x1, y1 = (int(v) for v in r)  # type: ignore[union-attr]
    except (TypeError, ValueError):
        raise ProtocolError(f"{name} rectangle {r!r} is not [x0, y0, x1, y1]") from None
    if not (0 <= x0 < x1 <= _U16 and 0 <= y0 < y1 <= _U16):
        raise ProtocolError(f"{name} rectangle {[x0, y0, x1, y1]} needs 0 <= x0 < x1 <= 65535, 0 <= y0 < y1")
    return x0, y0, x1, y1


# ---------------------------------------------------------------- decode


_BODY_SIZES = {
    MSG_HELLO: _HELLO.size,
    MSG_HELLO_ACK: _HELLO_ACK.size,
    MSG_HEARTBEAT: _HEARTBEAT.size,
    MSG_SYNC_REQUEST: _SYNC_REQUEST.size,
    MSG_SYNC_REPLY: _SYNC_REPLY.size,
    MSG_BYE: _BYE.size,
    MSG_IMAGE_REQUEST: _IMAGE_REQUEST.size,
    MSG_MASK_ACK: _MASK_ACK.size,
}
_TYPE_NAMES = {t: t.name.lower().replace("_", "-") for t in MsgType}  # "hello-ack", ... (error messages)


def _check_header(data: bytes, key: bytes | None, version_ok: int) -> tuple[int, int, int, int, int]:
    """Length, magic, version, size and tag checks shared by both versions; (mtype, sid, cid, body_len, n)."""
    n = len(data)
    if n > MAX_PACKET_BYTES:
        raise ProtocolError(f"oversize packet: {n} bytes > {MAX_PACKET_BYTES}")
    if n < HEADER_BYTES:
        raise ProtocolError(f"truncated packet: {n} bytes, the header alone is {HEADER_BYTES}")
    magic, version, mtype, hflags, _r0, sid, cid, body_len, _r1 = _HEADER.unpack_from(data)
    if magic != MAGIC:
        raise ProtocolError(f"bad magic {magic!r} (expected {MAGIC!r}): not a visionpos packet")
    if version != version_ok:
        if version > version_ok:
            hint = "the sender is newer; upgrade visionpos on this side (server or station)"
        else:
            hint = "the sender is older; upgrade the sender"
        raise ProtocolError(f"protocol version {version} unsupported (this build speaks {version_ok}): {hint}")
    end = HEADER_BYTES + body_len
    signed = hflags & HF_SIGNED
    expected = end + TAG_BYTES if signed else end
    if n != expected:
        what = "truncated" if n < expected else "trailing bytes in"
        raise ProtocolError(
            f"{what} packet: {n} bytes, header says {expected} "
            f"(body {body_len}{' + tag ' + str(TAG_BYTES) if signed else ''})"
        )
    if key is not None:
        if not signed:
            raise ProtocolError("unsigned packet rejected: this side requires HMAC (give the sender the shared key)")
        if not hmac.compare_digest(_tag(key, memoryview(data)[:end]), data[end:]):
            raise ProtocolError("bad signature: HMAC tag mismatch (check the shared key on both sides)")
    return mtype, sid, cid, body_len, end


def _check_blobs(data: bytes, start: int, end: int) -> None:
    """Reject NaN/inf blob values (see decode)."""
    hi = data[start + 3:end:4]
    if 0x7F in hi or 0xFF in hi:
        raise ProtocolError("frame blob value not finite (NaN, inf or beyond 2^127)")


def _check_hello(w: int, h: int, fps: float, kind: int) -> None:
    if not w or not h:
        raise ProtocolError(f"hello resolution {w}x{h}: width and height must be > 0")
    if not (0.0 < fps <= MAX_FPS):  # false for NaN too
        raise ProtocolError(f"hello fps {fps} out of range (0, {MAX_FPS:g}]")
    if kind >= len(CAMERA_KINDS):
        raise ProtocolError(f"hello camera kind {kind} unknown (expected 0..{len(CAMERA_KINDS) - 1})")


def decode(data: bytes, key: bytes | None = None, recv_ns: int = 0) -> Message:
    """One datagram -> message. Raises ProtocolError naming the problem.

    With `key` set, packets without a tag or with a wrong tag are rejected.
    Without a key, a tag that is present is skipped unchecked.
    recv_ns is stored on decoded BlobFrames (it is not on the wire).
    Decoded frame blobs are a read-only (N, 4) float32 view of the packet.
    """
    if type(data) is not bytes:
        data = bytes(data)  # own the memory: blobs view into it
    n = len(data)
    # the frame path is inlined (per packet); anything unusual is diagnosed by _check_header
    if n >= _BLOB0 and n <= MAX_PACKET_BYTES and data[5] == MSG_FRAME and (key is None or data[6] & HF_SIGNED):
        (magic, version, _t, hflags, _r0, sid, cid, body_len, _r1, session, seq, capture_ns, flags,
         count) = _FRAME_HEAD.unpack_from(data)
        end = HEADER_BYTES + body_len
        if (magic != MAGIC or version != PROTOCOL_VERSION or n != (end + TAG_BYTES if hflags & HF_SIGNED else end)
                or (key is not None and not hmac.compare_digest(_tag(key, memoryview(data)[:end]), data[end:]))):
            _check_header(data, key, PROTOCOL_VERSION)  # raises, naming the problem
            raise ProtocolError("malformed frame header")  # not reached: the checks above are the same
    else:
        _t, sid, cid, body_len, end = _check_header(data, key, PROTOCOL_VERSION)
        if _t == MSG_FRAME:  # shorter than the fixed part
            raise ProtocolError(f"truncated frame: body {body_len} bytes < {FRAME_FIXED_BYTES}")
        return _decode_control(data, _t, sid, cid, body_len)
    if body_len != FRAME_FIXED_BYTES + count * BLOB_BYTES:
        raise ProtocolError(
            f"frame blob count {count} does not match body length {body_len} "
            f"(expected {FRAME_FIXED_BYTES + count * BLOB_BYTES})"
        )
    if count > MAX_BLOBS_PER_PACKET:
        raise ProtocolError(f"frame blob count {count} > {MAX_BLOBS_PER_PACKET}, the most a frame may carry")
    # NaN/inf cheaply: a float32 whose high byte is 0x7f or 0xff has an exponent of at least 254, i.e. it
    # is NaN, +-inf or of magnitude >= 2**127 (no pixel value is that big)
    hi = data[_BLOB0 + 3:end:4]
    if 0x7F in hi or 0xFF in hi:
        raise ProtocolError("frame blob value not finite (NaN, inf or beyond 2^127)")
    blobs = np.frombuffer(data, _BLOB_DTYPE, count * 4, _BLOB0).reshape(count, 4)
    return BlobFrame(cid, seq, capture_ns, blobs, sid, flags, recv_ns, session)


def _decode_variable(data: bytes, mtype: int, sid: int, cid: int, body_len: int) -> Message:
    """IMAGE_CHUNK and MASK_UPDATE: a fixed part, then a checked number of bytes/rectangles."""
    if mtype == MSG_IMAGE_CHUNK:
        if body_len < _IMAGE_CHUNK.size:
            raise ProtocolError(f"image-chunk body is {body_len} bytes, less than its fixed {_IMAGE_CHUNK.size}")
        session, rid, index, count, total, cap, w, h, bg = _IMAGE_CHUNK.unpack_from(data, HEADER_BYTES)
        start = HEADER_BYTES + _IMAGE_CHUNK.size
        chunk = data[start:HEADER_BYTES + body_len]
        _check_chunk(index, count, total, len(chunk), w, h, bg)
        return ImageChunk(sid, cid, session, rid, index, count, total, cap, w, h, bg, chunk)
    if body_len < _MASK_UPDATE.size:
        raise ProtocolError(f"mask-update body is {body_len} bytes, less than its fixed {_MASK_UPDATE.size}")
    session, echo, rid, flags, n_ignore, n_rois = _MASK_UPDATE.unpack_from(data, HEADER_BYTES)
    if flags & ~int(MaskFlag.IGNORE | MaskFlag.ROIS) or not flags:
        raise ProtocolError(f"mask update flags {flags:#x}: expected IGNORE (1) and/or ROIS (2)")
    if n_ignore > MAX_MASK_RECTS or n_rois > MAX_MASK_RECTS:
        raise ProtocolError(f"mask update has {n_ignore} ignore and {n_rois} roi rectangles; at most "
                            f"{MAX_MASK_RECTS} each")
    if body_len != _MASK_UPDATE.size + (n_ignore + n_rois) * _MASK_RECT.size:
        raise ProtocolError(f"mask update of {n_ignore} + {n_rois} rectangles does not match body length {body_len}")
    rects = []
    for i in range(n_ignore + n_rois):
        r = _MASK_RECT.unpack_from(data, HEADER_BYTES + _MASK_UPDATE.size + i * _MASK_RECT.size)
        rects.append(_check_rect("ignore" if i < n_ignore else "rois", r))
    return MaskUpdate(sid, cid, session, echo, rid, flags, tuple(rects[:n_ignore]), tuple(rects[n_ignore:]))


def _decode_control(data: bytes, mtype: int, sid: int, cid: int, body_len: int) -> Message:
    if mtype == MSG_IMAGE_CHUNK or mtype == MSG_MASK_UPDATE:
        return _decode_variable(data, mtype, sid, cid, body_len)
    size = _BODY_SIZES.get(mtype)
    if size is None:
        raise ProtocolError(f"unknown message type {mtype} (station and server versions differ?)")
    if body_len != size:
        raise ProtocolError(f"{_TYPE_NAMES[mtype]} body is {body_len} bytes, expected {size}")
    if mtype == MSG_HELLO:
        session, counter, w, h, fps, kind, timebase, cookie, name, sw = _HELLO.unpack_from(data, HEADER_BYTES)
        _check_hello(w, h, fps, kind)
        return Hello(sid, cid, session, w, h, fps, CAMERA_KINDS[kind], _untext(name), _untext(sw), timebase,
                     counter, cookie)
    if mtype == MSG_HELLO_ACK:
        session, echo, status, start, server, dur, cookie = _HELLO_ACK.unpack_from(data, HEADER_BYTES)
        return HelloAck(sid, cid, session, start, server, status, dur, echo, cookie)
    if mtype == MSG_HEARTBEAT:
        (session, counter, status, temp, cap, drop, err, drift, off, unc, st_ns) = _HEARTBEAT.unpack_from(
            data, HEADER_BYTES
        )
        temp_c = None if temp == TEMPERATURE_UNKNOWN else temp / 100.0
        return Heartbeat(sid, cid, counter, session, status, cap, drop, err, off, unc, drift, temp_c, st_ns)
    if mtype == MSG_SYNC_REQUEST:
        session, counter, t1 = _SYNC_REQUEST.unpack_from(data, HEADER_BYTES)
        return SyncRequest(sid, cid, t1, counter, session)
    if mtype == MSG_SYNC_REPLY:
        session, echo, t1, t2, t3 = _SYNC_REPLY.unpack_from(data, HEADER_BYTES)
        return SyncReply(sid, cid, t1, t2, t3, echo, session)
    if mtype == MSG_IMAGE_REQUEST:
        session, echo, rid, max_width, quality = _IMAGE_REQUEST.unpack_from(data, HEADER_BYTES)
        if not 1 <= quality <= 100:
            raise ProtocolError(f"image request quality {quality} out of range [1, 100]")
        return ImageRequest(sid, cid, session, echo, rid, max_width, quality)
    if mtype == MSG_MASK_ACK:
        session, rid, status, text = _MASK_ACK.unpack_from(data, HEADER_BYTES)
        if status >= len(MaskStatus):
            raise ProtocolError(f"mask ack status {status} unknown (expected 0..{len(MaskStatus) - 1})")
        return MaskAck(sid, cid, session, rid, status, _untext(text))
    session, counter = _BYE.unpack_from(data, HEADER_BYTES)
    return Bye(sid, cid, session, counter)


# ---------------------------------------------------------------- version 1 (replay of old recordings only)

_V1_FRAME_HEAD = struct.Struct("<IHHq")  # seq, flags, count, capture_ns
_V1_BODIES = {
    MSG_HELLO: struct.Struct("<IHHfBBBB32s16s"),
    MSG_HEARTBEAT: struct.Struct("<IHhIIIiqqqI4x"),
    MSG_SYNC_REQUEST: struct.Struct("<qI4x"),
    MSG_BYE: struct.Struct("<I4x"),
}


def decode_v1(data: bytes) -> Message:
    """A protocol-1 station -> server packet (as recorded before version 2) -> the version-2 dataclass.

    For replays of old recordings only: the tag is not checked (a replay trusts its recording), v1
    has no counters, cookies or frame sessions (they decode as 0 / NO_COOKIE), and server -> station
    types are refused. The same validation as version 2 applies otherwise.
    """
    if type(data) is not bytes:
        data = bytes(data)
    mtype, sid, cid, body_len, end = _check_header(data, None, 1)
    if mtype == MSG_FRAME:
        if body_len < _V1_FRAME_HEAD.size:
            raise ProtocolError(f"truncated frame: body {body_len} bytes < {_V1_FRAME_HEAD.size}")
        seq, flags, count, capture_ns = _V1_FRAME_HEAD.unpack_from(data, HEADER_BYTES)
        start = HEADER_BYTES + _V1_FRAME_HEAD.size
        if body_len != _V1_FRAME_HEAD.size + count * BLOB_BYTES or count > MAX_BLOBS_PER_PACKET:
            raise ProtocolError(f"frame blob count {count} does not match body length {body_len} (v1)")
        _check_blobs(data, start, end)
        blobs = np.frombuffer(data, _BLOB_DTYPE, count * 4, start).reshape(count, 4)
        return BlobFrame(cid, seq, capture_ns, blobs, sid, flags)
    st = _V1_BODIES.get(mtype)
    if st is None:
        raise ProtocolError(f"message type {mtype} is not a v1 station -> server message")
    if body_len != st.size:
        raise ProtocolError(f"{_TYPE_NAMES[mtype]} body is {body_len} bytes, expected {st.size} (v1)")
    v = st.unpack_from(data, HEADER_BYTES)
    if mtype == MSG_HELLO:
        session, w, h, fps, kind, timebase, _a, _b, name, sw = v
        _check_hello(w, h, fps, kind)
        return Hello(sid, cid, session, w, h, fps, CAMERA_KINDS[kind], _untext(name), _untext(sw), timebase)
    if mtype == MSG_HEARTBEAT:
        seq, status, temp, cap, drop, err, drift, off, unc, st_ns, session = v
        temp_c = None if temp == TEMPERATURE_UNKNOWN else temp / 100.0
        return Heartbeat(sid, cid, seq, session, status, cap, drop, err, off, unc, drift, temp_c, st_ns)
    if mtype == MSG_SYNC_REQUEST:
        t1, seq = v
        return SyncRequest(sid, cid, t1, seq)
    return Bye(sid, cid, v[0])


def packet_version(data: bytes) -> int | None:
    """The version byte of a visionpos packet, None if it is not one."""
    return data[4] if len(data) >= HEADER_BYTES and data[:4] == MAGIC else None


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
    status: int = ACK_OK,
    duration_ns: int = 0,
    cookie: bytes = NO_COOKIE,
) -> HelloAck:
    """Server answer to a Hello (registration) or a Heartbeat (keep-alive).

    start_ns: the capture start (trigger) time on the server clock, the same
    for every station of a session; server_ns: server clock now. Answer a
    Heartbeat whose session the server does not know with
    status=ACK_UNKNOWN_SESSION so the station registers again at once. The
    ack echoes the request's session and counter (the station checks both).
    """
    return HelloAck(hello.station_id, hello.camera_id, hello.session, int(start_ns), int(server_ns), status,
                    duration_ns, hello.counter, cookie)


def seq_delta(new: int, old: int) -> int:
    """Signed difference new - old of two u32 sequence numbers, wrap-around aware.

    > 0: new is later (1 = next frame, k = k - 1 frames lost);
    <= 0: duplicate or replayed/reordered packet (drop it).
    """
    d = (int(new) - int(old)) & _U32
    return d - (1 << 32) if d >= (1 << 31) else d


def server_time_from_realtime(capture_realtime_ns: int, server_realtime_ns: int, server_clock_ns: int) -> int:
    """Convert a TIMEBASE_REALTIME capture stamp to the server clock.

    server_realtime_ns / server_clock_ns: the server's CLOCK_REALTIME and its
    own (monotonic) clock read back to back; valid when both hosts'
    realtime clocks are disciplined to the same reference (PTP/chrony).
    """
    return int(capture_realtime_ns) - (int(server_realtime_ns) - int(server_clock_ns))
