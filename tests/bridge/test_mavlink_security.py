"""MAVLink that cannot be hijacked (issue 14, item 5): on a udpin endpoint the bridge sends the poses only
to an autopilot authenticated by its MAVLink2 signature or by its configured address.

The autopilot and the attackers are plain UDP sockets speaking through pymavlink (third-party); the real
autopilot's pymavlink verifies the bridge's signatures with its own implementation, so every pose counted
at the real autopilot is one that a signing autopilot would accept.
"""

from __future__ import annotations

import hashlib
import logging
import socket
import time

import pytest
from pymavlink.dialects.v20 import common as mavlink2

from bridge import Bridge
from bridge.config import parse_vehicles
from visionpos.app.ports import free_port
from visionpos.benchmarks.factories import arena_with_vehicles, body_state
from visionpos.config.arena import ConfigError

KEY = hashlib.sha256(b"the fleet's passphrase").digest()  # MAVProxy's `signing setup` passphrase -> key rule
OTHER_KEY = hashlib.sha256(b"someone else's passphrase").digest()
SIGNING_EPOCH_S = 1420070400
N_POSES = 40
MS = 1_000_000


class Peer:
    """One side of a MAVLink link on 127.0.0.1: a UDP socket and pymavlink's own MAVLink2 (and signing)."""

    def __init__(self, sysid: int = 1, key: bytes | None = None, port: int = 0, link_id: int = 1,
                 timestamp: int | None = None):
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", port))
        self.sock.setblocking(False)
        self.port = self.sock.getsockname()[1]
        self.mav = mavlink2.MAVLink(None, srcSystem=sysid, srcComponent=1)
        self.mav.robust_parsing = True
        if key is not None:
            s = self.mav.signing
            s.secret_key, s.sign_outgoing, s.link_id = key, True, link_id
            s.allow_unsigned_callback = None  # like a signing autopilot: unsigned or badly signed is refused
            s.timestamp = int((time.time() - SIGNING_EPOCH_S) * 1e5) if timestamp is None else timestamp
        self.datagrams = 0
        self.poses: list = []
        self.heartbeats = 0
        self.rejected = 0

    def heartbeat(self) -> bytes:
        return self.mav.heartbeat_encode(mavlink2.MAV_TYPE_QUADROTOR, mavlink2.MAV_AUTOPILOT_ARDUPILOTMEGA,
                                         0, 0, mavlink2.MAV_STATE_STANDBY).pack(self.mav)

    def send(self, data: bytes, dest: tuple) -> None:
        self.sock.sendto(data, dest)

    def drain(self) -> None:
        while True:
            try:
                data = self.sock.recv(65535)
            except BlockingIOError:
                return
            self.datagrams += 1
            for m in self.mav.parse_buffer(data) or []:
                t = m.get_type()
                if t == "BAD_DATA":
                    self.rejected += 1
                elif t == "VISION_POSITION_ESTIMATE":
                    self.poses.append(m)
                elif t == "HEARTBEAT":
                    self.heartbeats += 1

    def wait(self, what: str, n: int, timeout_s: float = 5.0) -> bool:
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            self.drain()
            if (len(self.poses) if what == "poses" else self.heartbeats) >= n:
                return True
            time.sleep(0.002)
        return False

    def close(self) -> None:
        self.sock.close()


@pytest.fixture
def key_file(tmp_path):
    p = tmp_path / "fleet.key"
    p.write_text("the fleet's passphrase\n")  # a passphrase file: the bridge hashes it as MAVProxy does
    return str(p)


def start_bridge(vehicle: dict) -> tuple[Bridge, tuple]:
    port = free_port()
    v = {"body": "body1", "sysid": 1, "endpoint": f"udpin:127.0.0.1:{port}", "max_age_ms": 10000, **vehicle}
    bridge = Bridge(arena_with_vehicles([v]), {"report_interval_s": 0})
    bridge.start()
    end = time.monotonic() + 5.0
    while bridge.vehicles[0].link is None and time.monotonic() < end:  # the sender thread binds the port
        time.sleep(0.001)
    assert bridge.vehicles[0].link is not None
    return bridge, ("127.0.0.1", port)


def attack_while_publishing(bridge: Bridge, dest: tuple, spoofs: list[tuple[Peer, bytes | None]],
                            t0: int, n: int = N_POSES) -> None:
    """n poses 20 ms apart in capture time; before each, every spoofer sends its packet (None: a fresh HEARTBEAT)
    claiming the vehicle's sysid from its own port."""
    for i in range(n):
        for peer, data in spoofs:
            peer.send(data if data is not None else peer.heartbeat(), dest)
        time.sleep(0.002)  # the bridge reads the spoofs before it gets the pose
        bridge.publish([body_state(capture_ns=t0 + i * 20 * MS, position=(1.0, 2.0, 3.0))])
        assert bridge.flush(2.0)


def test_spoofed_heartbeats_do_not_divert_a_signed_udpin_link(key_file, caplog):
    bridge, dest = start_bridge({"signing": {"key_file": key_file}})
    real = Peer(key=KEY)
    captured = real.heartbeat()  # a genuine signed packet an attacker recorded, replayed later from elsewhere
    unsigned, wrong_key = Peer(), Peer(key=OTHER_KEY)
    future = Peer(key=OTHER_KEY, timestamp=(1 << 48) - 1000)  # forged, with a far-future timestamp
    replayer = Peer()
    spoofers = [unsigned, wrong_key, future, replayer]
    try:
        real.send(captured, dest)
        assert real.wait("heartbeats", 1), "the bridge never answered the signed autopilot"
        real.send(real.heartbeat(), dest)
        with caplog.at_level(logging.WARNING, logger="visionpos.bridge"):
            attack_while_publishing(bridge, dest, [(unsigned, None), (wrong_key, None), (future, None),
                                                   (replayer, captured)], time.monotonic_ns())
            real.send(real.heartbeat(), dest)  # the real autopilot is still heard after the attack
            assert real.wait("poses", N_POSES)
            time.sleep(0.05)
        for sp in spoofers:
            sp.drain()
        assert [sp.datagrams for sp in spoofers] == [0, 0, 0, 0]  # not one pose, not one heartbeat diverted
        assert len(real.poses) == N_POSES and real.rejected == 0  # all verified by pymavlink's signing
        assert all(p.get_signed() for p in real.poses)
        s = bridge.stats()["vehicles"]["body1"]
        assert s["rx_unsigned"] >= N_POSES and s["rx_bad_signature"] >= 2 * N_POSES
        assert s["rx_replayed"] >= N_POSES and s["peer_refused"] >= 4 * N_POSES
        assert s["reconnects"] == 0 and s["peer"] == f"127.0.0.1:{real.port}"
        # repeated warnings are rate-limited: one line per reason in this short attack, not one per packet
        refused = [r for r in caplog.records if "refused a packet" in r.getMessage()]
        assert 1 <= len(refused) <= 3
    finally:
        bridge.close()
        for p in [real] + spoofers:
            p.close()


def test_spoofed_heartbeats_do_not_divert_udpin_with_a_configured_address():
    ap_port = free_port()
    bridge, dest = start_bridge({"autopilot_address": f"127.0.0.1:{ap_port}"})
    real, spoofer = Peer(port=ap_port), Peer()
    try:
        real.send(real.heartbeat(), dest)
        assert real.wait("heartbeats", 1)
        attack_while_publishing(bridge, dest, [(spoofer, None)], time.monotonic_ns())
        assert real.wait("poses", N_POSES)
        time.sleep(0.05)
        spoofer.drain()
        assert spoofer.datagrams == 0 and len(real.poses) == N_POSES
        s = bridge.stats()["vehicles"]["body1"]
        assert s["rx_wrong_source"] >= N_POSES and s["peer_refused"] == s["rx_wrong_source"]
        assert s["peer"] == f"127.0.0.1:{ap_port}"
    finally:
        bridge.close()
        real.close()
        spoofer.close()


def test_rejected_packets_change_no_state_and_a_moved_autopilot_is_followed(key_file):
    """A forged packet with a far-future timestamp on the autopilot's own stream (link 1, sysid 1, comp 1)
    must not make the autopilot's later packets look replayed (pymavlink's own check stores the
    timestamp before verifying the signature); when the autopilot comes back from a new port, its
    signed packets move the poses there."""
    bridge, dest = start_bridge({"signing": {"key_file": key_file}})
    real = Peer(key=KEY)
    forged = Peer(key=OTHER_KEY, timestamp=(1 << 48) - 1000)
    unsigned = Peer()
    moved = None
    try:
        real.send(real.heartbeat(), dest)
        assert real.wait("heartbeats", 1)
        for _ in range(5):
            forged.send(forged.heartbeat(), dest)
            unsigned.send(unsigned.heartbeat(), dest)
        time.sleep(0.05)
        assert bridge.stats()["vehicles"]["body1"]["peer"] == f"127.0.0.1:{real.port}"
        real.close()  # the companion restarts: same key, same link id, a new source port
        moved = Peer(key=KEY)
        moved.send(moved.heartbeat(), dest)
        assert moved.wait("heartbeats", 1, 3.0), "the bridge did not follow the signed autopilot to its new port"
        t0 = time.monotonic_ns()
        for i in range(5):
            bridge.publish([body_state(capture_ns=t0 + i * 20 * MS)])
            assert bridge.flush(2.0)
        assert moved.wait("poses", 5) and moved.rejected == 0
        s = bridge.stats()["vehicles"]["body1"]
        assert s["reconnects"] == 1 and s["peer"] == f"127.0.0.1:{moved.port}"
        assert (s["rx_bad_signature"], s["rx_unsigned"], s["rx_replayed"]) == (5, 5, 0)
        forged.drain()
        unsigned.drain()
        assert forged.datagrams == 0 and unsigned.datagrams == 0
    finally:
        bridge.close()
        for p in (real, forged, unsigned, moved):
            if p is not None:
                p.close()


def test_an_older_signed_packet_from_another_port_does_not_move_the_peer(key_file):
    """Signed with the right key, on a stream the bridge has not seen, but older than the autopilot's
    newest packet (recorded from another of its links and replayed): accepted as genuine, never as a move."""
    bridge, dest = start_bridge({"signing": {"key_file": key_file}})
    now_ts = int((time.time() - SIGNING_EPOCH_S) * 1e5)
    real = Peer(key=KEY, link_id=1, timestamp=now_ts)
    old_other_link = Peer(key=KEY, link_id=2, timestamp=now_ts - 30 * 100_000)  # 30 s older, another link id
    try:
        real.send(real.heartbeat(), dest)
        assert real.wait("heartbeats", 1)
        old_other_link.send(old_other_link.heartbeat(), dest)
        feed_t0 = time.monotonic_ns()
        for i in range(3):
            bridge.publish([body_state(capture_ns=feed_t0 + i * 20 * MS)])
            assert bridge.flush(2.0)
        assert real.wait("poses", 3)
        time.sleep(0.05)
        old_other_link.drain()
        assert old_other_link.datagrams == 0
        s = bridge.stats()["vehicles"]["body1"]
        assert s["peer_refused"] == 1 and s["reconnects"] == 0
    finally:
        bridge.close()
        real.close()
        old_other_link.close()


def test_unsigned_udpin_without_an_address_is_refused_with_the_fix():
    with pytest.raises(ConfigError, match=r"vehicles\[0\]\.endpoint: a udpin endpoint without signing .*"
                                          r"`signing: \{key_file: \.\.\.\}`.*autopilot_address: HOST:PORT"):
        parse_vehicles(arena_with_vehicles([{"body": "body1", "endpoint": "udpin:0.0.0.0:14561"}]))


@pytest.mark.parametrize("vehicle, key, hint", [
    ({"endpoint": "udpin:0.0.0.0:14561", "signin": {"key_file": "k"}}, r"vehicles\[0\]\.signin", "`signing`"),
    ({"endpoint": "udpin:0.0.0.0:14561", "signing": {"keyfile": "k"}}, r"vehicles\[0\]\.signing\.keyfile",
     "`key_file`"),
    ({"endpoint": "udpin:0.0.0.0:14561", "autopilot_adress": "10.0.0.2:14550"},
     r"vehicles\[0\]\.autopilot_adress", "`autopilot_address`"),
])
def test_misspelt_signing_keys_are_errors_not_an_unsigned_link(vehicle, key, hint):
    with pytest.raises(ConfigError, match=rf"{key}: .*did you mean {hint}"):
        parse_vehicles(arena_with_vehicles([{"body": "body1", **vehicle}]))


@pytest.mark.parametrize("vehicle, text", [
    ({"endpoint": "udpout:10.0.0.2:14550", "autopilot_address": "10.0.0.2:14550"}, "only for udpin"),
    ({"endpoint": "udpin:0.0.0.0:14561", "autopilot_address": "10.0.0.2"}, "HOST:PORT"),
])
def test_autopilot_address_errors(vehicle, text):
    with pytest.raises(ConfigError, match=rf"vehicles\[0\]\.autopilot_address: .*{text}"):
        parse_vehicles(arena_with_vehicles([{"body": "body1", **vehicle}]))


def test_fake_autopilot_verifies_signatures_and_rejects_unsigned():
    from bridge.fake_autopilot import FakeAutopilot

    with FakeAutopilot("udpin:127.0.0.1:0", sysid=1, signing_key=KEY, heartbeat_hz=0, timesync_hz=0) as ap:
        dest = ("127.0.0.1", ap.port)
        good, unsigned, other = Peer(key=KEY), Peer(), Peer(key=OTHER_KEY)
        try:
            for p in (good, unsigned, other):
                p.send(p.mav.vision_position_estimate_encode(1, 1.0, 2.0, 3.0, 0.0, 0.0, 0.0).pack(p.mav), dest)
            end = time.monotonic() + 2.0
            while (ap.rejected_signature < 2 or not ap.received) and time.monotonic() < end:
                time.sleep(0.005)
            assert ap.rejected_signature == 2
            assert [(r.type, r.signed) for r in ap.received] == [("VISION_POSITION_ESTIMATE", True)]
        finally:
            for p in (good, unsigned, other):
                p.close()


@pytest.mark.slow
def test_demo_runs_signed():
    """`visionpos demo` signs its MAVLink: each vehicle gets a key, its fake autopilot verifies every pose
    with pymavlink's signing and rejects anything unsigned or signed otherwise."""
    import asyncio

    from visionpos.app.demo import demo_arena, run_demo

    arena = demo_arena("thesis", 1.0, 3, [])
    assert all(v.signing_key is not None and len(v.signing_key) == 32 for v in parse_vehicles(arena))
    summary = asyncio.run(run_demo(arena, 1.0, None))
    for b in summary["bodies"]:
        assert b["mavlink_signed"] is True
        assert b["mavlink_messages"] > 10  # only poses whose signature verified are recorded
        assert b["mavlink_rejected_signature"] == 0


def test_signature_check_passes_only_signed_newer_packets_and_says_why():
    """bridge/signing.py against packets signed by pymavlink's own signing (third-party)."""
    from bridge.signing import NEW_STREAM_WINDOW_TICKS, SignatureCheck

    def packet(key, link_id=1, timestamp=10_000_000, v2=True):
        mav = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
        if key is not None:
            s = mav.signing
            s.secret_key, s.sign_outgoing, s.link_id, s.timestamp = key, True, link_id, timestamp
        return bytearray(mav.heartbeat_encode(2, 3, 0, 0, 4).pack(mav))

    check = SignatureCheck(KEY)
    assert check.check(packet(None), True, 1) == (-1, "unsigned")
    assert check.check(packet(OTHER_KEY), True, 1) == (-1, "bad signature")
    assert check.newest_ts == -1  # a refused packet changes nothing
    ts, why = check.check(packet(KEY, timestamp=10_000_000), True, 1)
    assert (why, check.newest_ts) == ("", ts) and ts >= 10_000_000
    assert check.check(packet(KEY, timestamp=ts), True, 1) == (-1, "replayed")  # same stream, not newer
    assert check.check(packet(KEY, timestamp=ts + 1), True, 1)[1] == ""
    # a new stream (link id 2) may start behind the newest, but not by more than the window
    assert check.check(packet(KEY, link_id=2, timestamp=ts - NEW_STREAM_WINDOW_TICKS - 5), True, 1) == (-1, "replayed")
    assert check.check(packet(KEY, link_id=3, timestamp=ts - 100), True, 1)[1] == ""
