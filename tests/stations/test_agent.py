"""Station agent against a minimal test server on 127.0.0.1: registration,
clock sync, streaming, server restart, camera failures, sunlight, CLI."""

from __future__ import annotations

import socket
import subprocess
import sys
import threading
import time
from dataclasses import replace as dataclass_replace
from pathlib import Path

import cv2
import numpy as np
import pytest

from stations.agent import StationAgent
from stations.config import SourceConfig, parse_station
from stations.sources import FrameSource, SourceError
from visionpos import protocol as P
from visionpos.messages import FLAG_RESYNC, FLAG_TRUNCATED, BlobFrame
from visionpos.server.netstamps import SO_TIMESTAMPNS
from visionpos.server.netstamps import TIMESPEC as _TIMESPEC
from visionpos.sim.render import render_blobs

KEY = b"test-key-0123456789abcdef"
SERVER_OFFSET_NS = 7_000_000_000  # the test server's clock runs 7 s ahead of the station's
W, H = 160, 120
COOKIE = b"test-cookie-0123"
TRUE = np.array([[40.3, 30.6], [100.7, 80.2], [130.1, 20.9]])


class LoopbackServer:
    """Answers hello/heartbeat/sync like a fusion server would; records frames."""

    def __init__(self, port: int = 0, key: bytes | None = KEY, start_delay_s: float = 0.3,
                 offset_ns: int = SERVER_OFFSET_NS):
        self.offset_ns = offset_ns
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self.sock.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
        self.sock.bind(("127.0.0.1", port))
        self.sock.settimeout(0.02)
        self.port = self.sock.getsockname()[1]
        self.key = key
        self.start_ns = self.clock() + int(start_delay_s * 1e9)
        self.sessions: dict[tuple[int, int], int] = {}
        self.frames: list[BlobFrame] = []
        self.hellos: list[P.Hello] = []
        self.heartbeats: list[P.Heartbeat] = []
        self.syncs = 0
        self.unregistered_frames = 0
        self.errors: list[str] = []
        self._stop = threading.Event()
        self.thread = threading.Thread(target=self._loop, daemon=True)
        self.thread.start()

    def clock(self) -> int:
        return time.monotonic_ns() + self.offset_ns

    def _loop(self) -> None:
        while not self._stop.is_set():
            try:
                data, anc, _, addr = self.sock.recvmsg(2048, socket.CMSG_SPACE(16))
            except (socket.timeout, OSError):
                continue
            recv = self.clock()
            for level, kind, payload in anc:  # kernel receive stamp: t2 not delayed by the GIL
                if level == socket.SOL_SOCKET and kind == SO_TIMESTAMPNS:
                    sec, nsec = _TIMESPEC.unpack_from(payload)
                    recv = sec * 1_000_000_000 + nsec - (time.time_ns() - self.clock())
            try:
                msg = P.decode(data, self.key, recv)
            except P.ProtocolError as e:
                self.errors.append(str(e))
                continue
            out = None
            if isinstance(msg, BlobFrame):
                if self.sessions.get((msg.station_id, msg.camera_id)) == msg.session:
                    self.frames.append(msg)
                else:  # unregistered (we restarted): counted, never answered
                    self.unregistered_frames += 1
            elif isinstance(msg, P.Hello):
                if msg.cookie != COOKIE:  # the protocol's challenge round trip
                    out = P.make_hello_ack(msg, self.start_ns, self.clock(), P.AckStatus.CHALLENGE, cookie=COOKIE)
                else:
                    self.hellos.append(msg)
                    self.sessions[(msg.station_id, msg.camera_id)] = msg.session
                    out = P.make_hello_ack(msg, self.start_ns, self.clock())
            elif isinstance(msg, P.Heartbeat):
                self.heartbeats.append(msg)
                known = self.sessions.get((msg.station_id, msg.camera_id)) == msg.session
                status = P.AckStatus.OK if known else P.AckStatus.UNKNOWN_SESSION
                out = P.make_hello_ack(msg, self.start_ns, self.clock(), status)
            elif isinstance(msg, P.SyncRequest):
                # like the real server (Ingest._control): no clock for a session it does not know; answering
                # one would let the station move to this clock before it re-registers, and its first frame
                # on the new clock (FLAG_RESYNC) would be refused as unregistered
                if self.sessions.get((msg.station_id, msg.camera_id)) == msg.session:
                    self.syncs += 1
                    out = P.make_sync_reply(msg, recv, self.clock())
            if out is not None:
                self.sock.sendto(P.encode(out, self.key), addr)

    def close(self) -> None:
        self._stop.set()
        self.thread.join(2.0)
        self.sock.close()


class FakeCamera(FrameSource):
    """Pre-rendered frames at a steady rate; every 10th is a sunlit one
    (hundreds of blobs). Records the station-clock stamp of every frame."""

    kind = "fake"

    def __init__(self, fps: float = 200.0, fail_first: int = 0):
        super().__init__(SourceConfig(kind="images", width=W, height=H, fps=fps))
        rng = np.random.default_rng(0)
        self.normal = render_blobs(W, H, TRUE, [4.0] * 3, [200.0] * 3, rng)
        xs, ys = np.meshgrid(np.arange(6, W - 6, 8.0), np.arange(6, H - 6, 8.0))
        many = np.stack([xs.ravel(), ys.ravel()], axis=1)
        self.sunlit = render_blobs(W, H, many, [3.0] * len(many), [120.0] * len(many), rng)
        self.stamps: list[int] = []
        self.fail_first = fail_first
        self.opens = 0
        self.name = "fake camera"

    def open(self) -> None:
        self.opens += 1
        if self.opens <= self.fail_first:
            raise SourceError("fake camera unplugged")

    def read(self):
        time.sleep(1.0 / self.fps)
        t = self.clock()
        k = len(self.stamps)
        self.stamps.append(t)
        return (self.sunlit if k % 10 == 9 else self.normal), t


def station_cfg(port: int, **extra):
    data = {
        "station_id": 3,
        "camera_id": 5,
        "server": {"host": "127.0.0.1", "port": port},
        "source": {"kind": "sim"},
        "camera": {"kind": "pinhole", "name": "fake"},
        "detector": {"max_blobs": 20},
        "heartbeat_s": 0.2,
        "link_timeout_s": 1.0,
        "retry_max_s": 0.1,
    }
    if "key_file" not in extra:
        data["insecure"] = True  # a key, where a test wants one, is set on the parsed config
    data.update(extra)
    cfg = parse_station(data, "test.yaml")
    return cfg


def wait_for(cond, timeout=8.0):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if cond():
            return True
        time.sleep(0.02)
    return False


def start_agent(agent: StationAgent) -> threading.Thread:
    th = threading.Thread(target=agent.run, daemon=True)
    th.start()
    return th


def test_station_registers_syncs_streams_and_survives_a_server_restart():
    server = LoopbackServer()
    cfg = station_cfg(server.port)
    cfg = type(cfg)(**{**cfg.__dict__, "key": KEY})
    cam = FakeCamera()
    agent = StationAgent(cfg, source=cam)
    th = start_agent(agent)
    try:
        assert wait_for(lambda: len(server.frames) >= 40), f"no frames; hellos={len(server.hellos)}"
        h = server.hellos[0]
        assert (h.station_id, h.camera_id, h.width, h.height, h.camera_kind) == (3, 5, W, H, "pinhole")
        assert h.timebase == P.Timebase.SERVER and h.session == agent.session
        assert server.syncs >= 4
        frames = list(server.frames)
        # capture times are on the server clock: station stamp + 7 s, to loopback precision
        # (threads share the GIL on a busy machine, so single exchanges can be a few ms off)
        err = []
        for f in frames:
            assert f.station_id == 3 and f.camera_id == 5
            assert f.capture_ns >= server.start_ns  # nothing before the trigger time
            err.append(f.capture_ns - (cam.stamps[f.seq] + SERVER_OFFSET_NS))
        assert np.median(np.abs(err)) < 1_500_000 and np.max(np.abs(err)) < 10_000_000, err
        seqs = [f.seq for f in frames]
        assert seqs == sorted(seqs)
        normal = [f for f in frames if f.seq % 10 != 9]
        sunlit = [f for f in frames if f.seq % 10 == 9]
        assert normal and sunlit
        for f in normal:
            assert f.flags & ~FLAG_RESYNC == 0 and len(f.blobs) == 3  # RESYNC may mark early estimate updates
            d = np.linalg.norm(f.blobs[:, None, :2] - TRUE[None], axis=2).min(axis=1)
            assert d.max() < 0.2
        for f in sunlit:  # capped and flagged, not a flood
            assert f.flags & FLAG_TRUNCATED and len(f.blobs) == 20
        assert wait_for(lambda: len(server.heartbeats) >= 2)
        hb = server.heartbeats[-1]
        assert hb.status & P.HeartbeatStatus.CLOCK_SYNCED and hb.status & P.HeartbeatStatus.CAMERA_OK
        assert abs(hb.clock_offset_ns - SERVER_OFFSET_NS) < 10_000_000
        assert hb.frames_captured > 0 and 0 <= hb.clock_uncertainty_ns < 10_000_000
        assert not server.errors

        # server restart: same port, no memory of the station
        port = server.port
        server.close()
        time.sleep(0.3)
        # the new server process has a new clock (2 s further ahead)
        server = LoopbackServer(port=port, start_delay_s=0.0, offset_ns=SERVER_OFFSET_NS + 2_000_000_000)
        assert wait_for(lambda: len(server.frames) >= 20, timeout=10.0), "no frames after the restart"
        assert server.hellos and server.hellos[0].session == agent.session
        assert agent.stats.registrations >= 2
        assert not server.errors
        frames = list(server.frames)
        err = [f.capture_ns - (cam.stamps[f.seq] + server.offset_ns) for f in frames]
        assert np.median(np.abs(err)) < 1_500_000, err  # stamps follow the new clock after re-sync
        assert frames[0].flags & FLAG_RESYNC  # and the jump is flagged
    finally:
        agent.stop()
        th.join(5.0)
        server.close()
    assert not th.is_alive()


def test_camera_failure_is_retried_with_backoff_not_a_tight_loop(caplog):
    server = LoopbackServer(key=None)
    cam = FakeCamera(fail_first=3)
    agent = StationAgent(station_cfg(server.port, retry_max_s=0.2), source=cam)
    th = start_agent(agent)
    try:
        assert wait_for(lambda: len(server.frames) >= 5)
        assert agent.stats.camera_failures == 3
        assert cam.opens == 4
        assert "fake camera unplugged; retrying in" in caplog.text
        # heartbeats went on while the camera was down
        assert server.heartbeats
    finally:
        agent.stop()
        th.join(5.0)
        server.close()


def test_no_server_never_blocks_capture():
    """Nobody listens: frames are captured at full rate and counted as dropped."""
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    cam = FakeCamera(fps=500)
    agent = StationAgent(station_cfg(port), source=cam)
    t0 = time.monotonic()
    agent.run(max_frames=100)
    assert time.monotonic() - t0 < 5.0
    assert agent.stats.frames_captured == 100 and agent.stats.frames_sent == 0
    assert agent.stats.frames_dropped == 100
    assert not agent.registered


def test_station_process_streams_images_to_a_loopback_server(tmp_path: Path):
    """The real `python -m stations.cli` process with an image-folder source."""
    rng = np.random.default_rng(9)
    folder = tmp_path / "frames"
    folder.mkdir()
    for i in range(5):
        cv2.imwrite(str(folder / f"f{i:03d}.png"), render_blobs(W, H, TRUE + i * 0.5, [4.0] * 3, [200.0] * 3, rng))
    server = LoopbackServer(key=KEY, start_delay_s=0.0)
    (tmp_path / "key").write_bytes(KEY)
    (tmp_path / "station.yaml").write_text(
        f"station_id: 1\ncamera_id: 2\nserver: {{host: 127.0.0.1, port: {server.port}}}\nkey_file: key\n"
        f"source: {{kind: images, path: frames, fps: 50}}\nheartbeat_s: 0.2\n"
    )
    root = Path(__file__).resolve().parents[2]
    proc = subprocess.Popen([sys.executable, "-m", "stations.cli", "--config", str(tmp_path / "station.yaml"),
                             "--frames", "150"], cwd=root, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    try:
        assert wait_for(lambda: len(server.frames) >= 20, timeout=20.0), (
            proc.stdout.read1().decode() if proc.poll() is not None else "no frames"
        )
        f = server.frames[-1]
        assert (f.station_id, f.camera_id) == (1, 2) and len(f.blobs) == 3
        assert proc.wait(timeout=20) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        server.close()


def test_config_errors_name_file_and_key(tmp_path: Path):
    bad = tmp_path / "station.yaml"
    bad.write_text("station_id: 1\ncamera_id: 2\nsource: {kind: webcam}\n")
    root = Path(__file__).resolve().parents[2]
    r = subprocess.run([sys.executable, "-m", "stations.cli", "--config", str(bad)], cwd=root,
                       capture_output=True, text=True, timeout=30)
    assert r.returncode == 2
    assert "station.yaml: source.kind: 'webcam' is not one of" in r.stderr
    with pytest.raises(Exception, match=r"test.yaml: detector.max_blobs: must be <= 88"):
        station_cfg(1, detector={"max_blobs": 200})
    with pytest.raises(Exception, match=r"test.yaml: detector.thresold: unknown key"):
        station_cfg(1, detector={"thresold": 40})
    with pytest.raises(Exception, match=r"test.yaml: key_file: cannot read key file"):
        station_cfg(1, key_file=str(tmp_path / "missing"))


def test_unresolvable_server_name_is_retried_not_fatal(caplog):
    cfg = station_cfg(5600, server={"host": "no-such-host.invalid", "port": 5600})
    agent = StationAgent(cfg, source=FakeCamera(fps=500))
    assert agent.run(max_frames=30) == 0
    assert agent.stats.frames_captured == 30 and agent.stats.frames_sent == 0
    assert agent.stats.send_errors > 0
    assert caplog.text.count("cannot resolve server no-such-host.invalid") == 1


def test_sources_fail_clearly_and_files_play(tmp_path: Path):
    from stations.sources import EndOfStream, ImageFolderSource, OpenCVSource, Picamera2Source, VideoFileSource, to_grey

    with pytest.raises(SourceError, match="cannot open camera '/dev/video99'"):
        OpenCVSource(SourceConfig(kind="opencv", device="/dev/video99")).open()
    try:
        import picamera2  # noqa: F401
    except ImportError:
        with pytest.raises(SourceError, match="Picamera2 is not installed.*apt install python3-picamera2"):
            Picamera2Source(SourceConfig(kind="picamera2")).open()
    with pytest.raises(SourceError, match="holds no images"):
        ImageFolderSource(SourceConfig(kind="images", path=str(tmp_path))).open()
    with pytest.raises(SourceError, match="shape"):
        to_grey(np.zeros((4, 4, 2), np.uint8), "cam")
    assert to_grey(np.full((4, 4), 40000, np.uint16), "cam").max() == 40000 >> 8

    # a short video plays its frames in order, colour converted to grey, then ends
    path = str(tmp_path / "clip.avi")
    vw = cv2.VideoWriter(path, cv2.VideoWriter_fourcc(*"MJPG"), 30.0, (W, H))
    frames = [render_blobs(W, H, TRUE + i, [5.0] * 3, [200.0] * 3, None) for i in range(4)]
    for f in frames:
        vw.write(cv2.cvtColor(f, cv2.COLOR_GRAY2BGR))
    vw.release()
    src = VideoFileSource(SourceConfig(kind="video", path=path, loop=False, realtime=False))
    src.open()
    assert (src.width, src.height) == (W, H)
    for i in range(4):
        img, t = src.read()
        assert img.shape == (H, W) and img.dtype == np.uint8
        assert np.abs(img.astype(int) - frames[i]).mean() < 2.0  # JPEG-compressed copy of frame i
    with pytest.raises(EndOfStream):
        src.read()
    src.close()


def test_agent_and_real_ingest_shrug_off_forged_and_replayed_packets(tmp_path: Path):
    """End to end over loopback (issue 14): a real StationAgent streams to the server's real Ingest
    while an attacker sends forged UNKNOWN_SESSION replies to the station (signed, from another
    address, and unsigned) and frames with a far-ahead seq to the server. The station never drops
    out and the camera is never blinded. (On v1 the first forged ack knocked the station out.)"""
    import asyncio

    from visionpos.config.arena import load_yaml, parse_arena, resolve_config_path
    from visionpos.server.ingest import Ingest

    (tmp_path / "key").write_bytes(KEY)
    data = load_yaml(resolve_config_path("thesis"))
    data["cameras"][0].update(id=5, width=W, height=H, fps=200)
    data["server"] = {"key_file": str(tmp_path / "key"), "status_period_s": 0, "start_delay_s": 0.0}
    arena = parse_arena(data, str(tmp_path / "arena.yaml"))
    loop = asyncio.new_event_loop()
    ing = Ingest(arena)
    loop_thread = threading.Thread(target=loop.run_forever, daemon=True)
    loop_thread.start()
    asyncio.run_coroutine_threadsafe(ing.start("127.0.0.1", 0), loop).result(5)
    cfg = station_cfg(ing.port)
    agent = StationAgent(type(cfg)(**{**cfg.__dict__, "key": KEY}), source=FakeCamera())
    th = start_agent(agent)
    attacker = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        cam = ing.cameras[5]
        assert wait_for(lambda: cam.frames >= 30), ing.health()
        station_addr = ("127.0.0.1", agent.sock.getsockname()[1])
        for echo in range(0, 200, 4):
            forged = P.HelloAck(3, 5, agent.session, 0, 0, P.AckStatus.UNKNOWN_SESSION, 0, echo)
            attacker.sendto(P.encode(forged, KEY), station_addr)  # signed, from the wrong address
            attacker.sendto(P.encode(dataclass_replace(forged, session=0)), station_addr)  # v1-style, unsigned
            seq = cam.last_seq + 1_000_000
            frame = BlobFrame(5, seq, time.monotonic_ns() - 10**12, np.zeros((0, 4), np.float32), 3, 0, 0,
                              agent.session)
            attacker.sendto(P.encode(frame, KEY), ("127.0.0.1", ing.port))  # far-ahead seq, wrong address
            time.sleep(0.002)
        n = cam.frames
        assert wait_for(lambda: cam.frames >= n + 30), ing.health()
        assert agent.stats.registrations == 1 and agent.registered
        assert agent.stats.refused_replies >= 50 and agent.stats.bad_packets >= 50
        h = ing.health()["cameras"][5]
        assert h["wrong_address"] >= 50 and h["replayed"] == 0 and h["online"] and h["state"] == "streaming"
    finally:
        attacker.close()
        agent.stop()
        th.join(5.0)
        loop.call_soon_threadsafe(ing.close)
        loop.call_soon_threadsafe(loop.stop)
        loop_thread.join(5.0)
    assert not th.is_alive()
