"""`visionpos demo`: the whole chain on a simulated arena, over loopback, in real time.

    simulated stations (one asyncio task per camera, own UDP socket, own clock)
        --Hello / SyncRequest / Heartbeat / frames (the real protocol)--> FusionServer
        --> Bridge (MAVLink, one udpin endpoint per vehicle) --> FakeAutopilot per body
        --> every other output section of the arena (pose stream, VRPN, NatNet, Foxglove), as `serve`
            builds them (app/outputs.py): `--set vrpn.port=3883` serves VRPN clients

Every socket is on 127.0.0.1. The simulator renders the scenario's frames up
front (so generating them never stalls the event loop); each station then
registers, synchronises its clock (its clock is offset from the server's by
the scenario's raw station offset, and it converts its stamps with the
estimate, as a real station does), and sends each frame at its simulated
receive time, paced by the wall clock. Live status once a second; a summary
at the end (`--json` for a machine-readable one). Errors are against the
simulator's truth at each output's time.

The demo keeps the scenario's `vehicles` settings (message, rate, signing)
but always puts their endpoints on free loopback ports; without a `vehicles`
section it makes one vehicle per body (sysid = body id). MAVLink is signed, as
on a real set-up: a vehicle without a `signing` key gets a fresh one for the
run, and its fake autopilot signs with it and rejects anything unsigned.
"""

from __future__ import annotations

import asyncio
import atexit
import dataclasses
import logging
import os
import random
import secrets
import shutil
import tempfile
import time
from collections import deque
from typing import TYPE_CHECKING, Any, AsyncIterator, Awaitable, Callable, Protocol, TextIO

import numpy as np

from visionpos import jit
from visionpos import protocol as P
from visionpos.analysis import metrics as M
from visionpos.app.demo_summary import AutopilotPoses, Collector, latency_percentiles_ms
from visionpos.app.outputs import bridge_of, build_outputs
from visionpos.app.ports import free_port
from visionpos.app.serve import startup_heap_frozen
from visionpos.config.arena import ArenaConfig, apply_overrides, load_yaml, parse_arena, resolve_config_path
from visionpos.config.keys import KEY_BYTES
from visionpos.messages import BlobFrame
from visionpos.server.sinks import Sink

if TYPE_CHECKING:
    from bridge import Bridge
    from visionpos.server.service import FusionServer

log = logging.getLogger(__name__)

REGISTER_TIMEOUT_S = 5.0
STILL_BACKGROUND_DN = 8.0  # a simulated still image: dark background of this mean grey level ...
STILL_NOISE_DN = 3.0  # ... with this much noise (sigma), and marker discs ...
STILL_MARKER_DN = 230  # ... of this grey level where the blobs are
STILL_MIN_DIAMETER_PX = 4.0  # a one-pixel blob still shows as a disc
AUTOPILOT_KEEP_MESSAGES = 1024  # each fake autopilot keeps its newest messages only (the summary: AutopilotPoses)
STREAM_LEAD_S = 0.3  # first exposure this long after every station is registered and synced


# ---------------------------------------------------------------- set-up


def demo_arena(scenario: str, duration_s: float, seed: int | None, overrides: list[str]) -> ArenaConfig:
    """The scenario's arena with loopback vehicle endpoints, sim duration and seed applied. `vehicles.*`
    overrides are applied after the demo has made its vehicles (one per body when the file has none), so
    `--set vehicles.0.message=odometry` finds them."""
    path = resolve_config_path(scenario)
    data = load_yaml(path)
    vehicle_sets = [o for o in overrides if o.split("=", 1)[0].strip().startswith("vehicles.")]
    sets = ([o for o in overrides if o not in vehicle_sets] + [f"sim.duration={duration_s}"]
            + ([f"sim.seed={seed}"] if seed is not None else []))
    data = apply_overrides(data, sets)
    arena = parse_arena(data, str(path))
    vehicles = data.get("vehicles") or [{"body": b.name, "sysid": b.id} for b in arena.bodies]
    vehicles = [dict(v) for v in vehicles]
    for v in vehicles:
        v["endpoint"] = f"udpin:127.0.0.1:{free_port()}"
        v.pop("autopilot_address", None)
        if "signing" not in v:  # a key per vehicle: a pose over a crossed link fails the other autopilot's check
            v["signing"] = {"key_file": _demo_mavlink_key_file()}
    data["vehicles"] = vehicles
    return parse_arena(apply_overrides(data, vehicle_sets) if vehicle_sets else data, str(path))


def _demo_mavlink_key_file() -> str:
    """A fresh MAVLink signing key for this run, in a private temporary file removed at exit."""
    folder = tempfile.mkdtemp(prefix="visionpos-demo-")
    atexit.register(shutil.rmtree, folder, True)
    path = os.path.join(folder, "mavlink.key")
    with os.fdopen(os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600), "w") as f:
        f.write(secrets.token_hex(32) + "\n")
    return path


# ---------------------------------------------------------------- simulated station


class _StationProtocol(asyncio.DatagramProtocol):
    def __init__(self, station: "SimStation"):
        self.station = station

    def datagram_received(self, data: bytes, addr: Any) -> None:
        self.station.on_datagram(data, addr)

    def error_received(self, exc: Exception) -> None:
        self.station.send_errors += 1


class SimStation:
    """One camera station speaking the real protocol to the server on loopback.

    frames: this camera's BlobFrames with capture_ns and recv_ns already on the
    server clock (true exposure stamp and simulated network arrival time).
    clock_offset_ns: this station's raw clock minus the server clock. key: the server's HMAC key.
    config_path: the station YAML file (console.stations) whose detector ignore/rois this station applies
    to its blobs and where a MASK_UPDATE is saved; None: in memory only.
    Still images on request: a synthetic IR image of the newest frame (dark noisy background, bright discs
    where its blobs are), at most one per image_min_interval_s.
    """

    def __init__(self, camera, station_id: int, frames: list[BlobFrame], clock_offset_ns: int, server_port: int,
                 session: int, key: bytes | None = None, config_path: str | None = None,
                 image_min_interval_s: float = 1.0):
        from stations.clocksync import ClockSync
        from stations.session import StationLink
        from stations.still import StillLimiter

        self.camera = camera
        self.station_id = station_id
        self.frames = frames
        self.clock_offset_ns = int(clock_offset_ns)
        self.server = ("127.0.0.1", server_port)
        self.key = key
        self.link = StationLink(station_id, camera.id, session)  # registration, counters, reply checks
        self.session = self.link.session
        self.sync = ClockSync(station_id, camera.id, interval_s=1.0, burst=8, burst_interval_s=0.02)
        self.transport: asyncio.DatagramTransport | None = None
        self.ack: P.HelloAck | None = None
        self.acked = asyncio.Event()
        self.sent = 0
        self.send_errors = 0
        self.bad_replies = 0
        self._next_hb = 0  # next heartbeat, server clock (set when streaming starts)
        # the last packets this station sent and the replies it believed, as a sniffer on the
        # network would see them (the robustness benchmark replays them)
        self.sniffed_sent: deque[bytes] = deque(maxlen=64)
        self.sniffed_received: deque[bytes] = deque(maxlen=16)
        self.config_path = config_path
        self.ignore: tuple[tuple[int, int, int, int], ...] = ()
        self.rois: tuple[tuple[int, int, int, int], ...] = ()
        if config_path is not None:
            self._load_rects(config_path)
        self.stills = StillLimiter(image_min_interval_s)
        self._rng = np.random.default_rng(session)
        self.last_blobs: np.ndarray = np.zeros((0, 4), np.float32)  # the newest frame's blobs as sent
        self.last_raw_blobs: np.ndarray = self.last_blobs  # ... and as simulated, before ignore/rois
        self.last_capture_ns = 0
        self.last_still: np.ndarray | None = None  # the newest still image rendered, and its blobs (tests read them)
        self.last_still_blobs: np.ndarray = self.last_blobs
        self.mask_acks: list[Any] = []
        self._still_tasks: set[asyncio.Task] = set()

    def _load_rects(self, path: str) -> None:
        from stations.config import _rects
        from visionpos.config.arena import Section

        det = Section((load_yaml(path) or {}).get("detector") or {}, path, "detector")
        self.ignore, self.rois = _rects(det, "ignore"), _rects(det, "rois")

    def searched(self, blobs: np.ndarray) -> np.ndarray:
        """blobs whose centre the station's detector would search (inside a roi if any, outside every
        ignore rectangle), as a detector with that mask finds them."""
        if not (self.ignore or self.rois) or len(blobs) == 0:
            return blobs
        x, y = blobs[:, 0], blobs[:, 1]

        def inside(rects):
            hit = np.zeros(len(blobs), bool)
            for x0, y0, x1, y1 in rects:
                hit |= (x >= x0) & (x < x1) & (y >= y0) & (y < y1)
            return hit

        keep = ~inside(self.ignore)
        if self.rois:
            keep &= inside(self.rois)
        return blobs[keep]

    def render_still(self, blobs: np.ndarray) -> np.ndarray:
        """A frame with these blobs as a camera would see it: (H, W) uint8, noisy dark background, marker discs
        (the simulator's renderer, visionpos.sim.render)."""
        from visionpos.sim.render import render_blobs

        m = self.camera.model
        b = np.asarray(blobs, dtype=float).reshape(-1, 4)
        diameters_px = np.maximum(2.0 * np.sqrt(np.maximum(b[:, 2], 1.0) / np.pi), STILL_MIN_DIAMETER_PX)
        return render_blobs(m.width, m.height, b[:, :2], diameters_px, STILL_MARKER_DN - STILL_BACKGROUND_DN,
                            self._rng, background=STILL_BACKGROUND_DN, read_noise_dn=STILL_NOISE_DN)

    def _on_image_request(self, req: P.ImageRequest) -> None:
        if not self.stills.allow(time.monotonic_ns()):
            return
        # rendered and encoded off the loop: the demo's server shares it, and fusion must not wait
        task = asyncio.get_running_loop().create_task(self._still(req, self.last_blobs, self.last_capture_ns))
        self._still_tasks.add(task)
        task.add_done_callback(self._still_tasks.discard)

    async def _still(self, req: P.ImageRequest, blobs: np.ndarray, capture_ns: int) -> None:
        from stations.still import background_level, encode_still, image_chunks

        def make():
            img = self.render_still(blobs)
            return img, encode_still(img, req.max_width, req.quality), background_level(img, blobs)

        img, (jpeg, w, h), bg = await asyncio.to_thread(make)
        self.last_still, self.last_still_blobs = img, blobs
        if self.transport is not None:
            for chunk in image_chunks(req, jpeg, capture_ns, w, h, bg):
                self._send(chunk)

    def _on_mask_update(self, msg: P.MaskUpdate) -> None:
        from stations.still import check_rects, save_mask

        m = self.camera.model
        ignore = msg.ignore if msg.flags & P.MaskFlag.IGNORE else self.ignore
        rois = msg.rois if msg.flags & P.MaskFlag.ROIS else self.rois
        why = check_rects(ignore + rois, m.width, m.height)
        status, text = P.MaskStatus.REFUSED, why or ""
        if why is None:
            self.ignore, self.rois = tuple(ignore), tuple(rois)
            values = {k: v for k, v, bit in (("ignore", ignore, P.MaskFlag.IGNORE), ("rois", rois, P.MaskFlag.ROIS))
                      if msg.flags & bit}
            status, text = P.MaskStatus.APPLIED, "applied; this simulated station has no config file"
            if self.config_path is not None:
                try:
                    save_mask(self.config_path, values)
                    status, text = P.MaskStatus.SAVED, f"saved to {os.path.basename(self.config_path)}"
                except (OSError, ValueError) as e:
                    text = f"not saved: {e}"
        ack = P.MaskAck(self.station_id, self.camera.id, self.session, msg.request_id, status, text)
        self.mask_acks.append(ack)
        self._send(ack)

    def station_clock(self) -> int:
        return time.monotonic_ns() + self.clock_offset_ns

    def on_datagram(self, data: bytes, addr: Any) -> None:
        from stations.session import LinkEvent

        t4 = self.station_clock()
        try:
            msg = P.decode(data, self.key)
        except P.ProtocolError:
            self.bad_replies += 1
            return
        if isinstance(msg, (P.ImageRequest, P.MaskUpdate)):
            if not self.link.believe_command(msg, addr, self.server):
                self.bad_replies += 1
            elif isinstance(msg, P.ImageRequest):
                self._on_image_request(msg)
            else:
                self._on_mask_update(msg)
            return
        if not isinstance(msg, (P.SyncReply, P.HelloAck)) or not self.link.believe(msg, addr, self.server):
            self.bad_replies += 1
            return
        self.sniffed_received.append(data)
        if isinstance(msg, P.SyncReply):
            self.sync.reply(msg, t4)
            return
        event = self.link.on_ack(msg)
        if event in (LinkEvent.REGISTERED, LinkEvent.KEPT):
            self.ack = msg
            self.acked.set()
        elif event is LinkEvent.CHALLENGED:
            self._send(self.hello())  # the same HELLO with the server's cookie
        elif event is LinkEvent.LOST:
            self.acked.clear()
            self._send(self.hello())
        elif event is LinkEvent.RESYNC:
            self.sync.reset()
        else:
            self.bad_replies += 1

    @property
    def local_port(self) -> int:
        return self.transport.get_extra_info("sockname")[1]

    def _send(self, msg: Any) -> None:
        try:
            data = P.encode(msg, self.key)
            self.sniffed_sent.append(data)
            self.transport.sendto(data, self.server)
        except OSError:
            self.send_errors += 1

    def hello(self) -> P.Hello:
        m = self.camera.model
        return self.link.hello(m.width, m.height, float(self.camera.fps),
                               m.kind if m.kind in P.CAMERA_KINDS else "unknown", self.camera.name[:32],
                               "visionpos-demo")

    async def open(self) -> None:
        loop = asyncio.get_running_loop()
        # not connected, as a real station's socket: replies from anywhere reach the protocol's own checks
        self.transport, _ = await loop.create_datagram_endpoint(lambda: _StationProtocol(self),
                                                                local_addr=("127.0.0.1", 0))

    async def register_and_sync(self) -> None:
        """Hello until acknowledged, then a burst of clock-sync exchanges."""
        end = time.monotonic() + REGISTER_TIMEOUT_S
        while not self.acked.is_set():
            if time.monotonic() > end:
                raise RuntimeError(f"station {self.station_id}: the server did not acknowledge registration")
            self._send(self.hello())
            try:
                await asyncio.wait_for(self.acked.wait(), 0.2)
            except asyncio.TimeoutError:
                pass
        while self.sync.estimator.estimate is None or self.sync.estimator.estimate.samples < self.sync.burst:
            if time.monotonic() > end:
                raise RuntimeError(f"station {self.station_id}: clock sync got no replies")
            if self.sync.due(self.station_clock()):
                self._send(self.sync_request())
            await asyncio.sleep(0.005)

    def sync_request(self, t1_ns: int | None = None) -> P.SyncRequest:
        req = self.link.sync_request(self.station_clock() if t1_ns is None else t1_ns)
        return self.sync.request(req.t1_ns, req.counter, req.session)

    def heartbeat(self) -> P.Heartbeat:
        est = self.sync.estimator.estimate
        hb = P.HeartbeatStatus
        status = int(hb.CAMERA_OK | hb.STREAMING | (hb.CLOCK_SYNCED if est is not None else 0))
        return self.link.heartbeat(
            status=status, frames_captured=self.sent, frames_dropped=0, send_errors=self.send_errors,
            clock_offset_ns=0 if est is None else est.offset_ns,
            clock_uncertainty_ns=-1 if est is None else int(est.uncertainty_ns),
            drift_ppb=0 if est is None else int(est.drift_ppm * 1e3), station_ns=self.station_clock(),
        )

    async def stream(self, stop_ns: int) -> None:
        """Send every frame at its receive time (server clock), stamped via this station's own clock sync.

        self.frames: a list, or an async iterator of frames made live (run_demo's `live` source)."""
        self._next_hb = time.monotonic_ns()
        if hasattr(self.frames, "__aiter__"):
            async for f in self.frames:
                if f.recv_ns > stop_ns:
                    break
                await self._send_frame(f)
            return
        for f in self.frames:
            if f.recv_ns > stop_ns:
                break
            await self._send_frame(f)

    async def _send_frame(self, f: BlobFrame) -> None:
        wait = (f.recv_ns - time.monotonic_ns()) * 1e-9
        if wait > 0:
            await asyncio.sleep(wait)
        now_local = self.station_clock()
        if self.sync.due(now_local):
            self._send(self.sync_request(now_local))
        if time.monotonic_ns() >= self._next_hb:
            self._send(self.heartbeat())
            self._next_hb += 1_000_000_000
        # the station reads the exposure on its own clock and converts it with its sync estimate
        local = f.capture_ns + self.clock_offset_ns
        est = self.sync.estimator.estimate
        capture = est.to_server(local) if est is not None else f.capture_ns
        blobs = self.searched(f.blobs)
        self.last_raw_blobs, self.last_blobs, self.last_capture_ns = f.blobs, blobs, capture
        try:
            data = P.encode_frame(BlobFrame(f.camera_id, f.seq, capture, blobs, self.station_id, f.flags, 0,
                                            self.session), self.key)
            self.transport.sendto(data, self.server)
            self.sniffed_sent.append(data)
            self.sent += 1
        except OSError:
            self.send_errors += 1

    def close(self) -> None:
        for t in list(self._still_tasks):
            t.cancel()
        if self.transport is not None:
            self._send(self.link.bye())
            self.transport.close()
            self.transport = None


# ---------------------------------------------------------------- the run


class LiveSource(Protocol):
    """An arena driven from outside (run_demo's `live`), e.g. by ArduPilot SITL's true pose."""

    stopped_ns: int | None  # server clock when the streaming was told to stop; None while it runs

    def prepare(self, scenario: Any) -> Any:
        """The scenario to run: the given one with live trajectories in place of the simulated ones."""

    def frames(self, camera_index: int, shift_ns: int) -> AsyncIterator[BlobFrame]:
        """One camera's frames, made as the run goes; capture_ns/recv_ns on the server clock (sim time +
        shift_ns). Ends when the run is told to stop."""


@dataclasses.dataclass
class DemoContext:
    """What a `during` observer of run_demo can see: the live parts of the running demo."""

    arena: ArenaConfig
    server: FusionServer
    stations: list["SimStation"]
    bridge: Bridge
    key: bytes | None
    duration_s: float
    outputs: list[Sink] = dataclasses.field(default_factory=list)  # build_outputs' sinks (the bridge's among them)
    # body -> what its fake autopilot got so far (demo_summary.AutopilotPoses; .n counts the pose messages)
    autopilot_poses: dict[str, Any] = dataclasses.field(default_factory=dict)


@dataclasses.dataclass
class _Run:
    """The parts of one demo run, filled stage by stage (run_demo)."""

    arena: ArenaConfig
    sc: Any  # visionpos.sim.Scenario
    sim: Any  # its simulated frames (None: a live source makes them)
    sim_s: float  # wall time the simulation took
    server: FusionServer
    outputs: list[Sink]
    bridge: Bridge
    collector: Collector
    key: bytes | None
    autopilots: dict[str, tuple[Any, Any]] = dataclasses.field(default_factory=dict)  # body -> (FakeAutopilot, link)
    autopilot_poses: dict[str, AutopilotPoses] = dataclasses.field(default_factory=dict)  # body -> what it got
    stations: list[SimStation] = dataclasses.field(default_factory=list)
    shift: int = 0  # sim time + shift = server clock
    t_start: int = 0  # the streaming window, server clock
    t_stop: int = 0
    streaming: bool = False  # the window is set (so truth can be recorded)
    interpreted_at_start: bool = False  # the kernels were still compiling when the streaming began


async def run_demo(arena: ArenaConfig, duration_s: float, status_out: TextIO | None,
                   record: str | None = None,
                   during: Callable[[DemoContext], Awaitable[None]] | None = None,
                   live: "LiveSource | None" = None, console: Any = None,
                   on_console: Callable[[Any], None] | None = None) -> dict[str, Any]:
    """Run everything for duration_s seconds of streaming; returns the summary dict.

    record: MCAP path; the server records every station packet and output, and the
    simulator's truth (on the server clock) is added, so `visionpos replay` and
    `visionpos tune` work on the demo's session.
    during: awaited alongside the streaming (it starts when the stations do), e.g. the
    robustness benchmark's attacker; the demo waits for both.
    live: an externally driven arena (`visionpos sitl`): it replaces the scenario's trajectories
    and makes each camera's frames while the run goes (nothing is simulated up front); the
    streaming ends when it says so (its `stopped_ns`) or at the scenario's end.
    console: ConsoleSettings of the web console (None: none), on the same loop; on_console(ConsoleServer)
    once it listens.
    Every output section of the arena is served (build_outputs); one that cannot open its address stops
    the start with a SinkStartError naming its keys.
    Stages: _simulate, _start_server (outputs, collector, recording), _start_autopilots, _start_stations,
    _stream, _stop, _summary.
    """
    t_wall0 = time.perf_counter()
    sc, sim, sim_s = _simulate(arena, live)
    run = await _start_server(arena, sc, sim, sim_s, record)
    view = None
    try:
        if console is not None:
            from visionpos.app.console import open_console

            view = await open_console(console, run.server)
            if on_console is not None:
                on_console(view)
        _start_autopilots(run, live)
        await _start_stations(run, console.stations if console is not None else ())
        with startup_heap_frozen():
            await _stream(run, live, during, duration_s, status_out)
        health = run.server.health()
    finally:
        await _stop(run, view)
    return _summary(run, health, time.perf_counter() - t_wall0)


def _simulate(arena: ArenaConfig, live: LiveSource | None) -> tuple[Any, Any, float]:
    """The scenario (a live source's in its place) and its frames rendered up front; the seconds it took."""
    from visionpos.sim import parse_sim, simulate

    t0 = time.perf_counter()
    sc = parse_sim(arena)
    if live is not None:
        sc = live.prepare(sc)
    sim = simulate(sc) if live is None else None
    return sc, sim, time.perf_counter() - t0


async def _start_server(arena: ArenaConfig, sc: Any, sim: Any, sim_s: float, record: str | None) -> _Run:
    """The server listening on a free loopback port, with every output of the arena, the collector and the
    recording (closed again when the start fails)."""
    from visionpos.server.service import FusionServer
    from visionpos.server.settings import parse_server

    # a fresh key in memory, shared by the in-process stations and the server: signed like a real
    # set-up, and no key file needed (unless the arena names one, or says insecure: true)
    settings = dataclasses.replace(parse_server(arena, key=secrets.token_bytes(KEY_BYTES)),
                                   status_period_s=0.0)
    outputs = build_outputs(arena, report_interval_s=0)
    bridge = bridge_of(outputs)
    collector = Collector([b.name for b in arena.bodies])
    recorder = None
    if record is not None:
        from visionpos.recording import RecordingWriter

        recorder = RecordingWriter(record, arena.to_dict(), {"command": "demo", "scenario": arena.source,
                                                       "session": sc.session, "seed": sc.seed})
    server = FusionServer(arena, settings, sinks=[*outputs, collector], host="127.0.0.1", port=0, recorder=recorder)
    try:
        await server.start()
    except BaseException:
        if recorder is not None:
            recorder.close()
        raise
    return _Run(arena, sc, sim, sim_s, server, outputs, bridge, collector, settings.key)


def _start_autopilots(run: _Run, live: LiveSource | None) -> None:
    """A fake autopilot on each vehicle's link (none beside a live source's real one)."""
    from bridge.fake_autopilot import FakeAutopilot

    for v in run.bridge.vehicles:
        if live is not None:  # a real autopilot is on the link: a fake one beside it would answer as it
            run.autopilots[v.cfg.body] = (None, v)
            continue
        got = run.autopilot_poses[v.cfg.body] = AutopilotPoses(boot_stamps=v.cfg.time_base == "boot")
        # the summary's figures are running statistics (got): the autopilot keeps only its newest messages
        ap = FakeAutopilot(f"udpout:127.0.0.1:{v.cfg.endpoint.port}", sysid=v.cfg.sysid,
                           signing_key=v.cfg.signing_key, keep_received=AUTOPILOT_KEEP_MESSAGES, on_pose=got.on_pose)
        run.autopilots[v.cfg.body] = (ap.start(), v)


async def _start_stations(run: _Run, station_files: tuple[str, ...]) -> None:
    """One simulated station per camera, registered and clock-synced."""
    sc = run.sc
    rng = random.Random(sc.seed)
    files = _station_files(station_files)
    by_cam = run.sim.frames_by_camera() if run.sim is not None else {}
    timing = {t.camera_id: t for t in sc.timings}
    for cam in sc.cameras:
        sid = timing[cam.id].station_id
        clock = sc.clocks.get(sid)
        st = SimStation(cam, sid, by_cam.get(cam.id, []), clock.offset_ns if clock is not None else 0,
                        run.server.port, rng.randrange(1, 1 << 32), run.key, files.get(cam.id))
        await st.open()
        run.stations.append(st)
    await asyncio.gather(*(s.register_and_sync() for s in run.stations))


async def _stream(run: _Run, live: LiveSource | None, during: Callable[[DemoContext], Awaitable[None]] | None,
                  duration_s: float, status_out: TextIO | None) -> None:
    """Every station sends its frames at their times (the scenario starts STREAM_LEAD_S from now), with the
    live status and the `during` observer alongside; returns once the last frames' ticks are out."""
    from bridge.fake_autopilot import trajectory_truth

    sc = run.sc
    run.shift = shift = time.monotonic_ns() + int(STREAM_LEAD_S * 1e9) - sc.start_ns
    for s in run.stations:
        s.frames = [dataclasses.replace(f, capture_ns=f.capture_ns + shift, recv_ns=f.recv_ns + shift)
                    for f in sorted(s.frames, key=lambda f: f.recv_ns)]
    if live is not None:
        for i, s in enumerate(run.stations):
            s.frames = live.frames(i, shift)
    run.t_start, run.t_stop, run.streaming = sc.start_ns + shift, sc.end_ns + shift, True
    run.interpreted_at_start = jit.interpreting()
    run.collector.start_window(run.t_start, run.t_stop, lambda name, t: sc.truth_at(name, t - shift))
    for body, (ap, link) in run.autopilots.items():  # the fake autopilots' sensors follow the simulated truth
        if ap is not None and any(sb.name == body for sb in sc.bodies):
            ap.truth = trajectory_truth(sc.body(body).trajectory, sc.start_ns + shift)
            if link.cfg.yaw_offset_deg == 0 and not np.any(link.cfg.pivot_offset):  # world = NED turned about x
                run.autopilot_poses[body].score(run.t_start, run.t_stop,
                                                lambda t, body=body: sc.truth_at(body, t - shift)[0])
    tasks = [asyncio.create_task(s.stream(run.t_stop), name=f"station-{s.station_id}") for s in run.stations]
    status = asyncio.create_task(_status_loop(run, status_out))
    if during is not None:
        tasks.append(asyncio.create_task(during(DemoContext(run.arena, run.server, run.stations, run.bridge,
                                                            run.key, duration_s, run.outputs,
                                                            run.autopilot_poses))))
    await asyncio.gather(*tasks)
    if live is not None and live.stopped_ns is not None:
        run.t_stop = min(run.t_stop, live.stopped_ns)
    await asyncio.sleep(0.05)  # the last frames' ticks and sends
    status.cancel()
    try:
        await status
    except asyncio.CancelledError:
        pass
    run.bridge.flush(0.5)


async def _stop(run: _Run, view: Any) -> None:
    """Stations, the truth into the recording, the console, the server (its outputs and recording), the
    fake autopilots."""
    for s in run.stations:
        s.close()
    if run.server.recorder is not None and run.streaming:
        _record_truth(run.server.recorder, run.sc, run.shift, run.t_stop - run.shift)
    if view is not None:
        await view.stop()
    await run.server.stop()
    for ap, _ in run.autopilots.values():
        if ap is not None:
            ap.close()
    for got in run.autopilot_poses.values():  # closed: their last poses are scored here
        got.flush()


def _station_files(paths: tuple[str, ...]) -> dict[int, str]:
    """Camera id -> the station YAML of console.stations naming it (the simulated station uses its mask)."""
    out = {}
    for path in paths:
        data = load_yaml(path)
        cid = data.get("camera_id") if isinstance(data, dict) else None
        if isinstance(cid, int) and not isinstance(cid, bool):
            out[cid] = path
    return out


def _record_truth(recorder, sc, shift: int, end_ns: int) -> None:
    """The simulator's truth at its truth rate up to end_ns (sim time), on the server clock (as `visionpos sim`
    records it)."""
    step = int(round(1e9 / sc.truth_rate_hz))
    times = np.arange(sc.start_ns, min(end_ns, sc.end_ns) + 1, step, dtype=np.int64)
    for b in sc.bodies:
        pos, quat = sc.truth_at(b.name, times)
        for ti, p, q in zip(times, pos, quat):
            recorder.write_truth(int(ti + shift), b.name, p, q)


async def _status_loop(run: _Run, out: TextIO | None) -> None:
    """Once a second: each camera's accepted frames per second, each body's error against the truth and its
    MAVLink link."""
    if out is None:
        return
    server, bridge, collector, sc, shift = run.server, run.bridge, run.collector, run.sc, run.shift
    t_start = run.t_start
    prev: dict[int, int] = {}
    prev_t = time.monotonic_ns()
    while True:
        await asyncio.sleep(1.0)
        now = time.monotonic_ns()
        h = server.ingest.health(now)
        # frames the server accepted per camera since the last line
        dt = (now - prev_t) * 1e-9
        fps = " ".join(f"{cid}:{(c['frames'] - prev.get(cid, 0)) / dt:.0f}" for cid, c in h["cameras"].items())
        prev = {cid: c["frames"] for cid, c in h["cameras"].items()}
        prev_t = now
        parts = []
        for b in sc.bodies:
            s = collector.last.get(b.name)
            if s is None:
                continue
            if s.tracked:
                tp, tq = sc.truth_at(b.name, np.array([s.time_ns - shift]))
                err = M.position_errors(s.position[None], tp)[0] * 1e3
                rot = np.degrees(M.rotation_errors(np.asarray(s.quaternion)[None], tq))[0]
                state = f"tracked err {err:5.1f} mm {rot:4.1f} deg"
            else:
                state = "LOST"
            try:
                vs = bridge.vehicle(b.name).stats()
                lat = vs["latency_capture_ms_p50"]
                state += (
                    f" | capture->MAVLink p50 {lat:4.1f} ms, {vs['sent']} sent"
                    if np.isfinite(lat)
                    else " | nothing sent yet"
                )
                state += " | " + bridge.vehicle(b.name).status_part(with_name=False)
            except KeyError:
                pass
            parts.append(f"{b.name}: {state}")
        out.write(f"[{(now - t_start) * 1e-9:5.1f} s] fps {fps} | " + " | ".join(parts) + "\n")
        out.flush()


def _summary(run: _Run, health: dict[str, Any], wall: float) -> dict[str, Any]:
    """The run's figures: per body against the truth (the collector's running statistics) and what its
    autopilot got, per station, the server's counters."""
    arena, sc, t_start, t_stop = run.arena, run.sc, run.t_start, run.t_stop
    autopilots, stations = run.autopilots, run.stations
    body_stats = run.collector.finish(t_stop)
    n_ticks = run.collector.ticks
    span = t_stop - t_start
    all_send_lat = []
    bodies = []
    for name in [b.name for b in arena.bodies if any(sb.name == b.name for sb in sc.bodies)]:
        d = {"name": name, **body_stats[name].metrics(n_ticks, span)}
        if name in autopilots:
            ap, link = autopilots[name]
            got = run.autopilot_poses.get(name) if ap is not None else None
            n_poses = got.n if got is not None else 0
            st = link.stats()
            d["mavlink_messages"] = n_poses
            d["mavlink_signed"] = link.cfg.signing_key is not None
            d["mavlink_rejected_signature"] = ap.rejected_signature if ap is not None else None
            d["mavlink_rate_hz"] = n_poses / (span * 1e-9) if span > 0 else 0.0
            d["mavlink_max_gap_ms"] = got.max_gap_ns * 1e-6 if n_poses >= 2 else float("nan")
            send_lat = link.lat_capture.values()
            all_send_lat.append(send_lat)
            d["latency_ms"] = M.percentiles_ms(send_lat, (50, 99))
            if got is not None and got.scored:
                d["mavlink_position_rmse_mm"] = got.position_rmse_mm()
                d["mavlink_position_max_mm"] = got.err_max_mm
            d["bridge"] = {k: st[k] for k in ("sent", "rate_limited", "not_tracked", "dropped_stale", "no_link",
                                                "frozen", "timesync_answered", "held_for_origin", "held_identity")}
            d["autopilot_says"] = {"identity": st["identity"], "ekf": st["ekf"], "delay_ms": st["delay_ms"],
                                   "delay_detail": st["delay_detail"],
                                   "true_delay_ms": ap.true_delay_ms() if ap is not None else None}
        bodies.append(d)
    send = np.concatenate(all_send_lat) if all_send_lat else np.zeros(0)
    cams = health.get("cameras", {})
    stations_out = []
    for s in stations:
        c = cams.get(s.camera.id, {})
        stations_out.append({
            "camera_id": s.camera.id, "name": s.camera.name, "station_id": s.station_id,
            "frames_sent": s.sent, "frames_accepted": c.get("frames"), "fps": (s.sent / (span * 1e-9)) if span else 0.0,
            "clock_offset_true_ms": -s.clock_offset_ns * 1e-6,
            "clock_offset_reported_ms": c.get("clock_offset_ms"),
            "latency_ms": c.get("latency_ms"),
        })
    return _json_safe({
        "scenario": arena.source,
        "session": sc.session,
        "seed": sc.seed,
        "duration_s": span * 1e-9,
        "wall_s": wall,
        "simulate_s": run.sim_s,
        "output_rate_hz": n_ticks / (span * 1e-9) if span > 0 else 0.0,
        "ticks": n_ticks,
        "late_ticks": health.get("late_ticks"),
        "bodies": bodies,
        "latency_ms": M.percentiles_ms(send, (50, 99)),
        "latency_to_autopilot_ms": latency_percentiles_ms(list(run.autopilot_poses.values()), (2, 50, 99)),
        "stations": stations_out,
        "server": {k: health.get(k) for k in ("packets", "frames_accepted", "frames_shed", "malformed", "unknown",
                                              "pipeline_errors", "authenticated", "auth_failed",
                                              "tick_cost_max_ms")},
        "pipeline": {k: v for k, v in (health.get("pipeline") or {}).items() if isinstance(v, (int, float, str))},
        # a first run after installing: the fusion ran interpreted while a background process compiled it
        "kernels": {"interpreted_at_start": run.interpreted_at_start, "interpreted_at_end": jit.interpreting()},
    })


def _json_safe(x: Any) -> Any:
    if isinstance(x, dict):
        return {str(k): _json_safe(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_json_safe(v) for v in x]
    if isinstance(x, (float, np.floating)):
        return round(float(x), 4) if np.isfinite(x) else None
    if isinstance(x, (np.integer,)):
        return int(x)
    if isinstance(x, np.bool_):
        return bool(x)
    return x
