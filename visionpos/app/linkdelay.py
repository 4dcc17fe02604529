"""A loopback UDP relay that delays a MAVLink link by a fixed time each way (`visionpos sitl --link-delay-ms`).

    SITL SERIAL1 udpclient --> 127.0.0.1:relay.port  [held D ms]  --> the bridge's udpin endpoint
    SITL                   <--                       [held D ms]  <-- the bridge's replies

Every datagram is held D ms from the moment the relay reads it, then sent on: each direction is a FIFO
(a fixed delay keeps the order), nothing is dropped (the queues are unbounded; a loopback link of a few
hundred packets/s holds a few dozen at 50 ms). One thread serves both sockets; it ends on stop(), or
by itself lifetime_s after start(), so a caller that dies cannot leave it running.

The autopilot side follows the newest sender on 127.0.0.1 (SITL's udpclient port changes when it
reboots; the socket is bound to loopback only). Replies go to that sender. Only the bridge's address
is taken on the bridge side.

holds: for each datagram sent on towards the bridge or towards the autopilot, (send time, how long it was
held: send time less read time), time.monotonic_ns: D plus the thread's lateness, the figure the SITL
delay benchmark adds to the bridge's own stamp-to-send time.
"""

from __future__ import annotations

import collections
import selectors
import socket
import statistics
import threading
import time
from typing import Callable

RECV_BYTES = 65535


class RelayThread:
    """A relay's thread and sockets: start() runs _run on its own thread, stop() ends it and closes _sockets();
    a context manager. Subclasses call super().__init__() and give _run, _sockets and thread_name."""

    thread_name = "relay"

    def __init__(self) -> None:
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def _run(self) -> None:
        raise NotImplementedError

    def _sockets(self) -> list[socket.socket]:
        raise NotImplementedError

    def start(self):
        self._thread = threading.Thread(target=self._run, name=self.thread_name, daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(2.0)
            self._thread = None
        for s in self._sockets():
            s.close()

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()


class DelayRelay(RelayThread):
    """UDP relay on 127.0.0.1 holding each datagram delay_ms in both directions; see the module docstring.

    target: the bridge's (host, port); port: where the autopilot side sends (0: any free port)."""

    def __init__(self, target: tuple[str, int], delay_ms: float, port: int = 0, lifetime_s: float = 600.0):
        if not 0.0 <= delay_ms <= 1000.0:
            raise ValueError(f"link delay {delay_ms} ms: give 0 to 1000 ms")
        self.target = (socket.gethostbyname(target[0]), int(target[1]))
        self.delay_ns = int(round(delay_ms * 1e6))
        self.lifetime_s = float(lifetime_s)
        self.ap_sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.ap_sock.bind(("127.0.0.1", port))
        self.port = self.ap_sock.getsockname()[1]
        self.bridge_sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.bridge_sock.bind(("127.0.0.1", 0))
        for s in (self.ap_sock, self.bridge_sock):
            s.setblocking(False)
        self.ap_peer: tuple[str, int] | None = None
        self._to_bridge: collections.deque[tuple[int, bytes]] = collections.deque()
        self._to_ap: collections.deque[tuple[int, bytes]] = collections.deque()
        self.holds: dict[str, list[tuple[int, int]]] = {"to_bridge": [], "to_autopilot": []}
        self.unsent = 0  # datagrams to the autopilot before it had sent anything (no address yet)
        self.send_errors = 0
        # tap(read_ns, datagram): sees each datagram from the autopilot as it is read (on the relay's thread;
        # keep it cheap); the SITL harness reads its own TIMESYNC answers there
        self.tap: Callable[[int, bytes], None] | None = None
        super().__init__()

    thread_name = "link-delay-relay"

    def _sockets(self) -> list[socket.socket]:
        return [self.ap_sock, self.bridge_sock]

    def _run(self) -> None:
        end = time.monotonic_ns() + int(self.lifetime_s * 1e9)
        sel = selectors.DefaultSelector()
        sel.register(self.ap_sock, selectors.EVENT_READ, "ap")
        sel.register(self.bridge_sock, selectors.EVENT_READ, "bridge")
        try:
            while not self._stop.is_set():
                now = time.monotonic_ns()
                if now >= end:
                    return
                self._flush(now)
                due = [q[0][0] for q in (self._to_bridge, self._to_ap) if q]
                # wake for the next due datagram; at most every 0.1 s to see stop()
                wait_ns = min([100_000_000, end - now] + [d - now for d in due])
                for key, _ in sel.select(max(0.0, wait_ns * 1e-9)):
                    self._read(key.data)
        finally:
            sel.close()

    def _read(self, side: str) -> None:
        sock = self.ap_sock if side == "ap" else self.bridge_sock
        while True:  # drain: several may have arrived during one wait
            try:
                data, addr = sock.recvfrom(RECV_BYTES)
            except OSError:  # BlockingIOError: drained
                return
            now = time.monotonic_ns()
            if side == "ap":
                if addr[0] != "127.0.0.1":
                    continue
                self.ap_peer = addr
                self._to_bridge.append((now + self.delay_ns, data))
                if self.tap is not None:
                    self.tap(now, data)
            else:
                if addr != self.target:
                    continue
                self._to_ap.append((now + self.delay_ns, data))

    def _flush(self, now: int) -> None:
        for q, sock, name in ((self._to_bridge, self.bridge_sock, "to_bridge"), (self._to_ap, self.ap_sock,
                                                                                   "to_autopilot")):
            while q and q[0][0] <= now:
                due, data = q.popleft()
                dest = self.target if name == "to_bridge" else self.ap_peer
                if dest is None:
                    self.unsent += 1
                    continue
                # recorded before the send: whatever answers the datagram finds its hold already counted
                sent = time.monotonic_ns()
                self.holds[name].append((sent, sent - due + self.delay_ns))
                try:
                    sock.sendto(data, dest)
                except OSError:
                    self.send_errors += 1
                    self.holds[name].pop()

    def send_to_autopilot(self, data: bytes) -> int | None:
        """Send a datagram of our own to the autopilot now, unheld (any thread); the clock read just before the
        write, or None without an autopilot address yet or on an error."""
        peer = self.ap_peer
        if peer is None:
            return None
        t = time.monotonic_ns()
        try:
            self.ap_sock.sendto(data, peer)
        except OSError:
            return None
        return t

    def hold_ms_median(self, direction: str, since_ns: int = 0, until_ns: int | None = None) -> float | None:
        """Median hold (ms) of the datagrams sent on in direction ('to_bridge', 'to_autopilot') between since_ns
        and until_ns (send times; no end when None)."""
        end = until_ns if until_ns is not None else float("inf")
        h = [d for t, d in list(self.holds[direction]) if since_ns <= t <= end]  # list(): a copy under the GIL
        return statistics.median(h) * 1e-6 if h else None
