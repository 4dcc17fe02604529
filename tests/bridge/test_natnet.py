"""NatNet server on 127.0.0.1 against clients this project did not write: OptiTrack's `natnetsdk` Python client
(unicast, bitstreams 4.1 and 3.1) and libmotioncapture's `motioncapture` binding in `optitrack` mode (multicast on
the loopback interface: in unicast it listens on the data port of its own host while a Motive-compatible server
sends unicast frames to the address the client connected from, see docs/interop.md). Plus hostile input."""

import json
import math
import socket
import struct
import subprocess
import sys
import threading
import time

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from bridge.natnet import NatNetServer, parse_natnet
from visionpos.app.ports import free_ports
from visionpos.benchmarks.factories import body_state
from visionpos.config.arena import ConfigError, parse_arena

RATE_HZ = 100.0
# Streamed y-up axes from world z-up: (x, y, z) -> (x, z, -y); written out here, not taken from the code.
Y_UP = np.array([[1.0, 0, 0], [0, 0, 1.0], [0, -1.0, 0]])
MARKERS = [[[0.05, 0, 0], [0, 0.04, 0], [-0.03, -0.03, 0.01]], [[0.06, 0.01, 0], [0, -0.05, 0], [-0.02, 0.03, 0.02]]]


def arena(natnet: dict, source="natnet-test.yaml"):
    bodies = [{"name": "cf1", "id": 7, "markers": MARKERS[0]}, {"name": "drone_b", "id": 12, "markers": MARKERS[1]}]
    return parse_arena({"bodies": bodies, "natnet": natnet}, source)


def server(**kw):
    cfg = {"interface": "127.0.0.1", **dict(zip(("command_port", "data_port"), free_ports(2))), **kw}
    s = NatNetServer.from_arena(arena(cfg))
    s.start()
    return s


def poses(t: float, lost: bool = False):
    """Two moving bodies as the fusion hands them over; drone_b untracked when lost."""
    q1 = Rotation.from_euler("zyx", [0.3 + t, 0.2, -0.1]).as_quat()
    q2 = Rotation.from_euler("zyx", [-1.2, 0.05 * t, 0.4]).as_quat()
    return [
        body_state("cf1", 7, position=(1.25 + 0.1 * t, -0.5, 0.75), quaternion=q1, residual_mm=0.3),
        body_state("drone_b", 12, position=(-2.0, 3.5 - 0.2 * t, 1.1), quaternion=q2, tracked=not lost,
                   residual_mm=0.5),
    ]


def expected(st, up="y"):
    """Position and rotation matrix a client should see for a BodyState (world and body frames both re-axed)."""
    M = Y_UP if up == "y" else np.eye(3)
    R = Rotation.from_quat(st.quaternion).as_matrix()
    return M @ st.position, M @ R @ M.T


def check_pose(pos, quat_xyzw, st, up="y"):
    p, R = expected(st, up)
    np.testing.assert_allclose(pos, p, atol=1e-5)  # float32 on the wire
    got = Rotation.from_quat(quat_xyzw).as_matrix()
    np.testing.assert_allclose(got, R, atol=2e-6)  # float32 quaternion


def drive(srv, seconds, lost=False, rate_hz=RATE_HZ, sent=None):
    """Publish at rate_hz for `seconds` on this thread (like the server's output tick)."""
    t0 = time.monotonic()
    k = 0
    while True:
        due = t0 + k / rate_hz
        now = time.monotonic()
        if now - t0 >= seconds:
            return k
        if now < due:
            time.sleep(due - now)
        st = poses(k / rate_hz, lost)
        srv.publish(st)
        if sent is not None:
            sent.append(st)
        k += 1


# ---- natnetsdk -------------------------------------------------------------------------------------------------


def natnet_client(srv):
    NatNetClient = pytest.importorskip("natnetsdk.NatNetClient", reason="natnetsdk (OptiTrack's Python client) is "
                                       "not installed: pip install -e .[test]").NatNetClient
    c = NatNetClient()
    c.set_client_address("127.0.0.1")
    c.set_server_address("127.0.0.1")
    c.set_use_multicast(False)
    c.command_port = srv.command_port
    c.data_port = srv.data_port
    c.set_print_level(0)
    got = {"frames": [], "descs": []}
    unpack_frame = c._NatNetClient__unpack_mocap_data
    unpack_desc = c._NatNetClient__unpack_data_descriptions

    def on_frame(*a):
        off, data = unpack_frame(*a)
        got["frames"].append((time.monotonic(), data))
        return off, data

    def on_desc(*a):
        off, data = unpack_desc(*a)
        got["descs"].append(data)
        return off, data

    c._NatNetClient__unpack_mocap_data = on_frame  # their decoder, observed
    c._NatNetClient__unpack_data_descriptions = on_desc
    return c, got


def shutdown(c):
    """natnetsdk's shutdown joins a data thread blocked in recvfrom without timeout: wake it first."""
    c.stop_threads = True
    if c.data_socket is not None:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            s.sendto(struct.pack("<HH", 999, 0), ("127.0.0.1", c.data_socket.getsockname()[1]))
    c.shutdown()


def wait_for(pred, timeout_s=5.0):
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if pred():
            return True
        time.sleep(0.01)
    return False


def last_sent(sent, frame):
    """The published states whose cf1 position matches this frame (frames can be in flight)."""
    x = frame.rigid_body_data.rigid_body_list[0].pos[0]
    return min(sent, key=lambda s: abs(s[0].position[0] - x))


def test_natnetsdk_unicast_bodies_poses_validity_rate_and_bitstream_change():
    srv = server(transmission="unicast")
    c, got = natnet_client(srv)
    try:
        assert c.run()
        assert wait_for(lambda: c.get_server_version()[0] + c.get_server_version()[1] > 0 or
                        c.get_application_name() != "Not Set")
        assert c.get_application_name() == "visionpos"
        assert c.get_nat_net_version_server()[:2] == [4, 1]
        c.send_request(c.command_socket, c.NAT_REQUEST_MODELDEF, "", ("127.0.0.1", srv.command_port))
        assert wait_for(lambda: got["descs"])
        rbs = [d for d in got["descs"][0].rigid_body_list]
        assert [(r.sz_name.decode(), r.id_num) for r in rbs] == [("cf1", 7), ("drone_b", 12)]
        assert all(r.parent_id == -1 for r in rbs)
        # marker offsets in the body frame, re-axed like the world
        np.testing.assert_allclose([m.pos for m in rbs[0].rb_marker_list], (Y_UP @ np.array(MARKERS[0]).T).T,
                                   atol=1e-6)

        sent = []
        drive(srv, 0.3, sent=sent)  # warm-up
        time.sleep(0.2)  # the warm-up's frames still in flight arrive before the count starts
        n0 = len(got["frames"])
        k = drive(srv, 1.0, sent=sent)
        wait_for(lambda: len(got["frames"]) - n0 >= k, 1.0)
        # the frames of that second, counted when they arrive: the client's reader thread may run late on a
        # busy 2-core machine, so its receive times are not the send rate; a frame lost is still missing
        window = [f for _, f in got["frames"][n0:]]
        assert k >= 0.95 * RATE_HZ
        assert len(window) >= 0.9 * k, f"{len(window)} of the {k} frames sent in 1 s at {RATE_HZ} Hz"
        frame = got["frames"][-1][1]
        st = last_sent(sent, frame)
        by_id = {rb.id_num: rb for rb in frame.rigid_body_data.rigid_body_list}
        assert set(by_id) == {7, 12}
        for s in st:
            rb = by_id[s.body_id]
            assert rb.tracking_valid
            check_pose(rb.pos, rb.rot, s)
            assert rb.error == pytest.approx(s.residual_mm * 1e-3, rel=1e-5)
        sfx = frame.suffix_data
        assert sfx.stamp_camera_mid_exposure <= sfx.stamp_data_received <= sfx.stamp_transmit
        assert sfx.stamp_camera_mid_exposure == max(s.capture_ns for s in st)  # server monotonic ns
        numbers = [f.prefix_data.frame_number for _, f in got["frames"]]
        assert numbers == sorted(numbers)
        # labelled markers of the tracked bodies: model id in the high word
        ids = {lm.id_num >> 16 for lm in frame.labeled_marker_data.labeled_marker_list}
        assert ids == {7, 12}

        # drone_b lost: flagged not valid, never its old pose
        n1 = len(got["frames"])
        drive(srv, 0.2, lost=True)
        assert wait_for(lambda: len(got["frames"]) > n1 + 5)
        rb = {r.id_num: r for r in got["frames"][-1][1].rigid_body_data.rigid_body_list}
        assert rb[7].tracking_valid and not rb[12].tracking_valid
        assert tuple(rb[12].pos) == (0.0, 0.0, 0.0)

        # the client's bitstream change (it sends Bitstream,3.1 then timeline commands and waits 2 s)
        assert c.set_nat_net_version(3, 1) >= 0
        n2 = len(got["frames"])
        sent = []
        drive(srv, 0.3, sent=sent)
        assert wait_for(lambda: len(got["frames"]) > n2 + 10)
        frame = got["frames"][-1][1]
        assert frame.suffix_data.stamp_transmit > 0  # decoded as 3.1 (4.x adds fields it would misread)
        st = last_sent(sent, frame)
        for rb in frame.rigid_body_data.rigid_body_list:
            check_pose(rb.pos, rb.rot, next(s for s in st if s.body_id == rb.id_num))
        assert srv.stats()["clients"] == {f"127.0.0.1:{c.command_socket.getsockname()[1]}": "3.1"}
    finally:
        shutdown(c)
        srv.close()


# ---- libmotioncapture ------------------------------------------------------------------------------------------

MOCAP_CLIENT = r"""
import json, sys, time
import motioncapture
mc = motioncapture.connect("optitrack", {"hostname": "127.0.0.1", "interface_ip": "127.0.0.1",
                                         "port_command": sys.argv[1]})
print("ready", flush=True)
end = time.monotonic() + float(sys.argv[2])
while time.monotonic() < end:
    mc.waitForNextFrame()
    out = {n: [list(map(float, b.position)), [b.rotation.x, b.rotation.y, b.rotation.z, b.rotation.w]]
           for n, b in mc.rigidBodies.items()}
    print(json.dumps([time.monotonic(), out]), flush=True)
"""


@pytest.mark.parametrize("up", ["z", "y"])
def test_motioncapture_optitrack_multicast_on_loopback(up):
    pytest.importorskip("motioncapture", reason="motioncapture (libmotioncapture) is not installed: "
                        "pip install -e .[test]")
    srv = server(transmission="multicast", up_axis=up, bitstream="4.1" if up == "z" else "3.1")
    proc = subprocess.Popen([sys.executable, "-c", MOCAP_CLIENT, str(srv.command_port), "1.6"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    lines = []
    reader = threading.Thread(target=lambda: lines.extend(proc.stdout), daemon=True)
    reader.start()
    try:
        assert wait_for(lambda: lines and lines[0].startswith("ready"), 5.0), proc.stderr.read() if \
            proc.poll() is not None else "no answer"
        sent = []
        drive(srv, 0.2, sent=sent)
        n_warm = len(sent)
        drive(srv, 1.0, sent=sent)
        end = time.monotonic() + 5.0
        while proc.poll() is None and time.monotonic() < end:  # lost until the client has seen it and quit
            drive(srv, 0.1, lost=True)
        proc.wait(timeout=5)
        reader.join(timeout=2)
        frames = [json.loads(x) for x in lines[1:]]
        # the frames of the measured second, recognised by their pose (cf1's x grows 0.1 m/s from 1.25 m in
        # every drive; past 0.2 s of it no warm-up or lost pose has that x), not by the client's read times,
        # which a busy 2-core machine delays and bunches; a frame lost is still missing
        x_sent = np.array([st[0].position[0] for st in sent[n_warm:]])
        beyond = 1.25 + 0.1 * 0.2 + 1e-4
        got = {int(np.argmin(np.abs(x_sent - f["cf1"][0][0]))) for _, f in frames
               if "cf1" in f and f["cf1"][0][0] > beyond and np.abs(x_sent - f["cf1"][0][0]).min() < 1e-5}
        expected_n = int((x_sent > beyond).sum())
        assert expected_n >= 0.7 * RATE_HZ
        assert len(got) >= 0.85 * expected_n, f"{len(got)} of the {expected_n} frames sent"
        in_window = [f for _, f in frames if "cf1" in f and f["cf1"][0][0] > beyond]
        for body in in_window[-20:]:
            assert set(body) == {"cf1", "drone_b"}
        last = in_window[-1]
        x_axis = 0  # x is the same axis in both conventions
        st = min(sent, key=lambda s: abs(s[0].position[x_axis] - last["cf1"][0][0]))
        for s in st:
            check_pose(last[s.name][0], last[s.name][1], s, up)
        # drone_b lost: libmotioncapture leaves out bodies whose tracking-valid flag is clear
        assert set(frames[-1][1]) == {"cf1"}
    finally:
        if proc.poll() is None:
            proc.kill()
        srv.close()


# ---- hostile and odd input -------------------------------------------------------------------------------------


def command_socket(srv):
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    s.settimeout(1.0)
    return s


def ask(s, srv, msg_id, payload=b""):
    s.sendto(struct.pack("<HH", msg_id, len(payload)) + payload, ("127.0.0.1", srv.command_port))
    data = s.recv(65535)
    return struct.unpack_from("<H", data)[0], data[4:]


def test_requests_unknown_malformed_and_unconnected_are_answered_or_dropped(caplog):
    srv = server(transmission="unicast", max_clients=2)
    socks = [command_socket(srv) for _ in range(4)]
    try:
        s = socks[0]
        # not connected: dropped, nothing registered
        s.sendto(struct.pack("<HH", 4, 0), ("127.0.0.1", srv.command_port))
        with pytest.raises(socket.timeout):
            s.recv(100)
        assert srv.stats()["clients"] == {}
        mid, body = ask(s, srv, 0)  # libmotioncapture's connect: no payload -> the configured bitstream
        assert mid == 1 and body[:9] == b"visionpos"
        assert body[260:262] == bytes([4, 1])
        assert struct.unpack_from("<QHB", body, 264) == (1_000_000_000, srv.data_port, 0)
        assert ask(s, srv, 2, b"Bitstream\0") == (3, b"Bitstream,4.1\0")
        assert ask(s, srv, 2, b"UnitsToMillimeters\0") == (3, struct.pack("<f", 1000.0))
        assert ask(s, srv, 2, b"TimelinePlay\0") == (3, struct.pack("<i", 0))
        assert ask(s, srv, 2, b"SetPlaybackTakeName,take1\0")[0] == 100
        assert ask(s, srv, 2, b"Bitstream,2.9\0") == (3, struct.pack("<i", 1))
        assert ask(s, srv, 2, b"\xff\xfe\0")[0] == 100
        assert ask(s, srv, 77)[0] == 100
        mid, body = ask(s, srv, 12, struct.pack("<Q", 123456789))
        assert mid == 13 and struct.unpack("<Q", body[:8])[0] == 123456789
        # malformed: dropped, the server goes on answering
        for junk in (b"", b"\x00", b"\x02\x00\xff\x00abc", b"\x04\x00\xff\xff" + bytes(range(256)) * 100):
            s.sendto(junk, ("127.0.0.1", srv.command_port))
        assert ask(s, srv, 2, b"CurrentMode\0") == (3, struct.pack("<i", 0))
        # client limit: the third is refused with a message, the first two keep their place
        assert ask(socks[1], srv, 0)[0] == 1
        mid, body = ask(socks[2], srv, 0)
        assert mid == 8 and b"client limit (2)" in body
        assert len(srv.stats()["clients"]) == 2
        # one log line per cause despite repeats
        for _ in range(20):
            socks[3].sendto(b"\x01", ("127.0.0.1", srv.command_port))
        assert wait_for(lambda: srv.stats()["causes"].get("datagram shorter than the 4-byte header", 0) >= 21)
        lines = [r for r in caplog.records if "shorter than the 4-byte header" in r.getMessage()]
        assert len(lines) == 1
        assert all(t.is_alive() for t in srv._threads)
    finally:
        for x in socks:
            x.close()
        srv.close()


def test_publish_never_blocks_and_untracked_pose_is_never_sent():
    srv = server(transmission="unicast")
    try:
        t0 = time.perf_counter()
        for k in range(2000):
            srv.publish(poses(k * 0.01))
        assert (time.perf_counter() - t0) / 2000 < 1e-3  # a mailbox hand-over, not an encode-and-send
        f = srv.build_frame(poses(0.0, lost=True), None, time.monotonic_ns())
        b = {i: (p, q, ok) for i, p, q, e, ok in f.bodies}
        assert b[12][2] is False and np.all(b[12][0] == 0) and tuple(b[12][1]) == (0, 0, 0, 1)
        assert all(lid >> 16 != 12 for lid, *_ in f.labeled)
    finally:
        srv.close()


def test_config_errors_name_file_key_and_fix():
    with pytest.raises(ConfigError, match=r"natnet-test.yaml.*natnet.multicast_group.*239.255.42.99"):
        parse_natnet(arena({"multicast_group": "10.0.0.1"}))
    with pytest.raises(ConfigError, match=r"natnet.data_port.*differ"):
        parse_natnet(arena({"command_port": 1600, "data_port": 1600}))
    with pytest.raises(ConfigError, match=r"natnet.up_axis"):
        parse_natnet(arena({"up_axis": "x"}))
    with pytest.raises(ConfigError, match=r"natnet.bitstream"):
        parse_natnet(arena({"bitstream": "2.9"}))
    with pytest.raises(ConfigError, match=r"natnet.interface"):
        parse_natnet(arena({"interface": "eth0"}))
    with pytest.raises(ConfigError, match=r"natnet.*tranmission|did you mean"):
        parse_natnet(arena({"tranmission": "unicast"}))
    assert parse_natnet(arena({"enabled": False})) is None
    cfg = parse_natnet(arena({}))
    assert (cfg.transmission, cfg.command_port, cfg.data_port, cfg.multicast_group, cfg.up_axis, cfg.bitstream) == \
        ("multicast", 1510, 1511, "239.255.42.99", "y", (4, 1))
    assert math.isclose(cfg.client_timeout_s, 10.0)


def test_serve_creates_the_natnet_sink_from_the_arena():
    from visionpos.app.outputs import build_outputs

    sinks = build_outputs(arena({"interface": "127.0.0.1", **dict(zip(("command_port", "data_port"), free_ports(2)))}))
    assert [type(s).__name__ for s in sinks] == ["OffLoopOutputs"]
    assert [type(o).__name__ for o in sinks[0].outputs] == ["NatNetServer"]


def test_free_ports_are_distinct_and_bindable():
    """Two free_port() calls may get the same port back (the kernel reuses a port just freed: a NatNet server once
    refused its data port equal to its command port); free_ports binds them all at once."""
    import socket

    ports = free_ports(16)
    assert len(set(ports)) == 16
    socks = [socket.socket(socket.AF_INET, socket.SOCK_DGRAM) for _ in ports]
    try:
        for s, p in zip(socks, ports):
            s.bind(("127.0.0.1", p))
    finally:
        for s in socks:
            s.close()


def test_every_pose_and_its_markers_are_at_the_frames_mid_exposure_time():
    """Clients stamp NatNet poses with CameraMidExposureTimestamp (Motive's poses are at their frame's
    mid-exposure): each state, valid at its output tick, is moved back to the newest capture time among the
    states with its own velocity, body angular velocity and acceleration (written out here with scipy)."""
    import dataclasses
    from types import SimpleNamespace

    c = 5_000_000_000
    tick = c + 6_000_000
    a = dataclasses.replace(
        body_state("cf1", 7, capture_ns=c, dt_ns=tick - c, position=(1.0, -0.5, 0.8),
                   quaternion=Rotation.from_euler("zyx", [0.4, 0.2, -0.1]).as_quat(), velocity=(2.0, -1.0, 0.5),
                   angular_velocity=(0.3, -2.0, 1.0)),
        acceleration=np.array([1.0, 0.0, -2.0]))
    b = body_state("drone_b", 12, capture_ns=c - 3_000_000, dt_ns=tick - c + 3_000_000, position=(-2.0, 3.5, 1.1),
                   quaternion=Rotation.from_euler("zyx", [-1.2, 0.0, 0.4]).as_quat(), velocity=(0.0, 1.0, 0.0),
                   angular_velocity=(0.0, 0.0, 0.5))  # no acceleration (NaN): moved at constant velocity
    srv = server(transmission="unicast", markers=True)
    try:
        f = srv.build_frame([a, b], None, tick)
    finally:
        srv.close()
    assert f.mid_exposure_ticks == c and f.data_ready_ticks == tick
    dt = (tick - c) * 1e-9  # both move back by 6 ms: to the frame's mid-exposure, not each to its own capture
    moved = {
        7: (np.array([1.0, -0.5, 0.8]) - np.array([2.0, -1.0, 0.5]) * dt + 0.5 * np.array([1.0, 0.0, -2.0]) * dt**2,
            Rotation.from_quat(a.quaternion) * Rotation.from_rotvec(-np.array([0.3, -2.0, 1.0]) * dt)),
        12: (np.array([-2.0, 3.5, 1.1]) - np.array([0.0, 1.0, 0.0]) * dt,
             Rotation.from_quat(b.quaternion) * Rotation.from_rotvec(-np.array([0.0, 0.0, 0.5]) * dt)),
    }
    got = {i: (p, q, ok) for i, p, q, e, ok in f.bodies}
    for body_id, (p, R) in moved.items():
        assert got[body_id][2] is True
        check_pose(got[body_id][0], got[body_id][1], SimpleNamespace(position=p, quaternion=R.as_quat()))
    # cf1's first model marker, solved at the same instant, in the streamed axes
    marker = next(pt for lid, pt, *_ in f.labeled if lid == (7 << 16) | 1)
    np.testing.assert_allclose(marker, Y_UP @ (moved[7][0] + moved[7][1].apply(MARKERS[0][0])), atol=1e-9)
