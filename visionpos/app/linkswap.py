"""A loopback UDP relay for several vehicles' MAVLink links whose autopilots can be exchanged mid-flight: two
drones' radios swapped at the ground station, in a test or `visionpos sitl --vehicles N --swap-at S`.

    autopilot i --> 127.0.0.1:relay.autopilot_port(i) --> [leg route[i]] --> the bridge's endpoint of vehicle route[i]
    autopilot i <--                                    <-- [leg route[i]] <-- that endpoint's replies

Leg k always talks to the bridge's endpoint k from the same address, as a serial port keeps its name whichever
radio is plugged into it: after swap(i, j) the bridge hears autopilot j on vehicle i's link, from the address it
learned, and what it sends there reaches autopilot j. Nothing is delayed or dropped. One thread serves every
socket; it ends on stop(), or by itself lifetime_s after start().

to_autopilot: for each datagram sent on towards an autopilot, (send time, leg it came from, autopilot index),
time.monotonic_ns; with keep_data, the datagram too (tests decode the poses that reached each autopilot).
to_bridge: the same for the other direction (the first of autopilot j's datagrams on another leg is when the
bridge can first see a swap).
"""

from __future__ import annotations

import selectors
import socket
import threading
import time

from visionpos.app.linkdelay import RECV_BYTES, RelayThread


class CrossRelay(RelayThread):
    """Legs between autopilots and the bridge's endpoints on 127.0.0.1; see the module docstring.

    targets: the bridge's (host, port) of each vehicle, in the autopilots' order."""

    def __init__(self, targets: list[tuple[str, int]], lifetime_s: float = 600.0, keep_data: bool = False):
        self.targets = [(socket.gethostbyname(h), int(p)) for h, p in targets]
        self.lifetime_s = float(lifetime_s)
        self.keep_data = keep_data
        n = len(self.targets)
        self.ap_socks = [self._bound() for _ in range(n)]
        self.leg_socks = [self._bound() for _ in range(n)]
        self.ap_peers: list[tuple[str, int] | None] = [None] * n
        self.route = list(range(n))  # autopilot i talks on leg route[i]
        self.swaps: list[tuple[int, tuple[int, int]]] = []  # (monotonic ns, (i, j)) of each swap
        self.to_autopilot: list[tuple] = []
        self.to_bridge: list[tuple] = []
        self.send_errors = 0
        self._lock = threading.Lock()
        super().__init__()

    @staticmethod
    def _bound() -> socket.socket:
        s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        s.bind(("127.0.0.1", 0))
        s.setblocking(False)
        return s

    def autopilot_port(self, i: int) -> int:
        """Where autopilot i sends (its udpclient / udpout target)."""
        return self.ap_socks[i].getsockname()[1]

    def swap(self, i: int, j: int) -> int:
        """Exchange autopilots i and j's legs now (any thread); the clock at the swap."""
        with self._lock:
            self.route[i], self.route[j] = self.route[j], self.route[i]
            t = time.monotonic_ns()
            self.swaps.append((t, (i, j)))
        return t

    thread_name = "cross-relay"

    def _sockets(self) -> list[socket.socket]:
        return self.ap_socks + self.leg_socks

    def _run(self) -> None:
        end = time.monotonic() + self.lifetime_s
        sel = selectors.DefaultSelector()
        for i, s in enumerate(self.ap_socks):
            sel.register(s, selectors.EVENT_READ, ("ap", i))
        for k, s in enumerate(self.leg_socks):
            sel.register(s, selectors.EVENT_READ, ("leg", k))
        try:
            while not self._stop.is_set() and time.monotonic() < end:
                for key, _ in sel.select(0.1):
                    self._drain(*key.data)
        finally:
            sel.close()

    def _drain(self, side: str, index: int) -> None:
        sock = self.ap_socks[index] if side == "ap" else self.leg_socks[index]
        while True:
            try:
                data, addr = sock.recvfrom(RECV_BYTES)
            except OSError:  # BlockingIOError: drained
                return
            with self._lock:
                route = list(self.route)
            if side == "ap":
                if addr[0] != "127.0.0.1":
                    continue
                self.ap_peers[index] = addr
                leg = route[index]
                self._send(self.leg_socks[leg], data, self.targets[leg], self.to_bridge, leg, index)
            else:
                if addr != self.targets[index]:
                    continue
                ap = route.index(index)
                peer = self.ap_peers[ap]
                if peer is not None:
                    self._send(self.ap_socks[ap], data, peer, self.to_autopilot, index, ap)

    def _send(self, sock: socket.socket, data: bytes, dest: tuple, log: list, leg: int, ap: int) -> None:
        try:
            sock.sendto(data, dest)
        except OSError:
            self.send_errors += 1
            return
        t = time.monotonic_ns()
        log.append((t, leg, ap, data) if self.keep_data else (t, leg, ap))
