"""Time alignment: which camera frames are fused together, and at what time.

Cameras are asynchronous (own rates, random phases, jitter), so no two
frames share a capture time. Two methods:

motion_compensated (default)
    Every admitted frame triggers a fusion at reference time = the newest
    capture time of the group; the group is the newest frame of every
    camera captured within `window` of it. The pipeline shifts each view's
    observation by the tracked body's predicted motion between that view's
    capture time and the reference time, so the views agree as if they were
    simultaneous. It never waits for later frames: the latency it adds is
    zero, and at 3 m/s a 5 ms skew (15 mm) becomes the prediction error over
    5 ms instead (well under a millimetre for a tracked body).
    Optional rate limit (`min_interval`, for many fast cameras): a fusion is
    skipped when the previous one is less than the interval old and another
    camera's next frame is due within the interval (from its period), so the
    fusion happens at the end of a burst of frames and includes all of them.
    The skipped fusion is kept (`deferred`) until a later one takes its frame,
    and the next output tick fuses it (`take_deferred`): a frame whose burst
    never ends (the awaited frame lost or late) waits for no later burst, so
    no admitted frame is left out of a tick's output.

naive
    Frames are binned to the nearest point of a fixed grid (period `grid`);
    a bin is fused, without compensation, when the first frame of a later
    bin arrives, at the mean capture time of its frames. This is the
    nearest-timestamp grouping baseline; it waits up to one grid period.

Measured frame intervals: stations deliver what their host can, not what
the arena says (15 fps on a loaded Pi configured for 100). Each camera's
frame interval is the median of its last `_INTERVALS` capture-time
intervals, refused frames included (lost frames, jitter and a clock jump
do not move a median), the configured
period until `_MIN_INTERVALS` are in. The automatic window (`auto_window`)
is 1.2 x the slowest live camera's interval, the clock-jump lead is at
least that window (a camera one frame ahead of slower ones is not a jump),
and the rate limit predicts each camera's next frame from its interval; so
cameras configured at 100 Hz that deliver 15 fps are still fused together.

Both check the clocks: a frame stamped more than `max_lead` after the
newest frame of the other cameras is a clock jump and is dropped (unless
its camera is the only one still talking, or another camera's frame agrees
on the new time: then it is a real gap that every camera shows), a frame
older than the window behind the newest fused time is late and dropped, and
a frame not newer than its camera's previous frame is a duplicate or
reordered and dropped. Times are capture_ns only (never a wall clock), so
replays are deterministic.
"""

from __future__ import annotations

from enum import StrEnum
from typing import NamedTuple


class TimeAlignment(StrEnum):
    """The `fusion.time_alignment` setting; members compare equal to their YAML strings."""

    MOTION_COMPENSATED = "motion_compensated"
    NAIVE = "naive"


MOTION_COMPENSATED = TimeAlignment.MOTION_COMPENSATED
NAIVE = TimeAlignment.NAIVE
MODES = tuple(m.value for m in TimeAlignment)  # the setting's valid strings


class Rejection(StrEnum):
    """Why TimeAligner.admit drops a frame; the values are the pipeline's stats keys."""

    CLOCK_JUMP = "clock_jump"
    LATE = "late"
    REORDERED = "reordered"


CLOCK_JUMP, LATE, REORDERED = Rejection.CLOCK_JUMP, Rejection.LATE, Rejection.REORDERED

# a run of frames from one camera alone, with no other camera in between,
# spanning this much of its own capture time means the others went silent:
# a forward jump is then a real gap, not a clock fault
_SOLO_TRUST_NS = 200_000_000

_INTERVALS = 16  # a camera's frame interval is the median of its last this many
_MIN_INTERVALS = 8  # ... once it has this many; before, its configured period
_MAX_INTERVAL_NS = 2_000_000_000  # a longer gap is an outage, not a frame interval
WINDOW_PERIODS = 1.2  # the automatic window, in frame intervals of the slowest camera


class Group(NamedTuple):
    """cameras: ids of the frames to fuse (their latest stored frames);
    ref_ns: the reference time; compensate: shift views by predicted motion."""

    cameras: tuple[int, ...]
    ref_ns: int
    compensate: bool


class TimeAligner:
    """Decides groups from (camera_id, capture_ns) in arrival order."""

    def __init__(
        self,
        mode: str | TimeAlignment,
        window_ns: int,
        grid_ns: int,
        max_lead_ns: int,
        periods_ns: dict[int, int] | None = None,
        min_interval_ns: int = 0,
        auto_window: bool = False,
        max_window_ns: int = 1_000_000_000,
    ):
        """periods_ns: each camera's configured frame period (until its interval is measured).
        auto_window: the window follows the cameras' measured intervals (WINDOW_PERIODS x the
        slowest live one, at most max_window_ns); else window_ns is fixed."""
        if mode not in MODES:
            raise ValueError(f"time alignment '{mode}' is unknown; use one of {MODES}")
        self.mode = TimeAlignment(mode)
        self._naive = self.mode == TimeAlignment.NAIVE  # read per frame: a bool is cheaper than an enum member
        self.window_ns = int(window_ns)
        self.grid_ns = int(grid_ns)
        self.max_lead_ns = self.configured_lead_ns = int(max_lead_ns)
        self.auto_window = bool(auto_window)
        self.max_window_ns = int(max_window_ns)
        # camera -> [capture_ns of its previous frame (admitted or not), intervals seen, the last
        # _INTERVALS of them (a ring)]: one lookup per frame
        self._rate: dict[int, list] = {}
        self.measured_ns: dict[int, int] = {}  # camera -> measured frame interval (median)
        self.latest: dict[int, int] = {}  # camera -> capture_ns of its stored frame
        self.newest_ns: int | None = None  # newest admitted capture time
        self._last_cam: int | None = None
        self._solo_start = 0
        self._ahead: dict[int, int] = {}  # camera -> capture_ns of its last frame refused as a clock jump
        self.configured_ns = dict(periods_ns or {})
        self.periods_ns = dict(self.configured_ns)  # camera -> interval in use: measured, else configured
        self.min_interval_ns = int(min_interval_ns)
        self.last_fused_ns: int | None = None
        self.deferred: Group | None = None  # the fusion the rate limit skipped last, until one takes its frame
        self._bin: int | None = None  # naive: pending grid bin
        self._pending: dict[int, int] = {}  # naive: camera -> capture_ns in the pending bin

    def admit(self, camera_id: int, capture_ns: int) -> Rejection | None:
        """None if the frame may be used, else the reason it must be dropped."""
        prev_cam = self._last_cam
        self._last_cam = camera_id
        # the interval is measured on every frame, refused ones too: a camera whose every frame is
        # refused as a clock jump only because its real interval is longer than configured must not
        # stay refused for want of a measurement (a real jump is one outlier of the median)
        rate = self._rate.get(camera_id)
        if rate is None:
            self._rate[camera_id] = [capture_ns, 0, []]
        else:
            interval = capture_ns - rate[0]
            rate[0] = capture_ns
            if 0 < interval <= _MAX_INTERVAL_NS:  # longer: an outage, not a frame interval
                n = rate[1]
                if n < _INTERVALS:
                    rate[2].append(interval)
                else:
                    rate[2][n % _INTERVALS] = interval
                n += 1
                rate[1] = n
                if n >= _MIN_INTERVALS and not n & 3:  # the median every 4th frame: cheap, and fresh enough
                    self._measured(camera_id, sorted(rate[2])[len(rate[2]) // 2])
        if prev_cam != camera_id:
            self._solo_start = capture_ns
        latest = self.latest
        last = latest.get(camera_id)
        if last is not None and capture_ns <= last:
            return REORDERED
        if self.newest_ns is not None:
            lead = capture_ns - self.newest_ns
            others_alive = len(latest) > (last is not None)  # another camera has a stored frame
            if lead > self.max_lead_ns and others_alive and capture_ns - self._solo_start < _SOLO_TRUST_NS:
                # one camera alone ahead is a clock fault; two cameras that agree on the new time saw a
                # real gap (every station stalled, a network or host hiccup), which must not be refused
                # forever
                agree = any(c != camera_id and abs(t - capture_ns) <= self.max_lead_ns for c, t in self._ahead.items())
                self._ahead[camera_id] = capture_ns
                if not agree:
                    return CLOCK_JUMP
            if capture_ns < self.newest_ns - self.window_ns:
                return LATE
            if self._naive and self._bin is not None and self._bin_of(capture_ns) < self._bin:
                return LATE
        return None

    def _bin_of(self, capture_ns: int) -> int:
        return (capture_ns + self.grid_ns // 2) // self.grid_ns

    def add(self, camera_id: int, capture_ns: int) -> tuple[list[Group], list[Group]]:
        """Register an admitted frame.

        Returns (before, after): groups to fuse before the frame is stored
        (naive bins it closes) and after (groups that include it).
        """
        before: list[Group] = []
        after: list[Group] = []
        if not self._naive:  # motion-compensated
            latest = self.latest
            latest[camera_id] = capture_ns
            if self.newest_ns is None or capture_ns > self.newest_ns:
                self.newest_ns = capture_ns
            lo, hi = capture_ns - self.window_ns, capture_ns + self.window_ns
            members = []
            ref = capture_ns  # the newest capture time of the group
            for c, t in latest.items():
                if lo <= t <= hi:
                    members.append(c)
                    if t > ref:
                        ref = t
            members.sort()
            group = Group(tuple(members), ref, True)
            if self._defer(camera_id, ref):
                self.deferred = group
            else:
                self.deferred = None
                self.last_fused_ns = ref
                after.append(group)
        else:
            b = self._bin_of(capture_ns)
            if self._bin is not None and b > self._bin and self._pending:
                before.append(self._close())
            if self._bin is None or b > self._bin:
                self._bin = b
                self._pending = {}
            self._pending[camera_id] = capture_ns
            self.latest[camera_id] = capture_ns
            self.newest_ns = capture_ns if self.newest_ns is None else max(self.newest_ns, capture_ns)
        return before, after

    def take_deferred(self) -> Group | None:
        """The fusion the rate limit skipped last, when no later fusion has taken its frame (then it counts as
        done); None when there is none. The output tick calls it: the frame a burst's lost or late frame would
        hold back is fused by the tick, not by the next burst a frame period later."""
        g = self.deferred
        if g is not None:
            self.deferred = None
            self.last_fused_ns = g.ref_ns
        return g

    def _measured(self, camera_id: int, interval_ns: int) -> None:
        """A camera's new measured frame interval: the window and lead follow."""
        self.measured_ns[camera_id] = self.periods_ns[camera_id] = interval_ns
        self._refresh()

    def period_ns(self, camera_id: int) -> int | None:
        """The camera's frame interval: measured, else configured (None: neither)."""
        return self.periods_ns.get(camera_id)

    def slowest_period_ns(self) -> int:
        """The longest frame interval among the cameras with a stored frame (0: none known)."""
        periods = self.periods_ns
        return max((periods.get(c, 0) for c in self.latest), default=0)

    def _refresh(self) -> None:
        """Window and clock-jump lead from the cameras' intervals."""
        slowest = self.slowest_period_ns()
        if not slowest:
            return
        window = min(int(WINDOW_PERIODS * slowest), self.max_window_ns)
        if self.auto_window:
            self.window_ns = window
        self.max_lead_ns = max(self.configured_lead_ns, window)

    def _defer(self, camera_id: int, ref: int) -> bool:
        """Rate limit (min_interval_ns > 0): skip this fusion when one happened less than the
        interval ago *and* another camera's next frame is due within the interval, so the
        fusion lands at the end of a burst of frames and no frame waits longer than that."""
        if self.min_interval_ns <= 0 or self.last_fused_ns is None:
            return False
        if ref - self.last_fused_ns >= self.min_interval_ns or ref < self.last_fused_ns:
            return False
        for c, t in self.latest.items():
            period = self.periods_ns.get(c)
            if c == camera_id or not period or ref - t > 2 * period:  # silent cameras are not waited for
                continue
            nxt = t + period * max(1, -(-(ref - t) // period))  # its next frame after ref
            if nxt - ref <= self.min_interval_ns:
                return True
        return False

    def _close(self) -> Group:
        cams = tuple(sorted(self._pending))
        ref = sum(self._pending[c] for c in cams) // len(cams)
        self._pending = {}
        return Group(cams, int(ref), False)

    def remove(self, camera_id: int) -> None:
        """Forget a camera (its station vanished); its interval is measured afresh when it is back."""
        self.latest.pop(camera_id, None)
        self._pending.pop(camera_id, None)
        self._ahead.pop(camera_id, None)
        self._rate.pop(camera_id, None)
        self.measured_ns.pop(camera_id, None)
        if camera_id in self.configured_ns:
            self.periods_ns[camera_id] = self.configured_ns[camera_id]
        else:
            self.periods_ns.pop(camera_id, None)
        if self._last_cam == camera_id:
            self._last_cam = None
        self._refresh()
