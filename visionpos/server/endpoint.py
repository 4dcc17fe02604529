"""Ingest's UDP socket on the running asyncio loop: every waiting datagram per wake-up, at most ~2 ms of work
per batch so output ticks stay on time, kernel arrival stamps for the backlog (load shedding).

UdpEndpoint is the I/O half of Ingest (ingest.py is the protocol, without I/O): it reads datagrams, hands
each to `handle(data, addr, recv_ns, backlog_ns)` and sends the replies back to the sender.
"""

from __future__ import annotations

import asyncio
import logging
import socket
import time
from collections.abc import Callable

from visionpos import protocol as P
from visionpos.server.camera_health import Addr, IngestCounters, fmt_addr
from visionpos.server.netstamps import ANC_SIZE, enable_kernel_stamps, kernel_stamp_ns
from visionpos.server.settings import ServerSettings

log = logging.getLogger("visionpos.server.ingest")  # the ingest's log, as before the split


class UdpEndpoint:
    """The socket side of Ingest. The subclass provides handle, set_start, settings and counters, and calls
    _init_endpoint() from its __init__."""

    handle: Callable[[bytes, Addr, int, int], list[bytes]]
    set_start: Callable[[], None]
    settings: ServerSettings
    counters: IngestCounters

    def _init_endpoint(self) -> None:
        self.sock: socket.socket | None = None
        self._kernel_stamps = False
        self._drained_ns = 0  # when the socket was last read empty
        self._loop: asyncio.AbstractEventLoop | None = None
        self.port: int | None = None

    async def start(self, host: str = "127.0.0.1", port: int | None = None) -> None:
        """Listen on udp host:port (port 0: any free port, see .port)."""
        loop = asyncio.get_running_loop()
        port = self.settings.port if port is None else port
        try:
            family, _, _, _, sockaddr = socket.getaddrinfo(host, port, type=socket.SOCK_DGRAM)[0]
            sock = socket.socket(family, socket.SOCK_DGRAM)
        except OSError as e:
            raise OSError(getattr(e, "errno", None), f"cannot listen on udp {host}:{port}: {e}") from None
        try:
            # a deep receive buffer rides out loop stalls (a GC pause, a slow fusion step) without loss
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4 * 2**20)
            sock.bind(sockaddr)
            # kernel arrival stamps show how long a datagram queued here (load shedding)
            self._kernel_stamps = enable_kernel_stamps(sock)
        except OSError as e:
            sock.close()
            raise OSError(e.errno, f"cannot listen on udp {host}:{port}: {e.strerror}; "
                                   "is another server running? pick another port with --port") from None
        sock.setblocking(False)
        self.sock = sock
        self._rx_buf = bytearray(P.MAX_PACKET_BYTES + 1)
        self._rx_view = memoryview(self._rx_buf)
        self.port = sock.getsockname()[1]
        self._loop = loop
        loop.add_reader(sock.fileno(), self._readable)
        self.set_start()

    def _readable(self) -> None:
        """Drain the socket: one loop wake-up handles every datagram that is waiting (asyncio's own
        datagram transport reads one per wake-up, which costs ~4x more per packet under load)."""
        sock = self.sock
        if sock is None:
            return
        handle = self.handle
        clock = time.monotonic_ns
        deadline = clock() + 2_000_000
        stamps = self._kernel_stamps
        rt_minus_mono = time.time_ns() - clock() if stamps else 0  # kernel stamps are CLOCK_REALTIME
        backlog = 0
        # one receive buffer for every datagram: a longer datagram is cut to MAX_PACKET_BYTES + 1 and refused
        # as oversize, and junk of 64 KB costs no 64 KB allocation each (a flood of it grew the heap)
        buf = self._rx_buf
        view = self._rx_view
        for _ in range(512):  # bounded in count and time, so output ticks run on time during a flood
            try:
                if stamps:
                    n, anc, _, addr = sock.recvmsg_into((buf,), ANC_SIZE)
                else:
                    n, addr = sock.recvfrom_into(buf)
                data = bytes(view[:n])
            except (BlockingIOError, InterruptedError):
                self._drained_ns = clock()
                return
            except OSError as e:  # ICMP errors from stations that went away surface here
                log.debug("udp receive error: %s", e)
                continue
            recv_ns = clock()  # first thing: this stamp is t2 of the clock sync
            if stamps:
                k = kernel_stamp_ns(anc)
                backlog = recv_ns - (k - rt_minus_mono) if k else 0
                if not 0 <= backlog < 5_000_000_000:  # the realtime clock was stepped: no measure
                    backlog = 0
            if recv_ns > deadline:
                self._readable_again(data, addr, recv_ns, backlog)
                return
            try:
                replies = handle(data, addr, recv_ns, backlog)
            except Exception:  # handle() guards itself; this is the last line of defence
                self.counters.malformed += 1
                log.exception("ingest failed on a packet from %s", fmt_addr(addr))
                continue
            for r in replies:
                try:
                    sock.sendto(r, addr)
                except OSError as e:  # full send buffer or unreachable: the station will ask again
                    self.counters.send_errors += 1
                    log.debug("udp send to %s failed: %s", fmt_addr(addr), e)

    def _readable_again(self, data: bytes, addr: Addr, recv_ns: int, backlog_ns: int) -> None:
        """Out of time in this wake-up: handle this datagram first thing next loop iteration."""
        def later() -> None:
            try:
                for r in self.handle(data, addr, recv_ns, backlog_ns):
                    if self.sock is not None:
                        self.sock.sendto(r, addr)
            except Exception:
                log.exception("ingest failed on a packet from %s", fmt_addr(addr))
        self._loop.call_soon(later)

    def close(self) -> None:
        if self.sock is not None:
            try:
                self._loop.remove_reader(self.sock.fileno())
            except Exception:
                pass
            self.sock.close()
            self.sock = None
