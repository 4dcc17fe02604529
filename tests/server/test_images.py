"""StationImages (visionpos/server/images.py) through Ingest.handle: requests go to the registered station only,
chunks are reassembled out of order, anything not from that station/session/address/request is dropped and
counted with no state change, incomplete images time out, memory stays bounded."""

from __future__ import annotations

import asyncio
import dataclasses

import pytest

from visionpos import protocol as P
from visionpos.server import images as I
from visionpos.server.ingest import Ingest

from .test_ingest import ADDR, MS, T0, Clock, _arena, _hello, _send

N = P.IMAGE_CHUNK_BYTES
JPEG = bytes(range(256)) * 12  # 3072 bytes: three chunks


class Sock:
    def __init__(self):
        self.sent: list[tuple[bytes, tuple]] = []

    def sendto(self, data, addr):
        self.sent.append((data, addr))


def _rig():
    clock = Clock(T0)
    ing = Ingest(_arena({}), clock=clock)
    ing.sock = Sock()
    (ack,) = _send(ing, _hello(1), T0)
    assert ack.status == P.AckStatus.OK
    return ing, clock


def _chunks(req: P.ImageRequest, jpeg=JPEG, **kw):
    count = -(-len(jpeg) // N)
    return [P.ImageChunk(req.station_id, req.camera_id, req.session, req.request_id, i, count, len(jpeg),
                         kw.get("capture_ns", 123), 64, 48, kw.get("background", 12.0), jpeg[i * N:(i + 1) * N])
            for i in range(count)]


def _feed(ing, msg, addr=ADDR, recv_ns=T0, key=None):
    assert ing.handle(P.encode(msg, key), addr, recv_ns) == []  # never an answer


def test_request_goes_to_the_station_and_the_image_is_reassembled_out_of_order():
    async def run():
        ing, clock = _rig()
        fut = ing.images.request_image(1, 320, 70)
        ((data, addr),) = ing.sock.sent
        req = P.decode(data)
        assert addr == ADDR and isinstance(req, P.ImageRequest)
        assert (req.session, req.max_width, req.quality, req.echo) == (7, 320, 70, ing.cameras[1].last_counter)
        c0, c1, c2 = _chunks(req)
        for c in (c2, c0, c0, c1):  # out of order, one duplicate
            _feed(ing, c)
        img = fut.result()
        assert img.jpeg == JPEG and (img.capture_ns, img.background, img.width, img.height) == (123, 12.0, 64, 48)
        assert ing.images.latest[1] is img
        s = ing.images.stats()
        assert (s["images"], s["chunks"], s["duplicate_chunks"], s["pending"]) == (1, 3, 1, 0)
        # the chunks of a finished request are unknown from now on (a replay of them changes nothing)
        _feed(ing, c1)
        assert ing.images.stats()["unknown_chunks"] == 1 and ing.images.latest[1] is img
        assert "ImageChunk" not in str(ing.counters.not_recorded)

    asyncio.run(run())


@pytest.mark.parametrize("what", ["other address", "other session", "other request", "other camera",
                                  "other total", "unsigned"])
def test_chunks_not_of_the_pending_request_are_dropped_and_change_nothing(what):
    async def run():
        ing, clock = _rig()
        if what == "unsigned":
            ing.key = ing._decode_key = b"k" * 32
        fut = ing.images.request_image(1)
        req = P.decode(ing.sock.sent[0][0], ing.key)
        good = _chunks(req)
        bad, addr, key = good[0], ADDR, ing.key
        if what == "other address":
            addr = ("127.0.0.1", 40001)
        elif what == "other session":
            bad = dataclasses.replace(bad, session=8)
        elif what == "other request":
            bad = dataclasses.replace(bad, request_id=req.request_id + 1)
        elif what == "other camera":
            bad = dataclasses.replace(bad, camera_id=2)
        elif what == "other total":  # a forged first chunk with another total would own the buffer: after
            _feed(ing, good[1], key=key)  # the first real one it must agree
            bad = _chunks(req, JPEG + b"x" * N)[0]
        else:
            key = None
        before = ing.images.stats()
        _feed(ing, bad, addr, key=key)
        after = ing.images.stats()
        assert after["chunks"] == before["chunks"] and not fut.done()
        # the real chunks still make the image
        for c in good:
            _feed(ing, c, key=ing.key)
        assert fut.result().jpeg == JPEG

    asyncio.run(run())


def test_missing_chunk_times_out_and_the_buffer_is_freed():
    async def run():
        ing, clock = _rig()
        ing.images.timeout_ns = 50 * MS
        fut = ing.images.request_image(1)
        req = P.decode(ing.sock.sent[0][0])
        c0, c1, c2 = _chunks(req)
        _feed(ing, c0)
        _feed(ing, c2)
        with pytest.raises(TimeoutError):
            await ing.images.wait(fut)
        assert ing.images.stats()["pending"] == 0 and ing.images.stats()["timeouts"] == 1
        _feed(ing, c1, recv_ns=T0 + 100 * MS)  # too late: unknown, no image
        assert 1 not in ing.images.latest and ing.images.stats()["unknown_chunks"] == 1

    asyncio.run(run())


def test_open_requests_are_bounded_and_unregistered_cameras_not_asked():
    async def run():
        ing, clock = _rig()
        with pytest.raises(ValueError, match="no registered station"):
            ing.images.request_image(2)
        with pytest.raises(ValueError, match="not in the arena"):
            ing.images.request_image(99)
        futs = [ing.images.request_image(1) for _ in range(I.MAX_PENDING)]
        with pytest.raises(ValueError, match="still open"):
            ing.images.request_image(1)
        clock.t += int(I.REQUEST_TIMEOUT_S * 1e9) + 1  # the old ones expire: room again
        ing.images.request_image(1)
        assert all(isinstance(f.exception(), TimeoutError) for f in futs)
        assert ing.images.stats()["pending"] == 1

    asyncio.run(run())


def test_mask_update_and_its_ack():
    async def run():
        ing, clock = _rig()
        fut = ing.images.update_mask(1, ignore=[[0, 0, 10, 20]])
        upd = P.decode(ing.sock.sent[-1][0])
        assert isinstance(upd, P.MaskUpdate) and upd.ignore == ((0, 0, 10, 20),) and upd.flags == P.MaskFlag.IGNORE
        stale = P.MaskAck(1, 1, 7, upd.request_id + 1, int(P.MaskStatus.SAVED), "forged")
        _feed(ing, stale)
        assert not fut.done() and ing.images.stats()["unknown_acks"] == 1
        _feed(ing, P.MaskAck(1, 1, 7, upd.request_id, int(P.MaskStatus.SAVED), "saved to st.yaml"))
        assert fut.result().text == "saved to st.yaml"
        with pytest.raises(ValueError):
            ing.images.update_mask(1, ignore=[[5, 5, 1, 1]])  # empty rectangle: refused before sending
        assert ing.images.stats()["pending"] == 0

    asyncio.run(run())


def test_a_station_sending_server_commands_is_refused():
    ing, _ = _rig()
    before = ing.counters.malformed
    ing.handle(P.encode(P.ImageRequest(1, 1, 7, 1, 1)), ADDR, T0)
    assert ing.counters.malformed == before + 1
