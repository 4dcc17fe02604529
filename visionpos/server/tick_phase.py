"""Where in the frame period the output tick falls (server.tick_phase_lock).

The output tick runs on its own clock at server.output_rate_hz; the cameras run on theirs. Unsynchronised
cameras at one rate still arrive in a pattern that repeats every frame period (their phases are fixed), often
close together. The newest frame a tick carries is then as old as the time from that pattern's last arrival to
the tick, plus the frame's latency: from about the latency, for a tick just after the arrivals, to a whole frame
period more, for a tick just before them. Which one a server gets is chance (its start). OptiTrack Motive and
Vicon publish each frame as soon as it is solved; a fixed output rate is kept here (the autopilots want evenly
spaced poses), and its phase is moved to just after the arrivals instead.

best_phase_ns is the pure part; TickPhase keeps the arrivals and says when to move.
"""

from __future__ import annotations

from collections import deque

import numpy as np

CANDIDATES = 40  # phases tried per period
WINDOW_NS = 4_000_000_000  # arrivals judged
MIN_ARRIVALS = 50
EVERY_NS = 2_000_000_000  # how often the phase is judged
GAIN_PERIODS = 0.15  # a phase whose age is lower by this share of a period (and by GAIN_MIN_NS) is taken: less
# would follow the jitter of the arrivals, moving the tick back and forth
GAIN_MIN_NS = 1_000_000


def tick_ages_ns(arrival_ns: np.ndarray, capture_ns: np.ndarray, ticks_ns: np.ndarray) -> np.ndarray:
    """The age (ns) at each tick of the newest frame that arrived at or before it: the tick less the latest
    capture time among those frames. arrival_ns, capture_ns: (N,) int64 ns, sorted by arrival; ticks_ns: (T,)
    int64 ns. A tick before the first arrival gets -1."""
    newest = np.maximum.accumulate(capture_ns)
    i = np.searchsorted(arrival_ns, ticks_ns, side="right") - 1
    return np.where(i >= 0, ticks_ns - newest[np.maximum(i, 0)], -1)


def best_phase_ns(arrival_ns: np.ndarray, capture_ns: np.ndarray, period_ns: int,
                  candidates: int = CANDIDATES) -> tuple[int, np.ndarray]:
    """The tick phase (ns in [0, period_ns), of the tick times modulo period_ns) whose ticks would carry the
    youngest frames over these arrivals: (phase, the mean age (ns, float) at the ticks of each candidate phase
    k * period_ns / candidates). The mean, not a high percentile: a stall ages every phase's ticks alike, the
    arrivals' pattern does not. arrival_ns, capture_ns: (N,) int64 ns of the accepted frames, N >= 2, sorted
    by arrival."""
    arrival_ns = np.asarray(arrival_ns, np.int64)
    capture_ns = np.asarray(capture_ns, np.int64)
    first = (int(arrival_ns[0]) // period_ns + 1) * period_ns  # the first whole period after the first arrival
    n_ticks = max(int((int(arrival_ns[-1]) - first) // period_ns), 1)
    phases = np.arange(candidates, dtype=np.int64) * period_ns // candidates
    ticks = first + np.arange(n_ticks, dtype=np.int64)[None, :] * period_ns + phases[:, None]  # (C, T)
    ages = tick_ages_ns(arrival_ns, capture_ns, ticks.reshape(-1)).reshape(ticks.shape).astype(float)
    score = ages.mean(axis=1)
    return int(phases[int(np.argmin(score))]), score


class TickPhase:
    """The server's record of frame arrivals (note: one call per accepted frame) and its judgement of the tick's
    phase (shift: how far to put the next tick off, ns, every EVERY_NS)."""

    def __init__(self, period_ns: int) -> None:
        self.period_ns = int(period_ns)
        self._arrivals: deque[tuple[int, int]] = deque()
        self._next_judged_ns: int | None = None
        self.shifts = 0  # phase moves made

    def note(self, arrival_ns: int, capture_ns: int) -> None:
        """An accepted frame: server clock when it reached the fusion (called in that order), and its capture
        time."""
        self._arrivals.append((arrival_ns, capture_ns))
        while self._arrivals and self._arrivals[0][0] < arrival_ns - WINDOW_NS:
            self._arrivals.popleft()

    def shift_ns(self, now_ns: int, next_tick_ns: int) -> int:
        """How much later than planned the next tick (next_tick_ns) should run: 0, or the move (< a period) to
        the phase whose ticks carry younger frames, when it saves at least GAIN_PERIODS of a period. Only ever
        later: one interval grows, none shrinks (poses never closer than the output period)."""
        if self._next_judged_ns is None:
            self._next_judged_ns = now_ns + EVERY_NS
        if now_ns < self._next_judged_ns or len(self._arrivals) < MIN_ARRIVALS:
            return 0
        self._next_judged_ns = now_ns + EVERY_NS
        a = np.array(self._arrivals, np.int64)  # in arrival order: noted as they reach the fusion
        best, score = best_phase_ns(a[:, 0], a[:, 1], self.period_ns)
        current = int(next_tick_ns % self.period_ns)
        k_now = int(round(current * CANDIDATES / self.period_ns)) % CANDIDATES
        gain = float(score[k_now] - score.min())
        if gain < max(GAIN_PERIODS * self.period_ns, GAIN_MIN_NS):
            return 0
        self.shifts += 1
        return (best - current) % self.period_ns
