"""Kernel receive timestamps for UDP sockets (Linux SO_TIMESTAMPNS).

A user-space stamp taken when a program gets round to reading a datagram is
late by however long the datagram queued. The kernel's stamp is taken on
arrival. Stations use it for t4 of the clock sync; the server uses it to see
how far behind its receive queue is (load shedding).
"""

from __future__ import annotations

import socket
import struct
import sys

SO_TIMESTAMPNS = getattr(socket, "SO_TIMESTAMPNS", 35)  # Linux <asm-generic/socket.h>
TIMESPEC = struct.Struct("@ll")  # native struct timespec: 16 bytes on 64-bit, 8 on 32-bit (Pi OS armhf)
ANC_SIZE = socket.CMSG_SPACE(TIMESPEC.size) if hasattr(socket, "CMSG_SPACE") else 0


def enable_kernel_stamps(sock: socket.socket) -> bool:
    """Ask the kernel to stamp each datagram on arrival; False where the platform cannot."""
    if not sys.platform.startswith("linux") or not ANC_SIZE or not hasattr(sock, "recvmsg"):
        return False
    try:
        sock.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
    except OSError:
        return False
    return True


def kernel_stamp_ns(ancdata: list) -> int:
    """Arrival time (CLOCK_REALTIME ns) from recvmsg's ancillary data; 0 if it holds none."""
    for level, kind, payload in ancdata:
        if level == socket.SOL_SOCKET and kind == SO_TIMESTAMPNS and len(payload) >= TIMESPEC.size:
            sec, nsec = TIMESPEC.unpack_from(payload)
            return sec * 1_000_000_000 + nsec
    return 0
