"""The live Foxglove WebSocket server (foxglove-sdk), seen by a client speaking Foxglove's ws-protocol.

The client is the `websockets` library with the documented protocol on top (subprotocol
foxglove.sdk.v1: the server advertises its channels as JSON, the client subscribes, messages come
as binary frames: opcode 1, subscription id u32, log time u64, payload); the messages are parsed by
Foxglove's official protobuf classes. Skipped with the reason when the extra is not installed.
"""

from __future__ import annotations

import base64
import json
import struct
import time

import numpy as np
import pytest

pytest.importorskip("foxglove", reason="foxglove-sdk (the [foxglove] extra) runs the live server")
ws_client = pytest.importorskip("websockets.sync.client", reason="websockets (the [test] extra) is the client")
fox_pb = pytest.importorskip("foxglove_schemas_protobuf.SceneUpdate_pb2",
                             reason="foxglove-schemas-protobuf (the [test] extra) parses the messages")
from google.protobuf import descriptor_pb2  # noqa: E402  (after the skips: protobuf comes with them)

from bridge.foxglove_live import FoxgloveConfig, FoxgloveServer, parse_foxglove  # noqa: E402
from visionpos.config.arena import ConfigError, load_arena, parse_arena  # noqa: E402
from visionpos.foxglove import channels as C  # noqa: E402
from visionpos.messages import BodyState  # noqa: E402

SUBPROTOCOL = "foxglove.sdk.v1"


def _state(t: int, tracked: bool, x: float) -> BodyState:
    z3 = np.zeros(3)
    return BodyState(name="quad", body_id=1, time_ns=t, capture_ns=t,
                     position=np.array([x, 0.25, 1.0]) if tracked else np.full(3, np.nan),
                     quaternion=np.array([0.0, 0.0, 0.6, 0.8]) if tracked else np.full(4, np.nan),
                     velocity=z3, angular_velocity=z3, covariance=np.eye(6), velocity_covariance=np.eye(3),
                     tracked=tracked)


def _recv_json(ws, op: str, timeout_s: float = 5.0) -> dict:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        m = ws.recv(timeout=max(0.01, end - time.monotonic()))
        if isinstance(m, str) and json.loads(m).get("op") == op:
            return json.loads(m)
    raise AssertionError(f"no {op} within {timeout_s} s")


@pytest.fixture
def server():
    arena = load_arena("thesis")
    srv = FoxgloveServer(FoxgloveConfig(port=0), arena.cameras)  # port 0: any free one, for the test
    srv.start()
    yield srv, arena
    srv.close()


def test_live_scene_reaches_a_ws_protocol_client(server):
    srv, arena = server
    t = 1_000_000_000
    srv.publish([_state(t, True, 0.5)])  # creates the channels (advertised to clients that connect later)
    deadline = time.monotonic() + 5
    while srv.counters["messages"] < 3 and time.monotonic() < deadline:
        time.sleep(0.01)
    with ws_client.connect(f"ws://127.0.0.1:{srv.port}", subprotocols=[SUBPROTOCOL], open_timeout=5) as ws:
        assert ws.subprotocol == SUBPROTOCOL
        adv = _recv_json(ws, "advertise")
        chans = {c["topic"]: c for c in adv["channels"]}
        assert {C.TOPIC_TF, C.TOPIC_ARENA, C.TOPIC_BODIES} <= set(chans)
        body = chans[C.TOPIC_BODIES]
        assert (body["encoding"], body["schemaName"], body["schemaEncoding"]) == \
            ("protobuf", "foxglove.SceneUpdate", "protobuf")
        fds = descriptor_pb2.FileDescriptorSet.FromString(base64.b64decode(body["schema"]))
        assert "foxglove/SceneUpdate.proto" in {f.name for f in fds.file}
        ws.send(json.dumps({"op": "subscribe", "subscriptions": [{"id": 7, "channelId": body["id"]}]}))
        got = []
        tracked = [True] * 6 + [False] * 2
        end = time.monotonic() + 10
        i = 0
        while time.monotonic() < end and len(got) < 7:
            if i < len(tracked):  # one update per 50 ms of data time: past the 30 Hz limit each time
                t += 50_000_000
                srv.publish([_state(t, tracked[i], 0.5 + i)])
                i += 1
            try:
                m = ws.recv(timeout=0.2)
            except TimeoutError:
                continue
            if isinstance(m, bytes):
                op, sub, log_time = struct.unpack_from("<BIQ", m)
                assert (op, sub) == (1, 7)
                got.append((log_time, fox_pb.SceneUpdate.FromString(m[13:])))
    assert len(got) >= 6, f"{len(got)} body updates arrived"
    poses = [(lt, u) for lt, u in got if u.entities]
    assert poses
    for lt, u in poses:  # the pose published for that time, on that time
        (e,) = u.entities
        i = (lt - 1_000_000_000) // 50_000_000 - 1
        assert e.id == "body/quad" and e.timestamp.seconds * 10**9 + e.timestamp.nanos == lt
        assert e.lines[0].pose.position.x == 0.5 + i and e.lines[0].pose.orientation.z == 0.6
    lost = [u for lt, u in got if u.deletions]
    assert lost and [d.id for d in lost[0].deletions] == ["body/quad"] and not lost[0].entities


def test_publish_never_waits_for_clients(server):
    """A client that connects and never reads: the loop's publish() stays a mailbox drop."""
    import socket

    srv, _ = server
    s = socket.create_connection(("127.0.0.1", srv.port), timeout=5)
    s.sendall((f"GET / HTTP/1.1\r\nHost: 127.0.0.1:{srv.port}\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
               "Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\nSec-WebSocket-Version: 13\r\n"
               f"Sec-WebSocket-Protocol: {SUBPROTOCOL}\r\n\r\n").encode())
    try:
        t = 10**9
        worst = 0.0
        for i in range(3000):
            t += 40_000_000
            t0 = time.perf_counter()
            srv.publish([_state(t, True, float(i))])
            worst = max(worst, time.perf_counter() - t0)
        assert worst < 0.05, f"publish took {worst * 1e3:.1f} ms"
        assert srv.counters["errors"] == 0
    finally:
        s.close()


def test_section_is_checked_and_the_extra_named(arena_yaml):
    y = arena_yaml("thesis")
    y["foxglove"] = {"port": 70000}
    with pytest.raises(ConfigError, match="port"):
        parse_foxglove(parse_arena(y, "a.yaml"))
    y["foxglove"] = {"enabled": False}
    assert parse_foxglove(parse_arena(y, "a.yaml")) is None
    y["foxglove"] = {}
    assert parse_foxglove(parse_arena(y, "a.yaml")) == FoxgloveConfig(host="127.0.0.1", port=8765)


def test_without_the_extra_the_error_names_it(monkeypatch):
    import sys

    monkeypatch.setitem(sys.modules, "foxglove", None)  # as if foxglove-sdk were not installed
    arena = load_arena("thesis")
    with pytest.raises(ConfigError, match=r"visionpos\[foxglove\]"):
        FoxgloveServer(FoxgloveConfig(), arena.cameras, "a.yaml")


def test_serve_adds_the_server_only_when_the_section_asks(arena_yaml):
    from visionpos.app.serve import bridge_sinks

    def outputs(y):  # the network outputs sit behind the off-loop dispatcher
        return [o for s in bridge_sinks(parse_arena(y, "a.yaml")) for o in getattr(s, "outputs", [s])]

    y = arena_yaml("thesis")
    assert not any(isinstance(s, FoxgloveServer) for s in outputs(y))
    y["foxglove"] = {"port": 8799}
    (srv,) = [s for s in outputs(y) if isinstance(s, FoxgloveServer)]
    assert srv.cfg.port == 8799 and srv.cfg.host == "127.0.0.1"  # not started: serve starts its sinks
