"""The station side of the protocol's registration, freshness and reply checks (docs/protocol.md).

Pure: no sockets, no clock reads. `StationLink` builds every station -> server
control message (HELLO, HEARTBEAT, SYNC_REQUEST, BYE) with the session's next
control counter and the server's cookie, and decides whether a reply may be
believed: it must come from the server address the station sends to, name
this station, camera and session, and echo a counter the station sent recently
that is newer than the last accepted reply's. Anything else is ignored and
counted, so an unsigned or replayed UNKNOWN_SESSION cannot knock a station out.
Server commands (IMAGE_REQUEST, MASK_UPDATE) pass `believe_command`: the same source and
names, an echo of a recent counter, and (echo, request_id) newer than the last command's, so
a captured command replayed later does nothing.
Used by stations/agent.py and the demo's simulated stations (app/demo.py).
"""

from __future__ import annotations

import secrets
from collections import deque
from enum import Enum
from typing import Any

from visionpos import protocol as P

RECENT_COUNTERS = 64  # sent counters a reply may echo (replies to older requests are ignored)
_U32 = 0xFFFFFFFF


class LinkEvent(Enum):
    """What a believed HelloAck means for the station."""

    REGISTERED = "registered"  # OK to a HELLO: stream from start_ns
    KEPT = "kept"  # OK while registered (keep-alive)
    CHALLENGED = "challenged"  # the cookie to put in the next HELLO arrived
    LOST = "lost"  # UNKNOWN_SESSION: the server does not know this session (restart, new address)
    REJECTED = "rejected"  # the server refuses this camera: fix the configs
    RESYNC = "resync"  # keep streaming, but restart clock sync (the server saw clock jumps)
    IGNORED = "ignored"  # an unknown status


class StationLink:
    """Registration state and message building for one camera of one station process."""

    def __init__(self, station_id: int, camera_id: int, session: int | None = None):
        self.station_id, self.camera_id = int(station_id), int(camera_id)
        self.session = int(session) if session else (secrets.randbits(32) or 1)
        self.counter = 0
        self.cookie = P.NO_COOKIE
        self.registered = False
        self.rejected = False
        self.start_ns: int | None = None
        self.duration_ns = 0
        self.refused_replies = 0  # replies not believed (wrong source, session, stale echo)
        self._sent: deque[int] = deque(maxlen=RECENT_COUNTERS)
        self._last_echo: int | None = None
        self._cookie_sent = P.NO_COOKIE
        self._last_command: tuple[int, int] | None = None  # (echo, request_id) of the newest believed command

    def _next(self) -> int:
        self.counter = (self.counter + 1) & _U32
        self._sent.append(self.counter)
        return self.counter

    # ------------------------------------------------------------ station -> server

    def hello(self, width: int, height: int, fps: float, camera_kind: str = "unknown", camera_name: str = "",
              software: str = "", timebase: int = P.Timebase.SERVER) -> P.Hello:
        self._cookie_sent = self.cookie
        return P.Hello(self.station_id, self.camera_id, self.session, int(width), int(height), float(fps),
                       camera_kind, camera_name, software, timebase, self._next(), self.cookie)

    def heartbeat(self, **fields: Any) -> P.Heartbeat:
        """fields: the Heartbeat's health fields (status, frames_captured, clock_offset_ns, ...)."""
        return P.Heartbeat(self.station_id, self.camera_id, self._next(), self.session, **fields)

    def sync_request(self, t1_ns: int) -> P.SyncRequest:
        return P.SyncRequest(self.station_id, self.camera_id, int(t1_ns), self._next(), self.session)

    def bye(self) -> P.Bye:
        return P.Bye(self.station_id, self.camera_id, self.session, self._next())

    # ------------------------------------------------------------ server -> station

    def believe(self, msg: P.Message, src: Any, server: Any) -> bool:
        """True if `msg` (a decoded HelloAck or SyncReply from `src`) answers one of our recent requests
        from the server we send to; then its echo becomes the newest accepted one."""
        echo = getattr(msg, "echo", None)
        if (echo is None or src != server or msg.station_id != self.station_id or msg.camera_id != self.camera_id
                or msg.session != self.session or echo not in self._sent
                or (self._last_echo is not None and P.seq_delta(echo, self._last_echo) <= 0)):
            self.refused_replies += 1
            return False
        self._last_echo = echo
        return True

    def believe_command(self, msg: P.ImageRequest | P.MaskUpdate, src: Any, server: Any) -> bool:
        """True if a server command comes from the server we send to, names this station, camera and session,
        echoes a counter we sent recently, and is newer than the last believed command (echo first, then the
        server's request id): a replayed or reordered one is refused and counted."""
        if (src != server or msg.station_id != self.station_id or msg.camera_id != self.camera_id
                or msg.session != self.session or msg.echo not in self._sent):
            self.refused_replies += 1
            return False
        last = self._last_command
        if last is not None:
            d_echo = P.seq_delta(msg.echo, last[0])
            if d_echo < 0 or (d_echo == 0 and P.seq_delta(msg.request_id, last[1]) <= 0):
                self.refused_replies += 1
                return False
        self._last_command = (msg.echo, msg.request_id)
        return True

    def on_ack(self, ack: P.HelloAck) -> LinkEvent:
        """A believed HelloAck -> what the station does next."""
        status = ack.status
        if status == P.AckStatus.OK:
            self.start_ns, self.duration_ns = ack.start_ns, ack.duration_ns
            self.rejected = False
            if self.registered:
                return LinkEvent.KEPT
            self.registered = True
            return LinkEvent.REGISTERED
        if status == P.AckStatus.CHALLENGE:
            self.cookie = ack.cookie
            return LinkEvent.CHALLENGED
        if status == P.AckStatus.UNKNOWN_SESSION:
            self.registered = False
            return LinkEvent.LOST
        if status == P.AckStatus.REJECTED:
            self.registered = False
            self.rejected = True
            return LinkEvent.REJECTED
        if status == P.AckStatus.RESYNC:
            self.start_ns, self.duration_ns = ack.start_ns, ack.duration_ns
            return LinkEvent.RESYNC
        return LinkEvent.IGNORED

    @property
    def cookie_is_new(self) -> bool:
        """The cookie differs from the one the last HELLO carried (answer a challenge once, not in a loop)."""
        return self.cookie != self._cookie_sent

    def lost(self) -> None:
        """Back to registration (link timeout)."""
        self.registered = False
