"""How PX4 stamps our poses, as far as the bridge can tell, and the EKF2_EV_DELAY that follows from the link's
timing (bridge/estimator_delay.py has why each estimator wants what it wants).

PX4's mavlink receiver maps a pose's time_usec to its own clock only once its TIMESYNC filter has converged
(src/lib/timesync/Timesync.cpp, Timesync.hpp): it asks at 10 Hz on an Onboard-mode link, uses an answer only if
its round trip was under MAX_RTT_SAMPLE (10 ms), and has converged after CONVERGENCE_WINDOW (500) of them. Before
that, and after a reset (a clock jump, which only its timesync_status shows), it stamps each pose on arrival.
"""

from __future__ import annotations

import numpy as np

from bridge.estimator_delay import DelayAdvice, advised_delay

PX4_TIMESYNC_MAX_RTT_NS = 10_000_000  # MAX_RTT_SAMPLE
PX4_TIMESYNC_CONVERGENCE = 500  # CONVERGENCE_WINDOW
MIN_POSES, MIN_ANSWERS = 10, 3


class Px4TimesyncTracker:
    """Counts PX4's TIMESYNC requests we answered over a link whose round trip PX4 accepts."""

    def __init__(self) -> None:
        self.used = 0

    def reset(self) -> None:
        self.used = 0

    def answered(self, rtt_ns: float | None) -> None:
        """One request answered; rtt_ns: the link's round trip now (ours, which PX4's mirrors), None unknown."""
        if rtt_ns is not None and rtt_ns < PX4_TIMESYNC_MAX_RTT_NS:
            self.used += 1

    @property
    def converged(self) -> bool:
        return self.used >= PX4_TIMESYNC_CONVERGENCE


def median_round_trip_ns(round_trips_ns: list[float]) -> float | None:
    """The median of the recent TIMESYNC round trips (ns); None before MIN_ANSWERS."""
    return float(np.median(round_trips_ns)) if len(round_trips_ns) >= MIN_ANSWERS else None


def fastest_round_trip_ns(round_trips_ns: list[float]) -> float | None:
    """The fastest of the recent TIMESYNC round trips (ns), None before MIN_ANSWERS: the link's bare transit, half
    of it a pose's one way. The median also holds PX4's time to answer and either side's scheduling: through a
    relay adding 50 ms each way it read 105 ms where the fastest read 101.3, and the poses' delays in PX4's log
    matched the fastest within 1 ms (issue 31)."""
    return float(np.min(round_trips_ns)) if len(round_trips_ns) >= MIN_ANSWERS else None


def px4_link_advice(send_minus_stamp_ns: np.ndarray, rtt_ns: float | None, converged: bool,
                    message: str = "vision_position_estimate") -> DelayAdvice | None:
    """EKF2_EV_DELAY from the link's timing alone: stamped on arrival, a pose is its stamp-to-send time (N,) ns
    plus the link's one way, half the round trip rtt_ns (fastest_round_trip_ns), old when PX4 stamps it;
    converged, its own instant (0). No rotation or clock map is needed (PX4 SIH's clock runs about 1 % slow of
    ours, unevenly). message: the pose message, whose own trail EKF2 has (EKF2_ARRIVAL_TRAIL_MS). None before
    MIN_POSES poses and a round trip."""
    d = np.asarray(send_minus_stamp_ns, dtype=np.float64)
    if len(d) < MIN_POSES or rtt_ns is None:
        return None
    return advised_delay("px4", (d + 0.5 * rtt_ns) * 1e-6, converged, message=message)
