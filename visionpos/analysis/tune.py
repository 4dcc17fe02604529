"""`visionpos tune`: sweep settings over a recording and rank them.

Each point of the cartesian grid is one deterministic replay with `--set`
overrides. With ground truth in the log, settings rank by mean position RMSE
over bodies (settings that lose tracking rank after those that keep it);
without truth, by position jitter plus pipeline latency, each relative to the
best in the sweep.
"""

from __future__ import annotations

import itertools
import json
import sys
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence, TextIO

import numpy as np
import yaml

from visionpos.analysis import metrics as M
from visionpos.config.arena import ConfigError
from visionpos.errors import UsageError

# a setting keeps its rank by error only if it tracks at least this share of
# what the best-tracking setting of the sweep tracks
TRACKING_KEEP = 0.9

# the arena sections a replay reads: a grid key elsewhere could not change any trial
REPLAYED_SECTIONS = ("fusion", "server", "cameras", "bodies")


def parse_grid(items: list[str]) -> list[tuple[str, list[Any]]]:
    """['fusion.a=1,2', 'b=x,y'] -> [('fusion.a', [1, 2]), ('b', ['x', 'y'])] (values parsed as YAML)."""
    out: list[tuple[str, list[Any]]] = []
    for item in items:
        key, sep, values = item.partition("=")
        key = key.strip()
        if not sep or not key or not values.strip():
            raise ConfigError(
                "--grid", item, "expected key=v1,v2,..., e.g. --grid fusion.time_alignment=naive,motion_compensated"
            )
        vals = [yaml.safe_load(v.strip()) for v in values.split(",") if v.strip()]
        if any(k == key for k, _ in out):
            raise ConfigError("--grid", key, "given twice; list all its values in one --grid")
        out.append((key, vals))
    return out


def grid_points(grid: list[tuple[str, list[Any]]]) -> list[dict[str, Any]]:
    """Cartesian product, first key varying slowest."""
    keys = [k for k, _ in grid]
    return [dict(zip(keys, combo)) for combo in itertools.product(*[v for _, v in grid])]


def _override_strings(point: dict[str, Any]) -> list[str]:
    # json text is valid YAML and round-trips numbers, booleans and strings exactly
    return [f"{k}={json.dumps(v)}" for k, v in point.items()]


@dataclass
class TrialResult:
    point: dict[str, Any]
    has_truth: bool
    position_rmse_mm: float
    rotation_rmse_deg: float
    tracked_fraction: float
    jitter_mm: float
    latency_p50_ms: float
    latency_p99_ms: float
    wall_s: float
    error: str | None = None
    views_fraction: float = 0.0  # share of tracked outputs kept by single-camera updates (occlusion)


def _nanmean(xs: list[float]) -> float:
    a = np.asarray(xs, float)
    a = a[np.isfinite(a)]
    return float(a.mean()) if a.size else float("nan")


def run_trial(log: str, point: dict[str, Any], base_overrides: list[str], config: str | None) -> TrialResult:
    """One replay of the log with the grid point's overrides; summarised over bodies."""
    from visionpos.analysis.replay import replay_log, views_fraction

    try:
        res = replay_log(log, config, list(base_overrides) + _override_strings(point))
    except (ValueError, KeyError, TypeError) as e:  # a bad value for a setting: report it in the table
        nan = float("nan")
        return TrialResult(point, False, nan, nan, 0.0, nan, nan, nan, 0.0, error=str(e))
    ms = res.metrics()
    lat = np.concatenate([b.latency_ns[b.tracked] for b in res.bodies.values()] or [np.zeros(0, np.int64)])
    pct = M.percentiles_ms(lat)
    return TrialResult(
        point=point,
        has_truth=bool(res.truth),
        position_rmse_mm=_nanmean([m.position_rmse_mm for m in ms]),
        rotation_rmse_deg=_nanmean([m.rotation_rmse_deg for m in ms]),
        tracked_fraction=_nanmean([m.tracked_fraction for m in ms]) if ms else 0.0,
        jitter_mm=_nanmean([m.position_jitter_mm for m in ms]),
        latency_p50_ms=pct["p50"],
        latency_p99_ms=pct["p99"],
        wall_s=res.wall_s,
        views_fraction=_nanmean([views_fraction(b) for b in res.bodies.values()]) if res.bodies else 0.0,
    )


def rank(trials: list[TrialResult]) -> list[TrialResult]:
    """Best first. Truth: position RMSE among settings that keep tracking; else jitter + latency."""
    ok = [t for t in trials if t.error is None]
    best_tracked = max((t.tracked_fraction for t in ok), default=0.0)
    has_truth = any(t.has_truth for t in ok)
    min_jit = min((t.jitter_mm for t in ok if np.isfinite(t.jitter_mm) and t.jitter_mm > 0), default=1.0)
    min_lat = min((t.latency_p50_ms for t in ok if np.isfinite(t.latency_p50_ms) and t.latency_p50_ms > 0), default=1.0)

    def key(t: TrialResult) -> tuple:
        if t.error is not None:
            return (2, 0.0, 0.0)
        lost = t.tracked_fraction < TRACKING_KEEP * best_tracked
        if has_truth:
            score = t.position_rmse_mm
        else:
            score = t.jitter_mm / min_jit + t.latency_p50_ms / min_lat
        score = score if np.isfinite(score) else float("inf")
        return (int(lost), score, -t.tracked_fraction)

    return sorted(trials, key=key)


class Progress:
    """A one-line text progress bar on a stream (no dependency)."""

    def __init__(self, total: int, stream: TextIO | None = None, width: int = 30):
        self.total, self.stream, self.width = total, stream or sys.stderr, width
        self.done = 0
        self.t0 = time.perf_counter()
        self.tty = self.stream.isatty()
        self.draw("")

    def draw(self, label: str) -> None:
        frac = self.done / self.total if self.total else 1.0
        fill = int(round(frac * self.width))
        el = time.perf_counter() - self.t0
        eta = el / self.done * (self.total - self.done) if self.done else float("nan")
        eta_s = f"{eta:5.0f}s" if np.isfinite(eta) else "    ?"
        line = f"tune [{'#' * fill}{'.' * (self.width - fill)}] {self.done}/{self.total} {el:5.0f}s eta {eta_s} {label}"
        if self.tty:
            self.stream.write("\r" + line[:150].ljust(150))
        else:
            self.stream.write(line + "\n")
        self.stream.flush()

    def step(self, label: str = "") -> None:
        self.done += 1
        self.draw(label)

    def close(self) -> None:
        if self.tty:
            self.stream.write("\n")
            self.stream.flush()


def check_sweep(log: str, grid: list[tuple[str, list[Any]]], base_overrides: Sequence[str] = (),
                config: str | None = None) -> None:
    """Fail fast, before any trial: the recording opens, and every grid key is a setting.

    Each key is tried with each of its values on the recording's arena (or `config`), through
    the same config, fusion and server validation a replay does; a key none of whose values
    validate (an unknown key, a typo) raises a UsageError. A key with some bad values is left
    to the sweep, which reports those trials as failed.
    """
    from visionpos.analysis.replay import load_settings
    from visionpos.fusion.settings import parse_fusion
    from visionpos.recording import RecordingReader
    from visionpos.server.settings import ServerSettings

    if not Path(log).is_file():
        raise UsageError(f"{log}: no such recording; make one with `visionpos sim --out` or `visionpos record --out`")
    recorded = RecordingReader(log).config

    def validate(overrides: list[str]) -> None:
        arena = load_settings(recorded, config, overrides)
        parse_fusion(arena)
        ServerSettings.for_replay(arena)

    validate(list(base_overrides))
    for key, values in grid:
        if key.split(".")[0] not in REPLAYED_SECTIONS:
            raise UsageError(f"--grid {key}: not a setting a replay uses; sweep keys of the sections "
                             f"{', '.join(REPLAYED_SECTIONS)} (e.g. fusion.time_alignment=naive,motion_compensated)")
        errors = []
        for v in values:
            try:
                validate(list(base_overrides) + _override_strings({key: v}))
            except (ValueError, KeyError, TypeError) as e:
                errors.append(e)
        if errors and len(errors) == len(values):
            first = errors[0]
            detail = first.message if isinstance(first, ConfigError) and first.source == "--set" else first
            raise UsageError(f"--grid {key}: {detail}")


def sweep(
    log: str,
    grid: list[tuple[str, list[Any]]],
    base_overrides: list[str] = (),
    config: str | None = None,
    jobs: int = 1,
    progress: bool = True,
) -> list[TrialResult]:
    """Run every grid point (in `jobs` processes) and return them ranked, best first."""
    points = grid_points(grid)
    bar = Progress(len(points)) if progress else None
    results: list[TrialResult] = []
    label = lambda p: " ".join(f"{k.split('.')[-1]}={v}" for k, v in p.items())  # noqa: E731
    if jobs <= 1:
        for p in points:
            results.append(run_trial(log, p, list(base_overrides), config))
            if bar:
                bar.step(label(p))
    else:
        with ProcessPoolExecutor(max_workers=jobs) as ex:
            futs = {ex.submit(run_trial, log, p, list(base_overrides), config): p for p in points}
            for f in as_completed(futs):
                results.append(f.result())
                if bar:
                    bar.step(label(futs[f]))
    if bar:
        bar.close()
    # completion order differs between runs with jobs > 1: restore grid order before ranking
    order = {json.dumps(p, sort_keys=True): i for i, p in enumerate(points)}
    results.sort(key=lambda t: order[json.dumps(t.point, sort_keys=True)])
    return rank(results)


def table(ranked: list[TrialResult]) -> str:
    keys = list(ranked[0].point) if ranked else []
    rows = []
    for i, t in enumerate(ranked, 1):
        r: dict[str, Any] = {"rank": i, **{k: t.point[k] for k in keys}}
        r.update(
            rmse=t.position_rmse_mm,
            rot=t.rotation_rmse_deg,
            tracked=t.tracked_fraction,
            views=t.views_fraction,
            jitter=t.jitter_mm,
            p50=t.latency_p50_ms,
            p99=t.latency_p99_ms,
            note="failed (see below)" if t.error else "",
        )
        rows.append(r)
    truth = any(t.has_truth for t in ranked)
    cols = [("rank", "rank", "")] + [(k, k, "") for k in keys]
    if truth:
        cols += [("rmse", "pos RMSE mm", ".2f"), ("rot", "rot RMSE deg", ".3f")]
    cols += [
        ("tracked", "tracked", ".3f"),
        ("views", "single-view", ".3f"),
        ("jitter", "jitter mm", ".3f"),
        ("p50", "lat p50 ms", ".2f"),
        ("p99", "lat p99 ms", ".2f"),
        ("note", "note", ""),
    ]
    return M.format_table(rows, cols)
