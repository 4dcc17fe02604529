"""Datagrams <-> messages: FRAME (a `visionpos.messages.BlobFrame`, the per-packet path, kept inline), every
other type through its class's write/read, and version-1 packets for replays of old recordings."""

from __future__ import annotations

import hmac
import struct

import numpy as np

from visionpos.messages import BlobFrame
from visionpos.protocol.control import (
    Bye,
    Heartbeat,
    Hello,
    HelloAck,
    SyncReply,
    SyncRequest,
    check_hello,
    temperature_c,
)
from visionpos.protocol.stills import ImageChunk, ImageRequest, MaskAck, MaskUpdate
from visionpos.protocol.wire import (
    BLOB_BYTES,
    CAMERA_KINDS,
    FRAME_FIXED_BYTES,
    HEADER_BYTES,
    I64_MAX,
    I64_MIN,
    MAGIC,
    MAX_BLOBS_PER_PACKET,
    MAX_PACKET_BYTES,
    PROTOCOL_VERSION,
    SIGNED_BIT,
    TAG_BYTES,
    U16,
    U32,
    MsgType,
    ProtocolError,
    WireMessage,
    check_range,
    read_header,
    tag,
    unpack_text,
)

Message = (BlobFrame | Hello | HelloAck | Heartbeat | SyncRequest | SyncReply | Bye | ImageRequest | ImageChunk
           | MaskUpdate | MaskAck)

# every message type but FRAME, by its header byte
MESSAGE_CLASSES: dict[int, type[WireMessage]] = {
    cls.TYPE: cls for cls in (Hello, HelloAck, Heartbeat, SyncRequest, SyncReply, Bye, ImageRequest, ImageChunk,
                              MaskUpdate, MaskAck)
}
assert set(MESSAGE_CLASSES) | {MsgType.FRAME} == set(MsgType)

_FRAME_HEAD = struct.Struct("<4sBBBBHHHHIIqHH4x")  # header + fixed frame part, 40 bytes
_BLOB_DTYPE = np.dtype("<f4")
_BLOB0 = HEADER_BYTES + FRAME_FIXED_BYTES
_FRAME = int(MsgType.FRAME)  # the per-packet test compares plain ints

assert _FRAME_HEAD.size == _BLOB0
assert HEADER_BYTES + FRAME_FIXED_BYTES + MAX_BLOBS_PER_PACKET * BLOB_BYTES + TAG_BYTES <= MAX_PACKET_BYTES


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
    sid = check_range("station_id", frame.station_id, 0, U16)
    cid = check_range("camera_id", frame.camera_id, 0, U16)
    session = check_range("session", frame.session, 0, U32)
    seq = check_range("seq", frame.seq, 0, U32)
    flags = check_range("flags", frame.flags, 0, U16)
    cap = check_range("capture_ns", frame.capture_ns, I64_MIN, I64_MAX)
    hflags = SIGNED_BIT if key is not None else 0
    body_len = FRAME_FIXED_BYTES + n * BLOB_BYTES
    packet = _FRAME_HEAD.pack(
        MAGIC, PROTOCOL_VERSION, _FRAME, hflags, 0, sid, cid, body_len, 0, session, seq, cap, flags, n
    ) + np.ascontiguousarray(blobs, dtype=_BLOB_DTYPE).tobytes()
    if key is not None:
        packet += tag(key, packet)
    return packet


def encode(msg: Message, key: bytes | None = None) -> bytes:
    """Any protocol message -> one datagram (signed with HMAC-SHA256 when key is given)."""
    if isinstance(msg, BlobFrame):
        return encode_frame(msg, key)
    if isinstance(msg, WireMessage):
        return msg.write(key)
    raise ProtocolError(f"cannot encode {type(msg).__name__}: not a protocol message")


def _check_blobs(data: bytes, start: int, end: int) -> None:
    """Reject NaN/inf blob values cheaply: a float32 whose high byte is 0x7f or 0xff has an exponent of at
    least 254, i.e. it is NaN, +-inf or of magnitude >= 2**127 (no pixel value is that big)."""
    hi = data[start + 3:end:4]
    if 0x7F in hi or 0xFF in hi:
        raise ProtocolError("frame blob value not finite (NaN, inf or beyond 2^127)")


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
    # the frame path is inlined (per packet); anything unusual is diagnosed by read_header
    if n >= _BLOB0 and n <= MAX_PACKET_BYTES and data[5] == _FRAME and (key is None or data[6] & SIGNED_BIT):
        (magic, version, _t, hflags, _r0, sid, cid, body_len, _r1, session, seq, capture_ns, flags,
         count) = _FRAME_HEAD.unpack_from(data)
        end = HEADER_BYTES + body_len
        if (magic != MAGIC or version != PROTOCOL_VERSION or n != (end + TAG_BYTES if hflags & SIGNED_BIT else end)
                or (key is not None and not hmac.compare_digest(tag(key, memoryview(data)[:end]), data[end:]))):
            read_header(data, key, PROTOCOL_VERSION)  # raises, naming the problem
            raise ProtocolError("malformed frame header")  # not reached: the checks above are the same
    else:
        mtype, sid, cid, body_len, end = read_header(data, key, PROTOCOL_VERSION)
        if mtype == _FRAME:  # shorter than the fixed part
            raise ProtocolError(f"truncated frame: body {body_len} bytes < {FRAME_FIXED_BYTES}")
        cls = MESSAGE_CLASSES.get(mtype)
        if cls is None:
            raise ProtocolError(f"unknown message type {mtype} (station and server versions differ?)")
        return cls.read_body(data, sid, cid, body_len)
    if body_len != FRAME_FIXED_BYTES + count * BLOB_BYTES:
        raise ProtocolError(
            f"frame blob count {count} does not match body length {body_len} "
            f"(expected {FRAME_FIXED_BYTES + count * BLOB_BYTES})"
        )
    if count > MAX_BLOBS_PER_PACKET:
        raise ProtocolError(f"frame blob count {count} > {MAX_BLOBS_PER_PACKET}, the most a frame may carry")
    hi = data[_BLOB0 + 3:end:4]  # _check_blobs, inline (per packet)
    if 0x7F in hi or 0xFF in hi:
        raise ProtocolError("frame blob value not finite (NaN, inf or beyond 2^127)")
    blobs = np.frombuffer(data, _BLOB_DTYPE, count * 4, _BLOB0).reshape(count, 4)
    return BlobFrame(cid, seq, capture_ns, blobs, sid, flags, recv_ns, session)


# ---------------------------------------------------------------- version 1 (replay of old recordings only)

_V1_FRAME_HEAD = struct.Struct("<IHHq")  # seq, flags, count, capture_ns
_V1_BODIES = {
    MsgType.HELLO: struct.Struct("<IHHfBBBB32s16s"),
    MsgType.HEARTBEAT: struct.Struct("<IHhIIIiqqqI4x"),
    MsgType.SYNC_REQUEST: struct.Struct("<qI4x"),
    MsgType.BYE: struct.Struct("<I4x"),
}


def decode_v1(data: bytes) -> Message:
    """A protocol-1 station -> server packet (as recorded before version 2) -> the version-2 dataclass.

    For replays of old recordings only: the tag is not checked (a replay trusts its recording), v1
    has no counters, cookies or frame sessions (they decode as 0 / NO_COOKIE), and server -> station
    types are refused. The same validation as version 2 applies otherwise.
    """
    if type(data) is not bytes:
        data = bytes(data)
    mtype, sid, cid, body_len, end = read_header(data, None, 1)
    if mtype == MsgType.FRAME:
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
        raise ProtocolError(f"{MsgType(mtype).label} body is {body_len} bytes, expected {st.size} (v1)")
    v = st.unpack_from(data, HEADER_BYTES)
    if mtype == MsgType.HELLO:
        session, w, h, fps, kind, timebase, _a, _b, name, sw = v
        check_hello(w, h, fps, kind)
        return Hello(sid, cid, session, w, h, fps, CAMERA_KINDS[kind], unpack_text(name), unpack_text(sw), timebase)
    if mtype == MsgType.HEARTBEAT:
        seq, status, temp, cap, drop, err, drift, off, unc, st_ns, session = v
        return Heartbeat(sid, cid, seq, session, status, cap, drop, err, off, unc, drift, temperature_c(temp), st_ns)
    if mtype == MsgType.SYNC_REQUEST:
        t1, seq = v
        return SyncRequest(sid, cid, t1, seq)
    return Bye(sid, cid, v[0])
