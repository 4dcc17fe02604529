"""The robustness benchmark's attacker builds what it claims to, and the protocol refuses it."""

from __future__ import annotations

import pytest

from visionpos import protocol as P
from visionpos.benchmarks import attacks

CAMS = [{"station_id": 1, "camera_id": 1, "session": 0x1234, "width": 960, "height": 640},
        {"station_id": 2, "camera_id": 2, "session": 0x5678, "width": 960, "height": 640}]


def _spec(kind: str, n: int = 200) -> dict:
    return {"kind": kind, "packets": n, "rate_pps": 1000.0, "server_port": 5600, "cameras": CAMS,
            "station_ports": [40001, 40002], "mavlink_ports": [14550], "sysids": [1],
            "old_hex": ["00"], "sniffed_hex": ["01"], "reply_hex": []}


@pytest.mark.parametrize("kind", sorted(attacks.ATTACKS))
def test_every_attack_builds_its_packets(kind):
    dests, packets, _ = attacks.build(_spec(kind))
    assert len(packets) == 200
    assert all(0 <= d < len(dests) for d, _ in packets)
    assert all(isinstance(p, bytes) and p for _, p in packets)


def test_malformed_packets_are_each_refused_by_the_decoder():
    _, packets, _ = attacks.build(_spec("malformed", 64))
    variants = {p for _, p in packets}
    assert len(variants) >= 12  # version, type, truncated, trailing, flag without tag, 89, 90, NaN, 0x0, fps x3
    for p in variants:
        with pytest.raises(P.ProtocolError):
            P.decode(p)


def test_forged_packets_fail_authentication_with_the_real_key():
    _, packets, _ = attacks.build(_spec("forged", 64))
    for _, p in packets:
        with pytest.raises(P.ProtocolError, match="unsigned|signature"):
            P.decode(p, b"k" * 32)


def test_kernel_drops_of_a_flooded_socket_are_read():
    """The robustness bench's 'dropped by the kernel' column: a socket with a small receive buffer that
    is never read loses datagrams, and the host's counter rises by at least the ones that cannot fit."""
    import socket

    from visionpos.benchmarks.robustness import udp_receive_buffer_drops

    if udp_receive_buffer_drops() is None:
        pytest.skip("no /proc/net/snmp (not Linux): the column reads n/a")
    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        rx.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)  # the kernel doubles it: a few datagrams fit
        rx.bind(("127.0.0.1", 0))
        before = udp_receive_buffer_drops()
        for _ in range(500):
            tx.sendto(b"x" * 1000, rx.getsockname())
        after = udp_receive_buffer_drops()
        assert after - before >= 400, (before, after)
    finally:
        rx.close()
        tx.close()
