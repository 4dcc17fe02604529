"""Foxglove WebSocket server: the recordings' Foxglove channels live, for Foxglove and Lichtblick.

Off unless the arena has a `foxglove:` section; needs the optional extra (`pip install
visionpos[foxglove]`: foxglove-sdk, Foxglove's maintained server). The channels and their
messages are the recordings' (visionpos/foxglove/channels.py): the transforms, the arena scene
(frusta, floor, world axes) and the camera calibrations, the tracked bodies, the loose markers,
each camera's blobs as image annotations, and the health snapshots and server events as log lines.

publish() and publish_markers() (on the server's loop) only put the newest states or markers in
a one-slot mailbox; the packet tap (each accepted station packet, from Ingest) keeps the newest
frame of each camera, publish_health() the newest snapshot and publish_event() the last
EVENT_BACKLOG events. A sender thread encodes them (the blobs at most rate_hz per camera) and hands
them to the SDK, whose server queues at most `backlog` messages per client and drops the oldest for
a client that does not keep up. Nothing a client does reaches fusion.

Clients: the SDK (0.30) has no client limit and no hook on a connection (its ServerListener hears
subscriptions, not connects, and cannot close a client), so the SDK listens on a free loopback port
and `_ClientGate`, one thread, owns the configured address: it admits `max_clients` connections and
relays their bytes to the SDK, answers the others `HTTP 503` before the WebSocket upgrade, and
drops a connection whose handshake is not answered within `handshake_timeout_s`. The relay holds
at most RELAY_BUFFER_B per direction and client; past that it stops reading for that client, so the
SDK's per-client queue fills and drops that client's oldest messages, and the others are unaffected.
Each cause is logged once a minute at most, with a count.
The gate also reads each upgrade request: the SDK's server accepts only the subprotocol name
`foxglove.sdk.v1`, while clients from before that name (Foxglove Studio, Lichtblick up to 1.21)
offer `foxglove.websocket.v1`, the same protocol under the name of Foxglove's published spec; a
request offering only that name is relayed offering the SDK's, and the SDK's answer names the
client's again (offer_sdk_subprotocol, answer_legacy_subprotocol).
"""

from __future__ import annotations

import logging
import selectors
import socket
import threading
import time
from collections import deque
from dataclasses import dataclass
from typing import Any

import numpy as np

from visionpos import protocol as P
from visionpos.config.arena import ArenaConfig, ConfigError
from visionpos.config.schema import register_section
from visionpos.config.settings import Setting, section
from visionpos.foxglove.channels import FoxgloveChannels
from visionpos.foxglove.protobuf import file_descriptor_set
from visionpos.logutil import RateLimitedLog
from visionpos.messages import BodyState, LoosePoints
from visionpos.server.sinks import PacketTap, Sink

log = logging.getLogger(__name__)

EVENT_BACKLOG = 64  # server events held for the sender; beyond, the oldest are dropped (counted)
_CAMERA_ID_AT = 10  # header offset of the camera id (u16, little endian; docs/protocol.md)

FOXGLOVE = section(
    "foxglove",
    "Foxglove WebSocket server: the 3-D scene live in Foxglove or Lichtblick (docs/interop.md). Needs "
    "`pip install visionpos[foxglove]`.",
    Setting("enabled", "boolean", True, "false: the section is ignored"),
    Setting("host", "text", "127.0.0.1", "address to listen on (0.0.0.0: every interface; the server has no "
            "authentication, docs/security.md)"),
    Setting("port", "integer", 8765, "TCP port of the WebSocket server (Foxglove's default)", min=1, max=65535),
    Setting("rate_hz", "number", 30.0, "scene updates per second (bodies, markers)", min=1.0, max=200.0),
    Setting("backlog", "integer", 256, "messages queued per client; a client that falls further behind loses "
            "the oldest", min=16, max=100000),
    Setting("max_clients", "integer", 16, "clients connected at once; more are answered HTTP 503", min=1, max=256),
    Setting("handshake_timeout_s", "number", 5.0, "a connection whose WebSocket handshake is not done by then is "
            "closed", min=0.1, max=60.0),
)


@dataclass(frozen=True)
class FoxgloveConfig:
    """The `foxglove:` section, checked (see FOXGLOVE for each key)."""

    host: str = FOXGLOVE["host"].field_default
    port: int = FOXGLOVE["port"].field_default
    rate_hz: float = FOXGLOVE["rate_hz"].field_default
    backlog: int = FOXGLOVE["backlog"].field_default
    max_clients: int = FOXGLOVE["max_clients"].field_default
    handshake_timeout_s: float = FOXGLOVE["handshake_timeout_s"].field_default


def parse_foxglove(arena: ArenaConfig) -> FoxgloveConfig | None:
    """Validate `foxglove:`; None when absent or `enabled: false`."""
    if not arena.given("foxglove"):
        return None
    s = FOXGLOVE.check(arena.section("foxglove"))
    F = FOXGLOVE
    if not F.read(s, "enabled"):
        return None
    return FoxgloveConfig(host=F.read(s, "host"), port=F.read(s, "port"), rate_hz=F.read(s, "rate_hz"),
                          backlog=F.read(s, "backlog"), max_clients=F.read(s, "max_clients"),
                          handshake_timeout_s=F.read(s, "handshake_timeout_s"))


register_section("foxglove", FOXGLOVE, parse_foxglove)


def _sdk(source: str) -> Any:
    try:
        import foxglove
    except ImportError:
        raise ConfigError(source, "foxglove", "the Foxglove server needs the foxglove-sdk package: "
                          "`pip install visionpos[foxglove]`, or remove the foxglove section") from None
    return foxglove


class FoxgloveServer(Sink):
    """Sink: FoxgloveServer(cfg, cameras) or FoxgloveServer.from_arena(arena); start(), publish(states),
    publish_markers(lp), packet_taps(), publish_health(t, health), publish_event(t, info), stats(), close()."""

    def __init__(self, cfg: FoxgloveConfig, cameras: Any, source: str = "<arena>"):
        self.cfg = cfg
        self._sdk = _sdk(source)
        self._fox = FoxgloveChannels(cameras, cfg.rate_hz)
        self._lock = threading.Lock()  # the mailbox
        self._states: list[BodyState] | None = None
        self._markers: LoosePoints | None = None
        self._frames: dict[tuple[int, int], tuple[int, bytes]] = {}  # (camera, type) -> newest (recv_ns, packet)
        self._health: tuple[int, dict[str, Any]] | None = None
        self._events: deque[tuple[int, dict[str, Any]]] = deque(maxlen=EVENT_BACKLOG)
        self._wake = threading.Event()
        self._running = False
        self._thread: threading.Thread | None = None
        self._server: Any = None
        self._context: Any = None
        self._channels: dict[str, Any] = {}
        self._gate: _ClientGate | None = None
        self.port = 0
        self.counters = {"updates": 0, "messages": 0, "replaced": 0, "errors": 0, "packets": 0,
                         "events_dropped": 0}
        self.messages_by_topic: dict[str, int] = {}  # handed to the SDK (the bench compares a client's count)

    @classmethod
    def from_arena(cls, arena: ArenaConfig) -> "FoxgloveServer | None":
        cfg = parse_foxglove(arena)
        return None if cfg is None else cls(cfg, arena.cameras, arena.source)

    def opens(self) -> dict[str, Any]:
        return {"foxglove.host": self.cfg.host, "foxglove.port": self.cfg.port}

    def start(self) -> None:
        """Listen (RuntimeError from the SDK when the port is taken) and start the sender thread."""
        fg = self._sdk
        self._context = fg.Context()  # our channels only, not the SDK's global ones
        # the SDK on a loopback port of its own; clients reach it through the gate only
        self._server = fg.start_server(name="visionpos", host="127.0.0.1", port=0,
                                       context=self._context, message_backlog_size=self.cfg.backlog)
        try:
            self._gate = _ClientGate(self.cfg, self._server.port)
        except OSError as e:
            self._server.stop()
            self._server = None
            raise RuntimeError(f"Foxglove server: cannot listen on {self.cfg.host}:{self.cfg.port}: {e}") from e
        self.port = self._gate.port
        self._gate.start()
        self._running = True
        self._thread = threading.Thread(target=self._send_loop, name="foxglove-sender", daemon=True)
        self._thread.start()
        log.info("Foxglove WebSocket server on ws://%s:%d", self.cfg.host, self.port)

    def close(self) -> None:
        self._running = False
        self._wake.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None
        if self._gate is not None:
            self._gate.close()
            self._gate = None
        if self._server is not None:
            self._server.stop()
            self._server = None

    # ---- sink interface (server loop): never blocks ----------------------------------------------

    def publish(self, states: list[BodyState]) -> None:
        if not self._running:
            return
        with self._lock:
            if self._states is not None:
                self.counters["replaced"] += 1
            self._states = list(states)
        self._wake.set()

    def publish_markers(self, lp: LoosePoints) -> None:
        if not self._running:
            return
        with self._lock:
            self._markers = lp
        self._wake.set()

    def packet_taps(self) -> list[PacketTap]:
        return [self.packet]

    def packet(self, recv_ns: int, data: bytes) -> None:
        """An accepted station packet (Ingest's tap, per packet): the newest frame and hello of each camera
        are kept for the sender; no wake-up here (the next output tick wakes it)."""
        if not self._running or len(data) < P.HEADER_BYTES:
            return
        mtype = data[5]
        if mtype == P.MsgType.FRAME or mtype == P.MsgType.HELLO:
            key = (data[_CAMERA_ID_AT] | data[_CAMERA_ID_AT + 1] << 8, mtype)
            with self._lock:
                self._frames[key] = (recv_ns, data)

    def publish_health(self, time_ns: int, health: dict[str, Any]) -> None:
        if not self._running:
            return
        with self._lock:
            self._health = (int(time_ns), health)
        self._wake.set()

    def publish_event(self, time_ns: int, info: dict[str, Any]) -> None:
        if not self._running:
            return
        with self._lock:
            if len(self._events) == EVENT_BACKLOG:
                self.counters["events_dropped"] += 1
            self._events.append((int(time_ns), dict(info)))
        self._wake.set()

    def stats(self) -> dict[str, Any]:
        gate = self._gate.stats() if self._gate is not None else {}
        return dict(self.counters, port=self.port, **gate)

    # ---- sender thread ---------------------------------------------------------------------------

    def _channel(self, topic: str, schema: str) -> Any:
        ch = self._channels.get(topic)
        if ch is None:
            fg = self._sdk
            ch = self._channels[topic] = fg.Channel(
                topic, schema=fg.Schema(name=schema, encoding="protobuf", data=file_descriptor_set(schema)),
                message_encoding="protobuf", context=self._context)
        return ch

    def _send_loop(self) -> None:
        while self._running:
            self._wake.wait(0.5)
            self._wake.clear()
            with self._lock:
                states, self._states = self._states, None
                markers, self._markers = self._markers, None
                frames, self._frames = self._frames, {}
                health, self._health = self._health, None
                events = list(self._events)
                self._events.clear()
            out = []
            # hellos first: they say which cameras stamp frames on CLOCK_REALTIME
            for (_, mtype), (recv_ns, data) in sorted(frames.items(), key=lambda kv: kv[0][1] != P.MsgType.HELLO):
                self.counters["packets"] += 1
                out += self._fox.packet(recv_ns, data)
            if health is not None:
                out += self._fox.health(*health)
            for t, info in events:
                out += self._fox.event(t, info)
            if states is not None:
                out += self._fox.states(states)
            if markers is not None:
                pts = np.asarray(markers.points, dtype=np.float64).reshape(-1, 3)
                out += self._fox.markers(int(markers.time_ns), pts)
            if out:
                self.counters["updates"] += 1
            for topic, schema, t, data in out:
                try:
                    self._channel(topic, schema).log(data, log_time=t)
                    self.counters["messages"] += 1
                    self.messages_by_topic[topic] = self.messages_by_topic.get(topic, 0) + 1
                except Exception:  # the SDK failing must not end the thread: count, log once per burst
                    self.counters["errors"] += 1
                    if self.counters["errors"] == 1:
                        log.exception("Foxglove server: logging on %s failed", topic)


# ---------------------------------------------------------------- the client gate

RELAY_BUFFER_B = 256 * 1024  # bytes held per direction and client; past it the relay stops reading that side
REFUSE_LINGER_S = 1.0  # a refused connection is read (and ignored) this long, so the 503 is not lost to a reset
MAX_REFUSING = 64  # refused connections lingering at once; beyond, one is closed at once
_READ_B = 65536
_MAX_HEAD_B = 16384  # an upgrade request or its answer longer than this is relayed as it is
SDK_SUBPROTOCOL = "foxglove.sdk.v1"  # what the SDK's server accepts
# the same protocol under its first name (Foxglove's published ws-protocol spec), which older clients offer
LEGACY_SUBPROTOCOL = "foxglove.websocket.v1"


def offer_sdk_subprotocol(head: bytes) -> tuple[bytes, bool]:
    """A client's upgrade request with its offer of LEGACY_SUBPROTOCOL renamed SDK_SUBPROTOCOL, when it offers
    only the legacy name; (head, True) then, else (head unchanged, False). The SDK's server answers 400 to a
    request that does not offer its own name, and the two names are one protocol."""
    lines = head.split(b"\r\n")
    offered = [i for i, ln in enumerate(lines) if ln.lower().startswith(b"sec-websocket-protocol:")]
    tokens = [t.strip() for i in offered for t in lines[i].split(b":", 1)[1].split(b",")]
    if SDK_SUBPROTOCOL.encode() in tokens or LEGACY_SUBPROTOCOL.encode() not in tokens:
        return head, False
    for i in offered:
        name, value = lines[i].split(b":", 1)
        lines[i] = name + b": " + b", ".join(SDK_SUBPROTOCOL.encode() if t.strip() == LEGACY_SUBPROTOCOL.encode()
                                             else t.strip() for t in value.split(b","))
    return b"\r\n".join(lines), True


def answer_legacy_subprotocol(head: bytes) -> bytes:
    """The SDK's answer to a renamed offer, naming the subprotocol the client offered (LEGACY_SUBPROTOCOL)."""
    lines = head.split(b"\r\n")
    for i, ln in enumerate(lines):
        if ln.lower().startswith(b"sec-websocket-protocol:") and ln.split(b":", 1)[1].strip() == \
                SDK_SUBPROTOCOL.encode():
            lines[i] = ln.split(b":", 1)[0] + b": " + LEGACY_SUBPROTOCOL.encode()
    return b"\r\n".join(lines)


def _refusal(max_clients: int) -> bytes:
    body = f"visionpos: Foxglove client limit ({max_clients}) reached; try again later\n".encode()
    return (b"HTTP/1.1 503 Service Unavailable\r\nContent-Type: text/plain\r\nRetry-After: 5\r\n"
            b"Connection: close\r\nContent-Length: " + str(len(body)).encode() + b"\r\n\r\n" + body)


class _Link:
    """One admitted client: its socket (down), the one to the SDK (up) and the bytes in flight each way."""

    __slots__ = ("down", "up", "peer", "to_up", "to_down", "deadline", "events", "request", "answer")

    def __init__(self, down: socket.socket, up: socket.socket, peer: str, deadline: float):
        self.down, self.up, self.peer, self.deadline = down, up, peer, deadline
        self.to_up = bytearray()
        self.to_down = bytearray()
        self.events: dict[socket.socket, int] = {down: 0, up: 0}  # registered interest per socket
        # the upgrade request while it is read (None once relayed), the SDK's answer while it is read where
        # the subprotocol's name must be put back (None: relayed as it comes)
        self.request: bytearray | None = bytearray()
        self.answer: bytearray | None = None

    def handshake(self, down: bool, data: bytes) -> bytes:
        """The bytes to relay now of data read from the client (down) or the SDK: the upgrade request and its
        answer are held until complete, for the subprotocol's name (offer_sdk_subprotocol)."""
        held = self.request if down else self.answer
        if held is None:
            return data
        held += data
        if b"\r\n\r\n" not in held and len(held) < _MAX_HEAD_B:
            return b""
        end = held.find(b"\r\n\r\n") + 4 if b"\r\n\r\n" in held else len(held)
        head, rest = bytes(held[:end]), bytes(held[end:])
        if down:
            self.request = None
            head, legacy = offer_sdk_subprotocol(head)
            if legacy:
                self.answer = bytearray()
        else:
            self.answer = None
            head = answer_legacy_subprotocol(head)
        return head + rest


class _Refused:
    """A connection over the limit: its request is read (up to its blank line), then answered 503 and
    drained until the client closes, so the answer is not lost to a reset."""

    __slots__ = ("sock", "until", "head", "answered")

    def __init__(self, sock: socket.socket, until: float):
        self.sock, self.until = sock, until
        self.head = bytearray()
        self.answered = False


class _ClientGate:
    """The foxglove section's address: admits max_clients connections and relays them to the SDK on
    127.0.0.1:upstream_port; refuses the others with HTTP 503. One thread, non-blocking sockets."""

    def __init__(self, cfg: FoxgloveConfig, upstream_port: int, clock=time.monotonic):
        self.cfg = cfg
        self.upstream = ("127.0.0.1", upstream_port)
        self.clock = clock
        family, kind, proto, _, addr = socket.getaddrinfo(cfg.host, cfg.port, type=socket.SOCK_STREAM,
                                                          flags=socket.AI_PASSIVE)[0]
        self._listen = socket.socket(family, kind, proto)
        try:
            self._listen.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            self._listen.bind(addr)
            self._listen.listen(128)
            self._listen.setblocking(False)
        except OSError:
            self._listen.close()
            raise
        self.port = self._listen.getsockname()[1]
        self._refusal = _refusal(cfg.max_clients)
        self._sel = selectors.DefaultSelector()
        self._sel.register(self._listen, selectors.EVENT_READ, None)
        self._links: list[_Link] = []
        self._refused: list[_Refused] = []
        self._wake_r, self._wake_w = socket.socketpair()  # close() wakes the select
        self._sel.register(self._wake_r, selectors.EVENT_READ, "wake")
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._log = RateLimitedLog(log, interval_s=60.0)
        self.counters = {"admitted": 0, "relayed_b": 0, "buffered_b_max": 0}
        self.drops: dict[str, int] = {}  # cause -> connections refused or closed for it

    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, name="foxglove-gate", daemon=True)
        self._thread.start()

    def close(self) -> None:
        self._stop.set()
        try:
            self._wake_w.send(b"x")
        except OSError:
            pass
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None
        for link in list(self._links):
            self._close_link(link)
        for r in self._refused:
            r.sock.close()
        self._refused.clear()
        self._sel.close()
        for s in (self._listen, self._wake_r, self._wake_w):
            s.close()

    def stats(self) -> dict[str, Any]:
        return dict(self.counters, clients=len(self._links), max_clients=self.cfg.max_clients,
                    dropped=dict(self.drops))

    def _note(self, cause: str, detail: str) -> None:
        self.drops[cause] = self.drops.get(cause, 0) + 1
        self._log.log(cause, logging.WARNING, "foxglove: %s: %s", cause, detail)

    # ---- the thread --------------------------------------------------------------------------------

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                for key, mask in self._sel.select(0.25):
                    if key.data is None:
                        self._accept()
                    elif key.data == "wake":
                        self._wake_r.recv(64)
                    elif isinstance(key.data, _Refused):
                        self._linger(key.data)
                    elif key.data.events.get(key.fileobj):  # not closed by an earlier event of this batch
                        self._io(key.data, key.fileobj, mask)
                self._expire(self.clock())
            except Exception as e:  # a bug here must not end the gate: log it once a minute
                self._log.log("internal error", logging.ERROR, "foxglove gate: %r", e)

    def _accept(self) -> None:
        for _ in range(64):  # a burst of connects does not starve the admitted clients
            try:
                down, addr = self._listen.accept()
            except (BlockingIOError, InterruptedError):
                return
            except OSError as e:  # e.g. out of file descriptors: the connection stays in the backlog
                self._note("accept failed", repr(e))
                return
            peer = f"{addr[0]}:{addr[1]}"
            if len(self._links) >= self.cfg.max_clients:
                self._refuse(down, peer)
                continue
            try:
                up = socket.create_connection(self.upstream, timeout=1.0)  # loopback: the kernel completes it
            except OSError as e:
                down.close()
                self._note("server unreachable", f"{peer}: {e!r}")
                continue
            for s in (down, up):
                s.setblocking(False)
                s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            link = _Link(down, up, peer, self.clock() + self.cfg.handshake_timeout_s)
            self._links.append(link)
            self.counters["admitted"] += 1
            self._interest(link)

    def _refuse(self, sock: socket.socket, peer: str) -> None:
        self._note("too many clients", f"refused {peer} (max_clients {self.cfg.max_clients})")
        sock.setblocking(False)
        if len(self._refused) >= MAX_REFUSING:
            self._end_refused(self._refused[0])
        r = _Refused(sock, self.clock() + REFUSE_LINGER_S)
        self._refused.append(r)
        self._sel.register(sock, selectors.EVENT_READ, r)

    def _linger(self, r: _Refused) -> None:
        try:
            data = r.sock.recv(_READ_B)
        except (BlockingIOError, InterruptedError):
            return
        except OSError:
            data = b""
        if not data:
            self._end_refused(r)
        elif not r.answered:
            r.head += data
            if b"\r\n\r\n" in r.head or len(r.head) > 16384:
                self._answer(r)

    def _answer(self, r: _Refused) -> None:
        r.answered = True
        r.head = bytearray()
        try:
            r.sock.send(self._refusal)  # a few hundred bytes into an empty socket buffer
            r.sock.shutdown(socket.SHUT_WR)
        except OSError:
            self._end_refused(r)

    def _end_refused(self, r: _Refused) -> None:
        if r in self._refused:
            self._refused.remove(r)
            self._sel.unregister(r.sock)
            r.sock.close()

    def _io(self, link: _Link, sock: socket.socket, mask: int) -> None:
        down = sock is link.down
        src_buf, dst_buf = (link.to_up, link.to_down) if down else (link.to_down, link.to_up)
        try:
            if mask & selectors.EVENT_WRITE and dst_buf:
                n = sock.send(dst_buf)
                del dst_buf[:n]
            if mask & selectors.EVENT_READ and len(src_buf) < RELAY_BUFFER_B:
                data = sock.recv(_READ_B)
                if not data:
                    self._drop(link, "disconnected" if down else "closed by the server", logging.INFO)
                    return
                src_buf += link.handshake(down, data)
                if not down:
                    link.deadline = 0.0  # the SDK answered the handshake
                    self.counters["relayed_b"] += len(data)
                self.counters["buffered_b_max"] = max(self.counters["buffered_b_max"], len(src_buf))
        except (BlockingIOError, InterruptedError):
            pass
        except OSError as e:
            self._drop(link, "connection error", logging.INFO, repr(e))
            return
        self._interest(link)

    def _interest(self, link: _Link) -> None:
        """Read a side while its buffer has room, write it while bytes wait for it."""
        want = {link.down: (selectors.EVENT_READ if len(link.to_up) < RELAY_BUFFER_B else 0)
                | (selectors.EVENT_WRITE if link.to_down else 0),
                link.up: (selectors.EVENT_READ if len(link.to_down) < RELAY_BUFFER_B else 0)
                | (selectors.EVENT_WRITE if link.to_up else 0)}
        for s, ev in want.items():
            had = link.events[s]
            if ev == had:
                continue
            if not had:
                self._sel.register(s, ev, link)
            elif not ev:
                self._sel.unregister(s)
            else:
                self._sel.modify(s, ev, link)
            link.events[s] = ev

    def _drop(self, link: _Link, cause: str, level: int = logging.WARNING, detail: str = "") -> None:
        if link not in self._links:
            return
        if level == logging.INFO:  # ordinary ends: counted and logged, not warned about
            self.drops[cause] = self.drops.get(cause, 0) + 1
            self._log.log(cause, logging.INFO, "foxglove: client %s: %s%s", link.peer, cause,
                          f" ({detail})" if detail else "")
        else:
            self._note(cause, f"client {link.peer}{': ' + detail if detail else ''}")
        self._close_link(link)  # after counting: whoever sees the close sees the count

    def _close_link(self, link: _Link) -> None:
        self._links.remove(link)
        for s, pending in ((link.up, link.to_up), (link.down, link.to_down)):
            if pending:  # e.g. the client's close frame, read just before its end of stream
                try:
                    s.send(pending)
                except OSError:
                    pass
        for s in (link.down, link.up):
            if link.events[s]:
                self._sel.unregister(s)
                link.events[s] = 0
            s.close()

    def _expire(self, now: float) -> None:
        for link in [k for k in self._links if k.deadline and now >= k.deadline]:
            self._drop(link, "handshake timeout", detail=f"no WebSocket handshake within "
                       f"{self.cfg.handshake_timeout_s:g} s")
        for r in [r for r in self._refused if now >= r.until]:
            self._end_refused(r)
