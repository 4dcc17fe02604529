"""The still-image and mask messages of the station protocol: round trips, sizes, every malformed field refused."""

from __future__ import annotations

import struct

import pytest

from tests.support.protocol import assert_writes_and_reads
from visionpos import protocol as P
from visionpos.protocol.wire import tag

KEY = b"k" * 32
N = P.IMAGE_CHUNK_BYTES


def _chunk(index=0, count=2, total=N + 100, data=None, **kw):
    if data is None:
        data = bytes([index % 256]) * (N if index < count - 1 else total - index * N)
    f = dict(station_id=1, camera_id=2, session=3, request_id=4, index=index, count=count, total_bytes=total,
             capture_ns=-5, width=640, height=480, background=17.5, data=data)
    f.update(kw)
    return P.ImageChunk(**f)


MESSAGES = [
    P.ImageRequest(1, 2, 0xFFFFFFFF, 7, 8, 640, 80),
    P.ImageRequest(1, 2, 3, 0, 0, 0, 1),
    _chunk(0),
    _chunk(1),
    _chunk(0, 1, 1),
    _chunk(P.MAX_IMAGE_CHUNKS - 1, P.MAX_IMAGE_CHUNKS, P.MAX_IMAGE_BYTES),
    P.MaskUpdate(1, 2, 3, 4, 5, int(P.MaskFlag.IGNORE), ((0, 0, 10, 10), (5, 6, 7, 8))),
    P.MaskUpdate(1, 2, 3, 4, 5, int(P.MaskFlag.IGNORE)),  # clears the ignore list
    P.MaskUpdate(1, 2, 3, 4, 5, int(P.MaskFlag.IGNORE | P.MaskFlag.ROIS), ((0, 0, 1, 1),) * P.MAX_MASK_RECTS,
                 ((0, 0, 65535, 65535),) * P.MAX_MASK_RECTS),
    P.MaskAck(1, 2, 3, 4, int(P.MaskStatus.SAVED), "saved to station.yaml"),
    P.MaskAck(1, 2, 3, 4, int(P.MaskStatus.REFUSED), "x" * P.MASK_TEXT_BYTES),
]


@pytest.mark.parametrize("msg", MESSAGES, ids=lambda m: type(m).__name__)
@pytest.mark.parametrize("key", [None, KEY])
def test_round_trip_fits_one_datagram(msg, key):
    data = P.encode(msg, key)
    assert len(data) <= P.MAX_PACKET_BYTES
    assert P.decode(data, key) == msg


def test_a_full_chunk_signed_is_exactly_one_datagram():
    assert len(P.encode(_chunk(0), KEY)) == P.MAX_PACKET_BYTES


def test_wire_layout_of_an_image_request():
    data = P.encode(P.ImageRequest(1, 2, 0x11223344, 5, 6, 640, 80))
    assert data[5] == 8 and struct.unpack_from("<H", data, 12)[0] == 16
    assert struct.unpack_from("<IIIHB", data, 16) == (0x11223344, 5, 6, 640, 80)


def _le(v: int, n: int, signed: bool = False) -> bytes:
    return v.to_bytes(n, "little", signed=signed)


def _header(mtype: int, body: bytes) -> bytes:
    """docs/protocol.md's common header, field by field: station 1, camera 2."""
    return b"VPOS" + bytes([2, mtype, 0, 0]) + _le(1, 2) + _le(2, 2) + _le(len(body), 2) + _le(0, 2) + body


JPEG = bytes(range(256)) * 6  # 1536 bytes: two chunks, the second 128 bytes
HAND_WRITTEN = [  # (message, its datagram written from the offset tables of docs/protocol.md)
    (P.ImageRequest(1, 2, 0x11223344, 5, 6, 320, 90),
     _header(8, _le(0x11223344, 4) + _le(5, 4) + _le(6, 4) + _le(320, 2) + bytes([90, 0]))),
    (P.ImageChunk(1, 2, 3, 4, 1, 2, 1536, -7, 640, 480, 12.5, JPEG[1408:]),
     _header(9, _le(3, 4) + _le(4, 4) + _le(1, 2) + _le(2, 2) + _le(1536, 4) + _le(-7, 8, True) + _le(640, 2)
             + _le(480, 2) + struct.pack("<f", 12.5) + JPEG[1408:])),
    (P.MaskUpdate(1, 2, 3, 4, 5, 3, ((1, 2, 30, 40),), ((0, 0, 640, 480), (7, 8, 9, 10))),
     _header(10, _le(3, 4) + _le(4, 4) + _le(5, 4) + _le(3, 2) + bytes([1, 2])
             + b"".join(_le(v, 2) for v in (1, 2, 30, 40, 0, 0, 640, 480, 7, 8, 9, 10)))),
    (P.MaskAck(1, 2, 3, 4, 1, "applied, not saved"),
     _header(11, _le(3, 4) + _le(4, 4) + bytes([1, 0, 0, 0]) + b"applied, not saved".ljust(64, b"\0"))),
]


@pytest.mark.parametrize("msg, data", HAND_WRITTEN, ids=lambda v: type(v).__name__ if not isinstance(v, bytes) else "")
def test_each_message_writes_and_reads_its_documented_bytes(msg, data):
    assert_writes_and_reads(msg, data, KEY)


def _body_edit(msg, offset, fmt, value, key=None):
    """msg encoded, one body field overwritten (unsigned, or re-signed with key)."""
    data = bytearray(P.encode(msg))
    struct.pack_into(fmt, data, P.HEADER_BYTES + offset, value)
    data = bytes(data)
    if key is not None:
        data = bytes([*data[:6], P.HeaderFlag.SIGNED, *data[7:]])
        data += tag(key, data)
    return data


@pytest.mark.parametrize("offset,fmt,value,why", [
    (8, "<H", 5, "index"),  # index beyond count
    (10, "<H", 3, "count"),  # count not ceil(total / chunk)
    (12, "<I", 0, "total_bytes"),
    (12, "<I", P.MAX_IMAGE_BYTES + 1, "total_bytes"),  # oversize image refused
    (24, "<H", 0, "size"),  # width 0
    (28, "<f", float("nan"), "background"),
    (28, "<f", 256.0, "background"),
])
def test_malformed_chunks_are_refused(offset, fmt, value, why):
    with pytest.raises(P.ProtocolError, match=why):
        P.decode(_body_edit(_chunk(0), offset, fmt, value))


def test_chunk_with_the_wrong_amount_of_data_is_refused():
    for msg in (_chunk(0, data=b"x" * (N - 1)), _chunk(1, data=b"x" * 99)):
        with pytest.raises(P.ProtocolError):
            P.encode(msg)
    good = P.encode(_chunk(1))
    short = good[:-1]
    short = short[:12] + struct.pack("<H", len(short) - P.HEADER_BYTES) + short[14:]
    with pytest.raises(P.ProtocolError, match="carries"):
        P.decode(short)


def test_malformed_mask_updates_and_acks_are_refused():
    upd = P.MaskUpdate(1, 2, 3, 4, 5, int(P.MaskFlag.IGNORE), ((0, 0, 10, 10),))
    with pytest.raises(P.ProtocolError, match="flags"):
        P.decode(_body_edit(upd, 12, "<H", 0))
    with pytest.raises(P.ProtocolError, match="flags"):
        P.decode(_body_edit(upd, 12, "<H", 4))
    with pytest.raises(P.ProtocolError, match="rectangles"):
        P.decode(_body_edit(upd, 14, "<B", 2))  # says 2, carries 1
    with pytest.raises(P.ProtocolError, match="at most"):
        P.decode(_body_edit(upd, 14, "<B", P.MAX_MASK_RECTS + 1))
    with pytest.raises(P.ProtocolError, match="x0 < x1"):
        P.decode(_body_edit(upd, 16, "<H", 10))  # x0 == x1: empty
    with pytest.raises(P.ProtocolError):
        P.encode(P.MaskUpdate(1, 2, 3, 4, 5, 1, ((5, 5, 1, 1),)))
    with pytest.raises(P.ProtocolError):
        P.encode(P.MaskUpdate(1, 2, 3, 4, 5, 1, ((0, 0, 1, 1),) * (P.MAX_MASK_RECTS + 1)))
    ack = P.MaskAck(1, 2, 3, 4, 0, "ok")
    with pytest.raises(P.ProtocolError, match="status"):
        P.decode(_body_edit(ack, 8, "<B", 3))
    req = P.ImageRequest(1, 2, 3, 4, 5, 640, 80)
    with pytest.raises(P.ProtocolError, match="quality"):
        P.decode(_body_edit(req, 14, "<B", 0))
    with pytest.raises(P.ProtocolError, match="quality"):
        P.encode(P.ImageRequest(1, 2, 3, 4, 5, 640, 101))


@pytest.mark.parametrize("msg", MESSAGES, ids=lambda m: type(m).__name__)
def test_unsigned_or_forged_messages_are_refused_with_a_key(msg):
    with pytest.raises(P.ProtocolError, match="unsigned"):
        P.decode(P.encode(msg), KEY)
    with pytest.raises(P.ProtocolError, match="signature"):
        P.decode(P.encode(msg, b"x" * 32), KEY)
    data = bytearray(P.encode(msg, KEY))
    data[P.HEADER_BYTES] ^= 1  # one body bit flipped after signing
    with pytest.raises(P.ProtocolError, match="signature"):
        P.decode(bytes(data), KEY)


def test_truncated_fixed_parts_are_refused():
    for msg in (_chunk(0), P.MaskUpdate(1, 2, 3, 4, 5, 1, ()), P.ImageRequest(1, 2, 3, 4, 5), P.MaskAck(1, 2, 3, 4, 0)):
        data = P.encode(msg)
        cut = data[:P.HEADER_BYTES + 10]
        cut = cut[:12] + struct.pack("<H", 10) + cut[14:]
        with pytest.raises(P.ProtocolError):
            P.decode(cut)


def test_mask_statuses_and_flags_are_the_documented_values():
    import re
    from pathlib import Path

    doc = (Path(__file__).parents[1] / "docs" / "protocol.md").read_text()
    status = re.search(r"^\| 24 \| u8 \| status \| (.*`SAVED`.*)\|$", doc, re.MULTILINE).group(1)
    assert {n: int(v) for v, n in re.findall(r"(\d+) `(\w+)`", status)} == {m.name: m.value for m in P.MaskStatus}
    flags = re.search(r"^\| 28 \| u16 \| flags \| (.*)\|$", doc, re.MULTILINE).group(1)
    assert {n: 1 << int(b) for b, n in re.findall(r"bit (\d+) `(\w+)`", flags)} == {m.name: m.value
                                                                                   for m in P.MaskFlag}
    assert f"chunks of {P.IMAGE_CHUNK_BYTES}" in doc.replace("\n", " ")
