"""The network outputs (pose stream, NatNet, VRPN) fed from one thread off the server's loop.

Each output's publish() ends in a system call: a sendto (pose stream) or a wake-up of the output's
own thread (NatNet, VRPN). On a small host each such call on an idle core costs tens of microseconds
(measured by `visionpos bench --only bridge`), and on the event loop that is time the next station
packet waits. `OffLoopOutputs` takes the tick's states with one reference swap and one wake-up, and
calls the outputs from its own thread; it holds one slot (the newest states), so a late thread
skips to the newest tick and never sends a stale one after a newer one.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Sequence
from typing import Any

from visionpos.logutil import RateLimitedLog
from visionpos.messages import BodyState, LoosePoints
from visionpos.server.sinks import PacketTap, Sink, start_sink

log = logging.getLogger(__name__)


class OffLoopOutputs(Sink):
    """A sink that forwards poses and markers to `outputs` (sinks too) from a thread of its own; packet
    taps, health and events go to them straight (each is a mailbox store)."""

    def __init__(self, outputs: Sequence[Sink]):
        self.outputs = list(outputs)
        self._cond = threading.Condition()
        self._states: list[BodyState] | None = None
        self._markers: LoosePoints | None = None
        self._running = False
        self._thread: threading.Thread | None = None
        self.counters = {"ticks": 0, "superseded": 0, "marker_sets": 0, "errors": 0}
        self._log = RateLimitedLog(log)

    def start(self) -> None:
        started: list[Sink] = []
        try:
            for o in self.outputs:
                start_sink(o)
                started.append(o)
        except BaseException:  # one output could not open (a port taken): close the others again
            for o in started:
                o.close()
            raise
        self._running = True
        self._thread = threading.Thread(target=self._run, name="outputs-dispatch", daemon=True)
        self._thread.start()

    def publish(self, states: list[BodyState]) -> None:
        """Hand the tick's states over (never blocks: the lock is held only for a swap by either side)."""
        with self._cond:
            if self._states is not None:
                self.counters["superseded"] += 1
            self._states = states
            self._cond.notify()

    def publish_markers(self, points: LoosePoints) -> None:
        with self._cond:
            self._markers = points
            self._cond.notify()

    def _run(self) -> None:
        while True:
            with self._cond:
                while self._running and self._states is None and self._markers is None:
                    self._cond.wait()
                if not self._running:
                    return
                states, self._states = self._states, None
                markers, self._markers = self._markers, None
            if markers is not None:
                self.counters["marker_sets"] += 1
                self._call("publish_markers", markers)
            if states is not None:
                self.counters["ticks"] += 1
                self._call("publish", states)

    def packet_taps(self) -> list[PacketTap]:
        """The outputs' packet taps (Ingest calls them with each accepted packet, on the loop); each is a
        mailbox store, so they need no hand-over to this thread."""
        return [tap for o in self.outputs for tap in o.packet_taps()]

    def publish_health(self, time_ns: int, health: dict[str, Any]) -> None:
        """A health snapshot (every status period): straight to the outputs that show it (mailbox stores)."""
        self._call("publish_health", time_ns, health)

    def publish_event(self, time_ns: int, info: dict[str, Any]) -> None:
        """A server event (rare): straight to the outputs that show events (mailbox stores)."""
        self._call("publish_event", time_ns, info)

    def _call(self, method: str, *args: Any) -> None:
        for o in self.outputs:
            try:
                getattr(o, method)(*args)
            except Exception as e:  # one output's bug must not silence the others
                self.counters["errors"] += 1
                name = f"{type(o).__name__}.{method}"
                self._log.log(name, logging.WARNING, "output %s failed: %r", name, e)

    def stats(self) -> dict:
        out: dict[str, Any] = {"dispatch": dict(self.counters)}
        for o in self.outputs:
            st = o.stats()
            if st:
                out[o.name] = st
        return out

    def close(self) -> None:
        """Stop the thread, then close every output. Idempotent."""
        with self._cond:
            self._running = False
            self._cond.notify()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            self._thread = None
        for o in self.outputs:
            o.close()
