"""The MAVLink bridge on 127.0.0.1 against the pymavlink fake autopilot.

Expected values are hand-computed from the frame conventions (world z-up,
body FLU -> NED / FRD), never taken from the bridge's own conversion code.
"""

import hashlib
import math
import os
import socket
import tempfile
import time

import numpy as np
import pytest
from pymavlink.dialects.v20 import common as mavlink2

from bridge import Bridge
from bridge.fake_autopilot import FakeAutopilot, decode_pose
from visionpos.app.ports import free_port, free_ports
from visionpos.benchmarks.factories import arena_with_vehicles, body_state

S45 = math.sqrt(0.5)
YAW_LEFT_90 = (0.0, 0.0, S45, S45)
VPE, ODO, VSE = "VISION_POSITION_ESTIMATE", "ODOMETRY", "VISION_SPEED_ESTIMATE"


KEY = hashlib.sha256(b"visionpos test fleet").digest()
_KEY_DIR = tempfile.TemporaryDirectory(prefix="visionpos-test-keys-")  # removed when the module is unloaded


def key_file(key: bytes = KEY) -> str:
    """A key file holding key as 64 hex characters."""
    path = os.path.join(_KEY_DIR.name, key.hex()[:16] + ".key")
    if not os.path.exists(path):
        with open(path, "w") as f:
            f.write(key.hex() + "\n")
    return path


def start_pair(tmp_path=None, ap_kw=None, **vehicle):
    """A started Bridge with one signed vehicle on udpin and a fake autopilot with the same key pointed
    at it (heard by the bridge)."""
    port = free_port()
    v = {"body": "body1", "sysid": 1, "endpoint": f"udpin:127.0.0.1:{port}", "max_age_ms": 10000,
         "signing": {"key_file": key_file()}}
    v.update(vehicle)
    bridge = Bridge(arena_with_vehicles([v]), {"report_interval_s": 0})
    bridge.start()
    ap_kw = {"signing_key": KEY, **(ap_kw or {})}
    ap = FakeAutopilot(f"udpout:127.0.0.1:{port}", sysid=v["sysid"], **ap_kw).start()
    assert ap.wait_for("HEARTBEAT", 1, 5.0), "bridge never answered the autopilot's heartbeat"
    return bridge, ap


def feed(bridge, states):
    for st in states:
        bridge.publish([st])
        assert bridge.flush(2.0)


def test_vision_position_estimate_fields():
    bridge, ap = start_pair()
    try:
        C = np.diag([1e-4, 2e-4, 3e-4, 4e-4, 5e-4, 6e-4])
        C[0, 1] = C[1, 0] = 0.5e-4
        st = body_state(position=(1, 2, 3), quaternion=YAW_LEFT_90, covariance=C, reset_counter=3)
        feed(bridge, [st])
        assert ap.wait_for(VPE, 1)
        m = ap.messages(VPE)[0]
        f = m.fields
        assert (m.src_system, m.src_component) == (1, 197)
        assert f["usec"] == st.capture_ns // 1000  # boot time base: server monotonic clock in us
        assert (f["x"], f["y"], f["z"]) == pytest.approx((1, -2, -3), abs=1e-6)
        assert (f["roll"], f["pitch"], f["yaw"]) == pytest.approx((0, 0, -math.pi / 2), abs=1e-6)
        assert f["covariance"][0] == pytest.approx(1e-4) and f["covariance"][1] == pytest.approx(-0.5e-4)
        assert f["covariance"][6] == pytest.approx(2e-4) and f["covariance"][20] == pytest.approx(6e-4)
        assert f["reset_counter"] == 3
    finally:
        bridge.close()
        ap.close()


def test_odometry_fields():
    bridge, ap = start_pair(message="odometry")
    try:
        st = body_state(position=(1, 2, 3), quaternion=YAW_LEFT_90, velocity=(0, 2, 0), angular_velocity=(0, 0, 0.5))
        feed(bridge, [st])
        assert ap.wait_for(ODO, 1)
        f = ap.messages(ODO)[0].fields
        assert (f["frame_id"], f["child_frame_id"], f["estimator_type"]) == (20, 12, 2)
        assert f["time_usec"] == st.capture_ns // 1000
        assert (f["x"], f["y"], f["z"]) == pytest.approx((1, -2, -3), abs=1e-6)
        assert list(f["q"]) == pytest.approx([S45, 0, 0, -S45], abs=1e-6)  # w, x, y, z: yaw -90 deg
        # moving along world +y while facing +y: straight forward in FRD
        assert (f["vx"], f["vy"], f["vz"]) == pytest.approx((2, 0, 0), abs=1e-6)
        assert (f["rollspeed"], f["pitchspeed"], f["yawspeed"]) == pytest.approx((0, 0, -0.5), abs=1e-6)
        assert f["velocity_covariance"][0] == pytest.approx(1e-4)
        assert f["pose_covariance"][0] == pytest.approx(1e-6)
    finally:
        bridge.close()
        ap.close()


def test_vision_speed_estimate_option():
    bridge, ap = start_pair(vision_speed=True)
    try:
        feed(bridge, [body_state(velocity=(1, 2, 3))])
        assert ap.wait_for(VSE, 1)
        f = ap.messages(VSE)[0].fields
        assert (f["x"], f["y"], f["z"]) == pytest.approx((1, -2, -3), abs=1e-6)
        assert f["usec"] == ap.messages(VPE)[0].fields["usec"]
    finally:
        bridge.close()
        ap.close()


def test_rate_limit_50hz_from_100hz():
    bridge, ap = start_pair()
    try:
        t0 = time.monotonic_ns()
        states = [body_state(capture_ns=t0 + i * 10_000_000, position=(i * 0.01, 0, 1)) for i in range(100)]
        feed(bridge, states)
        assert ap.wait_for(VPE, 50, 5.0)
        time.sleep(0.1)
        got = [m.fields["usec"] for m in ap.messages(VPE)]
        assert got == [(t0 + i * 10_000_000) // 1000 for i in range(0, 100, 2)]
        s = bridge.stats()["vehicles"]["body1"]
        assert (s["sent"], s["rate_limited"]) == (50, 50)
        assert ap.report()["stamps_closer_than_20ms"] == 0
    finally:
        bridge.close()
        ap.close()


def test_even_50hz_stamps_from_uneven_captures():
    """Several asynchronous cameras: the newest capture at each 100 Hz output tick moves by
    uneven steps (here 6 and 14 ms in turn, with a few microseconds of jitter). Stamps still
    come 20 ms apart, never closer (one step longer where the grid follows the ticks' phase),
    so every pose is one EKF3 keeps and the rate is the full 50 Hz (stamping the captures
    themselves skips every other chance: about 36 Hz here), and each pose is the state moved
    back to its stamp, not the pose at the capture."""
    bridge, ap = start_pair()
    try:
        t0 = time.monotonic_ns() - 2_000_000_000  # a 2 s old flight, replayed in one go
        v = np.array([0.5, -0.2, 0.1])  # m/s, world
        p0 = np.array([1.0, 2.0, 1.0])
        states = []
        for k in range(100):
            tick = t0 + k * 10_000_000
            cap = tick - (4_000_000 if k % 2 else 0) - (k % 7) * 1_000  # 6 / 14 ms steps
            states.append(body_state(capture_ns=cap, dt_ns=tick - cap, position=p0 + v * (tick - t0) * 1e-9,
                                     velocity=v))
        feed(bridge, states)
        assert ap.wait_for(VPE, 45, 5.0)
        time.sleep(0.1)
        poses = [decode_pose(m) for m in ap.messages(VPE)]
        usec = np.array([p["usec"] for p in poses])
        assert len(poses) >= 48  # 100 ticks at 100 Hz: 50 poses at 50 Hz, less the grid's one longer step
        steps = np.diff(usec)
        assert steps.min() == 20_000 and (steps != 20_000).sum() <= 1
        assert ap.report()["stamps_closer_than_20ms"] == 0
        for p, u in zip(poses, usec):
            x, y, z = p0 + v * (u * 1000 - t0) * 1e-9  # the truth at the stamp, world z up
            assert np.allclose(p["position_ned"], [x, -y, -z], atol=1e-5)
    finally:
        bridge.close()
        ap.close()


def test_stop_on_loss_and_no_frozen_resend():
    bridge, ap = start_pair()
    try:
        t0 = time.monotonic_ns()
        feed(bridge, [body_state(capture_ns=t0)])
        feed(bridge, [body_state(capture_ns=t0)] * 3)  # frozen: same capture
        feed(bridge, [body_state(capture_ns=t0 + i * 30_000_000, tracked=False) for i in range(1, 5)])
        feed(bridge, [body_state(capture_ns=t0 + 200_000_000)])
        assert ap.wait_for(VPE, 2)
        time.sleep(0.1)
        assert [m.fields["usec"] for m in ap.messages(VPE)] == [t0 // 1000, (t0 + 200_000_000) // 1000]
        s = bridge.stats()["vehicles"]["body1"]
        assert (s["frozen"], s["not_tracked"], s["sent"]) == (3, 4, 2)
    finally:
        bridge.close()
        ap.close()


def test_stale_state_dropped():
    bridge, ap = start_pair(max_age_ms=1000)
    try:
        feed(bridge, [body_state(capture_ns=time.monotonic_ns() - 5_000_000_000)])
        feed(bridge, [body_state()])
        assert ap.wait_for(VPE, 1)
        time.sleep(0.05)
        assert len(ap.messages(VPE)) == 1
        assert bridge.stats()["vehicles"]["body1"]["dropped_stale"] == 1
    finally:
        bridge.close()
        ap.close()


def test_answer_timesync_false_leaves_the_autopilots_requests_unanswered_but_ours_still_go():
    """PX4 stamps every pose on arrival while its TIMESYNC requests go unanswered (docs/autopilot-setup.md, 3.);
    the back-channel's own requests, which time the link, go on."""
    bridge, ap = start_pair(answer_timesync=False, ap_kw={"timesync_hz": 20})
    try:
        deadline = time.monotonic() + 5.0
        while time.monotonic() < deadline and ap.timesync_requests_answered < 3:
            time.sleep(0.05)
        # ours, answered by the autopilot: over a second, in which it sent some 20 requests of its own
        assert ap.timesync_requests_answered >= 3 and len(ap._ts_sent) >= 10
        assert ap.report()["timesync_replies"] == 0
        v = bridge.stats()["vehicles"]["body1"]
        assert v["timesync_answered"] == 0 and v["timesync_rtt_ms"] is not None
    finally:
        bridge.close()
        ap.close()


def test_reset_counter_only_on_discontinuity():
    bridge, ap = start_pair()
    try:
        t0 = time.monotonic_ns()
        ms = 1_000_000
        feed(bridge, [body_state(capture_ns=t0, reset_counter=0)])
        feed(bridge, [body_state(capture_ns=t0 + 30 * ms, tracked=False)])  # dropout
        feed(bridge, [body_state(capture_ns=t0 + 60 * ms, reset_counter=0)])  # back: same counter
        feed(bridge, [body_state(capture_ns=t0 + 90 * ms, reset_counter=1)])  # server re-based: +1
        bridge.vehicle("body1").reset()  # origin / alignment changed in the bridge: +1
        feed(bridge, [body_state(capture_ns=t0 + 120 * ms, reset_counter=1)])
        feed(bridge, [body_state(capture_ns=t0 + 150 * ms, reset_counter=255)])  # wraps modulo 256
        assert ap.wait_for(VPE, 5)
        assert [m.fields["reset_counter"] for m in ap.messages(VPE)] == [0, 0, 1, 2, 0]
    finally:
        bridge.close()
        ap.close()


def test_heartbeat_identity_and_timesync():
    bridge, ap = start_pair(sysid=7, ap_kw={"timesync_hz": 20})
    try:
        assert ap.wait_for("TIMESYNC", 3, 5.0)
        hb = ap.messages("HEARTBEAT")[0]
        assert (hb.src_system, hb.src_component) == (7, 197)
        assert hb.fields["type"] == mavlink2.MAV_TYPE_ONBOARD_CONTROLLER
        assert hb.fields["autopilot"] == mavlink2.MAV_AUTOPILOT_INVALID
        r = ap.report()
        assert r["timesync_replies"] >= 3
        # the bridge's tc1 is the server monotonic clock in ns: same clock as ours, offset within the round trip
        rtt, offset = np.array(ap.timesync_samples[-1], dtype=float)
        assert abs(offset) <= rtt
        assert bridge.stats()["vehicles"]["body1"]["timesync_answered"] >= 3
    finally:
        bridge.close()
        ap.close()


def test_epoch_time_base_consistent_with_timesync():
    bridge, ap = start_pair(time_base="epoch", ap_kw={"timesync_hz": 20})
    try:
        st = body_state()
        feed(bridge, [st])
        assert ap.wait_for(VPE, 1) and ap.wait_for("TIMESYNC", 1)
        shift_ns = time.time_ns() - time.monotonic_ns()
        assert abs(ap.messages(VPE)[0].fields["usec"] - (st.capture_ns + shift_ns) // 1000) < 50_000
        rtt, offset = ap.timesync_samples[-1]
        assert abs(offset - shift_ns) < 50_000_000  # tc1 on the same epoch base as usec
    finally:
        bridge.close()
        ap.close()


def test_two_vehicles_no_cross_talk():
    pa, pb = free_ports(2)
    sign = {"key_file": key_file()}
    arena = arena_with_vehicles([
        {"body": "body1", "sysid": 1, "endpoint": f"udpin:127.0.0.1:{pa}", "signing": sign},
        {"body": "body2", "sysid": 2, "endpoint": f"udpin:127.0.0.1:{pb}", "message": "odometry", "signing": sign},
    ])
    bridge = Bridge(arena, {"report_interval_s": 0})
    bridge.start()
    aps = [FakeAutopilot(f"udpout:127.0.0.1:{p}", sysid=s, signing_key=KEY).start() for p, s in ((pa, 1), (pb, 2))]
    # a third system sending to body1's port with another sysid (even signed with the key) must not be answered
    intruder = FakeAutopilot(f"udpout:127.0.0.1:{pa}", sysid=9, heartbeat_hz=20, signing_key=KEY).start()
    try:
        assert aps[0].wait_for("HEARTBEAT", 1) and aps[1].wait_for("HEARTBEAT", 1)
        assert intruder.wait_for("HEARTBEAT", 1, 0.3) is False
        t0 = time.monotonic_ns()
        for i in range(10):
            c = t0 + i * 20_000_000
            bridge.publish([body_state("body1", 1, capture_ns=c, position=(1, 0, 0)),
                            body_state("body2", 2, capture_ns=c, position=(0, 5, 0))])
            assert bridge.flush(2.0)
        assert aps[0].wait_for(VPE, 10) and aps[1].wait_for(ODO, 10)
        time.sleep(0.1)
        a, b = aps[0].received, aps[1].received
        assert {r.src_system for r in a} == {1} and {r.src_system for r in b} == {2}
        assert not aps[0].messages(ODO) and not aps[1].messages(VPE)
        assert all(decode_pose(r)["position_ned"].tolist() == [1, 0, 0] for r in aps[0].messages(VPE))
        assert all(decode_pose(r)["position_ned"].tolist() == [0, -5, 0] for r in aps[1].messages(ODO))
        assert intruder.received == []
        assert bridge.stats()["vehicles"]["body1"]["rx_foreign"] > 0
    finally:
        bridge.close()
        for ap in aps + [intruder]:
            ap.close()


def _write_key(tmp_path, name, text):
    p = tmp_path / name
    p.write_text(text)
    return p


def test_signing_accepted_and_rejected(tmp_path):
    import hashlib

    key_file = _write_key(tmp_path, "fleet.key", "correct horse battery staple\n")
    key = hashlib.sha256(b"correct horse battery staple").digest()  # MAVProxy's passphrase -> key rule
    # udpout: the bridge sends whether or not it can verify the autopilot, so a wrong key shows up at the receiver
    good, bad = (FakeAutopilot("udpin:127.0.0.1:0", sysid=s, signing_key=k, timesync_hz=0).start()
                 for s, k in ((1, key), (2, hashlib.sha256(b"another fleet").digest())))
    arena = arena_with_vehicles([
        {
            "body": "body1", "sysid": 1, "endpoint": f"udpout:127.0.0.1:{good.port}",
            "signing": {"key_file": str(key_file)},
        },
        {
            "body": "body2", "sysid": 2, "endpoint": f"udpout:127.0.0.1:{bad.port}",
            "signing": {"key_file": str(key_file)},
        },
    ])
    bridge = Bridge(arena, {"report_interval_s": 0})
    bridge.start()
    try:
        t0 = time.monotonic_ns()
        for i in range(5):
            c = t0 + i * 20_000_000
            bridge.publish([body_state("body1", 1, capture_ns=c), body_state("body2", 2, capture_ns=c)])
            assert bridge.flush(2.0)
        assert good.wait_for(VPE, 5)
        assert all(r.signed for r in good.received)
        deadline = time.monotonic() + 2.0
        while bad.rejected_signature < 6 and time.monotonic() < deadline:
            time.sleep(0.01)
        assert bad.rejected_signature >= 6 and bad.received == []  # 5 poses + heartbeat, all refused
        # the bridge verifies what the autopilot signs: good's heartbeats are accepted, none rejected
        assert bridge.stats()["vehicles"]["body1"]["rx_bad"] == 0
    finally:
        bridge.close()
        good.close()
        bad.close()


def test_signing_key_file_forms(tmp_path):
    from bridge.config import load_signing_key

    raw = bytes(range(32))
    (tmp_path / "raw").write_bytes(raw)
    (tmp_path / "hex").write_text(raw.hex() + "\n")
    assert load_signing_key(tmp_path / "raw") == raw
    assert load_signing_key(tmp_path / "hex") == raw


def test_origin_and_home_target_the_vehicle():
    # PX4 takes SET_HOME_POSITION; ArduPilot gets MAV_CMD_DO_SET_HOME (test_backchannel)
    bridge, ap = start_pair(sysid=3, origin={"lat": 47.397742, "lon": 8.545594, "alt": 488.0},
                            ap_kw={"autopilot": "px4"})
    try:
        assert ap.wait_for("SET_GPS_GLOBAL_ORIGIN", 1) and ap.wait_for("SET_HOME_POSITION", 1)
        o = ap.messages("SET_GPS_GLOBAL_ORIGIN")[0].fields
        h = ap.messages("SET_HOME_POSITION")[0].fields
        assert (o["target_system"], o["latitude"], o["longitude"], o["altitude"]) == (3, 473977420, 85455940, 488000)
        assert (h["target_system"], h["latitude"], h["longitude"], h["altitude"]) == (3, 473977420, 85455940, 488000)
    finally:
        bridge.close()
        ap.close()


def test_tcp_reconnects_with_backoff():
    port = free_port(socket.SOCK_STREAM)
    arena = arena_with_vehicles([{"body": "body1", "sysid": 1, "endpoint": f"tcp:127.0.0.1:{port}",
                                  "reconnect_min_s": 0.05, "reconnect_max_s": 0.2}])
    bridge = Bridge(arena, {"report_interval_s": 0})
    bridge.start()
    aps = []
    try:
        deadline = time.monotonic() + 3
        while bridge.stats()["vehicles"]["body1"]["link_errors"] < 2 and time.monotonic() < deadline:
            time.sleep(0.01)
        assert bridge.stats()["vehicles"]["body1"]["link_errors"] >= 2  # nobody listening yet
        for round_ in range(2):
            ap = FakeAutopilot(f"tcpin:127.0.0.1:{port}", sysid=1, timesync_hz=0).start()
            aps.append(ap)
            deadline = time.monotonic() + 5
            while not ap.messages(VPE) and time.monotonic() < deadline:
                bridge.publish([body_state()])
                time.sleep(0.025)
            assert ap.messages(VPE), f"no pose over tcp in round {round_}"
            assert decode_pose(ap.messages(VPE)[0])["position_ned"].tolist() == [0, 0, 0]
            ap.close()  # the autopilot goes away; the bridge must come back to the next one
        assert bridge.stats()["vehicles"]["body1"]["reconnects"] >= 1
    finally:
        bridge.close()
        for ap in aps:
            ap.close()


def test_serial_link_over_pty():
    pytest.importorskip("serial")
    master, slave = os.openpty()
    try:
        arena = arena_with_vehicles([{"body": "body1", "sysid": 4, "endpoint": f"serial:{os.ttyname(slave)}:115200"}])
        bridge = Bridge(arena, {"report_interval_s": 0})
        bridge.start()
        parser = mavlink2.MAVLink(None)
        os.set_blocking(master, False)
        got = []
        try:
            deadline = time.monotonic() + 5
            while not any(m.get_type() == VPE for m in got) and time.monotonic() < deadline:
                bridge.publish([body_state(position=(0, 1, 0))])
                time.sleep(0.025)
                try:
                    got += parser.parse_buffer(os.read(master, 4096)) or []
                except BlockingIOError:
                    pass
        finally:
            bridge.close()
        poses = [m for m in got if m.get_type() == VPE]
        assert poses and (poses[0].get_srcSystem(), poses[0].get_srcComponent()) == (4, 197)
        assert (poses[0].x, poses[0].y, poses[0].z) == pytest.approx((0, -1, 0))
        assert any(m.get_type() == "HEARTBEAT" for m in got)
    finally:
        os.close(master)
        os.close(slave)


def test_publish_never_blocks_on_a_dead_link():
    # nobody ever answers on udpin: publish keeps only the newest state, nothing is sent
    bridge = Bridge(arena_with_vehicles([{"body": "body1", "endpoint": f"udpin:127.0.0.1:{free_port()}",
                                          "signing": {"key_file": key_file()}}]),
                    {"report_interval_s": 0})
    bridge.start()
    try:
        t0 = time.monotonic_ns()
        for i in range(200):
            bridge.publish([body_state(capture_ns=t0 + i * 10_000_000)])
        assert bridge.flush(2.0)
        s = bridge.stats()["vehicles"]["body1"]
        assert s["sent"] == 0 and s["link_up"] is False
        # every state is either superseded in the mailbox or counted as having no link
        assert s["superseded"] + s["no_link"] + s["rate_limited"] == 200
    finally:
        bridge.close()


def test_latency_advice_printed():
    lines = []
    port = free_port()
    arena = arena_with_vehicles([{"body": "body1", "endpoint": f"udpin:127.0.0.1:{port}",
                                  "signing": {"key_file": key_file()}}])
    bridge = Bridge(arena, {"report_interval_s": 3600, "report": lines.append})
    bridge.start()
    ap = FakeAutopilot(f"udpout:127.0.0.1:{port}", sysid=1, signing_key=KEY).start()
    try:
        assert ap.wait_for("HEARTBEAT", 1)
        feed(bridge, [body_state(capture_ns=time.monotonic_ns() - 15_000_000)])
        assert ap.wait_for(VPE, 1)
    finally:
        bridge.close()
        ap.close()
    assert lines and "VISO_DELAY_MS=" in lines[-1] and "EKF2_EV_DELAY" in lines[-1]
    lat = bridge.stats()["vehicles"]["body1"]["latency_capture_ms_p50"]
    assert lat >= 15.0  # the state was captured 15 ms before it was published


def test_udpin_relearns_the_autopilot_address():
    bridge, ap1 = start_pair(ap_kw={"timesync_hz": 0})
    port = bridge.vehicles[0].cfg.endpoint.port
    ap2 = None
    try:
        # captured 200 ms ago, so the next pose is never inside the 50 Hz rate limit however fast ap2 starts
        feed(bridge, [body_state(position=(1, 0, 0), capture_ns=time.monotonic_ns() - 200_000_000)])
        assert ap1.wait_for(VPE, 1)
        ap1.close()  # the companion restarts and comes back from another source port
        ap2 = FakeAutopilot(f"udpout:127.0.0.1:{port}", sysid=1, timesync_hz=0, signing_key=KEY).start()
        assert ap2.wait_for("HEARTBEAT", 1)
        feed(bridge, [body_state(position=(2, 0, 0))])
        assert ap2.wait_for(VPE, 1)
        assert decode_pose(ap2.messages(VPE)[0])["position_ned"].tolist() == [2, 0, 0]
        assert len(ap1.messages(VPE)) == 1
        s = bridge.stats()["vehicles"]["body1"]
        assert s["reconnects"] == 1 and s["peer"].endswith(str(ap2._sock.getsockname()[1]))
    finally:
        bridge.close()
        ap1.close()
        if ap2 is not None:
            ap2.close()


def test_latency_percentiles_are_numpys():
    from bridge.link_stats import percentiles_ms

    rng = np.random.default_rng(5)
    for n in (1, 2, 7, 4096):
        lat_ns = rng.integers(0, 50_000_000, n)
        assert np.allclose(percentiles_ms(lat_ns, (0, 50, 99, 100)), np.percentile(lat_ns, [0, 50, 99, 100]) * 1e-6,
                           rtol=1e-12, atol=0)
    assert all(np.isnan(percentiles_ms(np.zeros(0, np.int64), (50, 99))))


def test_the_latency_line_advises_ardupilot_the_smallest_and_px4_the_mean_and_what_ekf2_trails_by():
    """docs/autopilot-setup.md, 3.: before the back-channel measures, the report line's two settings."""
    from pathlib import Path

    from bridge.link_stats import delay_advice

    stats = {"body": "b", "sysid": 1, "latency_capture_ms_p50": 12.0, "latency_capture_ms_p99": 31.0,
             "latency_stamp_ms_p50": 11.0, "latency_stamp_ms_mean": 13.0, "latency_stamp_ms_jitter_min": 10.0,
             "latency_bridge_ms_p50": 0.1}
    line = delay_advice(stats)
    assert "ArduPilot VISO_DELAY_MS=10 (the smallest of each 100 poses + link latency)" in line
    assert "PX4 EKF2_EV_DELAY=14.3 (the mean +1.35 ms + link latency) without TIMESYNC" in line  # 13 + 1.35
    line = delay_advice({**stats, "message": "odometry", "latency_stamp_ms_mean": 20.0})
    assert "PX4 EKF2_EV_DELAY=20.6 (the mean +0.62 ms + link latency) without TIMESYNC" in line  # 20 - 1.26 + 1.88
    doc = " ".join((Path(__file__).resolve().parents[2] / "docs" / "autopilot-setup.md").read_text().split())
    assert "PX4 EKF2_EV_DELAY=M (the mean +1.35 ms + link latency) without TIMESYNC, ~0 with TIMESYNC " \
           "converged`" in doc


def test_several_vehicles_share_one_reset_counter():
    """With several vehicles every pose carries one counter, the sum of every body's and every link's resets: a
    pose that reaches another autopilot over a crossed link (before the bridge hears that autopilot) carries the
    counter that autopilot already has, so its EKF gates the other drone's position instead of resetting to it
    (ArduPilot resets its position to the vision at any change of the counter: measured with two SITLs)."""
    pa, pb = free_ports(2)
    sign = {"signing": {"key_file": key_file()}, "max_age_ms": 10000}
    bridge = Bridge(arena_with_vehicles([
        {"body": "body1", "sysid": 1, "endpoint": f"udpin:127.0.0.1:{pa}", **sign},
        {"body": "body2", "sysid": 2, "endpoint": f"udpin:127.0.0.1:{pb}", **sign}]), {"report_interval_s": 0})
    bridge.start()
    aps = [FakeAutopilot(f"udpout:127.0.0.1:{p}", sysid=s, signing_key=KEY).start() for p, s in ((pa, 1), (pb, 2))]
    try:
        assert all(ap.wait_for("HEARTBEAT", 1, 5.0) for ap in aps)
        t0, ms = time.monotonic_ns(), 1_000_000
        for k, (r1, r2, local) in enumerate([(0, 0, 0), (1, 0, 0), (1, 3, 0), (1, 3, 1)]):
            if local:
                bridge.vehicle("body2").reset()  # a bridge reset of one vehicle counts for all
            c = t0 + 30 * ms * k
            bridge.publish([body_state("body1", 1, capture_ns=c, reset_counter=r1),
                            body_state("body2", 2, capture_ns=c, reset_counter=r2)])
            assert bridge.flush(2.0)
        assert all(ap.wait_for(VPE, 4) for ap in aps)
        for ap in aps:
            assert [m.fields["reset_counter"] for m in ap.messages(VPE)] == [0, 1, 4, 5]
    finally:
        bridge.close()
        for ap in aps:
            ap.close()
