"""MAVLink2 signing on a vehicle's link: the incoming signatures checked, the outgoing timestamps kept.

Incoming signatures are checked here, not by pymavlink, whose check records a packet's timestamp
before the signature is verified (one forged packet with a far-future timestamp would make every
genuine one after it look replayed). A packet passes when it is MAVLink2, signed, its signature
verifies with the vehicle's key, and its timestamp is newer than the last one on its stream (link
id, component); a stream seen for the first time may start at most NEW_STREAM_WINDOW_TICKS behind
the newest timestamp seen on any stream. Only a packet that passes changes the state.

Outgoing timestamps count from the wall clock at start, then follow the monotonic clock (never
stepping back with NTP), and are never behind the newest the autopilot has sent (it refuses a new
stream over a minute behind its own).
"""

from __future__ import annotations

import hashlib
import hmac
import time

SIGNING_EPOCH_S = 1420070400  # MAVLink2 signing timestamps count 10 us units from 2015-01-01
SIGNING_TICKS_PER_S = 100_000
NEW_STREAM_WINDOW_TICKS = 60 * SIGNING_TICKS_PER_S  # a new signed stream may start this far behind the newest seen
SIGNATURE_BLOCK_LEN = 13  # link id (1), timestamp (6, LE, 10 us), signature (6)
MAVLINK2_MAGIC = 0xFD


class SignatureCheck:
    """The signatures of what one vehicle sends, stream by stream.

    check(buf, v2, compid) -> (timestamp in 10 us ticks, "") for a packet that passes, else
    (-1, "unsigned" | "bad signature" | "replayed"). newest_ts: the newest verified timestamp, any stream."""

    def __init__(self, key: bytes):
        self.key = key
        self.stream_ts: dict[tuple[int, int], int] = {}  # (link id, component) -> last verified timestamp
        self.newest_ts = -1

    def check(self, buf: bytearray, v2: bool, compid: int) -> tuple[int, str]:
        if not v2 or not buf[2] & 0x01 or len(buf) < 12 + SIGNATURE_BLOCK_LEN:
            return -1, "unsigned"
        sig = hashlib.sha256(self.key + bytes(buf[:-6])).digest()[:6]
        if not hmac.compare_digest(sig, bytes(buf[-6:])):
            return -1, "bad signature"
        stream = (buf[-13], compid)
        ts = int.from_bytes(buf[-12:-6], "little")
        last = self.stream_ts.get(stream)
        if (ts <= last) if last is not None else (ts + NEW_STREAM_WINDOW_TICKS < self.newest_ts):
            return -1, "replayed"
        self.stream_ts[stream] = ts
        if ts > self.newest_ts:
            self.newest_ts = ts
        return ts, ""


class SigningClock:
    """Outgoing signing timestamps (10 us ticks since SIGNING_EPOCH_S): the wall clock at start, then the
    monotonic clock."""

    def __init__(self) -> None:
        self.base = int((max(time.time(), SIGNING_EPOCH_S) - SIGNING_EPOCH_S) * SIGNING_TICKS_PER_S)
        self._mono0 = time.monotonic_ns()

    def now(self) -> int:
        return self.base + (time.monotonic_ns() - self._mono0) // 10_000
