"""The still-image and mask messages (docs/protocol.md, "Still images"), each reading and writing itself.

On request only, the server asks a station for a still image (IMAGE_REQUEST, answered by IMAGE_CHUNKs of the
JPEG) or sets its mask (MASK_UPDATE, answered by MASK_ACK); stations/still.py and visionpos/server/images.py
are the two sides.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from typing import ClassVar

from visionpos.protocol.wire import (
    HEADER_BYTES,
    I64_MAX,
    I64_MIN,
    IMAGE_CHUNK_BYTES,
    MASK_TEXT_BYTES,
    MAX_IMAGE_BYTES,
    MAX_MASK_RECTS,
    MAX_PACKET_BYTES,
    TAG_BYTES,
    U16,
    U32,
    MaskFlag,
    MaskStatus,
    MsgType,
    ProtocolError,
    WireMessage,
    check_body_size,
    check_range,
    unpack_text,
)

_IMAGE_REQUEST = struct.Struct("<IIIHBx")  # 16 bytes
_IMAGE_CHUNK = struct.Struct("<IIHHIqHHf")  # 32 bytes, then the chunk's JPEG bytes
_MASK_UPDATE = struct.Struct("<IIIHBB")  # 16 bytes, then (n_ignore + n_rois) x 4 x u16
_MASK_RECT = struct.Struct("<HHHH")
_MASK_ACK = struct.Struct("<IIB3x64s")  # 76 bytes
_MASK_FLAGS = int(MaskFlag.IGNORE | MaskFlag.ROIS)

assert HEADER_BYTES + _IMAGE_CHUNK.size + IMAGE_CHUNK_BYTES + TAG_BYTES == MAX_PACKET_BYTES  # a signed full chunk


def check_chunk(index: int, count: int, total: int, n: int, width: int, height: int, background: float) -> None:
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
    if not (0 < width <= U16 and 0 < height <= U16):
        raise ProtocolError(f"image chunk size {width}x{height}: width and height must be in 1..65535")
    if not 0.0 <= background <= 255.0:  # false for NaN too
        raise ProtocolError(f"image chunk background {background} out of range [0, 255]")


def check_rect(name: str, r: object) -> tuple[int, int, int, int]:
    """A mask rectangle [x0, y0, x1, y1] in pixels: non-empty and inside the u16 range."""
    try:
        x0, y0, x1, y1 = (int(v) for v in r)  # type: ignore[union-attr]
    except (TypeError, ValueError):
        raise ProtocolError(f"{name} rectangle {r!r} is not [x0, y0, x1, y1]") from None
    if not (0 <= x0 < x1 <= U16 and 0 <= y0 < y1 <= U16):
        raise ProtocolError(f"{name} rectangle {[x0, y0, x1, y1]} needs 0 <= x0 < x1 <= 65535, 0 <= y0 < y1")
    return x0, y0, x1, y1


@dataclass(frozen=True, slots=True)
class ImageRequest(WireMessage):
    """Server -> station: send one still image of the camera (docs/protocol.md, "Still images").

    session: the station's session. echo: the newest control counter the server accepted from it (the
    station believes only an echo of a counter it sent recently). request_id: the server's, increasing
    (with echo, the station's replay guard). max_width: downscale the image to at most this many pixels
    wide (0 = full size). quality: JPEG quality 1..100.
    """

    TYPE: ClassVar[MsgType] = MsgType.IMAGE_REQUEST

    station_id: int
    camera_id: int
    session: int
    echo: int
    request_id: int
    max_width: int = 640
    quality: int = 80

    def write_body(self) -> bytes:
        return _IMAGE_REQUEST.pack(
            check_range("session", self.session, 0, U32),
            check_range("echo", self.echo, 0, U32),
            check_range("request_id", self.request_id, 0, U32),
            check_range("max_width", self.max_width, 0, U16),
            check_range("quality", self.quality, 1, 100),
        )

    @classmethod
    def read_body(cls, data: bytes, station_id: int, camera_id: int, body_len: int) -> ImageRequest:
        check_body_size(cls.TYPE, body_len, _IMAGE_REQUEST.size)
        session, echo, rid, max_width, quality = _IMAGE_REQUEST.unpack_from(data, HEADER_BYTES)
        if not 1 <= quality <= 100:
            raise ProtocolError(f"image request quality {quality} out of range [1, 100]")
        return cls(station_id, camera_id, session, echo, rid, max_width, quality)


@dataclass(frozen=True, slots=True)
class ImageChunk(WireMessage):
    """Station -> server: one slice of the JPEG answering ImageRequest request_id.

    index/count: this chunk and how many make the image; total_bytes: the JPEG's length. capture_ns: the
    frame's capture time (station clock converted to the server's when synced, else the station clock).
    width/height: the JPEG's size in pixels. background: the station's background level of that frame
    (grey levels 0..255, see stations/still.py). data: bytes [index * IMAGE_CHUNK_BYTES, ...) of the JPEG.
    """

    TYPE: ClassVar[MsgType] = MsgType.IMAGE_CHUNK

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

    def write_body(self) -> bytes:
        data = bytes(self.data)
        check_chunk(self.index, self.count, self.total_bytes, len(data), self.width, self.height, self.background)
        return _IMAGE_CHUNK.pack(
            check_range("session", self.session, 0, U32),
            check_range("request_id", self.request_id, 0, U32),
            self.index, self.count, self.total_bytes,
            check_range("capture_ns", self.capture_ns, I64_MIN, I64_MAX),
            self.width, self.height, float(self.background),
        ) + data

    @classmethod
    def read_body(cls, data: bytes, station_id: int, camera_id: int, body_len: int) -> ImageChunk:
        if body_len < _IMAGE_CHUNK.size:
            raise ProtocolError(f"image-chunk body is {body_len} bytes, less than its fixed {_IMAGE_CHUNK.size}")
        session, rid, index, count, total, cap, w, h, bg = _IMAGE_CHUNK.unpack_from(data, HEADER_BYTES)
        chunk = data[HEADER_BYTES + _IMAGE_CHUNK.size:HEADER_BYTES + body_len]
        check_chunk(index, count, total, len(chunk), w, h, bg)
        return cls(station_id, camera_id, session, rid, index, count, total, cap, w, h, bg, chunk)


@dataclass(frozen=True, slots=True)
class MaskUpdate(WireMessage):
    """Server -> station: replace the detector's ignore rectangles and/or rois ([x0, y0, x1, y1] px, x1 > x0,
    y1 > y0) and save them to the station's config. flags: MaskFlag bits saying which list is set (an empty
    list with its flag clears it). session/echo/request_id: as ImageRequest."""

    TYPE: ClassVar[MsgType] = MsgType.MASK_UPDATE

    station_id: int
    camera_id: int
    session: int
    echo: int
    request_id: int
    flags: int
    ignore: tuple[tuple[int, int, int, int], ...] = ()
    rois: tuple[tuple[int, int, int, int], ...] = ()

    def write_body(self) -> bytes:
        flags = check_range("flags", self.flags, 0, _MASK_FLAGS)
        rects = []
        for name, lst in (("ignore", self.ignore), ("rois", self.rois)):
            if len(lst) > MAX_MASK_RECTS:
                raise ProtocolError(f"mask update has {len(lst)} {name} rectangles; at most {MAX_MASK_RECTS} fit")
            for r in lst:
                rects.append(_MASK_RECT.pack(*check_rect(name, r)))
        return _MASK_UPDATE.pack(
            check_range("session", self.session, 0, U32),
            check_range("echo", self.echo, 0, U32),
            check_range("request_id", self.request_id, 0, U32),
            flags, len(self.ignore), len(self.rois),
        ) + b"".join(rects)

    @classmethod
    def read_body(cls, data: bytes, station_id: int, camera_id: int, body_len: int) -> MaskUpdate:
        if body_len < _MASK_UPDATE.size:
            raise ProtocolError(f"mask-update body is {body_len} bytes, less than its fixed {_MASK_UPDATE.size}")
        session, echo, rid, flags, n_ignore, n_rois = _MASK_UPDATE.unpack_from(data, HEADER_BYTES)
        if flags & ~_MASK_FLAGS or not flags:
            raise ProtocolError(f"mask update flags {flags:#x}: expected IGNORE (1) and/or ROIS (2)")
        if n_ignore > MAX_MASK_RECTS or n_rois > MAX_MASK_RECTS:
            raise ProtocolError(f"mask update has {n_ignore} ignore and {n_rois} roi rectangles; at most "
                                f"{MAX_MASK_RECTS} each")
        if body_len != _MASK_UPDATE.size + (n_ignore + n_rois) * _MASK_RECT.size:
            raise ProtocolError(f"mask update of {n_ignore} + {n_rois} rectangles does not match body length "
                                f"{body_len}")
        rects = []
        for i in range(n_ignore + n_rois):
            r = _MASK_RECT.unpack_from(data, HEADER_BYTES + _MASK_UPDATE.size + i * _MASK_RECT.size)
            rects.append(check_rect("ignore" if i < n_ignore else "rois", r))
        return cls(station_id, camera_id, session, echo, rid, flags, tuple(rects[:n_ignore]),
                   tuple(rects[n_ignore:]))


@dataclass(frozen=True, slots=True)
class MaskAck(WireMessage):
    """Station -> server: the answer to MaskUpdate request_id; status a MaskStatus, text why (UTF-8, 64 bytes)."""

    TYPE: ClassVar[MsgType] = MsgType.MASK_ACK

    station_id: int
    camera_id: int
    session: int
    request_id: int
    status: int
    text: str = ""

    def write_body(self) -> bytes:
        # cut to the field at a character boundary (a reason is informative, never refused for its length)
        text = self.text.encode("utf-8")[:MASK_TEXT_BYTES].decode("utf-8", errors="ignore").encode("utf-8")
        return _MASK_ACK.pack(
            check_range("session", self.session, 0, U32),
            check_range("request_id", self.request_id, 0, U32),
            check_range("status", self.status, 0, len(MaskStatus) - 1),
            text,
        )

    @classmethod
    def read_body(cls, data: bytes, station_id: int, camera_id: int, body_len: int) -> MaskAck:
        check_body_size(cls.TYPE, body_len, _MASK_ACK.size)
        session, rid, status, text = _MASK_ACK.unpack_from(data, HEADER_BYTES)
        if status >= len(MaskStatus):
            raise ProtocolError(f"mask ack status {status} unknown (expected 0..{len(MaskStatus) - 1})")
        return cls(station_id, camera_id, session, rid, status, unpack_text(text))
