"""`visionpos bench`: run benchmark groups, print a table, optionally JSON and docs (visionpos.benchmarks.runner).

Each group runs in its own child process with one BLAS/OpenCV thread, so figures are one-core
figures and one group cannot disturb another.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from visionpos.benchmarks import GROUPS, BenchResult
from visionpos.benchmarks.runner import format_value, goal_rows, merged_metrics, run_group_in_child, write_docs


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--only", action="append", choices=sorted(GROUPS), help="run only this group (repeatable)")
    p.add_argument("--quick", action="store_true", help="shorter runs (smoke test; figures are noisier)")
    p.add_argument("--json", action="store_true", help="print all metrics as one JSON object")
    p.add_argument("--write-docs", metavar="FILE",
                   help="write the results as markdown (e.g. docs/benchmarks.md), merged with the groups stored "
                        "beside it (FILE with .json): a run of some groups replaces only theirs")


def run(args: argparse.Namespace) -> int:
    groups = args.only or list(GROUPS)
    results: dict[str, tuple[BenchResult, float]] = {}
    failed = False
    for g in groups:
        if not args.json:
            print(f"[bench] {g} ...", file=sys.stderr, flush=True)
        res, elapsed = run_group_in_child(g, args.quick)
        failed |= any("failed (exit" in n for n in res.notes)
        results[g] = (res, elapsed)
        if not args.json:
            print(f"\n== {g} ({elapsed:.1f} s)")
            width = max((len(k) for k in res.metrics), default=10)
            for k, v in res.metrics.items():
                print(f"  {k:<{width}}  {format_value(v)}")
            for title, table in res.tables.items():
                print(f"\n  {title}\n" + "\n".join("  " + line for line in table.strip().splitlines()))
            for n in res.notes:
                print(f"  note: {n}")
    if not args.json:
        goals = goal_rows(results)
        if goals:
            print("\n== goals from the issues")
            for g, v, op, t, ok in goals:
                print(f"  {'met ' if ok else 'MISS'}  {g}: {format_value(v)} (target {op} {format_value(t)})")
    if args.json:
        print(json.dumps(merged_metrics(results), indent=2, default=float))
    if args.write_docs:
        cmd = ("visionpos bench" + "".join(f" --only {g}" for g in (args.only or []))
               + (" --quick" if args.quick else ""))
        write_docs(Path(args.write_docs), results, cmd, args.quick)
        print(f"wrote {args.write_docs}", file=sys.stderr)
    return 1 if failed else 0
