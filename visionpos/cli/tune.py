"""`visionpos tune`: sweep settings over a recording and rank them (visionpos.analysis.tune)."""

from __future__ import annotations

import argparse
import json
import os

import numpy as np

from visionpos.analysis.tune import check_sweep, grid_points, parse_grid, sweep, table
from visionpos.errors import UsageError


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("log", help="recording (.mcap)")
    p.add_argument("--grid", action="append", required=True, metavar="KEY=V1,V2,...",
                   help="a setting and its values to sweep (repeatable: cartesian product)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="fixed override applied to every trial")
    p.add_argument("--config", help="arena YAML replacing the one stored in the recording")
    p.add_argument("--jobs", type=int, default=1, help="parallel replays (processes); default 1")
    p.add_argument("--json", action="store_true", help="print the ranked results as JSON")


def run(args: argparse.Namespace) -> int:
    grid = parse_grid(args.grid)
    if args.jobs < 1:
        raise UsageError(f"--jobs {args.jobs}: must be >= 1")
    check_sweep(args.log, grid, args.set, args.config)
    jobs = min(args.jobs, os.cpu_count() or 1, len(grid_points(grid)))
    ranked = sweep(args.log, grid, args.set, args.config, jobs=jobs, progress=True)
    if args.json:
        out = [
            {k: (v if not isinstance(v, float) or np.isfinite(v) else None) for k, v in t.__dict__.items()}
            for t in ranked
        ]
        print(json.dumps(out, indent=2))
    else:
        if any(t.has_truth for t in ranked):
            basis = "mean position RMSE (settings that lose tracking last)"
        else:
            basis = "jitter + latency relative to the best (the log has no ground truth)"
        print(f"ranked by {basis}; best first")
        print(table(ranked))
        errors: dict[str, list[str]] = {}
        for t in ranked:
            if t.error:
                errors.setdefault(t.error, []).append(" ".join(f"{k}={v}" for k, v in t.point.items()))
        for err, pts in errors.items():
            print(f"failed ({len(pts)}x, e.g. {pts[0]}): {err}")
    return 1 if all(t.error for t in ranked) else 0
