"""Console benchmark (issue 17): the server's per-packet cost with one browser connected, and its update rate.

    visionpos bench --only console [--quick]

The demo's live chain on the thesis arena (4 cameras x 100 Hz), same seed and duration, without the
console and with it plus one WebSocket client in a process of its own (as a browser would be) that
counts the state updates it receives. Per run, between OUTPUT_SETTLE_S after the stations start and
OUTPUT_TAIL_S before they stop: the server's event-loop thread CPU time per received station packet
(time.thread_time on the loop thread only; the console runs on the same loop, so its whole cost is in
it), output ticks/s, and the client's updates/s (console.update_rate_hz = BENCH_UPDATE_RATE_HZ). Goals:
cost ratio <= 1.05, client >= 30 updates/s.

The measurement: the first run of a process compiles the numba kernels and warms the caches, so one
unmeasured warm-up run comes first (it made the first "off" run dearer and the ratio read low, 0.92).
Then PAIRS_QUICK / PAIRS_FULL pairs, each an "off" and an "on" run back to back, the order swapped
every pair (a load that drifts over the bench falls on both sides); console_cost_ratio is the median
of the pairs' ratios, so one run disturbed by another process on a shared host moves it little;
console_cost_ratio_spread (largest minus smallest pair ratio) says how far to trust it. On the shared
2-core development host one run's loop CPU per packet moved by +-20 % with the other processes' load,
3 pairs' ratios spread by 0.08 to 0.46 and their median moved between 0.96 and 1.12 for the same code:
the two-run ratio cannot judge 5 % there, whatever the console does. The console's own work, timed
inside it (update task and sends, thread CPU time; console_own_cost_ratio = (off + own) / off), moved
by +-0.01 between the same runs: it leaves out only what the console makes the loop do outside its
own code (the sender's wake-ups, the socket's callbacks), and is the figure to watch for its changes.
"""

from __future__ import annotations

import asyncio
import json
import sys
import time
from typing import Any

import numpy as np

from visionpos.benchmarks import BenchResult
from visionpos.benchmarks.bridge import (
    OUTPUT_DURATION_S_FULL,
    OUTPUT_DURATION_S_QUICK,
    OUTPUT_SETTLE_S,
    OUTPUT_TAIL_S,
    _client_counts,
)

# just above the 30 updates/s the goal asks for, so that the client's count over a window (+- one update) clears
# it; the camera views ride on the console's default camera_view_rate_hz (10) of them
BENCH_UPDATE_RATE_HZ = 31.0
# pairs of runs (off, on); one pair's ratio moved by +-20 % on a shared 2-core host, the median of several less
PAIRS_QUICK, PAIRS_FULL = 4, 8
WARMUP_S = 2.5  # the unmeasured first run


async def _client_main(url: str) -> None:
    """The client process: one WebSocket, counts state messages; answers each stdin line with the count."""
    import aiohttp

    count = {"states": 0, "bytes": 0}

    async def receive(ws) -> None:
        async for msg in ws:
            if msg.type == aiohttp.WSMsgType.TEXT and msg.data.startswith('{"type": "state"'):
                count["states"] += 1
                count["bytes"] += len(msg.data)

    async with aiohttp.ClientSession() as http:
        async with http.ws_connect(url, max_msg_size=0) as ws:
            task = asyncio.create_task(receive(ws))
            print("ready", flush=True)
            loop = asyncio.get_running_loop()
            while await loop.run_in_executor(None, sys.stdin.readline):
                print(json.dumps({"t": time.perf_counter(), **count}), flush=True)
            task.cancel()


def _demo_run(arena, duration_s: float, console: bool) -> dict[str, Any]:
    from console.settings import ConsoleSettings
    from visionpos.app.demo import run_demo

    got: dict[str, Any] = {}
    views: list = []

    async def during(ctx) -> None:
        server = ctx.server
        t_end = time.monotonic() + ctx.duration_s - OUTPUT_TAIL_S
        client = None
        if console:
            url = f"ws://127.0.0.1:{views[0].port}/ws"
            client = await asyncio.create_subprocess_exec(sys.executable, "-m", "visionpos.benchmarks.console", url,
                                                          stdin=asyncio.subprocess.PIPE, stdout=asyncio.subprocess.PIPE)
            await client.stdout.readline()  # "ready"
        try:
            await asyncio.sleep(OUTPUT_SETTLE_S)
            cpu0, pk0, tk0, t0 = time.thread_time(), server.ingest.counters.packets, server.ticks, time.perf_counter()
            own0 = views[0].cpu_ns if views else 0
            c0 = await _client_counts(client)
            await asyncio.sleep(max(0.5, t_end - time.monotonic()))
            cpu1, pk1, tk1, t1 = time.thread_time(), server.ingest.counters.packets, server.ticks, time.perf_counter()
            own1 = views[0].cpu_ns if views else 0
            c1 = await _client_counts(client)
        finally:
            if client is not None:
                client.stdin.close()
                await client.wait()
        got.update(cpu_s=cpu1 - cpu0, packets=pk1 - pk0, ticks_hz=(tk1 - tk0) / (t1 - t0),
                   console_cpu_s=(own1 - own0) * 1e-9)
        if c1:
            dt = c1["t"] - c0["t"]
            got["client_hz"] = (c1["states"] - c0["states"]) / dt
            got["client_kb_per_s"] = (c1["bytes"] - c0["bytes"]) / dt / 1e3
            got["dropped"] = views[0].stats()["dropped"]

    settings = ConsoleSettings(port=0, update_rate_hz=BENCH_UPDATE_RATE_HZ) if console else None
    summary = asyncio.run(run_demo(arena, duration_s, None, during=during, console=settings, on_console=views.append))
    got["cpu_us_per_packet"] = got["cpu_s"] / max(got["packets"], 1) * 1e6
    got["console_us_per_packet"] = got["console_cpu_s"] / max(got["packets"], 1) * 1e6
    got["output_rate_hz"] = summary["output_rate_hz"]
    got["tracked_fraction"] = min(b["tracked_fraction"] for b in summary["bodies"])
    return got


def bench_console(quick: bool) -> tuple[dict[str, float], list[dict]]:
    from visionpos.app.demo import demo_arena

    duration_s = OUTPUT_DURATION_S_QUICK if quick else OUTPUT_DURATION_S_FULL
    pairs = PAIRS_QUICK if quick else PAIRS_FULL
    arena = demo_arena("thesis", duration_s, 1, [])
    _demo_run(demo_arena("thesis", WARMUP_S, 1, []), WARMUP_S, True)  # compiles, warms; not measured
    runs: dict[bool, list[dict]] = {False: [], True: []}
    for i in range(pairs):
        for console in ((False, True) if i % 2 == 0 else (True, False)):
            runs[console].append(_demo_run(arena, duration_s, console))
    off, on = runs[False], runs[True]
    ratios = [a["cpu_us_per_packet"] / b["cpu_us_per_packet"] for a, b in zip(on, off)]
    for r, ratio in zip(on, ratios):
        r["pair_ratio"] = ratio
    cost_off = float(np.median([r["cpu_us_per_packet"] for r in off]))
    cost_on = float(np.median([r["cpu_us_per_packet"] for r in on]))
    metrics = {
        "console_loop_cpu_us_per_packet_off": cost_off,
        "console_loop_cpu_us_per_packet_on": cost_on,
        "console_cost_ratio": float(np.median(ratios)),
        "console_cost_ratio_spread": max(ratios) - min(ratios),
        # the console's own work (update task + sends, timed inside it) per packet: immune to the run-to-run noise
        # of a shared host that the ratio of two runs carries
        "console_own_cpu_us_per_packet": float(np.median([r["console_us_per_packet"] for r in on])),
        "console_client_updates_hz": float(np.median([r["client_hz"] for r in on])),
        "console_client_kb_per_s": float(np.median([r["client_kb_per_s"] for r in on])),
        "console_output_rate_ratio": float(np.median([r["output_rate_hz"] for r in on]))
        / float(np.median([r["output_rate_hz"] for r in off])),
    }
    metrics["console_own_cost_ratio"] = (cost_off + metrics["console_own_cpu_us_per_packet"]) / cost_off
    rows = [dict(r, console=c) for c in (False, True) for r in runs[c]]
    return metrics, rows


def run(quick: bool = False) -> BenchResult:
    res = BenchResult()
    m, rows = bench_console(quick)
    res.metrics.update(m)
    lines = ["| console | loop CPU µs / station packet | on / off (its pair) | of it the console's own "
             "| output ticks/s | client updates/s | client kB/s | updates dropped | tracked |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        cells = ["one client" if r["console"] else "off", f"{r['cpu_us_per_packet']:.1f}",
                 f"{r['pair_ratio']:.3f}" if r["console"] else "-",
                 f"{r['console_us_per_packet']:.1f}" if r["console"] else "-", f"{r['output_rate_hz']:.1f}"]
        if r["console"]:
            cells += [f"{r['client_hz']:.1f}", f"{r['client_kb_per_s']:.1f}", str(r["dropped"])]
        else:
            cells += ["-", "-", "-"]
        lines.append("| " + " | ".join(cells + [f"{r['tracked_fraction']:.4f}"]) + " |")
    dur = OUTPUT_DURATION_S_QUICK if quick else OUTPUT_DURATION_S_FULL
    res.tables[f"Console on the live demo: thesis arena (4 cameras x 100 Hz), {dur:.0f} s per run, without it and "
               "with one WebSocket client at "
               f"{BENCH_UPDATE_RATE_HZ:.0f} updates/s"] = "\n".join(lines)
    res.notes.append(
        f"Console: per-packet cost on the server's event-loop thread with one client / without: "
        f"{m['console_cost_ratio']:.3f}, the median of {len(rows) // 2} pairs' ratios (spread "
        f"{m['console_cost_ratio_spread']:.3f}; {m['console_loop_cpu_us_per_packet_off']:.1f} -> "
        f"{m['console_loop_cpu_us_per_packet_on']:.1f} µs, medians over runs, after a warm-up run); timed inside"
        " the console, its own "
        f"work is {m['console_own_cpu_us_per_packet']:.1f} µs per packet (ratio {m['console_own_cost_ratio']:.3f}): "
        "on a shared host the two runs' difference carries the other processes' noise. The client received "
        f"{m['console_client_updates_hz']:.1f} updates/s ({m['console_client_kb_per_s']:.0f} kB/s). The console "
        "builds and encodes each update once on the loop (a camera's view only when it has something new) and hands "
        "it to the client's sender; its whole cost is in the loop's CPU time."
    )
    return res


if __name__ == "__main__":  # the client of bench_console: python -m visionpos.benchmarks.console WS_URL
    asyncio.run(_client_main(sys.argv[1]))
