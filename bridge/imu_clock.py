"""The autopilot's clock map: the autopilot's clock less the capture clock at any instant, for the IMU's samples
(bridge/imu_feed.py), the identity check and the fleet binding (Backchannel.ap_to_server_ns).

Two sources. The delay measurement (Backchannel.measure_delay) correlates the autopilot's gyro with the optical
rates: the clock lag of one physical instant, but only once the vehicle has turned, and for an instant seconds back.
TIMESYNC's answers give the clocks' offset at any time (the request's one-way share taken as half its round trip).
The map is the measured lag carried forward by TIMESYNC's drift since the instant it stands for, or, before the
vehicle has turned (on the ground, through a take-off's climb), TIMESYNC's offset alone where its round trips are
short. On ArduPilot SITL the two agreed within 1-4 ms.

The drift needs only steady round trips, not short ones: a link's constant one-way delays cancel in the offset's
change. So over a slow link (a relay, a telemetry radio) the drift comes from the answers near the fastest round
trip, while TIMESYNC's offset alone is not trusted. PX4 SIH's lockstep clock drifts 13 ms a second against ours:
a lag held constant for a minute of hover is most of a second off when the vehicle moves again.
"""

from __future__ import annotations

import numpy as np

from bridge.telemetry import Ring
from visionpos.analysis.autopilot import theil_sen_line

# TIMESYNC answers whose round trip is this short (the one-way share, taken as half, then known to +-5 ms), over
# this window, while the newest is this recent
IMU_TIMESYNC_MAX_RTT_NS = 10_000_000
IMU_TIMESYNC_WINDOW_NS = 10_000_000_000
IMU_TIMESYNC_STALE_NS = 3_000_000_000
# over a slower link, the answers this close to the window's fastest round trip give the drift
IMU_TIMESYNC_BAND_NS = 10_000_000


def _offsets(timesync: Ring, since_ns: float) -> tuple[np.ndarray, np.ndarray, bool]:
    """TIMESYNC's answers since server time since_ns (Ring of send time s1: (tc1 - s1, round trip) ns) as
    offsets: (M,) times s1 + rtt / 2, (M,) autopilot-less-server offsets tc1 - s1 - rtt / 2, and whether they are
    absolute: those with round trips under IMU_TIMESYNC_MAX_RTT_NS, or where there are none, those within
    IMU_TIMESYNC_BAND_NS of the fastest (then only their changes mean anything)."""
    t, v = timesync.since(int(since_ns))
    rtt = v[:, 1]
    fastest = float(rtt.min()) if len(rtt) else 0.0
    absolute = fastest <= IMU_TIMESYNC_MAX_RTT_NS
    ok = rtt <= (IMU_TIMESYNC_MAX_RTT_NS if absolute else fastest + IMU_TIMESYNC_BAND_NS)
    return t[ok] + 0.5 * rtt[ok], v[ok, 0] - 0.5 * rtt[ok], absolute


class ImuClockMap:
    """TIMESYNC's clock offset as a line, and its value where the delay measurement's lag stands for."""

    def __init__(self) -> None:
        self.line: tuple[float, float, float] | None = None  # theil_sen_line: server ns t0, offset ns at t0, slope
        self.absolute = False  # the line's offset itself is known (short round trips), not only its drift
        self.newest_ns = 0.0  # server time of the newest answer the line was fitted to
        self.lag_ts_offset_ns: float | None = None  # TIMESYNC's offset at the measured lag's instant

    def reset(self) -> None:
        self.line = self.lag_ts_offset_ns = None
        self.absolute = False

    def fit(self, timesync: Ring) -> None:
        """Refit the line to the recent answers (Ring of server send time s1: (tc1 - s1, round trip) ns): each
        one's offset tc1 - s1 - rtt / 2 at s1 + rtt / 2, from the answers with round trips under
        IMU_TIMESYNC_MAX_RTT_NS, or where there are none, within IMU_TIMESYNC_BAND_NS of the fastest (then only
        its drift is used); robust (theil_sen_line), as a late answer now and then is no drift."""
        mid, offset, self.absolute = _offsets(timesync, timesync.last_t() - IMU_TIMESYNC_WINDOW_NS)
        self.line = theil_sen_line(mid, offset)
        if self.line is not None:
            self.newest_ns = float(mid[-1])

    def offset_at(self, t_ns: float) -> float | None:
        """TIMESYNC's autopilot-less-server offset (ns) at server time t_ns; None without a recent line. Where
        the line is not `absolute`, only differences of it mean anything."""
        line = self.line
        if line is None or t_ns - self.newest_ns > IMU_TIMESYNC_STALE_NS:
            return None
        return line[1] + line[2] * (t_ns - line[0])

    def mark_lag(self, at_ns: float) -> None:
        """A delay measurement's lag now stands for server time at_ns."""
        self.lag_ts_offset_ns = self.offset_at(at_ns)

    def stamps_at(self, timesync: Ring, t_ap_ns: np.ndarray, off_ns: float, off_at_ns: float, at_ns: float
                  ) -> tuple[np.ndarray, float]:
        """Autopilot-clock stamps (N,) ns moved by TIMESYNC's drift onto the autopilot's clock as it ran at server
        time at_ns, and an offset off_ns (autopilot less server, ns, at server time off_at_ns) carried back to
        at_ns; both as they are without a line. For the gyro/optical correlation: PX4 SIH's clock runs 1.3 %
        slow, a quarter second over its 20 s window, and its rate wanders with the host's load, so the offset
        is followed answer by answer (a running median of 5 through them), not along one line."""
        if self.line is None:
            return t_ap_ns, off_ns
        mid, o, _ = _offsets(timesync, min(float(t_ap_ns[0]) - off_ns, at_ns) - IMU_TIMESYNC_WINDOW_NS)
        if len(o) < 5:
            return t_ap_ns, off_ns
        o = np.median(np.lib.stride_tricks.sliding_window_view(np.pad(o, 2, mode="edge"), 5), axis=1)
        o_at = float(np.interp(at_ns, mid, o))
        off_ns -= float(np.interp(off_at_ns, mid, o)) - o_at
        return t_ap_ns - (np.interp(t_ap_ns - off_ns, mid, o) - o_at), off_ns

    def lag_ns(self, t_ap_ns: int, clock_lag_ns: float | None) -> float | None:
        """The clock lag (ns) for a sample stamped t_ap_ns on the autopilot's clock: the measured clock_lag_ns
        carried by TIMESYNC's drift since mark_lag, or TIMESYNC's offset alone while none is measured; None while
        neither is known (or only TIMESYNC over a link whose round trips exceed IMU_TIMESYNC_MAX_RTT_NS)."""
        line = self.line
        ts = None if line is None else self.offset_at(t_ap_ns - (clock_lag_ns if clock_lag_ns is not None
                                                                  else line[1]))
        if clock_lag_ns is None:
            return ts if self.absolute else None
        mark = self.lag_ts_offset_ns
        if ts is None or mark is None:
            return clock_lag_ns
        return clock_lag_ns + (ts - mark)

    def lags_ns(self, t_ap_ns: np.ndarray, clock_lag_ns: float) -> np.ndarray:
        """lag_ns for many samples (N,) stamped on the autopilot's clock, with a measured clock_lag_ns: (N,) ns.
        Safe from another thread (the line and the mark are read once)."""
        line, mark = self.line, self.lag_ts_offset_ns
        t_srv = np.asarray(t_ap_ns, dtype=np.float64) - clock_lag_ns
        if line is None or mark is None or not len(t_srv) or float(t_srv.max()) - self.newest_ns > \
                IMU_TIMESYNC_STALE_NS:
            return np.full(len(t_srv), clock_lag_ns)
        return clock_lag_ns + (line[1] + line[2] * (t_srv - line[0]) - mark)
