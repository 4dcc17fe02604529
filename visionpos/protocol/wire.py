"""The protocol's constants and enums, the common header and its HMAC tag (docs/protocol.md, "Common header").

Every packet is one UDP datagram:

    common header (16 bytes) | body (body_len bytes) | optional HMAC tag (16 bytes)

`write_packet` frames a message body; `read_header` checks a datagram's length, magic, version, size and tag
and says which message it holds. `WireMessage` is what every message dataclass (control.py, stills.py) is:
it writes itself (`write(key) -> bytes`, its body `write_body()`) and reads itself (`read(data, key)`, its
body `read_body(...)`), in the manner of the mcap library's records. The field helpers (`check_range`,
`pack_text`, ...) are what those methods use.
"""

from __future__ import annotations

import hashlib
import hmac
import struct
from enum import IntEnum, IntFlag
from typing import ClassVar, Self

from visionpos.errors import VisionposError

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

TEMPERATURE_UNKNOWN = -32768  # Heartbeat temperature field value for "no sensor"
UNCERTAINTY_UNKNOWN = -1

# Still images (IMAGE_CHUNK): every chunk but the last carries exactly IMAGE_CHUNK_BYTES of the JPEG, so a
# signed chunk is one datagram; an image is at most MAX_IMAGE_BYTES (count <= MAX_IMAGE_CHUNKS).
IMAGE_CHUNK_BYTES = MAX_PACKET_BYTES - HEADER_BYTES - 32 - TAG_BYTES  # 1408
MAX_IMAGE_BYTES = 512 * 1024
MAX_IMAGE_CHUNKS = -(-MAX_IMAGE_BYTES // IMAGE_CHUNK_BYTES)
MAX_MASK_RECTS = 64  # per list in a MASK_UPDATE: 16 + 16 + 128 x 8 + 16 <= 1472
MASK_TEXT_BYTES = 64

U16 = 0xFFFF
U32 = 0xFFFFFFFF
I64_MIN, I64_MAX = -(1 << 63), (1 << 63) - 1


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

    @property
    def label(self) -> str:
        """"hello-ack", ...: the type in error messages."""
        return self.name.lower().replace("_", "-")


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
    """Hello.camera_kind on the wire; Hello carries its lower-case name (CAMERA_KINDS)."""

    UNKNOWN = 0
    PINHOLE = 1
    FISHEYE = 2


class HeartbeatStatus(IntFlag):
    """Heartbeat.status bits."""

    CAMERA_OK = 0x01  # the last capture attempt produced a frame
    CLOCK_SYNCED = 0x02  # clock offset estimate is valid (or the clock is external)
    CLOCK_EXTERNAL = 0x04  # built-in sync is off: host clock disciplined by PTP/chrony
    STREAMING = 0x08  # trigger time reached, frames are being sent


CAMERA_KINDS = tuple(k.name.lower() for k in CameraKind)  # Hello.camera_kind values, in wire order

# The per-packet paths test the bit as a plain int: `int & IntFlag` builds a new IntFlag (~1 us a packet).
SIGNED_BIT = int(HeaderFlag.SIGNED)

HEADER = struct.Struct("<4sBBBBHHHH")
assert HEADER.size == HEADER_BYTES


class ProtocolError(VisionposError, ValueError):  # ValueError: callers that catch it still do
    """A packet that cannot be encoded or decoded; the message says why and what to do."""


# ---------------------------------------------------------------- fields


def check_range(name: str, v: int, lo: int, hi: int) -> int:
    """int(v), refused with a ProtocolError naming the field when outside [lo, hi]."""
    v = int(v)
    if not lo <= v <= hi:
        raise ProtocolError(f"{name}={v} out of range [{lo}, {hi}] for the wire format")
    return v


def pack_text(name: str, s: str, size: int) -> bytes:
    """A UTF-8 text field of at most `size` bytes (struct pads it with zeros)."""
    b = s.encode("utf-8")
    if len(b) > size:
        raise ProtocolError(f"{name} {s!r} is {len(b)} bytes UTF-8; the wire field holds {size}")
    return b


def unpack_text(b: bytes) -> str:
    return b.rstrip(b"\0").decode("utf-8", errors="replace")


def check_cookie(name: str, c: bytes) -> bytes:
    if type(c) is not bytes or len(c) != COOKIE_BYTES:
        raise ProtocolError(f"{name} must be {COOKIE_BYTES} bytes, got {c!r}")
    return c


# ---------------------------------------------------------------- header and tag


def tag(key: bytes, data: bytes | memoryview) -> bytes:
    """The packet's HMAC tag: HMAC-SHA256 over header and body, its first TAG_BYTES bytes."""
    return hmac.new(key, data, hashlib.sha256).digest()[:TAG_BYTES]


def write_packet(mtype: int, station_id: int, camera_id: int, body: bytes, key: bytes | None) -> bytes:
    """Prefix the common header to a message body and append the tag when a key is given."""
    sid = check_range("station_id", station_id, 0, U16)
    cid = check_range("camera_id", camera_id, 0, U16)
    flags = SIGNED_BIT if key is not None else 0
    packet = HEADER.pack(MAGIC, PROTOCOL_VERSION, mtype, flags, 0, sid, cid, len(body), 0) + body
    if key is not None:
        packet += tag(key, packet)
    return packet


def read_header(data: bytes, key: bytes | None, version_ok: int) -> tuple[int, int, int, int, int]:
    """Length, magic, version, size and tag checks shared by both versions; (mtype, sid, cid, body_len, end)."""
    n = len(data)
    if n > MAX_PACKET_BYTES:
        raise ProtocolError(f"oversize packet: {n} bytes > {MAX_PACKET_BYTES}")
    if n < HEADER_BYTES:
        raise ProtocolError(f"truncated packet: {n} bytes, the header alone is {HEADER_BYTES}")
    magic, version, mtype, hflags, _r0, sid, cid, body_len, _r1 = HEADER.unpack_from(data)
    if magic != MAGIC:
        raise ProtocolError(f"bad magic {magic!r} (expected {MAGIC!r}): not a visionpos packet")
    if version != version_ok:
        if version > version_ok:
            hint = "the sender is newer; upgrade visionpos on this side (server or station)"
        else:
            hint = "the sender is older; upgrade the sender"
        raise ProtocolError(f"protocol version {version} unsupported (this build speaks {version_ok}): {hint}")
    end = HEADER_BYTES + body_len
    signed = hflags & SIGNED_BIT
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
        if not hmac.compare_digest(tag(key, memoryview(data)[:end]), data[end:]):
            raise ProtocolError("bad signature: HMAC tag mismatch (check the shared key on both sides)")
    return mtype, sid, cid, body_len, end


def packet_version(data: bytes) -> int | None:
    """The version byte of a visionpos packet, None if it is not one."""
    return data[4] if len(data) >= HEADER_BYTES and data[:4] == MAGIC else None


def check_body_size(mtype: MsgType, body_len: int, size: int) -> None:
    """A fixed-size message's body must be exactly its documented size."""
    if body_len != size:
        raise ProtocolError(f"{mtype.label} body is {body_len} bytes, expected {size}")


class WireMessage:
    """A protocol message that writes and reads itself (every message but FRAME, which is a BlobFrame).

    Subclasses are frozen dataclasses whose first fields are station_id and camera_id (the header's) and
    that set TYPE and implement write_body / read_body.
    """

    __slots__ = ()
    TYPE: ClassVar[MsgType]
    station_id: int
    camera_id: int

    def write_body(self) -> bytes:
        """The body bytes (docs/protocol.md, the message's table), every field range-checked."""
        raise NotImplementedError

    @classmethod
    def read_body(cls, data: bytes, station_id: int, camera_id: int, body_len: int) -> Self:
        """The message from a datagram whose header read_header checked (body at HEADER_BYTES)."""
        raise NotImplementedError

    def write(self, key: bytes | None = None) -> bytes:
        """This message as one datagram, signed with HMAC-SHA256 when key is given."""
        return write_packet(self.TYPE, self.station_id, self.camera_id, self.write_body(), key)

    @classmethod
    def read(cls, data: bytes, key: bytes | None = None) -> Self:
        """One datagram that must hold this message type -> the message; ProtocolError names what is wrong.

        With `key` set, packets without a tag or with a wrong tag are rejected; without one, a tag is skipped.
        """
        data = bytes(data)
        mtype, sid, cid, body_len, _end = read_header(data, key, PROTOCOL_VERSION)
        if mtype != cls.TYPE:
            try:
                got = MsgType(mtype).label
            except ValueError:
                got = f"type {mtype}"
            raise ProtocolError(f"a {got} packet where a {cls.TYPE.label} was expected")
        return cls.read_body(data, sid, cid, body_len)
