"""`visionpos bench --only scale`: what fusion costs as bodies and cameras grow, and whether one core keeps up.

1. The matrix: 1, 5, 10, 20 and 50 bodies sharing one 4-marker layout (the fleet's), hovering on small
   figure-eights on a 0.6 m grid, seen by 4, 8 and 16 cameras at 120 Hz on a ring around them (arenas
   made here, `ring_arena`). Each run is simulated, then fed to a FusionPipeline in arrival order with
   ticks at 100 Hz (as the server does); once every body is tracked (or after WARM_S), the CPU time of
   each packet's protocol decode + push and of each tick is measured (time.thread_time: one core).
   Output rate: tracked poses per second per body.
2. Real time: the fleet20 scenario (12 cameras at 120 Hz, 20 identical quads taking off, crossing,
   landing) through a one-core server model (`one_core`): packets arrive at their receive times, the
   core decodes and fuses them one at a time and ticks at 100 Hz; a packet that waited longer than the
   server's `shed_backlog_ms` (15 ms) before its turn is shed, as the server sheds it. Each packet's
   cost is its measured CPU time, so the model runs as fast as this machine's core does.
3. Where the time goes: a profile of the pipeline on that scenario (functions by own time).
"""

from __future__ import annotations

import cProfile
import pstats
import time

import numpy as np

from visionpos.benchmarks import BenchResult
from visionpos.config.arena import parse_arena
from visionpos.fusion.pipeline import FusionPipeline
from visionpos.protocol import decode, encode_frame
from visionpos.sim import load_scenario, parse_sim, simulate

LAYOUT = [[0.086, 0.073, 0.030], [-0.051, 0.104, 0.008], [-0.079, -0.089, 0.003], [0.026, -0.091, 0.054]]
PINHOLE = {"model": "pinhole", "width": 1280, "height": 800, "fx": 712.4, "fy": 712.1, "cx": 641.3, "cy": 401.2,
           "dist": [-0.262, 0.071, 0.0004, -0.0003, -0.0081]}
GRID_M = 0.6  # body spacing
RING_RADIUS_M, RING_HEIGHT_M = 4.5, 3.0
FPS = 120.0
TICK_NS = 10_000_000  # the server's default output rate, 100 Hz
WARM_S = 1.5  # the measured part starts once every body is tracked, at the latest this long after the first frame
SHED_BACKLOG_NS = 15_000_000  # server.shed_backlog_ms's default
BODIES = (1, 5, 10, 20, 50)
CAMERAS = (4, 8, 16)


def ring_arena(n_cameras: int, n_bodies: int, duration_s: float, seed: int = 1) -> dict:
    """An arena (the YAML's mapping) of n_cameras at FPS on a ring around n_bodies that share LAYOUT, each on a
    0.3 m x 0.2 m figure-eight about its point of a GRID_M grid at 1.0-1.4 m."""
    cams = []
    for i in range(n_cameras):
        a = 2 * np.pi * (i + 0.5) / n_cameras
        pos = [float(RING_RADIUS_M * np.cos(a)), float(RING_RADIUS_M * np.sin(a)), RING_HEIGHT_M]
        cams.append({"id": i + 1, "name": f"ring{i + 1}", **PINHOLE, "fps": FPS,
                     "pose": {"position": pos, "look_at": [0.0, 0.0, 1.0]}})
    cols = int(np.ceil(np.sqrt(n_bodies)))
    rows = int(np.ceil(n_bodies / cols))
    bodies, session = [], {}
    for b in range(n_bodies):
        c, r = b % cols, b // cols
        centre = [(c - (cols - 1) / 2) * GRID_M, (r - (rows - 1) / 2) * GRID_M, 1.0 + 0.4 * ((b * 7) % 5) / 4]
        bodies.append({"name": f"quad{b + 1}", "id": b + 1, "marker_diameter": 0.019, "markers": LAYOUT})
        session[f"quad{b + 1}"] = {"trajectory": "figure8", "center": centre, "size": [0.3, 0.2],
                                   "period": 4.0 + 0.1 * (b % 7)}
    return {"cameras": cams, "bodies": bodies,
            "sim": {"duration": duration_s, "seed": seed, "centroid_noise_px": 0.15, "latency_ms": {"mean": 3.0},
                    "sessions": {"hover": session}}}


def _packets(frames) -> list[tuple[int, bytes]]:
    """(receive ns, datagram) in arrival order."""
    fr = sorted(frames, key=lambda f: (f.recv_ns, f.camera_id))
    return [(int(f.recv_ns), encode_frame(f)) for f in fr]


def measure(arena_data: dict) -> dict[str, float]:
    """One matrix cell: per-packet and per-tick CPU (us), output rate (poses/s per body), load (core s per s)."""
    arena = parse_arena(arena_data, "<scale bench>")
    sim = simulate(parse_sim(arena))
    packets = _packets(sim.frames)
    pipe = FusionPipeline(arena)
    n_bodies = len(arena.bodies)
    next_tick = (packets[0][0] // TICK_NS + 1) * TICK_NS
    warm_end = packets[0][0] + int(WARM_S * 1e9)
    start = None
    push_ns, tick_ns, poses, ticks = [], [], 0, 0
    acquire_cpu = time.thread_time_ns()
    for recv, data in packets:
        while recv > next_tick:
            t0 = time.thread_time_ns()
            states = pipe.tick(next_tick)
            dt = time.thread_time_ns() - t0
            if start is not None:
                tick_ns.append(dt)
                poses += sum(s.tracked for s in states)
                ticks += 1
            next_tick += TICK_NS
        if start is None and (all(t.tracked for t in pipe.tracks) or recv >= warm_end):
            start = recv
            acquire_cpu = time.thread_time_ns() - acquire_cpu
        t0 = time.thread_time_ns()
        pipe.push(decode(data, recv_ns=recv))
        if start is not None:
            push_ns.append(time.thread_time_ns() - t0)
    span_s = (packets[-1][0] - start) * 1e-9
    push = np.array(push_ns) * 1e-3
    return {
        "us_per_packet": float(push.mean()),
        "us_per_packet_p99": float(np.percentile(push, 99)),
        "us_per_tick": float(np.mean(tick_ns) * 1e-3),
        "output_hz": poses / max(ticks, 1) / n_bodies * 1e9 / TICK_NS,
        "load": (push.sum() * 1e-6 + np.sum(tick_ns) * 1e-9) / span_s,
        "packets_per_s": len(push) / span_s,
        "acquire_s": (start - packets[0][0]) * 1e-9,
        "acquire_cpu_s": acquire_cpu * 1e-9,
        "tracked": sum(t.tracked for t in pipe.tracks),
        "fusions_per_s": pipe.stats()["fusions"] / ((packets[-1][0] - packets[0][0]) * 1e-9),
    }


def one_core(arena, packets: list[tuple[int, bytes]], shed_ns: int = SHED_BACKLOG_NS) -> dict[str, float]:
    """The one-core server model (module docstring) over packets (receive ns, datagram): shed fraction, busy
    fraction, queueing delay p50/p99/max (ms), output ticks/s."""
    pipe = FusionPipeline(arena)
    free_at = packets[0][0]  # when the core is free (ns, the packets' clock)
    next_tick = (packets[0][0] // TICK_NS + 1) * TICK_NS
    busy = 0
    shed = 0
    waits = []
    ticks = 0
    for recv, data in packets:
        while next_tick <= max(recv, free_at):  # a due tick runs before the next packet
            begin = max(next_tick, free_at)
            t0 = time.thread_time_ns()
            pipe.tick(next_tick)
            dt = time.thread_time_ns() - t0
            free_at, busy, ticks = begin + dt, busy + dt, ticks + 1
            next_tick += TICK_NS
        begin = max(recv, free_at)
        waits.append(begin - recv)
        if begin - recv > shed_ns:
            shed += 1  # counted and recorded, not fused: no fusion cost
            continue
        t0 = time.thread_time_ns()
        pipe.push(decode(data, recv_ns=recv))
        dt = time.thread_time_ns() - t0
        free_at, busy = begin + dt, busy + dt
    span = max(packets[-1][0], free_at) - packets[0][0]  # until the core is done with the last
    w = np.array(waits) * 1e-6
    return {"shed_fraction": shed / len(packets), "busy_fraction": busy / span,
            "wait_p50_ms": float(np.percentile(w, 50)), "wait_p99_ms": float(np.percentile(w, 99)),
            "wait_max_ms": float(w.max()), "ticks_per_s": ticks / (span * 1e-9), "packets": len(packets),
            "tracked": sum(t.tracked for t in pipe.tracks), "bodies": len(pipe.tracks)}


def profile(arena, packets: list[tuple[int, bytes]], top: int = 8) -> list[tuple[str, float, int]]:
    """(function, share of the pipeline's own time, calls) of the top functions by own time, every packet pushed."""
    pipe = FusionPipeline(arena)
    prof = cProfile.Profile()
    prof.enable()
    for recv, data in packets:
        pipe.push(decode(data, recv_ns=recv))
    prof.disable()
    st = pstats.Stats(prof)
    total = sum(v[2] for v in st.stats.values())
    rows = sorted(st.stats.items(), key=lambda kv: -kv[1][2])[:top]
    return [(f"{fn.rsplit('/', 2)[-1] if '/' in fn else fn}:{line} {name}", tt / total, nc)
            for (fn, line, name), (_, nc, tt, _, _) in rows]


def _growth(x: list[int], y: list[float]) -> float:
    """Log-log slope of y over x from the second point on (1 body or 4 cameras carry fixed costs)."""
    return float(np.polyfit(np.log(x[1:]), np.log(y[1:]), 1)[0])


def run(quick: bool = False, bodies: tuple[int, ...] = BODIES, cameras: tuple[int, ...] = CAMERAS,
        realtime: bool = True) -> BenchResult:
    res = BenchResult()
    dur = WARM_S + (1.5 if quick else 4.0)
    cells = {(c, b): measure(ring_arena(c, b, dur)) for c in cameras for b in bodies}
    tbl = ["| cameras | bodies | packets/s | us per packet (mean) | p99 | us per tick | fusions/s | core load "
           "(CPU s per s) | poses/s per body | tracked | acquiring all (s) |",
           "|---|---|---|---|---|---|---|---|---|---|---|"]
    for (c, b), m in cells.items():
        tag = f"c{c}_b{b}"
        res.metrics[f"scale_us_per_packet_{tag}"] = round(float(m["us_per_packet"]), 1)
        res.metrics[f"scale_load_{tag}"] = round(float(m["load"]), 3)
        res.metrics[f"scale_output_hz_{tag}"] = round(float(m["output_hz"]), 1)
        tbl.append(f"| {c} | {b} | {m['packets_per_s']:.0f} | {m['us_per_packet']:.0f} | {m['us_per_packet_p99']:.0f} "
                   f"| {m['us_per_tick']:.0f} | {m['fusions_per_s']:.0f} | {m['load']:.2f} | {m['output_hz']:.1f} "
                   f"| {m['tracked']}/{b} | {m['acquire_s']:.2f} |")
    growth = []
    if len(bodies) > 2:
        for c in cameras:
            g = _growth(list(bodies), [cells[(c, b)]["us_per_packet"] for b in bodies])
            res.metrics[f"scale_growth_bodies_c{c}"] = round(g, 2)
            growth.append(f"per packet ~ bodies^{g:.2f} at {c} cameras")
    if len(cameras) > 2:
        for b in bodies:
            g = _growth(list(cameras), [cells[(c, b)]["load"] for c in cameras])
            res.metrics[f"scale_load_growth_cameras_b{b}"] = round(g, 2)
            growth.append(f"load ~ cameras^{g:.2f} with {b} bodies")
    res.tables["Scale: fusion cost by cameras (120 Hz, ring) and bodies (one shared layout), one core"] = "\n".join(
        tbl + ["", "Growth (log-log slope from 5 bodies / 8 cameras up): " + "; ".join(growth) + "."])
    if realtime:
        _realtime(quick, res)
    return res


def _realtime(quick: bool, res: BenchResult) -> None:
    """fleet20 (12 cameras x 120 Hz, 20 bodies) through the one-core model, and its profile."""
    sc = load_scenario("fleet20", ["sim.duration=12"] if quick else [])
    packets = _packets(simulate(sc).frames)
    m = one_core(sc.arena, packets)
    for k in ("shed_fraction", "busy_fraction", "wait_p99_ms", "ticks_per_s"):
        res.metrics[f"scale_realtime_{k}"] = round(float(m[k]), 4)
    res.tables["Scale: one server core, fleet20 (12 cameras x 120 Hz, 20 bodies), real time"] = "\n".join([
        "| packets | shed | core busy | queueing p50 / p99 / max (ms) | output ticks/s | tracked at the end |",
        "|---|---|---|---|---|---|",
        f"| {m['packets']} | {m['shed_fraction'] * 100:.2f} % | {m['busy_fraction'] * 100:.1f} % | "
        f"{m['wait_p50_ms']:.2f} / {m['wait_p99_ms']:.2f} / {m['wait_max_ms']:.1f} | {m['ticks_per_s']:.1f} | "
        f"{m['tracked']}/{m['bodies']} |",
        "",
        f"{sc.duration_s:g} s of the fleet flight; each packet's cost is its measured CPU time on this machine "
        "(decode + push), ticks at 100 Hz; shed: waited longer than 15 ms (server.shed_backlog_ms).",
    ])
    prof = profile(sc.arena, packets[: len(packets) // 2])
    res.tables["Scale: where fleet20's fusion time goes (own time, cProfile, first half of the flight)"] = "\n".join(
        ["| function | share | calls |", "|---|---|---|"]
        + [f"| `{name}` | {share * 100:.1f} % | {calls} |" for name, share, calls in prof])
