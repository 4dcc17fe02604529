"""The demo's summary: the output collector's running statistics of every published pose, in memory that
does not grow, and the summary in words (format_summary).

The demo's summary scores each body's poses against the simulator's truth. Keeping every pose for
that grew the demo by 17 MB a minute; the collector instead buffers the last HOLD_NS of ticks and folds
older ones, BATCH_TICKS at a time, into running sums (`BodyStats`), so an hour-long demo holds what a
minute-long one does.
It reproduces visionpos.analysis.metrics.body_metrics on the same poses: the same truth (sampled
on the summary's 5 ms grid from the window's start and interpolated between its two neighbouring
samples), the same jitter (second differences of consecutive tracked positions, breaking at gaps
over 3x the median interval); the medians and percentiles come from histograms of HIST_BIN_NS
bins, so they agree to within a bin (10 µs).
"""

from __future__ import annotations

import math
import time
from typing import Any, Callable

import numpy as np

from bridge.estimator_delay import EKF2_ARRIVAL_TRAIL_MS
from bridge.fake_autopilot import decode_pose
from visionpos.analysis import metrics as M
from visionpos.geometry.frames import ned_to_world
from visionpos.messages import BodyState
from visionpos.server.sinks import Sink

BATCH_TICKS = 64  # ticks folded into the sums at once: 0.64 s at 100 Hz, ~3 ms on the loop (512 held it ~9 ms)
# the newest ticks stay buffered this long before they are folded: finish(t_stop) can still leave them out (a live
# source that stops before the window's end)
HOLD_NS = 2_000_000_000
TRUTH_STEP_NS = 5_000_000  # the summary's truth grid
SCORE_BATCH = 64  # autopilot poses scored per call of the truth (AutopilotPoses)
HIST_BIN_NS = 10_000  # latency and interval histograms: 10 µs bins ...
HIST_BINS = 20_000  # ... up to 200 ms (larger values counted in the last bin)
LATENCY_QS = (50, 90, 99)


def _hist_percentiles_ns(hist: np.ndarray, qs: tuple[float, ...]) -> list[float]:
    """np.percentile's linear interpolation on samples given as a histogram of HIST_BIN_NS bins (each
    sample at its bin's centre); nan when empty."""
    n = int(hist.sum())
    if n == 0:
        return [float("nan")] * len(qs)
    cum = np.cumsum(hist)
    out = []
    for q in qs:
        rank = q / 100.0 * (n - 1)  # the (fractional) order statistic np.percentile interpolates
        lo, hi = int(np.floor(rank)), int(np.ceil(rank))
        v_lo = np.searchsorted(cum, lo + 1)
        v_hi = np.searchsorted(cum, hi + 1)
        v = v_lo + (rank - lo) * (v_hi - v_lo)
        out.append((float(v) + 0.5) * HIST_BIN_NS)
    return out


class BodyStats:
    """One body's running sums over the tracked poses in the window (see the module docstring)."""

    def __init__(self) -> None:
        self.ticks = 0  # poses in the window, tracked or not
        self.tracked = 0
        self.scored = 0
        self.pos_sq_m2 = 0.0
        self.pos_max_m = float("nan")
        self.rot_sq_rad2 = 0.0
        self.latency_hist = np.zeros(HIST_BINS, np.int64)
        self.interval_hist = np.zeros(HIST_BINS, np.int64)  # between consecutive tracked poses
        # second differences d2 of consecutive tracked positions: sum |d2|^2 by the larger of their two intervals
        self.d2_sq_by_gap = np.zeros(HIST_BINS, np.float64)
        self.d2_n_by_gap = np.zeros(HIST_BINS, np.int64)
        self._tail_t = np.zeros(0, np.int64)  # the last two tracked poses, for the next batch's differences
        self._tail_p = np.zeros((0, 3))

    def add(self, t_ns: np.ndarray, tracked: np.ndarray, pos: np.ndarray, quat: np.ndarray, latency_ns: np.ndarray,
            truth: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray, np.ndarray]]) -> None:
        """Fold a batch in: t_ns (N,) validity times, tracked (N,), pos (N, 3) m, quat (N, 4) xyzw,
        latency_ns (N,) capture -> tick; truth(times) -> (positions, quaternions, valid) at those times."""
        self.ticks += len(t_ns)
        t, p, q, lat = t_ns[tracked], pos[tracked], quat[tracked], latency_ns[tracked]
        self.tracked += len(t)
        if len(t) == 0:
            return
        np.add.at(self.latency_hist, np.clip(lat // HIST_BIN_NS, 0, HIST_BINS - 1), 1)
        tp, tq, valid = truth(t)
        if valid.any():
            pe = M.position_errors(p[valid], tp[valid])
            re = M.rotation_errors(q[valid], tq[valid])
            self.scored += int(valid.sum())
            self.pos_sq_m2 += float(np.sum(pe * pe))
            self.rot_sq_rad2 += float(np.sum(re * re))
            self.pos_max_m = float(np.nanmax([self.pos_max_m, pe.max()]))
        tt = np.concatenate([self._tail_t, t])
        pp = np.concatenate([self._tail_p, p])
        dt = np.diff(tt)
        np.add.at(self.interval_hist, np.clip(dt[len(self._tail_t) - 1 if len(self._tail_t) else 0:] // HIST_BIN_NS,
                                              0, HIST_BINS - 1), 1)
        if len(tt) >= 3:
            d2 = pp[:-2] - 2 * pp[1:-1] + pp[2:]
            gap = np.clip(np.maximum(dt[:-1], dt[1:]) // HIST_BIN_NS, 0, HIST_BINS - 1)
            np.add.at(self.d2_sq_by_gap, gap, np.sum(d2 * d2, axis=1))
            np.add.at(self.d2_n_by_gap, gap, 3)
        self._tail_t, self._tail_p = tt[-2:], pp[-2:]

    def metrics(self, n_ticks: int, span_ns: int) -> dict[str, Any]:
        """The summary's figures (the keys of the demo's per-body summary)."""
        jitter = float("nan")
        if self.tracked >= 3:
            med_ns = _hist_percentiles_ns(self.interval_hist, (50,))[0]
            ok = np.arange(HIST_BINS) * HIST_BIN_NS <= 3 * med_ns
            n = self.d2_n_by_gap[ok].sum()
            if n:
                jitter = float(np.sqrt(self.d2_sq_by_gap[ok].sum() / n / 6.0))
        scored = self.scored
        lat = _hist_percentiles_ns(self.latency_hist, LATENCY_QS)
        return {
            "position_rmse_mm": float(np.sqrt(self.pos_sq_m2 / scored)) * 1e3 if scored else float("nan"),
            "position_max_mm": self.pos_max_m * 1e3 if scored else float("nan"),
            "rotation_rmse_deg": float(np.degrees(np.sqrt(self.rot_sq_rad2 / scored))) if scored else float("nan"),
            "tracked_fraction": self.tracked / n_ticks if n_ticks else 0.0,
            "rate_hz": self.tracked / (span_ns * 1e-9) if span_ns > 0 else 0.0,
            "jitter_mm": jitter * 1e3,
            "pipeline_latency_ms": {f"p{q:g}": v * 1e-6 for q, v in zip(LATENCY_QS, lat)},
        }


class Collector(Sink):
    """The demo's sink: the newest state per body (the live status line) and running statistics of the
    poses published in the streaming window (tick time = the server clock at publish).

    start_window(t_start_ns, t_end_ns, truth) once the streaming's times are known: ticks outside
    [t_start_ns, t_end_ns] are not scored; truth(name, times_ns) -> (positions (N, 3), quaternions (N, 4))
    is the simulator's truth on the server clock. finish(t_stop_ns) folds the rest in (ticks after
    t_stop_ns left out: those of the last HOLD_NS before the call are still buffered) and returns
    {body: BodyStats}.
    """

    def __init__(self, names: list[str], clock: Callable[[], int] = time.monotonic_ns):
        self.names = list(names)
        self.clock = clock
        self.last: dict[str, BodyState] = {}
        self.ticks = 0  # ticks folded in the window
        self.stats_by_body = {n: BodyStats() for n in self.names}
        self._window: tuple[int, int] | None = None
        self._truth: Callable[[str, np.ndarray], tuple[np.ndarray, np.ndarray]] | None = None
        self._buffer: list[tuple[int, list[BodyState]]] = []

    def start_window(self, t_start_ns: int, t_end_ns: int,
                     truth: Callable[[str, np.ndarray], tuple[np.ndarray, np.ndarray]]) -> None:
        self._window, self._truth = (int(t_start_ns), int(t_end_ns)), truth

    def publish(self, states: list[BodyState]) -> None:
        now = self.clock()
        for s in states:
            self.last[s.name] = s
        if self._window is None or not self._window[0] <= now <= self._window[1]:
            return
        self._buffer.append((now, states))
        if len(self._buffer) >= BATCH_TICKS and self._buffer[BATCH_TICKS - 1][0] < now - HOLD_NS:
            self._fold(self._buffer[:BATCH_TICKS])
            del self._buffer[:BATCH_TICKS]

    def finish(self, t_stop_ns: int) -> dict[str, BodyStats]:
        self._fold([(tick, states) for tick, states in self._buffer if tick <= t_stop_ns])
        self._buffer = []
        return self.stats_by_body

    def _truth_on_grid(self, name: str, at_ns: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The truth at at_ns as the summary takes it: sampled every TRUTH_STEP_NS from the window's start up to
        its end, linearly interpolated (slerp) between the two samples around each time."""
        t0, t1 = self._window
        last = t0 + (t1 - t0) // TRUTH_STEP_NS * TRUTH_STEP_NS
        k0 = max(0, (int(at_ns.min()) - t0) // TRUTH_STEP_NS)
        k1 = min((last - t0) // TRUTH_STEP_NS, (int(at_ns.max()) - t0) // TRUTH_STEP_NS + 1)
        if k1 < k0:  # every time is outside the window
            return np.zeros((len(at_ns), 3)), np.tile([0.0, 0, 0, 1], (len(at_ns), 1)), np.zeros(len(at_ns), bool)
        grid = t0 + np.arange(k0, k1 + 1, dtype=np.int64) * TRUTH_STEP_NS
        tp, tq = self._truth(name, grid)
        p, q, valid = M.interpolate_truth(grid, tp, tq, at_ns)
        return p, q, valid & (at_ns >= t0) & (at_ns <= last)

    def _fold(self, rows: list[tuple[int, list[BodyState]]]) -> None:
        if not rows:
            return
        self.ticks += len(rows)
        for name, acc in self.stats_by_body.items():
            mine = [(tick, s) for tick, states in rows for s in states if s.name == name]
            if not mine:
                continue
            acc.add(np.array([s.time_ns for _, s in mine], np.int64), np.array([bool(s.tracked) for _, s in mine]),
                    np.array([s.position for _, s in mine], float).reshape(-1, 3),
                    np.array([s.quaternion for _, s in mine], float).reshape(-1, 4),
                    np.array([tick - s.capture_ns for tick, s in mine], np.int64),
                    lambda at, name=name: self._truth_on_grid(name, at))


class AutopilotPoses:
    """Running statistics of the pose messages one fake autopilot received (its on_pose callback, called on
    its own thread, is the only writer; read them after it closed): how many, the largest gap between two
    arrivals, the stamp-to-arrival latency (a histogram of HIST_BIN_NS bins; only for stamps on the server's
    clock: boot_stamps) and, once score() set the window and the truth, the position error of every pose
    stamped inside it. The demo kept every message for these before, which grew it by about 6 MB a minute.
    The positions are scored SCORE_BATCH at a time, in one call of the truth: one call per pose cost the
    autopilot's thread a millisecond each, on the GIL the server's loop needs.

    truth(times_ns) -> positions (N, 3) m in the world frame at those server-clock times.
    """

    def __init__(self, boot_stamps: bool) -> None:
        self.boot_stamps = boot_stamps
        self.n = 0
        self.max_gap_ns = 0
        self.latency_hist = np.zeros(HIST_BINS, np.int64)
        self.err_sq_mm2 = 0.0
        self.err_max_mm = float("nan")
        self.scored = 0
        self._last_recv_ns: int | None = None
        self._window: tuple[int, int] | None = None
        self._truth: Callable[[np.ndarray], np.ndarray] | None = None
        self._stamps_ns: list[int] = []  # poses waiting to be scored: their stamps and positions (NED, m)
        self._positions: list[np.ndarray] = []

    def score(self, t_start_ns: int, t_stop_ns: int, truth: Callable[[np.ndarray], np.ndarray]) -> None:
        """Score the positions of poses stamped in [t_start_ns, t_stop_ns] against truth from now on."""
        self._truth, self._window = truth, (int(t_start_ns), int(t_stop_ns))

    def on_pose(self, r: Any) -> None:
        """One pose message (bridge.fake_autopilot.Received) as the autopilot got it."""
        self.n += 1
        if self._last_recv_ns is not None:
            self.max_gap_ns = max(self.max_gap_ns, r.recv_ns - self._last_recv_ns)
        self._last_recv_ns = r.recv_ns
        if not self.boot_stamps:
            return
        pose = decode_pose(r)
        stamp_ns = int(pose["usec"]) * 1000
        self.latency_hist[min(max(r.recv_ns - stamp_ns, 0) // HIST_BIN_NS, HIST_BINS - 1)] += 1
        if self._window is not None and self._window[0] <= stamp_ns <= self._window[1]:
            self._stamps_ns.append(stamp_ns)
            self._positions.append(pose["position_ned"])
            if len(self._stamps_ns) >= SCORE_BATCH:
                self.flush()

    def flush(self) -> None:
        """Score the poses still waiting (the summary calls it once the autopilot has closed)."""
        if not self._stamps_ns:
            return
        world = ned_to_world(np.array(self._positions, float).reshape(-1, 3))
        e_mm = np.linalg.norm(world - self._truth(np.array(self._stamps_ns, np.int64)), axis=1) * 1e3
        self._stamps_ns, self._positions = [], []
        self.err_sq_mm2 += float(np.sum(e_mm * e_mm))
        self.err_max_mm = float(e_mm.max()) if self.scored == 0 else max(self.err_max_mm, float(e_mm.max()))
        self.scored += len(e_mm)

    def position_rmse_mm(self) -> float:
        return float(np.sqrt(self.err_sq_mm2 / self.scored)) if self.scored else float("nan")


def latency_percentiles_ms(tallies: list[AutopilotPoses], qs: tuple[float, ...]) -> dict[str, float]:
    """{'p50': ms, ...}: the stamp-to-arrival latency percentiles over every autopilot's poses together."""
    hist = sum((t.latency_hist for t in tallies), np.zeros(HIST_BINS, np.int64))
    out = {f"p{q:g}": v * 1e-6 for q, v in zip(qs, _hist_percentiles_ns(hist, qs))}
    n = int(hist.sum())
    out["mean"] = float((hist * (np.arange(HIST_BINS) + 0.5)).sum() / n * HIST_BIN_NS * 1e-6) if n else math.nan
    return out


def _plural(n: int, word: str) -> str:
    return f"{n} {word}" if n == 1 else f"{n} {word}s"


def format_summary(s: dict[str, Any]) -> str:
    """The summary in words: every figure says what it measures and in which unit."""
    fmt = lambda v, spec=".2f": "-" if v is None else format(v, spec)  # noqa: E731
    fps = ", ".join(f"camera {x['camera_id']} {x['fps']:.0f}" for x in s["stations"])
    lines = [
        f"visionpos demo on {s['scenario']} (session {s['session']}, seed {s['seed']}): "
        f"{_plural(len(s['stations']), 'simulated station')} streamed {s['duration_s']:.1f} s of camera frames "
        f"(frames per second: {fps}); the server published {s['ticks']} pose updates",
    ]
    for b in s["bodies"]:
        lat = b.get("latency_ms") or {}
        tracked = b["tracked_fraction"]
        lines += [
            f"{b['name']}:",
            f"  tracked in {fmt(None if tracked is None else 100 * tracked, '.1f')}% of the pose updates, "
            f"at {fmt(b['rate_hz'], '.1f')} poses per second",
            f"  position error against the simulator's truth: RMS {fmt(b['position_rmse_mm'])} mm, "
            f"largest {fmt(b['position_max_mm'])} mm; rotation error RMS {fmt(b['rotation_rmse_deg'], '.3f')} deg",
        ]
        if "mavlink_rate_hz" in b:
            lines.append(f"  MAVLink: {fmt(b['mavlink_rate_hz'], '.1f')} pose messages per second reached the "
                         f"autopilot; position error of what it got: RMS {fmt(b.get('mavlink_position_rmse_mm'))} mm")
            lines.append(f"  latency from camera exposure to MAVLink send: median {fmt(lat.get('p50'))} ms, "
                         f"99th percentile {fmt(lat.get('p99'))} ms")
        if "autopilot_says" in b:
            a = b["autopilot_says"]
            true = "" if a["true_delay_ms"] is None else f" (its true value {fmt(a['true_delay_ms'], '.1f')} ms)"
            measured = (f"{fmt(a['delay_ms'], '.1f')} ms{true}"
                        if a["delay_ms"] is not None else f"not measured ({a['delay_detail']})")
            lines.append(f"  the autopilot's view: identity check {a['identity']}, EKF {a['ekf']}; "
                         f"capture-to-autopilot delay measured from its gyro {measured}")
    lat = s["latency_ms"]
    server = s["server"]
    shed = server.get("frames_shed")
    lines += [
        f"latency from camera exposure to MAVLink send, all bodies: median {fmt(lat['p50'])} ms, "
        f"99th percentile {fmt(lat['p99'])} ms; from a pose's timestamp to its arrival at the autopilot: "
        f"median {fmt(s['latency_to_autopilot_ms']['p50'])} ms, 2nd percentile "
        f"{fmt(s['latency_to_autopilot_ms'].get('p2'))} ms, mean {fmt(s['latency_to_autopilot_ms'].get('mean'))} ms "
        "(ArduPilot's VISO_DELAY_MS: near the smallest, its jitter correction takes each pose at the smallest delay "
        "of its last 100; PX4's EKF2_EV_DELAY: the mean and "
        f"{EKF2_ARRIVAL_TRAIL_MS['vision_position_estimate'].ms_at_zero:g} ms on VISION_POSITION_ESTIMATE, "
        f"{EKF2_ARRIVAL_TRAIL_MS['odometry'].least_ms:+g} ms on a direct link to "
        f"{EKF2_ARRIVAL_TRAIL_MS['odometry'].most_ms:+g} ms through a slow one on ODOMETRY, it stamps poses on arrival "
        "without TIMESYNC and follows the mean of their timing errors, by that much more; "
        "docs/autopilot-setup.md section 3)",
        f"server: accepted {server['frames_accepted']} camera frames"
        + (f" ({shed} not fused: they queued too long)" if shed else "")
        + f", {_plural(server['malformed'] or 0, 'malformed packet')}, "
        f"{_plural(s['late_ticks'] or 0, 'output tick')} late; the demo ran for {s['wall_s']:.1f} s of "
        f"wall-clock time, of which simulating the camera frames took {s['simulate_s']:.1f} s",
    ]
    k = s.get("kernels") or {}
    if k.get("interpreted_at_start"):
        lines.append("the fusion kernels were still being compiled (the first run after installing or updating): "
                     "the fusion ran interpreted " + ("for the whole run" if k.get("interpreted_at_end") else
                                                      "until they were ready")
                     + ", slower, so these figures are not what this host does; the next run uses the compiled "
                     "kernels")
    return "\n".join(lines)
