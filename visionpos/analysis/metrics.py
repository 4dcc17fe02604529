"""Error metrics of estimated trajectories against ground truth, and timing statistics.

Pure functions on numpy arrays (no I/O). Times are int64 ns, positions m,
quaternions scalar-last (x, y, z, w). Used by `demo`, `replay`, `tune` and
the replay benchmark.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
from scipy.spatial.transform import Rotation, Slerp


def interpolate_truth(
    truth_times_ns: np.ndarray, positions: np.ndarray, quaternions: np.ndarray, at_ns: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Ground truth at arbitrary times: linear in position, slerp in rotation.

    truth_times_ns: (T,) int64 strictly increasing; positions: (T, 3);
    quaternions: (T, 4) xyzw; at_ns: (N,) int64.
    Returns (positions (N, 3), quaternions (N, 4), valid (N,) bool); times
    outside [truth_times_ns[0], truth_times_ns[-1]] are not valid (their rows
    hold the nearest end sample) so callers never score extrapolated truth.
    """
    t = np.asarray(truth_times_ns, dtype=np.int64)
    at = np.asarray(at_ns, dtype=np.int64)
    p = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    q = np.asarray(quaternions, dtype=np.float64).reshape(-1, 4)
    if len(t) == 0:
        return np.zeros((len(at), 3)), np.tile([0.0, 0, 0, 1], (len(at), 1)), np.zeros(len(at), bool)
    valid = (at >= t[0]) & (at <= t[-1])
    # relative float seconds keep ns precision over long recordings
    ts = (t - t[0]).astype(np.float64) * 1e-9
    xs = np.clip((at - t[0]).astype(np.float64) * 1e-9, ts[0], ts[-1])
    pos = np.stack([np.interp(xs, ts, p[:, k]) for k in range(3)], axis=1)
    if len(t) == 1:
        quat = np.tile(q[0], (len(at), 1))
    else:
        quat = Slerp(ts, Rotation.from_quat(q))(xs).as_quat()
    return pos, quat, valid


def position_errors(estimated: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """Euclidean position error. estimated, truth: (N, 3) m -> (N,) m."""
    return np.linalg.norm(np.asarray(estimated, float) - np.asarray(truth, float), axis=-1)


def rotation_errors(estimated: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """Geodesic angle between rotations. estimated, truth: (N, 4) xyzw -> (N,) rad in [0, pi].

    Sign-invariant: q and -q are the same rotation.
    """
    a = np.asarray(estimated, float)
    b = np.asarray(truth, float)
    a = a / np.linalg.norm(a, axis=-1, keepdims=True)
    b = b / np.linalg.norm(b, axis=-1, keepdims=True)
    d = np.abs(np.sum(a * b, axis=-1))
    return 2.0 * np.arccos(np.clip(d, 0.0, 1.0))


def rms(x: np.ndarray) -> float:
    """Root mean square of (N,) values; nan when empty."""
    x = np.asarray(x, float)
    return float(np.sqrt(np.mean(x * x))) if x.size else float("nan")


def percentiles_ms(latencies_ns: np.ndarray, qs: tuple[float, ...] = (50, 90, 99)) -> dict[str, float]:
    """(N,) latencies in ns -> {'p50': ms, ...}; nan when empty."""
    x = np.asarray(latencies_ns, dtype=np.float64) * 1e-6
    if x.size == 0:
        return {f"p{q:g}": float("nan") for q in qs}
    vals = np.percentile(x, qs)
    return {f"p{q:g}": float(v) for q, v in zip(qs, vals)}


def position_jitter(times_ns: np.ndarray, positions: np.ndarray) -> float:
    """High-frequency position noise without ground truth, m.

    Uses second differences of consecutive samples: for a smooth trajectory
    sampled finely, p[k-1] - 2 p[k] + p[k+1] is almost all noise, and for
    white noise of std s per axis its variance is 6 s^2. Returns the per-axis
    noise std estimate sqrt(mean(d2^2) / 6) over the three axes pooled.
    Samples further apart than 3x the median interval (dropouts) break the
    sequence so a gap is not counted as noise.
    times_ns: (N,) int64; positions: (N, 3).
    """
    t = np.asarray(times_ns, dtype=np.int64)
    p = np.asarray(positions, float).reshape(-1, 3)
    if len(t) < 3:
        return float("nan")
    dt = np.diff(t)
    med = np.median(dt)
    ok = (dt[:-1] <= 3 * med) & (dt[1:] <= 3 * med)
    d2 = p[:-2] - 2 * p[1:-1] + p[2:]
    d2 = d2[ok]
    if len(d2) == 0:
        return float("nan")
    return float(np.sqrt(np.mean(d2 * d2) / 6.0))


def rate_hz(times_ns: np.ndarray, span_ns: int | None = None) -> float:
    """Mean rate of events at times_ns (N,) over span_ns (default: first to last)."""
    t = np.asarray(times_ns, dtype=np.int64)
    if span_ns is None:
        if len(t) < 2:
            return 0.0
        return float((len(t) - 1) / ((t[-1] - t[0]) * 1e-9)) if t[-1] > t[0] else 0.0
    return float(len(t) / (span_ns * 1e-9)) if span_ns > 0 else 0.0


@dataclass
class BodyMetrics:
    """Summary of one body's output stream (JSON-friendly via as_dict)."""

    name: str
    n_outputs: int
    tracked_fraction: float
    rate_hz: float
    position_rmse_mm: float
    position_max_mm: float
    rotation_rmse_deg: float
    position_jitter_mm: float
    latency_ms: dict[str, float]
    n_scored: int

    def as_dict(self) -> dict:
        return asdict(self)


def body_metrics(
    name: str,
    times_ns: np.ndarray,
    tracked: np.ndarray,
    positions: np.ndarray,
    quaternions: np.ndarray,
    latencies_ns: np.ndarray | None = None,
    truth: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
    n_ticks: int | None = None,
    span_ns: int | None = None,
) -> BodyMetrics:
    """Metrics of one body's outputs.

    times_ns: (N,) output validity times; tracked: (N,) bool; positions (N, 3);
    quaternions (N, 4); latencies_ns: (N,) capture -> output (only tracked rows
    are used); truth: (times (T,), positions (T, 3), quaternions (T, 4)) or None.
    n_ticks: number of output opportunities (default N) for tracked_fraction;
    span_ns: duration for rate_hz (default first to last output).
    Errors are over tracked rows whose time lies inside the truth's time span.
    """
    t = np.asarray(times_ns, dtype=np.int64)
    trk = np.asarray(tracked, bool)
    p = np.asarray(positions, float).reshape(-1, 3)
    q = np.asarray(quaternions, float).reshape(-1, 4)
    denom = n_ticks if n_ticks else len(t)
    frac = float(trk.sum() / denom) if denom else 0.0
    tt = t[trk]
    pos_rmse = pos_max = rot_rmse = float("nan")
    n_scored = 0
    if truth is not None and trk.any():
        tp, tq, valid = interpolate_truth(truth[0], truth[1], truth[2], tt)
        if valid.any():
            pe = position_errors(p[trk][valid], tp[valid])
            re = rotation_errors(q[trk][valid], tq[valid])
            pos_rmse, pos_max, rot_rmse = rms(pe) * 1e3, float(pe.max()) * 1e3, float(np.degrees(rms(re)))
            n_scored = int(valid.sum())
    lat = np.asarray(latencies_ns if latencies_ns is not None else [], dtype=np.int64)
    lat = lat[trk] if len(lat) == len(t) else lat
    return BodyMetrics(
        name=name,
        n_outputs=len(t),
        tracked_fraction=frac,
        rate_hz=rate_hz(tt, span_ns),
        position_rmse_mm=pos_rmse,
        position_max_mm=pos_max,
        rotation_rmse_deg=rot_rmse,
        position_jitter_mm=position_jitter(tt, p[trk]) * 1e3,
        latency_ms=percentiles_ms(lat),
        n_scored=n_scored,
    )


def format_table(rows: list[dict], columns: list[tuple[str, str, str]]) -> str:
    """Plain-text table. columns: (key, header, format spec like '.2f'); nan shows as '-'."""
    heads = [h for _, h, _ in columns]
    cells = []
    for r in rows:
        line = []
        for key, _, fmt in columns:
            v = r.get(key)
            if isinstance(v, float) and not np.isfinite(v):
                line.append("-")
            elif fmt and isinstance(v, (int, float)) and not isinstance(v, bool):
                line.append(format(v, fmt))
            else:
                line.append(str(v))
        cells.append(line)
    widths = [max([len(h)] + [len(c[i]) for c in cells]) for i, h in enumerate(heads)]
    out = ["  ".join(h.ljust(w) for h, w in zip(heads, widths)), "  ".join("-" * w for w in widths)]
    out += ["  ".join(c.ljust(w) for c, w in zip(line, widths)) for line in cells]
    return "\n".join(out)
