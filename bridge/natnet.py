"""NatNet server: visionpos as Motive's streaming engine, for OptiTrack clients (docs/interop.md).

Two UDP sockets, as Motive has them:
- command channel (default port 1510): NAT_CONNECT (bitstream negotiation) -> NAT_SERVERINFO,
  NAT_REQUEST_MODELDEF -> NAT_MODELDEF, NAT_REQUEST strings ("Bitstream", "FrameRate", ...),
  NAT_KEEPALIVE, NAT_ECHOREQUEST, NAT_DISCONNECT; anything else -> NAT_UNRECOGNIZED_REQUEST.
  Only NAT_CONNECT is answered for an address that has not connected.
- data channel (default port 1511): NAT_FRAMEOFDATA sent from the data port, to the multicast
  group, or in unicast to each connected client's address at the bitstream version it asked for.

publish() (on the server's loop) only stores the newest states in a one-slot mailbox; a sender
thread encodes and sends, the command thread answers requests. Nothing a client sends can block
fusion: a full socket buffer drops a datagram (counted), malformed input is dropped with one log
line per cause (repeated at most every LOG_INTERVAL_S with a count).
"""

from __future__ import annotations

import ipaddress
import logging
import math
import socket
import struct
import threading
import time
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

import visionpos
from bridge import natnet_packets as nn
from bridge.convert import pose_at
from bridge.transport import RateGrid
from visionpos.config.arena import ArenaConfig, BodyConfig
from visionpos.config.schema import register_section
from visionpos.config.settings import Setting, section
from visionpos.geometry.rotations import matrix_from_quat
from visionpos.messages import BodyState, LoosePoints
from visionpos.server.sinks import Sink

log = logging.getLogger(__name__)

LOG_INTERVAL_S = 10.0
APP_NAME = "visionpos"
BITSTREAMS = tuple(f"{a}.{b}" for a, b in nn.VERSIONS)
# Timeline commands a live system accepts with nothing to do (clients send them around a bitstream change).
LIVE_NOOPS = frozenset({"TimelinePlay", "TimelineStop", "SetPlaybackStartFrame", "SetPlaybackStopFrame",
                        "SetPlaybackLooping", "SetPlaybackCurrentFrame", "LiveMode"})

NATNET = section(
    "natnet",
    "NatNet server: the poses as Motive streams them, for OptiTrack clients (docs/interop.md).",
    Setting("enabled", "boolean", True, "false: the section is ignored"),
    Setting("transmission", "text", "multicast", "frames to the multicast group or to each connected client",
            choices=("multicast", "unicast")),
    Setting("interface", "text", "0.0.0.0", "IPv4 address the command and data sockets bind to; multicast "
            "leaves by it unless it is 0.0.0.0 (Motive's 'Local Interface')"),
    Setting("command_port", "integer", 1510, "UDP port of the command channel", min=1, max=65535),
    Setting("data_port", "integer", 1511, "UDP port frames are sent from (and to, in multicast)", min=1,
            max=65535),
    Setting("multicast_group", "text", "239.255.42.99", "IPv4 multicast group of the data channel"),
    Setting("multicast_ttl", "integer", 1, "multicast time-to-live", min=0, max=255),
    Setting("up_axis", "text", "y", "streamed world up axis: y (Motive's default) or z (visionpos's world)",
            choices=("y", "z")),
    Setting("bitstream", "text", "4.1", "NatNet version of multicast frames and of clients that ask for none",
            choices=BITSTREAMS),
    Setting("rate_hz", "number", 0.0, "frames per second (0 = every output tick)", min=0.0, max=1000.0),
    Setting("max_clients", "integer", 16, "connected clients at most (a further NAT_CONNECT is refused)",
            min=1, max=1024),
    Setting("client_timeout_s", "number", 10.0, "a client silent this long is forgotten (unicast clients "
            "send keep-alives)", min=0.5, max=86400.0),
    Setting("markers", "boolean", True, "also stream labelled (model-solved body) and unlabelled markers"),
)


@dataclass(frozen=True)
class NatNetConfig:
    """The `natnet:` section, checked (see NATNET for each key)."""

    transmission: str = NATNET["transmission"].field_default
    interface: str = NATNET["interface"].field_default
    command_port: int = NATNET["command_port"].field_default
    data_port: int = NATNET["data_port"].field_default
    multicast_group: str = NATNET["multicast_group"].field_default
    multicast_ttl: int = NATNET["multicast_ttl"].field_default
    up_axis: str = NATNET["up_axis"].field_default
    bitstream: tuple[int, int] = (4, 1)
    rate_hz: float = NATNET["rate_hz"].field_default
    max_clients: int = NATNET["max_clients"].field_default
    client_timeout_s: float = NATNET["client_timeout_s"].field_default
    markers: bool = NATNET["markers"].field_default

    @property
    def multicast(self) -> bool:
        return self.transmission == "multicast"


def parse_natnet(arena: ArenaConfig) -> NatNetConfig | None:
    """Validate `natnet:`; None when absent or `enabled: false`."""
    if not arena.given("natnet"):
        return None
    s = NATNET.check(arena.section("natnet"))
    N = NATNET
    if not N.read(s, "enabled"):
        return None
    iface = N.read(s, "interface")
    try:
        ipaddress.IPv4Address(iface)
    except ValueError:
        raise s.error("interface", f"expected the IPv4 address of a local interface (or 0.0.0.0), got {iface!r}") \
            from None
    group = N.read(s, "multicast_group")
    try:
        ok = ipaddress.IPv4Address(group).is_multicast
    except ValueError:
        ok = False
    if not ok:
        raise s.error("multicast_group", f"expected an IPv4 multicast address (224.0.0.0-239.255.255.255, "
                                         f"Motive's default 239.255.42.99), got {group!r}")
    cmd, data = N.read(s, "command_port"), N.read(s, "data_port")
    if cmd == data:
        raise s.error("data_port", f"must differ from command_port ({cmd}); Motive uses 1510 and 1511")
    for b in arena.bodies:
        if len(b.name.encode()) >= nn.NAME_FIELD or "\0" in b.name:
            raise s.error("enabled", f"body name {b.name!r} cannot be streamed over NatNet (at most 255 bytes, "
                                     "no NUL); rename the body")
    major, minor = (int(x) for x in N.read(s, "bitstream").split("."))
    return NatNetConfig(
        transmission=N.read(s, "transmission"), interface=iface, command_port=cmd, data_port=data,
        multicast_group=group, multicast_ttl=N.read(s, "multicast_ttl"), up_axis=N.read(s, "up_axis"),
        bitstream=(major, minor), rate_hz=N.read(s, "rate_hz"), max_clients=N.read(s, "max_clients"),
        client_timeout_s=N.read(s, "client_timeout_s"), markers=N.read(s, "markers"),
    )


register_section("natnet", NATNET, parse_natnet)


def to_stream_axes(points: np.ndarray, up_axis: str) -> np.ndarray:
    """(..., 3) world z-up (or body FLU) -> the streamed axes: y-up is (x, z, -y), a +90 deg turn about x
    that maps up (z) onto y; z-up is unchanged."""
    p = np.asarray(points, float)
    if up_axis == "z":
        return p
    return np.stack([p[..., 0], p[..., 2], -p[..., 1]], axis=-1)


def quat_to_stream_axes(q: np.ndarray, up_axis: str) -> np.ndarray:
    """Body->world quaternion (x y z w) re-expressed with both frames in the streamed axes: the vector part
    turns like a point (a level body facing +x is the identity in both)."""
    q = np.asarray(q, float)
    if up_axis == "z":
        return q
    return np.stack([q[..., 0], q[..., 2], -q[..., 1], q[..., 3]], axis=-1)


class _Notes:
    """One log line per cause, repeated at most every LOG_INTERVAL_S with the count since."""

    def __init__(self, clock_ns: Callable[[], int]):
        self.clock_ns = clock_ns
        self.counts: dict[str, int] = {}
        self._last: dict[str, tuple[int, int]] = {}  # cause -> (logged at ns, count then)

    def __call__(self, cause: str, detail: str = "") -> None:
        n = self.counts.get(cause, 0) + 1
        self.counts[cause] = n
        now = self.clock_ns()
        last = self._last.get(cause)
        if last is None or now - last[0] >= LOG_INTERVAL_S * 1e9:
            since = n - (last[1] if last else 0)
            log.warning("natnet: %s%s (%d time%s%s)", cause, f": {detail}" if detail else "", since,
                        "" if since == 1 else "s", " since the last report" if last else "")
            self._last[cause] = (now, n)


@dataclass
class _Client:
    version: tuple[int, int]
    last_ns: int


class NatNetServer(Sink):
    """Sink: NatNetServer(cfg, bodies) or NatNetServer.from_arena(arena); start(), publish(states),
    publish_markers(points), stats(), close(). Timestamps are on clock_ns (the server's monotonic clock,
    the one BodyState times are on), sent as ticks of 1 ns."""

    def __init__(self, cfg: NatNetConfig, bodies: tuple[BodyConfig, ...] | list[BodyConfig],
                 clock_ns: Callable[[], int] = time.monotonic_ns):
        self.cfg = cfg
        self.clock_ns = clock_ns
        self.models = {b.id: nn.BodyModel(b.name, b.id, to_stream_axes(np.asarray(b.markers, float).reshape(-1, 3),
                                                                        cfg.up_axis)) for b in bodies}
        self._body_markers = {b.id: np.asarray(b.markers, float).reshape(-1, 3) for b in bodies}
        self._marker_size = {b.id: float(b.marker_diameter) for b in bodies}
        self._modeldef = {v: nn.model_definitions(list(self.models.values()), v) for v in nn.VERSIONS}
        self.note = _Notes(clock_ns)
        self.counters = {"frames": 0, "datagrams": 0, "bytes": 0, "send_errors": 0, "skipped_rate": 0,
                         "requests": 0, "replies": 0, "dropped_requests": 0, "connects": 0, "refused": 0}
        self._clients: dict[tuple[str, int], _Client] = {}
        self._lock = threading.Lock()  # guards _slot, _loose, _clients
        self._slot: tuple[list[BodyState], LoosePoints | None, int] | None = None
        self._loose: LoosePoints | None = None
        self._wake = threading.Event()
        self._running = False
        self._threads: list[threading.Thread] = []
        self.cmd_sock: socket.socket | None = None
        self.data_sock: socket.socket | None = None
        self._grid = RateGrid(cfg.rate_hz)
        self._frame_number = 0
        self._start_ns = 0
        self._last_frame: nn.Frame | None = None
        self._interval_ns = 0.0  # smoothed spacing of published frames, for the FrameRate request
        self._last_publish_ns = 0
        v = [int(x) for x in visionpos.__version__.split(".")[:4] if x.isdigit()]
        self._app_version = tuple((v + [0, 0, 0, 0])[:4])

    @classmethod
    def from_arena(cls, arena: ArenaConfig, clock_ns: Callable[[], int] = time.monotonic_ns) -> "NatNetServer | None":
        cfg = parse_natnet(arena)
        return None if cfg is None else cls(cfg, arena.bodies, clock_ns)

    # ---- lifecycle -------------------------------------------------------------------------------

    def opens(self) -> dict[str, Any]:
        return {"natnet.interface": self.cfg.interface, "natnet.command_port": self.cfg.command_port,
                "natnet.data_port": self.cfg.data_port}

    def start(self) -> None:
        """Open both sockets (OSError when a port is taken) and start the command and sender threads."""
        cfg = self.cfg
        cmd = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        data = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            cmd.bind((cfg.interface, cfg.command_port))
            cmd.settimeout(0.2)
            # Clients on this host bind the data port too (libmotioncapture does, with SO_REUSEADDR).
            data.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            data.bind((cfg.interface, cfg.data_port))
            if hasattr(socket, "IP_MULTICAST_ALL"):  # send-only: never queue group traffic on this socket
                data.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_ALL, 0)
            if cfg.multicast:
                data.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, cfg.multicast_ttl)
                data.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_LOOP, 1)
                if cfg.interface != "0.0.0.0":
                    data.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF, socket.inet_aton(cfg.interface))
            data.setblocking(False)
        except BaseException:
            cmd.close()
            data.close()
            raise
        self.cmd_sock, self.data_sock = cmd, data
        self.command_port = cmd.getsockname()[1]
        self.data_port = data.getsockname()[1]
        self._start_ns = self.clock_ns()
        self._running = True
        self._threads = [threading.Thread(target=self._command_loop, name="natnet-command", daemon=True),
                         threading.Thread(target=self._send_loop, name="natnet-sender", daemon=True)]
        for t in self._threads:
            t.start()

    def close(self) -> None:
        self._running = False
        self._wake.set()
        for t in self._threads:
            t.join(timeout=2.0)
        self._threads = []
        for s in (self.cmd_sock, self.data_sock):
            if s is not None:
                s.close()
        self.cmd_sock = self.data_sock = None

    # ---- sink interface (server loop) ------------------------------------------------------------

    def publish(self, states: list[BodyState]) -> None:
        """Hand the newest states to the sender thread (rate-limited to rate_hz). Never blocks."""
        if not self._running:
            return
        now = self.clock_ns()
        if not self._grid.due(now):
            self.counters["skipped_rate"] += 1
            return
        if self._last_publish_ns:
            dt = now - self._last_publish_ns
            self._interval_ns = dt if not self._interval_ns else 0.9 * self._interval_ns + 0.1 * dt
        self._last_publish_ns = now
        with self._lock:
            self._slot = (list(states), self._loose, now)
            self._loose = None  # each set of loose markers goes out once, never repeated stale
        self._wake.set()

    def publish_markers(self, lp: LoosePoints) -> None:
        if self.cfg.markers:
            with self._lock:
                self._loose = lp

    def stats(self) -> dict:
        with self._lock:
            clients = {f"{h}:{p}": f"{c.version[0]}.{c.version[1]}" for (h, p), c in self._clients.items()}
        return dict(self.counters, clients=clients, causes=dict(self.note.counts),
                    transmission=self.cfg.transmission, up_axis=self.cfg.up_axis)

    # ---- frames ----------------------------------------------------------------------------------

    def build_frame(self, states: list[BodyState], loose: LoosePoints | None, ready_ns: int) -> nn.Frame:
        """States (world z-up) -> one frame in the streamed axes. Every pose is moved to the frame's
        CameraMidExposureTimestamp, the newest capture time among the states (bridge.convert.pose_at), as
        Motive's poses are at their frame's mid-exposure and clients stamp them so. An untracked body (or one
        with a non-finite pose) is sent as not valid at the origin with identity orientation, never stale."""
        up = self.cfg.up_axis
        bodies, sets, labeled = [], [], []
        capture = max((int(st.capture_ns) for st in states), default=0)
        zero, ident = np.zeros(3), np.array([0.0, 0.0, 0.0, 1.0])
        for st in states:
            ok = bool(st.tracked) and bool(np.all(np.isfinite(st.position)) and np.all(np.isfinite(st.quaternion)))
            if ok:
                position, quaternion = pose_at(st, capture)
                ok = bool(np.all(np.isfinite(position)) and np.all(np.isfinite(quaternion)))
            if not ok:
                bodies.append((st.body_id, zero, ident, 0.0, False))
                if self.cfg.markers and st.body_id in self.models:
                    sets.append((st.name, np.zeros((0, 3))))
                continue
            err = float(st.residual_mm) * 1e-3 if math.isfinite(st.residual_mm) else 0.0
            bodies.append((st.body_id, to_stream_axes(position, up), quat_to_stream_axes(quaternion, up), err, True))
            m = self._body_markers.get(st.body_id)
            if self.cfg.markers and m is not None:
                world = position + m @ matrix_from_quat(quaternion).T
                pts = to_stream_axes(world, up)
                sets.append((st.name, pts))
                flags = nn.MARKER_MODEL_SOLVED | nn.MARKER_HAS_MODEL
                labeled += [((st.body_id << 16) | (k + 1), p, flags, err) for k, p in enumerate(pts)]
        if loose is not None and self.cfg.markers:
            pts = to_stream_axes(np.asarray(loose.points, float).reshape(-1, 3), up)
            # residual 0: ours is in pixels, NatNet's in metres
            labeled += [(k + 1, p, nn.MARKER_UNLABELED, 0.0) for k, p in enumerate(pts) if np.all(np.isfinite(p))]
        if not states:
            capture = ready_ns
        self._frame_number += 1
        return nn.Frame(frame_number=self._frame_number, timestamp_s=(ready_ns - self._start_ns) * 1e-9,
                        mid_exposure_ticks=max(capture, 0), data_ready_ticks=ready_ns, bodies=bodies,
                        marker_sets=sets, labeled=labeled)

    def _encode(self, frame: nn.Frame, version: tuple[int, int], cache: dict) -> bytes:
        head = cache.get(version)
        if head is None:
            head = cache[version] = nn.frame_body(frame, version)
            if len(head) + 64 > nn.MAX_PAYLOAD and (frame.marker_sets or frame.labeled):
                self.note("frame too large for one datagram, markers left out")
                slim = nn.Frame(frame.frame_number, frame.timestamp_s, frame.mid_exposure_ticks,
                                frame.data_ready_ticks, frame.bodies, [], [])
                head = cache[version] = nn.frame_body(slim, version)
        return nn.frame_packet(head, nn.transmit_suffix(frame, version, self.clock_ns()))

    def _destinations(self) -> list[tuple[tuple[str, int], tuple[int, int]]]:
        if self.cfg.multicast:
            return [((self.cfg.multicast_group, self.data_port), self.cfg.bitstream)]
        with self._lock:
            return [(addr, c.version) for addr, c in self._clients.items()]

    def _send(self, pkt: bytes, addr: tuple[str, int]) -> None:
        try:
            self.data_sock.sendto(pkt, addr)
            self.counters["datagrams"] += 1
            self.counters["bytes"] += len(pkt)
        except OSError as e:  # buffer full, no route, refused: drop, never block
            self.counters["send_errors"] += 1
            self.note("send failed", f"{addr[0]}:{addr[1]}: {e.strerror or e}")

    def _send_loop(self) -> None:
        while self._running:
            self._wake.wait(0.5)
            self._wake.clear()
            with self._lock:
                item, self._slot = self._slot, None
            if item is None or not self._running:
                continue
            try:
                frame = self.build_frame(*item)
                self._last_frame = frame
                cache: dict = {}
                for addr, version in self._destinations():
                    self._send(self._encode(frame, version, cache), addr)
                self.counters["frames"] += 1
            except Exception:  # a bad state must not end the stream
                self.note("frame could not be built")
                log.debug("natnet frame", exc_info=True)

    # ---- command channel -------------------------------------------------------------------------

    def _command_loop(self) -> None:
        sock = self.cmd_sock
        next_sweep = 0
        while self._running:
            try:
                data, addr = sock.recvfrom(65535)
            except socket.timeout:
                data = None
            except OSError:
                if not self._running:
                    return
                self.note("command socket error")
                time.sleep(0.05)
                continue
            now = self.clock_ns()
            if data is not None:
                try:
                    replies = self.handle(data, addr, now)
                except Exception:  # hostile input must never end the command channel
                    self.note("request could not be handled", f"from {addr[0]}")
                    log.debug("natnet request", exc_info=True)
                    replies = []
                for r in replies:
                    try:
                        sock.sendto(r, addr)
                        self.counters["replies"] += 1
                    except OSError as e:
                        self.note("reply failed", str(e.strerror or e))
            if now >= next_sweep:
                self._expire(now)
                next_sweep = now + 500_000_000

    def _expire(self, now: int) -> None:
        limit = int(self.cfg.client_timeout_s * 1e9)
        with self._lock:
            for addr in [a for a, c in self._clients.items() if now - c.last_ns > limit]:
                del self._clients[addr]
                log.info("natnet: client %s:%d silent for %.1f s, forgotten", addr[0], addr[1],
                         self.cfg.client_timeout_s)

    def handle(self, data: bytes, addr: tuple[str, int], now_ns: int) -> list[bytes]:
        """One command datagram -> the replies to send back to addr (a frame request is sent here)."""
        self.counters["requests"] += 1
        if len(data) < 4:
            return self._drop("datagram shorter than the 4-byte header", addr)
        msg, n = struct.unpack_from("<HH", data)
        payload = data[4:4 + n]
        if len(payload) < n:
            return self._drop("datagram shorter than its byte count", addr)
        if msg == nn.NAT_CONNECT:
            return self._connect(payload, addr, now_ns)
        with self._lock:
            client = self._clients.get(addr)
            if client is not None:
                client.last_ns = now_ns
        if client is None:
            return self._drop("request from an address that has not sent NAT_CONNECT", addr)
        if msg == nn.NAT_KEEPALIVE:
            return []
        if msg == nn.NAT_DISCONNECT:
            with self._lock:
                self._clients.pop(addr, None)
            log.info("natnet: client %s:%d disconnected", addr[0], addr[1])
            return []
        if msg == nn.NAT_REQUEST_MODELDEF:
            return [self._modeldef[client.version]]
        if msg == nn.NAT_ECHOREQUEST:
            r = nn.echo_response(payload, now_ns)
            return [r] if r is not None else self._drop("NAT_ECHOREQUEST without its 8-byte stamp", addr)
        if msg == nn.NAT_REQUEST_FRAMEOFDATA:
            frame = self._last_frame
            if frame is not None and self.data_sock is not None:
                self._send(self._encode(frame, client.version, {}), addr)
            return []
        if msg == nn.NAT_REQUEST:
            return [self._request(payload, client, addr)]
        self.note("unknown message id", f"{msg} from {addr[0]}")
        return [nn.unrecognized()]

    def _drop(self, cause: str, addr: tuple[str, int]) -> list[bytes]:
        self.counters["dropped_requests"] += 1
        self.note(cause, f"from {addr[0]}:{addr[1]}")
        return []

    def _connect(self, payload: bytes, addr: tuple[str, int], now_ns: int) -> list[bytes]:
        asked = nn.connect_version(payload)
        version = self.cfg.bitstream if self.cfg.multicast else nn.supported_version(asked, self.cfg.bitstream)
        with self._lock:
            if addr not in self._clients and len(self._clients) >= self.cfg.max_clients:
                limit = int(self.cfg.client_timeout_s * 1e9)
                stale = [a for a, c in self._clients.items() if now_ns - c.last_ns > limit]
                for a in stale:
                    del self._clients[a]
                full = len(self._clients) >= self.cfg.max_clients
            else:
                full = False
            if not full:
                new = addr not in self._clients
                self._clients[addr] = _Client(version, now_ns)
        if full:
            self.counters["refused"] += 1
            self.note("client limit reached, NAT_CONNECT refused", f"{addr[0]}:{addr[1]} (max_clients "
                                                                    f"{self.cfg.max_clients})")
            return [nn.packet(nn.NAT_MESSAGESTRING,
                              f"{APP_NAME}: client limit ({self.cfg.max_clients}) reached".encode() + b"\0")]
        self.counters["connects"] += 1
        if new:
            log.info("natnet: client %s:%d connected, bitstream %d.%d", addr[0], addr[1], *version)
        return [nn.server_info(APP_NAME, self._app_version, version, self.data_port, self.cfg.multicast,
                               self.cfg.multicast_group)]

    def _request(self, payload: bytes, client: _Client, addr: tuple[str, int]) -> bytes:
        raw = payload.split(b"\0", 1)[0]
        try:
            text = raw.decode("ascii")
        except UnicodeDecodeError:
            self.note("NAT_REQUEST that is not ASCII text", f"from {addr[0]}")
            return nn.unrecognized()
        name, comma, arg = text.partition(",")
        if name == "Bitstream":
            if not comma:
                return nn.response_text(f"Bitstream,{client.version[0]}.{client.version[1]}")
            v = nn.parse_version(arg)
            if self.cfg.multicast or v not in nn.VERSIONS:
                # multicast: every client shares one stream; other versions: not produced
                self.note("bitstream change refused", f"{arg!r} from {addr[0]} ({self.cfg.transmission})")
                return nn.response_int(1)
            with self._lock:
                client.version = v
            log.info("natnet: client %s:%d now at bitstream %d.%d", addr[0], addr[1], *v)
            return nn.response_int(0)
        if name == "FrameRate":
            rate = 1e9 / self._interval_ns if self._interval_ns else self.cfg.rate_hz
            return nn.response_float(rate)
        if name == "UnitsToMillimeters":
            return nn.response_float(1000.0)  # positions are in metres
        if name == "CurrentMode":
            return nn.response_int(0)  # live
        if name in LIVE_NOOPS:
            return nn.response_int(0)
        self.note("unrecognized NAT_REQUEST", f"{name[:40]!r} from {addr[0]}")
        return nn.unrecognized()
