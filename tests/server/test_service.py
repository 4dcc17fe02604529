"""Fusion server over loopback UDP: tracking from simulated stations, a station vanishing,
bad traffic, recording, and the serve/record commands (SIGTERM and SIGKILL).

Every network test uses 127.0.0.1, a port chosen by the OS, and stops by itself.
"""

from __future__ import annotations

import asyncio
import os
import signal
import socket
import subprocess
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import pytest

from visionpos import protocol as P
from visionpos.app.outputs import build_outputs
from visionpos.fusion.layout import PARAM_SV_ENABLED, SV_PARAM_ALWAYS, SV_PARAM_OCCLUSION
from visionpos.messages import BlobFrame
from visionpos.recording import RecordingDamagedWarning, RecordingReader, RecordingWriter
from visionpos.server.service import FusionServer, load_config_with_overrides
from visionpos.server.sinks import Sink

ROOT = Path(__file__).resolve().parents[2]
MS = 1_000_000
# the thesis arena with 30 Hz cameras (light on a shared 2-core machine), 3 s; generous
# vanish/age windows keep the real-time test independent of scheduling hiccups
SIM_SET = ["sim.duration=3.0"] + [f"cameras.{i}.fps=30" for i in range(4)]
SERVER_SET = ["server.vanish_min_s=0.6", "server.max_age_ms=3000", "server.status_period_s=0"]
INSECURE = "server.insecure=true"  # the tests' stations send unsigned packets, and say so


class Collect(Sink):
    """A sink that keeps what the server published (and checks it is called with lists)."""

    def __init__(self):
        self.ticks: list[list] = []

    def publish(self, states):
        assert isinstance(states, list)
        self.ticks.append(states)


class TimedPipeline:
    """The real pipeline, noting how late each frame reaches it (receive stamp - capture time)."""

    def __init__(self, pipe):
        self.pipe = pipe
        self.latency_ns: list[int] = []

    def push(self, frame):
        self.latency_ns.append(frame.recv_ns - frame.capture_ns)
        self.pipe.push(frame)

    def __getattr__(self, name):
        return getattr(self.pipe, name)


def _scenario():
    sim = pytest.importorskip("visionpos.sim")
    return sim.load_scenario("thesis", SIM_SET)


async def _station_sockets(loop, port, cams):
    socks = {}
    for c in cams:
        s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        s.setblocking(False)
        s.connect(("127.0.0.1", port))
        socks[c] = s
    return socks


async def _recv(loop, sock, timeout=2.0):
    return await asyncio.wait_for(loop.sock_recv(sock, 2048), timeout)


def _hello(c, session, cookie=P.NO_COOKIE, counter=1):
    return P.Hello(c, c, session, 960, 640, 30.0, "fisheye", f"pi{c}", "test", P.Timebase.SERVER, counter, cookie)


async def _register(loop, sock, c, session, key=None) -> bytes:
    """HELLO, CHALLENGE, HELLO with the cookie, OK: as a station registers. Returns the accepted HELLO."""
    sock.send(P.encode(_hello(c, session), key))
    challenge = P.decode(await _recv(loop, sock), key)
    assert challenge.status == P.AckStatus.CHALLENGE and challenge.echo == 1
    hello = P.encode(_hello(c, session, challenge.cookie, 2), key)
    sock.send(hello)
    ack = P.decode(await _recv(loop, sock), key)
    assert isinstance(ack, P.HelloAck) and ack.status == P.AckStatus.OK and ack.session == session and ack.echo == 2
    return hello


def _register_blocking(sock, addr, c, session, key=None) -> bytes:
    """As _register, blocking; returns once the trigger time has come (same host, same clock)."""
    sock.settimeout(2.0)
    sock.sendto(P.encode(_hello(c, session), key), addr)
    challenge = P.decode(sock.recv(2048), key)
    hello = P.encode(_hello(c, session, challenge.cookie, 2), key)
    sock.sendto(hello, addr)
    ack = P.decode(sock.recv(2048), key)
    assert ack.status == P.AckStatus.OK
    time.sleep(max(0.0, (ack.start_ns + 10 * MS - time.monotonic_ns()) * 1e-9))  # frames are stamped 3 ms back
    return hello


async def _replay_frames(frames, socks, offset_ns, skip=lambda f: False, key=None):
    """Send sim frames at their receive time (shifted onto this clock), capture times shifted alike."""
    for f in frames:
        if skip(f):
            continue
        target = f.recv_ns + offset_ns
        delay = (target - time.monotonic_ns()) * 1e-9
        if delay > 0:
            await asyncio.sleep(delay)
        g = BlobFrame(f.camera_id, f.seq, f.capture_ns + offset_ns, f.blobs, f.camera_id, f.flags, 0,
                      100 + f.camera_id)
        socks[f.camera_id].send(P.encode_frame(g, key))


def test_tracking_continues_after_station_vanishes():
    pytest.importorskip("visionpos.fusion.pipeline")
    sc = _scenario()
    sim = pytest.importorskip("visionpos.sim")
    res = sim.simulate(sc)
    frames = res.frames_by_recv()
    # the vehicle output goes to a local UDP socket: the bridge is plugged in as the config asks
    autopilot = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    autopilot.bind(("127.0.0.1", 0))
    autopilot.settimeout(0.01)
    vehicles = [f"vehicles=[{{body: quad, endpoint: 'udpout:127.0.0.1:{autopilot.getsockname()[1]}'}}]"]
    arena = load_config_with_overrides("thesis", SIM_SET + SERVER_SET + vehicles + [INSECURE])
    cut_ns = sc.start_ns + 1_500 * MS  # camera 2 goes silent half-way through
    from visionpos.fusion.pipeline import FusionPipeline

    pipe = TimedPipeline(FusionPipeline(arena, arena.raw.get("fusion")))

    async def main():
        loop = asyncio.get_running_loop()
        sink = Collect()
        server = FusionServer(arena, sinks=[sink, *build_outputs(arena)], port=0, pipeline=pipe)
        await server.start()
        try:
            socks = await _station_sockets(loop, server.port, [1, 2, 3, 4])
            for c, s in socks.items():  # register like a station does
                await _register(loop, s, c, 100 + c)
            offset = time.monotonic_ns() + 100 * MS - sc.start_ns
            await _replay_frames(frames, socks, offset, skip=lambda f: f.camera_id == 2 and f.capture_ns >= cut_ns)
            await asyncio.sleep(0.05)
            health = server.health()
            for s in socks.values():
                s.close()
            return sink, health, offset
        finally:
            await server.stop()

    sink, health, offset = asyncio.run(main())
    late = np.mean(np.array(pipe.latency_ns) > 100 * MS)
    if late > 0.1:  # a real-time test cannot judge tracking when the server could not run in real time
        pytest.skip(f"{late:.0%} of frames reached fusion > 100 ms after capture: machine too loaded")
    mav = []
    try:
        while True:
            mav.append(autopilot.recv(2048))
    except (socket.timeout, BlockingIOError):
        pass
    autopilot.close()
    # MAVLink 2 pose messages (VISION_POSITION_ESTIMATE 102 or ODOMETRY 331) reached the "autopilot"
    assert mav and all(m[0] == 0xFD for m in mav)
    assert any(int.from_bytes(m[7:10], "little") in (102, 331) for m in mav)
    cams = health["cameras"]
    assert cams[2]["vanished"] >= 1 and not cams[2]["online"]
    assert health["pipeline"]["removed_camera"] >= 1
    assert health["malformed"] == 0 and health["unknown"] == 0 and health["sink_errors"] == {}
    assert "Bridge" in health["sinks"]
    assert all(cams[c]["frames"] > 0 for c in (1, 3, 4))
    # outputs after camera 2 went away: judged against simulator truth at the time each claims
    after = [s for tick in sink.ticks for s in tick if s.time_ns - offset > cut_ns + 700 * MS]
    assert len(after) > 20
    tracked = [s for s in after if s.tracked]
    assert len(tracked) > 0.5 * len(after)  # not 100%: a starved loop may let predictions expire
    assert all(s.n_cameras <= 3 for s in tracked)
    t_sim = np.array([s.time_ns - offset for s in tracked], dtype=np.int64)
    pos_true, _ = sc.truth_at("quad", t_sim)
    err = np.linalg.norm(np.array([s.position for s in tracked]) - pos_true, axis=1)
    assert np.median(err) < 0.01, f"median error {np.median(err) * 1e3:.1f} mm with 3 cameras"
    # untracked outputs never carry a (frozen) pose
    assert all(np.isnan(s.position).all() for s in after if not s.tracked)


def test_bad_traffic_over_udp(tmp_path):
    """Garbage, truncated packets, wrong key, unknown camera, replayed seqs: counted, dropped, server fine."""
    key, wrong = b"k" * 32, b"w" * 32
    (tmp_path / "key").write_bytes(key)
    data = __import__("visionpos.config.arena", fromlist=["x"]).load_yaml(ROOT / "visionpos/configs/thesis_arena.yaml")
    data["server"] = {"key_file": str(tmp_path / "key"), "status_period_s": 0, "max_age_ms": 3000}
    arena = __import__("visionpos.config.arena", fromlist=["x"]).parse_arena(data, str(tmp_path / "arena.yaml"))
    rec_path = tmp_path / "bad.mcap"

    async def main():
        loop = asyncio.get_running_loop()
        rec = RecordingWriter(rec_path, arena.raw)
        sink = Collect()
        server = FusionServer(arena, sinks=[sink], port=0, recorder=rec)
        await server.start()
        sent = []
        try:
            (s,) = (await _station_sockets(loop, server.port, [1])).values()

            def send(b):
                sent.append(b)
                s.send(b)

            rng = np.random.default_rng(0)
            good = P.encode(_hello(1, 5), key)
            for n in (0, 1, 15, 16, 40):
                send(good[:n])  # truncated
            for _ in range(30):
                send(rng.integers(0, 256, rng.integers(1, 1400)).astype(np.uint8).tobytes())  # garbage
            send(P.encode(_hello(1, 5), wrong))  # wrong key
            send(P.encode(_hello(1, 5)))  # unsigned
            send(P.encode(P.Hello(7, 42, 5, 960, 640, 100.0), key))  # unknown camera
            ack = P.decode(await _recv(loop, s), key)
            assert ack.camera_id == 42 and ack.status == P.AckStatus.REJECTED
            sent.append(await _register(loop, s, 1, 5, key))
            now = time.monotonic_ns()
            frames = {}
            for seq in (10, 11, 12, 11, 10, 12, 13):  # duplicates / reordering
                frames[seq] = P.encode_frame(BlobFrame(1, seq, now - 5 * MS + seq * MS, np.zeros((0, 4), np.float32),
                                                       1, 0, 0, 5), key)
                send(frames[seq])
            sync = P.encode(P.SyncRequest(1, 1, 777, 3, 5), key)
            send(sync)
            rep = P.decode(await _recv(loop, s), key)
            assert isinstance(rep, P.SyncReply) and rep.t1_ns == 777 and rep.echo == 3 and rep.session == 5
            assert now <= rep.t2_ns <= rep.t3_ns <= time.monotonic_ns()
            await asyncio.sleep(0.05)
            s.close()
            return server.health(), sent, [sent[-9]] + [frames[q] for q in (10, 11, 12, 13)] + [sync]
        finally:
            await server.stop()

    health, sent, accepted = asyncio.run(main())
    assert health["auth_failed"] == 2
    assert health["unknown"] == 1 and health["unknown_sources"] == {"7/42": 1}
    assert health["malformed"] >= 35 - 1  # a random buffer is almost surely not a valid signed packet
    cam = health["cameras"][1]
    assert cam["frames"] == 4 and cam["duplicates"] + cam["reordered"] == 3
    assert health["packets"] == len(sent) + 1  # + the challenged HELLO
    # the recording holds only what was accepted, in order (not junk, not refused), and the final health
    r = RecordingReader(rec_path)
    assert [d for _, d in r.packets()] == accepted
    nr = list(r.json("/server/health"))[-1][1]["not_recorded"]
    assert nr["unauthenticated"] == 2 and nr["unknown camera"] == 1 and nr["no valid cookie"] == 1
    assert nr["duplicate seq"] + nr["reordered"] == 3 and nr["undecodable"] == health["malformed"]


def test_sink_errors_do_not_stop_outputs():
    pytest.importorskip("visionpos.fusion.pipeline")
    arena = load_config_with_overrides("thesis", ["server.status_period_s=0", "server.output_rate_hz=200", INSECURE])

    class Broken(Sink):
        def publish(self, states):
            raise RuntimeError("sink bug")

    async def main():
        good = Collect()
        server = FusionServer(arena, sinks=[Broken(), good], port=0)
        async with server:
            while len(good.ticks) < 20:
                await asyncio.sleep(0.01)
        return server.health(), good

    health, good = asyncio.run(main())
    assert health["sink_errors"]["Broken"] >= 20
    # one state per configured body per tick, untracked (no stations)
    assert all(len(t) == 1 and t[0].name == "quad" and not t[0].tracked for t in good.ticks)


def _serve(args, tmp_path):
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    return subprocess.Popen([sys.executable, "-m", "visionpos", *args], cwd=tmp_path, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _port_from(proc) -> int:
    line = proc.stdout.readline()
    assert "listening on udp" in line, line + proc.stderr.read()
    return int(line.split("listening on udp ")[1].split(",")[0].split(";")[0].rsplit(":", 1)[1])


def _assert_recorded(r, sent):
    """The recording holds what was accepted: the HELLO that carried the cookie, then every frame."""
    assert [d for _, d in r.packets()] == sent


def _send_frames(port, n, sleep_s=0.0):
    """Register camera 1 and send n frames; returns what the server accepts (and records)."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        sent = [_register_blocking(s, ("127.0.0.1", port), 1, 9)]
        for i in range(n):
            f = BlobFrame(1, i, time.monotonic_ns() - 3 * MS, np.full((2, 4), i, np.float32), 1, 0, 0, 9)
            b = P.encode_frame(f)
            s.sendto(b, ("127.0.0.1", port))
            sent.append(b)
            if sleep_s:
                time.sleep(sleep_s)
    return sent


@pytest.mark.parametrize("command", ["serve", "record"])
def test_command_sigterm_flushes_recording(command, tmp_path):
    pytest.importorskip("visionpos.fusion.pipeline")
    out = tmp_path / "run.mcap"
    args = (["serve", "--config", "thesis", "--record", str(out)] if command == "serve"
            else ["record", "--out", str(out), "--config", "thesis"])
    # a generous age window: a frame that queued while the server warmed up is still accepted (and recorded)
    proc = _serve(args + ["--host", "127.0.0.1", "--port", "0", "--set", "server.status_period_s=0",
                          "--set", "server.max_age_ms=60000", "--set", INSECURE], tmp_path)
    try:
        port = _port_from(proc)
        sent = _send_frames(port, 200)
        time.sleep(0.3)
        proc.send_signal(signal.SIGTERM)
        stdout, stderr = proc.communicate(timeout=20)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0, stderr
    r = RecordingReader(out)
    assert r.complete
    assert r.config["cameras"][0]["name"] == "pi1"
    _assert_recorded(r, sent)
    if command == "serve":
        states = list(r.states())
        assert len(states) > 5 and {s.name for s in states} == {"quad"}
    else:
        assert list(r.states()) == []


def test_serve_killed_leaves_readable_recording(tmp_path):
    pytest.importorskip("visionpos.fusion.pipeline")
    out = tmp_path / "killed.mcap"
    proc = _serve(["serve", "--config", "thesis", "--record", str(out), "--host", "127.0.0.1", "--port", "0",
                   "--set", "server.status_period_s=0", "--set", "server.max_age_ms=60000", "--set", INSECURE],
                  tmp_path)
    try:
        port = _port_from(proc)
        sent = _send_frames(port, 300, sleep_s=0.001)
        time.sleep(1.0)  # the recorder flushes every 0.25 s
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=10)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RecordingDamagedWarning)
        r = RecordingReader(out)
        assert not r.complete
        _assert_recorded(r, sent)
        assert len(list(r.states())) > 0


def test_serve_bad_config_names_the_key(tmp_path):
    proc = _serve(["serve", "--config", "thesis", "--port", "0", "--set", "server.output_rate_hz=fast"], tmp_path)
    _, stderr = proc.communicate(timeout=30)
    assert proc.returncode == 2
    assert "server.output_rate_hz" in stderr and "expected a number" in stderr and "thesis_arena.yaml" in stderr
    bad = tmp_path / "bad.yaml"
    bad.write_text("cameras: []\nbodies: []\nserver: {port: 5600, keyfile: k}\n")
    proc = _serve(["serve", "--config", str(bad), "--port", "0"], tmp_path)
    _, stderr = proc.communicate(timeout=30)
    assert proc.returncode == 2 and "server.keyfile" in stderr and "unknown key" in stderr


def test_server_stall_is_not_a_vanished_station():
    """Frames queued in the socket while the loop was blocked count as arrived, not as silence."""
    import threading

    from visionpos.server.ingest import Ingest

    arena = load_config_with_overrides("thesis", ["server.vanish_min_s=0.2", "server.vanish_periods=2", INSECURE])
    pushed = []

    class Frames:  # what ingest hands on (no fusion involved)
        def push(self, f):
            pushed.append(f.camera_id)

        def remove_camera(self, cid):
            pushed.append(-cid)

    async def main():
        ing = Ingest(arena, pipeline=Frames())
        await ing.start("127.0.0.1", 0)
        stop_all, stop_cam1 = threading.Event(), threading.Event()

        def station():
            with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
                for cam in (1, 2):
                    _register_blocking(s, ("127.0.0.1", ing.port), cam, 50 + cam)
                seq = 0
                while not stop_all.is_set():
                    for cam in (1, 2):
                        if cam == 1 and stop_cam1.is_set():
                            continue
                        f = BlobFrame(cam, seq, time.monotonic_ns() - 2 * MS, np.zeros((1, 4), np.float32), cam, 0,
                                      0, 50 + cam)
                        s.sendto(P.encode_frame(f), ("127.0.0.1", ing.port))
                    seq += 1
                    time.sleep(0.01)

        th = threading.Thread(target=station, daemon=True)
        th.start()
        try:
            await asyncio.sleep(0.3)
            time.sleep(0.6)  # the loop stalls (a slow step) while stations keep sending
            stalled = ing.check_vanished(time.monotonic_ns())
            await asyncio.sleep(0.1)  # drain the backlog
            after_drain = ing.check_vanished(time.monotonic_ns())
            stop_cam1.set()
            gone = []
            for _ in range(100):  # bounded: 2 s at most
                await asyncio.sleep(0.02)
                gone += ing.check_vanished(time.monotonic_ns())
                if gone:
                    break
            return stalled, after_drain, gone, ing.health()
        finally:
            stop_all.set()
            th.join(5)
            ing.close()

    stalled, after_drain, gone, health = asyncio.run(main())
    assert stalled == [] and after_drain == []
    assert gone == [1] and -1 in pushed and -2 not in pushed
    assert health["cameras"][2]["online"] and health["cameras"][2]["vanished"] == 0


def test_port_in_use_is_a_message(tmp_path):
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
        proc = _serve(["serve", "--config", "thesis", "--host", "127.0.0.1", "--port", str(port), "--set", INSECURE],
                      tmp_path)
        _, stderr = proc.communicate(timeout=30)
    assert proc.returncode == 2 and f"127.0.0.1:{port}" in stderr and "--port" in stderr
    assert "Traceback" not in stderr


def test_loose_markers_reach_sinks_and_the_recording(tmp_path):
    """Markers of no body (the calibration wand, not in `bodies`) are triangulated and handed to
    every sink with publish_markers once per new set, and recorded on /fusion/markers."""
    from scipy.spatial.transform import Rotation

    from visionpos.fusion.pipeline import FusionPipeline
    from visionpos.sim import load_scenario, simulate

    sc = load_scenario("thesis", ["sim.duration=1.0", "sim.spurious.random_per_frame=0", INSECURE], session="wand")
    sim = simulate(sc)

    class Markers(Sink):
        def __init__(self):
            self.sets = []

        def publish(self, states):
            pass

        def publish_markers(self, lp):
            self.sets.append(lp)

    sink = Markers()
    pipe = FusionPipeline(sc.arena)
    rec = RecordingWriter(str(tmp_path / "m.mcap"), sc.arena.raw)
    server = FusionServer(sc.arena, sinks=[sink], port=0, pipeline=pipe, recorder=rec)
    frames = sorted(sim.frames, key=lambda f: f.recv_ns)
    for k, f in enumerate(frames):
        pipe.push(f)
        if k % 4 == 3:
            server.tick(f.recv_ns)
    rec.close()
    assert len(sink.sets) >= 10 and len({lp.time_ns for lp in sink.sets}) == len(sink.sets)  # each set once
    # the wand's three markers, against the simulator's truth at the set's time
    wand = np.asarray(next(x for x in sc.arena.raw["sim"]["props"] if x["name"] == "wand")["markers"])
    hits = 0
    for lp in sink.sets[2:]:
        p, q = sc.truth_at("wand", [lp.time_ns])
        truth = Rotation.from_quat(q[0]).apply(wand) + p[0]
        if len(lp.points):
            d = np.linalg.norm(lp.points[:, None] - truth[None], axis=-1).min(axis=0)
            hits += int((d < 0.005).sum())
    assert hits >= 2.5 * len(sink.sets[2:])
    assert server.health()["loose_markers"] == len(sink.sets[-1].points)
    recorded = list(RecordingReader(str(tmp_path / "m.mcap")).json("/fusion/markers"))
    assert len(recorded) == len(sink.sets) and len(recorded[-1][1]["points"]) == len(sink.sets[-1].points)


def test_backlogged_frames_are_shed_over_a_real_socket():
    """Frames that queued in the kernel while the loop was blocked (kernel arrival stamps) are
    counted and not fused; frames that arrive once it keeps up are fused."""
    arena = load_config_with_overrides("thesis", ["server.status_period_s=0", "server.shed_backlog_ms=30", INSECURE])

    class Frames:
        def __init__(self):
            self.seqs = []
            self.pauses = []

        def push(self, frame):
            self.seqs.append(frame.seq)

        def remove_camera(self, camera_id):
            pass

        def pause_view_updates(self, paused):
            self.pauses.append((len(self.seqs), paused))
            return paused

        def tick(self, now_ns):
            return []

        def stats(self):
            return {}

        loose_points = None

    pipe = Frames()

    async def main():
        server = FusionServer(arena, port=0, pipeline=pipe)
        async with server:
            await asyncio.sleep(0.05)  # captures after the trigger time
            with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
                await asyncio.to_thread(_register_blocking, s, ("127.0.0.1", server.port), 1, 4)

                def send(seq):
                    f = BlobFrame(1, seq, time.monotonic_ns() - 3 * MS, np.full((2, 4), 1.0, np.float32), 1, 0, 0, 4)
                    s.sendto(P.encode_frame(f), ("127.0.0.1", server.port))

                for seq in range(1, 21):
                    send(seq)
                time.sleep(0.1)  # the loop is stuck: these 20 wait in the kernel's queue
                await asyncio.sleep(0.05)
                for seq in range(21, 26):
                    send(seq)
                    await asyncio.sleep(0.01)
            await asyncio.sleep(0.05)
            return server.health()

    health = asyncio.run(main())
    if not health.get("frames_shed") and sys.platform != "linux":
        pytest.skip("no kernel receive stamps on this platform")
    assert health["frames_accepted"] == 25
    assert health["frames_shed"] == 20 and pipe.seqs == list(range(21, 26))
    assert pipe.pauses[0] == (0, True) and health["pipeline_errors"] == 0  # the backlog paused the view updates


def test_oversize_datagrams_over_udp_are_refused_whole(tmp_path):
    """64 KB and 1473-byte datagrams on the live socket are counted as oversize and change nothing; a
    frame right after them is handled normally (the receive buffer is one preallocated bytearray)."""
    from visionpos.server.ingest import Ingest

    arena = load_config_with_overrides("thesis", [INSECURE])

    async def main():
        ing = Ingest(arena)
        await ing.start("127.0.0.1", 0)
        try:
            with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
                for size in (65000, P.MAX_PACKET_BYTES + 1, 9000):
                    s.sendto(P.MAGIC + bytes(size - 4), ("127.0.0.1", ing.port))
                s.sendto(P.encode(P.Hello(1, 1, 77, 960, 640, 100.0, counter=1)), ("127.0.0.1", ing.port))
                for _ in range(100):  # bounded: 1 s at most
                    await asyncio.sleep(0.01)
                    if ing.counters.packets >= 4:
                        break
        finally:
            ing.close()
        return ing

    ing = asyncio.run(main())
    assert ing.counters.packets == 4
    assert ing.counters.malformed == 3
    assert ing.counters.malformed_reasons.get("oversize packet") == 3, ing.counters.malformed_reasons
    assert ing.counters.challenges == 1  # the HELLO after them was read whole and answered


def test_the_servers_feed_passes_the_load_relief_to_its_pipeline():
    """What Ingest pushes into in a server with a camera monitor (its feed around the FusionPipeline) pauses the
    pipeline's view updates (a feed without the method failed every pause in a live SITL fleet flight)."""
    arena = load_config_with_overrides("thesis", ["server.status_period_s=0", INSECURE])
    server = FusionServer(arena, port=0)
    feed = server.ingest.pipeline
    assert feed.pause_view_updates(True) is True
    assert server.pipeline._kernel_params[PARAM_SV_ENABLED] == SV_PARAM_OCCLUSION
    assert feed.pause_view_updates(False) is False
    assert server.pipeline._kernel_params[PARAM_SV_ENABLED] == SV_PARAM_ALWAYS
