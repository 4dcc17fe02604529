"""A vehicle's vision gap: its poses stopped for longer than `vision_gap_s` after they had been going.

The EKF dead-reckons on its IMU through a gap and keeps saying it is healthy (against SITL a 5 s gap drifted
185 mm with EKF3's flags still good, only SYS_STATUS's vision bit dropped): visionpos knows when it stops
sending, so it says so loudly. VisionGap is the state machine, on the vehicle's sender thread and its clock;
VehicleLink turns its events into the log, the STATUSTEXT to the autopilot and the health.
"""

from __future__ import annotations

import dataclasses

REPEAT_NS = 5_000_000_000  # while the gap lasts: said again this often (log and STATUSTEXT)


@dataclasses.dataclass(frozen=True)
class GapEvent:
    kind: str  # 'lost' (the gap began), 'still' (it goes on: the rate-limited repeat), 'resumed'
    gap_s: float  # how long no pose had gone, at the event


class VisionGap:
    """Feed on_sent(now) with every pose sent and check(now) periodically; each returns the event to say, if any.

    gap_ns: the configured vision_gap_s in ns. Times are the link's clock (ns)."""

    def __init__(self, gap_ns: int, repeat_ns: int = REPEAT_NS):
        self.gap_ns = int(gap_ns)
        self.repeat_ns = int(repeat_ns)
        self.last_sent_ns: int | None = None
        self.in_gap = False
        self.gaps = 0  # gaps seen
        self.longest_s = 0.0
        self.last_gap_s: float | None = None  # the length of the last gap that ended
        self._next_say = 0

    def deadline_ns(self) -> int | None:
        """When check() may next have something to say (for the thread's wait); None: nothing pending."""
        if self.last_sent_ns is None:
            return None
        return self._next_say if self.in_gap else self.last_sent_ns + self.gap_ns + 1

    def check(self, now: int) -> GapEvent | None:
        if self.last_sent_ns is None:
            return None  # nothing sent yet: no vision to lose
        gap = now - self.last_sent_ns
        if not self.in_gap:
            if gap <= self.gap_ns:
                return None
            self.in_gap = True
            self.gaps += 1
            self._next_say = now + self.repeat_ns
            return GapEvent("lost", gap * 1e-9)
        if now >= self._next_say:
            self._next_say = now + self.repeat_ns
            return GapEvent("still", gap * 1e-9)
        return None

    def on_sent(self, now: int) -> GapEvent | None:
        event = None
        if self.in_gap and self.last_sent_ns is not None:
            gap_s = (now - self.last_sent_ns) * 1e-9
            self.in_gap = False
            self.last_gap_s = gap_s
            self.longest_s = max(self.longest_s, gap_s)
            event = GapEvent("resumed", gap_s)
        self.last_sent_ns = now
        return event

    def state(self, now: int) -> dict:
        """For the health: state 'ok' | 'gap' | 'not started', the current gap (s), gaps so far, the longest."""
        if self.last_sent_ns is None:
            st, cur = "not started", None
        else:
            cur = (now - self.last_sent_ns) * 1e-9
            st = "gap" if self.in_gap else "ok"
        return {"state": st, "since_last_pose_s": cur, "gaps": self.gaps, "longest_s": self.longest_s,
                "last_gap_s": self.last_gap_s, "threshold_s": self.gap_ns * 1e-9}
