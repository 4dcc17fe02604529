"""Station protocol: byte layout against docs/protocol.md, round trips, rejections."""

from __future__ import annotations

import hashlib
import hmac
import re
import struct
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from tests.support.protocol import assert_writes_and_reads
from visionpos import protocol as P
from visionpos.messages import FLAG_RESYNC, FLAG_TRUNCATED, BlobFrame, FrameFlag
from visionpos.protocol.wire import SIGNED_BIT

KEY = b"0123456789abcdef-shared"


def _frame(n=3, seq=7, cap=123456789012345, flags=0, sid=2, cid=3, session=0x51):
    blobs = np.arange(n * 4, dtype=np.float32).reshape(n, 4) + 0.25
    return BlobFrame(cid, seq, cap, blobs, sid, flags, 0, session)


def test_frame_bytes_match_the_documented_layout():
    """Build the worked example of docs/protocol.md by hand with struct and compare."""
    blobs = np.array([[320.25, 240.5, 12, 200], [100.0, 50.75, 6, 150]], np.float32)
    f = BlobFrame(3, 1000, 1_700_000_000_123_456_789, blobs, 2, 0, 0, 0x12345678)
    expect = b"VPOS" + bytes([2, 1, 0, 0]) + struct.pack("<HHHH", 2, 3, 56, 0)
    expect += struct.pack("<IIqHH4x", 0x12345678, 1000, 1_700_000_000_123_456_789, 0, 2)
    expect += struct.pack("<8f", 320.25, 240.5, 12, 200, 100.0, 50.75, 6, 150)
    assert P.encode_frame(f) == expect
    hexdump = (
        "56504f530201000002000300380000007856341" "2e803000015cd853dfe9c9717"
        "00000200000000000020a043008070430000404100004843" "0000c84200004b420000c04000001643"
    )
    assert expect.hex() == hexdump  # the hex printed in docs/protocol.md
    signed = P.encode_frame(f, b"example-key")
    body = bytearray(expect)
    body[6] = 1
    tag = hmac.new(b"example-key", bytes(body), hashlib.sha256).digest()[:16]
    assert signed == bytes(body) + tag
    assert tag.hex() == "425e84565419f0c6887ab25f6e60b912"


def test_control_bytes_match_the_documented_layout():
    """HELLO and HELLO_ACK by hand with struct: session and counter first, cookie where the tables say."""
    cookie = bytes(range(16))
    hello = P.Hello(2, 3, 0x12345678, 960, 640, 100.0, "fisheye", "pi", "vp", P.Timebase.SERVER, 9, cookie)
    expect = b"VPOS" + bytes([2, 2, 0, 0]) + struct.pack("<HHHH", 2, 3, 84, 0)
    expect += struct.pack("<IIHHfBB2x", 0x12345678, 9, 960, 640, 100.0, 2, 0) + cookie
    expect += b"pi" + bytes(30) + b"vp" + bytes(14)
    assert P.encode(hello) == expect
    ack = P.HelloAck(2, 3, 0x12345678, 5, 6, P.AckStatus.CHALLENGE, 7, 9, cookie)
    expect = b"VPOS" + bytes([2, 3, 0, 0]) + struct.pack("<HHHH", 2, 3, 56, 0)
    expect += struct.pack("<IIB7xqqq", 0x12345678, 9, 3, 5, 6, 7) + cookie
    assert P.encode(ack) == expect
    hb = P.encode(P.Heartbeat(2, 3, 11, 0x12345678))
    assert struct.unpack_from("<II", hb, 16) == (0x12345678, 11)
    assert struct.unpack_from("<IIq", P.encode(P.SyncRequest(2, 3, -5, 12, 0x12345678)), 16) == (0x12345678, 12, -5)
    assert struct.unpack_from("<IIqqq", P.encode(P.SyncReply(2, 3, 1, 2, 3, 12, 0x12345678)), 16) == (
        0x12345678, 12, 1, 2, 3)
    assert struct.unpack_from("<II", P.encode(P.Bye(2, 3, 0x12345678, 13)), 16) == (0x12345678, 13)


def _le(v: int, n: int, signed: bool = False) -> bytes:
    return v.to_bytes(n, "little", signed=signed)


def _header(mtype: int, body: bytes, sid: int = 2, cid: int = 3) -> bytes:
    """docs/protocol.md's common header, field by field: magic, version 2, type, hflags 0, 0, ids, length, 0."""
    return b"VPOS" + bytes([2, mtype, 0, 0]) + _le(sid, 2) + _le(cid, 2) + _le(len(body), 2) + _le(0, 2) + body


S = 0x12345678  # a session in every hand-written body
HAND_WRITTEN = [  # (message, its datagram written from the offset tables of docs/protocol.md)
    (P.Hello(2, 3, S, 960, 640, 100.0, "pinhole", "cam0", "vp 1", P.Timebase.REALTIME, 9, bytes(range(16))),
     _header(2, _le(S, 4) + _le(9, 4) + _le(960, 2) + _le(640, 2) + struct.pack("<f", 100.0) + bytes([1, 1, 0, 0])
             + bytes(range(16)) + b"cam0".ljust(32, b"\0") + b"vp 1".ljust(16, b"\0"))),
    (P.HelloAck(2, 3, S, -5, 6, P.AckStatus.RESYNC, 7, 8, bytes(range(16, 32))),
     _header(3, _le(S, 4) + _le(8, 4) + bytes([4]) + bytes(7) + _le(-5, 8, True) + _le(6, 8, True) + _le(7, 8, True)
             + bytes(range(16, 32)))),
    (P.Heartbeat(2, 3, 11, S, 0b1011, 1000, 3, 2, -4_000, 250, -12, 41.25, 10**15),
     _header(4, _le(S, 4) + _le(11, 4) + _le(0b1011, 2) + _le(4125, 2, True) + _le(1000, 4) + _le(3, 4) + _le(2, 4)
             + _le(-12, 4, True) + bytes(4) + _le(-4_000, 8, True) + _le(250, 8, True) + _le(10**15, 8, True))),
    (P.Heartbeat(2, 3, 12, S),  # no temperature sensor, uncertainty unknown
     _header(4, _le(S, 4) + _le(12, 4) + _le(0, 2) + _le(-32768, 2, True) + bytes(16) + bytes(4)
             + bytes(8) + _le(-1, 8, True) + bytes(8))),
    (P.SyncRequest(2, 3, -5, 12, S), _header(5, _le(S, 4) + _le(12, 4) + _le(-5, 8, True))),
    (P.SyncReply(2, 3, 1, 2, 3, 12, S), _header(6, _le(S, 4) + _le(12, 4) + _le(1, 8) + _le(2, 8) + _le(3, 8))),
    (P.Bye(2, 3, S, 13), _header(7, _le(S, 4) + _le(13, 4))),
]


@pytest.mark.parametrize("msg, data", HAND_WRITTEN, ids=lambda v: type(v).__name__ if not isinstance(v, bytes) else "")
def test_each_message_writes_and_reads_its_documented_bytes(msg, data):
    assert_writes_and_reads(msg, data, KEY)


def test_read_refuses_another_type():
    with pytest.raises(P.ProtocolError, match="a bye packet where a hello was expected"):
        P.Hello.read(P.Bye(2, 3, 4, 5).write())
    with pytest.raises(P.ProtocolError, match="a frame packet where a bye was expected"):
        P.Bye.read(P.encode_frame(_frame()))
    with pytest.raises(P.ProtocolError, match="a type 12 packet where a bye was expected"):
        P.Bye.read(P.Bye(2, 3, 4, 5).write()[:5] + b"\x0c" + P.Bye(2, 3, 4, 5).write()[6:])


blob_arrays = st.integers(0, P.MAX_BLOBS_PER_PACKET).flatmap(
    lambda n: st.lists(
        st.floats(-1e4, 1e4, allow_nan=False, width=32), min_size=4 * n, max_size=4 * n
    ).map(lambda v: np.array(v, np.float32).reshape(-1, 4))
)


@settings(max_examples=60, deadline=None)
@given(
    blobs=blob_arrays,
    seq=st.integers(0, 2**32 - 1),
    cap=st.integers(-(2**63), 2**63 - 1),
    flags=st.integers(0, 0xFFFF),
    sid=st.integers(0, 0xFFFF),
    cid=st.integers(0, 0xFFFF),
    signed=st.booleans(),
)
def test_frame_round_trip(blobs, seq, cap, flags, sid, cid, signed):
    key = KEY if signed else None
    f = BlobFrame(cid, seq, cap, blobs, sid, flags)
    data = P.encode(f, key)
    assert len(data) <= P.MAX_PACKET_BYTES
    g = P.decode(data, key, recv_ns=99)
    assert (g.camera_id, g.seq, g.capture_ns, g.station_id, g.flags, g.recv_ns) == (cid, seq, cap, sid, flags, 99)
    assert g.session == 0
    assert g.blobs.shape == (len(blobs), 4) and g.blobs.dtype == np.float32
    np.testing.assert_array_equal(g.blobs, blobs)


i64 = st.integers(-(2**63), 2**63 - 1)
u32 = st.integers(0, 2**32 - 1)
u16 = st.integers(0, 0xFFFF)
text = st.text(alphabet=st.characters(min_codepoint=33, max_codepoint=126), max_size=16)

u16p = st.integers(1, 0xFFFF)
cookies = st.binary(min_size=16, max_size=16)
messages = st.one_of(
    st.builds(P.Hello, u16, u16, u32, u16p, u16p, st.floats(0.5, 1000, width=32), st.sampled_from(P.CAMERA_KINDS),
              text, text, st.sampled_from([P.Timebase.SERVER, P.Timebase.REALTIME]), u32, cookies),
    st.builds(P.HelloAck, u16, u16, u32, i64, i64, st.sampled_from(list(P.AckStatus)), st.integers(0, 2**63 - 1),
              u32, cookies),
    st.builds(P.Heartbeat, u16, u16, u32, u32, u16, u32, u32, u32, i64, st.integers(-1, 2**63 - 1),
              st.integers(-(2**31), 2**31 - 1),
              st.one_of(st.none(), st.integers(-30000, 30000).map(lambda c: c / 100.0)), i64),
    st.builds(P.SyncRequest, u16, u16, i64, u32, u32),
    st.builds(P.SyncReply, u16, u16, i64, i64, i64, u32, u32),
    st.builds(P.Bye, u16, u16, u32, u32),
)


@settings(max_examples=150, deadline=None)
@given(msg=messages, signed=st.booleans())
def test_message_round_trip(msg, signed):
    key = KEY if signed else None
    assert P.decode(P.encode(msg, key), key) == msg


def test_body_sizes_as_documented():
    sizes = {
        P.Hello(1, 2, 3, 4, 5, 6.0): 84,
        P.HelloAck(1, 2, 3, 4, 5): 56,
        P.Heartbeat(1, 2, 3): 56,
        P.SyncRequest(1, 2, 3): 16,
        P.SyncReply(1, 2, 3, 4, 5): 32,
        P.Bye(1, 2, 3): 8,
    }
    for msg, body in sizes.items():
        data = P.encode(msg)
        assert len(data) == 16 + body
        assert struct.unpack_from("<H", data, 12)[0] == body


def test_full_signed_frame_fits_one_datagram():
    f = _frame(n=P.MAX_BLOBS_PER_PACKET)
    assert len(P.encode(f, KEY)) == 16 + 24 + 88 * 16 + 16 == 1464 <= 1472
    with pytest.raises(P.ProtocolError, match="89 blobs; at most 88 fit"):
        P.encode(_frame(n=P.MAX_BLOBS_PER_PACKET + 1))


@pytest.mark.parametrize(
    "mutate, pattern",
    [
        (lambda d: d[:10], "truncated packet: 10 bytes"),
        (lambda d: d[:-4], "truncated packet"),
        (lambda d: d + b"\0", "trailing bytes"),
        (lambda d: d + b"\0" * 1500, "oversize packet"),
        (lambda d: b"XPOS" + d[4:], "bad magic"),
        (lambda d: d[:4] + b"\x03" + d[5:], "protocol version 3 unsupported.*upgrade"),
        (lambda d: d[:4] + b"\x01" + d[5:], "protocol version 1 unsupported.*upgrade the sender"),
        (lambda d: d[:4] + b"\x00" + d[5:], "protocol version 0 unsupported"),
        (lambda d: d[:5] + b"\x0c" + d[6:], "unknown message type 12"),
        (lambda d: d[:34] + struct.pack("<H", 5) + d[36:], "blob count 5 does not match"),
    ],
)
def test_malformed_packets_are_rejected_with_a_reason(mutate, pattern):
    data = P.encode(_frame())
    with pytest.raises(P.ProtocolError, match=pattern):
        P.decode(mutate(data))


def test_authentication():
    f = _frame()
    signed = P.encode(f, KEY)
    assert P.decode(signed, KEY).seq == f.seq
    assert P.decode(signed).seq == f.seq  # no key here: tag skipped
    with pytest.raises(P.ProtocolError, match="bad signature.*shared key"):
        P.decode(signed, b"another key, wrong one")
    with pytest.raises(P.ProtocolError, match="unsigned packet rejected"):
        P.decode(P.encode(f), KEY)
    tampered = bytearray(signed)
    tampered[24] ^= 1  # capture time
    with pytest.raises(P.ProtocolError, match="bad signature"):
        P.decode(bytes(tampered), KEY)
    tampered = bytearray(signed)
    tampered[16] ^= 1  # session: bound into the tag
    with pytest.raises(P.ProtocolError, match="bad signature"):
        P.decode(bytes(tampered), KEY)
    # clearing the SIGNED flag and dropping the tag must not pass either
    stripped = bytearray(signed[:-16])
    stripped[6] = 0
    with pytest.raises(P.ProtocolError, match="unsigned"):
        P.decode(bytes(stripped), KEY)


def test_decoded_blobs_do_not_alias_a_reused_buffer():
    buf = bytearray(P.encode(_frame()))
    g = P.decode(buf)
    before = g.blobs.copy()
    buf[40:56] = b"\xff" * 16
    np.testing.assert_array_equal(g.blobs, before)


def test_encode_rejects_out_of_range_fields():
    with pytest.raises(P.ProtocolError, match="seq=4294967296 out of range"):
        P.encode(_frame(seq=2**32))
    with pytest.raises(P.ProtocolError, match="camera_id"):
        P.encode(_frame(cid=70000))
    with pytest.raises(P.ProtocolError, match="camera_name"):
        P.encode(P.Hello(1, 2, 3, 4, 5, 6.0, camera_name="x" * 40))
    with pytest.raises(P.ProtocolError, match="shape"):
        P.encode(BlobFrame(1, 1, 1, np.zeros((3, 3), np.float32)))


def test_server_helpers():
    req = P.SyncRequest(4, 5, 1000, 17, 0xABC)
    rep = P.make_sync_reply(req, 2000, 2100)
    assert rep == P.SyncReply(4, 5, 1000, 2000, 2100, 17, 0xABC)  # echoes the request's counter and session
    hello = P.Hello(4, 5, 0xDEADBEEF, 960, 640, 100.0, counter=33)
    ack = P.make_hello_ack(hello, start_ns=10**12, server_ns=10**12 + 5)
    assert (ack.session, ack.start_ns, ack.status, ack.echo) == (0xDEADBEEF, 10**12, P.AckStatus.OK, 33)
    assert P.seq_delta(5, 4) == 1
    assert P.seq_delta(0, 2**32 - 1) == 1  # wrap-around
    assert P.seq_delta(4, 5) == -1
    assert P.seq_delta(7, 7) == 0
    assert (
        P.server_time_from_realtime(1_700_000_000_000_000_000, 1_700_000_000_500_000_000, 3_000_000_000)
        == 2_500_000_000
    )


def test_truncated_flag_survives():
    f = _frame(flags=FLAG_TRUNCATED)
    assert P.decode(P.encode(f)).flags & FLAG_TRUNCATED


# ---------------------------------------------------------------- enums against docs/protocol.md

_DOC = (Path(__file__).resolve().parents[1] / "docs" / "protocol.md").read_text(encoding="utf-8")


def _doc_cell(section: str, field: str) -> str:
    """The last cell of the table row for `field` in the docs section whose heading starts with `section`."""
    (body,) = [part for part in _DOC.split("\n### ")[1:] if part.startswith(section)]
    for line in body.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) >= 4 and cells[2] == field:
            return cells[-1]
    raise AssertionError(f"no row {field!r} under {section!r} in docs/protocol.md")


def _doc_numbered(cell: str) -> dict[str, int]:
    """"0 `OK`; 1 `UNKNOWN_SESSION`: ..." -> {"OK": 0, "UNKNOWN_SESSION": 1}."""
    return {name: int(n) for n, name in re.findall(r"(\d+) `(\w+)`", cell)}


def _doc_bits(cell: str) -> dict[str, int]:
    """"bit 0 `SIGNED`: ..." or "bit 0 camera OK; ..." -> {"SIGNED": 1, "CAMERA_OK": 1, ...}."""
    found = re.findall(r"bit (\d+) (`\w+`|[A-Za-z ]+?)(?=[:;(]| \(|$)", cell)
    return {name.strip("`").strip().upper().replace(" ", "_"): 1 << int(bit) for bit, name in found}


def _members(enum) -> dict[str, int]:
    return {m.name: m.value for m in enum}


def test_message_types_are_the_documented_bytes():
    rows = re.findall(r"^\|\s*(\d+)\s*\|\s*([A-Z_]+)\s*\|\s*(?:station|server) →", _DOC, re.MULTILINE)
    assert len(rows) == 11
    assert _members(P.MsgType) == {name: int(n) for n, name in rows}
    # every other type reads and writes itself: one class each, keyed by its byte
    assert sorted(P.MESSAGE_CLASSES) == [t for t in P.MsgType if t != P.MsgType.FRAME]
    assert all(cls.TYPE == t for t, cls in P.MESSAGE_CLASSES.items())
    assert not hasattr(P, "MSG_HELLO_ACK") and not hasattr(P, "ACK_OK")  # the enums only


def test_statuses_and_kinds_are_the_documented_values():
    assert _members(P.AckStatus) == _doc_numbered(_doc_cell("HELLO_ACK", "status"))
    assert _members(P.Timebase) == _doc_numbered(_doc_cell("HELLO ", "timebase"))
    kinds = dict(re.findall(r"(\d+) (\w+)", _doc_cell("HELLO ", "camera_kind")))
    assert P.CAMERA_KINDS == tuple(kinds[str(i)] for i in range(len(kinds)))
    assert _members(P.CameraKind) == {name.upper(): int(n) for n, name in kinds.items()}


def test_flag_bits_are_the_documented_bits():
    assert _members(P.HeaderFlag) == _doc_bits(_doc_cell("Common header", "hflags"))
    assert _members(FrameFlag) == _doc_bits(_doc_cell("FRAME", "flags"))
    assert _members(P.HeartbeatStatus) == _doc_bits(_doc_cell("HEARTBEAT", "status"))
    # the per-packet tests use plain ints: `int & IntFlag` would build an IntFlag per packet
    assert type(FLAG_RESYNC) is int and FLAG_RESYNC == FrameFlag.RESYNC
    assert type(SIGNED_BIT) is int and SIGNED_BIT == P.HeaderFlag.SIGNED


def test_worked_example_header_bytes_are_the_enums():
    dumps = re.findall(r"```\n((?:[0-9a-f]{4}  [0-9a-f ]+\n)+)```", _DOC)
    unsigned, tag = (bytes.fromhex("".join(line[6:] for line in d.splitlines())) for d in dumps)
    assert len(unsigned) == 72 and len(tag) == 16
    assert len(unsigned) == 72 and unsigned[4] == P.PROTOCOL_VERSION
    assert unsigned[5] == P.MsgType.FRAME and unsigned[6] == 0
    signed = P.decode(unsigned[:6] + bytes([P.HeaderFlag.SIGNED]) + unsigned[7:] + tag, b"example-key")
    assert (signed.station_id, signed.camera_id, signed.seq, signed.session) == (2, 3, 1000, 0x12345678)


# ---------------------------------------------------------------- validation (issue 14: each passed on v1's decoder)


def _raw_frame(blobs: np.ndarray, count: int | None = None) -> bytes:
    """A v2 frame packed by hand, so counts the encoder refuses can be sent."""
    n = len(blobs) if count is None else count
    body = struct.pack("<IIqHH4x", 7, 1, 10**9, 0, n) + np.asarray(blobs, "<f4").tobytes()
    return b"VPOS" + bytes([2, 1, 0, 0]) + struct.pack("<HHHH", 1, 1, len(body), 0) + body


@pytest.mark.parametrize("n", [89])  # 90 no longer fits 1472 bytes
def test_frames_over_88_blobs_are_rejected(n):
    assert P.decode(_raw_frame(np.ones((88, 4)))).blobs.shape == (88, 4)
    with pytest.raises(P.ProtocolError, match=f"blob count {n} > 88"):
        P.decode(_raw_frame(np.ones((n, 4))))


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf, 3e38])
@pytest.mark.parametrize("col", [0, 1, 2, 3])
def test_non_finite_blob_values_are_rejected(bad, col):
    blobs = np.full((3, 4), 100.0)
    blobs[1, col] = bad
    with pytest.raises(P.ProtocolError, match="not finite"):
        P.decode(_raw_frame(blobs))
    blobs[1, col] = -1.6e38  # large but below 2**127: a number, passed on (fusion bounds pixels)
    assert P.decode(_raw_frame(blobs)).blobs[1, col] == np.float32(-1.6e38)


@pytest.mark.parametrize("w, h, fps, what", [
    (0, 0, 100.0, "resolution 0x0"), (960, 0, 100.0, "resolution 960x0"), (0, 640, 100.0, "resolution 0x640"),
    (960, 640, float("inf"), "fps inf"), (960, 640, float("nan"), "fps nan"), (960, 640, 0.0, "fps 0.0"),
    (960, 640, -5.0, "fps -5.0"), (960, 640, 1000.5, "fps 1000.5"),
])
def test_hello_with_impossible_camera_is_rejected(w, h, fps, what):
    data = P.encode(P.Hello(1, 1, 7, w, h, fps))
    with pytest.raises(P.ProtocolError, match=what):
        P.decode(data)
    assert P.decode(P.encode(P.Hello(1, 1, 7, 960, 640, 1000.0))).fps == 1000.0


def test_v1_decoder_reads_hand_packed_v1_packets():
    """Version-1 bytes packed here with struct from the v1 spec (not by the code under test)."""
    hdr = lambda t, n: b"VPOS" + bytes([1, t, 0, 0]) + struct.pack("<HHHH", 2, 3, n, 0)  # noqa: E731
    blobs = struct.pack("<8f", 320.25, 240.5, 12, 200, 100.0, 50.75, 6, 150)
    frame = hdr(1, 48) + struct.pack("<IHHq", 1000, 4, 2, 1_700_000_000_123_456_789) + blobs
    f = P.decode_v1(frame)
    assert (f.camera_id, f.station_id, f.seq, f.flags, f.capture_ns, f.session) == (
        3, 2, 1000, 4, 1_700_000_000_123_456_789, 0)
    np.testing.assert_array_equal(f.blobs, [[320.25, 240.5, 12, 200], [100.0, 50.75, 6, 150]])
    hello = hdr(2, 64) + struct.pack("<IHHfBBBB32s16s", 0x5102, 960, 640, 100.0, 2, 0, 0, 0, b"pi2", b"sim")
    assert P.decode_v1(hello) == P.Hello(2, 3, 0x5102, 960, 640, 100.0, "fisheye", "pi2", "sim", 0)
    hb = hdr(4, 56) + struct.pack("<IHhIIIiqqqI4x", 5, 3, 4150, 10, 1, 0, -20, 123, 40, 99, 0x5102)
    assert P.decode_v1(hb) == P.Heartbeat(2, 3, 5, 0x5102, 3, 10, 1, 0, 123, 40, -20, 41.5, 99)
    assert P.decode_v1(hdr(5, 16) + struct.pack("<qI4x", -7, 4)) == P.SyncRequest(2, 3, -7, 4)
    assert P.decode_v1(hdr(7, 8) + struct.pack("<I4x", 0x5102)) == P.Bye(2, 3, 0x5102)
    with pytest.raises(P.ProtocolError, match="version 1 unsupported"):
        P.decode(frame)  # live peers must speak v2
    with pytest.raises(P.ProtocolError, match="not a v1 station"):
        P.decode_v1(hdr(3, 32) + bytes(32))  # a v1 HELLO_ACK is not recorded station traffic
