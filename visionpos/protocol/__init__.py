"""The station <-> server wire protocol (UDP, binary, little-endian, versioned).

docs/protocol.md specifies every byte; this package is the reference implementation used by stations, the
fusion server, the simulator and replay:

    wire.py      constants, the enums (MsgType, AckStatus, ...), the common header and its HMAC tag
    control.py   HELLO, HELLO_ACK, HEARTBEAT, SYNC_REQUEST, SYNC_REPLY, BYE; the server's reply helpers
    stills.py    IMAGE_REQUEST, IMAGE_CHUNK, MASK_UPDATE, MASK_ACK
    packets.py   encode / decode of any datagram (FRAME inline), decode_v1

Every packet is one UDP datagram:

    common header (16 bytes) | body (body_len bytes) | optional HMAC tag (16 bytes)

Frames decode to `visionpos.messages.BlobFrame`; every other message is a small frozen dataclass that
writes and reads itself (`Hello(...).write(key)`, `Hello.read(data, key)`). `decode` raises `ProtocolError`
with a message naming what was wrong, so a server can count and drop bad packets.

Version 2 binds every message to its station session and makes every one fresh: frames carry the session
and their own seq; control messages carry a per-session counter; HELLO carries the server's cookie; replies
echo the session and the counter they answer. All of it is inside the HMAC. `decode_v1` reads version-1
packets (recordings made before version 2) for replay only.
"""

from visionpos.protocol.control import (
    Bye,
    Heartbeat,
    Hello,
    HelloAck,
    SyncReply,
    SyncRequest,
    make_hello_ack,
    make_sync_reply,
    seq_delta,
    server_time_from_realtime,
)
from visionpos.protocol.packets import MESSAGE_CLASSES, Message, decode, decode_v1, encode, encode_frame
from visionpos.protocol.stills import ImageChunk, ImageRequest, MaskAck, MaskUpdate
from visionpos.protocol.wire import (
    BLOB_BYTES,
    CAMERA_KINDS,
    COOKIE_BYTES,
    DEFAULT_PORT,
    FRAME_FIXED_BYTES,
    HEADER_BYTES,
    IMAGE_CHUNK_BYTES,
    MAGIC,
    MASK_TEXT_BYTES,
    MAX_BLOBS_PER_PACKET,
    MAX_FPS,
    MAX_IMAGE_BYTES,
    MAX_IMAGE_CHUNKS,
    MAX_MASK_RECTS,
    MAX_PACKET_BYTES,
    NO_COOKIE,
    PROTOCOL_VERSION,
    TAG_BYTES,
    TEMPERATURE_UNKNOWN,
    UNCERTAINTY_UNKNOWN,
    AckStatus,
    CameraKind,
    HeaderFlag,
    HeartbeatStatus,
    MaskFlag,
    MaskStatus,
    MsgType,
    ProtocolError,
    Timebase,
    WireMessage,
    packet_version,
)

__all__ = [
    "BLOB_BYTES", "CAMERA_KINDS", "COOKIE_BYTES", "DEFAULT_PORT", "FRAME_FIXED_BYTES", "HEADER_BYTES",
    "IMAGE_CHUNK_BYTES", "MAGIC", "MASK_TEXT_BYTES", "MAX_BLOBS_PER_PACKET", "MAX_FPS", "MAX_IMAGE_BYTES",
    "MAX_IMAGE_CHUNKS", "MAX_MASK_RECTS", "MAX_PACKET_BYTES", "MESSAGE_CLASSES", "NO_COOKIE", "PROTOCOL_VERSION",
    "TAG_BYTES", "TEMPERATURE_UNKNOWN", "UNCERTAINTY_UNKNOWN",
    "AckStatus", "Bye", "CameraKind", "HeaderFlag", "Heartbeat", "HeartbeatStatus", "Hello", "HelloAck",
    "ImageChunk", "ImageRequest", "MaskAck", "MaskFlag", "MaskStatus", "MaskUpdate", "Message", "MsgType",
    "ProtocolError", "SyncReply", "SyncRequest", "Timebase", "WireMessage",
    "decode", "decode_v1", "encode", "encode_frame", "make_hello_ack", "make_sync_reply", "packet_version",
    "seq_delta", "server_time_from_realtime",
]
