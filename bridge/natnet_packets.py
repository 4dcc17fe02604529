"""NatNet wire format (the packets Motive's streaming engine sends and reads), no I/O.

Every packet: uint16 message id, uint16 payload byte count, payload; little-endian, packed.
Supported bitstream versions: 3.0, 3.1, 4.0, 4.1 (`VERSIONS`); 4.1 adds a byte count after each
data-section count and after each description type. docs/interop.md documents what visionpos
puts in each field; the layouts follow the NatNet SDK's published headers and sample clients.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

import numpy as np

NAT_CONNECT = 0
NAT_SERVERINFO = 1
NAT_REQUEST = 2
NAT_RESPONSE = 3
NAT_REQUEST_MODELDEF = 4
NAT_MODELDEF = 5
NAT_REQUEST_FRAMEOFDATA = 6
NAT_FRAMEOFDATA = 7
NAT_MESSAGESTRING = 8
NAT_DISCONNECT = 9
NAT_KEEPALIVE = 10
NAT_ECHOREQUEST = 12
NAT_ECHORESPONSE = 13
NAT_UNRECOGNIZED_REQUEST = 100

VERSIONS = ((3, 0), (3, 1), (4, 0), (4, 1))
MAX_PAYLOAD = 65503  # 65535 - IP and UDP headers - the 4-byte NatNet header
NAME_FIELD = 256  # fixed-size name in server info and connect
CONNECT_VERSION_AT = 265  # in the NAT_CONNECT payload: name[256], app version[4], NatNet version[4], flag, version[4]
TICKS_PER_SECOND = 1_000_000_000  # timestamps are server monotonic nanoseconds

# Data description types
DESC_MARKERSET = 0
DESC_RIGIDBODY = 1

# Labelled-marker params bits
MARKER_MODEL_SOLVED = 0x04
MARKER_HAS_MODEL = 0x08
MARKER_UNLABELED = 0x10

_HEADER = struct.Struct("<HH")
_I32 = struct.Struct("<i")
_F32 = struct.Struct("<f")
_RB = struct.Struct("<i3f4ffh")  # id, x y z, qx qy qz qw, mean marker error (m), params (bit 0: tracking valid)
_LABELED = struct.Struct("<i3ffhf")  # id, x y z, size (m), params, residual (m)
_SUFFIX = struct.Struct("<IIdQQQ")  # timecode, subframe, timestamp (s), mid-exposure, data ready, transmit (ticks)
_PRECISION = struct.Struct("<II")  # 4.x precision timestamp (s, fraction): 0 = not available
_TAIL = struct.Struct("<hi")  # frame params, end-of-data tag
_SERVER_TAIL = struct.Struct("<4B4BQHB4B")
_RB_DESC = struct.Struct("<ii3f")  # id, parent id, offset from parent (m)
_ECHO_REQUEST = struct.Struct("<Q")
_ECHO_RESPONSE = struct.Struct("<QQ")


def packet(message_id: int, payload: bytes = b"") -> bytes:
    return _HEADER.pack(message_id, len(payload)) + payload


def has_section_sizes(version: tuple[int, int]) -> bool:
    """4.1 and later write a byte count after each data section's count and each description type."""
    return version >= (4, 1)


def supported_version(requested: tuple[int, int], default: tuple[int, int]) -> tuple[int, int]:
    """The bitstream a client gets: what it asked for when supported, 4.1 for a newer 4.x, else `default`."""
    if requested in VERSIONS:
        return requested
    if requested[0] == 4 and requested > VERSIONS[-1]:
        return VERSIONS[-1]
    return default


def connect_version(payload: bytes) -> tuple[int, int]:
    """The bitstream version a NAT_CONNECT payload asks for; (0, 0) when it asks for none (short payload)."""
    if len(payload) >= CONNECT_VERSION_AT + 2:
        return payload[CONNECT_VERSION_AT], payload[CONNECT_VERSION_AT + 1]
    return 0, 0


def parse_version(text: str) -> tuple[int, int] | None:
    """'4.1' -> (4, 1); None when not MAJOR.MINOR with small integers."""
    major, dot, minor = text.strip().partition(".")
    if not dot:
        minor = "0"
    if not (major.isdigit() and minor.isdigit()) or len(major) > 3 or len(minor) > 3:
        return None
    return int(major), int(minor)


def server_info(app_name: str, app_version: tuple[int, int, int, int], version: tuple[int, int],
                data_port: int, multicast: bool, group: str) -> bytes:
    """NAT_SERVERINFO: name[256], app version, NatNet version, tick frequency, data port, multicast flag, group."""
    name = app_name.encode()[: NAME_FIELD - 1].ljust(NAME_FIELD, b"\0")
    g = [int(x) for x in group.split(".")] if multicast else [0, 0, 0, 0]
    tail = _SERVER_TAIL.pack(*app_version, version[0], version[1], 0, 0, TICKS_PER_SECOND, data_port,
                             1 if multicast else 0, *g)
    return packet(NAT_SERVERINFO, name + tail)


def response_int(value: int) -> bytes:
    return packet(NAT_RESPONSE, _I32.pack(value))


def response_float(value: float) -> bytes:
    return packet(NAT_RESPONSE, _F32.pack(value))


def response_text(text: str) -> bytes:
    return packet(NAT_RESPONSE, text.encode() + b"\0")


def unrecognized() -> bytes:
    return packet(NAT_UNRECOGNIZED_REQUEST)


def echo_response(payload: bytes, now_ticks: int) -> bytes | None:
    """NAT_ECHORESPONSE: the client's 8-byte stamp and our receive time, for its clock mapping."""
    if len(payload) < _ECHO_REQUEST.size:
        return None
    (stamp,) = _ECHO_REQUEST.unpack_from(payload)
    return packet(NAT_ECHORESPONSE, _ECHO_RESPONSE.pack(stamp, now_ticks))


@dataclass(frozen=True)
class BodyModel:
    """One rigid body as clients see it: name, id, marker offsets (M, 3) in the streamed body frame (m)."""

    name: str
    body_id: int
    markers: np.ndarray


def model_definitions(bodies: list[BodyModel], version: tuple[int, int]) -> bytes:
    """NAT_MODELDEF: a marker set and a rigid body description per body (no parent, zero offset)."""
    sized = has_section_sizes(version)
    parts = [_I32.pack(2 * len(bodies))]
    for b in bodies:
        name = b.name.encode() + b"\0"
        labels = [f"Marker{i + 1}".encode() + b"\0" for i in range(len(b.markers))]
        ms = name + _I32.pack(len(labels)) + b"".join(labels)
        m = np.asarray(b.markers, "<f4").reshape(-1, 3)
        rb = (name + _RB_DESC.pack(b.body_id, -1, 0.0, 0.0, 0.0) + _I32.pack(len(m)) + m.tobytes()
              + np.zeros(len(m), "<i4").tobytes())  # active labels: 0 = passive markers
        if version[0] >= 4:
            rb += b"".join(labels)
        for kind, desc in ((DESC_MARKERSET, ms), (DESC_RIGIDBODY, rb)):
            parts.append(_I32.pack(kind))
            if sized:
                parts.append(_I32.pack(len(desc)))
            parts.append(desc)
    return packet(NAT_MODELDEF, b"".join(parts))


@dataclass
class Frame:
    """One frame of data, already in the streamed axes: everything but the version-specific layout.

    bodies: (id, position (3,), quaternion x y z w (4,), mean error m, tracked) per body.
    marker_sets: (name, (M, 3) positions) per body. labeled: (id, position, params, residual m).
    Times in ticks (ns on the server's monotonic clock).
    """

    frame_number: int
    timestamp_s: float
    mid_exposure_ticks: int
    data_ready_ticks: int
    bodies: list[tuple[int, np.ndarray, np.ndarray, float, bool]]
    marker_sets: list[tuple[str, np.ndarray]]
    labeled: list[tuple[int, np.ndarray, int, float]]
    marker_size_m: float = 0.014


def _section(count: int, body: bytes, sized: bool) -> bytes:
    if sized:
        return _I32.pack(count) + _I32.pack(len(body)) + body
    return _I32.pack(count) + body


def frame_body(f: Frame, version: tuple[int, int]) -> bytes:
    """The frame payload up to the timestamps (the same for every client of one version)."""
    sized = has_section_sizes(version)
    ms = b"".join(n.encode() + b"\0" + _I32.pack(len(p)) + np.asarray(p, "<f4").tobytes() for n, p in f.marker_sets)
    rb = b"".join(_RB.pack(i, p[0], p[1], p[2], q[0], q[1], q[2], q[3], e, 1 if ok else 0)
                  for i, p, q, e, ok in f.bodies)
    lm = b"".join(_LABELED.pack(i, p[0], p[1], p[2], f.marker_size_m, flags, r) for i, p, flags, r in f.labeled)
    out = [_I32.pack(f.frame_number & 0x7FFFFFFF),
           _section(len(f.marker_sets), ms, sized),
           _section(0, b"", sized),  # legacy "other markers": unlabelled ones go in the labelled list (3.0+)
           _section(len(f.bodies), rb, sized),
           _section(0, b"", sized)]  # skeletons
    if version >= (4, 1):
        out.append(_section(0, b"", sized))  # assets
    out += [_section(len(f.labeled), lm, sized),
            _section(0, b"", sized),  # force plates
            _section(0, b"", sized)]  # devices
    return b"".join(out)


def transmit_suffix(f: Frame, version: tuple[int, int], transmit_ticks: int) -> bytes:
    """Timecode, timestamps (the transmit one taken at send), params, end-of-data tag."""
    s = _SUFFIX.pack(0, 0, f.timestamp_s, f.mid_exposure_ticks, f.data_ready_ticks, transmit_ticks)
    if version[0] >= 4:
        s += _PRECISION.pack(0, 0)
    return s + _TAIL.pack(0, 0)


def frame_packet(head: bytes, suffix: bytes) -> bytes:
    return packet(NAT_FRAMEOFDATA, head + suffix)
