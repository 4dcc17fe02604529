"""UDP pose stream on 127.0.0.1: JSON lines, binary layout as documented, the docs' client examples."""

import json
import math
import re
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from bridge import Bridge, PoseStream
from bridge.config import parse_pose_stream
from bridge.pose_stream import decode_binary, upper_to_full
from visionpos.app.ports import free_port
from visionpos.benchmarks.factories import arena_with_vehicles, body_state
from visionpos.config.arena import ConfigError

DOC = Path(__file__).resolve().parents[2] / "docs" / "pose-stream.md"


def receiver():
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    s.settimeout(5.0)
    return s, s.getsockname()[1]


def states():
    C = np.diag([1e-6, 2e-6, 3e-6, 4e-5, 5e-5, 6e-5])
    C[0, 1] = C[1, 0] = 5e-7
    a = body_state("body1", 1, position=(1.25, -2.5, 0.75), quaternion=(0, 0, math.sqrt(0.5), math.sqrt(0.5)),
                   velocity=(0.5, 0, -0.25), angular_velocity=(0, 0, 0.3), covariance=C, reset_counter=2,
                   n_markers=4, n_cameras=5, residual_mm=0.42, dt_ns=7_000_000)
    b = body_state("body2", 2, position=(0, 0, 0), tracked=False, residual_mm=float("nan"), n_markers=0, n_cameras=0)
    return [a, b]


def test_json_lines_content():
    sock, port = receiver()
    ps = PoseStream.to(f"127.0.0.1:{port}")
    ps.start()
    try:
        sts = states()
        ps.publish(sts)
        data, _ = sock.recvfrom(65535)
    finally:
        ps.close()
        sock.close()
    lines = data.decode().splitlines()
    assert data.endswith(b"\n") and len(lines) == 2
    a, b = (json.loads(x) for x in lines)
    assert (a["name"], a["id"], a["tracked"], b["name"], b["tracked"]) == ("body1", 1, True, "body2", False)
    assert a["position"] == [1.25, -2.5, 0.75] and a["velocity"] == [0.5, 0.0, -0.25]
    assert a["quaternion"] == pytest.approx([0, 0, math.sqrt(0.5), math.sqrt(0.5)], abs=1e-7)
    assert a["time_ns"] - a["capture_ns"] == 7_000_000 and a["capture_ns"] == sts[0].capture_ns
    assert a["sent_ns"] >= a["capture_ns"]
    assert len(a["covariance"]) == 21 and a["covariance"][:2] == [1e-6, 5e-7] and a["covariance"][6] == 2e-6
    assert a["covariance"][20] == 6e-5 and len(a["velocity_covariance"]) == 6
    assert (a["n_markers"], a["n_cameras"], a["residual_mm"], a["reset_counter"]) == (4, 5, 0.42, 2)
    assert b["residual_mm"] is None  # NaN -> null


def test_binary_layout_matches_docs():
    import struct

    sock, port = receiver()
    ps = PoseStream.to(f"127.0.0.1:{port}", format="binary")
    ps.start()
    try:
        sts = states()
        ps.publish(sts)
        data, _ = sock.recvfrom(65535)
    finally:
        ps.close()
        sock.close()
    assert len(data) == 24 + 2 * 208
    magic, version, n, size, seq, _, sent_ns = struct.unpack_from("<4sBBHIIq", data, 0)
    assert (magic, version, n, size, seq) == (b"VPS1", 1, 2, 208, 1)
    o = 24  # first record, offsets from the table in docs/pose-stream.md
    assert struct.unpack_from("<HBBBB", data, o) == (1, 1, 4, 5, 2)
    assert struct.unpack_from("<qq", data, o + 8) == (sts[0].time_ns, sts[0].capture_ns)
    assert struct.unpack_from("<3d", data, o + 24) == (1.25, -2.5, 0.75)
    assert struct.unpack_from("<4f", data, o + 48) == pytest.approx((0, 0, math.sqrt(0.5), math.sqrt(0.5)), abs=1e-7)
    assert struct.unpack_from("<3f", data, o + 64) == (0.5, 0.0, -0.25)
    assert struct.unpack_from("<f", data, o + 88)[0] == pytest.approx(0.42)
    cov = struct.unpack_from("<21f", data, o + 92)
    assert cov[0] == pytest.approx(1e-6) and cov[1] == pytest.approx(5e-7) and cov[20] == pytest.approx(6e-5)
    assert struct.unpack_from("<B", data, 24 + 208 + 2)[0] == 0  # second body not tracked
    h, recs = decode_binary(data)
    np.testing.assert_allclose(upper_to_full(recs["covariance"][0], 6), sts[0].covariance, rtol=1e-6)
    assert recs["body_id"].tolist() == [1, 2]
    with pytest.raises(ValueError, match="truncated"):
        decode_binary(data[:100])


def test_rate_limit_with_server_clock():
    now = [0]
    ps = PoseStream.to("127.0.0.1:9", rate_hz=50, clock_ns=lambda: now[0])
    ps.start()
    try:
        for i in range(100):  # 100 Hz ticks for one second
            now[0] = i * 10_000_000
            ps.publish(states()[:1])
    finally:
        ps.close()
    assert ps.stats()["ticks"] == 50 and ps.stats()["skipped_rate"] == 50


def test_bridge_runs_the_arena_pose_stream():
    sock, port = receiver()
    arena = arena_with_vehicles([], pose_stream={"destinations": [f"127.0.0.1:{port}"]}, n_bodies=2)
    bridge = Bridge(arena, {"report_interval_s": 0})
    bridge.start()
    try:
        bridge.publish(states())
        data, _ = sock.recvfrom(65535)
    finally:
        bridge.close()
        sock.close()
    assert [json.loads(x)["name"] for x in data.splitlines()] == ["body1", "body2"]
    assert bridge.stats()["pose_stream"]["datagrams"] == 1


def test_multicast_socket_options():
    ps = PoseStream.to("239.255.42.99:5005", multicast_ttl=3, multicast_loopback=False)
    ps.start()  # nothing is sent: only the options are checked
    try:
        assert ps.sock.getsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL) == 3
        assert ps.sock.getsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_LOOP) == 0
    finally:
        ps.close()


def test_config_errors_name_the_key():
    with pytest.raises(ConfigError, match=r"test-arena.yaml: pose_stream.destinations\[0\]"):
        arena = arena_with_vehicles([], pose_stream={"destinations": ["localhost"]})
        parse_pose_stream(arena)
    with pytest.raises(ConfigError, match=r"pose_stream.format: 'xml' is not one of"):
        parse_pose_stream(arena_with_vehicles([], pose_stream={"destinations": ["127.0.0.1:5005"], "format": "xml"}))
    assert parse_pose_stream(arena_with_vehicles([], pose_stream={"enabled": False})) is None


def _doc_block(marker: str) -> str:
    text = DOC.read_text()
    m = re.search(rf"<!-- {marker}:[^>]*-->\s*```python\n(.*?)```", text, re.S)
    assert m, f"{marker} block missing from {DOC}"
    return m.group(1)


def test_docs_client_example_runs(tmp_path):
    code = _doc_block("pose-stream-client")
    assert len(code.strip().splitlines()) <= 26
    script = tmp_path / "client.py"
    script.write_text(code)
    port = free_port()
    proc = subprocess.Popen(
        [sys.executable, str(script), str(port), "3"], stdout=subprocess.PIPE, stderr=subprocess.PIPE
    )
    ps = PoseStream.to(f"127.0.0.1:{port}")
    ps.start()
    try:
        deadline = time.monotonic() + 15
        while proc.poll() is None and time.monotonic() < deadline:
            ps.publish(states())
            time.sleep(0.05)
    finally:
        ps.close()
        if proc.poll() is None:
            proc.kill()
    out, err = proc.communicate(timeout=5)
    assert proc.returncode == 0, err.decode()
    lines = out.decode().splitlines()
    assert len(lines) == 6  # 3 datagrams x 2 bodies
    assert re.fullmatch(r"\s*body1 tracked x=\+1\.250 y=-2\.500 z=\+0\.750 m  latency \d+\.\d ms", lines[0])
    assert "body2 LOST" in lines[1]


def test_docs_binary_decoder_runs():
    ns: dict = {}
    exec(_doc_block("pose-stream-binary"), ns)
    sock, port = receiver()
    ps = PoseStream.to(f"127.0.0.1:{port}", format="binary")
    ps.start()
    try:
        sts = states()
        ps.publish(sts)
        data, _ = sock.recvfrom(65535)
    finally:
        ps.close()
        sock.close()
    seq, sent_ns, bodies = ns["decode"](data)
    assert seq == 1 and [b[0] for b in bodies] == [1, 2] and [b[1] for b in bodies] == [True, False]
    assert bodies[0][2] == sts[0].capture_ns and bodies[0][3] == (1.25, -2.5, 0.75)


def test_loose_markers_in_datagrams_of_their_own_json_and_binary():
    from bridge.pose_stream import decode_markers_binary
    from visionpos.messages import LoosePoints

    pts = np.array([[0.1, -0.2, 0.05], [1.5, 2.25, 0.007], [-3.0, 0.0, 1.0]])
    lp = LoosePoints(123_456_789, pts, np.array([0.12, 0.3, 0.05]))
    sock, port = receiver()
    try:
        js = PoseStream.to(f"127.0.0.1:{port}", markers=True)
        bn = PoseStream.to(f"127.0.0.1:{port}", format="binary", markers=True)
        off = PoseStream.to(f"127.0.0.1:{port}")  # markers are opt-in: body clients see no new lines
        for ps in (js, bn, off):
            ps.start()
            ps.publish_markers(lp)
        first, _ = sock.recvfrom(65535)
        second, _ = sock.recvfrom(65535)
        sock.settimeout(0.2)
        with pytest.raises(socket.timeout):
            sock.recvfrom(65535)
    finally:
        for ps in (js, bn, off):
            ps.close()
        sock.close()
    obj = json.loads(first)
    assert first.count(b"\n") == 1 and "name" not in obj
    assert obj["markers"] == pts.tolist() and obj["residual_px"] == [0.12, 0.3, 0.05]
    assert obj["time_ns"] == 123_456_789 and obj["sent_ns"] > 0
    h, recs = decode_markers_binary(second)
    assert int(h["n_markers"]) == 3 and int(h["time_ns"]) == 123_456_789
    assert np.array_equal(recs["position"], pts)
    assert recs["residual_px"] == pytest.approx([0.12, 0.3, 0.05], abs=1e-6)
    assert off.stats()["marker_sets"] == 0 and js.stats()["marker_sets"] == 1
    with pytest.raises(ValueError, match="not a visionpos marker"):
        decode_markers_binary(b"VPS1" + second[4:])
    with pytest.raises(ValueError, match="truncated"):
        decode_markers_binary(second[:-8])


def test_json_fast_path_reads_as_the_reference_encoding():
    """The %-format line (all numbers finite) must parse to exactly what json.dumps(state_to_json) gives, for
    values that round at every printed digit; a body with a NaN takes the reference path (NaN -> null)."""
    from bridge.pose_stream import _json_line, state_to_json

    rng = np.random.default_rng(7)
    for k in range(200):
        A = rng.normal(size=(6, 6)) * 10.0 ** rng.integers(-5, 0)
        q = rng.normal(size=4)
        st = body_state(f"quad \"{k}\"/ü", k, capture_ns=int(rng.integers(1, 2**62)), dt_ns=int(rng.integers(0, 10**7)),
                        position=rng.normal(size=3) * 10.0 ** rng.integers(-8, 2), quaternion=q / np.linalg.norm(q),
                        velocity=rng.normal(size=3), angular_velocity=rng.normal(size=3) * 5,
                        covariance=A @ A.T, velocity_covariance=np.diag(rng.uniform(0, 1e-3, 3)),
                        residual_mm=float(rng.uniform(0, 3)), n_markers=int(rng.integers(0, 9)),
                        n_cameras=int(rng.integers(0, 9)), reset_counter=int(rng.integers(0, 1000)),
                        tracked=bool(k % 3))
        line = _json_line(st, 1234)
        assert line.endswith(b"\n") and line.count(b"\n") == 1
        assert json.loads(line) == json.loads(json.dumps(state_to_json(st, 1234)))
    lost = states()[1]  # residual NaN
    assert json.loads(_json_line(lost, 5))["residual_mm"] is None


def test_a_record_moved_back_as_the_docs_say_is_the_pose_vrpn_and_natnet_send():
    """docs/pose-stream.md: the line's pose, moved back by time_ns - capture_ns with its velocity and body angular
    velocity (the rotation multiplied on the right), is the capture-time pose the other outputs send
    (bridge.convert.pose_at), but for the filter's acceleration, which the line does not carry."""
    from scipy.spatial.transform import Rotation

    from bridge.convert import pose_at
    from bridge.pose_stream import encode_json

    st = body_state("cf1", 7, capture_ns=10_000_000_000, dt_ns=6_000_000, position=(1.0, -0.5, 0.8),
                    quaternion=Rotation.from_euler("zyx", [0.4, 0.2, -0.1]).as_quat(), velocity=(2.0, -1.0, 0.5),
                    angular_velocity=(0.3, -2.0, 1.0))
    line = json.loads(encode_json([st], st.time_ns)[0].decode().splitlines()[0])
    dt = (line["time_ns"] - line["capture_ns"]) / 1e9
    p = np.array(line["position"]) - np.array(line["velocity"]) * dt
    q = (Rotation.from_quat(line["quaternion"]) * Rotation.from_rotvec(-np.array(line["angular_velocity"]) * dt))
    p_sent, q_sent = pose_at(st, st.capture_ns)  # no acceleration here: the two agree to the line's rounding
    np.testing.assert_allclose(p, p_sent, atol=2e-6)
    assert (q * Rotation.from_quat(q_sent).inv()).magnitude() < 1e-6
