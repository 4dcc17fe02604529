"""Still images and mask updates: the server's side of IMAGE_REQUEST / IMAGE_CHUNK / MASK_UPDATE / MASK_ACK.

`StationImages` (one per Ingest, `ingest.images`) sends a request to a registered station's address and
reassembles the answer's chunks; the console (console/server.py) awaits the result. Nothing here is on
fusion's path: a chunk costs one dictionary look-up and one copy into its image's buffer, and nobody
waits in Ingest.handle.

Hostile input: a chunk counts only if it passed the decoder's checks (HMAC with a key; the chunking
rule; total <= MAX_IMAGE_BYTES) and comes from the registered station, session and address of the
camera a pending request asked, with the request's id; its header must agree with the request's first
chunk. Anything else is dropped and counted (changes no state). Memory is bounded: at most
MAX_PENDING requests at once, each buffer at most MAX_IMAGE_BYTES, and a request with chunks missing
is dropped after its timeout.
"""

from __future__ import annotations

import asyncio
from collections import OrderedDict
from dataclasses import dataclass, field
from typing import Any, Sequence

from visionpos import protocol as P

MAX_PENDING = 8  # requests (images and masks) outstanding at once
REQUEST_TIMEOUT_S = 3.0  # a still image or mask ack not complete by then is dropped
_U32 = 0xFFFFFFFF


@dataclass(frozen=True)
class StillImage:
    """A station's still image: JPEG bytes (width x height px), its frame's capture time (server clock when
    the station is synced), the station's background level (0..255) and when it was complete (server clock)."""

    camera_id: int
    jpeg: bytes
    capture_ns: int
    background: float
    width: int
    height: int
    received_ns: int


@dataclass
class _Pending:
    kind: str  # "image" or "mask"
    camera_id: int
    station_id: int
    session: int
    addr: Any
    created_ns: int
    future: asyncio.Future
    header: tuple | None = None  # (count, total, capture_ns, width, height, background) of the first chunk
    buf: bytearray = field(default_factory=bytearray)
    got: bytearray = field(default_factory=bytearray)  # 1 per chunk received
    left: int = 0


@dataclass
class ImageCounters:
    image_requests: int = 0
    images: int = 0
    chunks: int = 0
    duplicate_chunks: int = 0
    unknown_chunks: int = 0  # no pending request of that id, camera, station, session and address
    inconsistent_chunks: int = 0  # header differs from the request's first chunk
    timeouts: int = 0
    mask_updates: int = 0
    mask_acks: int = 0
    unknown_acks: int = 0


class StationImages:
    """Requests to stations and their answers, for one Ingest (its cameras, socket, key and clock)."""

    def __init__(self, ingest: Any, timeout_s: float = REQUEST_TIMEOUT_S):
        self.ingest = ingest
        self.timeout_ns = int(timeout_s * 1e9)
        self.counters = ImageCounters()
        self.latest: dict[int, StillImage] = {}
        self._pending: OrderedDict[int, _Pending] = OrderedDict()
        self._next_id = 0

    # ---------------------------------------------------------------- requests (the console's loop)

    def _start(self, kind: str, camera_id: int) -> tuple[int, Any, _Pending]:
        ing = self.ingest
        cam = ing.cameras.get(camera_id)
        if cam is None:
            raise ValueError(f"camera {camera_id} is not in the arena")
        if not cam.registered or cam.addr is None or cam.session is None:
            raise ValueError(f"camera {camera_id} ({cam.name}) has no registered station to ask")
        if ing.sock is None:
            raise ValueError("the server is not listening (a replay has no stations to ask)")
        now = ing.clock()
        self.expire(now)
        if len(self._pending) >= MAX_PENDING:
            raise ValueError(f"{MAX_PENDING} requests to stations are still open; try again in a few seconds")
        self._next_id = (self._next_id + 1) & _U32
        fut = asyncio.get_running_loop().create_future()
        p = _Pending(kind, camera_id, cam.station_id, cam.session, cam.addr, now, fut)
        self._pending[self._next_id] = p
        return self._next_id, cam, p

    def _send(self, msg: P.Message, addr: Any) -> None:
        try:
            self.ingest.sock.sendto(P.encode(msg, self.ingest.key), addr)
        except OSError as e:
            raise ValueError(f"cannot send to the station at {addr[0]}:{addr[1]}: {e}") from None

    def request_image(self, camera_id: int, max_width: int = 640, quality: int = 80) -> asyncio.Future:
        """Ask camera_id's station for a still image; the future's result is a StillImage (or TimeoutError).
        Raises ValueError when it cannot be asked (unknown or unregistered camera, too many open requests)."""
        rid, cam, p = self._start("image", camera_id)
        try:
            self._send(P.ImageRequest(cam.station_id, camera_id, cam.session, cam.last_counter, rid, max_width,
                                      quality), cam.addr)
        except ValueError:
            self._pending.pop(rid, None)
            raise
        self.counters.image_requests += 1
        return p.future

    def update_mask(self, camera_id: int, ignore: Sequence[Sequence[int]] | None = None,
                    rois: Sequence[Sequence[int]] | None = None) -> asyncio.Future:
        """Send camera_id's station a MASK_UPDATE setting ignore and/or rois (None: leave that list); the
        future's result is the station's MaskAck. Raises ValueError as request_image, or for bad rectangles."""
        if ignore is None and rois is None:
            raise ValueError("a mask update sets ignore rectangles, rois or both")
        flags = (P.MaskFlag.IGNORE if ignore is not None else 0) | (P.MaskFlag.ROIS if rois is not None else 0)
        rid, cam, p = self._start("mask", camera_id)
        try:
            msg = P.MaskUpdate(cam.station_id, camera_id, cam.session, cam.last_counter, rid, int(flags),
                               tuple(tuple(int(v) for v in r) for r in ignore or ()),
                               tuple(tuple(int(v) for v in r) for r in rois or ()))
            self._send(msg, cam.addr)
        except (ValueError, P.ProtocolError) as e:
            self._pending.pop(rid, None)
            raise ValueError(str(e)) from None
        self.counters.mask_updates += 1
        return p.future

    async def still(self, camera_id: int, max_width: int = 640, quality: int = 80) -> StillImage:
        """request_image and wait for it (TimeoutError after the timeout)."""
        return await self.wait(self.request_image(camera_id, max_width, quality))

    async def mask(self, camera_id: int, ignore: Sequence[Sequence[int]] | None = None,
                   rois: Sequence[Sequence[int]] | None = None) -> P.MaskAck:
        return await self.wait(self.update_mask(camera_id, ignore, rois))

    async def wait(self, fut: asyncio.Future) -> Any:
        try:
            return await asyncio.wait_for(asyncio.shield(fut), self.timeout_ns / 1e9)
        except asyncio.TimeoutError:
            self.expire(self.ingest.clock(), force=fut)
            raise TimeoutError("the station did not answer in time (is it running this version? a request "
                               "within image_min_interval_s of the last is not answered)") from None

    def expire(self, now_ns: int, force: asyncio.Future | None = None) -> None:
        """Drop requests older than the timeout (and the one whose future is force)."""
        for rid, p in list(self._pending.items()):
            if p.future is force or now_ns - p.created_ns > self.timeout_ns:
                del self._pending[rid]
                self.counters.timeouts += 1
                if not p.future.done():
                    p.future.set_exception(TimeoutError(f"no complete answer from camera {p.camera_id}'s station"))
                    p.future.exception()  # retrieved: no "never retrieved" warning when nobody waits

    # ---------------------------------------------------------------- answers (Ingest.handle, per packet)

    def _match(self, msg: P.ImageChunk | P.MaskAck, addr: Any, kind: str) -> _Pending | None:
        p = self._pending.get(msg.request_id)
        if (p is None or p.kind != kind or p.camera_id != msg.camera_id or p.station_id != msg.station_id
                or p.session != msg.session or p.addr != addr):
            return None
        cam = self.ingest.cameras.get(msg.camera_id)
        if cam is None or not cam.registered or cam.session != p.session or cam.addr != addr:
            return None  # the station registered again since: its answer is stale
        return p

    def on_chunk(self, msg: P.ImageChunk, addr: Any, recv_ns: int) -> bool:
        """One decoded chunk; True if it was part of a pending request's image."""
        c = self.counters
        p = self._match(msg, addr, "image")
        if p is None:
            c.unknown_chunks += 1
            return False
        if recv_ns - p.created_ns > self.timeout_ns:
            self.expire(recv_ns)
            c.unknown_chunks += 1
            return False
        header = (msg.count, msg.total_bytes, msg.capture_ns, msg.width, msg.height, msg.background)
        if p.header is None:
            p.header = header
            p.buf = bytearray(msg.total_bytes)
            p.got = bytearray(msg.count)
            p.left = msg.count
        elif header != p.header:
            c.inconsistent_chunks += 1
            return False
        if p.got[msg.index]:
            c.duplicate_chunks += 1
            return False
        start = msg.index * P.IMAGE_CHUNK_BYTES
        p.buf[start:start + len(msg.data)] = msg.data
        p.got[msg.index] = 1
        p.left -= 1
        c.chunks += 1
        if p.left == 0:
            del self._pending[msg.request_id]
            img = StillImage(msg.camera_id, bytes(p.buf), msg.capture_ns, float(msg.background), msg.width,
                             msg.height, recv_ns)
            self.latest[msg.camera_id] = img
            c.images += 1
            if not p.future.done():
                p.future.set_result(img)
        return True

    def on_mask_ack(self, msg: P.MaskAck, addr: Any) -> bool:
        p = self._match(msg, addr, "mask")
        if p is None:
            self.counters.unknown_acks += 1
            return False
        del self._pending[msg.request_id]
        self.counters.mask_acks += 1
        if not p.future.done():
            p.future.set_result(msg)
        return True

    def stats(self) -> dict[str, Any]:
        return {**self.counters.__dict__, "pending": len(self._pending)}
