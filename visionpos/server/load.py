"""Load relief before load shedding: pause the per-frame view updates while the receive queue is behind.

With fusion.single_view.mode `always` (the default), every fusion also updates each triangulated body from the
views its triangulation did not use. With twenty bodies on twelve cameras at 120 Hz that is about a quarter of
one core (`visionpos bench --only scale`), and the bursts it adds are what made a core that was 72 % busy on
average shed frames (a frame that waited over server.shed_backlog_ms is not fused at all). Pausing those
updates while the queue is behind keeps every frame: each is still triangulated with the others, and a body
hidden from the triangulation still takes its single views (mode `occlusion`).

ViewUpdatePause: paused once a frame waited more than `pause_views_backlog_ms` in the receive queue, resumed
once one waited less than RESUME_FRACTION of it (hysteresis: a queue that just drained stays relieved for a
moment). Replays have no backlog and never pause.
"""

from __future__ import annotations

RESUME_FRACTION = 0.2  # resumed once a frame waited less than this fraction of the pause threshold


class ViewUpdatePause:
    """The pause's state from each frame's backlog (module docstring). pause_backlog_ns: 0 = never."""

    def __init__(self, pause_backlog_ns: int):
        self.pause_ns = int(pause_backlog_ns)
        self.resume_ns = int(pause_backlog_ns * RESUME_FRACTION)
        self.paused = False

    def update(self, backlog_ns: int) -> bool | None:
        """This frame's wait in the receive queue (ns): the new state where it changes, else None."""
        if self.pause_ns <= 0:
            return None
        now = backlog_ns > self.pause_ns or (self.paused and backlog_ns >= self.resume_ns)
        if now == self.paused:
            return None
        self.paused = now
        return now
