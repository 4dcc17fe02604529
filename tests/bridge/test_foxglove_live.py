"""The live Foxglove WebSocket server (foxglove-sdk), seen by a client speaking Foxglove's ws-protocol.

The client is the `websockets` library with the documented protocol on top (subprotocol
foxglove.sdk.v1: the server advertises its channels as JSON, the client subscribes, messages come
as binary frames: opcode 1, subscription id u32, log time u64, payload); the messages are parsed by
Foxglove's official protobuf classes. Skipped with the reason when the extra is not installed.
"""

from __future__ import annotations

import base64
import contextlib
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
from websockets.exceptions import InvalidStatus  # noqa: E402

from bridge import foxglove_live  # noqa: E402
from bridge.foxglove_live import FoxgloveConfig, FoxgloveServer, parse_foxglove  # noqa: E402
from visionpos.config.arena import ConfigError, load_arena, parse_arena  # noqa: E402
from visionpos.foxglove import channels as C  # noqa: E402
from visionpos.messages import BodyState, LoosePoints  # noqa: E402

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


def test_both_subprotocol_names_connect_and_the_answer_names_the_one_offered(server):
    """foxglove.websocket.v1 (the published ws-protocol spec, Foxglove Studio, Lichtblick up to 1.21) and
    foxglove.sdk.v1 (the SDK's): each client gets the name it offered and the same protocol after it."""
    srv, arena = server
    srv.publish([_state(1_000_000_000, True, 0.5)])
    got = {}
    for offer in (["foxglove.websocket.v1"], ["foxglove.sdk.v1"], ["foxglove.websocket.v1", "foxglove.sdk.v1"]):
        with ws_client.connect(f"ws://127.0.0.1:{srv.port}", subprotocols=offer, open_timeout=5) as ws:
            got[offer[-1] if len(offer) == 1 else "both"] = (ws.subprotocol, _recv_json(ws, "serverInfo")["name"])
    with pytest.raises(InvalidStatus):  # no Foxglove name offered: the SDK's own refusal
        ws_client.connect(f"ws://127.0.0.1:{srv.port}", subprotocols=["other.v1"], open_timeout=5)
    assert got["foxglove.websocket.v1"][0] == "foxglove.websocket.v1"
    assert got["foxglove.sdk.v1"][0] == got["both"][0] == "foxglove.sdk.v1"
    assert len({name for _, name in got.values()}) == 1


def test_only_a_legacy_only_offer_is_renamed():
    from bridge.foxglove_live import answer_legacy_subprotocol, offer_sdk_subprotocol

    req = b"GET / HTTP/1.1\r\nHost: x\r\nSec-WebSocket-Protocol: a.v1, foxglove.websocket.v1\r\n\r\n"
    assert offer_sdk_subprotocol(req) == (req.replace(b"foxglove.websocket.v1", b"foxglove.sdk.v1"), True)
    both = b"GET / HTTP/1.1\r\nsec-websocket-protocol: foxglove.websocket.v1\r\nSec-WebSocket-Protocol: " \
           b"foxglove.sdk.v1\r\n\r\n"
    assert offer_sdk_subprotocol(both) == (both, False)
    answer = b"HTTP/1.1 101 Switching Protocols\r\nSec-WebSocket-Protocol: foxglove.sdk.v1\r\n\r\n"
    assert answer_legacy_subprotocol(answer) == answer.replace(b"foxglove.sdk.v1", b"foxglove.websocket.v1")


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
    for key, bad in (("max_clients", 0), ("max_clients", 257), ("handshake_timeout_s", 0.0)):
        y["foxglove"] = {key: bad}
        with pytest.raises(ConfigError, match=key):
            parse_foxglove(parse_arena(y, "a.yaml"))
    y["foxglove"] = {"max_clients": 3, "handshake_timeout_s": 0.5}
    cfg = parse_foxglove(parse_arena(y, "a.yaml"))
    assert (cfg.max_clients, cfg.handshake_timeout_s) == (3, 0.5)
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
    from visionpos.app.outputs import build_outputs

    def outputs(y):  # the network outputs sit behind the off-loop dispatcher
        return [o for s in build_outputs(parse_arena(y, "a.yaml")) for o in getattr(s, "outputs", [s])]

    y = arena_yaml("thesis")
    assert not any(isinstance(s, FoxgloveServer) for s in outputs(y))
    y["foxglove"] = {"port": 8799}
    (srv,) = [s for s in outputs(y) if isinstance(s, FoxgloveServer)]
    assert srv.cfg.port == 8799 and srv.cfg.host == "127.0.0.1"  # not started: serve starts its sinks


# ---------------------------------------------------------------- client limit, stalls (issue 16)

def _started(**cfg) -> FoxgloveServer:
    srv = FoxgloveServer(FoxgloveConfig(port=0, **cfg), load_arena("thesis").cameras)
    srv.start()
    srv.publish([_state(10**9, True, 0.5)])  # creates the channels
    srv.publish_markers(LoosePoints(10**9, np.zeros((1, 3))))
    deadline = time.monotonic() + 5
    while srv.counters["messages"] < 4 and time.monotonic() < deadline:
        time.sleep(0.01)
    return srv


def _connect(port: int, **kw):
    return ws_client.connect(f"ws://127.0.0.1:{port}", subprotocols=[SUBPROTOCOL], open_timeout=5, **kw)


def _subscribe(ws, topic: str, sub_id: int) -> None:
    chans = {c["topic"]: c["id"] for c in _recv_json(ws, "advertise")["channels"]}
    ws.send(json.dumps({"op": "subscribe", "subscriptions": [{"id": sub_id, "channelId": chans[topic]}]}))


def _next_data(ws, timeout_s: float = 5.0) -> tuple[int, int, bytes]:
    """(subscription id, log time, payload) of the next message frame."""
    end = time.monotonic() + timeout_s
    while True:
        m = ws.recv(timeout=max(0.01, end - time.monotonic()))
        if isinstance(m, bytes):
            _, sub, log_time = struct.unpack_from("<BIQ", m)
            return sub, log_time, m[13:]


def test_clients_beyond_max_clients_are_refused_and_the_admitted_served(caplog):
    srv = _started(max_clients=4)
    admitted: list = []
    refused = []
    clients = contextlib.ExitStack()
    try:
        with caplog.at_level("WARNING", logger=foxglove_live.__name__):
            for _ in range(40):
                try:
                    admitted.append(clients.enter_context(_connect(srv.port)))
                except InvalidStatus as e:  # the HTTP answer to the upgrade request
                    refused.append(e.response)
        assert len(admitted) == 4 and len(refused) == 36
        assert {r.status_code for r in refused} == {503}
        assert all(b"client limit (4) reached" in r.body for r in refused)
        assert srv.stats()["dropped"] == {"too many clients": 36} and srv.stats()["clients"] == 4
        assert len([r for r in caplog.records if "too many clients" in r.getMessage()]) == 1  # once per cause

        for i, ws in enumerate(admitted):
            _subscribe(ws, C.TOPIC_BODIES, 100 + i)
        time.sleep(0.2)  # the subscriptions reach the SDK before the first update
        t = 10**9
        for k in range(5):  # every admitted client gets every update (50 ms apart: past the 30 Hz limit)
            t += 50_000_000
            srv.publish([_state(t, True, float(k))])
            for i, ws in enumerate(admitted):
                assert _next_data(ws)[:2] == (100 + i, t)

        admitted.pop().close()  # a slot frees up: the next client is admitted
        deadline = time.monotonic() + 5
        while srv.stats()["clients"] == 4 and time.monotonic() < deadline:
            time.sleep(0.02)
        admitted.append(clients.enter_context(_connect(srv.port)))
        assert srv.stats()["clients"] == 4
        with pytest.raises(InvalidStatus), _connect(srv.port):
            pass
    finally:
        clients.close()
        srv.close()


def test_a_stalled_client_does_not_slow_the_others():
    """A client that subscribes and never reads: the relay holds a bounded amount for it and the
    reading client still gets every update at once."""
    srv = _started(max_clients=4, backlog=16)
    clients = contextlib.ExitStack()
    try:
        stalled = clients.enter_context(_connect(srv.port, max_queue=1, close_timeout=0.5))  # reads 1 frame
        reader = clients.enter_context(_connect(srv.port))
        _subscribe(stalled, C.TOPIC_MARKERS, 1)
        _subscribe(reader, C.TOPIC_MARKERS, 2)
        time.sleep(0.2)
        rng = np.random.default_rng(1)
        pts = rng.uniform(-2, 2, (2000, 3))  # some 200 kB per update: more than the kernel buffers in 30
        t = 10**9
        slowest = 0.0
        k = 0
        # 30 updates, and on until the stalled client's buffer reached its bound or the SDK dropped the client (a
        # loaded host drains the SDK's side more slowly)
        while k < 30 or (k < 200 and srv.stats()["buffered_b_max"] < foxglove_live.RELAY_BUFFER_B
                         and not srv.stats()["dropped"].get("closed by the server")):
            k += 1
            t += 50_000_000
            t0 = time.monotonic()
            srv.publish_markers(LoosePoints(t, pts + k))
            while True:  # the reader sees this update (not an older one) promptly
                sub, log_time, payload = _next_data(reader, timeout_s=2.0)
                if log_time == t:
                    break
            assert sub == 2 and len(payload) > 150_000
            slowest = max(slowest, time.monotonic() - t0)
        st = srv.stats()
        assert slowest < 1.0, f"an update took {slowest:.2f} s to reach the reading client"
        # the stalled client's buffer stayed within its bound (one read past it at most), and reached it unless
        # the SDK dropped the client first (on a loaded host its own queue can overflow before the relay's fills)
        dropped = st["dropped"].get("closed by the server") == 1
        assert st["buffered_b_max"] <= foxglove_live.RELAY_BUFFER_B + 65536
        assert dropped or st["buffered_b_max"] >= foxglove_live.RELAY_BUFFER_B
        assert st["clients"] == 2 or dropped
    finally:
        clients.close()
        srv.close()


def test_a_connection_without_a_handshake_is_closed_and_its_slot_freed():
    import socket

    srv = _started(max_clients=1, handshake_timeout_s=0.3)
    s = socket.create_connection(("127.0.0.1", srv.port), timeout=5)
    try:
        t0 = time.monotonic()
        assert s.recv(100) == b""  # closed by the server, not by the 5 s socket timeout
        assert time.monotonic() - t0 < 3.0
        assert srv.stats()["dropped"] == {"handshake timeout": 1}
        with _connect(srv.port) as ws:  # the one slot is free again
            assert _recv_json(ws, "advertise")["channels"]
    finally:
        s.close()
        srv.close()


# ---------------------------------------------------------------- fed by a running fusion server (issue 16)

def _collect(ws, want: set[str], timeout_s: float) -> dict[str, list[tuple[int, bytes]]]:
    """Subscribe to the topics in `want` as they are advertised; (log time, payload) per topic until each
    topic has a message or the time is up."""
    got: dict[str, list[tuple[int, bytes]]] = {t: [] for t in want}
    subs: dict[int, str] = {}
    end = time.monotonic() + timeout_s
    while time.monotonic() < end and not all(got.values()):
        try:
            m = ws.recv(timeout=0.1)
        except TimeoutError:
            continue
        if isinstance(m, str):
            msg = json.loads(m)
            if msg.get("op") == "advertise":
                new = [c for c in msg["channels"] if c["topic"] in want and c["topic"] not in subs.values()]
                for c in new:
                    subs[1000 + c["id"]] = c["topic"]
                if new:
                    ws.send(json.dumps({"op": "subscribe", "subscriptions": [
                        {"id": 1000 + c["id"], "channelId": c["id"]} for c in new]}))
        else:
            _, sub, log_time = struct.unpack_from("<BIQ", m)
            if sub in subs:
                got[subs[sub]].append((log_time, m[13:]))
    return got


def test_a_running_server_streams_each_cameras_blobs_and_its_health(arena_yaml):
    """The server's accepted packets and health snapshots reach a live client: camera 2's blobs as
    ImageAnnotations at the pixels the station sent, and the health as a Log naming the camera."""
    import asyncio
    import socket
    import threading

    from foxglove_schemas_protobuf.ImageAnnotations_pb2 import ImageAnnotations
    from foxglove_schemas_protobuf.Log_pb2 import Log

    from visionpos import protocol as P
    from visionpos.app.outputs import build_outputs
    from visionpos.app.ports import free_port
    from visionpos.messages import BlobFrame
    from visionpos.server.service import FusionServer
    from visionpos.server.settings import parse_server

    y = arena_yaml("thesis")
    fox_port = free_port(socket.SOCK_STREAM)
    y["foxglove"] = {"port": fox_port}
    y["server"] = {"insecure": True, "status_period_s": 0.2, "start_delay_s": 0.0}
    arena = parse_arena(y, "a.yaml")
    sinks = build_outputs(arena)
    server = FusionServer(arena, parse_server(arena), sinks, host="127.0.0.1", port=0)
    loop = asyncio.new_event_loop()
    started = threading.Event()
    stop: asyncio.Event | None = None

    async def run():
        nonlocal stop
        stop = asyncio.Event()
        await server.start()
        started.set()
        await stop.wait()
        await server.stop()

    th = threading.Thread(target=loop.run_until_complete, args=(run(),), daemon=True)
    th.start()
    assert started.wait(10), "the server did not start"
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.settimeout(2.0)
    addr = ("127.0.0.1", server.port)
    cam = 2
    try:
        def hello(cookie, counter):
            return P.encode(P.Hello(cam, cam, 9, 960, 640, 30.0, "fisheye", "pi", "test", P.Timebase.SERVER,
                                    counter, cookie))

        sock.sendto(hello(P.NO_COOKIE, 1), addr)
        challenge = P.decode(sock.recv(2048))
        sock.sendto(hello(challenge.cookie, 2), addr)
        ack = P.decode(sock.recv(2048))
        assert ack.status == P.AckStatus.OK
        time.sleep(max(0.0, (ack.start_ns - time.monotonic_ns()) * 1e-9) + 0.01)
        blobs = np.array([[101.25, 202.5, 30.0, 200.0], [640.0, 17.75, 12.0, 180.0]])
        stop_frames = threading.Event()

        def frames():  # 30 fps until the client has what it waits for
            seq = 0
            while not stop_frames.is_set():
                seq += 1
                f = BlobFrame(cam, seq, time.monotonic_ns() - 3_000_000, blobs, cam, 0, 0, 9)
                sock.sendto(P.encode_frame(f), addr)
                time.sleep(1 / 30)

        sender = threading.Thread(target=frames, daemon=True)
        sender.start()
        try:
            # the first frames may wait for the fusion kernels' compilation (a cold numba cache: a minute or
            # more) and then be refused as stale; wait until frames are flowing
            deadline = time.monotonic() + 300
            while server.ingest.counters.frames_accepted < 30 and time.monotonic() < deadline:
                time.sleep(0.1)
            with _connect(fox_port) as ws:
                got = _collect(ws, {C.blobs_topic(cam), C.TOPIC_LOG}, timeout_s=20.0)
        finally:
            stop_frames.set()
            sender.join(2)
        fox = [o for s in sinks for o in getattr(s, "outputs", []) if isinstance(o, FoxgloveServer)][0]
        assert got[C.blobs_topic(cam)], ("no blob annotations arrived", fox.stats(), fox.messages_by_topic,
                                         {k: len(v) for k, v in got.items()}, server.ingest.health()["cameras"][cam])
        ann = ImageAnnotations.FromString(got[C.blobs_topic(cam)][-1][1])
        centres = sorted((c.position.x, c.position.y) for c in ann.circles)
        # Foxglove puts the top-left pixel's centre at (0.5, 0.5); visionpos at (0, 0)
        assert centres == [(101.75, 203.0), (640.5, 18.25)]
        logs = [Log.FromString(p) for _, p in got[C.TOPIC_LOG]]
        assert any(lg.name == "visionpos.health" and "camera 2 " in lg.message and "streaming" in lg.message
                   for lg in logs), [lg.message for lg in logs]
        stats = [o.stats() for s in sinks for o in getattr(s, "outputs", []) if isinstance(o, FoxgloveServer)][0]
        assert stats["packets"] > 0 and stats["errors"] == 0
    finally:
        sock.close()
        loop.call_soon_threadsafe(stop.set)
        th.join(10)
