"""`visionpos replay LOG --view`: a recording run through the server's ingest and a fresh pipeline, at the
speed the console asks for, with play, pause, seek and speed.

The session steps the recording exactly as analysis/replay.py's run_pipeline does (the same Ingest
with trusted registrations, ticks on the grid t0 + k / output rate before any later packet, the
vanish check every 20 ms of recording time), but a slice at a time on the event loop, so the
console stays responsive: each wake-up moves the recording clock by the wall time elapsed times
the speed, at most MAX_STEP_S of work before it yields. Seeking backwards starts a fresh ingest and
pipeline and runs them up to the target as fast as they go (fusion state depends on the past);
seeking forwards runs on from where it is.
"""

from __future__ import annotations

import asyncio
import time
from typing import Any, Sequence

from visionpos import protocol as P
from visionpos.analysis.replay import V1Upgrade
from visionpos.config.arena import ArenaConfig
from visionpos.fusion.pipeline import FusionPipeline
from visionpos.messages import BodyState
from visionpos.server.ingest import Ingest
from visionpos.server.service import VANISH_CHECK_S
from visionpos.server.settings import ServerSettings

MAX_STEP_S = 0.02  # wall time of pipeline work per slice before yielding to the loop (and the console)
WAKE_S = 0.01
SPEEDS = (0.1, 0.25, 0.5, 1.0, 2.0, 4.0, 8.0)


class ReplaySession:
    """A recording's packets replayed on demand; the console's source (arena, pipeline, last_states,
    health(), clock()) and its controls (command()). calibration: an object with push(BlobFrame)
    (console/calibration.py) that gets every accepted frame of each packet once: a seek back or a play after the
    end runs the pipeline again from the start but keeps the wand frames gathered so far (none counted twice).
    name: what the console's header shows (the recording's file name)."""

    console_mode = "replay"  # the page shows only what a replay can do (console/view.py scene)

    def __init__(self, arena: ArenaConfig, packets: Sequence[tuple], rate_hz: float | None = None,
                 realtime_minus_monotonic_ns: int | None = None, calibration: Any = None, name: str | None = None):
        if not packets:
            raise ValueError("the recording holds no station packets; record with stations streaming")
        self.arena = arena
        self.packets = list(packets)
        self.settings = ServerSettings.for_replay(arena)
        self.period_ns = int(round(1e9 / float(rate_hz or self.settings.output_rate_hz)))
        self.t0_ns = int(self.packets[0][0])
        self.end_ns = int(self.packets[-1][0])
        self.rt_ns = realtime_minus_monotonic_ns
        self.playing = True
        self.speed = 1.0
        self.finished = False
        self._seeking = False
        self.calibration = calibration
        self.source_name = name
        self._fed = 0  # packets [0, _fed) have given the calibration their frames
        self._reset()

    def _reset(self) -> None:
        self.pipeline = FusionPipeline(self.arena)
        self._now = self.t0_ns
        fed: Any = self.pipeline
        if self.calibration is not None:
            fed = _Tee(self.pipeline, self.calibration, self)
        self.ingest = Ingest(self.arena, self.settings, fed, None, clock=lambda: self._now,
                             verify_cookies=False, authenticate=False)
        self.ingest.set_start(-(1 << 62))
        if self.rt_ns is not None:
            self.ingest.realtime_minus_monotonic_ns = int(self.rt_ns)
        self._upgrade = V1Upgrade()
        self._i = 0  # next packet
        self._next_tick = self.t0_ns + self.period_ns
        self._next_check = 0
        self.last_states: list[BodyState] = []
        self.ticks = 0
        self._tracked: dict[str, int] = {}

    # ---------------------------------------------------------------- the source's face

    def clock(self) -> int:
        return self._now

    def health(self) -> dict[str, Any]:
        h = self.ingest.health(self._now)
        h["ticks"] = self.ticks
        h["bodies_tracked_ticks"] = dict(self._tracked)
        h["pipeline"] = dict(self.pipeline.stats())
        h["sinks"] = {}
        return h

    def position(self) -> dict[str, Any]:
        return {"replay": {"t_s": round((self._now - self.t0_ns) * 1e-9, 3),
                           "duration_s": round((self.end_ns - self.t0_ns) * 1e-9, 3), "playing": self.playing,
                           "speed": self.speed, "finished": self.finished}}

    # ---------------------------------------------------------------- stepping

    def _tick(self, t: int) -> None:
        self._now = t
        if t >= self._next_check:
            self._next_check = t + int(VANISH_CHECK_S * 1e9)
            self.ingest.check_vanished(t)
        self.last_states = self.pipeline.tick(t)
        self.ticks += 1
        for s in self.last_states:
            if s.tracked:
                self._tracked[s.name] = self._tracked.get(s.name, 0) + 1

    def advance_to(self, target_ns: int, budget_s: float | None = None) -> bool:
        """Process packets and ticks up to target_ns (recording clock); stop early after budget_s of wall
        time. True when target_ns was reached."""
        t_end = None if budget_s is None else time.perf_counter() + budget_s
        packets = self.packets
        while self._i < len(packets):
            item = packets[self._i]
            recv_ns = int(item[0])
            if recv_ns > target_ns:
                break
            while self._next_tick <= recv_ns:
                self._tick(self._next_tick)
                self._next_tick += self.period_ns
            data = item[1]
            if len(data) > 4 and data[4] == 1 and data[:4] == P.MAGIC:
                data = self._upgrade(data)
            self._now = recv_ns
            self.ingest.handle(data, item[2] if len(item) > 2 and item[2] is not None else ("replay", 0), recv_ns)
            self._i += 1
            self._fed = max(self._fed, self._i)
            if t_end is not None and (self._i & 63) == 0 and time.perf_counter() > t_end:
                return False
        while self._next_tick <= min(target_ns, self.end_ns):
            self._tick(self._next_tick)
            self._next_tick += self.period_ns
        self._now = max(self._now, min(target_ns, self.end_ns))
        if self._i >= len(packets) and target_ns >= self.end_ns:
            self.finished = True
            self.playing = False
        return True

    async def run(self) -> None:
        """Play while playing, until cancelled (the console's task)."""
        loop = asyncio.get_running_loop()
        last = loop.time()
        while True:
            await asyncio.sleep(WAKE_S)
            now = loop.time()
            dt, last = now - last, now
            if self.playing and not self.finished and not self._seeking:
                self.advance_to(self._now + int(min(dt, 0.1) * self.speed * 1e9), MAX_STEP_S)

    async def command(self, msg: dict[str, Any]) -> dict[str, Any]:
        """The console's controls: {"cmd": "play" | "pause" | "seek" (t_s) | "speed" (x)}; ValueError for
        anything else (the console answers it)."""
        cmd = msg.get("cmd")
        if cmd == "play":
            if self.finished:
                await self.seek(0.0)
            self.playing = True
        elif cmd == "pause":
            self.playing = False
        elif cmd == "speed":
            x = msg.get("x")
            if isinstance(x, bool) or not isinstance(x, (int, float)) or not 0.05 <= x <= 16:
                raise ValueError("speed: give x between 0.05 and 16")
            self.speed = float(x)
        elif cmd == "seek":
            t = msg.get("t_s")
            span_s = (self.end_ns - self.t0_ns) * 1e-9
            if isinstance(t, bool) or not isinstance(t, (int, float)) or not 0 <= t <= span_s:
                raise ValueError(f"seek: give t_s between 0 and {span_s:.3f}")
            await self.seek(float(t))
        else:
            raise ValueError(f"unknown command {cmd!r}: play, pause, seek or speed")
        return self.position()["replay"]

    async def seek(self, t_s: float) -> None:
        target = self.t0_ns + int(t_s * 1e9)
        if target < self._now:
            self._reset()
        self.finished = False
        self._seeking = True
        try:
            while not self.advance_to(target, MAX_STEP_S):
                await asyncio.sleep(0)
        finally:
            self._seeking = False


class _Tee:
    """What the ingest pushes into: the pipeline, and each frame also to the calibration assistant, once: the
    frames of a packet the session replays again (after a seek back) are not given twice."""

    def __init__(self, pipeline: FusionPipeline, calibration: Any, session: ReplaySession):
        self.pipeline = pipeline
        self.calibration = calibration
        self.session = session

    def push(self, frame: Any) -> None:
        self.pipeline.push(frame)
        if self.session._i >= self.session._fed:
            self.calibration.push(frame)

    def remove_camera(self, camera_id: int) -> None:
        self.pipeline.remove_camera(camera_id)
