"""Station clock synchronisation against the fusion server (NTP-style).

Each exchange gives four timestamps: t1 station send, t2 server receive,
t3 server send (server clock), t4 station receive. Then

    offset = ((t2 - t1) + (t3 - t4)) / 2      server clock - station clock
    delay  = (t4 - t1) - (t3 - t2)            round trip on the wire

The offset of one exchange is wrong by up to delay/2 (path asymmetry and
queueing), so the estimator keeps a window of exchanges, trusts the
lowest-delay ones, and fits offset = a + b (t - t_ref) with a robust line
(b = drift). `ClockSync` adds the request/reply bookkeeping; the socket I/O
is the agent's.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from visionpos.protocol import SyncReply, SyncRequest


@dataclass(frozen=True)
class ClockEstimate:
    """offset_ns at ref_ns (station clock) and drift (server - station rate, ppm).
    uncertainty_ns: 1-sigma of the offset near the newest samples."""

    offset_ns: int
    ref_ns: int
    drift_ppm: float
    uncertainty_ns: float
    samples: int

    def offset_at(self, station_ns: int) -> int:
        """Offset (server - station) at station clock station_ns, with drift."""
        return self.offset_ns + int(round(self.drift_ppm * 1e-6 * (station_ns - self.ref_ns)))

    def to_server(self, station_ns: int) -> int:
        """Station clock time -> server clock time (int64 ns)."""
        return int(station_ns) + self.offset_at(station_ns)


def exchange_offset_delay(t1: int, t2: int, t3: int, t4: int) -> tuple[int, int]:
    """(offset, delay) of one four-timestamp exchange, ns (integer arithmetic,
    so large absolute clocks lose no precision)."""
    offset = ((t2 - t1) + (t3 - t4)) // 2
    delay = (t4 - t1) - (t3 - t2)
    return offset, delay


class ClockEstimator:
    """Offset and drift of the server clock relative to the station clock.

    window: exchanges kept. best_fraction: share of the window (lowest delay)
    used for the fit. min_samples: exchanges before the estimate is valid.
    min_drift_span_s: time span the kept samples must cover before the drift
    is fitted (shorter spans give slope noise, so the drift stays 0 / last).
    """

    def __init__(
        self,
        window: int = 64,
        best_fraction: float = 0.5,
        min_samples: int = 4,
        min_drift_span_s: float = 10.0,
        max_delay_ns: int = 200_000_000,
    ):
        self.window = window
        self.best_fraction = best_fraction
        self.min_samples = min_samples
        self.min_drift_span_ns = int(min_drift_span_s * 1e9)
        self.max_delay_ns = max_delay_ns
        self.tau_fraction = 0.25
        self._samples: deque[tuple[int, int, int]] = deque(maxlen=window)  # (t_mid, offset, delay)
        self._estimate: ClockEstimate | None = None
        self.rejected = 0

    def add(self, t1: int, t2: int, t3: int, t4: int) -> bool:
        """Add one exchange; returns False (and counts it) when implausible:
        negative delay (clocks stepped) or delay over max_delay_ns."""
        offset, delay = exchange_offset_delay(int(t1), int(t2), int(t3), int(t4))
        if delay < 0 or delay > self.max_delay_ns or t3 < t2:
            self.rejected += 1
            return False
        self._samples.append(((int(t1) + int(t4)) // 2, offset, delay))
        self._estimate = self._fit()
        return True

    @property
    def estimate(self) -> ClockEstimate | None:
        """The current estimate, None before min_samples exchanges."""
        return self._estimate

    @property
    def valid(self) -> bool:
        return self._estimate is not None

    def reset(self) -> None:
        """Forget all samples (the server restarted: its clock is a new one)."""
        self._samples.clear()
        self._estimate = None

    def _fit(self) -> ClockEstimate | None:
        n = len(self._samples)
        if n < self.min_samples:
            return None
        s = np.array(self._samples, dtype=np.int64)  # (n, 3)
        # lowest-delay samples carry the least asymmetry error
        k = max(self.min_samples, int(math.ceil(self.best_fraction * n)))
        best = s[np.argsort(s[:, 2], kind="stable")[:k]]
        ref_t = int(s[-1, 0])
        ref_off = int(best[0, 1])
        t = (best[:, 0] - ref_t).astype(np.float64)  # ns relative, exact in float64
        y = (best[:, 1] - ref_off).astype(np.float64)
        d = best[:, 2].astype(np.float64)
        dmin = float(d.min())
        # weight by closeness to the best delay: queueing adds error ~ (d - dmin) / 2
        w = 1.0 / (1.0 + ((d - dmin) / max(self.tau_fraction * dmin, 10_000.0)) ** 2)
        span = float(t.max() - t.min())
        fit_drift = span >= self.min_drift_span_ns and k >= 6
        slope = 0.0
        if fit_drift:
            slope, icpt = _robust_line(t, y, w)
        else:
            prev = self._estimate
            slope = prev.drift_ppm * 1e-6 if prev is not None else 0.0
            icpt = _weighted_median(y - slope * t, w)
        resid = y - (icpt + slope * t)
        mad = float(np.median(np.abs(resid - np.median(resid))))
        scatter = 1.4826 * mad / math.sqrt(k)
        # asymmetry bound of the best exchange, as a uniform +-dmin/2 error
        asym = dmin / (2.0 * math.sqrt(3.0))
        unc = math.sqrt(scatter**2 + asym**2)
        return ClockEstimate(ref_off + int(round(icpt)), ref_t, slope * 1e6, unc, n)


def _weighted_median(v: np.ndarray, w: np.ndarray) -> float:
    o = np.argsort(v)
    cw = np.cumsum(w[o])
    return float(v[o][np.searchsorted(cw, cw[-1] / 2.0)])


def _robust_line(t: np.ndarray, y: np.ndarray, w: np.ndarray, iters: int = 3) -> tuple[float, float]:
    """Weighted least-squares line y = a + b t with iterative outlier
    down-weighting (Tukey-like, 3 MAD). t, y, w: (k,). Returns (b, a)."""
    ww = w.copy()
    b = a = 0.0
    for _ in range(iters):
        sw = ww.sum()
        tm, ym = (ww * t).sum() / sw, (ww * y).sum() / sw
        var = (ww * (t - tm) ** 2).sum()
        b = (ww * (t - tm) * (y - ym)).sum() / var if var > 0 else 0.0
        a = ym - b * tm
        r = y - (a + b * t)
        s = 1.4826 * float(np.median(np.abs(r))) + 1.0
        ww = w * (np.abs(r) <= 3.0 * s)
        if ww.sum() < 3:
            break
    return float(b), float(a)


class ClockSync:
    """Request/reply bookkeeping around a ClockEstimator (no I/O).

    request(now_ns) -> SyncRequest to send; reply(msg, t4_ns) feeds matching
    replies to the estimator. Burst of `burst` requests at `burst_interval_s`,
    then one every `interval_s`. jump_ns: a change of the estimate by more
    than this between frames is reported as a resync (FLAG_RESYNC).
    """

    def __init__(
        self,
        station_id: int,
        camera_id: int,
        estimator: ClockEstimator | None = None,
        interval_s: float = 2.0,
        burst: int = 8,
        burst_interval_s: float = 0.1,
        jump_ns: int = 1_000_000,
    ):
        self.station_id, self.camera_id = station_id, camera_id
        self.estimator = estimator or ClockEstimator()
        self.interval_ns = int(interval_s * 1e9)
        self.burst = burst
        self.burst_interval_ns = int(burst_interval_s * 1e9)
        self.jump_ns = jump_ns
        self._seq = 0
        self._outstanding: dict[int, int] = {}  # seq -> t1
        self._last_sent: int | None = None
        self._accepted = 0

    def due(self, now_ns: int) -> bool:
        if self._last_sent is None:
            return True
        gap = self.burst_interval_ns if self._accepted < self.burst else self.interval_ns
        return now_ns - self._last_sent >= gap

    def request(self, now_ns: int, counter: int | None = None, session: int = 0) -> SyncRequest:
        """The next request, t1 = now_ns. counter: the session's control counter (stations/session.py);
        None numbers requests here (tests, tools)."""
        if counter is None:
            self._seq = (self._seq + 1) & 0xFFFFFFFF
            counter = self._seq
        self._outstanding[counter] = int(now_ns)
        if len(self._outstanding) > 16:  # lost replies: forget the oldest
            self._outstanding.pop(next(iter(self._outstanding)))
        self._last_sent = int(now_ns)
        return SyncRequest(self.station_id, self.camera_id, int(now_ns), counter, session)

    def reply(self, msg: SyncReply, t4_ns: int) -> bool:
        """Feed a reply received at station time t4_ns; False if it answers no
        outstanding request (late, duplicate or forged) or is implausible."""
        t1 = self._outstanding.get(msg.echo)
        if t1 is None or t1 != msg.t1_ns:
            return False
        del self._outstanding[msg.echo]
        ok = self.estimator.add(t1, msg.t2_ns, msg.t3_ns, t4_ns)
        self._accepted += ok
        return ok

    def reset(self) -> None:
        """New server (restart): forget samples and start a new burst."""
        self.estimator.reset()
        self._outstanding.clear()
        self._accepted = 0
        self._last_sent = None
