"""Cold start benchmark (issue 26): from `visionpos demo` to its first pose, with no kernel cache and with one.

    visionpos bench --only coldstart [--quick]

Each run is a fresh process running the demo CLI (`visionpos demo --quiet --no-console`) with
NUMBA_CACHE_DIR set to a new temporary folder, so numba finds nothing compiled: a fresh install.
The process reports the monotonic clock (system-wide on Linux) at the first non-empty publish
its outputs receive (the demo's Collector); the figure is that minus the parent's clock just
before starting the process, so it includes the interpreter's start, the imports, the
simulation, registration and the time synchronisation. The cold run's background compilation
(fusion/warmup.py) goes on after the demo ends; the benchmark waits for its record of a
complete cache, then runs the warm start the same way on that cache. Also reported: the CPU
(user) seconds of the demo process up to its first pose and the load average before each run
(the 2-core development host is shared). Goal: cold start to first pose <= 20 s.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from visionpos.benchmarks import BenchResult

FIRST_POSE_TAG = "VISIONPOS_FIRST_POSE"  # the line the demo process prints: tag, monotonic s, user CPU s
DEMO_S, DEMO_S_QUICK = 12.0, 6.0  # streaming seconds of each demo run
COMPILE_WAIT_S = 900.0  # the longest the benchmark waits for the background compilation

# The demo CLI with its output collector told to print the first pose; the rest is `visionpos demo`.
_DRIVER = f"""
import os, sys, time
from visionpos.app import demo
_publish = demo.Collector.publish
def publish(self, states):
    if states and not getattr(self, "_first_seen", False):
        self._first_seen = True
        print("{FIRST_POSE_TAG}", time.monotonic(), os.times().user, file=sys.stderr, flush=True)
    _publish(self, states)
demo.Collector.publish = publish
from visionpos.cli.main import main
sys.exit(main(sys.argv[1:]))
"""


def first_pose(stderr: str, t_start: float) -> tuple[float | None, float | None]:
    """(seconds from t_start to the first pose, user CPU seconds of the demo process by then) from the demo
    process's stderr; Nones when it never printed a pose."""
    for line in stderr.splitlines():
        parts = line.split()
        if len(parts) == 3 and parts[0] == FIRST_POSE_TAG:
            return float(parts[1]) - t_start, float(parts[2])
    return None, None


def demo_command(duration_s: float) -> list[str]:
    """The process a run starts: the driver above running `visionpos demo`."""
    return [sys.executable, "-c", _DRIVER, "demo", "--duration", f"{duration_s:g}", "--quiet", "--no-console"]


def run_once(cache_dir: str, duration_s: float) -> dict[str, float | None]:
    """One demo process on the kernel cache `cache_dir`: first pose (s), its user CPU (s), wall (s), load."""
    env = dict(os.environ, NUMBA_CACHE_DIR=cache_dir)
    load = os.getloadavg()[0]
    t0 = time.monotonic()
    proc = subprocess.run(demo_command(duration_s), env=env, capture_output=True, text=True)
    wall = time.monotonic() - t0
    pose_s, cpu_s = first_pose(proc.stderr, t0)
    if proc.returncode != 0 and pose_s is None:
        raise RuntimeError(f"the demo failed (exit {proc.returncode}): {proc.stderr.strip()[-800:]}")
    return {"first_pose_s": pose_s, "cpu_s": cpu_s, "wall_s": wall, "load": load}


def wait_for_record(cache_dir: str, timeout_s: float) -> float | None:
    """Seconds until the background compilation's record of a complete cache appears under cache_dir
    (fusion/warmup.py); None after timeout_s."""
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout_s:
        if any(Path(cache_dir).glob("fusion-warm-up-*.pickle")):
            return time.monotonic() - t0
        time.sleep(1.0)
    return None


def table(cold: dict, warm: dict | None, compile_after_s: float | None) -> str:
    """The markdown table of the two runs."""
    def cell(v, fmt="{:.1f}"):
        return "-" if v is None else fmt.format(v)

    rows = ["| start | first pose (s) | demo process CPU by then (s) | load average before |", "|---|---|---|---|"]
    for name, r in (("cold (empty NUMBA_CACHE_DIR)", cold), ("warm (the cache the cold run filled)", warm)):
        if r is not None:
            rows.append(f"| {name} | {cell(r['first_pose_s'])} | {cell(r['cpu_s'])} | {cell(r['load'], '{:.2f}')} |")
    rows.append("")
    rows.append(f"The cold run's background compilation finished {cell(compile_after_s)} s after that demo ended.")
    return "\n".join(rows)


def run(quick: bool = False) -> BenchResult:
    duration = DEMO_S_QUICK if quick else DEMO_S
    res = BenchResult()
    cache = tempfile.mkdtemp(prefix="visionpos-coldstart-")
    try:
        cold = run_once(cache, duration)
        compiled_after = wait_for_record(cache, COMPILE_WAIT_S)
        warm = run_once(cache, duration) if compiled_after is not None else None
    finally:
        shutil.rmtree(cache, ignore_errors=True)
    for prefix, r in (("coldstart", cold), ("warmstart", warm)):
        if r is None or r["first_pose_s"] is None:
            res.notes.append(f"{prefix}: the demo published no pose")
            continue
        res.metrics[f"{prefix}_first_pose_s"] = r["first_pose_s"]
        res.metrics[f"{prefix}_cpu_s"] = r["cpu_s"]
    if compiled_after is not None:
        res.metrics["coldstart_compile_after_demo_s"] = compiled_after
    else:
        res.notes.append(f"the background compilation did not finish within {COMPILE_WAIT_S:.0f} s: no warm run")
    res.tables["Cold start to first pose (visionpos demo)"] = table(cold, warm, compiled_after)
    return res
