"""Two vehicles' endpoints swapped mid-flight (their radios exchanged at the ground station): the bridge hears
another of its autopilots on a vehicle's link and stops the poses there at once, before the identity check could
see anything, and resumes when the links are put back (bridge/vehicle_link.py, a crossed link)."""

from __future__ import annotations

import hashlib
import logging
import time

import numpy as np
import pytest

from bridge import Bridge
from bridge.fake_autopilot import FakeAutopilot, decode_pose, trajectory_truth
from visionpos.app.linkswap import CrossRelay
from visionpos.app.ports import free_port, free_ports
from visionpos.benchmarks.factories import arena_with_vehicles, body_state
from visionpos.sim import trajectories as T

VPE = "VISION_POSITION_ESTIMATE"
KEYS = [hashlib.sha256(b"drone one").digest(), hashlib.sha256(b"drone two").digest()]
# each body hovers at its own place: a pose's position says whose it is (NED: y -> -E)
PLACES = [np.array([1.0, 0.0, 1.0]), np.array([0.0, 5.0, 1.0])]
CLOCK_SLACK_NS = 60_000_000  # a pose already on its way when the bridge read the other autopilot's packet


def _key_file(tmp_path, key: bytes, name: str) -> str:
    p = tmp_path / name
    p.write_text(key.hex() + "\n")
    p.chmod(0o600)
    return str(p)


def _fly(tmp_path, shared_key: bool, swap_back: bool):
    """Two fake autopilots behind a CrossRelay, a bridge whose vehicles are signed (one key for both, or one each);
    poses streamed at 50 Hz, the relay swapping the autopilots 1 s in (and back 1 s later with swap_back)."""
    keys = [KEYS[0], KEYS[0]] if shared_key else KEYS
    ports = free_ports(2)
    vehicles = [{"body": f"body{i + 1}", "sysid": i + 1, "endpoint": f"udpin:127.0.0.1:{p}",
                 "signing": {"key_file": _key_file(tmp_path, keys[i], f"k{i}")}} for i, p in enumerate(ports)]
    bridge = Bridge(arena_with_vehicles(vehicles), {"report_interval_s": 0})
    relay = CrossRelay([("127.0.0.1", p) for p in ports], lifetime_s=60, keep_data=True).start()
    t0 = time.monotonic_ns()
    aps = [FakeAutopilot(f"udpout:127.0.0.1:{relay.autopilot_port(i)}", sysid=i + 1, signing_key=keys[i],
                         truth=trajectory_truth(T.Static(PLACES[i]), t0),
                         telemetry_hz=50).start() for i in range(2)]
    bridge.start()
    swap_ns: list[int] = []
    try:
        start = time.monotonic_ns()
        plan = [1.0] + ([2.0] if swap_back else [])
        end_s = 2.0 if not swap_back else 5.0
        while (t := (time.monotonic_ns() - start) * 1e-9) < end_s:
            if plan and t >= plan[0]:
                plan.pop(0)
                swap_ns.append(relay.swap(0, 1))
            now = time.monotonic_ns()
            bridge.publish([body_state(f"body{i + 1}", i + 1, capture_ns=now, position=PLACES[i]) for i in range(2)])
            time.sleep(0.02)
        health = [v.health() for v in bridge.vehicles]
        status = bridge.status_line()
    finally:
        bridge.close()
        for ap in aps:
            ap.close()
        relay.stop()
    return relay, aps, swap_ns, health, status


def _poses_at(relay: CrossRelay, ap: int) -> list[tuple[int, int]]:
    """(arrival ns, whose body: 0 or 1) of each pose that reached autopilot ap through the relay."""
    from pymavlink.dialects.v20 import common as mavlink2

    out = []
    parser = mavlink2.MAVLink(None)
    parser.robust_parsing = True
    for t, leg, to_ap, data in list(relay.to_autopilot):
        if to_ap != ap:
            continue
        for m in parser.parse_buffer(data) or []:
            if m.get_type() == VPE:
                east = m.y  # NED east of the pose: 0 for body1, -5 for body2 (world y = 5 -> E = -5)
                out.append((t, 0 if abs(east) < 1 else 1))
    return out


def _first_crossed_ns(relay: CrossRelay, leg: int, since_ns: int) -> int:
    """When the bridge's endpoint `leg` first got a datagram of the other autopilot after since_ns."""
    return min(t for t, lg, ap in ((r[0], r[1], r[2]) for r in relay.to_bridge) if t >= since_ns and lg == leg
               and ap != leg)


@pytest.mark.parametrize("shared_key", [True, False], ids=["one fleet key", "a key per drone"])
def test_swapped_endpoints_stop_the_poses_at_the_first_packet_of_the_other_autopilot(tmp_path, caplog, shared_key):
    with caplog.at_level(logging.ERROR, logger="visionpos.bridge"):
        relay, aps, swap_ns, health, status = _fly(tmp_path, shared_key, swap_back=False)
    (t_swap,) = swap_ns
    for ap in range(2):
        poses = _poses_at(relay, ap)
        assert sum(1 for t, who in poses if t < t_swap and who == ap) > 20  # it flew on its own poses
        assert not [1 for t, who in poses if t < t_swap and who != ap]
        wrong = [t for t, who in poses if t >= t_swap and who != ap]
        # the other vehicle's poses reach it only until the bridge hears it on that vehicle's link
        caught = _first_crossed_ns(relay, 1 - ap, t_swap)
        assert all(t <= caught + CLOCK_SLACK_NS for t in wrong), ((caught - t_swap) * 1e-6,
                                                                   [(t - t_swap) * 1e-6 for t in wrong])
        assert len(wrong) <= 3
    for i, h in enumerate(health):
        other = 2 - i
        assert h["crossed"] == {"sysid": other, "episodes": 1}
        assert h["sending"] == f"stopped: sysid {other}'s autopilot answers on this link (endpoints swapped?)"
        assert h["output"]["held_crossed"] > 10
        assert f"sysid {other}'s autopilot answers on this link" in status
    said = [r.getMessage() for r in caplog.records if "answers on this link" in r.getMessage()]
    assert len(said) == 2 and all("endpoints swapped" in s for s in said), said


def test_links_put_back_resume_the_poses_to_their_own_autopilots(tmp_path):
    relay, aps, swap_ns, health, status = _fly(tmp_path, True, swap_back=True)
    _, t_back = swap_ns
    for ap in range(2):
        after = [(t, who) for t, who in _poses_at(relay, ap) if t > t_back + 50_000_000]
        # silent for the clearing time (the other autopilot gone 2 s, its own heard since), then its own again
        assert after and all(who == ap for _, who in after)
        assert after[0][0] - t_back >= 1.9e9
    for h in health:
        assert h["crossed"]["sysid"] is None and h["crossed"]["episodes"] == 1
        assert h["sending"] == "sending"


def test_an_unverified_packet_of_another_sysid_from_the_peer_changes_nothing(tmp_path):
    """A signed link: another sysid's autopilot packet from the autopilot's own address, signed with a key the
    bridge does not have, is refused: the poses go on."""
    port = free_port()
    bridge = Bridge(arena_with_vehicles([{"body": "body1", "sysid": 1, "endpoint": f"udpin:127.0.0.1:{port}",
                                          "signing": {"key_file": _key_file(tmp_path, KEYS[0], "k")}}]),
                    {"report_interval_s": 0})
    bridge.start()
    ap = FakeAutopilot(f"udpout:127.0.0.1:{port}", sysid=1, signing_key=KEYS[0], heartbeat_hz=10).start()
    try:
        from pymavlink.dialects.v20 import common as mavlink2

        v = bridge.vehicles[0]
        end = time.monotonic() + 5.0
        while not v.health()["link"]["up"] and time.monotonic() < end:  # the bridge has learned the autopilot
            time.sleep(0.01)
        stranger = mavlink2.MAVLink(None, srcSystem=2, srcComponent=1)
        stranger.signing.secret_key, stranger.signing.sign_outgoing = KEYS[1], True
        stranger.signing.link_id, stranger.signing.timestamp = 0, int((time.time() - 1420070400) * 1e5)
        for _ in range(100):
            bridge.publish([body_state("body1", 1, capture_ns=time.monotonic_ns(), position=PLACES[0])])
            ap.write(stranger.heartbeat_encode(2, 3, 0, 0, 4).pack(stranger))
            time.sleep(0.01)
        assert v.counters["rx_foreign"] >= 90 and v.counters["crossed"] == 0
        assert v.health()["crossed"]["sysid"] is None and v.counters["sent"] > 40
        assert ap.messages(VPE) and all(decode_pose(r)["position_ned"][1] == 0 for r in ap.messages(VPE))
    finally:
        bridge.close()
        ap.close()


def test_the_docs_say_what_the_crossed_link_does():
    """docs/autopilot-setup.md (Endpoints): the status text, clearing time and health key, as the code has them."""
    from pathlib import Path

    from bridge.crossed_link import CLEAR_NS
    from bridge.vehicle_link import COUNTERS

    doc = " ".join((Path(__file__).resolve().parents[2] / "docs" / "autopilot-setup.md").read_text().split())
    assert "`stopped: sysid 2's autopilot answers on this link (endpoints swapped?)`" in doc
    assert f"silent on the link for {CLEAR_NS * 1e-9:.0f} s" in doc
    assert '`health()["crossed"]`' in doc and "held_crossed" in COUNTERS and "`held_crossed`" in doc
    assert "at most three poses" in doc  # test_swapped_endpoints_...: len(wrong) <= 3
