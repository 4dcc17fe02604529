"""The link-delay relay of `visionpos sitl --link-delay-ms`: both directions held D ms, in order, nothing lost."""

from __future__ import annotations

import socket
import struct
import threading
import time

import numpy as np
import pytest

from visionpos.app.linkdelay import DelayRelay


def _sock() -> socket.socket:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    s.settimeout(2.0)
    return s


def _send_and_receive(src: socket.socket, dest: tuple[str, int], sink: socket.socket, first: int,
                      n: int) -> list[tuple[int, int, int]]:
    """n numbered datagrams src -> dest, 1 ms apart, read from sink as they come (a thread):
    (sequence number, send time, arrival time) of each."""
    out: list[tuple[int, int, int]] = []

    def receive() -> None:
        for _ in range(n):
            data, _ = sink.recvfrom(100)
            seq, sent = struct.unpack("<Iq", data)
            out.append((seq, sent, time.monotonic_ns()))

    reader = threading.Thread(target=receive, daemon=True)
    reader.start()
    for i in range(n):
        src.sendto(struct.pack("<Iq", first + i, time.monotonic_ns()), dest)
        time.sleep(0.001)
    reader.join(5.0)
    return out


def _late_bound_ms(delay_ms: float) -> float:
    """Highest median latency (ms) taken as "held delay_ms": well under 2 x delay_ms for the delays tested."""
    return delay_ms + max(10.0, 0.25 * delay_ms)


@pytest.mark.parametrize("delay_ms", [0.0, 20.0, 50.0])
def test_relay_delays_both_directions_in_order(delay_ms):
    bridge, autopilot = _sock(), _sock()
    with DelayRelay(bridge.getsockname(), delay_ms, lifetime_s=20.0) as relay:
        n = 60
        up = _send_and_receive(autopilot, ("127.0.0.1", relay.port), bridge, 0, n)
        # bridge -> autopilot: replies go to the autopilot's address as the relay saw it
        down = _send_and_receive(bridge, relay.bridge_sock.getsockname(), autopilot, 1000, n)
    for got, first in ((up, 0), (down, 1000)):
        assert [s for s, _, _ in got] == list(range(first, first + n))  # order kept, none lost
        lat_ms = np.array([(t - sent) * 1e-6 for _, sent, t in got])
        # the relay never sends early (correctness); how late a loaded 2-core host wakes it is speed, so the
        # upper bound only has to catch a wrong hold (twice the delay, or the delay added in both hops)
        assert lat_ms.min() >= delay_ms - 0.05, lat_ms.min()
        assert np.median(lat_ms) <= _late_bound_ms(delay_ms), np.median(lat_ms)
    holds = np.array([h for _, h in relay.holds["to_bridge"] + relay.holds["to_autopilot"]]) * 1e-6
    assert len(holds) == 2 * n and holds.min() >= delay_ms - 0.05
    assert delay_ms <= relay.hold_ms_median("to_autopilot") <= _late_bound_ms(delay_ms)
    assert relay.unsent == 0 and not relay.running  # stopped by the context manager
    bridge.close()
    autopilot.close()


def test_relay_ignores_strangers_on_the_bridge_side_and_stops_by_itself():
    bridge, autopilot, stranger = _sock(), _sock(), _sock()
    relay = DelayRelay(bridge.getsockname(), 5.0, lifetime_s=0.5).start()
    autopilot.sendto(b"hello", ("127.0.0.1", relay.port))
    assert bridge.recvfrom(100)[0] == b"hello"
    stranger.sendto(b"not the bridge", relay.bridge_sock.getsockname())  # only the bridge's replies go through
    bridge.sendto(b"reply", relay.bridge_sock.getsockname())
    assert autopilot.recvfrom(100)[0] == b"reply"
    deadline = time.monotonic() + 3.0
    while relay.running and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not relay.running  # its lifetime ran out without stop()
    relay.stop()
    for s in (bridge, autopilot, stranger):
        s.close()


def test_relay_refuses_a_delay_out_of_range():
    with pytest.raises(ValueError, match="0 to 1000 ms"):
        DelayRelay(("127.0.0.1", 9), -1.0)
