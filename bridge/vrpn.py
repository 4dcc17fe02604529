"""VRPN server: one tracker per body, for every VRPN client (vrpn_client_ros, vrpn_mocap, libmotioncapture).

The arena's `vrpn:` section turns it on (docs/interop.md, "VRPN"). The server speaks VRPN's
connection protocol (vrpn_Connection.C, cookie "vrpn: ver. 07.xx") on TCP and UDP port 3883:

- A client connects in one of two ways. A plain name (`Body@host`, `host:3883`) sends a UDP
  datagram "<its address> <tcp port>" to our UDP port and waits for us to connect back to that
  TCP port; we connect to the datagram's source address (never to a third host it names). A
  `tcp://` name connects to our TCP port itself and gets everything over TCP.
- Both sides send a 24-byte cookie; after the client's, we describe our senders (one per body,
  named as the body) and message types. A callback client then describes its own UDP port and
  gets the reports by UDP (lossy, no head-of-line blocking), several messages per datagram of at
  most 1472 bytes; a TCP client gets them on its TCP stream.
- Messages: a 24-byte header (length without padding, time s, time us, sender, type, sequence
  number; big-endian int32) and a payload padded to 8 bytes. Negative types are the system
  messages (sender -1, type -2, UDP -3, log -4, disconnect -5).
- Reports: "vrpn_Tracker Pos_Quat" (sensor 0, position m, quaternion x y z w, float64) for
  every tracked body with a new capture, stamped with the capture time on the Unix clock, the
  pose moved back to that time with the body's velocities. "vrpn_Tracker Velocity" (m/s world,
  the world-frame rotation over VELOCITY_DT_S, that dt) goes to clients that registered the
  type (every vrpn_Tracker_Remote does) when `velocity: true`. An untracked body sends nothing.
  A "vrpn_Base ping_message" for a body is answered with a pong (clients warn without one).

Threading: publish() runs on the fusion loop and only hands the newest states to the server's
own thread (one reference swap and one byte on a socketpair). The thread owns every socket, all
non-blocking: a client that stalls (its queued bytes pass `send_queue_kb`), sends a malformed
message, or does not finish the handshake within `handshake_timeout_s` is dropped; at most
`max_clients` are served; each cause is logged once a minute at most, with a count.
"""

from __future__ import annotations

import errno
import ipaddress
import logging
import selectors
import socket
import struct
import threading
import time
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from bridge.convert import pose_at
from bridge.transport import RateGrid, pack_datagrams
from visionpos.config.arena import ArenaConfig, ConfigError
from visionpos.config.schema import register_section
from visionpos.config.settings import Setting, section
from visionpos.geometry.rotations import matrix_from_quat, quat_from_rotvec
from visionpos.messages import BodyState
from visionpos.server.sinks import Sink

log = logging.getLogger("visionpos.bridge.vrpn")

DEFAULT_PORT = 3883
COOKIE_PREFIX = b"vrpn: ver. 07."  # major version; minor versions interoperate (check_vrpn_cookie)
COOKIE = b"vrpn: ver. 07.38  0".ljust(24, b"\0")  # magic (16) + two spaces + log mode '0', padded to 24
COOKIE_SIZE = 24
ALIGN = 8
HEADER = struct.Struct("!iiiiii")  # length (header + payload, unpadded), sec, usec, sender, type, sequence
HEADER_SIZE = HEADER.size  # 24: 20 bytes padded to ALIGN
MAX_PAYLOAD = 64000  # a VRPN endpoint's TCP buffer: no real message is longer
MAX_NAME = 100  # vrpn_CNAME: sender and type names, terminating NUL included
UDP_DATAGRAM_MAX = 1472  # vrpn_CONNECTION_UDP_BUFLEN
VELOCITY_DT_S = 0.01  # the velocity report's rotation is over this interval (angles stay far below pi)

SENDER_DESCRIPTION, TYPE_DESCRIPTION, UDP_DESCRIPTION, LOG_DESCRIPTION, DISCONNECT_MESSAGE = -1, -2, -3, -4, -5

POS_QUAT = "vrpn_Tracker Pos_Quat"
VELOCITY = "vrpn_Tracker Velocity"
PING = "vrpn_Base ping_message"
PONG = "vrpn_Base pong_message"
OUR_TYPES = (POS_QUAT, VELOCITY, PONG)  # our type ids are their indices
T_POS_QUAT, T_VELOCITY, T_PONG = 0, 1, 2

POS_QUAT_PAYLOAD = struct.Struct("!ii3d4d")  # sensor, padding, position, quaternion xyzw
VELOCITY_PAYLOAD = struct.Struct("!ii3d4dd")  # sensor, padding, velocity, rotation over dt (xyzw), dt

VRPN = section(
    "vrpn",
    "VRPN server: one tracker per body (docs/interop.md, VRPN).",
    Setting("enabled", "boolean", True, "false: the section is ignored"),
    Setting("host", "text", "0.0.0.0", "IPv4 address to listen on (0.0.0.0: every interface)"),
    Setting("port", "integer", DEFAULT_PORT, "TCP and UDP port (VRPN's is 3883; 0: a free one, for tests)",
            min=0, max=65535),
    Setting("rate_hz", "number", 0.0, "reports per second per body (0 = every output tick)", min=0.0,
            max=1000.0),
    Setting("velocity", "boolean", True, "also send vrpn_Tracker Velocity reports to clients that register it"),
    Setting("max_clients", "integer", 16, "clients served at once (more are refused)", min=1, max=256),
    Setting("handshake_timeout_s", "number", 5.0, "a client that has not finished the handshake by then is "
            "dropped", min=0.1, max=60.0),
    Setting("send_queue_kb", "integer", 256, "bytes queued for one client beyond its socket buffer (kB); "
            "a client that lets more pile up has stalled and is dropped", min=4, max=65536),
)


@dataclass(frozen=True)
class VrpnConfig:
    """The `vrpn:` section, checked. bodies: the tracker names (every body in the arena, in order)."""

    bodies: tuple[str, ...]
    host: str = VRPN["host"].field_default
    port: int = VRPN["port"].field_default
    rate_hz: float = VRPN["rate_hz"].field_default
    velocity: bool = VRPN["velocity"].field_default
    max_clients: int = VRPN["max_clients"].field_default
    handshake_timeout_s: float = VRPN["handshake_timeout_s"].field_default
    send_queue_kb: int = VRPN["send_queue_kb"].field_default


def parse_vrpn(arena: ArenaConfig) -> VrpnConfig | None:
    """Validate `vrpn:`; None when absent or `enabled: false`."""
    if not arena.given("vrpn"):
        return None
    s = VRPN.check(arena.section("vrpn"))
    if not VRPN.read(s, "enabled"):
        return None
    host = VRPN.read(s, "host")
    try:
        ipaddress.IPv4Address(host)
    except ValueError:
        raise s.error("host", f"expected the IPv4 address of a local interface or 0.0.0.0, got {host!r}") from None
    for i, b in enumerate(arena.bodies):
        if len(b.name.encode("utf-8")) >= MAX_NAME or not b.name.isprintable():
            raise ConfigError(arena.source, f"bodies[{i}].name", f"{b.name!r} cannot be a VRPN tracker name: "
                              f"use at most {MAX_NAME - 1} bytes of printable text, or remove the `vrpn` section")
    return VrpnConfig(
        bodies=tuple(b.name for b in arena.bodies),
        host=host,
        port=VRPN.read(s, "port"),
        rate_hz=VRPN.read(s, "rate_hz"),
        velocity=VRPN.read(s, "velocity"),
        max_clients=VRPN.read(s, "max_clients"),
        handshake_timeout_s=VRPN.read(s, "handshake_timeout_s"),
        send_queue_kb=VRPN.read(s, "send_queue_kb"),
    )


# ---------------------------------------------------------------- wire format (no I/O)


def pad8(n: int) -> int:
    """n rounded up to a multiple of ALIGN."""
    return (n + ALIGN - 1) & ~(ALIGN - 1)


def encode_message(sender: int, msg_type: int, sec: int, usec: int, payload: bytes, seq: int = 0) -> bytes:
    """One VRPN message: header, payload, zero padding to ALIGN."""
    head = HEADER.pack(HEADER_SIZE + len(payload), sec, usec, sender, msg_type, seq & 0x7FFFFFFF)
    return head + payload + bytes(pad8(len(payload)) - len(payload))


def encode_name(sender: int, msg_type: int, name: str, sec: int, usec: int) -> bytes:
    """A sender (-1) or type (-2) description: the described id in the sender field, then the
    name's length with its NUL (int32) and the name with its NUL."""
    raw = name.encode("utf-8") + b"\0"
    return encode_message(sender, msg_type, sec, usec, struct.pack("!i", len(raw)) + raw)


def decode_name(payload: bytes) -> str:
    """The name in a sender or type description. ValueError when malformed."""
    if len(payload) < 5 or len(payload) > MAX_NAME + 4:
        raise ValueError(f"description of {len(payload)} bytes")
    (n,) = struct.unpack_from("!i", payload)
    if not 1 <= n <= len(payload) - 4:
        raise ValueError(f"name length {n} in a description of {len(payload)} bytes")
    return payload[4:4 + n].split(b"\0", 1)[0].decode("utf-8", "replace")


def wall_time(ns: int) -> tuple[int, int]:
    """Unix time in ns -> (seconds, microseconds) as VRPN stamps messages."""
    sec, usec = divmod(ns // 1000, 1_000_000)
    return int(sec), int(usec)


def report_pose(st: BodyState) -> tuple[np.ndarray, np.ndarray]:
    """A state's pose at its capture time: (position (3,) m world, quaternion (4,) xyzw body->world).

    The filter's state is valid at time_ns (the send time); the report is stamped with the
    capture time, so the pose is moved back to it (bridge.convert.pose_at, as MAVLink's)."""
    return pose_at(st, st.capture_ns)


def encode_reports(st: BodyState, sender: int, wall_ns: int, seq: int) -> tuple[bytes, bytes] | None:
    """(Pos_Quat message, Velocity message) of one tracked state, stamped wall_ns; None if not finite."""
    p, q = report_pose(st)
    v = np.asarray(st.velocity, float)
    w_world = matrix_from_quat(q) @ np.asarray(st.angular_velocity, float)
    vq = quat_from_rotvec(w_world * VELOCITY_DT_S)
    if not (np.isfinite(p).all() and np.isfinite(q).all()):
        return None
    sec, usec = wall_time(wall_ns)
    pose = encode_message(sender, T_POS_QUAT, sec, usec, POS_QUAT_PAYLOAD.pack(0, 0, *p, *q), seq)
    if not (np.isfinite(v).all() and np.isfinite(vq).all()):
        return pose, b""
    vel = encode_message(sender, T_VELOCITY, sec, usec, VELOCITY_PAYLOAD.pack(0, 0, *v, *vq, VELOCITY_DT_S), seq)
    return pose, vel


class MessageReader:
    """Splits a TCP byte stream into messages: feed(bytes) -> [(sender, type, sec, usec, payload)].

    Keeps at most one partial message; ValueError on a length no VRPN peer sends."""

    def __init__(self) -> None:
        self.buf = bytearray()

    def feed(self, data: bytes) -> list[tuple[int, int, int, int, bytes]]:
        buf = self.buf
        buf += data
        out = []
        pos = 0
        while len(buf) - pos >= HEADER_SIZE:
            length, sec, usec, sender, msg_type, _seq = HEADER.unpack_from(buf, pos)
            n = length - HEADER_SIZE
            if n < 0 or n > MAX_PAYLOAD:
                raise ValueError(f"message length {length}")
            total = HEADER_SIZE + pad8(n)
            if len(buf) - pos < total:
                break
            out.append((sender, msg_type, sec, usec, bytes(buf[pos + HEADER_SIZE:pos + HEADER_SIZE + n])))
            pos += total
        del buf[:pos]
        return out


# ---------------------------------------------------------------- the server

CONNECTING, COOKIE_WAIT, READY = "connecting", "cookie", "ready"
LOG_INTERVAL_NS = 60_000_000_000  # a cause is logged at most once a minute (with the count since)
MAX_LOBS_PER_WAKE = 64
RECV_CHUNK = 65536


class _Client:
    """One VRPN peer, owned by the server thread."""

    __slots__ = ("sock", "peer", "tcp_only", "state", "deadline_ns", "reader", "out", "udp_addr",
                 "types", "senders", "velocity", "want_write", "target")

    def __init__(self, sock: socket.socket, peer: tuple[str, int], tcp_only: bool, state: str, deadline_ns: int,
                 target: tuple[str, int] | None = None):
        self.sock = sock
        self.peer = peer
        self.tcp_only = tcp_only
        self.state = state
        self.deadline_ns = deadline_ns
        self.reader = MessageReader()
        self.out = bytearray()
        self.udp_addr: tuple[str, int] | None = None
        self.types: dict[int, str] = {}  # the client's type ids -> names
        self.senders: dict[int, str] = {}  # the client's sender ids -> names
        self.velocity = False  # registered vrpn_Tracker Velocity
        self.want_write = False
        self.target = target  # callback clients: the (address, port) we connected to


class VrpnServer(Sink):
    """A sink serving every body as a VRPN tracker (module docstring; docs/interop.md).

    VrpnServer(cfg) with a VrpnConfig; start() binds the port and starts the thread; publish(states)
    hands the newest states over (never blocks); close(); stats(); port (the bound port).
    clock_ns: the server clock the states' times are on; wall_clock_ns: Unix time (report stamps).
    """

    def __init__(self, cfg: VrpnConfig, clock_ns: Callable[[], int] = time.monotonic_ns,
                 wall_clock_ns: Callable[[], int] = time.time_ns):
        self.cfg = cfg
        self.clock_ns = clock_ns
        self.wall_clock_ns = wall_clock_ns
        self.index = {name: i for i, name in enumerate(cfg.bodies)}
        self.counters = {"ticks": 0, "skipped_rate": 0, "reports": 0, "velocity_reports": 0, "frozen": 0,
                         "untracked": 0, "datagrams": 0, "send_errors": 0, "connections": 0, "pongs": 0}
        self.drops: dict[str, int] = {}  # cause -> clients dropped or requests refused for it
        self.port: int | None = None
        self._pending: list[BodyState] | None = None
        self._last_capture = [-(1 << 62)] * len(cfg.bodies)
        self._grid = RateGrid(cfg.rate_hz)
        self._seq = 0
        self._wall_offset_ns = 0
        self._offset_at_ns = -(1 << 62)
        self._clients: dict[socket.socket, _Client] = {}
        self._logged: dict[str, tuple[int, int]] = {}  # cause -> (next log time, suppressed count)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._sel: selectors.BaseSelector | None = None
        self._tcp: socket.socket | None = None
        self._udp: socket.socket | None = None
        self._wake_r: socket.socket | None = None
        self._wake_w: socket.socket | None = None

    @classmethod
    def from_arena(cls, arena: ArenaConfig) -> "VrpnServer | None":
        cfg = parse_vrpn(arena)
        return None if cfg is None else cls(cfg)

    # ---------------------------------------------------------------- fusion side

    def opens(self) -> dict[str, Any]:
        return {"vrpn.host": self.cfg.host, "vrpn.port": self.cfg.port}

    def start(self) -> None:
        """Bind TCP and UDP on cfg.host:cfg.port (0: one free port for both) and start the thread."""
        if self._thread is not None:
            return
        tcp, udp = self._bind()
        self._tcp, self._udp = tcp, udp
        self.port = tcp.getsockname()[1]
        self._wake_r, self._wake_w = socket.socketpair()
        for s in (self._wake_r, self._wake_w):
            s.setblocking(False)
        self._sel = selectors.DefaultSelector()
        self._sel.register(tcp, selectors.EVENT_READ, "accept")
        self._sel.register(udp, selectors.EVENT_READ, "lob")
        self._sel.register(self._wake_r, selectors.EVENT_READ, "wake")
        self._thread = threading.Thread(target=self._run, name="vrpn-server", daemon=True)
        self._thread.start()

    def _bind(self) -> tuple[socket.socket, socket.socket]:
        for _ in range(20 if self.cfg.port == 0 else 1):
            tcp = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            tcp.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            tcp.bind((self.cfg.host, self.cfg.port))
            udp = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            try:
                udp.bind((self.cfg.host, tcp.getsockname()[1]))
            except OSError:
                udp.close()
                tcp.close()
                if self.cfg.port:
                    raise
                continue  # a free TCP port whose UDP twin is taken: pick another
            tcp.listen(16)
            tcp.setblocking(False)
            udp.setblocking(False)
            return tcp, udp
        raise OSError(f"no free port with both TCP and UDP on {self.cfg.host}")

    def publish(self, states: list[BodyState]) -> None:
        """Hand the newest states to the server thread (a reference swap and a wake-up byte)."""
        if self._wake_w is None:
            return
        self._pending = states
        try:
            self._wake_w.send(b"\0")
        except OSError:  # the wake-up pipe is full: a wake-up is pending already
            pass

    def stats(self) -> dict:
        clients = list(self._clients.values())
        return dict(self.counters, port=self.port, clients=sum(c.state == READY for c in clients),
                    handshaking=sum(c.state != READY for c in clients), dropped=dict(self.drops))

    def close(self) -> None:
        """Stop the thread and close every socket. Idempotent."""
        if self._thread is not None:
            self._stop.set()
            try:
                self._wake_w.send(b"\0")
            except OSError:
                pass
            self._thread.join(timeout=5.0)
            self._thread = None
        for c in list(self._clients.values()):
            c.sock.close()
        self._clients.clear()
        for s in (self._tcp, self._udp, self._wake_r, self._wake_w):
            if s is not None:
                s.close()
        self._tcp = self._udp = self._wake_r = self._wake_w = None
        if self._sel is not None:
            self._sel.close()
            self._sel = None

    # ---------------------------------------------------------------- server thread

    def _run(self) -> None:
        sel = self._sel
        while not self._stop.is_set():
            try:
                events = sel.select(timeout=0.2)
            except OSError:  # pragma: no cover - a closed selector at shutdown
                return
            for key, mask in events:
                tag = key.data
                try:
                    if tag == "wake":
                        self._drain_wake()
                    elif tag == "accept":
                        self._accept()
                    elif tag == "lob":
                        self._lobs()
                    else:
                        self._client_event(tag, mask)
                except Exception as e:  # never let one peer end the server
                    if isinstance(tag, _Client):
                        self._drop(tag, "internal error", repr(e))
                    else:
                        self._note("internal error", repr(e))
            if self._stop.is_set():
                return
            states, self._pending = self._pending, None
            if states is not None:
                self._send_reports(states)
            self._expire(self.clock_ns())

    def _drain_wake(self) -> None:
        try:
            while self._wake_r.recv(4096):
                pass
        except OSError:
            pass

    def _note(self, cause: str, detail: str) -> None:
        """Log a cause the first time and then at most once a minute, with the count since."""
        now = self.clock_ns()
        nxt, suppressed = self._logged.get(cause, (0, 0))
        if now >= nxt:
            more = f" ({suppressed} more since the last report)" if suppressed else ""
            log.log(logging.INFO if cause == "disconnected" else logging.WARNING, "vrpn: %s: %s%s", cause, detail, more)
            self._logged[cause] = (now + LOG_INTERVAL_NS, 0)
        else:
            self._logged[cause] = (nxt, suppressed + 1)

    def _refuse(self, cause: str, detail: str) -> None:
        self.drops[cause] = self.drops.get(cause, 0) + 1
        self._note(cause, detail)

    def _drop(self, c: _Client, cause: str, detail: str = "") -> None:
        if self._clients.pop(c.sock, None) is None:
            return
        try:
            self._sel.unregister(c.sock)
        except (KeyError, ValueError):
            pass
        c.sock.close()
        self._refuse(cause, f"client {c.peer[0]}:{c.peer[1]} dropped{': ' + detail if detail else ''}")

    def _add(self, c: _Client) -> None:
        self._clients[c.sock] = c
        self._sel.register(c.sock, selectors.EVENT_WRITE if c.state == CONNECTING else selectors.EVENT_READ, c)
        c.want_write = c.state == CONNECTING

    def _new_socket_options(self, s: socket.socket) -> None:
        s.setblocking(False)
        s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        # a small kernel buffer, so that a stalled reader shows up in our bounded queue quickly
        s.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, max(4096, self.cfg.send_queue_kb * 1024 // 4))

    def _accept(self) -> None:
        for _ in range(16):
            try:
                s, addr = self._tcp.accept()
            except (BlockingIOError, InterruptedError):
                return
            except OSError as e:
                self._note("accept failed", str(e))
                return
            if len(self._clients) >= self.cfg.max_clients:
                s.close()
                self._refuse("too many clients", f"refused {addr[0]}:{addr[1]} (max_clients {self.cfg.max_clients})")
                continue
            self._new_socket_options(s)
            c = _Client(s, (addr[0], addr[1]), True, COOKIE_WAIT, self._deadline())
            self._add(c)
            self._queue(c, COOKIE)

    def _deadline(self) -> int:
        return self.clock_ns() + int(self.cfg.handshake_timeout_s * 1e9)

    def _lobs(self) -> None:
        """Connection requests on UDP: '<address> <tcp port>\\0'; we connect back to the sender."""
        for _ in range(MAX_LOBS_PER_WAKE):
            try:
                data, addr = self._udp.recvfrom(256)
            except (BlockingIOError, InterruptedError):
                return
            except OSError:  # e.g. ICMP port unreachable from an earlier send
                continue
            port = _parse_lob(data)
            if port is None:
                self._refuse("malformed connection request", f"from {addr[0]}:{addr[1]}: {data[:60]!r}")
                continue
            target = (addr[0], port)
            if any(c.target == target for c in self._clients.values()):
                continue  # the client repeats its request every second until we call
            if len(self._clients) >= self.cfg.max_clients:
                self._refuse("too many clients", f"ignored a request from {addr[0]} (max_clients "
                                                  f"{self.cfg.max_clients})")
                continue
            s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            self._new_socket_options(s)
            err = s.connect_ex(target)
            if err not in (0, errno.EINPROGRESS, errno.EWOULDBLOCK):
                s.close()
                self._refuse("cannot call back", f"{target[0]}:{target[1]}: {err}")
                continue
            self._add(_Client(s, target, False, CONNECTING, self._deadline(), target=target))

    def _client_event(self, c: _Client, mask: int) -> None:
        if c.state == CONNECTING:
            err = c.sock.getsockopt(socket.SOL_SOCKET, socket.SO_ERROR)
            if err:
                self._drop(c, "cannot call back", f"connect failed ({err})")
                return
            c.state = COOKIE_WAIT
            self._queue(c, COOKIE)
            return
        if mask & selectors.EVENT_WRITE:
            self._flush(c)
            if c.sock not in self._clients:
                return
        if mask & selectors.EVENT_READ:
            self._read(c)

    def _read(self, c: _Client) -> None:
        try:
            data = c.sock.recv(RECV_CHUNK)
        except (BlockingIOError, InterruptedError):
            return
        except OSError as e:
            self._drop(c, "disconnected mid-message" if c.reader.buf else "connection error", str(e))
            return
        if not data:
            self._drop(c, "disconnected mid-message" if c.reader.buf else "disconnected")
            return
        if c.state == COOKIE_WAIT:
            c.reader.buf += data
            if len(c.reader.buf) < COOKIE_SIZE:
                return
            cookie = bytes(c.reader.buf[:COOKIE_SIZE])
            del c.reader.buf[:COOKIE_SIZE]
            if not cookie.startswith(COOKIE_PREFIX):
                self._drop(c, "not a VRPN client", f"cookie {cookie[:19]!r}")
                return
            c.state = READY
            self.counters["connections"] += 1
            self._describe(c)
            data = b""
        try:
            messages = c.reader.feed(data)
        except ValueError as e:
            self._drop(c, "malformed message", str(e))
            return
        for sender, msg_type, _sec, _usec, payload in messages:
            if not self._handle(c, sender, msg_type, payload):
                return

    def _describe(self, c: _Client) -> None:
        """Our senders (the bodies) and message types, right after the client's cookie."""
        sec, usec = wall_time(self.wall_clock_ns())
        parts = [encode_name(i, SENDER_DESCRIPTION, name, sec, usec) for i, name in enumerate(self.cfg.bodies)]
        parts += [encode_name(i, TYPE_DESCRIPTION, name, sec, usec) for i, name in enumerate(OUR_TYPES)]
        self._queue(c, b"".join(parts))

    def _handle(self, c: _Client, sender: int, msg_type: int, payload: bytes) -> bool:
        """One message from a client; False when the client was dropped for it."""
        if msg_type >= 0:
            if c.types.get(msg_type) == PING:
                name = c.senders.get(sender)
                i = self.index.get(name) if name is not None else None
                if i is not None:
                    sec, usec = wall_time(self.wall_clock_ns())
                    self.counters["pongs"] += 1
                    self._queue(c, encode_message(i, T_PONG, sec, usec, b""))
                    return c.sock in self._clients
            return True  # other requests (to-room, update rate, ...) have no effect here
        if msg_type in (SENDER_DESCRIPTION, TYPE_DESCRIPTION):
            try:
                name = decode_name(payload)
            except ValueError as e:
                self._drop(c, "malformed message", str(e))
                return False
            table = c.senders if msg_type == SENDER_DESCRIPTION else c.types
            if sender < 0 or (sender not in table and len(table) >= 2000):  # vrpn_CONNECTION_MAX_TYPES
                self._drop(c, "malformed message", f"description id {sender}")
                return False
            table[sender] = name
            if msg_type == TYPE_DESCRIPTION and name == VELOCITY:
                c.velocity = True
        elif msg_type == UDP_DESCRIPTION:
            # the port is in the sender field; we send to the address the TCP connection comes from
            if not c.tcp_only and 0 < sender < 65536:
                c.udp_addr = (c.peer[0], sender)
        # LOG_DESCRIPTION (we keep no logs for clients), DISCONNECT_MESSAGE (file playback) and unknown
        # system types are ignored
        return True

    def _set_write(self, c: _Client, on: bool) -> None:
        if c.want_write != on:
            c.want_write = on
            self._sel.modify(c.sock, selectors.EVENT_READ | (selectors.EVENT_WRITE if on else 0), c)

    def _queue(self, c: _Client, data: bytes) -> None:
        """Send now what the socket takes, queue the rest; drop a client whose queue overflows."""
        if c.state == CONNECTING:
            return
        if not c.out:
            try:
                n = c.sock.send(data)
            except (BlockingIOError, InterruptedError):
                n = 0
            except OSError as e:
                self._drop(c, "connection error", str(e))
                return
            data = data[n:]
            if not data:
                self._set_write(c, False)
                return
        if len(c.out) + len(data) > self.cfg.send_queue_kb * 1024:
            self._drop(c, "stalled", f"more than {self.cfg.send_queue_kb} kB waiting to be read")
            return
        c.out += data
        self._set_write(c, True)

    def _flush(self, c: _Client) -> None:
        try:
            n = c.sock.send(c.out)
        except (BlockingIOError, InterruptedError):
            return
        except OSError as e:
            self._drop(c, "connection error", str(e))
            return
        del c.out[:n]
        if not c.out:
            self._set_write(c, False)

    def _expire(self, now: int) -> None:
        for c in [c for c in self._clients.values() if c.state != READY and now > c.deadline_ns]:
            self._drop(c, "handshake timeout", f"no {'connection' if c.state == CONNECTING else 'cookie'} "
                                               f"within {self.cfg.handshake_timeout_s:g} s")

    def _send_reports(self, states: list[BodyState]) -> None:
        now = self.clock_ns()
        if not self._grid.due(now):
            self.counters["skipped_rate"] += 1
            return
        if now - self._offset_at_ns > 1_000_000_000:  # follow steps of the wall clock (NTP)
            self._wall_offset_ns = self.wall_clock_ns() - self.clock_ns()
            self._offset_at_ns = now
        self.counters["ticks"] += 1
        pairs: list[tuple[bytes, bytes]] = []
        for st in states:
            i = self.index.get(st.name)
            if i is None:
                continue
            if not st.tracked:
                self.counters["untracked"] += 1
                continue
            if st.capture_ns <= self._last_capture[i]:
                self.counters["frozen"] += 1  # no new frame since the last report: never resent
                continue
            self._seq += 1
            enc = encode_reports(st, i, st.capture_ns + self._wall_offset_ns, self._seq)
            if enc is None:
                continue
            self._last_capture[i] = st.capture_ns
            pairs.append(enc)
        if not pairs or not self._clients:
            return
        poses = [p for p, _ in pairs]
        with_vel = [m for p, v in pairs for m in ((p, v) if v else (p,))]
        n_vel = len(with_vel) - len(poses)
        grams: dict[bool, list[bytes]] = {}
        for c in list(self._clients.values()):
            if c.state != READY:
                continue
            v = self.cfg.velocity and c.velocity and n_vel > 0
            msgs = with_vel if v else poses
            self.counters["reports"] += len(poses)
            if v:
                self.counters["velocity_reports"] += n_vel
            if c.udp_addr is None:
                self._queue(c, b"".join(msgs))
                continue
            if v not in grams:
                grams[v] = pack_datagrams(msgs, UDP_DATAGRAM_MAX)
            for g in grams[v]:
                try:
                    self._udp.sendto(g, c.udp_addr)
                    self.counters["datagrams"] += 1
                except OSError:  # buffer full, ICMP refused: lossy by design, never block
                    self.counters["send_errors"] += 1


def _parse_lob(data: bytes) -> int | None:
    """The TCP port of a connection request '<address> <port>' (VRPN's rules: port >= 1024, the
    address of letters, digits and dots); None when malformed."""
    text = data.split(b"\0", 1)[0]
    parts = text.split()
    if len(parts) != 2 or not parts[1].isdigit() or len(parts[1]) > 5:
        return None
    host, port = parts[0], int(parts[1])
    if not 1024 <= port <= 65535 or not all(ch in _HOST_CHARS for ch in host):
        return None
    return port


_HOST_CHARS = frozenset(b"abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ0123456789.")

register_section("vrpn", VRPN, parse_vrpn)
