"""The fusion service: asyncio glue, one event loop, one thread (`visionpos serve` runs it).

    stations --UDP--> Ingest.handle --push--> FusionPipeline
                                                 | tick(now) every 1/output_rate_hz
                                                 v
                                   sinks: publish(states)  (bridge, pose stream, recorder)

Sinks are `visionpos.server.sinks.Sink`s: publish(states) at every output tick, publish_markers
when the pipeline triangulated a new set of loose markers, packet taps, health and events, start,
close and stats (sinks.py says when each is called). A sink that raises is logged and keeps being
called. The server knows no concrete output: visionpos.app.outputs builds them from the arena.

Programmatic use (demo, tests):

    server = FusionServer(arena, sinks=[my_sink], port=0)   # listens on settings.bind
    await server.start(); print(server.port)
    ...; server.health(); await server.stop()
"""

from __future__ import annotations

import asyncio
import ipaddress
import logging
import signal
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from visionpos.config.arena import ArenaConfig, apply_overrides, load_yaml, parse_arena, resolve_config_path
from visionpos.messages import BlobFrame, BodyState, LoosePoints
from visionpos.server.ingest import Ingest
from visionpos.server.settings import ServerSettings, parse_server
from visionpos.server.sinks import Sink, start_sink
from visionpos.server.tick_phase import TickPhase

if TYPE_CHECKING:
    from visionpos.camera.model import Camera
    from visionpos.fusion.camera_monitor import CameraMonitor
    from visionpos.fusion.pipeline import FusionPipeline
    from visionpos.recording import RecordingWriter

log = logging.getLogger(__name__)
# the periodic status line: INFO, but `serve` and `record` turn this logger on by default
status_log = logging.getLogger("visionpos.status")

VANISH_CHECK_S = 0.02


def load_config_with_overrides(config: str | Path, overrides: Sequence[str] = ()) -> ArenaConfig:
    """Arena from a path or built-in name, with `key=value` overrides applied before validation."""
    path = resolve_config_path(config)
    data = load_yaml(path)
    if overrides:
        data = apply_overrides(data, list(overrides))
    return parse_arena(data, str(path))


class _RecorderSink(Sink):
    """The recording as a sink: it records every tick's states and loose markers. The server closes the
    recording itself, last (it also records the final health)."""

    def __init__(self, recorder: RecordingWriter):
        self.recorder = recorder

    @property
    def name(self) -> str:
        return "RecordingWriter"

    def publish(self, states: list[BodyState]) -> None:
        self.recorder.publish(states)

    def publish_markers(self, points: LoosePoints) -> None:
        self.recorder.publish_markers(points)

    def stats(self) -> dict[str, Any]:
        return self.recorder.stats()


class FusionServer:
    """Ingest + pipeline + output tick + sinks on the running event loop.

    arena: validated ArenaConfig. settings: ServerSettings (default: the arena's `server:`
    section). sinks: the outputs (visionpos.app.outputs.build_outputs(arena) for the arena's own).
    pipeline: default FusionPipeline(arena).
    recorder: a RecordingWriter; it gets every packet, events and health snapshots, the outputs (as a
    sink), and is closed by stop() (the server owns it from then on).
    host: None = settings.bind. port: None = settings.port; 0 = any free port (see .port after start()).
    """

    def __init__(self, arena: ArenaConfig, settings: ServerSettings | None = None, sinks: Sequence[Sink] = (),
                 host: str | None = None, port: int | None = None, pipeline: FusionPipeline | None = None,
                 recorder: RecordingWriter | None = None, clock: Callable[[], int] = time.monotonic_ns):
        self.arena = arena
        self.settings = settings or parse_server(arena)
        if pipeline is None:
            from visionpos.fusion.pipeline import FusionPipeline

            pipeline = FusionPipeline(arena)
        self.pipeline = pipeline
        self.recorder = recorder
        self.outputs: list[Sink] = list(sinks)  # the outputs; self.sinks adds the recording
        self.sinks: list[Sink] = self.outputs + ([_RecorderSink(recorder)] if recorder is not None else [])
        for s in self.outputs:  # which body is which, where bodies share a layout (the bridge binds them)
            s.use_identity(getattr(pipeline, "identity", None))
            for drain in s.imu_sources() if hasattr(pipeline, "add_imu_source") else ():  # the vehicles' IMU
                pipeline.add_imu_source(drain)
        self._tap_imu(recorder)
        self.host = self.settings.bind if host is None else host
        self._port_req = self.settings.port if port is None else int(port)
        self.clock = clock
        self.monitor: CameraMonitor | None = None  # continuous calibration (fusion/camera_monitor.py)
        from visionpos.fusion import camera_monitor

        monitor_settings = camera_monitor.parse_camera_monitor(arena)
        if monitor_settings.enabled:
            self.monitor = camera_monitor.CameraMonitor(arena, monitor_settings)
        self.period_ns = int(round(1e9 / self.settings.output_rate_hz))
        # the output tick's phase follows the frames' arrivals (server/tick_phase.py)
        self.tick_phase = TickPhase(self.period_ns) if self.settings.tick_phase_lock else None
        feed: FusionPipeline | _Feed = pipeline
        if self.monitor is not None or self.tick_phase is not None:
            feed = _Feed(pipeline, self.monitor, self.tick_phase, clock)
        self._feed = feed
        # the recording gets packets and events from Ingest and the server directly
        taps = [tap for s in self.outputs for tap in s.packet_taps()]
        self.ingest = Ingest(arena, self.settings, feed, recorder, clock=clock, events=self._on_event, taps=taps)
        self.ticks = 0
        self.late_ticks = 0
        self.sink_errors: dict[str, int] = {}
        self.tick_cost_ns_max = 0
        self.states_out = 0
        self._body_tracked: dict[str, int] = {}
        self._body_counts_prev: dict[str, int] = {}
        self._status_prev_ns = 0
        self._tasks: list[asyncio.Task] = []
        self._running = False
        self.last_states: list[BodyState] = []
        self._markers_ns: int | None = None  # time of the last loose-marker set handed to sinks
        self.loose_markers = 0  # markers in that set

    # ---------------------------------------------------------------- lifecycle

    @property
    def port(self) -> int | None:
        return self.ingest.port

    async def start(self) -> None:
        started: list[Sink] = []
        try:
            for s in self.sinks:
                start_sink(s)
                started.append(s)
        except BaseException:  # a port taken: what did start is closed again, nothing is left running
            for s in reversed(started):
                if s in self.outputs:
                    s.close()
            raise
        await self.ingest.start(self.host, self._port_req)
        self._running = True
        self._status_prev_ns = self.clock()
        loop = asyncio.get_running_loop()
        self._tasks = [loop.create_task(self._tick_loop(), name="visionpos-tick")]
        if self.settings.status_period_s > 0:
            self._tasks.append(loop.create_task(self._status_loop(), name="visionpos-status"))
        log.info("fusion server listening on udp %s:%d (%d cameras, %d bodies, %g Hz output%s)", self.host,
                 self.port, len(self.arena.cameras), len(self.arena.bodies), self.settings.output_rate_hz,
                 ", HMAC on" if self.settings.key else "")
        warn_if_insecure(self.settings, self.arena.source)

    async def stop(self) -> None:
        """Stop ingest and ticks, close sinks (the recorder last: it holds everything). Idempotent."""
        if not self._running:
            return
        self._running = False
        self.ingest.close()
        for t in self._tasks:
            t.cancel()
        for t in self._tasks:
            try:
                await t
            except (asyncio.CancelledError, Exception):
                pass
        self._tasks = []
        for s in self.outputs:
            try:
                s.close()
            except Exception:
                log.exception("closing sink %s failed", s.name)
        if self.recorder is not None:
            try:
                self.recorder.write_json("/server/health", self.clock(), self.health())
            except Exception:
                log.exception("could not record final health")
            self.recorder.close()

    def start_recording(self, recorder: RecordingWriter) -> None:
        """Record from now on (the console's record button): every accepted packet, event, health snapshot and
        output goes to recorder, as with a recorder given at construction. ValueError while one records."""
        if self.recorder is not None:
            raise ValueError(f"already recording to {self.recorder.path.name}")
        self.recorder = recorder
        self.sinks = [*self.sinks, _RecorderSink(recorder)]
        self.ingest.recorder = recorder
        self._tap_imu(recorder)

    def _tap_imu(self, recorder: RecordingWriter | None) -> None:
        """The IMU samples the pipeline takes go to recorder (an input: a replay hands them over again)."""
        if hasattr(self.pipeline, "imu_tap"):
            self.pipeline.imu_tap = recorder.write_imu if recorder is not None else None

    def detach_recording(self) -> RecordingWriter:
        """Stop recording: the recorder (with its final health written) no longer gets anything; the caller
        closes it (RecordingWriter.close, which loses nothing handed to it before). ValueError when none records."""
        rec = self.recorder
        if rec is None:
            raise ValueError("not recording")
        self.ingest.recorder = None
        self._tap_imu(None)
        self.sinks = [s for s in self.sinks if not (isinstance(s, _RecorderSink) and s.recorder is rec)]
        self.recorder = None
        try:
            rec.write_json("/server/health", self.clock(), self.health())
        except Exception:
            log.exception("could not record final health")
        return rec

    async def __aenter__(self) -> "FusionServer":
        await self.start()
        return self

    async def __aexit__(self, *exc: Any) -> None:
        await self.stop()

    # ---------------------------------------------------------------- loops

    def tick(self, now_ns: int) -> list[BodyState]:
        """One output tick: pipeline.tick(now_ns) -> every sink's publish. Errors are counted in
        health()['sink_errors'] (under 'pipeline.tick' or the sink's class name), never raised."""
        t0 = time.perf_counter_ns()
        try:
            states = self.pipeline.tick(now_ns)
        except Exception:
            self.sink_errors["pipeline.tick"] = self.sink_errors.get("pipeline.tick", 0) + 1
            if self.sink_errors["pipeline.tick"] in (1, 100, 10_000):
                log.exception("pipeline.tick failed")
            states = []
        self.ticks += 1
        self.states_out += len(states)
        for s in states:
            if s.tracked:
                self._body_tracked[s.name] = self._body_tracked.get(s.name, 0) + 1
        self.last_states = states
        if self.monitor is not None:
            self._monitor_step(states, now_ns)
        for sink in self.sinks:
            self._to_sink(sink.name, sink.publish, states)
        lp = self.pipeline.loose_points
        if lp is not None and lp.time_ns != self._markers_ns:
            self._markers_ns = lp.time_ns
            self.loose_markers = len(lp.points)
            for sink in self.sinks:
                self._to_sink(sink.name + ".publish_markers", sink.publish_markers, lp)
        cost = time.perf_counter_ns() - t0
        if cost > self.tick_cost_ns_max:
            self.tick_cost_ns_max = cost
        return states

    def _monitor_step(self, states: list[BodyState], now_ns: int) -> None:
        """The camera monitor sees the tick's states; about once a second it fits each camera, and a moved
        camera's corrected pose goes into the pipeline (and the recording, as an event)."""
        try:
            self.monitor.observe_states(states)
            for c in self.monitor.step(now_ns):
                self.pipeline.set_camera_pose(c.camera_id, c.camera)
                self._on_event("camera_pose_corrected", {"camera_id": c.camera_id, "rotation_deg": c.rotation_deg,
                                                          "shift_m": c.shift_m, "pose": c.camera.to_dict()["pose"]})
        except Exception:  # the monitor must never stop the outputs
            self.sink_errors["camera_monitor"] = self.sink_errors.get("camera_monitor", 0) + 1
            if self.sink_errors["camera_monitor"] in (1, 100, 10_000):
                log.exception("camera monitor failed")

    def set_cameras(self, cameras: Sequence[Camera]) -> None:
        """Swap every camera's pose at once (a recalibration applied from the console): one call on the loop, so
        between two frames, and no fusion mixes old and new poses; the camera monitor starts again from them.
        ValueError (nothing changed) when the cameras are not the arena's."""
        if sorted(c.id for c in cameras) != sorted(c.id for c in self.arena.cameras):
            raise ValueError(f"set_cameras: camera ids {sorted(c.id for c in cameras)} are not the arena's "
                             f"{sorted(c.id for c in self.arena.cameras)}")
        by_id = {c.id: c for c in cameras}
        for c in cameras:
            self.pipeline.set_camera_pose(c.id, c)
        self.arena = self.arena.with_cameras([by_id[c.id] for c in self.arena.cameras])
        if self.monitor is not None:
            from visionpos.fusion.camera_monitor import CameraMonitor

            events = self.monitor.events
            self.monitor = CameraMonitor(self.arena, self.monitor.settings)
            self.monitor.events = events
            self._feed.monitor = self.monitor

    def _to_sink(self, name: str, method: Any, *args: Any) -> None:
        """method(*args); a failure is counted under `name` and logged at the 1st, 100th, 10000th time."""
        try:
            method(*args)
        except Exception:
            self.sink_errors[name] = self.sink_errors.get(name, 0) + 1
            if self.sink_errors[name] in (1, 100, 10_000):
                log.exception("sink %s failed (%d times)", name, self.sink_errors[name])

    async def _tick_loop(self) -> None:
        period = self.period_ns
        next_t = self.clock() + period
        next_check = 0
        check_ns = int(VANISH_CHECK_S * 1e9)
        while self._running:
            delay = (next_t - self.clock()) * 1e-9
            if delay > 0:
                await asyncio.sleep(delay)
            else:
                await asyncio.sleep(0)  # let ingest in even when ticks run late
            now = self.clock()
            if now >= next_check:
                next_check = now + check_ns
                self.ingest.check_vanished(now)
            self.tick(now)
            next_t += period
            if self.tick_phase is not None:
                next_t += self.tick_phase.shift_ns(now, next_t)
            if now - next_t > 2 * period:  # far behind (loop stalled): skip the missed ticks, never burst, and
                self.late_ticks += 1  # keep the phase
                next_t += ((now - next_t) // period + 1) * period

    async def _status_loop(self) -> None:
        while self._running:
            await asyncio.sleep(self.settings.status_period_s)
            status_log.info("%s", self.status_line())
            if self.recorder is None and not self.outputs:
                continue
            now = self.clock()
            health = self.health()
            if self.recorder is not None:  # health history in the log, for post-mortems
                try:
                    self.recorder.write_json("/server/health", now, health)
                except Exception:
                    log.exception("could not record health")
            for sink in self.outputs:
                self._to_sink(sink.name + ".publish_health", sink.publish_health, now, health)

    def status_line(self) -> str:
        now = self.clock()
        span = (now - self._status_prev_ns) * 1e-9 if self._status_prev_ns else None
        parts = []
        for b in self.arena.bodies:
            n = self._body_tracked.get(b.name, 0)
            rate = (n - self._body_counts_prev.get(b.name, 0)) / span if span else None
            parts.append(f"{b.name}:{'-' if rate is None else f'{rate:.0f}Hz'} tracked")
            self._body_counts_prev[b.name] = n
        self._status_prev_ns = now
        # sinks that report per-vehicle state (the bridge: what each autopilot says about our poses)
        extra = "".join(" | " + line for line in (s.status_line() for s in self.outputs) if line)
        return (insecure_prefix(self.settings) + self.ingest.status_line() + " | bodies: "
                + (" ".join(parts) or "none") + extra)

    # ---------------------------------------------------------------- observability

    def _on_event(self, kind: str, info: dict[str, Any]) -> None:
        event = {"kind": kind, **info}
        now = self.clock()
        if self.recorder is not None:
            self.recorder.write_json("/server/events", now, event)
        for sink in self.outputs:
            self._to_sink(sink.name + ".publish_event", sink.publish_event, now, event)

    def health(self) -> dict[str, Any]:
        h = self.ingest.health()
        h["insecure"] = self.settings.insecure
        h["ticks"] = self.ticks
        h["late_ticks"] = self.late_ticks
        h["tick_phase_moves"] = self.tick_phase.shifts if self.tick_phase is not None else 0
        h["states_out"] = self.states_out
        h["loose_markers"] = self.loose_markers
        h["tick_cost_max_ms"] = self.tick_cost_ns_max * 1e-6
        h["sink_errors"] = dict(self.sink_errors)
        h["bodies_tracked_ticks"] = dict(self._body_tracked)
        if self.monitor is not None:
            h["camera_monitor"] = {"cameras": self.monitor.report(), "events": self.monitor.events[-10:],
                                   "paused": self.monitor.paused}
        try:
            h["pipeline"] = dict(self.pipeline.stats())
        except Exception as e:
            h["pipeline"] = {"error": repr(e)}
        sinks = {}
        for s in self.sinks:
            try:
                st = s.stats()
            except Exception as e:
                st = {"error": repr(e)}
            if st:
                sinks[s.name] = st
        h["sinks"] = sinks
        return h


class _Feed:
    """What Ingest pushes frames into: the pipeline; the tick's phase notes the fused frame's arrival; then the
    camera monitor (which only reads the frame)."""

    def __init__(self, pipeline: FusionPipeline, monitor: CameraMonitor | None, tick_phase: TickPhase | None,
                 clock: Callable[[], int]):
        self.pipeline, self.monitor, self.tick_phase, self.clock = pipeline, monitor, tick_phase, clock

    def push(self, frame: BlobFrame) -> None:
        monitor = self.monitor
        if monitor is None or monitor.admits(frame.camera_id):  # a knocked camera is left out until it agrees
            self.pipeline.push(frame)
            if self.tick_phase is not None:
                self.tick_phase.note(self.clock(), frame.capture_ns)
        if monitor is None:
            return
        try:
            monitor.observe_frame(frame)
        except Exception:  # a monitor bug must not cost the frame its fusion (it is fused above)
            log.debug("camera monitor: frame not observed", exc_info=True)

    def remove_camera(self, camera_id: int) -> None:
        self.pipeline.remove_camera(camera_id)

    def pause_view_updates(self, paused: bool) -> bool:
        return self.pipeline.pause_view_updates(paused)


def insecure_prefix(settings: ServerSettings) -> str:
    """The status line's first words when the server runs without a key."""
    return "INSECURE (no key, packets unauthenticated) | " if settings.insecure else ""


def warn_if_insecure(settings: ServerSettings, source: str) -> None:
    if settings.insecure:
        log.warning("INSECURE: server.insecure is true (%s), so station packets are neither signed nor checked; "
                    "anyone who can reach the port can inject poses. Run `visionpos keygen`, copy the key to "
                    "every station and remove `insecure` (docs/security.md)", source)


def loopback_note(host: str) -> str | None:
    """What `serve` and `record` add when they listen on loopback, where no real station reaches them."""
    try:
        loopback = ipaddress.ip_address(host).is_loopback
    except ValueError:
        return None
    if not loopback:
        return None
    return (f"{host} is loopback: stations on other hosts cannot reach it; set server.bind to this host's "
            "address on the lab network (or pass --host ADDRESS)")


async def run_until_signal(duration_s: float | None = None, status: Callable[[], None] | None = None,
                           status_period_s: float = 0.0) -> None:
    """Wait for SIGINT/SIGTERM (or duration_s); call status() every status_period_s."""
    loop = asyncio.get_running_loop()
    stop = asyncio.Event()
    installed = []
    for sig in (signal.SIGINT, signal.SIGTERM):
        try:
            loop.add_signal_handler(sig, stop.set)
            installed.append(sig)
        except (NotImplementedError, RuntimeError):  # not the main thread / platform
            pass
    try:
        t_end = None if duration_s is None else loop.time() + duration_s
        while not stop.is_set():
            timeout = status_period_s if status_period_s > 0 else None
            if t_end is not None:
                left = t_end - loop.time()
                if left <= 0:
                    break
                timeout = left if timeout is None else min(timeout, left)
            try:
                await asyncio.wait_for(stop.wait(), timeout)
            except asyncio.TimeoutError:
                if t_end is not None and loop.time() >= t_end:
                    break
                if status is not None and status_period_s > 0 and not stop.is_set():
                    status()
    finally:
        for sig in installed:
            loop.remove_signal_handler(sig)


async def record_traffic(arena: ArenaConfig, settings: ServerSettings, out: str | Path, host: str | None = None,
                         duration_s: float | None = None,
                         on_listening: Callable[[int], None] | None = None, pipeline: Any = None,
                         on_ingest: Callable[[Ingest], Any] | None = None) -> int:
    """Record live station traffic to `out` until a signal (or duration_s): no fusion, no outputs.

    Answers registration, clock sync and heartbeats as the server does, so stations stream as
    they would to it, and logs every packet. host: None = settings.bind. on_listening(port) is
    called once the socket is open; an OSError (port in use, bad address) propagates. Returns
    the packets recorded. pipeline: gets every accepted frame (push) without fusing (the console's
    blob view); on_ingest(ingest): awaited once listening, returns an async closer awaited at the end.
    """
    from visionpos.recording import TOPIC_PACKETS, RecordingWriter

    with RecordingWriter(out, arena.to_dict(), {"command": "record"}) as rec:
        ingest = Ingest(arena, settings, pipeline=pipeline, recorder=rec,
                        events=lambda kind, info: rec.write_json("/server/events", time.monotonic_ns(),
                                                                 {"kind": kind, **info}))
        await ingest.start(settings.bind if host is None else host, settings.port)
        warn_if_insecure(settings, arena.source)
        if on_listening is not None:
            on_listening(ingest.port)
        closer = None

        def status() -> None:
            ingest.check_vanished(time.monotonic_ns())
            status_log.info("%s%s | recorded %d packets", insecure_prefix(settings), ingest.status_line(),
                            rec.counts.get(TOPIC_PACKETS, 0))

        try:
            closer = await on_ingest(ingest) if on_ingest is not None else None
            await run_until_signal(duration_s, status=status, status_period_s=settings.status_period_s)
        finally:
            if closer is not None:
                await closer()
            ingest.close()
            rec.write_json("/server/health", time.monotonic_ns(), ingest.health())
        return rec.counts.get(TOPIC_PACKETS, 0)
