"""One vehicle's MAVLink link: its endpoint, its sysid, its sender thread.

The server calls Bridge.publish(states) (bridge/mavlink.py) on its asyncio loop at every output
tick. publish only drops the newest state into each vehicle's single-slot
mailbox and pokes the vehicle's thread through a pipe: it never waits on a
socket. The thread owns the link (reads, writes, reconnects), stamps the poses
on an even 1/rate_hz grid of capture time, drops stale or frozen poses,
answers TIMESYNC and sends the HEARTBEAT, origin and home. It also reads what
the autopilot sends back (bridge/backchannel.py: its attitude and gyro for the
identity check and the measured delay, the EKF's state, the origin it reports),
from the vehicle's sysid and the authenticated peer only.

Origin and home: SET_GPS_GLOBAL_ORIGIN, resent every second until the
autopilot reports it back (GPS_GLOBAL_ORIGIN) and every origin_interval_s
after; home with MAV_CMD_DO_SET_HOME (COMMAND_INT: ArduCopter 4.3 and later
has no SET_HOME_POSITION handler), repeated until acknowledged, plus
SET_HOME_POSITION for other autopilots. While an autopilot that talks to us has
not confirmed the origin, no pose goes to it (hold_until_origin): an EKF that
starts on vision before its origin settles centimetres off in height.

MAVLink2 is forced: each link has its own pymavlink v2 MAVLink objects (the
parser in the ardupilotmega dialect, a superset of common) (never
mavutil's process-wide dialect, which switches v1 -> v2 on the first v2
packet and loses a signing setup in the switch): one encodes and signs what we
send, one only parses what we receive. Incoming signatures are checked by
bridge/signing.py (SignatureCheck), not by pymavlink.

Who gets the poses on a udpin endpoint: the configured autopilot_address, or
the address of the newest packet whose signature verifies with the vehicle's
key. Nothing else moves it (config.py refuses udpin with neither).
"""

from __future__ import annotations

import logging
import math
import os
import selectors
import threading
import time
from typing import Callable

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega
from pymavlink.dialects.v20 import common as mavlink2

from bridge.backchannel import MAV_CMD_DO_SET_HOME, MAV_COMP_ID_AUTOPILOT1, Backchannel
from bridge.config import VehicleConfig, pivot_array
from bridge.convert import (
    MAV_FRAME_LOCAL_FRD,
    MAV_FRAME_LOCAL_NED,
    convert_position_only,
    convert_state,
    odometry_fields,
    vision_position_fields,
    vision_speed_fields,
)
from bridge.crossed_link import CrossedLink
from bridge.estimator_delay import jitter_corrected_delay_ms
from bridge.link_stats import LatencyRing, fmt_addr, percentiles_ms
from bridge.signing import MAVLINK2_MAGIC, SignatureCheck, SigningClock
from bridge.stamp_grid import StampGrid
from bridge.transport import Link, LinkDown, make_link
from bridge.vision_gap import GapEvent, VisionGap
from visionpos.logutil import RateLimitedLog
from visionpos.messages import BodyState

log = logging.getLogger("visionpos.bridge")

MAV_COMP_ID_VISUAL_INERTIAL_ODOMETRY = 197
WARN_INTERVAL_S = 10.0  # a repeated warning (same kind) at most this often, with the count held back
ORIGIN_UNCONFIRMED_INTERVAL_NS = 1_000_000_000  # origin resend period until the autopilot reports it back
GCS_SYSID = 255
STATUSTEXT_MIN_INTERVAL_NS = 1_000_000_000  # our STATUSTEXTs to the autopilot: at most one a second
RX_BAD_WARN = 20  # undecodable packets before the log says so

COUNTERS = (
    "sent",  # pose messages (VISION_POSITION_ESTIMATE or ODOMETRY) handed to the link
    "sent_speed",  # VISION_SPEED_ESTIMATE
    "heartbeats",
    "origin_sent",
    "superseded",  # a newer state replaced one the sender had not taken yet
    "rate_limited",  # no stamp due yet: the next grid point is less than the stamp age before the tick
    "frame_too_old",  # a stamp was due but the tick's newest frame is older than the next grid point
    "frozen",  # capture_ns not newer than the last sent: never resent
    "not_tracked",
    "dropped_stale",  # older than max_age_ms when the sender took it
    "no_link",  # link down or (udpin) no autopilot heard yet
    "held_for_origin",  # the autopilot is heard but has not confirmed the origin yet (hold_until_origin)
    "held_identity",  # the identity check found these poses are not this vehicle's (identity_check: stop)
    "held_crossed",  # another autopilot (an authenticated sysid not this vehicle's) answers on this link
    "crossed",  # such episodes: swapped endpoints (two radios' ports exchanged) or a wrong vehicles[].sysid
    "home_sent",
    "tx_dropped",  # stream buffer full (slow serial)
    "link_errors",
    "reconnects",
    "timesync_answered",
    "rx_packets",
    "rx_bad",  # CRC / framing errors
    "rx_foreign",  # from another sysid: ignored, not answered, not learned as peer
    "rx_gcs",  # of them, a ground station's (sysid 255, or one whose HEARTBEAT says GCS) the autopilot forwards
    "rx_accepted",  # passed every check and went to the back-channel
    "rx_unsigned",  # signed link: an unsigned (or MAVLink1) packet as the vehicle: dropped
    "rx_bad_signature",  # signed link: signature does not verify with the key: dropped
    "rx_replayed",  # signed link: timestamp not newer than its stream's last (or a stale new stream): dropped
    "rx_wrong_source",  # udpin with autopilot_address, or unsigned udpout: from another address, dropped unread
    "peer_refused",  # udpin: a datagram or packet from an address other than the autopilot's that may not move it
)

# SignatureCheck's reasons for refusing a packet -> the counter they go to
REFUSED_COUNTER = {"unsigned": "rx_unsigned", "bad signature": "rx_bad_signature", "replayed": "rx_replayed"}


class VehicleLink:
    """One vehicle's endpoint and sender thread.

    offer(state) is the only call made from the server's loop; everything
    else runs on the vehicle's thread. clock_ns is the server's monotonic
    clock (the one BodyState times are on).
    """

    def __init__(self, cfg: VehicleConfig, clock_ns: Callable[[], int] = time.monotonic_ns):
        self.cfg = cfg
        self.clock_ns = clock_ns
        # usec and TIMESYNC tc1 share one time base: the server clock, or the
        # server clock shifted to the Unix epoch (time_base: epoch)
        self.base_offset_ns = (time.time_ns() - clock_ns()) if cfg.time_base == "epoch" else 0
        # self.mav encodes (and signs) what we send; self._rx only parses, signatures are checked in _verify
        self.mav = mavlink2.MAVLink(self, srcSystem=cfg.sysid, srcComponent=MAV_COMP_ID_VISUAL_INERTIAL_ODOMETRY)
        self._rx = ardupilotmega.MAVLink(None)  # common + ArduPilot's own (EKF_STATUS_REPORT)
        self._rx.robust_parsing = True
        self._key = cfg.signing_key
        self._sign_clock = SigningClock()  # wall time at start, then the monotonic clock (never steps back)
        if self._key is not None:
            s = self.mav.signing
            s.secret_key = self._key
            s.sign_outgoing = True
            s.link_id = cfg.signing_link_id
            s.timestamp = self._sign_clock.base
        self._signed = SignatureCheck(self._key) if self._key is not None else None
        self._warn = RateLimitedLog(log, interval_s=WARN_INTERVAL_S, clock=lambda: clock_ns() * 1e-9)
        self.pivot = pivot_array(cfg)
        self.yaw_offset_rad = math.radians(cfg.yaw_offset_deg)
        self.counters = dict.fromkeys(COUNTERS, 0)
        self.lat_capture = LatencyRing()
        self.lat_stamp = LatencyRing()
        self.lat_bridge = LatencyRing()
        self.link: Link | None = None
        self.last_error = ""
        self.last_rx_ns = 0  # last packet from the vehicle's sysid
        self.local_resets = 0
        self._lock = threading.Lock()
        self._slot: BodyState | None = None
        self._slot_ns = 0
        self._busy = False
        self._last_capture: int | None = None
        self.stamps = StampGrid(cfg.period_ns, int(cfg.rate_tolerance_ms * 1e6),
                                None if cfg.stamp_age_ms is None else int(round(cfg.stamp_age_ms * 1e6)))
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._wake_r, self._wake_w = os.pipe()
        os.set_blocking(self._wake_r, False)
        os.set_blocking(self._wake_w, False)
        self._next_hb = 0
        self._next_origin = 0
        self._origin_done = False
        self._last_write_ok = False
        self._logged_once: set[str] = set()
        self._gcs_sysids: set[int] = set()
        self.sent_times = LatencyRing()  # send times (server clock) for the recent rate
        self._write_ns = 0  # the clock just before the last write to the link
        self.bc = Backchannel(cfg, clock_ns, self.mav, self._send, self._warn.warning, self.base_offset_ns,
                              write_ns=lambda: self._write_ns)
        self._bc_reboots = 0
        self.gap = VisionGap(int(cfg.vision_gap_s * 1e9))
        self.not_sent_why = "no state from the server"  # the last reason a pose was not sent (for a gap)
        self._statustext_ns = -STATUSTEXT_MIN_INTERVAL_NS
        self.statustexts_sent = 0
        self._gap_told = False  # the autopilot was told of the current gap
        self.cross = CrossedLink(cfg.name, cfg.sysid, self._key)  # another of our autopilots on this link
        self.held_unconfirmed = 0  # states the Bridge held: armed on a pad binding its motion has not confirmed
        # with several vehicles, the Bridge's one reset counter for all (Bridge.publish): a pose that reaches another
        # autopilot (a crossed link) carries the counter it already has, so its EKF gates the jump, not resets to it
        self.reset_shared: int | None = None

    # ---------------------------------------------------------------- server side
    def offer(self, state: BodyState) -> None:
        """Put the newest state in the mailbox (O(1), never blocks)."""
        now = self.clock_ns()
        with self._lock:
            if self._slot is not None:
                self.counters["superseded"] += 1
            self._slot = state
            self._slot_ns = now
        try:
            os.write(self._wake_w, b"\0")
        except (BlockingIOError, OSError):
            pass  # pipe full: the thread is awake anyway

    def pending(self) -> bool:
        """True while the mailbox holds a state or the thread is handling one."""
        with self._lock:
            return self._slot is not None or self._busy

    def reset(self) -> None:
        """Count a discontinuity the bridge makes itself (origin or alignment change)."""
        self.local_resets += 1

    # ---------------------------------------------------------------- lifecycle
    def start(self) -> None:
        if self._thread is not None:
            return
        self._announce()
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name=f"mavlink-{self.cfg.name}", daemon=True)
        self._thread.start()

    def close(self, timeout_s: float = 2.0) -> None:
        self._stop.set()
        try:
            os.write(self._wake_w, b"\0")
        except OSError:
            pass
        if self._thread is not None:
            self._thread.join(timeout_s)
            self._thread = None
        fds = (self._wake_r, self._wake_w)
        self._wake_r = self._wake_w = -1  # before closing, so a late offer() cannot hit a reused fd
        for fd in fds:
            if fd >= 0:
                os.close(fd)

    # ---------------------------------------------------------------- thread
    def _run(self) -> None:
        sel = selectors.DefaultSelector()
        sel.register(self._wake_r, selectors.EVENT_READ, "wake")
        backoff = self.cfg.reconnect_min_s
        next_open = 0
        registered_mask = 0
        try:
            while not self._stop.is_set():
                now = self.clock_ns()
                if self.link is None and now >= next_open:
                    link = make_link(self.cfg.endpoint, self.cfg.autopilot_address)
                    try:
                        link.open()
                    except LinkDown as e:
                        if str(e) != self.last_error:
                            log.warning("vehicle %s: %s; retrying every %.1f-%.1f s", self.cfg.name, e,
                                        self.cfg.reconnect_min_s, self.cfg.reconnect_max_s)
                        self.last_error = str(e)
                        self.counters["link_errors"] += 1
                        next_open = now + int(backoff * 1e9)
                        backoff = min(backoff * 2, self.cfg.reconnect_max_s)
                    else:
                        self.link = link
                        backoff = self.cfg.reconnect_min_s
                        registered_mask = selectors.EVENT_READ
                        sel.register(link.fileno(), registered_mask, "link")
                        self._on_link_up()
                deadlines = [self._next_hb]
                if self.link is None:
                    deadlines.append(next_open)
                if self.cfg.origin is not None and not self._origin_done:
                    deadlines.append(self._next_origin)
                gap_due = self.gap.deadline_ns()
                if gap_due is not None:
                    deadlines.append(gap_due)
                timeout = min(max(0.0, (min(deadlines) - now) * 1e-9), 0.5)
                if self.link is not None:
                    want = selectors.EVENT_READ | (selectors.EVENT_WRITE if self.link.wants_write() else 0)
                    if want != registered_mask:
                        sel.modify(self.link.fileno(), want, "link")
                        registered_mask = want
                for key, mask in sel.select(timeout):
                    if key.data == "wake":
                        try:
                            while os.read(self._wake_r, 4096):
                                pass
                        except BlockingIOError:
                            pass
                    elif self.link is not None:
                        try:
                            if mask & selectors.EVENT_READ:
                                self._on_readable()
                            if mask & selectors.EVENT_WRITE and self.link is not None:
                                self.link.flush()
                        except LinkDown as e:
                            self._link_down(sel, e)
                            next_open = self.clock_ns() + int(backoff * 1e9)
                try:
                    self._service()
                except LinkDown as e:
                    self._link_down(sel, e)
                    next_open = self.clock_ns() + int(backoff * 1e9)
        finally:
            if self.link is not None:
                self.link.close()
                self.link = None
            sel.close()

    def _link_down(self, sel: selectors.BaseSelector, e: LinkDown) -> None:
        log.warning("vehicle %s: link lost: %s; reconnecting", self.cfg.name, e)
        self.last_error = str(e)
        self.counters["link_errors"] += 1
        self.counters["reconnects"] += 1
        try:
            sel.unregister(self.link.fileno())
        except (KeyError, ValueError, OSError):
            pass
        self.link.close()
        self.link = None

    def _on_link_up(self) -> None:
        log.info("vehicle %s: link %s open", self.cfg.name, self.cfg.endpoint)
        self.last_error = ""
        self._next_hb = self.clock_ns()
        self._origin_done = False
        self._next_origin = self.clock_ns()
        self.bc.on_link_up(self.clock_ns())

    def _announce(self) -> None:
        """Say once at start who the poses go to and how that is authenticated."""
        cfg = self.cfg
        if cfg.endpoint.kind == "udpin" and cfg.autopilot_address is not None:
            log.info("vehicle %s: %s: poses go to %s:%d only; datagrams from anywhere else are dropped",
                     cfg.name, cfg.endpoint, *cfg.autopilot_address)
        elif cfg.endpoint.kind == "udpin":
            log.info("vehicle %s: %s: nothing is sent until a packet signed with the vehicle's key arrives; "
                     "poses then go to its address", cfg.name, cfg.endpoint)
        if self._key is None:
            log.warning("vehicle %s: MAVLink link %s is not signed: the autopilot cannot tell our poses from "
                        "forged ones; set up signing (docs/autopilot-setup.md, Signing)", cfg.name, cfg.endpoint)

    def _log_once(self, kind: str, msg: str, *args, level: int = logging.WARNING) -> None:
        if kind not in self._logged_once:
            self._logged_once.add(kind)
            log.log(level, msg, *args)

    def _is_gcs(self, m, sysid: int) -> bool:
        """A ground station's packet: sysid 255 (MAVLink's convention for a GCS; `visionpos sitl`'s own link,
        which SITL forwards), or a system whose HEARTBEAT said MAV_TYPE_GCS (remembered: its other messages)."""
        if m.get_type() == "HEARTBEAT" and m.type == mavlink2.MAV_TYPE_GCS:
            self._gcs_sysids.add(sysid)
        return sysid == GCS_SYSID or sysid in self._gcs_sysids

    def _peer_known(self) -> bool:
        return self.link is not None and self.link.peer is not None

    def _on_readable(self) -> None:
        c = self.counters
        link = self.link
        rx = self._rx
        learning = link.kind == "udpin" and not link.fixed
        for data, addr in link.read():
            if link.kind == "udpout" and self._key is None and addr != link.peer:
                # unsigned: only the address we send to speaks for the autopilot (what it says back can stop
                # the poses or confirm an origin)
                c["rx_wrong_source"] += 1
                self._warn.warning("wrong_source", "vehicle %s: dropped a datagram from %s: the autopilot is "
                                   "at %s on this unsigned link", self.cfg.name, fmt_addr(addr), fmt_addr(link.peer))
                continue
            if link.kind == "udpin" and addr != link.peer:
                if not learning:
                    c["rx_wrong_source"] += 1
                    c["peer_refused"] += 1
                    self._warn.warning("wrong_source", "vehicle %s: dropped a datagram from %s:%d: the autopilot "
                                       "is configured at %s:%d", self.cfg.name, *addr, *link.peer)
                    continue
            msgs = rx.parse_buffer(data) or []
            if rx.buf_len():  # a datagram holds whole packets: never let a fragment join the next sender's
                rx.buf = bytearray()
                rx.buf_index = 0
                rx.expected_length = mavlink2.HEADER_LEN_V1 + 2
            for m in msgs:
                if m.get_type() == "BAD_DATA":
                    c["rx_bad"] += 1
                    if c["rx_bad"] >= RX_BAD_WARN:  # a few at connect are normal (a stream joined mid-packet)
                        self._log_once("rx_bad", "vehicle %s: bytes on the link %s that are not MAVLink packets "
                                       "(counted in rx_bad, ignored; logged once): check the autopilot port's "
                                       "baud rate and that it speaks MAVLink2 (SERIALn_PROTOCOL=2)",
                                       self.cfg.name, self.cfg.endpoint)
                    continue
                c["rx_packets"] += 1
                buf = m.get_msgbuf()
                v2 = buf[0] == MAVLINK2_MAGIC
                sysid, compid = (buf[5], buf[6]) if v2 else (buf[3], buf[4])
                if sysid != self.cfg.sysid:
                    c["rx_foreign"] += 1
                    if self._is_gcs(m, sysid):
                        c["rx_gcs"] += 1  # the autopilot routes its GCS's traffic to every port: normal
                        self._log_once(f"gcs{sysid}", "vehicle %s: the autopilot forwards a ground station's "
                                       "packets (sysid %d) on this link; ignored (counted in rx_gcs)",
                                       self.cfg.name, sysid, level=logging.INFO)
                        continue
                    if compid == MAV_COMP_ID_AUTOPILOT1 and (addr is None or addr == link.peer) and \
                            self.cross.verified(buf, v2, sysid, compid):
                        c["crossed"] += self.cross.heard(sysid, addr, self.cfg.endpoint, self.clock_ns())
                        continue
                    self._log_once("rx_foreign", "vehicle %s: packets from sysid %d on the link of sysid %d are "
                                   "ignored (counted in rx_foreign; logged once): if that is this vehicle's "
                                   "autopilot, set its sysid in the vehicles section (or SYSID_THISMAV / "
                                   "MAV_SYS_ID on the autopilot)", self.cfg.name, sysid, self.cfg.sysid)
                    continue
                ts, newest_before = -1, (self._signed.newest_ts if self._signed is not None else -1)
                if self._key is not None:
                    ts = self._verify(buf, v2, compid, addr)
                    if ts < 0:
                        continue
                if learning and addr != link.peer:
                    if ts <= newest_before:
                        c["peer_refused"] += 1  # genuine but older than what we have had: a replay elsewhere
                        self._warn.warning("stale", "vehicle %s: a signed packet from %s:%d is older than the "
                                           "autopilot's newest; not moving the poses there", self.cfg.name, *addr)
                        continue
                    self._learn_peer(addr)
                now = self.last_rx_ns = self.clock_ns()
                c["rx_accepted"] += 1
                if m.get_type() == "TIMESYNC":
                    if m.tc1 == 0:
                        if self.cfg.answers_timesync:
                            c["timesync_answered"] += 1  # before sending: the reply can arrive before we return
                            self._send(self.mav.timesync_encode(self.now_base_ns(), m.ts1))
                            self.bc.on_timesync_request()
                    else:
                        self.bc.on_timesync_reply(m.ts1, m.tc1, now)
                    continue
                self.bc.handle(m, compid, now)

    def crossed(self, now: int | None = None) -> int | None:
        """The sysid of another autopilot answering on this link while it is crossed (bridge/crossed_link.py)."""
        return self.cross.current(self.clock_ns() if now is None else now, self.last_rx_ns)

    def _verify(self, buf: bytearray, v2: bool, compid: int, addr: tuple | None) -> int:
        """The packet's signing timestamp if it is signed with the vehicle's key and newer than the last
        on its stream (link id, component); else -1, counted. State changes only for a packet that passes."""
        ts, reason = self._signed.check(buf, v2, compid)
        if ts >= 0:
            return ts
        self.counters[REFUSED_COUNTER[reason]] += 1
        if self.link is not None and addr != self.link.peer:
            self.counters["peer_refused"] += 1
            self._warn.warning(reason, "vehicle %s: refused a packet as sysid %d from %s (%s); the poses go "
                               "only to an autopilot whose packets verify with the vehicle's key",
                               self.cfg.name, self.cfg.sysid, fmt_addr(addr), reason)
        return -1

    def _learn_peer(self, addr: tuple) -> None:
        old = self.link.peer
        self.link.peer = addr
        if old is not None:
            self.counters["reconnects"] += 1
            log.warning("vehicle %s: autopilot now answers from %s:%d (was %s:%d)", self.cfg.name, *addr, *old)
        else:
            log.info("vehicle %s: autopilot heard from %s:%d", self.cfg.name, *addr)
        self._next_hb = self.clock_ns()
        self._origin_done = False
        self._next_origin = self.clock_ns()

    def estimator(self) -> str | None:
        """Whose estimator takes the poses: the `autopilot` setting, or (auto) what its HEARTBEAT says; None
        while unknown (ArduPilot's rules then)."""
        return self.cfg.autopilot if self.cfg.autopilot != "auto" else self.bc.autopilot

    def now_base_ns(self) -> int:
        return self.clock_ns() + self.base_offset_ns

    def _service(self) -> None:
        now = self.clock_ns()
        event = self.gap.check(now)
        if event is not None:
            self._say_gap(event)
        if self._peer_known():
            if now >= self._next_hb:
                self._send_heartbeat()
                self._next_hb = now + int(1e9 / self.cfg.heartbeat_hz)
            bc = self.bc
            if bc.reboots != self._bc_reboots:  # a rebooted autopilot has lost its origin and home
                self._bc_reboots = bc.reboots
                self._origin_done = False
                self._next_origin = now
            if self.cfg.origin is not None and not self._origin_done and now >= self._next_origin:
                self._send_origin()
                if not bc.origin_confirmed:
                    self._next_origin = now + ORIGIN_UNCONFIRMED_INTERVAL_NS
                elif self.cfg.origin_interval_s > 0:
                    self._next_origin = now + int(self.cfg.origin_interval_s * 1e9)
                else:
                    self._origin_done = True
            bc.service(now)
        else:
            self._next_hb = max(self._next_hb, now + int(1e9 / self.cfg.heartbeat_hz))
        with self._lock:
            st, offered = self._slot, self._slot_ns
            self._slot = None
            self._busy = st is not None
        if st is None:
            return
        try:
            self._handle_state(st, offered, now)
        finally:
            with self._lock:
                self._busy = False

    def _handle_state(self, st: BodyState, offered_ns: int, now: int) -> None:
        c = self.counters
        if not st.tracked:
            c["not_tracked"] += 1
            self.not_sent_why = "the body is not tracked"
            return
        self.stamps.observe(st.time_ns, st.capture_ns)
        last = self._last_capture
        if last is not None and st.capture_ns <= last:
            c["frozen"] += 1
            return
        stamp = (self.stamps.due_on_captures(st.capture_ns) if self.estimator() == "px4"
                 else self.stamps.due(st.time_ns, st.capture_ns))
        if stamp is None:
            c["rate_limited" if self.stamps.why == "rate" else "frame_too_old"] += 1
            return
        if now - st.capture_ns > self.cfg.max_age_ms * 1e6:
            c["dropped_stale"] += 1
            self.not_sent_why = f"the poses reach the bridge over max_age_ms ({self.cfg.max_age_ms:g} ms) old"
            return
        bc = self.bc
        if self.cfg.position_only:  # a point body: no attitude to send or to check
            conv = convert_position_only(st, self.yaw_offset_rad, at_ns=stamp)
        else:
            conv = convert_state(st, self.pivot, self.yaw_offset_rad, at_ns=stamp)
            euler, rate = conv.euler, conv.angular_velocity_frd
            bc.on_optical(stamp, euler[0], euler[1], rate, conv.quaternion_ned_frd)  # also while held
        if not self._peer_known():
            c["no_link"] += 1
            self.not_sent_why = "the link is down"
            return
        if (crossed := self.crossed(now)) is not None:
            c["held_crossed"] += 1
            self.not_sent_why = f"stopped: sysid {crossed}'s autopilot answers on this link"
            return
        if bc.blocks:
            c["held_identity"] += 1
            self.not_sent_why = "stopped: identity mismatch"
            return
        if bc.holds_for_origin(now):
            c["held_for_origin"] += 1
            self.not_sent_why = "held until the autopilot confirms its origin"
            self._warn.warning("origin_wait", "vehicle %s: holding the poses until the autopilot confirms its "
                               "origin (GPS_GLOBAL_ORIGIN); %s", self.cfg.name,
                               "resending it every second" + (
                                   f", for at most {self.cfg.origin_confirm_timeout_s:.0f} s"
                                   if self.cfg.origin_confirm_timeout_s > 0 else ""))
            return
        usec = (stamp + self.base_offset_ns) // 1000
        shared = self.reset_shared
        reset = (shared if shared is not None else int(st.reset_counter) + self.local_resets) % 256
        if self.cfg.message == "odometry":
            # PX4 never aligns its yaw to LOCAL_FRD (no arming); ArduPilot takes LOCAL_FRD only
            frame = MAV_FRAME_LOCAL_NED if self.estimator() == "px4" else MAV_FRAME_LOCAL_FRD
            ok = self._send(self.mav.odometry_encode(**odometry_fields(conv, usec, reset, self.cfg.quality, frame)))
            t_write = self._write_ns
        else:
            ok = self._send(self.mav.vision_position_estimate_encode(**vision_position_fields(conv, usec, reset)))
            t_write = self._write_ns
            if ok and self.cfg.vision_speed:
                if self._send(self.mav.vision_speed_estimate_encode(**vision_speed_fields(conv, usec, reset))):
                    c["sent_speed"] += 1
        if ok:
            self._last_capture = st.capture_ns
            self.stamps.sent(stamp, st.time_ns)
            c["sent"] += 1
            t = self.clock_ns()
            event = self.gap.on_sent(t)
            if event is not None:
                self._say_gap(event)
            bc.on_sent(t_write, stamp)
            self.sent_times.add(t)
            self.lat_capture.add(t - st.capture_ns)
            self.lat_stamp.add(t - stamp)
            self.lat_bridge.add(t - offered_ns)

    def _send(self, msg) -> bool:
        self._last_write_ok = False
        if self._key is not None:
            # never behind the clock nor the autopilot (it refuses a new stream over a minute behind its own)
            s = self.mav.signing
            s.timestamp = max(s.timestamp, self._sign_clock.now(), self._signed.newest_ts + 1)
        self.mav.send(msg)
        return self._last_write_ok

    # mav.send() writes here
    def write(self, buf: bytes) -> None:
        self._write_ns = self.clock_ns()
        ok = self.link is not None and self.link.write(buf)
        if not ok:
            self.counters["tx_dropped" if self.link is not None and self.link.peer is not None else "no_link"] += 1
        self._last_write_ok = bool(ok)

    def _say_gap(self, e: GapEvent) -> None:
        """A vision gap's event, loudly: the log (WARNING), and a STATUSTEXT to the autopilot (which routes it to its
        ground station) when the link is up, at most one a second."""
        name = self.cfg.name
        if e.kind == "resumed":
            self._warn.warning("gap_resumed", "vision resumed: vehicle %s: poses go again after a %.2f s gap", name,
                               e.gap_s)
            if self._gap_told:  # the autopilot heard of the gap: it hears of its end too, whatever the rate
                self._statustext(mavlink2.MAV_SEVERITY_NOTICE, f"visionpos: vision resumed after {e.gap_s:.1f}s")
            self._gap_told = False
            return
        # gaps that come and go: one line per kind every WARN_INTERVAL_S, with the count held back
        self._warn.warning(f"gap_{e.kind}", "VISION %s: vehicle %s: no pose sent for %.2f s (vision_gap_s %g): %s; "
                           "the autopilot is on its IMU alone and drifting", "LOST" if e.kind == "lost" else
                           "STILL LOST", name, e.gap_s, self.cfg.vision_gap_s, self.not_sent_why)
        # gaps coming and going: at most one warning a STATUSTEXT_MIN_INTERVAL_NS to the autopilot
        if self.clock_ns() - self._statustext_ns >= STATUSTEXT_MIN_INTERVAL_NS:
            self._gap_told = self._statustext(mavlink2.MAV_SEVERITY_WARNING,
                                              f"visionpos: NO VISION for {e.gap_s:.1f}s") or self._gap_told

    def _statustext(self, severity: int, text: str) -> bool:
        """STATUSTEXT (50 characters at most) to the autopilot, which routes it to its GCS; False: link down."""
        if not self._peer_known() or self.cross.other is not None:  # crossed: it would reach another autopilot
            return False
        self._statustext_ns = self.clock_ns()
        ok = self._send(self.mav.statustext_encode(severity, text[:50].encode()))
        self.statustexts_sent += int(ok)
        return ok

    def _send_heartbeat(self) -> None:
        tracked_recently = self._last_capture is not None and self.clock_ns() - self._last_capture < 1e9
        status = mavlink2.MAV_STATE_ACTIVE if tracked_recently else mavlink2.MAV_STATE_STANDBY
        if self._send(self.mav.heartbeat_encode(
            mavlink2.MAV_TYPE_ONBOARD_CONTROLLER, mavlink2.MAV_AUTOPILOT_INVALID, 0, 0, status
        )):
            self.counters["heartbeats"] += 1

    def _send_origin(self) -> None:
        o = self.cfg.origin
        lat, lon, alt = int(round(o.lat * 1e7)), int(round(o.lon * 1e7)), int(round(o.alt * 1000))
        t_usec = self.now_base_ns() // 1000
        bc = self.bc
        ok = self._send(self.mav.set_gps_global_origin_encode(self.cfg.sysid, lat, lon, alt, t_usec))
        if ok:
            self.counters["origin_sent"] += 1
        if not bc.origin_confirmed:
            bc.request_origin()
        if self.cfg.set_home and bc.home_acked and bc.home_reported is None:
            bc.request_home()  # read it back: within 1 cm of the origin (HOME_TOLERANCE_M)
        if self.cfg.set_home and not bc.home_acked:
            # DO_SET_HOME needs the origin first on ArduPilot (refused before): repeated until acknowledged
            if self._send(self.mav.command_int_encode(
                self.cfg.sysid, MAV_COMP_ID_AUTOPILOT1, mavlink2.MAV_FRAME_GLOBAL, MAV_CMD_DO_SET_HOME, 0, 0,
                0.0, 0.0, 0.0, float("nan"), lat, lon, float(o.alt),
            )):
                self.counters["home_sent"] += 1
            if bc.autopilot != "ardupilot":
                self._send(self.mav.set_home_position_encode(
                    self.cfg.sysid, lat, lon, alt, 0.0, 0.0, 0.0, [1.0, 0.0, 0.0, 0.0], 0.0, 0.0, 0.0, t_usec))

    # ---------------------------------------------------------------- reporting
    def stats(self) -> dict:
        out: dict = dict(self.counters)
        lc, ls, lb = self.lat_capture.values(), self.lat_stamp.values(), self.lat_bridge.values()
        lc_p, lb_p = (percentiles_ms(v, (50, 99)) for v in (lc, lb))
        ls_p = percentiles_ms(ls, (50, 99, 2))
        out.update(
            sysid=self.cfg.sysid,
            body=self.cfg.body,
            endpoint=str(self.cfg.endpoint),
            message=self.cfg.message,
            rate_hz=self.cfg.rate_hz,
            link_up=self._peer_known(),
            peer=(fmt_addr(self.link.peer) if self._peer_known() else None),
            signed=self._key is not None,
            last_error=self.last_error,
            autopilot_heard_s_ago=((self.clock_ns() - self.last_rx_ns) * 1e-9 if self.last_rx_ns else None),
            latency_capture_ms_p50=lc_p[0],
            latency_capture_ms_p99=lc_p[1],
            latency_stamp_ms_p2=ls_p[2],
            latency_stamp_ms_jitter_min=jitter_corrected_delay_ms(ls * 1e-6) if len(ls) else math.nan,
            latency_stamp_ms_p50=ls_p[0],
            latency_stamp_ms_mean=float(ls.mean()) * 1e-6 if len(ls) else math.nan,
            latency_stamp_ms_p99=ls_p[1],
            stamp_age_ms=(self.stamps.age_ns * 1e-6 if self.stamps.age_ns is not None else math.nan),
            latency_bridge_ms_p50=lb_p[0],
            latency_bridge_ms_p99=lb_p[1],
            latency_samples=len(lc),
            rate_hz_recent=self._recent_rate_hz(),
        )
        out.update(self.bc.snapshot(self.clock_ns()))
        out["vision_gap"] = self.vision_gap_state()
        return out

    def vision_gap_state(self) -> dict:
        """The vision gap (bridge/vision_gap.py): state 'ok' | 'gap' | 'not started', since_last_pose_s, gaps,
        longest_s, last_gap_s, threshold_s, why (the last reason a pose was not sent), statustexts_sent."""
        st = self.gap.state(self.clock_ns())
        st["why"] = self.not_sent_why if st["state"] == "gap" else None
        st["statustexts_sent"] = self.statustexts_sent
        return st

    def _recent_rate_hz(self, window_ns: int = 2_000_000_000) -> float:
        t = self.sent_times.values()
        now = self.clock_ns()
        return float(np.count_nonzero(t > now - window_ns)) / (window_ns * 1e-9)

    def health(self) -> dict:
        """One structured snapshot of this vehicle's health (for a console or the logs): link, what was sent
        and at what rate, TIMESYNC round trip, signing, the EKF's state, the identity check, the measured
        delay, the origin. Read from any thread (values may be a few packets apart)."""
        now = self.clock_ns()
        c = self.counters
        bc = self.bc.snapshot(now)
        return {
            "vehicle": self.cfg.name, "body": self.cfg.body, "sysid": self.cfg.sysid,
            "link": {"endpoint": str(self.cfg.endpoint), "up": self._peer_known(),
                     "peer": fmt_addr(self.link.peer) if self._peer_known() else None,
                     "last_error": self.last_error or None, "signed": self._key is not None,
                     "autopilot": bc["autopilot"], "autopilot_heard_s_ago": bc["autopilot_heard_s_ago"],
                     "reboots": bc["reboots"], "timesync_rtt_ms": bc["timesync_rtt_ms"],
                     "rx_accepted": c["rx_accepted"], "rx_refused": c["rx_bad"] + c["rx_foreign"] + c["rx_unsigned"]
                     + c["rx_bad_signature"] + c["rx_replayed"] + c["rx_wrong_source"]},
            "output": {"message": self.cfg.message, "sent": c["sent"], "rate_hz": self._recent_rate_hz(),
                       "rate_hz_configured": self.cfg.rate_hz, "held_for_origin": c["held_for_origin"],
                       "held_identity": c["held_identity"], "held_crossed": c["held_crossed"],
                       "latency_capture_ms_p50": percentiles_ms(self.lat_capture.values(), (50,))[0]},
            "sending": self.sending_state(now),
            "ekf": {"state": bc["ekf"], "detail": bc["ekf_detail"], "flags": bc["ekf_flags"],
                    "test_ratios": bc["ekf_test_ratios"], "ext_nav_statustext": bc["ext_nav_statustext"],
                    "statustexts": bc["statustexts"]},
            "identity": {"state": bc["identity"], "detail": bc["identity_detail"],
                         "statistic": bc["identity_statistic"], "action": self.cfg.identity_check,
                         "tripped_after_s": bc["identity_tripped_after_s"]},
            "delay": {"measured_ms": bc["delay_ms"], "detail": bc["delay_detail"], "advice": bc["delay_advice"],
                      "param": bc["delay_param"], "advised_ms": bc["delay_advised_ms"],
                      "param_set": bc["delay_param_set"], "horizon_param": bc["delay_horizon_param"],
                      "horizon_ms": bc["delay_horizon_ms"]},
            "vision_gap": self.vision_gap_state(),
            "crossed": {"sysid": self.crossed(now), "episodes": c["crossed"]},
            "origin": {"state": bc["origin"], "home_acked": bc["home_acked"], "home_reported": bc["home_reported"],
                       "home_error_m": bc["home_error_m"]},
        }

    def sending_state(self, now: int | None = None) -> str:
        """'sending', 'no link', 'stopped: sysid N's autopilot answers on this link ...' (a crossed link),
        'stopped: identity mismatch', 'waiting for the origin' or 'idle'."""
        now = self.clock_ns() if now is None else now
        if not self._peer_known():
            return "no link"
        if (crossed := self.crossed(now)) is not None:
            return f"stopped: sysid {crossed}'s autopilot answers on this link (endpoints swapped?)"
        if self.bc.blocks:
            return "stopped: identity mismatch"
        if self.bc.holds_for_origin(now):
            return "waiting for the autopilot to confirm its origin"
        return "sending" if self._recent_rate_hz() > 0 else "idle"

    def status_part(self, with_name: bool = True) -> str:
        """The vehicle's part of a status line: what is sent, and what the autopilot says about it."""
        now = self.clock_ns()
        bc = self.bc
        ekf, _ = bc.ekf_state(now)
        parts = [(f"{self.cfg.name}: " if with_name else "") + f"{self.sending_state(now)} "
                 f"{self._recent_rate_hz():.0f}Hz"]
        if self.gap.in_gap and self.gap.last_sent_ns is not None:
            parts[0] = (f"{self.cfg.name}: " if with_name else "") + (
                f"VISION GAP {(now - self.gap.last_sent_ns) * 1e-9:.1f}s ({self.not_sent_why})")
        if bc.autopilot is None:
            parts.append("autopilot silent")
        else:
            parts.append(f"EKF {ekf}")
            parts.append(f"identity {bc.identity}")
            if bc.delay_ms is not None:
                parts.append(f"delay {bc.delay_ms:.1f}ms")
        if self.cfg.origin is not None:
            parts.append(f"origin {bc.origin_state(now)}")
        return ", ".join(parts)
