"""`visionpos bench --only scale`: what fusion costs as bodies and cameras grow, and whether one core keeps up.

1. The matrix: 1, 5, 10, 20 and 50 bodies sharing one 4-marker layout (the fleet's), hovering on small
   figure-eights on a 0.6 m grid, seen by 4, 8 and 16 cameras at 120 Hz on a ring around them (arenas
   made here, `ring_arena`). Each run is simulated, then fed to a FusionPipeline in arrival order with
   ticks at 100 Hz (as the server does); stations send up to one datagram's worth of blobs a frame (88: the
   protocol's limit; 50 bodies are 200 markers, so their frames are cut, FLAG_TRUNCATED, and some bodies
   are never acquired); once every body is tracked (or after WARM_S), the CPU time of
   each packet's protocol decode + push and of each tick is measured (time.thread_time: one core).
   Output rate: tracked poses per second per body.
2. Real time: the fleet20 scenario (12 cameras at 120 Hz, 20 identical quads taking off, crossing,
   landing) through a one-core server model (`one_core`): packets arrive at their receive times, the
   core decodes and fuses them one at a time and ticks at 100 Hz; a packet that waited longer than the
   server's `shed_backlog_ms` (15 ms) before its turn is shed, as the server sheds it. Each packet's
   cost is its measured CPU time, so the model runs as fast as this machine's core does.
3. Where the time goes: a profile of the pipeline on that scenario (functions by own time).
4. The fleet of 10 identical quads (`fleet_identity`): tracked fraction, RMSE against its bound and swaps
   against the simulator's truth, with identity by continuity (fusion/identity.py).
"""

from __future__ import annotations

import cProfile
import pstats
import time

import numpy as np

from visionpos.benchmarks import BenchResult
from visionpos.config.arena import parse_arena
from visionpos.fusion.pipeline import FusionPipeline
from visionpos.protocol import MAX_BLOBS_PER_PACKET, decode, encode_frame
from visionpos.server.load import ViewUpdatePause
from visionpos.server.settings import SERVER
from visionpos.sim import load_scenario, parse_sim, simulate

LAYOUT = [[0.086, 0.073, 0.030], [-0.051, 0.104, 0.008], [-0.079, -0.089, 0.003], [0.026, -0.091, 0.054]]
PINHOLE = {"model": "pinhole", "width": 1280, "height": 800, "fx": 712.4, "fy": 712.1, "cx": 641.3, "cy": 401.2,
           "dist": [-0.262, 0.071, 0.0004, -0.0003, -0.0081]}
GRID_M = 0.6  # body spacing
RING_RADIUS_M, RING_HEIGHT_M = 4.5, 3.0
FPS = 120.0
TICK_NS = 10_000_000  # the server's default output rate, 100 Hz
WARM_S = 1.5  # the measured part starts once every body is tracked, at the latest this long after the first frame
SHED_BACKLOG_NS = int(SERVER["shed_backlog_ms"].field_default * 1e6)
PAUSE_VIEWS_NS = int(SERVER["pause_views_backlog_ms"].field_default * 1e6)  # the load relief (server/load.py)
STARTUP_NS = 1_000_000_000  # the first acquisition of a whole fleet (about 40 ms of work, in steps) and first calls
BODIES = (1, 5, 10, 20, 50)
# the real-time model's fusion settings: the defaults, then the two knobs of the per-body work per packet
REALTIME_VARIANTS = (("defaults", None, PAUSE_VIEWS_NS),
                     ("defaults without the load relief (server.pause_views_backlog_ms: 0)", None, 0),
                     ("single_view.mode: occlusion (no per-frame view updates of triangulated bodies)",
                      {"single_view": {"mode": "occlusion"}}, PAUSE_VIEWS_NS),
                     ("min_fusion_interval_ms: 4 (half the fusions), no load relief", {"min_fusion_interval_ms": 4.0},
                      0))
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
                    "max_blobs": MAX_BLOBS_PER_PACKET,
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


def one_core(arena, packets: list[tuple[int, bytes]], shed_ns: int = SHED_BACKLOG_NS,
             settings: dict | None = None, pause_views_ns: int = PAUSE_VIEWS_NS) -> dict[str, float]:
    """The one-core server model (module docstring) over packets (receive ns, datagram), the fusion with
    `settings` (FusionPipeline's) and the server's load relief at pause_views_ns (server/load.py, as the
    server applies it; 0: none): shed fraction, busy fraction, queueing delay p50/p99/max (ms), output ticks/s,
    the fraction of packets fused with the view updates paused, the longest single push or tick (ms)."""
    pipe = FusionPipeline(arena, settings)
    pause = ViewUpdatePause(pause_views_ns)
    paused = 0
    free_at = packets[0][0]  # when the core is free (ns, the packets' clock)
    next_tick = (packets[0][0] // TICK_NS + 1) * TICK_NS
    busy = 0
    shed = 0
    waits = []
    ticks = 0
    all_tracked_ns = None  # when every body was first tracked
    shed_first = 0  # packets shed in the first STARTUP_NS (the first acquisition and its backlog)
    longest_ns = 0  # the longest single push or tick
    for recv, data in packets:
        if all_tracked_ns is None and all(t.tracked for t in pipe.tracks):
            all_tracked_ns = recv
        while next_tick <= max(recv, free_at):  # a due tick runs before the next packet
            begin = max(next_tick, free_at)
            t0 = time.thread_time_ns()
            pipe.tick(next_tick)
            dt = time.thread_time_ns() - t0
            free_at, busy, ticks, longest_ns = begin + dt, busy + dt, ticks + 1, max(longest_ns, dt)
            next_tick += TICK_NS
        begin = max(recv, free_at)
        waits.append(begin - recv)
        if begin - recv > shed_ns:
            shed += 1  # counted and recorded, not fused: no fusion cost
            shed_first += recv - packets[0][0] < STARTUP_NS
            continue
        changed = pause.update(begin - recv)
        if changed is not None:
            pipe.pause_view_updates(changed)
        paused += pause.paused
        t0 = time.thread_time_ns()
        pipe.push(decode(data, recv_ns=recv))
        dt = time.thread_time_ns() - t0
        free_at, busy, longest_ns = begin + dt, busy + dt, max(longest_ns, dt)
    span = max(packets[-1][0], free_at) - packets[0][0]  # until the core is done with the last
    w = np.array(waits) * 1e-6
    return {"shed_fraction": shed / len(packets), "busy_fraction": busy / span,
            "wait_p50_ms": float(np.percentile(w, 50)), "wait_p99_ms": float(np.percentile(w, 99)),
            "wait_max_ms": float(w.max()), "ticks_per_s": ticks / (span * 1e-9), "packets": len(packets),
            "tracked": sum(t.tracked for t in pipe.tracks), "bodies": len(pipe.tracks),
            "all_tracked_s": (all_tracked_ns - packets[0][0]) * 1e-9 if all_tracked_ns is not None else float("nan"),
            "shed_first_s": shed_first, "shed_after_first_s": (shed - shed_first) / len(packets),
            "paused_fraction": paused / len(packets), "longest_step_ms": longest_ns * 1e-6}


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
    for c in cameras:  # over the cells in which every body was tracked (a lost body costs no fusion)
        bs = [b for b in bodies if cells[(c, b)]["tracked"] == b]
        if len(bs) > 2:
            g = _growth(bs, [cells[(c, b)]["us_per_packet"] for b in bs])
            res.metrics[f"scale_growth_bodies_c{c}"] = round(g, 2)
            growth.append(f"per packet ~ bodies^{g:.2f} at {c} cameras ({bs[1]}-{bs[-1]} bodies)")
    for b in bodies:
        cs = [c for c in cameras if cells[(c, b)]["tracked"] == b]
        if len(cs) > 2:
            g = _growth(cs, [cells[(c, b)]["load"] for c in cs])
            res.metrics[f"scale_load_growth_cameras_b{b}"] = round(g, 2)
            growth.append(f"load ~ cameras^{g:.2f} with {b} bodies")
    res.tables["Scale: fusion cost by cameras (120 Hz, ring) and bodies (one shared layout), one core"] = "\n".join(
        tbl + ["", "Growth (log-log slope from 5 bodies / 8 cameras up, over the runs that tracked every body): "
               + "; ".join(growth) + "."])
    if realtime:
        _realtime(quick, res)
        _fleet(quick, res)
    return res


def _realtime(quick: bool, res: BenchResult) -> None:
    """fleet20 (12 cameras x 120 Hz, 20 bodies) through the one-core model, and its profile."""
    sc = load_scenario("fleet20", ["sim.duration=12"] if quick else [])
    packets = _packets(simulate(sc).frames)
    rows = []
    for label, settings, pause_ns in REALTIME_VARIANTS:
        m = one_core(sc.arena, packets, settings=settings, pause_views_ns=pause_ns)
        if label == "defaults":
            for k in ("shed_fraction", "shed_after_first_s", "busy_fraction", "wait_p99_ms", "ticks_per_s",
                      "paused_fraction", "longest_step_ms"):
                res.metrics[f"scale_realtime_{k}"] = round(float(m[k]), 4)
        rows.append(
            f"| {label} | {m['packets']} | {m['shed_fraction'] * 100:.2f} % | {m['shed_first_s']} | "
            f"{m['shed_after_first_s'] * 100:.2f} % | {m['longest_step_ms']:.1f} | "
            f"{m['paused_fraction'] * 100:.1f} % | "
            f"{m['all_tracked_s']:.2f} | {m['busy_fraction'] * 100:.1f} % | {m['wait_p50_ms']:.2f} / "
            f"{m['wait_p99_ms']:.2f} / {m['wait_max_ms']:.1f} | {m['ticks_per_s']:.1f} | "
            f"{m['tracked']}/{m['bodies']} |")
    res.tables["Scale: one server core, fleet20 (12 cameras x 120 Hz, 20 bodies), real time"] = "\n".join([
        "| fusion settings | packets | shed | of them in the first second | shed after it | longest step (ms) | "
        "fused with the view "
        "updates paused | every body tracked after (s) | core busy | queueing p50 / p99 / max (ms) | output "
        "ticks/s | tracked at the end |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
        *rows,
        "",
        f"{sc.duration_s:g} s of the fleet flight; each packet's cost is its measured CPU time on this machine "
        "(decode + push), ticks at 100 Hz; shed: waited longer than 15 ms (server.shed_backlog_ms); the load relief "
        "(server.pause_views_backlog_ms, 5 ms by default) pauses the per-frame view updates while the queue is "
        "behind (server/load.py). The first second holds the first acquisition of all 20 (the fleet parked in "
        "view: about 40 ms of work, in steps of fusion.acquire_step_ms, 5 ms of estimated work, 10 ms apart) and "
        "the backlog it leaves.",
    ])
    prof = profile(sc.arena, packets[: len(packets) // 2])
    res.tables["Scale: where fleet20's fusion time goes (own time, cProfile, first half of the flight)"] = "\n".join(
        ["| function | share | calls |", "|---|---|---|"]
        + [f"| `{name}` | {share * 100:.1f} % | {calls} |" for name, share, calls in prof])


def fleet_identity(name: str = "fleet", duration_s: float | None = None) -> dict:
    """The fleet scenario replayed (ticks at 100 Hz): per body, the tracked fraction while >= 2 cameras see >= 3
    of its markers, position RMSE (mm) over the tracked ticks and its single-snapshot bound along the path
    (fusion_flights.path_crb), and the ticks whose pose is nearer another body's truth than its own (a swap);
    the identity states at the end and the ambiguities the identity book saw."""
    from visionpos.benchmarks.fusion_flights import CRB_EVERY, path_crb, seeing_cameras
    from visionpos.benchmarks.fusion_replay import replay

    sc = load_scenario(name, [f"sim.duration={duration_s}"] if duration_s else [])
    sim = simulate(sc)
    rep = replay(sc.arena, sim.frames)
    t = rep.times_ns
    names = [b.name for b in sc.bodies]
    truth = {n: sc.truth_at(n, t)[0] for n in names}
    rows = []
    for b, n in enumerate(names):
        seen = seeing_cameras(sim.frames, sim.frame_truth, b, t) >= 2
        ok = rep.tracked[n]
        err = np.linalg.norm(rep.positions[n][ok] - truth[n][ok], axis=1)
        nearest = np.argmin([np.linalg.norm(rep.positions[n][ok] - truth[m][ok], axis=1) for m in names], axis=0)
        wrong = nearest != b
        crb_mm, _ = path_crb(sc, sim, n, t[ok & seen][::CRB_EVERY])
        rows.append({"body": n, "tracked_when_seen": float(ok[seen].mean()) if seen.any() else float("nan"),
                     "rmse_mm": float(np.sqrt(np.mean(err**2)) * 1e3), "crb_mm": crb_mm,
                     "wrong_ticks": int(wrong.sum()), "swaps": int(np.sum(np.diff(wrong.astype(int)) == 1) + wrong[0]),
                     "identity": rep.pipeline.identity.describe(b)})
    return {"rows": rows, "ambiguities": rep.pipeline.identity.swaps_suspected, "duration_s": sc.duration_s,
            "acquisitions": rep.pipeline.stats()["acquisitions"], "lost": rep.pipeline.stats()["lost"]}


def _fleet(quick: bool, res: BenchResult) -> None:
    m = fleet_identity("fleet", 15.0 if quick else None)
    rows = m["rows"]
    res.metrics["scale_fleet_tracked_when_seen_min"] = round(min(r["tracked_when_seen"] for r in rows), 4)
    res.metrics["scale_fleet_rmse_over_crb_max"] = round(max(r["rmse_mm"] / r["crb_mm"] for r in rows), 3)
    res.metrics["scale_fleet_swaps"] = sum(r["swaps"] for r in rows)
    res.metrics["scale_fleet_ambiguities"] = m["ambiguities"]
    res.tables["Scale: fleet of 10 identical quads (fleet scenario, replay), identity by continuity"] = "\n".join(
        ["| body | tracked while >= 2 cameras see it | position RMSE (mm) | bound (mm) | RMSE / bound | ticks on "
         "another body | swaps | identity at the end |", "|---|---|---|---|---|---|---|---|"]
        + [f"| {r['body']} | {r['tracked_when_seen'] * 100:.2f} % | {r['rmse_mm']:.3f} | {r['crb_mm']:.3f} | "
           f"{r['rmse_mm'] / r['crb_mm']:.2f} | {r['wrong_ticks']} | {r['swaps']} | {r['identity']} |" for r in rows]
        + ["", f"{m['duration_s']:g} s: take-off in turn from the floor, crossings within 0.28 m, overtakings within "
           f"0.25 m, the 0.35 m hover grid, landing. {m['acquisitions']} acquisitions, {m['lost']} losses, "
           f"{m['ambiguities']} ambiguous encounters (two tracks of the layout within the swap distance). "
           "Swaps: ticks at which a body's output is nearer another body's truth than its own, counted per run of "
           "them. Bound: the single-snapshot Cramer-Rao bound of its pose along the path."])
