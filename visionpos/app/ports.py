"""Free loopback ports, for everything that runs a whole chain on one machine (demo, benchmarks, tests)."""

from __future__ import annotations

import socket


def free_port(kind: int = socket.SOCK_DGRAM) -> int:
    """A currently free 127.0.0.1 port (UDP by default; socket.SOCK_STREAM for TCP)."""
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]
