"""Non-blocking byte links for one MAVLink endpoint: udpin, udpout, tcp, serial.

Each link exposes fileno() for select, read() -> list of (bytes, address),
write(bytes) that never blocks, and open()/close(). Stream links (tcp,
serial) keep a bounded outgoing buffer so a packet is either written whole
or dropped whole; a full buffer drops the newest packet rather than
stalling the sender. Errors raise LinkDown; the owner reopens with backoff.

Why not mavutil's connections: its udpin answers every address that ever
wrote to the port (a second sender on a vehicle's port would receive that
vehicle's poses), and its tcp reconnect sleeps and prints inside read/write.
"""

from __future__ import annotations

import abc
import errno
import os
import socket

from bridge.config import Endpoint

STREAM_BUFFER_MAX = 64 * 1024


def pack_datagrams(chunks, max_bytes: int) -> list[bytes]:
    """Byte strings -> UDP payloads of whole chunks, each at most max_bytes (a chunk is never split, so a
    single chunk longer than max_bytes goes alone)."""
    out: list[bytes] = []
    cur = bytearray()
    for c in chunks:
        if cur and len(cur) + len(c) > max_bytes:
            out.append(bytes(cur))
            cur = bytearray()
        cur += c
    if cur:
        out.append(bytes(cur))
    return out


class RateGrid:
    """Output ticks on an even grid of 1/rate_hz (rate_hz <= 0: every call is due); after a pause the grid
    restarts near now instead of bursting to catch up."""

    __slots__ = ("period_ns", "next_ns")

    def __init__(self, rate_hz: float):
        self.period_ns = int(1e9 / rate_hz) if rate_hz > 0 else 0
        self.next_ns = 0

    def due(self, now_ns: int) -> bool:
        """True when an output is due at now_ns (and the grid moves on)."""
        if not self.period_ns:
            return True
        if now_ns < self.next_ns:
            return False
        self.next_ns = max(self.next_ns + self.period_ns, now_ns - self.period_ns // 2)
        return True


class LinkDown(Exception):
    """The link failed; str() says why. The owner closes and reopens it."""


class Link(abc.ABC):
    """One open endpoint. write() returns False when the packet was not sent (no peer yet, buffer full)."""

    kind = ""
    fixed = False  # udpin with a configured autopilot address: the peer never moves

    def __init__(self, endpoint: Endpoint):
        self.endpoint = endpoint
        self.peer: tuple | None = None  # where write() sends (udpin: learned)

    @abc.abstractmethod
    def open(self) -> None: ...

    @abc.abstractmethod
    def fileno(self) -> int: ...

    @abc.abstractmethod
    def read(self) -> list[tuple[bytes, tuple | None]]: ...

    @abc.abstractmethod
    def write(self, buf: bytes) -> bool: ...

    @abc.abstractmethod
    def close(self) -> None: ...

    def wants_write(self) -> bool:
        return False

    def flush(self) -> None:
        return None


class UdpLink(Link):
    """udpin: bind HOST:PORT, answer the peer (fixed_peer, or learned by the owner). udpout: send to HOST:PORT.

    fixed_peer (udpin only): (host, port) the autopilot sends from; it is resolved at open() and
    is then the only peer (`fixed` is True: the owner drops datagrams from anywhere else).
    """

    def __init__(self, endpoint: Endpoint, fixed_peer: tuple[str, int] | None = None):
        super().__init__(endpoint)
        self.kind = endpoint.kind
        self.sock: socket.socket | None = None
        self.fixed_peer = fixed_peer
        self.fixed = False

    def open(self) -> None:
        s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            if self.kind == "udpin":
                s.bind((self.endpoint.host, self.endpoint.port))
                if self.fixed_peer is not None:
                    self.peer = (socket.gethostbyname(self.fixed_peer[0]), self.fixed_peer[1])
                    self.fixed = True
            else:
                self.peer = (socket.gethostbyname(self.endpoint.host), self.endpoint.port)
        except OSError as e:
            s.close()
            raise LinkDown(f"{self.endpoint}: {e.strerror or e}") from None
        s.setblocking(False)
        self.sock = s

    def fileno(self) -> int:
        return self.sock.fileno()

    def local_port(self) -> int:
        return self.sock.getsockname()[1]

    def read(self) -> list[tuple[bytes, tuple | None]]:
        out = []
        while True:
            try:
                data, addr = self.sock.recvfrom(65535)
            except (BlockingIOError, InterruptedError):
                return out
            except ConnectionRefusedError:
                continue  # ICMP from an earlier send to a closed port: not fatal for UDP
            except OSError as e:
                raise LinkDown(f"{self.endpoint}: receive failed: {e.strerror or e}") from None
            out.append((data, addr))

    def write(self, buf: bytes) -> bool:
        if self.peer is None:
            return False
        try:
            self.sock.sendto(buf, self.peer)
            return True
        except (BlockingIOError, ConnectionRefusedError):
            return False
        except OSError as e:
            raise LinkDown(f"{self.endpoint}: send failed: {e.strerror or e}") from None

    def close(self) -> None:
        if self.sock is not None:
            self.sock.close()
            self.sock = None


class _StreamLink(Link):
    """Shared buffering for tcp and serial."""

    def __init__(self, endpoint: Endpoint):
        super().__init__(endpoint)
        self.out = bytearray()
        self.dropped_full = 0

    @abc.abstractmethod
    def _send_some(self, data: bytes) -> int: ...

    def write(self, buf: bytes) -> bool:
        if self.out:
            if len(self.out) + len(buf) > STREAM_BUFFER_MAX:
                self.dropped_full += 1
                return False
            self.out += buf
            self.flush()
            return True
        n = self._send_some(buf)
        if n < len(buf):
            self.out += buf[n:]
        return True

    def wants_write(self) -> bool:
        return bool(self.out)

    def flush(self) -> None:
        if self.out:
            n = self._send_some(bytes(self.out))
            del self.out[:n]


class TcpLink(_StreamLink):
    """tcp: connect to HOST:PORT (autopilot, SITL 5760, a companion's router)."""

    kind = "tcp"

    def __init__(self, endpoint: Endpoint, connect_timeout_s: float = 1.0):
        super().__init__(endpoint)
        self.sock: socket.socket | None = None
        self.connect_timeout_s = connect_timeout_s

    def open(self) -> None:
        try:
            s = socket.create_connection((self.endpoint.host, self.endpoint.port), timeout=self.connect_timeout_s)
        except OSError as e:
            raise LinkDown(f"{self.endpoint}: connect failed: {e.strerror or e}") from None
        s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        s.setblocking(False)
        self.sock = s
        self.peer = (self.endpoint.host, self.endpoint.port)
        self.out.clear()

    def fileno(self) -> int:
        return self.sock.fileno()

    def read(self) -> list[tuple[bytes, tuple | None]]:
        try:
            data = self.sock.recv(65536)
        except (BlockingIOError, InterruptedError):
            return []
        except OSError as e:
            raise LinkDown(f"{self.endpoint}: {e.strerror or e}") from None
        if not data:
            raise LinkDown(f"{self.endpoint}: closed by the other end")
        return [(data, self.peer)]

    def _send_some(self, data: bytes) -> int:
        try:
            return self.sock.send(data)
        except (BlockingIOError, InterruptedError):
            return 0
        except OSError as e:
            raise LinkDown(f"{self.endpoint}: send failed: {e.strerror or e}") from None

    def close(self) -> None:
        if self.sock is not None:
            self.sock.close()
            self.sock = None


class SerialLink(_StreamLink):
    """serial: DEVICE at BAUD, 8N1, raw, through pyserial for the port setup."""

    kind = "serial"

    def __init__(self, endpoint: Endpoint):
        super().__init__(endpoint)
        self.port = None
        self.fd = -1

    def open(self) -> None:
        try:
            import serial  # pyserial, pymavlink's serial dependency
        except ImportError:
            raise LinkDown(f"{self.endpoint}: serial links need pyserial (pip install pyserial)") from None
        try:
            self.port = serial.Serial(self.endpoint.device, self.endpoint.baud, timeout=0, write_timeout=0)
        except (OSError, serial.SerialException, ValueError) as e:
            raise LinkDown(f"{self.endpoint}: cannot open: {e}") from None
        self.fd = self.port.fileno()
        os.set_blocking(self.fd, False)
        self.peer = (self.endpoint.device,)
        self.out.clear()

    def fileno(self) -> int:
        return self.fd

    def read(self) -> list[tuple[bytes, tuple | None]]:
        try:
            data = os.read(self.fd, 4096)
        except (BlockingIOError, InterruptedError):
            return []
        except OSError as e:
            if e.errno == errno.EAGAIN:
                return []
            raise LinkDown(f"{self.endpoint}: {e.strerror or e}") from None
        if not data:
            raise LinkDown(f"{self.endpoint}: device hung up")
        return [(data, self.peer)]

    def _send_some(self, data: bytes) -> int:
        try:
            return os.write(self.fd, data)
        except (BlockingIOError, InterruptedError):
            return 0
        except OSError as e:
            raise LinkDown(f"{self.endpoint}: write failed: {e.strerror or e}") from None

    def close(self) -> None:
        if self.port is not None:
            try:
                self.port.close()
            except OSError:
                pass
            self.port = None
            self.fd = -1


def make_link(endpoint: Endpoint, fixed_peer: tuple[str, int] | None = None) -> Link:
    """The link for an endpoint; fixed_peer: a udpin endpoint's configured autopilot address."""
    if endpoint.kind in ("udpin", "udpout"):
        return UdpLink(endpoint, fixed_peer)
    if endpoint.kind == "tcp":
        return TcpLink(endpoint)
    if endpoint.kind == "serial":
        return SerialLink(endpoint)
    raise ValueError(f"unknown endpoint kind {endpoint.kind!r}")
