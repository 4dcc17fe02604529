"""Freshness benchmark (issue 29): how old the newest fused frame is at each output tick, on the live demo.

    visionpos bench --only freshness [--quick]

The thesis arena's demo (4 cameras x 100 Hz, random phases) with everything a user runs on: the console with
one WebSocket client (its own process, as a browser), the pose stream, NatNet, VRPN and Foxglove with a client
each (their own process), and the MAVLink bridge with its fake autopilot. A sink added to the server records,
at every output tick, each tracked body's state: the tick time and the capture time of the newest frame in the
body's last accepted update (BodyState.capture_ns, what the pose stream, NatNet and the MAVLink stamp carry).
Its age, tick - capture, is judged in frame periods of the arena's cameras: p99 <= 1.5 (goal). An age of one
period is a frame that reached the fusion a whole frame late, or a fusion that waited for one.

Where an old one comes from, per tick (the `where` columns): the newest frame the pipeline admitted was old
too (it had not been received or handled: the station, the network or the server's loop), or it was admitted
but not fused yet (the pipeline's rate limit deferred it), or fused but not taken by the filter (gated out).
The simulated stations share the server's loop and process: a loop that stalls (a loaded host) delays their
sending as well, so on a shared host the figures carry its load (run it on a quiet one).

The causes found (issue 29):
- the rate limit (fusion.min_fusion_interval_ms) skips a fusion when another camera's frame is due within the
  interval, so that one fusion takes the whole burst; when that frame was lost or late, the skipped frame
  waited for the next burst, a frame period later. The output tick now fuses it (TimeAligner.take_deferred):
  `freshness_fused_at_tick` counts those;
- the tick's phase: the thesis cameras' frames arrive within 2 ms of each other every period, and a tick just
  before them carried a frame a period older than a tick just after them (the median age of a run was 6 or
  13 ms by the chance of the server's start). The tick's phase now follows the arrivals
  (server/tick_phase.py): `freshness_tick_phase_moves` counts its moves;
- the camera monitor held the loop for 5-13 ms (median 7.5) 4 times a second, one camera's triangulation and
  fit, and took 12-14 % of a core in all, most of it pairing sampled frames (0.4 ms each); its pairing,
  triangulation and fit are compiled now: a fit holds the loop 2.6 ms (median, 5.4 at most), and the monitor
  takes about 3 % of a core (10 s demo runs on the 2-core bench host). On that host the p99 was 1.70-1.87
  periods in 3 runs before and 0.87-1.62 in 4 runs after;
- the largest age of every run, 44-48 ms, was the bench's own: its window, started once the clients were up,
  ran past the stations' last frame. It ends there now;
- all four stations' sends 16-18 ms late at once, every 5.12 s: the demo's summary folded 512 ticks into its
  scores on the loop (about 9 ms of CPU). It folds 64 at a time now (about 3 ms). On the 2-core bench host the
  p99 was then 0.79-0.85 periods in 4 runs (before it, 0.78-1.62 in 7), the largest age 17-18 ms;
- what is left are threads that share the GIL (the bridge's outputs, the demo's fake autopilot) and the host.
"""

from __future__ import annotations

import asyncio
import sys
import time
from typing import Any

import numpy as np

from visionpos.benchmarks import BenchResult
from visionpos.server.sinks import Sink

SETTLE_S = 2.0  # judged from this long after the stations start (registration, clients, filter settling)
DURATION_S_QUICK, DURATION_S_FULL = 8.0, 20.0
CONSOLE_UPDATE_HZ = 31.0  # as the console group: the goal's 30 updates/s
PIPELINE_S_QUICK, PIPELINE_S_FULL = 6.0, 12.0  # the pipeline alone (pipeline_rows)
LATE_PERIODS = 1.0  # a tick whose newest fused frame is this many frame periods old counts as late


class _AgeSink(Sink):
    """Records, per tick: the server clock, each tracked body's capture_ns, and the pipeline's newest admitted
    and newest fused capture times (to tell where an old frame waited)."""

    def __init__(self, server: Any):
        self.server = server
        self.rows: list[tuple[int, int, int, int]] = []  # (tick ns, state capture ns, newest admitted, fused)
        self.recording = False
        self.until_ns: int | None = None  # the stations' last frame: later ticks have no new frame to carry

    @property
    def name(self) -> str:
        return "bench-freshness"

    def publish(self, states: list) -> None:
        if not self.recording or (self.until_ns is not None and states and states[0].time_ns > self.until_ns):
            return
        al = self.server.pipeline.aligner
        newest = al.newest_ns if al.newest_ns is not None else 0
        fused = al.last_fused_ns if al.last_fused_ns is not None else 0
        for s in states:
            if s.tracked:
                self.rows.append((s.time_ns, s.capture_ns, newest, fused))


def _overrides() -> list[str]:
    from visionpos.app.ports import free_ports
    from visionpos.benchmarks.bridge import _output_overrides

    return _output_overrides(*free_ports(4))


def _demo_run(duration_s: float) -> tuple[list[tuple[int, int, int, int]], dict[str, Any]]:
    """One live demo with the console, all outputs and their clients; returns the age sink's rows and the run's
    figures (shed frames, deferred fusions and those the tick did, late ticks, tracked fraction)."""
    from bridge.foxglove_live import FoxgloveServer
    from bridge.natnet import NatNetServer
    from bridge.pose_stream import PoseStream
    from bridge.vrpn import VrpnServer
    from console.settings import ConsoleSettings
    from visionpos.app.demo import demo_arena, run_demo
    from visionpos.app.outputs import network_of

    arena = demo_arena("thesis", duration_s, 1, _overrides())
    views: list = []
    got: dict[str, Any] = {}

    async def during(ctx) -> None:
        server = ctx.server
        sink = _AgeSink(server)
        # judged while every station streams: the clients' start-up shifts the window past the stream's end, where
        # the last ticks carried ever older frames (up to 47 ms: the largest age of every run until this was cut)
        sink.until_ns = min(max(f.recv_ns for f in s.frames) for s in ctx.stations)
        server.sinks.append(sink)
        network = network_of(ctx.outputs)
        pose, natnet, vrpn, fox = (next((o for o in network if isinstance(o, cls)), None)
                                   for cls in (PoseStream, NatNetServer, VrpnServer, FoxgloveServer))
        # the clients in processes of their own, as a browser and other programs would be
        outputs = await asyncio.create_subprocess_exec(
            sys.executable, "-m", "visionpos.benchmarks.bridge",
            str(pose.cfg.destinations[0][1] if pose else 0), str(natnet.command_port if natnet else 0),
            str(vrpn.port if vrpn else 0), str(fox.port if fox else 0), arena.bodies[0].name,
            stdin=asyncio.subprocess.PIPE, stdout=asyncio.subprocess.PIPE)
        browser = await asyncio.create_subprocess_exec(
            sys.executable, "-m", "visionpos.benchmarks.console", f"ws://127.0.0.1:{views[0].port}/ws",
            stdin=asyncio.subprocess.PIPE, stdout=asyncio.subprocess.PIPE)
        try:
            await outputs.stdout.readline()  # "ready"
            await browser.stdout.readline()
            browser.stdin.write(b"connect\n")
            await browser.stdin.drain()
            await browser.stdout.readline()
            await asyncio.sleep(SETTLE_S)
            st0 = server.pipeline.stats()
            shed0, defer0, late0 = server.ingest.counters.frames_shed, st0.get("deferred", 0), server.late_ticks
            at_tick0 = st0.get("fused_at_tick", 0)
            sink.recording = True
            await asyncio.sleep(max(0.5, duration_s - SETTLE_S - 0.5))
            sink.recording = False
            st1 = server.pipeline.stats()
            got["tick_phase_moves"] = server.health()["tick_phase_moves"]
            got.update(shed=server.ingest.counters.frames_shed - shed0, late_ticks=server.late_ticks - late0,
                       deferred=st1.get("deferred", 0) - defer0, fused_at_tick=st1.get("fused_at_tick", 0) - at_tick0)
        finally:
            for proc in (outputs, browser):
                proc.stdin.close()
                await proc.wait()
        got["rows"] = sink.rows

    console = ConsoleSettings(port=0, update_rate_hz=CONSOLE_UPDATE_HZ)
    summary = asyncio.run(run_demo(arena, duration_s, None, during=during, console=console,
                                   on_console=views.append))
    got["tracked_fraction"] = min(b["tracked_fraction"] for b in summary["bodies"])
    got["period_ms"] = 1e3 / max(c.fps for c in arena.cameras)
    return got.pop("rows"), got


def ages(rows: list[tuple[int, int, int, int]], period_ms: float) -> dict[str, float]:
    """The ages (ms) of the newest fused frame at the ticks: p50/p99/max, p99 in frame periods, the share of
    ticks at least LATE_PERIODS old, and of those the share whose newest admitted frame was as old (not
    received or handled in time), admitted but not fused yet, or fused but not in the body's state."""
    a = np.array(rows, dtype=np.int64).reshape(-1, 4)
    age = (a[:, 0] - a[:, 1]) * 1e-6
    admitted = (a[:, 0] - a[:, 2]) * 1e-6
    fused = (a[:, 0] - a[:, 3]) * 1e-6
    late = age >= LATE_PERIODS * period_ms
    n_late = max(int(late.sum()), 1)
    cut = 0.5 * period_ms  # a newer frame than this in a stage means the old state waited in a later stage
    not_in = late & (admitted >= LATE_PERIODS * period_ms - cut)
    not_fused = late & ~not_in & (fused >= LATE_PERIODS * period_ms - cut)
    return {
        "ticks": float(len(age)),
        "age_ms_p50": float(np.percentile(age, 50)),
        "age_ms_p99": float(np.percentile(age, 99)),
        "age_ms_max": float(age.max()),
        "age_p99_periods": float(np.percentile(age, 99) / period_ms),
        "late_fraction": float(late.mean()),
        "late_not_admitted": float(not_in.sum() / n_late),
        "late_not_fused": float(not_fused.sum() / n_late),
        "late_not_taken": float((late & ~not_in & ~not_fused).sum() / n_late),
    }


def pipeline_rows(duration_s: float, seed: int = 1) -> tuple[list[tuple[int, int, int, int]], float]:
    """The pipeline alone, without the live loop: arena8's three-drone flight (8 cameras at 100 and 120 Hz,
    random phases, the simulator's arrival jitter and 0.2 % lost frames) fed in arrival order and ticked at
    100 Hz on the receive clock (benchmarks.fusion_replay.replay). Rows as the live sink's; the frame period (ms)
    of its fastest camera."""
    from visionpos.benchmarks.fusion_replay import replay
    from visionpos.sim import load_scenario, simulate

    sc = load_scenario("arena8", session="flight", duration=duration_s, seed=seed)
    sim = simulate(sc)
    pipes: list = []
    rows: list[tuple[int, int, int, int]] = []
    judged_from_ns = sc.start_ns + int(SETTLE_S * 1e9)

    def tick(t_ns: int, states: list) -> None:
        al = pipes[0].aligner
        if t_ns >= judged_from_ns:
            rows.extend((t_ns, s.capture_ns, al.newest_ns, al.last_fused_ns) for s in states if s.tracked)

    replay(sc.arena, sim.frames, raw_cb=lambda p: pipes[:1] or pipes.append(p), tick_cb=tick)
    return rows, 1e3 / max(c.fps for c in sc.arena.cameras)


def run(quick: bool = False) -> BenchResult:
    res = BenchResult()
    duration_s = DURATION_S_QUICK if quick else DURATION_S_FULL
    _demo_run(4.0)  # compiles, warms the caches; not measured
    t0 = time.perf_counter()
    rows, got = _demo_run(duration_s)
    m = ages(rows, got["period_ms"])
    res.metrics.update({f"freshness_{k}": v for k, v in m.items()})
    res.metrics.update({"freshness_shed_frames": float(got["shed"]), "freshness_deferred_fusions":
                        float(got["deferred"]), "freshness_fused_at_tick": float(got["fused_at_tick"]),
                        "freshness_late_ticks": float(got["late_ticks"]),
                        "freshness_tick_phase_moves": float(got["tick_phase_moves"]),
                        "freshness_tracked_fraction": got["tracked_fraction"]})
    lines = ["| ticks x bodies | age p50 (ms) | p99 (ms) | max (ms) | p99 / frame period | ticks >= 1 period old | "
             "of them: newest admitted as old | admitted, not fused | fused, not in the state |",
             "|---|---|---|---|---|---|---|---|---|",
             f"| {m['ticks']:.0f} | {m['age_ms_p50']:.2f} | {m['age_ms_p99']:.2f} | {m['age_ms_max']:.2f} | "
             f"{m['age_p99_periods']:.2f} | {100 * m['late_fraction']:.2f} % | {100 * m['late_not_admitted']:.0f} % | "
             f"{100 * m['late_not_fused']:.0f} % | {100 * m['late_not_taken']:.0f} % |"]
    res.tables[f"Age of the newest fused frame at each output tick: thesis demo (4 cameras x 100 Hz), console with "
               f"a client and all outputs on, {duration_s:g} s (judged after {SETTLE_S:g} s; shed frames "
               f"{got['shed']}, deferred fusions {got['deferred']} (by the tick {got['fused_at_tick']}), late ticks "
               f"{got['late_ticks']}, tick phase moves {got['tick_phase_moves']}, tracked "
               f"{100 * got['tracked_fraction']:.2f} %)"] = "\n".join(lines)
    prows, period_ms = pipeline_rows(PIPELINE_S_QUICK if quick else PIPELINE_S_FULL)
    pm = ages(prows, period_ms)
    res.metrics.update({f"freshness_pipeline_{k}": v for k, v in pm.items()})
    res.tables["Age of the newest fused frame at each output tick, the pipeline alone (arena8's three-drone flight, "
               "8 cameras at 100/120 Hz, arrival jitter and 0.2 % lost frames, replayed on a 100 Hz tick grid)"] = \
        "\n".join(lines[:2] + [f"| {pm['ticks']:.0f} | {pm['age_ms_p50']:.2f} | {pm['age_ms_p99']:.2f} | "
                               f"{pm['age_ms_max']:.2f} | {pm['age_p99_periods']:.2f} | "
                               f"{100 * pm['late_fraction']:.2f} % | - | - | - |"])
    res.notes.append(f"Freshness: one run of {time.perf_counter() - t0:.0f} s wall; the age is the tick's time less "
                     "the capture time the outputs carry (BodyState.capture_ns).")
    return res
