"""Where each pose sent to an autopilot is stamped: on an even grid, a steady age behind the tick that sends it.

ArduPilot maps every stamp with the smallest stamp -> arrival delay of its last 100 poses (JitterCorrection,
bridge/estimator_delay.py), so a delay that wanders moves EKF3's time alignment with that smallest one: it wants
the delay steady, not just small. (PX4's links keep the captures' grid, due_on_captures: against PX4 SIH the
steady age did worse, for a reason not found.)

Stamped on the captures' grid (a pose going out at the first tick whose newest frame reached the next grid point)
the delay at send was 5 to 25 ms: where a grid point falls between the 100 Hz ticks, and how old the newest frame
is at a tick, both drift with the cameras' clocks and the tick's phase. In one ArduPilot SITL flight the
100-pose minimum wandered over 14 ms (SITL's own log: VISP's corrected less remote time), and VISO_DELAY_MS,
set once, was right only part of the time.

So a pose is stamped `age` before the tick that sends it: the filter's state moved back from the newest frame to
the stamp (never forward by more than the tolerance). The stamps keep an exact grid of one period (never
closer: EKF3 drops external-navigation samples under 20 ms apart), whose phase follows the ticks': a tick late
or carrying an old frame sends its pose later, which only raises that pose's delay, never the smallest. The
age is the frames' own at the ticks (auto: their 90th percentile over the first 5 s the body is tracked, then
kept: the delay the autopilot was set for must not move), or a fixed setting. A frame older than the age is
stamped at the grid point it reaches, which lengthens that pose's delay only. Tried and left: an age that
followed the percentile (at once upwards, it ratcheted up with the host's stalls: 12 to 24 ms in one SITL
flight; with 10 s of hysteresis it still moved after VISO_DELAY_MS was set, as the ticks' phase lock moved
the share of ticks carrying older frames), and judging the ticks' phases apart.
"""

from __future__ import annotations

from collections import deque

import numpy as np

AGES_JUDGED = 500  # the automatic age: the first this many tracked ticks' (5 s at 100 Hz), then kept
AGE_EVERY = 100  # ticks between judgements until then
AGE_PERCENTILE = 90.0
PHASES_KEPT = 25  # sends whose slack is judged (0.5 s at 50 Hz)
SLACK_MAX_NS = 1_000_000  # the grid moves later when every recent send had more slack than this ...
SLACK_KEPT_NS = 500_000  # ... leaving this much (tick jitter of microseconds must not make a tick miss its point)


class StampGrid:
    """The stamps of one vehicle's poses (ns, server clock). due() says which stamp a tick's state goes out for
    (None: not yet, or its newest frame is older than the stamp), sent() records it; observe() feeds the
    automatic age. period_ns: the stamps' spacing; forward_ns: how far past its newest frame a state may be
    moved; age_ns: a fixed age (None: automatic)."""

    def __init__(self, period_ns: int, forward_ns: int, age_ns: int | None = None) -> None:
        self.period_ns = int(period_ns)
        self.forward_ns = int(forward_ns)
        self.fixed = age_ns is not None
        self.age_ns: int | None = None if age_ns is None else int(age_ns)
        self.last_ns: int | None = None
        self.why = ""  # why due() said None: "rate" (no grid point due) or "old" (newest frame too old)
        self._shift_ns = 0  # added once to the next grid step: the grid follows the ticks' phase
        self._slack: deque[int] = deque(maxlen=PHASES_KEPT)
        self._frame_limited = False
        self._ages = np.zeros(AGES_JUDGED, np.int64)
        self._n_ages = 0

    @property
    def settled(self) -> bool:
        """The age is fixed from now on (set, or the automatic one judged)."""
        return self.fixed or self._n_ages >= AGES_JUDGED

    def observe(self, tick_ns: int, capture_ns: int) -> None:
        """A tracked state's tick and newest capture: the frames' age at the ticks, for the automatic age."""
        if self.fixed or self._n_ages >= AGES_JUDGED:
            return
        age = int(tick_ns) - int(capture_ns)
        self._ages[self._n_ages] = age
        self._n_ages += 1
        if self._n_ages < AGE_EVERY:  # starting: cover every age seen, the first stamp being the first capture
            self.age_ns = age if self.age_ns is None else max(self.age_ns, age)
        elif self._n_ages % AGE_EVERY == 0:
            self.age_ns = int(np.percentile(self._ages[: self._n_ages], AGE_PERCENTILE))

    def due_on_captures(self, capture_ns: int) -> int | None:
        """The stamp for PX4 (EKF2, stamping on arrival without a converged TIMESYNC): the grid follows the
        captures, a pose going out once a frame reached the next grid point (less forward_ns), stamped there
        (or at its capture after a gap of a period): the stamping before the steady age, which PX4 SIH flew
        closer to the truth with (docs/autopilot-setup.md, Rate)."""
        if self.last_ns is None:
            return int(capture_ns)
        first = self.last_ns + self.period_ns
        if capture_ns < first - self.forward_ns:
            self.why = "rate"
            return None
        self._frame_limited = True  # no tick phase to judge
        return first if capture_ns - first < self.period_ns else int(capture_ns)

    def due(self, tick_ns: int, capture_ns: int) -> int | None:
        """The stamp the state of the tick at tick_ns (its newest frame captured at capture_ns) goes out for:
        the latest grid point at least the age before the tick and at most forward_ns after the frame; None
        when none is due since the last sent (why "rate") or the frame is older than the next grid point (why
        "old": a later tick sends it, with a newer frame). A frame older than the age is thus stamped at the
        grid point it reaches: a longer delay for that pose only; after a stall the points its frames never
        reached are skipped, not sent in a burst."""
        age = self.age_ns if self.age_ns is not None else int(tick_ns) - int(capture_ns)
        latest = int(tick_ns) - age
        if self.last_ns is None:
            return min(latest, int(capture_ns) + self.forward_ns)
        first = self.last_ns + self.period_ns + self._shift_ns
        if latest < first:
            self.why = "rate"
            return None
        reach = min(latest, int(capture_ns) + self.forward_ns)  # never moved forward past its frame
        self._frame_limited = reach < latest  # the stamp waits for the frame, not the tick: no phase to judge
        if reach < first:
            self.why = "old"
            return None
        return first + (reach - first) // self.period_ns * self.period_ns

    def sent(self, stamp_ns: int, tick_ns: int) -> None:
        """The pose for stamp_ns (from due) went out at the tick at tick_ns."""
        self._shift_ns = 0
        self.last_ns = int(stamp_ns)
        if self._frame_limited:
            return
        age = self.age_ns if self.age_ns is not None else 0
        self._slack.append(int(tick_ns) - age - int(stamp_ns))
        if len(self._slack) == PHASES_KEPT and min(self._slack) > SLACK_MAX_NS:
            self._shift_ns = min(self._slack) - SLACK_KEPT_NS
            self._slack.clear()
