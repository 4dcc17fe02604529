"""Free loopback ports, for everything that runs a whole chain on one machine (demo, benchmarks, tests)."""

from __future__ import annotations

import socket


def free_port(kind: int = socket.SOCK_DGRAM) -> int:
    """A currently free 127.0.0.1 port (UDP by default; socket.SOCK_STREAM for TCP)."""
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def free_ports(n: int, kind: int = socket.SOCK_DGRAM) -> list[int]:
    """n distinct currently free 127.0.0.1 ports: all bound at once, so the kernel cannot hand one out twice (as
    free_port() called twice may)."""
    socks = [socket.socket(socket.AF_INET, kind) for _ in range(n)]
    try:
        for s in socks:
            s.bind(("127.0.0.1", 0))
        return [s.getsockname()[1] for s in socks]
    finally:
        for s in socks:
            s.close()
