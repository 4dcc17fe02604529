"""Station agent: capture -> detect -> stamp -> send, plus registration,
heartbeats and clock sync with the fusion server (docs/protocol.md). The
protocol's registration state and reply checks live in stations/session.py
(StationLink); this module is its socket and capture loop.

One thread. The network never blocks capture: the UDP socket is
non-blocking, incoming packets are drained between frames, and a send that
would block is counted and the frame dropped (never queued). A failing camera
is closed and reopened with exponential back-off while the agent keeps
talking to the server (heartbeats say camera not OK).
"""

from __future__ import annotations

import dataclasses
import logging
import select
import socket
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np

from stations.clocksync import ClockSync
from stations.config import StationConfig, build_mask, load_background
from stations.detector import Detector
from stations.session import LinkEvent, StationLink
from stations.sources import EndOfStream, FrameSource, SourceError, make_source
from stations.still import StillLimiter, background_level, check_rects, encode_still, image_chunks, save_mask
from visionpos import protocol as P
from visionpos.config.arena import ConfigError
from visionpos.logutil import RateLimitedLog
from visionpos.messages import FLAG_RESYNC, FLAG_TRUNCATED, BlobFrame
from visionpos.server.netstamps import ANC_SIZE, enable_kernel_stamps, kernel_stamp_ns

log = logging.getLogger("visionpos.station")

try:
    from importlib.metadata import version as _pkg_version

    SOFTWARE = f"visionpos {_pkg_version('visionpos')}"[:16]
except Exception:  # running from a source tree without installed metadata
    SOFTWARE = "visionpos"

HELLO_FIRST_S = 0.5
HELLO_MAX_S = 5.0
THERMAL = Path("/sys/class/thermal/thermal_zone0/temp")


@dataclass
class AgentStats:
    frames_captured: int = 0
    frames_sent: int = 0
    frames_dropped: int = 0  # captured, not sent: not registered / not synced / send failed
    frames_before_start: int = 0
    send_errors: int = 0
    truncated_frames: int = 0
    camera_failures: int = 0
    registrations: int = 0
    bad_packets: int = 0  # undecodable or unauthenticated
    refused_replies: int = 0  # decoded, but not from the server / session / a recent request of ours
    images_sent: int = 0  # still images sent on the server's request
    images_refused: int = 0  # image requests inside image_min_interval_s (answered by nothing) or with no frame yet
    mask_updates: int = 0  # MASK_UPDATEs answered (applied or refused)


def read_temperature() -> float | None:
    """CPU temperature in deg C from the Linux thermal zone, None if absent."""
    try:
        return int(THERMAL.read_text().strip()) / 1000.0
    except (OSError, ValueError):
        return None


class StationAgent:
    """Runs one camera. `source` and `clock` may be injected (tests, sim).

    clock: station clock in ns; default time.monotonic_ns with the built-in
    sync, time.time_ns (CLOCK_REALTIME, PTP/chrony-disciplined) without.
    """

    def __init__(
        self,
        cfg: StationConfig,
        source: FrameSource | None = None,
        clock: Callable[[], int] | None = None,
        sleep: Callable[[float], None] = time.sleep,
    ):
        self.cfg = cfg
        self.clock = clock or (time.monotonic_ns if cfg.clock_sync else time.time_ns)
        # a simulated camera renders the scenario at the capture time on the server clock (to_server)
        self.source = source or make_source(cfg.source, self.clock, cfg.camera_id, to_shared=self.to_server)
        self.timebase = P.Timebase.SERVER if cfg.clock_sync else P.Timebase.REALTIME
        self.link = StationLink(cfg.station_id, cfg.camera_id)
        self.stats = AgentStats()
        self.sync = ClockSync(cfg.station_id, cfg.camera_id) if cfg.clock_sync else None
        self.detector: Detector | None = None
        self.camera_ok = False
        self._stop = threading.Event()
        self._sleep = sleep
        self._seq = 0
        self._hello_gap_s = HELLO_FIRST_S
        self._next_hello = 0
        self._next_hb = 0
        self._last_heard: int | None = None
        self._estimate_seen = None
        self._size: tuple[int, int] | None = None
        # the newest frame and its blobs, kept by reference (no copy per frame) for a still image on request
        self._last_image: np.ndarray | None = None
        self._last_blobs: np.ndarray | None = None
        self._last_t = 0
        self.stills = StillLimiter(cfg.image_min_interval_s)
        self.rlog = RateLimitedLog(log)
        self._addr: tuple | None = None
        self._next_resolve = 0.0
        self.sock: socket.socket | None = None
        if not self._resolve():
            self.sock = self._make_socket(socket.AF_INET)

    @property
    def session(self) -> int:
        return self.link.session

    @property
    def registered(self) -> bool:
        return self.link.registered

    @property
    def rejected(self) -> bool:
        return self.link.rejected

    @property
    def start_ns(self) -> int | None:
        return self.link.start_ns

    @property
    def duration_ns(self) -> int:
        return self.link.duration_ns

    # ------------------------------------------------------------ network

    def _resolve(self) -> bool:
        """Resolve the server address (retried every 5 s: DNS may come up
        after the station at boot); makes a socket of the right family."""
        if self._addr is not None:
            return True
        now = time.monotonic()
        if now < self._next_resolve:
            return False
        self._next_resolve = now + 5.0
        try:
            family, _, _, _, addr = socket.getaddrinfo(self.cfg.server_host, self.cfg.server_port,
                                                       type=socket.SOCK_DGRAM)[0]
        except OSError as e:
            self._log_once(f"resolve {e}", logging.WARNING, "cannot resolve server %s: %s; retrying every 5 s",
                           self.cfg.server_host, e)
            return False
        if self.sock is None or self.sock.family != family:
            if self.sock is not None:
                self.sock.close()
            self.sock = self._make_socket(family)
        self._addr = addr
        return True

    def _make_socket(self, family: int) -> socket.socket:
        s = socket.socket(family, socket.SOCK_DGRAM)
        s.setblocking(False)
        # Kernel receive timestamps: the agent reads the socket only between
        # frames, so a user-space t4 would be late by up to a frame period and
        # bias the clock offset by half of that.
        self._rx_stamps = enable_kernel_stamps(s)
        return s

    def _log_once(self, key: str, level: int, msg: str, *args: object) -> None:
        """Rate-limited per problem (a misconfigured or hostile peer must not flood the journal)."""
        self.rlog.log(key, level, msg, *args)

    def _recv(self) -> tuple[bytes, Any, int]:
        """One datagram, its sender and its receive time on the station clock."""
        if not self._rx_stamps:
            data, src = self.sock.recvfrom(2048)
            return data, src, self.clock()
        data, anc, _, src = self.sock.recvmsg(2048, ANC_SIZE)
        k = kernel_stamp_ns(anc)
        if k:  # kernel stamp is CLOCK_REALTIME: move it onto the station clock
            return data, src, k - (time.time_ns() - self.clock())
        return data, src, self.clock()

    def _send(self, data: bytes) -> bool:
        if not self._resolve():
            self.stats.send_errors += 1
            return False
        try:
            self.sock.sendto(data, self._addr)
            return True
        except (BlockingIOError, InterruptedError):
            self.stats.send_errors += 1
        except OSError as e:  # ECONNREFUSED from an earlier ICMP, ENETUNREACH, ...
            self.stats.send_errors += 1
            log.debug("send to %s failed: %s", self._addr, e)
        return False

    def _drain(self) -> None:
        """Handle every pending datagram; never blocks."""
        while True:
            try:
                data, src, t4 = self._recv()
            except (BlockingIOError, InterruptedError):
                return
            except OSError:  # ICMP port unreachable surfaces here on Linux: server is down
                continue
            try:
                msg = P.decode(data, self.cfg.key)
            except P.ProtocolError as e:
                self.stats.bad_packets += 1
                self._log_once(f"bad {str(e)[:24]}", logging.WARNING, "dropping packets from %s: %s", src, e)
                continue
            if isinstance(msg, (P.ImageRequest, P.MaskUpdate)):
                if self.link.believe_command(msg, src, self._addr):
                    self._last_heard = t4
                    self._on_command(msg)
                else:
                    self.stats.refused_replies += 1
                    self._log_once("refused command", logging.WARNING, "ignoring a %s from %s: not from the server "
                                   "%s for this station's session, or replayed", type(msg).__name__, src, self._addr)
                continue
            if not isinstance(msg, (P.HelloAck, P.SyncReply)) or not self.link.believe(msg, src, self._addr):
                self.stats.refused_replies += 1
                self._log_once("refused", logging.WARNING, "ignoring a %s from %s: not an answer from the server "
                               "%s to this station's session", type(msg).__name__, src, self._addr)
                continue
            self._last_heard = t4
            if isinstance(msg, P.HelloAck):
                self._on_ack(msg, t4)
            elif self.sync is not None:
                self.sync.reply(msg, t4)

    # ------------------------------------------------------------ server commands (on request only)

    def _on_command(self, msg: P.ImageRequest | P.MaskUpdate) -> None:
        if isinstance(msg, P.ImageRequest):
            self._send_still(msg)
        else:
            self.stats.mask_updates += 1
            self._send(P.encode(self.apply_mask(msg), self.cfg.key))

    def _send_still(self, req: P.ImageRequest) -> None:
        """The newest frame as a JPEG in IMAGE_CHUNKs, at most one per image_min_interval_s."""
        image, blobs = self._last_image, self._last_blobs
        if image is None or blobs is None or not self.stills.allow(self.clock()):
            self.stats.images_refused += 1
            return
        t = self.to_server(self._last_t)
        stamp = self._last_t if t is None else t
        # encoding takes 40-70 ms on a Pi: a thread of its own, so the capture loop drops no frame for it; on
        # a copy, because a camera source may reuse its buffer for the next frame
        threading.Thread(target=self._encode_still, args=(req, image.copy(), np.array(blobs), stamp),
                         name="still-image", daemon=True).start()

    def _encode_still(self, req: P.ImageRequest, image: np.ndarray, blobs: np.ndarray, stamp_ns: int) -> None:
        try:
            jpeg, w, h = encode_still(image, req.max_width, req.quality)
        except ValueError as e:  # OpenCV could not encode it: the server's request times out
            self._log_once("jpeg", logging.WARNING, "cannot send a still image: %s", e)
            return
        bg = background_level(image, blobs)
        for chunk in image_chunks(req, jpeg, stamp_ns, w, h, bg):
            self._send(P.encode(chunk, self.cfg.key))
        self.stats.images_sent += 1

    def apply_mask(self, msg: P.MaskUpdate) -> P.MaskAck:
        """Check a MASK_UPDATE against the image size, put it on the running detector, save it to the
        station's config file; the MASK_ACK saying which of these happened."""
        def ack(status: P.MaskStatus, text: str) -> P.MaskAck:
            return P.MaskAck(self.cfg.station_id, self.cfg.camera_id, self.session, msg.request_id, status, text)

        if self.detector is None or self._size is None:
            return ack(P.MaskStatus.REFUSED, "the camera is not open yet")
        w, h = self._size
        ignore = msg.ignore if msg.flags & P.MaskFlag.IGNORE else self.cfg.ignore
        rois = msg.rois if msg.flags & P.MaskFlag.ROIS else self.cfg.rois
        why = check_rects(ignore + rois, w, h)
        if why is not None:
            return ack(P.MaskStatus.REFUSED, why)
        cfg = dataclasses.replace(self.cfg, ignore=tuple(ignore), rois=tuple(rois))
        try:
            mask = build_mask(cfg, w, h)
        except ConfigError as e:  # the mask image went missing or changed since start
            return ack(P.MaskStatus.REFUSED, str(e))
        self.detector.mask = mask
        self.cfg = cfg
        values = {}
        if msg.flags & P.MaskFlag.IGNORE:
            values["ignore"] = ignore
        if msg.flags & P.MaskFlag.ROIS:
            values["rois"] = rois
        if not Path(self.cfg.source_file).is_file():
            return ack(P.MaskStatus.APPLIED, "applied; no config file to save it in")
        try:
            save_mask(self.cfg.source_file, values)
        except (OSError, ValueError) as e:
            log.warning("mask applied but not saved to %s: %s", self.cfg.source_file, e)
            return ack(P.MaskStatus.APPLIED, f"not saved: {e}")
        log.info("mask from the server applied and saved to %s: %s", self.cfg.source_file, values)
        return ack(P.MaskStatus.SAVED, f"saved to {Path(self.cfg.source_file).name}")

    def _on_ack(self, ack: P.HelloAck, now: int) -> None:
        event = self.link.on_ack(ack)
        if event is LinkEvent.LOST:
            self._log_once("lost", logging.WARNING, "server does not know this station's session (it restarted, or "
                           "this station's address changed): registering again")
            self._lost(now)
            self._next_hello = now  # at once
        elif event is LinkEvent.CHALLENGED:
            if self.link.cookie_is_new:
                self._next_hello = now  # answer the challenge at once
        elif event is LinkEvent.REJECTED:
            self._log_once("rejected", logging.ERROR, "server %s:%d rejected camera %d of station %d: the camera id "
                           "is not in its arena config or the resolution differs; fix the configs (retrying every "
                           "%.0f s)", self.cfg.server_host, self.cfg.server_port, self.cfg.camera_id,
                           self.cfg.station_id, HELLO_MAX_S)
            self._hello_gap_s = HELLO_MAX_S
        elif event is LinkEvent.RESYNC:
            self._log_once("resync", logging.WARNING, "server saw this camera's capture times jump: restarting "
                           "clock sync")
            if self.sync is not None:
                self.sync.reset()  # frames wait for the new estimate; the first one carries FLAG_RESYNC
        elif event is LinkEvent.REGISTERED:
            self.stats.registrations += 1
            log.info("registered with %s:%d (session %08x); capture start at server time %d",
                     self.cfg.server_host, self.cfg.server_port, self.session, ack.start_ns)
            self._next_hb = now
            self._hello_gap_s = HELLO_FIRST_S
        elif event is LinkEvent.IGNORED:
            self._log_once("status", logging.WARNING, "server answered with unknown status %d; ignoring", ack.status)

    def _lost(self, now: int) -> None:
        """Back to registration; the server may be a new one, so its clock too."""
        self.link.lost()
        self._hello_gap_s = HELLO_FIRST_S
        self._last_heard = None
        if self.sync is not None:
            # keep _estimate_seen: the first frame on the new estimate gets
            # FLAG_RESYNC if the offset moved (a restarted server's new clock)
            self.sync.reset()

    def service(self) -> None:
        """Drain replies and send whatever is due (hello, heartbeat, sync)."""
        self._drain()
        now = self.clock()
        if self.registered and self._last_heard is not None and now - self._last_heard > self.cfg.link_timeout_s * 1e9:
            log.warning("no answer from server %s:%d for %.1f s: registering again",
                        self.cfg.server_host, self.cfg.server_port, self.cfg.link_timeout_s)
            self._lost(now)
            self._next_hello = now
        if not self.registered:
            # a HELLO says the resolution: none before the camera has told it (a source whose size comes with
            # open(), the simulator's, a camera without a configured size), or the server refuses it as malformed
            if now >= self._next_hello and self.source.width and self.source.height:
                self._send(P.encode(self._hello(), self.cfg.key))
                self._next_hello = now + int(self._hello_gap_s * 1e9)
                self._hello_gap_s = min(self._hello_gap_s * 2, HELLO_MAX_S)
            return
        if now >= self._next_hb:
            self._send(P.encode(self._heartbeat(now), self.cfg.key))
            self._next_hb = now + int(self.cfg.heartbeat_s * 1e9)
        if self.sync is not None and self.sync.due(now):
            t1 = self.clock()
            req = self.link.sync_request(t1)
            self._send(P.encode(self.sync.request(t1, req.counter, req.session), self.cfg.key))

    def _hello(self) -> P.Hello:
        src = self.source
        name = (self.cfg.camera_name or src.name).encode()[:32].decode(errors="ignore")
        kind = self.cfg.camera_kind
        if kind == "unknown" and getattr(src, "camera_kind", "unknown") in P.CAMERA_KINDS:
            kind = src.camera_kind
        return self.link.hello(int(src.width or 0), int(src.height or 0), float(src.fps or 0.0), kind, name,
                               SOFTWARE, self.timebase)

    def _heartbeat(self, now: int) -> P.Heartbeat:
        hb = P.HeartbeatStatus
        status = hb(0)
        if self.camera_ok:
            status |= hb.CAMERA_OK
        if self.streaming(now):
            status |= hb.STREAMING
        off, unc, drift = 0, P.UNCERTAINTY_UNKNOWN, 0
        if self.sync is None:
            status |= hb.CLOCK_EXTERNAL | hb.CLOCK_SYNCED
        elif self.sync.estimator.estimate is not None:
            est = self.sync.estimator.estimate
            status |= hb.CLOCK_SYNCED
            off, unc, drift = est.offset_at(now), int(round(est.uncertainty_ns)), int(round(est.drift_ppm * 1000))
        s = self.stats
        return self.link.heartbeat(status=status, frames_captured=s.frames_captured, frames_dropped=s.frames_dropped,
                                   send_errors=s.send_errors, clock_offset_ns=off, clock_uncertainty_ns=unc,
                                   drift_ppb=drift, temperature_c=read_temperature(), station_ns=now)

    def to_server(self, t_local: int) -> int | None:
        """Station-clock capture time -> server clock; None while unsynced."""
        if self.sync is None:
            return t_local
        est = self.sync.estimator.estimate
        return None if est is None else est.to_server(t_local)

    def streaming(self, now_local: int) -> bool:
        t = self.to_server(now_local)
        return self.registered and t is not None and self.start_ns is not None and t >= self.start_ns

    # ------------------------------------------------------------ capture

    def _open_camera(self) -> None:
        self.source.open()
        if self.detector is None or self._size != (self.source.width, self.source.height):
            w, h = int(self.source.width), int(self.source.height)
            self.detector = Detector(self.cfg.detector, build_mask(self.cfg, w, h), load_background(self.cfg, w, h))
            self._size = (w, h)
            if self.cfg.background_frames > 0 and not self.cfg.background_path:
                frames = [self.source.read()[0] for _ in range(self.cfg.background_frames)]
                self.detector.set_background(Detector.learn_background(frames))
                log.info("learned a static background from %d frames", len(frames))
        log.info("camera open: %s, %dx%d at %.1f fps", self.source.name, self.source.width, self.source.height,
                 self.source.fps or 0.0)

    def _wait(self, seconds: float) -> None:
        """Sleep while still serving the network (used during camera back-off)."""
        end = time.monotonic() + seconds
        while not self._stop.is_set():
            left = end - time.monotonic()
            if left <= 0:
                return
            try:
                select.select([self.sock], [], [], min(left, 0.05))
            except (OSError, ValueError):
                self._sleep(min(left, 0.05))
            self.service()

    def process(self, image: np.ndarray, t_local: int) -> BlobFrame | None:
        """Detect, stamp and send one captured frame; returns what was sent."""
        self.stats.frames_captured += 1
        seq = self._seq
        self._seq = (self._seq + 1) & 0xFFFFFFFF
        blobs, flags = self.detector.detect(image)
        self._last_image, self._last_blobs, self._last_t = image, blobs, t_local
        if flags & FLAG_TRUNCATED:
            self.stats.truncated_frames += 1
        if len(blobs) > P.MAX_BLOBS_PER_PACKET:  # detector cap is validated <= this; defensive
            blobs, flags = blobs[: P.MAX_BLOBS_PER_PACKET], flags | FLAG_TRUNCATED
        t_server = self.to_server(t_local)
        if not self.registered or t_server is None or self.start_ns is None:
            self.stats.frames_dropped += 1
            return None
        if t_server < self.start_ns:
            self.stats.frames_before_start += 1
            return None
        if self.duration_ns and t_server >= self.start_ns + self.duration_ns:
            self.stats.frames_before_start += 1
            return None
        if self.sync is not None:
            est = self.sync.estimator.estimate
            if est is not self._estimate_seen:
                if self._estimate_seen is not None and (
                    abs(est.offset_at(t_local) - self._estimate_seen.offset_at(t_local)) > self.sync.jump_ns
                ):
                    flags |= FLAG_RESYNC
                self._estimate_seen = est
        frame = BlobFrame(self.cfg.camera_id, seq, t_server, blobs, self.cfg.station_id, flags, 0, self.session)
        if self._send(P.encode_frame(frame, self.cfg.key)):
            self.stats.frames_sent += 1
            return frame
        self.stats.frames_dropped += 1
        return None

    def stop(self) -> None:
        self._stop.set()

    def run(self, max_frames: int | None = None) -> int:
        """Capture until stop() (or max_frames, or a non-looping file ends).
        Returns 0; camera failures are retried, never fatal."""
        first_backoff = min(1.0, self.cfg.retry_max_s)
        backoff = first_backoff
        opened = False
        try:
            while not self._stop.is_set():
                self.service()
                if not opened:
                    try:
                        self._open_camera()
                        opened = True
                    except SourceError as e:
                        self._camera_failed(e, backoff)
                        backoff = min(backoff * 2, self.cfg.retry_max_s)
                        continue
                try:
                    image, t = self.source.read()
                except EndOfStream:
                    log.info("end of %s", self.source.name)
                    break
                except SourceError as e:
                    self.source.close()
                    opened = False
                    self._camera_failed(e, backoff)
                    backoff = min(backoff * 2, self.cfg.retry_max_s)
                    continue
                try:
                    self.process(image, t)
                except ValueError as e:  # frame of the wrong size/type mid-stream: treat as a camera fault
                    self.source.close()
                    opened = False
                    self._camera_failed(SourceError(str(e)), backoff)
                    backoff = min(backoff * 2, self.cfg.retry_max_s)
                    continue
                self.camera_ok = True
                backoff = first_backoff
                if max_frames is not None and self.stats.frames_captured >= max_frames:
                    break
        finally:
            self.source.close()
            if self.registered:
                self._send(P.encode(self.link.bye(), self.cfg.key))
            self.sock.close()
        return 0

    def _camera_failed(self, e: Exception, backoff: float) -> None:
        self.camera_ok = False
        self.stats.camera_failures += 1
        log.warning("camera %d (%s): %s; retrying in %.0f s", self.cfg.camera_id, self.cfg.source.kind, e, backoff)
        self._wait(backoff)
