"""The IMU's clock map: the autopilot's clock less the capture clock at each IMU sample (bridge/imu_feed.py).

Two sources. The delay measurement (Backchannel.measure_delay) correlates the autopilot's gyro with the optical
rates: the clock lag of one physical instant, but only once the vehicle has turned, and for an instant seconds back.
TIMESYNC's answers give the clocks' offset at any time (the request's one-way share taken as half its round trip).
The map is the measured lag carried forward by TIMESYNC's drift since the instant it stands for, or, before the
vehicle has turned (on the ground, through a take-off's climb), TIMESYNC's offset alone where its round trips are
short. On ArduPilot SITL the two agreed within 1-4 ms.
"""

from __future__ import annotations

from bridge.telemetry import Ring
from visionpos.analysis.autopilot import theil_sen_line

# TIMESYNC answers whose round trip is this short (the one-way share, taken as half, then known to +-5 ms), over
# this window, while the newest is this recent
IMU_TIMESYNC_MAX_RTT_NS = 10_000_000
IMU_TIMESYNC_WINDOW_NS = 10_000_000_000
IMU_TIMESYNC_STALE_NS = 3_000_000_000


class ImuClockMap:
    """TIMESYNC's clock offset as a line, and its value where the delay measurement's lag stands for."""

    def __init__(self) -> None:
        self.line: tuple[float, float, float] | None = None  # theil_sen_line: server ns t0, offset ns at t0, slope
        self.newest_ns = 0.0  # server time of the newest answer the line was fitted to
        self.lag_ts_offset_ns: float | None = None  # TIMESYNC's offset at the measured lag's instant

    def reset(self) -> None:
        self.line = self.lag_ts_offset_ns = None

    def fit(self, timesync: Ring) -> None:
        """Refit the line to the recent answers (Ring of server send time s1: (tc1 - s1, round trip) ns) with
        short round trips: each one's offset tc1 - s1 - rtt / 2 at s1 + rtt / 2; robust (theil_sen_at), as the
        clocks drift."""
        t, v = timesync.since(timesync.last_t() - IMU_TIMESYNC_WINDOW_NS)
        ok = v[:, 1] <= IMU_TIMESYNC_MAX_RTT_NS
        mid = t[ok] + 0.5 * v[ok, 1]
        self.line = theil_sen_line(mid, v[ok, 0] - 0.5 * v[ok, 1])
        if self.line is not None:
            self.newest_ns = float(mid[-1])

    def offset_at(self, t_ns: float) -> float | None:
        """TIMESYNC's autopilot-less-server offset (ns) at server time t_ns; None without a recent line."""
        line = self.line
        if line is None or t_ns - self.newest_ns > IMU_TIMESYNC_STALE_NS:
            return None
        return line[1] + line[2] * (t_ns - line[0])

    def mark_lag(self, at_ns: float) -> None:
        """A delay measurement's lag now stands for server time at_ns."""
        self.lag_ts_offset_ns = self.offset_at(at_ns)

    def lag_ns(self, t_ap_ns: int, clock_lag_ns: float | None) -> float | None:
        """The clock lag (ns) for a sample stamped t_ap_ns on the autopilot's clock: the measured clock_lag_ns
        carried by TIMESYNC's drift since mark_lag, or TIMESYNC's offset alone while none is measured; None while
        neither is known (or only TIMESYNC over a link whose round trips exceed IMU_TIMESYNC_MAX_RTT_NS)."""
        line = self.line
        ts = None if line is None else self.offset_at(t_ap_ns - (clock_lag_ns if clock_lag_ns is not None
                                                                  else line[1]))
        if clock_lag_ns is None:
            return ts
        if ts is None or self.lag_ts_offset_ns is None:
            return clock_lag_ns
        return clock_lag_ns + (ts - self.lag_ts_offset_ns)
