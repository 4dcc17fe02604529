"""The attacker of `visionpos bench --only robustness`: hostile packets of each kind the issues found.

Runs as its own process (`python -m visionpos.benchmarks.attacks SPEC.json`), so the server under test
shares no interpreter with it and its send loop costs the server nothing but the packets. The spec
(written by benchmarks/robustness.py) names the attack, the targets and what the attacker knows:

- the arena (public: camera and station ids, the calibration) and so the blobs a fake body would make;
- what a sniffer on the network saw (`sniffed_hex`: exact bytes the stations and the server sent in
  this session, which it can resend but not alter);
- packets of an earlier session signed with the arena's key (`old_hex`), as a copy of an old
  recording would hold.

It never knows the current key. It prints one JSON line: {"sent": N, "send_errors": M, "seconds": S}.

Kinds (see ATTACKS): junk, malformed, forged, replay_old, replay_sniffed, spoof_replies, many_sources,
mavlink_spoof.
"""

from __future__ import annotations

import json
import math
import os
import socket
import struct
import sys
import time

import numpy as np

from visionpos import protocol as P
from visionpos.messages import BlobFrame

ATTACKS: dict[str, str] = {
    "junk": "random datagrams of 1 B to 64 KB, some starting with the protocol's magic",
    "malformed": "protocol packets with a wrong version, type, length, blob count (89, 90), a zero "
                 "resolution, fps inf/NaN, a flagged but missing tag, NaN blobs",
    "forged": "frames (fake body at the arena centre, seq far ahead, plausible capture times), HELLO, "
              "HEARTBEAT and BYE for every configured camera, with each station's sniffed session: unsigned "
              "and signed with a wrong key",
    "replay_old": "an earlier session's signed frames, HELLO, HEARTBEAT and BYE, resent",
    "replay_sniffed": "this session's own signed frames and control messages, resent as captured",
    "spoof_replies": "to the stations: unsigned and wrong-key HelloAck UNKNOWN_SESSION (session 0 and the "
                     "station's own), and the server's sniffed replies resent",
    "many_sources": "forged frames and HELLOs from a new source port each (per-sender tables)",
    "mavlink_spoof": "to each autopilot link: HEARTBEAT with the vehicle's sysid from other ports, unsigned "
                     "and signed with a wrong key",
}

WRONG_KEY = b"\x5a" * 32
# byte offsets in a packet (docs/protocol.md): header body_len; frame body session u32, seq u32,
# capture_ns i64, flags u16, count u16; hello body session u32, counter u32, width u16, height u16, fps f32
_BODY_LEN_AT = 12
_FRAME_COUNT_AT = P.HEADER_BYTES + 18
_HELLO_WIDTH_AT = P.HEADER_BYTES + 8


def _frame(station_id: int, camera_id: int, seq: int, capture_ns: int, blobs: np.ndarray, session: int,
           key: bytes | None) -> bytes:
    return P.encode_frame(BlobFrame(camera_id, seq, capture_ns, blobs, station_id, 0, 0, session), key)


def _malformed(rng: np.random.Generator, cams: list[dict], n: int) -> list[bytes]:
    cam = cams[0]
    blobs = rng.uniform(0, 600, (8, 4)).astype(np.float32)
    good = _frame(cam["station_id"], cam["camera_id"], 1, time.monotonic_ns(), blobs, cam["session"], None)
    hello = P.encode(P.Hello(cam["station_id"], cam["camera_id"], 7, cam["width"], cam["height"], 100.0, counter=1))
    variants = []
    b = bytearray(good)
    b[4] = 9  # version
    variants.append(bytes(b))
    b = bytearray(good)
    b[5] = 77  # type
    variants.append(bytes(b))
    variants.append(good[:-3])  # truncated
    variants.append(good + b"\0\0")  # trailing
    b = bytearray(good)
    b[6] |= 1  # "signed", no tag
    variants.append(bytes(b))
    for count in (89, 90):  # more blobs than the spec allows, consistent lengths
        head = bytearray(good[:P.HEADER_BYTES + P.FRAME_FIXED_BYTES])
        struct.pack_into("<H", head, _BODY_LEN_AT, P.FRAME_FIXED_BYTES + count * P.BLOB_BYTES)
        struct.pack_into("<H", head, _FRAME_COUNT_AT, count)
        variants.append(bytes(head) + np.zeros((count, 4), np.float32).tobytes())
    nan_blobs = blobs.copy()
    nan_blobs[0, 0] = np.nan
    variants.append(_set_blobs(good, nan_blobs))
    hb = bytearray(hello)
    struct.pack_into("<HH", hb, _HELLO_WIDTH_AT, 0, 0)  # width = height = 0
    variants.append(bytes(hb))
    for fps in (math.inf, math.nan, -5.0):
        hb = bytearray(hello)
        struct.pack_into("<f", hb, _HELLO_WIDTH_AT + 4, fps)
        variants.append(bytes(hb))
    return [variants[i % len(variants)] for i in range(n)]


def _set_blobs(packet: bytes, blobs: np.ndarray) -> bytes:
    start = len(packet) - blobs.size * 4
    return packet[:start] + blobs.astype(np.float32).tobytes()


def _forged(rng: np.random.Generator, cams: list[dict], fake_blobs: dict, n: int) -> list[tuple[int, bytes]]:
    out: list[tuple[int, bytes]] = []
    seq_far = 1 << 30
    i = 0
    while len(out) < n:
        cam = cams[i % len(cams)]
        key = None if (i // len(cams)) % 2 == 0 else WRONG_KEY
        blobs = np.asarray(fake_blobs.get(str(cam["camera_id"]), np.zeros((0, 4))), np.float32).reshape(-1, 4)
        now = time.monotonic_ns()
        k = i % 8
        if k < 5:
            pk = _frame(cam["station_id"], cam["camera_id"], seq_far + i, now - 5_000_000, blobs,
                        cam["session"], key)
        elif k == 5:
            pk = P.encode(P.Hello(cam["station_id"], cam["camera_id"], int(rng.integers(1, 2**32)), cam["width"],
                                  cam["height"], 100.0, counter=1), key)
        elif k == 6:
            pk = P.encode(P.Heartbeat(cam["station_id"], cam["camera_id"], seq_far + i, cam["session"]), key)
        else:
            pk = P.encode(P.Bye(cam["station_id"], cam["camera_id"], cam["session"], seq_far + i), key)
        out.append((0, pk))
        i += 1
    return out


def seq_guess(i: int) -> int:
    """An echo counter a spoofer might try: small counts, as a station has sent early in its session."""
    return 1 + i % 64


def build(spec: dict) -> tuple[list[tuple[str, int]], list[tuple[int, bytes]], int]:
    """The attack's (destinations, [(destination index, packet)], new source port every k packets (0: never))."""
    kind, n = spec["kind"], int(spec["packets"])
    rng = np.random.default_rng(spec.get("seed", 0))
    server = ("127.0.0.1", int(spec["server_port"]))
    cams = spec["cameras"]
    if kind == "junk":
        sizes = rng.integers(1, P.MAX_PACKET_BYTES + 1, n)
        big = rng.random(n)
        sizes[big > 0.92] = rng.integers(P.MAX_PACKET_BYTES + 1, 9000, int((big > 0.92).sum()))
        sizes[big > 0.995] = rng.integers(60000, 65000, int((big > 0.995).sum()))
        pool = rng.integers(0, 256, 70000, dtype=np.uint8).tobytes()
        packets = []
        for i, s in enumerate(sizes):
            off = int(rng.integers(0, len(pool) - s))
            data = pool[off:off + s]
            if i % 3 == 0 and s >= 4:
                data = P.MAGIC + data[4:]
            packets.append((0, data))
        return [server], packets, 0
    if kind == "malformed":
        return [server], [(0, p) for p in _malformed(rng, cams, n)], 0
    if kind == "forged":
        return [server], _forged(rng, cams, spec.get("fake_blobs", {}), n), 0
    if kind == "many_sources":
        return [server], _forged(rng, cams, spec.get("fake_blobs", {}), n), 1
    if kind in ("replay_old", "replay_sniffed"):
        pool = [bytes.fromhex(h) for h in spec["old_hex" if kind == "replay_old" else "sniffed_hex"]]
        return [server], [(0, pool[i % len(pool)]) for i in range(n)], 0
    if kind == "spoof_replies":
        dests = [("127.0.0.1", int(p)) for p in spec["station_ports"]]
        sniffed = [bytes.fromhex(h) for h in spec.get("reply_hex", [])]
        packets = []
        for i in range(n):
            d = i % len(dests)
            cam = cams[d % len(cams)]
            k = (i // len(dests)) % 4
            if k == 3 and sniffed:
                packets.append((d, sniffed[i % len(sniffed)]))
                continue
            session = 0 if k == 0 else cam["session"]
            ack = P.HelloAck(cam["station_id"], cam["camera_id"], session, 0, time.monotonic_ns(),
                             P.AckStatus.UNKNOWN_SESSION, 0, seq_guess(i))
            packets.append((d, P.encode(ack, None if k < 2 else WRONG_KEY)))
        return dests, packets, 0
    if kind == "mavlink_spoof":
        from pymavlink.dialects.v20 import common as mavlink2

        dests = [("127.0.0.1", int(p)) for p in spec["mavlink_ports"]]
        packets = []
        for d, sysid in enumerate(spec["sysids"]):
            for signed in (False, True):
                mav = mavlink2.MAVLink(None, srcSystem=int(sysid), srcComponent=1)
                if signed:
                    mav.signing.secret_key, mav.signing.sign_outgoing, mav.signing.link_id = WRONG_KEY, True, 1
                    mav.signing.timestamp = int((time.time() - 1420070400) * 1e5)
                msg = mav.heartbeat_encode(mavlink2.MAV_TYPE_QUADROTOR, mavlink2.MAV_AUTOPILOT_ARDUPILOTMEGA,
                                           0, 0, mavlink2.MAV_STATE_STANDBY)
                packets.append((d, bytes(msg.pack(mav))))
        return dests, [packets[i % len(packets)] for i in range(n)], 4
    raise ValueError(f"unknown attack {kind!r}; one of {sorted(ATTACKS)}")


def send(dests: list[tuple[str, int]], packets: list[tuple[int, bytes]], rate_pps: float, rotate_every: int,
         duration_s: float) -> dict[str, float]:
    """Send the packets paced at rate_pps (for at most duration_s); a fresh source port every rotate_every."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sent = errors = 0
    t0 = time.perf_counter()
    batch = max(1, int(rate_pps / 1000))  # pace in 1 ms batches: the sleep granularity
    for i, (d, data) in enumerate(packets):
        if rotate_every and i % rotate_every == 0 and i:
            sock.close()
            sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            sock.sendto(data, dests[d])
            sent += 1
        except OSError:
            errors += 1
        if i % batch == batch - 1:
            ahead = (i + 1) / rate_pps - (time.perf_counter() - t0)
            if ahead > 0:
                time.sleep(ahead)
            elif time.perf_counter() - t0 > duration_s:
                break
    sock.close()
    return {"sent": sent, "send_errors": errors, "seconds": time.perf_counter() - t0}


def main(argv: list[str]) -> int:
    with open(argv[1]) as f:
        spec = json.load(f)
    dests, packets, rotate = build(spec)
    out = send(dests, packets, float(spec["rate_pps"]), rotate, float(spec.get("duration_s", 60.0)))
    out["kind"] = spec["kind"]
    out["pid"] = os.getpid()
    print(json.dumps(out), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
