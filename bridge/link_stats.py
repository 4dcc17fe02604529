"""What a vehicle's link reports about itself: latency percentiles and the autopilot delay to set.

LatencyRing keeps the last LATENCY_SAMPLES latencies (ns) of a link; percentiles_ms reads them;
delay_advice turns a VehicleLink.stats() dict into the line the bridge prints every report_interval_s.
"""

from __future__ import annotations

import numpy as np

from bridge.estimator_delay import ekf2_arrival_trail_ms

LATENCY_SAMPLES = 4096


def fmt_addr(addr: tuple | None) -> str:
    """(host, port) -> 'host:port'; '?' for None."""
    return ":".join(str(x) for x in addr) if addr else "?"


def percentiles_ms(samples: np.ndarray, qs: tuple[float, ...]) -> tuple[float, ...]:
    """Percentiles qs (0-100) of latencies samples (ns) in ms, numpy's linear interpolation; NaN when empty.
    One sort for all of them: np.percentile costs ~35 us a call, and the console reads these at 2 Hz."""
    n = len(samples)
    if not n:
        return tuple(float("nan") for _ in qs)
    s = np.sort(samples)
    out = []
    for q in qs:
        h = (n - 1) * q / 100.0
        i = int(h)
        lo = float(s[i])
        out.append((lo + (float(s[min(i + 1, n - 1)]) - lo) * (h - i)) * 1e-6)
    return tuple(out)


class LatencyRing:
    """Last LATENCY_SAMPLES latencies (ns) for percentiles."""

    def __init__(self):
        self.buf = np.zeros(LATENCY_SAMPLES, dtype=np.int64)
        self.n = 0

    def add(self, ns: int) -> None:
        self.buf[self.n % LATENCY_SAMPLES] = ns
        self.n += 1

    def values(self) -> np.ndarray:
        """The kept latencies, oldest first."""
        if self.n <= LATENCY_SAMPLES:
            return self.buf[: self.n].copy()
        return np.roll(self.buf, -(self.n % LATENCY_SAMPLES))


def delay_advice(stats: dict) -> str:
    """One line per vehicle: measured latencies and the autopilot delay to set (the age of a
    pose's stamp when it is sent: what the autopilot must wait for)."""
    p50, p99 = stats["latency_capture_ms_p50"], stats["latency_capture_ms_p99"]
    if not np.isfinite(p50):
        return f"{stats['body']} (sysid {stats['sysid']}): no pose sent yet"
    age = stats["latency_stamp_ms_p50"]
    # estimator_delay.py: why each
    mean = stats.get("latency_stamp_ms_mean", age)
    trail = ekf2_arrival_trail_ms(stats.get("message", "vision_position_estimate"), mean)
    d = round(mean + trail, 1)
    low = int(round(stats.get("latency_stamp_ms_jitter_min", age)))
    if stats.get("delay_ms") is not None:
        return (f"{stats['body']} (sysid {stats['sysid']}): capture->send latency p50 {p50:.1f} ms, p99 {p99:.1f} ms; "
                f"{stats['delay_advice']}")
    return (
        f"{stats['body']} (sysid {stats['sysid']}): capture->send latency p50 {p50:.1f} ms, p99 {p99:.1f} ms; "
        f"pose stamp->send p50 {age:.1f} ms (bridge adds p50 {stats['latency_bridge_ms_p50']:.2f} ms) -> "
        f"ArduPilot VISO_DELAY_MS={low} (the smallest of each 100 poses + link latency); PX4 EKF2_EV_DELAY={d} "
        f"(the mean {trail:+.2f} ms + link latency) without TIMESYNC, "
        f"~0 with TIMESYNC converged"
    )
