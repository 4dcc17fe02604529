"""Demo memory benchmark: the resident set size (RSS) of a long `visionpos demo`, and how fast it grows.

A demo left running (an exhibition, a soak test) must not grow without bound. The demo runs
for `duration_s` seconds of streaming (DURATION_S, 600, by default; QUICK_DURATION_S in quick
mode) on the thesis arena, in this process; an observer samples its RSS every SAMPLE_S. The
growth is the least-squares slope over the samples after SETTLE_S (start-up allocates: the
kernels, the simulated frames, the buffers). The collector once kept every pose: 17 MB/min.
"""

from __future__ import annotations

import asyncio
import os
import time
from typing import Any

import numpy as np

from visionpos.benchmarks import BenchResult

DURATION_S = 600.0
QUICK_DURATION_S = 120.0
SAMPLE_S = 1.0
SETTLE_S = 20.0  # samples before this are start-up, not growth (at most half the run's)


def rss_bytes() -> int:
    """This process's resident set size now (Linux /proc; 0 where it has none)."""
    try:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError, IndexError):
        return 0


def growth_mb_per_min(times_s: np.ndarray, rss: np.ndarray, settle_s: float = SETTLE_S) -> float:
    """Least-squares slope of rss (N,) bytes over times_s (N,) seconds, in MB (1e6 bytes) per minute, over the
    samples from min(settle_s, half the span) on; nan with fewer than 3 of them."""
    t = np.asarray(times_s, float)
    y = np.asarray(rss, float)
    if len(t) == 0:
        return float("nan")
    keep = t >= t[0] + min(settle_s, 0.5 * (t[-1] - t[0]))
    if keep.sum() < 3:
        return float("nan")
    slope_bytes_per_s = np.polyfit(t[keep], y[keep], 1)[0]
    return float(slope_bytes_per_s * 60.0 / 1e6)


def measure(duration_s: float, scenario: str = "thesis") -> dict[str, Any]:
    """One demo of duration_s seconds with RSS sampled every SAMPLE_S: the samples, the growth and the summary's
    tracked fraction (a demo that stopped tracking would grow less and prove nothing)."""
    from visionpos.app.demo import demo_arena, run_demo

    times: list[float] = []
    samples: list[int] = []

    async def sample(ctx) -> None:
        t0 = time.monotonic()
        while time.monotonic() - t0 < ctx.duration_s:
            times.append(time.monotonic() - t0)
            samples.append(rss_bytes())
            await asyncio.sleep(SAMPLE_S)

    arena = demo_arena(scenario, duration_s, 1, [])
    summary = asyncio.run(run_demo(arena, duration_s, None, during=sample))
    t, rss = np.asarray(times), np.asarray(samples, float)
    return {"times_s": t, "rss_bytes": rss, "growth_mb_per_min": growth_mb_per_min(t, rss),
            "rss_start_mb": float(rss[0]) / 1e6 if len(rss) else float("nan"),
            "rss_end_mb": float(rss[-1]) / 1e6 if len(rss) else float("nan"),
            "tracked_fraction": min(b["tracked_fraction"] for b in summary["bodies"])}


def run(quick: bool = False, duration_s: float | None = None) -> BenchResult:
    """duration_s: seconds of demo (default DURATION_S; QUICK_DURATION_S in quick mode)."""
    duration = duration_s if duration_s is not None else (QUICK_DURATION_S if quick else DURATION_S)
    m = measure(duration)
    res = BenchResult()
    res.metrics.update({"demo_rss_growth_mb_per_min": m["growth_mb_per_min"], "demo_rss_start_mb": m["rss_start_mb"],
                        "demo_rss_end_mb": m["rss_end_mb"], "demo_rss_tracked_fraction": m["tracked_fraction"]})
    res.tables["Demo memory (thesis arena, one process)"] = "\n".join([
        "| demo s | RSS at start MB | RSS at end MB | growth MB/min (after start-up) | tracked |",
        "|---|---|---|---|---|",
        f"| {duration:.0f} | {m['rss_start_mb']:.1f} | {m['rss_end_mb']:.1f} | {m['growth_mb_per_min']:.2f} "
        f"| {m['tracked_fraction']:.3f} |",
    ])
    res.notes.append(f"RSS of the demo's process every {SAMPLE_S:g} s; the growth is the least-squares slope of the "
                     f"samples after the first {SETTLE_S:g} s (or half the run, if shorter).")
    return res
