"""Station ingest: the server side of the station protocol, and per-camera health.

`Ingest.handle(data, addr, recv_ns)` is the whole per-packet path and does no I/O
of its own (it returns the replies to send), so tests and replays can drive it
with chosen receive times; `Ingest.start()` (endpoint.py) puts it on a UDP socket
read by the running asyncio loop (every waiting datagram per wake-up, at most ~2 ms
of work per batch so output ticks stay on time). camera_health.py holds what it
knows and counts (CameraHealth, IngestCounters) and the reasons it names.

Everything from the network is hostile until it passes every check, and a
packet that fails one changes no state but its rejection counters (and the
camera's "dropping (reason)" shown in status_line/health). Per packet: decode
(HMAC-checked when the arena has a key; with a key, unsigned packets count
nowhere else), then by type (docs/protocol.md has the rules byte by byte):
  Hello        needs the server's cookie (stateless challenge: a HELLO without a
               valid one is answered CHALLENGE and changes nothing); then registers
               the camera to (station, session, source address), or refreshes it
               (same session: its counter must be newer); a session that was
               replaced on this camera is refused. Unknown cameras -> REJECTED
  Heartbeat    from the registered session, address and a newer counter: keeps the
               station's clock health, answered OK (or RESYNC when the frames' times
               asked for a clock resync); an unknown session -> UNKNOWN_SESSION
  SyncRequest  same checks; answered SyncReply (t2 = receive stamp, t3 = send stamp)
  Bye          same checks; the camera leaves now: pipeline.remove_camera()
  ImageChunk,  answers to the server's IMAGE_REQUEST / MASK_UPDATE (server/images.py, `self.images`):
  MaskAck      kept only when they match a pending request from that camera's registered station,
               session and address; never recorded, never answered
  BlobFrame    from the registered station, session and address; seq newer (loss,
               duplicate, reordered, replayed); capture time sane (in the future /
               too old / going backwards = clock jump). Only then does any state
               change; then pipeline.push(frame). Nothing is ever sent in answer
               to a frame: a station learns that it is unknown, or that the server
               wants a clock resync, from the reply to its next heartbeat.
Only accepted packets are recorded (recorder.write_packet); the others are counted
in counters.not_recorded by reason. Replays (analysis/replay.py) build an Ingest
with verify_cookies=False (the live server's secret is gone; the recording holds
only what it accepted) and authenticate=False (no key needed to replay).
Nothing from the network can raise out of handle(). Warnings are rate-limited
(visionpos.logutil.RateLimitedLog) and keyed by camera or kind, never by sender,
and unknown_sources is a bounded LRU, so spoofed senders cannot grow any table.

A camera that sends no accepted frame for `vanish_periods` frame periods (at least
`vanish_min_s`; the period is its measured one when it delivers fewer frames than
it announced) is reported and removed from the pipeline so fusion stops waiting
for it; its next accepted frame brings it back.

Frame rate: a camera that delivers less than LOW_RATE_FRACTION of its configured
fps (cameras[i].fps) for LOW_RATE_AFTER_S is reported, once per episode, with what
to do (lower the configured rate or the station's load); health() carries it as a
structured warning (measured and configured fps, message) and status_line marks it.
The rate is measured only while the camera streams: after a gap in accepted frames longer than
OUTAGE_MIN_S and its vanish timeout (a reboot, a cable), the measurement starts again at its next frame.
"""

from __future__ import annotations

import hashlib
import hmac
import logging
import re
import secrets
import struct
import time
from collections import OrderedDict
from collections.abc import Callable, Sequence
from typing import Any, Protocol

from visionpos import protocol as P
from visionpos.config.arena import ArenaConfig
from visionpos.logutil import RateLimitedLog
from visionpos.messages import FLAG_RESYNC, BlobFrame
from visionpos.server.camera_health import (
    LOW_RATE_AFTER_S,
    LOW_RATE_FRACTION,
    OUTAGE_MIN_S,
    Addr,
    CameraHealth,
    ClockJump,
    IngestCounters,
    IngestEvent,
    Refusal,
    fmt_addr,
)
from visionpos.server.endpoint import UdpEndpoint
from visionpos.server.images import StationImages
from visionpos.server.load import ViewUpdatePause
from visionpos.server.settings import ServerSettings, parse_server

log = logging.getLogger(__name__)

_REORDER_WINDOW = 64  # a frame this many seqs late is "reordered"; older is a replay
_SEQ_RESTART = 1 << 20  # a forward seq jump this big is a restart, not 1M lost frames
_REASON = re.compile(r"[A-Za-z][A-Za-z -]*")  # the words of a ProtocolError message, its drop reason
_U32 = 0xFFFFFFFF
COOKIE_BUCKET_NS = 10_000_000_000  # a cookie is valid in its 10 s bucket and the next one
UNKNOWN_SOURCES_MAX = 64
_COOKIE_FIELDS = struct.Struct("<HHIq")


class PipelineLike(Protocol):
    def push(self, frame: BlobFrame) -> Any: ...
    def remove_camera(self, camera_id: int) -> Any: ...
    def pause_view_updates(self, paused: bool) -> Any: ...


class RecorderLike(Protocol):
    def write_packet(self, recv_ns: int, data: bytes, source: tuple[str, int] | None = None) -> None: ...


class Ingest(UdpEndpoint):
    """Server side of the station protocol for one arena. Not thread-safe: run on one loop.

    verify_cookies=False and authenticate=False are for replays of recordings (which hold only
    packets a live server accepted): registrations are trusted without the cookie round trip and
    tags are not checked, so a recording replays on a machine without the key.
    """

    def __init__(self, arena: ArenaConfig, settings: ServerSettings | None = None, pipeline: PipelineLike | None = None,
                 recorder: RecorderLike | None = None, clock=time.monotonic_ns, events=None, *,
                 verify_cookies: bool = True, authenticate: bool = True,
                 taps: Sequence[Callable[[int, bytes], None]] = ()):
        self.arena = arena
        self.settings = settings or parse_server(arena)
        self.pipeline = pipeline
        self.recorder = recorder
        self.clock = clock
        self.events = events  # optional callable(kind: str, info: dict) for the recorder/demo
        # tap(recv_ns, data) for each accepted packet, after the recorder (live outputs: the Foxglove
        # server's blob annotations); each must cost about a dictionary store
        self.taps = tuple(taps)
        self.key = self.settings.key
        self._decode_key = self.key if authenticate else None
        self.verify_cookies = verify_cookies
        self._secret = secrets.token_bytes(32)  # cookie key: this process only
        self.counters = IngestCounters()
        self.cameras: dict[int, CameraHealth] = {}
        stations = arena.camera_stations()  # checked at load: integers or None
        for i, cam in enumerate(arena.cameras):
            req = stations[cam.id]
            self.cameras[cam.id] = CameraHealth(cam.id, cam.name, float(cam.fps), cam.model.width,
                                                cam.model.height, req, fps_configured=float(cam.fps),
                                                config_key=f"cameras[{i}].fps")
        self.start_ns = 0
        self.duration_ns = int(self.settings.duration_s * 1e9)
        self._future_ns = int(self.settings.max_future_ms * 1e6)
        self._max_age_ns = int(self.settings.max_age_ms * 1e6)
        self._shed_ns = int(self.settings.shed_backlog_ms * 1e6) or None
        self._last_shed_log_ns = -(1 << 62)
        self.view_pause = ViewUpdatePause(int(self.settings.pause_views_backlog_ms * 1e6))
        self._last_pause_log_ns = -(1 << 62)
        self.rlog = RateLimitedLog(log)
        # (station, camera) -> packets of cameras not configured (or pinned to another station); LRU
        self.unknown_sources: OrderedDict[tuple[int, int], int] = OrderedDict()
        self._rt_minus_mono = 0
        self._rt_update_ns = 0
        # CLOCK_REALTIME - server clock for Timebase.REALTIME stations; None = read the host clocks
        # (live). A replay sets it from the recording's meta (wall_start_unix_ns - monotonic_start_ns).
        self.realtime_minus_monotonic_ns: int | None = None
        self._init_endpoint()
        self.images = StationImages(self)  # still images and mask updates on request (the console)
        self.set_start()

    # ---------------------------------------------------------------- run control

    def set_start(self, start_ns: int | None = None) -> None:
        """Trigger time handed to stations (default: now + start_delay_s)."""
        self.start_ns = int(self.clock() + self.settings.start_delay_s * 1e9) if start_ns is None else int(start_ns)

    def _warn(self, key: tuple, level: int, msg: str, *args: Any) -> None:
        """Log a problem, rate-limited per key (keys name a camera or a kind, never a sender)."""
        self.rlog.log(key, level, msg, *args)

    def _event(self, kind: IngestEvent, **info: Any) -> None:
        if self.events is not None:
            try:
                self.events(kind, info)
            except Exception:  # an observer must never take ingest down
                log.exception("event observer failed on %s", kind)

    def _refused(self, reason: str) -> None:
        if self.recorder is not None:
            nr = self.counters.not_recorded
            nr[reason] = nr.get(reason, 0) + 1

    def _record(self, data: bytes, addr: Addr, recv_ns: int) -> None:
        if self.recorder is not None:
            self.recorder.write_packet(recv_ns, data, (str(addr[0]), int(addr[1])) if addr else None)
        if self.taps:
            self._tap(data, recv_ns)

    def _tap(self, data: bytes, recv_ns: int) -> None:
        """Hand an accepted packet to the taps; a failing tap is counted and logged, never raised."""
        for tap in self.taps:
            try:
                tap(recv_ns, data)
            except Exception as e:
                self.counters.tap_errors += 1
                name = getattr(tap, "__qualname__", repr(tap))
                self._warn(("tap", name), logging.WARNING, "packet tap %s failed: %r (%d failures so far)", name, e,
                           self.counters.tap_errors)

    # ---------------------------------------------------------------- per packet

    def handle(self, data: bytes, addr: Addr, recv_ns: int, backlog_ns: int = 0) -> list[bytes]:
        """Process one datagram received at recv_ns (server monotonic ns); returns replies for addr.

        backlog_ns: how long it waited in the receive queue before recv_ns (live only; a frame
        that waited longer than server.shed_backlog_ms is not fused)."""
        c = self.counters
        c.packets += 1
        c.bytes += len(data)
        try:
            msg = P.decode(data, self._decode_key, recv_ns)
        except P.ProtocolError as e:
            self._undecodable(str(e), addr)
            return []
        except Exception as e:  # decode must not fail otherwise, but a packet never takes the server down
            c.malformed += 1
            self._refused("undecodable")
            self._warn(("crash", type(e).__name__), logging.ERROR, "decoder failed on a packet from %s: %r",
                       fmt_addr(addr), e)
            return []
        if type(msg) is BlobFrame:
            c.by_type["frame"] = c.by_type.get("frame", 0) + 1
            self._frame(msg, data, addr, recv_ns, backlog_ns)
            return []  # never an answer to a frame: no amplification
        return self._message(msg, data, addr, recv_ns)

    def _undecodable(self, text: str, addr: Addr) -> None:
        """A packet that failed decode (text: the ProtocolError's): counted as unauthenticated or as
        malformed by reason."""
        c = self.counters
        if self._decode_key is not None and (text.startswith("bad signature") or text.startswith("unsigned")):
            c.auth_failed += 1
            self._refused("unauthenticated")
            self._warn(("auth",), logging.WARNING, "dropping packets that fail authentication (last from %s): %s",
                       fmt_addr(addr), text)
            return
        c.malformed += 1
        self._refused("undecodable")
        # the reason's fixed words only: packet bytes in the text must not grow the dict
        m = _REASON.match(text)
        reason = m.group(0).removesuffix(" b").strip() if m else "undecodable"
        c.malformed_reasons[reason] = c.malformed_reasons.get(reason, 0) + 1
        self._warn(("bad", reason), logging.WARNING, "dropping malformed packet (last from %s): %s",
                   fmt_addr(addr), text)

    def _message(self, msg: P.Message, data: bytes, addr: Addr, recv_ns: int) -> list[bytes]:
        """Every message but a frame, by type; an accepted one is recorded. Returns the replies."""
        c = self.counters
        name = type(msg).__name__
        c.by_type[name] = c.by_type.get(name, 0) + 1
        try:
            if isinstance(msg, P.SyncRequest):
                replies, refusal = self._sync(msg, addr, recv_ns)
            elif isinstance(msg, P.Hello):
                replies, refusal = self._hello(msg, addr, recv_ns)
            elif isinstance(msg, P.Heartbeat):
                replies, refusal = self._heartbeat(msg, addr, recv_ns)
            elif isinstance(msg, P.Bye):
                replies, refusal = self._bye(msg, addr, recv_ns)
            elif isinstance(msg, P.ImageChunk):  # not recorded: a replay needs none of it
                self.images.on_chunk(msg, addr, recv_ns)
                return []
            elif isinstance(msg, P.MaskAck):
                self.images.on_mask_ack(msg, addr)
                return []
            else:  # HelloAck, SyncReply, ImageRequest, MaskUpdate go server -> station: the sender is confused
                c.malformed += 1
                self._refused(Refusal.WRONG_DIRECTION)
                self._warn(("dir", name), logging.WARNING,
                           "dropping %s from %s: that message goes server -> station", name, fmt_addr(addr))
                return []
        except P.ProtocolError as e:  # a reply field out of range: drop
            c.malformed += 1
            self._refused("undecodable")
            self._warn(("reply", name), logging.WARNING, "cannot answer %s from %s: %s", name, fmt_addr(addr), e)
            return []
        if refusal is None:
            self._record(data, addr, recv_ns)
        else:
            self._refused(refusal)
        return replies

    def _camera(self, station_id: int, camera_id: int, addr: Addr, what: str) -> CameraHealth | None:
        cam = self.cameras.get(camera_id)
        if cam is None or (cam.required_station is not None and cam.required_station != station_id):
            c = self.counters
            c.unknown += 1
            k = (station_id, camera_id)
            src = self.unknown_sources
            n = src.pop(k, 0) + 1
            if n == 1 and len(src) >= UNKNOWN_SOURCES_MAX:
                src.popitem(last=False)
                c.unknown_sources_evicted += 1
            src[k] = n
            if cam is None:
                self._warn(("unknown",), logging.WARNING,
                           "refusing %s from station %d camera %d at %s: camera %d is not in the arena config "
                           "(%s); add it under `cameras` or fix the station's camera id", what, station_id,
                           camera_id, fmt_addr(addr), camera_id, self.arena.source)
            else:
                self._warn(("unknown", camera_id), logging.WARNING,
                           "refusing %s from station %d camera %d at %s: the config says camera %d belongs to "
                           "station %d", what, station_id, camera_id, fmt_addr(addr), camera_id, cam.required_station)
            return None
        return cam

    def _ack(self, msg: P.Hello | P.Heartbeat, status: P.AckStatus, cookie: bytes = P.NO_COOKIE) -> bytes:
        self.counters.replies += 1
        ack = P.make_hello_ack(msg, self.start_ns, self.clock(), status, self.duration_ns, cookie)
        return P.encode(ack, self.key)

    def cookie(self, msg: P.Hello, addr: Addr, bucket: int) -> bytes:
        """The HELLO cookie for this sender and 10 s bucket: a MAC under this process's secret, so the
        server keeps no state for it and a HELLO replayed later or from elsewhere fails."""
        h = hmac.new(self._secret, _COOKIE_FIELDS.pack(msg.station_id, msg.camera_id, msg.session, bucket),
                     hashlib.sha256)
        h.update(f"{addr[0] if addr else ''}|{addr[1] if addr else ''}".encode())
        return h.digest()[:P.COOKIE_BYTES]

    def _cookie_ok(self, msg: P.Hello, addr: Addr, recv_ns: int) -> bool:
        if msg.cookie == P.NO_COOKIE:
            return False
        b = recv_ns // COOKIE_BUCKET_NS
        return (hmac.compare_digest(msg.cookie, self.cookie(msg, addr, b))
                or hmac.compare_digest(msg.cookie, self.cookie(msg, addr, b - 1)))

    def _hello(self, msg: P.Hello, addr: Addr, recv_ns: int) -> tuple[list[bytes], str | None]:
        cam = self._camera(msg.station_id, msg.camera_id, addr, "registration")
        if cam is None:
            self.counters.rejected_hello += 1
            return [self._ack(msg, P.AckStatus.REJECTED)], Refusal.UNKNOWN_CAMERA
        refused = self._hello_refused(cam, msg, addr, recv_ns)
        if refused is not None:
            return refused
        self._register(cam, msg, addr, recv_ns)
        return [self._ack(msg, P.AckStatus.OK)], None

    def _hello_refused(self, cam: CameraHealth, msg: P.Hello, addr: Addr,
                       recv_ns: int) -> tuple[list[bytes], str] | None:
        """The checks a HELLO for a configured camera passes before it changes anything: None, or the
        replies and the refusal."""
        if (msg.width, msg.height) != (cam.width, cam.height):
            self.counters.rejected_hello += 1
            self._warn(("res", msg.camera_id), logging.WARNING,
                       "refusing camera %d (%s) at %s: it streams %dx%d but the arena calibration is for %dx%d; "
                       "set the station's resolution or recalibrate", msg.camera_id, cam.name, fmt_addr(addr),
                       msg.width, msg.height, cam.width, cam.height)
            return [self._ack(msg, P.AckStatus.REJECTED)], Refusal.REJECTED
        if self.verify_cookies and not self._cookie_ok(msg, addr, recv_ns):
            # stateless: the answer goes to the claimed sender only, and is no bigger than the HELLO
            self.counters.challenges += 1
            return [self._ack(msg, P.AckStatus.CHALLENGE, self.cookie(msg, addr, recv_ns // COOKIE_BUCKET_NS))], \
                Refusal.CHALLENGED
        if msg.session in cam.retired:
            cam.stale_control += 1
            self._warn(("retired", cam.camera_id), logging.WARNING,
                       "camera %d (%s): refusing a HELLO from %s for session %08x, which a newer session replaced "
                       "(a replay)", cam.camera_id, cam.name, fmt_addr(addr), msg.session)
            return [], Refusal.RETIRED_SESSION
        if _same_session(cam, msg):
            if P.seq_delta(msg.counter, cam.last_counter) <= 0:
                cam.stale_control += 1
                return [], Refusal.STALE_COUNTER
        elif cam.registered and cam.station_id != msg.station_id and cam.online:
            self.counters.rejected_hello += 1
            self._warn(("dupcam", msg.camera_id), logging.WARNING,
                       "refusing camera %d from station %d at %s: station %d is already streaming it; "
                       "two stations are configured with the same camera id", msg.camera_id, msg.station_id,
                       fmt_addr(addr), cam.station_id)
            return [self._ack(msg, P.AckStatus.REJECTED)], Refusal.REJECTED
        return None

    def _register(self, cam: CameraHealth, msg: P.Hello, addr: Addr, recv_ns: int) -> None:
        """An accepted HELLO registers the camera to its station, session and address (a new session
        restarts the sequence and retires the old one), or refreshes the registration."""
        if not _same_session(cam, msg):
            if cam.session is not None:
                cam.retired.append(cam.session)
                log.info("camera %d (%s): station %d restarted (new session)", cam.camera_id, cam.name,
                         msg.station_id)
            else:
                log.info("camera %d (%s) registered from station %d at %s (%s, %.0f fps, %s)", cam.camera_id,
                         cam.name, msg.station_id, fmt_addr(addr), msg.software or "?", msg.fps, msg.camera_kind)
            cam.reset_sequence()
            cam.resync_pending = False
            self._event(IngestEvent.REGISTERED, camera_id=cam.camera_id, station_id=msg.station_id, session=msg.session)
        cam.station_id, cam.session, cam.addr, cam.registered = msg.station_id, msg.session, addr, True
        cam.last_counter = msg.counter
        cam.timebase, cam.software = msg.timebase, msg.software
        cam.fps_nominal = float(msg.fps)
        cam.last_seen_ns = recv_ns

    def _control(self, msg: P.Heartbeat | P.SyncRequest | P.Bye, addr: Addr,
                 what: str) -> tuple[CameraHealth | None, str | None]:
        """The checks every station -> server control message passes before it changes anything."""
        cam = self._camera(msg.station_id, msg.camera_id, addr, what)
        if cam is None:
            return None, Refusal.UNKNOWN_CAMERA
        if not cam.registered or cam.session != msg.session or cam.station_id != msg.station_id:
            if cam.registered:
                cam.wrong_session += 1
            return cam, Refusal.WRONG_SESSION if cam.registered else Refusal.NOT_REGISTERED
        if P.seq_delta(msg.counter, cam.last_counter) <= 0:
            cam.stale_control += 1
            self._warn(("stale", cam.camera_id), logging.WARNING,
                       "camera %d (%s): dropping a %s from %s whose counter %d is not newer than %d (replayed)",
                       cam.camera_id, cam.name, what, fmt_addr(addr), msg.counter, cam.last_counter)
            return cam, Refusal.STALE_COUNTER
        if addr != cam.addr:
            cam.wrong_address += 1
            return cam, Refusal.WRONG_ADDRESS
        return cam, None

    def _heartbeat(self, msg: P.Heartbeat, addr: Addr, recv_ns: int) -> tuple[list[bytes], str | None]:
        cam, refusal = self._control(msg, addr, "heartbeat")
        if refusal is not None:
            if refusal == Refusal.UNKNOWN_CAMERA:
                return [self._ack(msg, P.AckStatus.REJECTED)], refusal
            if refusal == Refusal.STALE_COUNTER:
                return [], refusal
            # unknown session (the server restarted), or a new address: the station registers (again)
            return [self._ack(msg, P.AckStatus.UNKNOWN_SESSION)], refusal
        cam.last_counter = msg.counter
        cam.last_seen_ns = recv_ns
        cam.clock_offset_ns = msg.clock_offset_ns
        cam.clock_uncertainty_ns = msg.clock_uncertainty_ns
        cam.drift_ppb = msg.drift_ppb
        cam.station_status = msg.status
        cam.station_frames_captured = msg.frames_captured
        cam.station_frames_dropped = msg.frames_dropped
        cam.station_send_errors = msg.send_errors
        cam.temperature_c = msg.temperature_c
        if cam.resync_pending:
            cam.resync_pending = False
            return [self._ack(msg, P.AckStatus.RESYNC)], None
        return [self._ack(msg, P.AckStatus.OK)], None

    def _sync(self, msg: P.SyncRequest, addr: Addr, recv_ns: int) -> tuple[list[bytes], str | None]:
        cam, refusal = self._control(msg, addr, "clock sync")
        if refusal is not None:
            return [], refusal
        cam.last_counter = msg.counter
        cam.last_seen_ns = recv_ns
        self.counters.replies += 1
        # t2 = the datagram's receive stamp, t3 = as late as possible before the send
        return [P.encode(P.make_sync_reply(msg, recv_ns, self.clock()), self.key)], None

    def _bye(self, msg: P.Bye, addr: Addr, recv_ns: int) -> tuple[list[bytes], str | None]:
        cam, refusal = self._control(msg, addr, "bye")
        if refusal is not None:
            return [], refusal
        log.info("camera %d (%s): station %s said bye", cam.camera_id, cam.name, msg.station_id)
        cam.retired.append(cam.session)
        cam.registered = False
        cam.session = None
        cam.resync_pending = False
        cam.reset_sequence()
        cam.last_seen_ns = recv_ns
        if cam.online:
            cam.online = False
            self._remove(cam, "station said bye")
        return [], None

    def _drop(self, cam: CameraHealth, reason: str, recv_ns: int) -> None:
        """A refused frame: only its counters and the camera's drop reason change."""
        cam.drop_reason = reason
        cam.last_drop_ns = recv_ns
        self._refused(reason)

    def _clock_jump(self, cam: CameraHealth, kind: ClockJump, addr: Addr, lat: int, recv_ns: int) -> None:
        cam.clock_jumps += 1
        cam.jump_run += 1
        cam.jumped_since_accepted += 1
        self._drop(cam, f"clock jump: {kind}", recv_ns)
        # says what was refused (this frame, the count), not what will be: the next frame with a sane
        # capture time is accepted
        self._warn(("jump", cam.camera_id, kind), logging.WARNING,
                   "camera %d (%s): clock jump (%s): capture time is %.1f ms %s the receive time; frame refused "
                   "(%d refused since its last accepted frame, %d since start; frames with a sane capture time "
                   "are still accepted)", cam.camera_id, cam.name, kind, abs(lat) * 1e-6,
                   "after" if lat < 0 else "before", cam.jumped_since_accepted, cam.clock_jumps)
        if cam.jump_run >= self.settings.resync_after and not cam.resync_pending:
            # ask the station (in the reply to its next heartbeat) to resync; restart the time checks
            cam.jump_run = 0
            cam.last_capture_ns = None
            cam.resync_pending = True
            cam.resync_requests += 1
            self._warn(("resync", cam.camera_id), logging.WARNING,
                       "camera %d (%s): %d clock-jumped frames in a row; asking the station to resync",
                       cam.camera_id, cam.name, self.settings.resync_after)
            self._event(IngestEvent.RESYNC_REQUEST, camera_id=cam.camera_id)

    def _frame(self, f: BlobFrame, data: bytes, addr: Addr, recv_ns: int, backlog_ns: int = 0) -> None:
        """A frame is checked completely (sender, sequence, capture time) before any state moves; a refused
        one changes only its counters and the camera's drop reason. Then it is recorded and fused."""
        cam = self._frame_sender(f, addr, recv_ns)
        if cam is None:
            return
        d = self._frame_seq_delta(cam, f, addr, recv_ns)
        if d is None:
            return
        timed = self._frame_time(cam, f, addr, recv_ns)
        if timed is None:
            return
        f, capture, lat = timed
        # accepted: now the state moves
        self._record(data, addr, recv_ns)
        self._advance_sequence(cam, f.seq, d, capture, recv_ns)
        self._frame_health(cam, lat, recv_ns)
        self._fuse(cam, f, recv_ns, backlog_ns)

    def _frame_sender(self, f: BlobFrame, addr: Addr, recv_ns: int) -> CameraHealth | None:
        """Who: only the registered station, session and address; the camera, or None (refused)."""
        cam = self.cameras.get(f.camera_id)
        if cam is None or (cam.required_station is not None and cam.required_station != f.station_id):
            self._camera(f.station_id, f.camera_id, addr, "frames")
            self._refused(Refusal.UNKNOWN_CAMERA)
            return None
        if not cam.registered:
            cam.unregistered += 1
            self._warn(("unreg", cam.camera_id), logging.WARNING,
                       "camera %d (%s): dropping frames from %s: the camera has not registered (no HELLO accepted)",
                       cam.camera_id, cam.name, fmt_addr(addr))
            return self._drop(cam, Refusal.NOT_REGISTERED, recv_ns)
        if f.session != cam.session or f.station_id != cam.station_id:
            cam.wrong_session += 1
            self._warn(("session", cam.camera_id), logging.WARNING,
                       "camera %d (%s): dropping frames from %s of station %d session %08x: registered is station %d "
                       "session %08x", cam.camera_id, cam.name, fmt_addr(addr), f.station_id, f.session,
                       cam.station_id, cam.session)
            return self._drop(cam, Refusal.WRONG_SESSION, recv_ns)
        if addr != cam.addr:
            cam.wrong_address += 1
            self._warn(("addr", cam.camera_id), logging.WARNING,
                       "camera %d (%s): dropping frames from %s: the station registered from %s",
                       cam.camera_id, cam.name, fmt_addr(addr), fmt_addr(cam.addr))
            return self._drop(cam, Refusal.WRONG_ADDRESS, recv_ns)
        return cam

    def _frame_seq_delta(self, cam: CameraHealth, f: BlobFrame, addr: Addr, recv_ns: int) -> int | None:
        """Sequence: later only (seqs after the last accepted one, wrap-around aware: > 0, 1 = the next);
        None when refused: older is a duplicate, reordered (within _REORDER_WINDOW) or replayed."""
        last_seq = cam.last_seq
        if last_seq is None:
            return 1
        d = (f.seq - last_seq) & _U32
        if d >= 0x80000000:
            d -= 0x100000000
        if d > 0:
            return d
        if d == 0:
            cam.duplicates += 1
            return self._drop(cam, Refusal.DUPLICATE, recv_ns)
        if d >= -_REORDER_WINDOW:
            # refused, so it stays lost: loss counts the seqs never accepted (a replayed old frame
            # must not hide real loss)
            cam.reordered += 1
            return self._drop(cam, Refusal.REORDERED, recv_ns)
        cam.replayed += 1
        self._warn(("replay", cam.camera_id), logging.WARNING,
                   "camera %d (%s): dropping frame seq %d from %s, older than the last accepted %d "
                   "(replayed)", cam.camera_id, cam.name, f.seq, fmt_addr(addr), last_seq)
        return self._drop(cam, Refusal.REPLAYED, recv_ns)

    def _frame_time(self, cam: CameraHealth, f: BlobFrame, addr: Addr,
                    recv_ns: int) -> tuple[BlobFrame, int, int] | None:
        """Time: capture must be on the server clock, a little before receive, and move forward.
        (the frame with its capture time on the server clock, capture_ns, latency ns), or None (refused)."""
        capture = f.capture_ns
        if cam.timebase == P.Timebase.REALTIME:
            if self.realtime_minus_monotonic_ns is not None:  # replay: the recording's offset
                rt = self.realtime_minus_monotonic_ns
            else:
                if recv_ns - self._rt_update_ns > 1_000_000_000:
                    self._rt_minus_mono = time.time_ns() - time.monotonic_ns()
                    self._rt_update_ns = recv_ns
                rt = self._rt_minus_mono
            capture = capture - rt
            f = BlobFrame(f.camera_id, f.seq, capture, f.blobs, f.station_id, f.flags, recv_ns, f.session)
        lat = recv_ns - capture
        if lat < -self._future_ns:
            cam.future += 1
            return self._clock_jump(cam, ClockJump.FUTURE, addr, lat, recv_ns)
        if lat > self._max_age_ns:
            cam.stale += 1
            return self._clock_jump(cam, ClockJump.STALE, addr, lat, recv_ns)
        if cam.last_capture_ns is not None and capture <= cam.last_capture_ns and not f.flags & FLAG_RESYNC:
            cam.backwards += 1
            return self._clock_jump(cam, ClockJump.BACKWARDS, addr, lat, recv_ns)
        if capture < self.start_ns:
            cam.before_start += 1
            return self._drop(cam, Refusal.BEFORE_START, recv_ns)
        return f, capture, lat

    def _advance_sequence(self, cam: CameraHealth, seq: int, d: int, capture: int, recv_ns: int) -> None:
        """An accepted frame's seq (d after the last accepted) and capture time become the camera's; the
        seqs skipped are lost (a jump of _SEQ_RESTART or more is a station restart, not loss)."""
        if d > 1:
            if d < _SEQ_RESTART:
                cam.lost += d - 1
                cam._bucket_lost += d - 1
            else:
                cam.seq_restarts += 1
        cam.last_seq = seq
        cam.jump_run = 0
        if cam.jumped_since_accepted:
            self._warn(("jump_end", cam.camera_id), logging.INFO,
                       "camera %d (%s): frames accepted again after %d refused for a clock jump",
                       cam.camera_id, cam.name, cam.jumped_since_accepted)
            cam.jumped_since_accepted = 0
        cam.last_capture_ns = capture
        cam.last_seen_ns = recv_ns

    def _frame_health(self, cam: CameraHealth, lat: int, recv_ns: int) -> None:
        """An accepted frame's latency (recv - capture, ns) and the camera's 1 s rate bucket; the camera is
        online (back, if it had vanished)."""
        cam.frames += 1
        if cam.frames == 1:
            cam.latency_ewma_ns = cam.latency_min_ns = cam.latency_max_ns = lat
        else:
            cam.latency_ewma_ns += 0.05 * (lat - cam.latency_ewma_ns)
            if lat < cam.latency_min_ns:
                cam.latency_min_ns = lat
            elif lat > cam.latency_max_ns:
                cam.latency_max_ns = lat
        outage_ns = max(OUTAGE_MIN_S * 1e9, self.vanish_timeout_ns(cam))
        if cam.last_frame_ns and recv_ns - cam.last_frame_ns > outage_ns:
            # back after an outage (a reboot, a cable): the rate is measured only while the camera streams,
            # so the bucket restarts here and the silence is no low-rate run
            cam._bucket_start, cam._bucket_frames, cam._bucket_lost = recv_ns, 0, 0
            cam.low_rate_since_ns = 0
        cam.last_frame_ns = recv_ns
        cam._bucket_frames += 1
        if recv_ns - cam._bucket_start >= 1_000_000_000:
            if cam._bucket_start:
                span = (recv_ns - cam._bucket_start) * 1e-9
                cam.fps = cam._bucket_frames / span
                exp = cam._bucket_frames + cam._bucket_lost
                cam.loss_rate = cam._bucket_lost / exp if exp else 0.0
                self._check_rate(cam, recv_ns)
            cam._bucket_start, cam._bucket_frames, cam._bucket_lost = recv_ns, 0, 0
        if not cam.online:
            cam.online = True
            if cam.vanished:
                log.warning("camera %d (%s) is back", cam.camera_id, cam.name)
                self._event(IngestEvent.CAMERA_BACK, camera_id=cam.camera_id)
        self.counters.frames_accepted += 1

    def _fuse(self, cam: CameraHealth, f: BlobFrame, recv_ns: int, backlog_ns: int) -> None:
        """Hand an accepted frame to the pipeline, unless it queued longer than server.shed_backlog_ms
        (load shedding: counted, not fused). A queue behind pauses the view updates first (server/load.py)."""
        changed = self.view_pause.update(backlog_ns)
        if changed is not None and self.pipeline is not None:
            self._pause_views(changed, backlog_ns, recv_ns)
        if self._shed_ns is not None and backlog_ns > self._shed_ns:
            cam.shed += 1
            self.counters.frames_shed += 1
            if recv_ns - self._last_shed_log_ns > 5_000_000_000:
                self._last_shed_log_ns = recv_ns
                log.warning("a frame queued %.0f ms before its turn: not fused (%d so far). Now and then this is a "
                            "stall (start-up, a pause); if it keeps happening this host is too slow for these "
                            "cameras (fewer cameras, a lower frame rate, a faster host, or a higher "
                            "fusion.min_fusion_interval_ms)", backlog_ns * 1e-6, self.counters.frames_shed)
            return
        if self.pipeline is not None:
            if self.view_pause.paused:
                self.counters.frames_without_view_updates += 1
            self._call_pipeline(self.pipeline.push, f, what="push failed (%d times so far); frame dropped")

    def _call_pipeline(self, method, *args, what: str) -> None:
        """A pipeline bug must not take the server down: counted, logged at the first and every 1000th."""
        try:
            method(*args)
        except Exception:
            self.counters.pipeline_errors += 1
            if self.counters.pipeline_errors == 1 or self.counters.pipeline_errors % 1000 == 0:
                log.exception("pipeline." + what, self.counters.pipeline_errors)

    def _pause_views(self, paused: bool, backlog_ns: int, recv_ns: int) -> None:
        """server/load.py: tell the pipeline; say it when it first pauses (then at most every 5 s)."""
        self._call_pipeline(self.pipeline.pause_view_updates, paused,
                            what="pause_view_updates failed (%d pipeline errors so far)")
        if paused and recv_ns - self._last_pause_log_ns > 5_000_000_000:
            self._last_pause_log_ns = recv_ns
            log.warning("a frame queued %.0f ms before its turn: per-frame view updates paused until the queue "
                        "drains (%d frames fused without them so far; every frame is still fused)",
                        backlog_ns * 1e-6, self.counters.frames_without_view_updates)

    def _check_rate(self, cam: CameraHealth, recv_ns: int) -> None:
        """After each 1 s bucket: a run of buckets below LOW_RATE_FRACTION of the configured fps that
        lasts LOW_RATE_AFTER_S is warned once; a bucket at the rate ends the run."""
        if cam.fps_configured <= 0:
            return
        if cam.fps >= LOW_RATE_FRACTION * cam.fps_configured:
            if cam.low_rate:
                log.info("camera %d (%s) delivers %.0f fps again (configured %g)", cam.camera_id, cam.name,
                         cam.fps, cam.fps_configured)
            cam.low_rate_since_ns, cam.low_rate = 0, False
            return
        if not cam.low_rate_since_ns:
            cam.low_rate_since_ns = cam._bucket_start  # the run starts with the bucket just measured
        if not cam.low_rate and recv_ns - cam.low_rate_since_ns >= LOW_RATE_AFTER_S * 1e9:
            cam.low_rate = True
            self._warn(("low_rate", cam.camera_id), logging.WARNING, "%s", cam.low_rate_message())

    # ---------------------------------------------------------------- periodic

    def vanish_timeout_ns(self, cam: CameraHealth) -> int:
        # the measured rate when it is lower than announced: a slow station is slow, not gone
        fps = min(cam.fps_nominal, cam.fps) if cam.fps > 0 else cam.fps_nominal
        period = 1.0 / fps if fps > 0 else 0.1
        return int(max(self.settings.vanish_periods * period, self.settings.vanish_min_s) * 1e9)

    def check_vanished(self, now_ns: int) -> list[int]:
        """Mark cameras silent for longer than their vanish timeout as gone; returns their ids.

        Live, silence is judged at the last moment the socket was found empty: when the server
        itself stalls, the frames still queued in the socket must not make every camera "vanish".
        """
        ref = min(now_ns, self._drained_ns) if self.sock is not None else now_ns
        gone = []
        for cam in self.cameras.values():
            if cam.online and ref - cam.last_frame_ns > self.vanish_timeout_ns(cam):
                cam.online = False
                cam.vanished += 1
                gone.append(cam.camera_id)
                why = f"no frames for {(ref - cam.last_frame_ns) * 1e-6:.0f} ms"
                if cam.last_drop_ns > cam.last_frame_ns:  # frames arrive but are refused
                    why = f"no frames accepted for {(ref - cam.last_frame_ns) * 1e-6:.0f} ms, dropping its " \
                          f"frames ({cam.drop_reason})"
                self._remove(cam, why)
        return gone

    def _remove(self, cam: CameraHealth, why: str) -> None:
        log.warning("camera %d (%s) lost: %s; fusing without it", cam.camera_id, cam.name, why)
        self._event(IngestEvent.CAMERA_LOST, camera_id=cam.camera_id, reason=why)
        if self.pipeline is not None:
            try:
                self.pipeline.remove_camera(cam.camera_id)
            except Exception:
                self.counters.pipeline_errors += 1
                log.exception("pipeline.remove_camera(%d) failed", cam.camera_id)

    def health(self, now_ns: int | None = None) -> dict[str, Any]:
        now = self.clock() if now_ns is None else now_ns
        c = self.counters
        return {
            "cameras": {cid: cam.snapshot(now, self.vanish_timeout_ns(cam)) for cid, cam in self.cameras.items()},
            "packets": c.packets,
            "bytes": c.bytes,
            "frames_accepted": c.frames_accepted,
            "frames_shed": c.frames_shed,
            "frames_without_view_updates": c.frames_without_view_updates,
            "malformed": c.malformed,
            "malformed_reasons": dict(c.malformed_reasons),
            "auth_failed": c.auth_failed,
            "unknown": c.unknown,
            "unknown_sources": {f"{s}/{cid}": n for (s, cid), n in self.unknown_sources.items()},
            "unknown_sources_evicted": c.unknown_sources_evicted,
            "rejected_hello": c.rejected_hello,
            "challenges": c.challenges,
            "not_recorded": dict(c.not_recorded),
            "log_suppressed": self.rlog.suppressed,
            "pipeline_errors": c.pipeline_errors,
            "tap_errors": c.tap_errors,
            "replies": c.replies,
            "send_errors": c.send_errors,
            "by_type": dict(c.by_type),
            "start_ns": self.start_ns,
            "authenticated": self.key is not None,
            "images": self.images.stats(),
        }

    def status_line(self, now_ns: int | None = None) -> str:
        now = self.clock() if now_ns is None else now_ns
        parts = []
        for cam in self.cameras.values():
            if not cam.online:
                state = cam.state(now, self.vanish_timeout_ns(cam))
                parts.append(f"{cam.camera_id}:{state}({cam.drop_reason})" if state == "dropping"
                             else f"{cam.camera_id}:{state}")
                continue
            off = "" if cam.clock_offset_ns is None else f" off{cam.clock_offset_ns * 1e-6:+.1f}ms"
            low = f"(LOW, configured {cam.fps_configured:g})" if cam.low_rate else ""
            parts.append(f"{cam.camera_id}:{cam.fps:.0f}fps{low} loss{100 * cam.loss_rate:.1f}%"
                         f" lat{cam.latency_ewma_ns * 1e-6:.1f}ms{off}")
        c = self.counters
        bad = f" bad {c.malformed}" if c.malformed else ""
        auth = f" auth-fail {c.auth_failed}" if c.auth_failed else ""
        unk = f" unknown {c.unknown}" if c.unknown else ""
        return "stations: " + " ".join(parts) + bad + auth + unk


def _same_session(cam: CameraHealth, msg: P.Hello) -> bool:
    """The HELLO is of the camera's registered station and session (a refresh, not a new registration)."""
    return cam.registered and cam.session == msg.session and cam.station_id == msg.station_id
