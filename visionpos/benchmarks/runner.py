"""Runs benchmark groups for `visionpos bench`: results, goals and the markdown of docs/benchmarks.md.

Each group runs in its own child process with one BLAS/OpenCV thread, so
figures are one-core figures and one group cannot disturb another.
"""

from __future__ import annotations

import datetime as _dt
import importlib
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

from visionpos.benchmarks import GOALS, GROUPS, BenchResult

_ONE_THREAD = {
    "OMP_NUM_THREADS": "1",
    "OPENBLAS_NUM_THREADS": "1",
    "MKL_NUM_THREADS": "1",
    "VECLIB_MAXIMUM_THREADS": "1",
    "NUMEXPR_NUM_THREADS": "1",
}


def machine_description() -> str:
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    import numpy
    import scipy

    try:
        import cv2

        cv = cv2.__version__
    except ImportError:
        cv = "missing"
    return (
        f"{cpu}, {os.cpu_count()} logical cores, {platform.system()} {platform.release()}, "
        f"Python {platform.python_version()}, numpy {numpy.__version__}, scipy {scipy.__version__}, OpenCV {cv}"
    )


def run_group_in_child(group: str, quick: bool) -> tuple[BenchResult, float]:
    """Run one group in a child process with one BLAS/OpenCV thread: (result, seconds it took)."""
    env = dict(os.environ, **_ONE_THREAD)
    t0 = time.perf_counter()
    proc = subprocess.run(
        [sys.executable, "-m", "visionpos.benchmarks.runner", group, "1" if quick else "0"],
        env=env,
        capture_output=True,
        text=True,
    )
    elapsed = time.perf_counter() - t0
    if proc.returncode != 0:
        tail = "\n".join(proc.stderr.strip().splitlines()[-15:])
        return BenchResult(notes=[f"group '{group}' failed (exit {proc.returncode}):\n{tail}"]), elapsed
    data = json.loads(proc.stdout.strip().splitlines()[-1])
    return BenchResult(metrics=data["metrics"], tables=data["tables"], notes=data["notes"]), elapsed


def _child(group: str, quick: bool) -> None:
    try:
        import cv2

        cv2.setNumThreads(1)
    except ImportError:
        pass
    module = importlib.import_module(f"visionpos.benchmarks.{GROUPS[group]}")
    res: BenchResult = module.run(quick=quick)
    print(json.dumps({"metrics": res.metrics, "tables": res.tables, "notes": res.notes}, default=float))


def format_value(v: float) -> str:
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        return str(v)
    a = abs(v)
    if a == 0 or 0.01 <= a < 1e5:
        return f"{v:.3f}".rstrip("0").rstrip(".") if a < 100 else f"{v:.1f}"
    return f"{v:.3g}"


def merged_metrics(results: dict[str, tuple[BenchResult, float]]) -> dict[str, float]:
    """Every group's metrics in one mapping."""
    merged: dict[str, float] = {}
    for res, _ in results.values():
        merged.update(res.metrics)
    return merged


def goal_rows(results: dict[str, tuple[BenchResult, float]]) -> list[tuple[str, float, str, float, bool]]:
    """(description, measured, op, target, met) for every goal whose metric was run."""
    merged = merged_metrics(results)
    rows = []
    for g in GOALS:
        v, t, ok = g.check(merged)
        if ok is not None:
            rows.append((g.what, v, g.op, t, ok))
    return rows


def _run_record(res: BenchResult, elapsed_s: float, command: str, quick: bool, when: str, machine: str) -> dict:
    return {"metrics": res.metrics, "tables": res.tables, "notes": res.notes, "elapsed_s": elapsed_s,
            "command": command, "quick": quick, "date": when, "machine": machine}


def _skipped(res: BenchResult) -> bool:
    """A group that measured nothing because what it needs is absent (its notes all say "skipped: ...")."""
    return not res.metrics and bool(res.notes) and all(n.startswith("skipped:") for n in res.notes)


def merge_runs(stored: dict[str, dict], results: dict[str, tuple[BenchResult, float]], command: str, quick: bool,
               when: str | None = None, machine: str | None = None) -> dict[str, dict]:
    """The stored runs (group -> record, as in docs/benchmarks.json) with the groups just run replaced: each
    record keeps the command, date and machine of the run that produced it, so a partial run
    (`--only ...`) refreshes its groups and leaves the others as they were measured. A group that skipped (what
    it needs is absent: "skipped: ..." notes, no metrics) keeps its stored figures, with a note saying so."""
    when = when or _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    machine = machine or machine_description()
    merged = dict(stored)
    for group, (res, elapsed) in results.items():
        if _skipped(res) and group in stored and stored[group]["metrics"]:
            # nothing measured now (no SITL binary here): the last figures stay, saying they were not re-run
            kept = dict(stored[group])
            kept["notes"] = [n for n in kept["notes"] if not n.startswith("not re-run by ")] + [
                f"not re-run by `{command}` on {when}: " + "; ".join(res.notes)]
            merged[group] = kept
            continue
        merged[group] = _run_record(res, elapsed, command, quick, when, machine)
    return {g: merged[g] for g in [*GROUPS, *sorted(set(merged) - set(GROUPS))] if g in merged}


def _results_of(runs: dict[str, dict]) -> dict[str, tuple[BenchResult, float]]:
    return {g: (BenchResult(metrics=r["metrics"], tables=r["tables"], notes=r["notes"]), r["elapsed_s"])
            for g, r in runs.items()}


def _run_label(r: dict) -> str:
    return f"`{r['command']}`" + (" (quick mode)" if r["quick"] else "") + f", {r['date']}"


def runs_to_markdown(runs: dict[str, dict]) -> str:
    """docs/benchmarks.md from every stored group run (merge_runs); the goals table judges the newest
    figure of each metric. Where the groups come from more than one run, each section names its own."""
    labels = {_run_label(r) for r in runs.values()}
    machines = {r["machine"] for r in runs.values()}
    out = [
        "# Benchmarks",
        "",
        "Generated by `visionpos bench --write-docs docs/benchmarks.md`; do not edit by hand. A run of some groups",
        "(`--only`) replaces their sections and keeps the others (docs/benchmarks.json holds every group's figures",
        "with the command, date and machine that produced them).",
        "",
    ]
    if len(labels) == 1:
        out.append(f"- Command: {labels.pop()}")
    else:
        out.append("- Commands: each group's section names the run it comes from")
    if len(machines) == 1:
        out.append(f"- Machine: {machines.pop()}")
    else:
        out.append("- Machines: each group's section names its own")
    out += ["- Each group runs in its own process with one BLAS/OpenCV thread.", ""]
    results = _results_of(runs)
    goals = goal_rows(results)
    if goals:
        out += ["## Goals from the issues", "", "| goal | measured | target | met |", "|---|---|---|---|"]
        out += [
            f"| {g} | {format_value(v)} | {op} {format_value(t)} | {'yes' if ok else '**no**'} |"
            for g, v, op, t, ok in goals
        ]
        out.append("")
    single = len({_run_label(r) for r in runs.values()}) == 1 and len({r["machine"] for r in runs.values()}) == 1
    for group, r in runs.items():
        res = results[group][0]
        out += [f"## {group}", ""]
        out += [f"Run time {r['elapsed_s']:.1f} s." if single else
                f"Run time {r['elapsed_s']:.1f} s, by {_run_label(r)} on {r['machine']}.", ""]
        if res.metrics:
            out += ["| metric | value |", "|---|---|"]
            out += [f"| `{k}` | {format_value(v)} |" for k, v in res.metrics.items()]
            out.append("")
        for title, table in res.tables.items():
            out += [f"### {title}", "", table.strip(), ""]
        for note in res.notes:
            out += [f"> {line}" for line in note.splitlines()] + [""]
    return "\n".join(out)


def write_docs(markdown_path: Path, results: dict[str, tuple[BenchResult, float]], command: str,
               quick: bool) -> None:
    """Merge these results into the runs stored beside markdown_path (.json) and rewrite both."""
    store = markdown_path.with_suffix(".json")
    stored = json.loads(store.read_text()) if store.exists() else {}
    runs = merge_runs(stored, results, command, quick)
    store.write_text(json.dumps(runs, indent=1, default=float) + "\n")
    markdown_path.write_text(runs_to_markdown(runs))


def to_markdown(results: dict[str, tuple[BenchResult, float]], command: str, quick: bool) -> str:
    """The markdown of one run alone (nothing stored merged in)."""
    return runs_to_markdown(merge_runs({}, results, command, quick))


if __name__ == "__main__":  # child entry point: python -m visionpos.benchmarks.runner GROUP QUICK
    _child(sys.argv[1], sys.argv[2] == "1")
