"""Console benchmark (issue 17): the server's per-packet cost with one browser connected, and its update rate.

    visionpos bench --only console [--quick]

The demo's live chain on the thesis arena (4 cameras x 100 Hz) with the console on, and one WebSocket
client in a process of its own (as a browser would be) that connects and disconnects on command and
counts the state updates it receives (console.update_rate_hz = BENCH_UPDATE_RATE_HZ). After SETTLE_S,
the run alternates windows of WINDOW_S without and with the client connected (each after SWITCH_S for
the connection to open or close). Per window: the server's event-loop thread CPU time per received
station packet (time.thread_time on the loop thread only; the console runs on the same loop, so its
whole cost is in it), the console's own work timed inside it (update task and sends), output ticks/s
and the client's updates/s.

The ratio: for each window with the client, its cost over the cost without the console, which is
the mean of its two neighbouring windows less the console's own work in them (without a client the
console still reads the health once a second and runs its watches, a few µs per packet, timed
inside it); console_cost_ratio is the median over the windows with the client. Why windows of one
run and not whole runs with and without the console: on the shared 2-core development host one
run's loop CPU per packet moved by +-20 % with the other processes' load, and the median of 8 pairs
of runs read 0.996, 1.067 and 1.126 for the same code within two hours; neighbouring windows of one
run share the host's load of the moment, and the run makes many of them. The windows still move by
+-10 % each, so console_cost_ratio_iqr (the ratios' interquartile range) says how far to trust the
median, and console_own_cost_ratio = (off + own) / off, from the console's own timing (steady to
+-0.01), is the figure to watch for its changes. Goals: cost ratio <= 1.05, client >= 30 updates/s.
"""

from __future__ import annotations

import asyncio
import json
import sys
import time
from typing import Any

import numpy as np

from visionpos.benchmarks import BenchResult, windows_between

# just above the 30 updates/s the goal asks for, so that the client's count over a window (+- one update) clears
# it; the camera views ride on the console's default camera_view_rate_hz (10) of them
BENCH_UPDATE_RATE_HZ = 31.0
SETTLE_S = 2.5  # the first window starts this long after the stations do (registration, compile, client start)
SWITCH_S = 0.3  # after connecting or disconnecting, before a window's measurement starts
WINDOW_S = 2.0
WINDOWS_QUICK, WINDOWS_FULL = 11, 41  # odd: the first and the last are without the client
WARMUP_S = 2.5  # the unmeasured first run (compiles, warms the caches)


async def _client_main(url: str) -> None:
    """The client process: answers each stdin line with its counts (JSON) after doing what it says: "connect"
    opens the WebSocket and counts state messages, "disconnect" closes it, anything else only counts."""
    import aiohttp

    count = {"states": 0, "bytes": 0}

    async def receive(ws) -> None:
        async for msg in ws:
            if msg.type == aiohttp.WSMsgType.TEXT and msg.data.startswith('{"type": "state"'):
                count["states"] += 1
                count["bytes"] += len(msg.data)

    async with aiohttp.ClientSession() as http:
        ws, task = None, None
        loop = asyncio.get_running_loop()
        print("ready", flush=True)
        while line := await loop.run_in_executor(None, sys.stdin.readline):
            cmd = line.strip()
            if cmd == "connect" and ws is None:
                ws = await http.ws_connect(url, max_msg_size=0)
                task = asyncio.create_task(receive(ws))
            elif cmd == "disconnect" and ws is not None:
                task.cancel()
                await ws.close()
                ws = None
            print(json.dumps({"t": time.perf_counter(), **count}), flush=True)


def _demo_run(arena, duration_s: float, windows: int) -> tuple[list[dict[str, Any]], dict[str, Any]]:
    """One live demo with the console; `windows` alternating windows, the first without the client.
    Returns the windows' figures and the run's (tracked fraction, updates the console dropped)."""
    from console.settings import ConsoleSettings
    from visionpos.app.demo import run_demo

    views: list = []
    rows: list[dict[str, Any]] = []
    got: dict[str, Any] = {}

    async def during(ctx) -> None:
        server = ctx.server
        url = f"ws://127.0.0.1:{views[0].port}/ws"
        client = await asyncio.create_subprocess_exec(sys.executable, "-m", "visionpos.benchmarks.console", url,
                                                      stdin=asyncio.subprocess.PIPE, stdout=asyncio.subprocess.PIPE)

        async def say(cmd: str) -> dict[str, Any]:
            client.stdin.write(cmd.encode() + b"\n")
            await client.stdin.drain()
            return json.loads(await client.stdout.readline())

        try:
            await client.stdout.readline()  # "ready"
            await asyncio.sleep(SETTLE_S)
            for i in range(windows):
                connected = i % 2 == 1
                await say("connect" if connected else "disconnect")
                await asyncio.sleep(SWITCH_S)
                c0 = await say("count")
                cpu0, pk0, tk0, own0 = time.thread_time(), server.ingest.counters.packets, server.ticks, views[0].cpu_ns
                t0 = time.perf_counter()
                await asyncio.sleep(WINDOW_S)
                cpu1, pk1, tk1, own1 = time.thread_time(), server.ingest.counters.packets, server.ticks, views[0].cpu_ns
                t1 = time.perf_counter()
                c1 = await say("count")
                n = max(pk1 - pk0, 1)
                dt = c1["t"] - c0["t"]
                rows.append({"client": connected, "cpu_us_per_packet": (cpu1 - cpu0) / n * 1e6,
                             "console_us_per_packet": (own1 - own0) * 1e-3 / n, "ticks_hz": (tk1 - tk0) / (t1 - t0),
                             "client_hz": (c1["states"] - c0["states"]) / dt,
                             "client_kb_per_s": (c1["bytes"] - c0["bytes"]) / dt / 1e3})
            got["dropped"] = views[0].stats()["dropped"]
        finally:
            client.stdin.close()
            await client.wait()

    settings = ConsoleSettings(port=0, update_rate_hz=BENCH_UPDATE_RATE_HZ)
    summary = asyncio.run(run_demo(arena, duration_s, None, during=during, console=settings, on_console=views.append))
    got["tracked_fraction"] = min(b["tracked_fraction"] for b in summary["bodies"])
    return rows, got


def window_ratios(rows: list[dict[str, Any]]) -> tuple[list[float], list[float], list[float]]:
    """Per window with the client (each between two without): its cost over the cost without the console (the
    neighbours' mean less their console's own work), that cost without the console (µs/packet), and the idle
    console's own share of it."""
    ratios, off, idle = [], [], []
    for k in windows_between([r["client"] for r in rows]):
        base = (rows[k - 1]["cpu_us_per_packet"] + rows[k + 1]["cpu_us_per_packet"]) / 2
        own_idle = (rows[k - 1]["console_us_per_packet"] + rows[k + 1]["console_us_per_packet"]) / 2
        ratios.append(rows[k]["cpu_us_per_packet"] / (base - own_idle))
        off.append(base - own_idle)
        idle.append(own_idle / (base - own_idle))
    return ratios, off, idle


def bench_console(quick: bool) -> tuple[dict[str, float], list[dict], dict[str, Any]]:
    from visionpos.app.demo import demo_arena

    windows = WINDOWS_QUICK if quick else WINDOWS_FULL
    duration_s = SETTLE_S + windows * (WINDOW_S + SWITCH_S + 0.2) + 2.0
    _demo_run(demo_arena("thesis", WARMUP_S + 3.0, 1, []), WARMUP_S + 3.0, 1)  # compiles, warms; not measured
    rows, got = _demo_run(demo_arena("thesis", duration_s, 1, []), duration_s, windows)
    ratios, off, idle = window_ratios(rows)
    on = [r for r in rows if r["client"]]
    none = [r for r in rows if not r["client"]]
    cost_off = float(np.median(off))
    q1, q3 = np.percentile(ratios, [25, 75])
    metrics = {
        "console_loop_cpu_us_per_packet_off": cost_off,
        "console_loop_cpu_us_per_packet_on": float(np.median([r["cpu_us_per_packet"] for r in on])),
        "console_cost_ratio": float(np.median(ratios)),
        "console_cost_ratio_iqr": float(q3 - q1),
        "console_windows_with_client": float(len(ratios)),
        "console_own_cpu_us_per_packet": float(np.median([r["console_us_per_packet"] for r in on])),
        "console_idle_own_share": float(np.median(idle)),
        "console_client_updates_hz": float(np.median([r["client_hz"] for r in on])),
        "console_client_kb_per_s": float(np.median([r["client_kb_per_s"] for r in on])),
        "console_output_rate_ratio": float(np.median([r["ticks_hz"] for r in on]))
        / float(np.median([r["ticks_hz"] for r in none])),
    }
    metrics["console_own_cost_ratio"] = (cost_off + metrics["console_own_cpu_us_per_packet"]) / cost_off
    return metrics, rows, got


def run(quick: bool = False) -> BenchResult:
    res = BenchResult()
    m, rows, got = bench_console(quick)
    res.metrics.update(m)
    ratios = iter(window_ratios(rows)[0])
    lines = ["| window | client | loop CPU µs / station packet | of it the console's own | on / off (neighbours less "
             "the idle console) | output ticks/s | client updates/s | client kB/s |",
             "|---|---|---|---|---|---|---|---|"]
    for i, r in enumerate(rows):
        ratio = f"{next(ratios):.3f}" if r["client"] and 0 < i < len(rows) - 1 else "-"
        lines.append(f"| {i + 1} | {'connected' if r['client'] else '-'} | {r['cpu_us_per_packet']:.1f} | "
                     f"{r['console_us_per_packet']:.1f} | {ratio} | {r['ticks_hz']:.1f} | "
                     + (f"{r['client_hz']:.1f} | {r['client_kb_per_s']:.1f} |" if r["client"] else "- | - |"))
    res.tables[f"Console on the live demo: thesis arena (4 cameras x 100 Hz), one run, {len(rows)} windows of "
               f"{WINDOW_S:g} s alternately without and with one WebSocket client at {BENCH_UPDATE_RATE_HZ:.0f} "
               f"updates/s (tracked {100 * got['tracked_fraction']:.2f} %, updates dropped {got['dropped']})"] = \
        "\n".join(lines)
    res.notes.append(
        f"Console: per-packet cost on the server's event-loop thread with one client / without the console: "
        f"{m['console_cost_ratio']:.3f}, the median over {m['console_windows_with_client']:.0f} windows with the "
        f"client (interquartile range {m['console_cost_ratio_iqr']:.3f}; "
        f"{m['console_loop_cpu_us_per_packet_off']:.1f} -> {m['console_loop_cpu_us_per_packet_on']:.1f} µs); timed "
        f"inside the console, its own work is {m['console_own_cpu_us_per_packet']:.1f} µs per packet (ratio "
        f"{m['console_own_cost_ratio']:.3f}), and without a client {100 * m['console_idle_own_share']:.2f} % (its "
        f"health read and watches). The client received {m['console_client_updates_hz']:.1f} updates/s "
        f"({m['console_client_kb_per_s']:.0f} kB/s). The console builds and encodes each update once on the loop "
        "(a camera's view only when it has something new) and hands it to the client's sender."
    )
    return res


if __name__ == "__main__":  # the client of bench_console: python -m visionpos.benchmarks.console WS_URL
    asyncio.run(_client_main(sys.argv[1]))
