"""The output tick's phase follows the frames' arrivals (server/tick_phase.py, server.tick_phase_lock)."""

from __future__ import annotations

import asyncio
import time

import numpy as np

from visionpos.server import tick_phase as TP
from visionpos.server.service import FusionServer, load_config_with_overrides
from visionpos.server.settings import SERVER
from visionpos.server.sinks import Sink

MS = 1_000_000
P_NS = 10 * MS  # 100 Hz
LATENCY_NS = 4 * MS


def _burst(n_periods: int, phases_ms=(2.1, 2.6, 3.1, 4.0), base_ns: int = 10**12):
    """Four unsynchronised 100 Hz cameras captured at these phases, each frame arriving LATENCY_NS later:
    (arrivals, captures) sorted by arrival."""
    cap = np.sort((base_ns + np.arange(n_periods)[:, None] * P_NS + (np.array(phases_ms) * MS)[None, :]).ravel())
    return cap + LATENCY_NS, cap


def test_ages_at_ticks_by_hand():
    arrivals = np.array([10, 20, 30]) * MS
    captures = np.array([6, 12, 29]) * MS
    ages = TP.tick_ages_ns(arrivals, captures, np.array([5, 10, 25, 31]) * MS)
    assert list(ages) == [-1, 4 * MS, 13 * MS, 2 * MS]
    # a later arrival of an older capture does not make the tick's newest frame older
    ages = TP.tick_ages_ns(np.array([10, 20]) * MS, np.array([9, 5]) * MS, np.array([21]) * MS)
    assert list(ages) == [12 * MS]


def test_the_best_phase_is_just_after_the_burst():
    arrivals, captures = _burst(300)
    best, score = TP.best_phase_ns(arrivals, captures, P_NS)
    # the last camera (4.0 ms) arrives at 8.0 ms into each period: a tick there carries a 4 ms old frame
    assert best == 8 * MS
    assert abs(score.min() - 4 * MS) < 1e3
    # (a tick right after an earlier camera's arrival carries an older capture: 7.25 ms carries 3.1 ms's)
    assert abs(score[int(7.25 / 10 * TP.CANDIDATES)] - 4.15 * MS) < 1e3
    # a tick just before the burst carries the previous period's last frame: 5.75 - (4.0 - 10) ms
    k_before = int(5.75 / 10 * TP.CANDIDATES)  # before the first arrival at 6.1 ms
    assert abs(score[k_before] - 11.75 * MS) < 1e3


def test_a_tick_moves_once_forward_and_then_stays():
    arrivals, captures = _burst(500)
    tp = TP.TickPhase(P_NS)
    for a, c in zip(arrivals, captures):
        tp.note(int(a), int(c))
    now = int(arrivals[-1])
    next_tick = (now // P_NS + 1) * P_NS + 6 * MS  # phase 6 ms: before the burst
    assert tp.shift_ns(now, next_tick) == 0  # the first call only starts the clock
    shift = tp.shift_ns(now + TP.EVERY_NS, next_tick)
    assert shift == 2 * MS and tp.shifts == 1  # to 8 ms: later, never earlier
    assert tp.shift_ns(now + 2 * TP.EVERY_NS, next_tick + shift) == 0  # there it stays
    # 9.25 ms saves 1.25 ms, less than GAIN_PERIODS of a period: it stays; from 9.75 ms the move is 8.25 ms
    # forward, never 1.75 ms back
    tp2 = TP.TickPhase(P_NS)
    for a, c in zip(arrivals, captures):
        tp2.note(int(a), int(c))
    tp2.shift_ns(now, 0)
    period0 = (now // P_NS + 1) * P_NS
    assert tp2.shift_ns(now + TP.EVERY_NS, period0 + 9_250_000) == 0
    assert tp2.shift_ns(now + 2 * TP.EVERY_NS, period0 + 9_750_000) == 8_250_000


def test_evenly_spread_cameras_leave_the_tick_where_it_is():
    arrivals, captures = _burst(500, phases_ms=tuple(1.25 * np.arange(8)))  # eight cameras
    _, score = TP.best_phase_ns(arrivals, captures, P_NS)
    assert score.max() - score.min() < TP.GAIN_PERIODS * P_NS  # no phase is worth a move
    tp = TP.TickPhase(P_NS)
    for a, c in zip(arrivals, captures):
        tp.note(int(a), int(c))
    now = int(arrivals[-1])
    tp.shift_ns(now, 0)
    assert all(tp.shift_ns(now + k * TP.EVERY_NS, now + k * TP.EVERY_NS + ph * MS) == 0
               for k, ph in ((1, 0.3), (2, 1.7), (3, 4.1)))


def test_the_setting_is_documented_and_on_by_default():
    assert SERVER["tick_phase_lock"].field_default is True
    text = open("docs/configuration.md").read()
    assert "| `tick_phase_lock` | boolean | true |" in text


class _TickTimes(Sink):
    def __init__(self) -> None:
        self.ticks_ns: list[int] = []

    def publish(self, states) -> None:
        self.ticks_ns.append(time.monotonic_ns())


def _live_tick_phases(lock: bool, monkeypatch) -> tuple[float, float]:
    """A live server whose frames (one camera's) arrive 5 ms of a period after its first ticks: the ticks'
    phase (ms) after the arrivals, median over the first 0.2 s and the last 0.4 s of 1.5 s."""
    monkeypatch.setattr(TP, "EVERY_NS", 300 * MS)
    monkeypatch.setattr(TP, "WINDOW_NS", 600 * MS)
    monkeypatch.setattr(TP, "MIN_ARRIVALS", 20)
    arena = load_config_with_overrides("thesis", ["server.status_period_s=0", "server.insecure=true",
                                                  f"server.tick_phase_lock={'true' if lock else 'false'}"])
    sink = _TickTimes()

    async def main():
        server = FusionServer(arena, sinks=[sink], port=0)
        async with server:
            await asyncio.sleep(0.1)
            first = int(np.median(np.array(sink.ticks_ns) % P_NS))
            burst_end = (first + 5 * MS) % P_NS  # half a period after the ticks
            t0 = time.monotonic_ns()
            k = 0
            while time.monotonic_ns() - t0 < 1.5e9:  # the arrivals, noted as the feed notes them
                now = time.monotonic_ns()
                while (t := (t0 // P_NS + k) * P_NS + burst_end) <= now:
                    if server.tick_phase is not None:
                        server.tick_phase.note(t, t - LATENCY_NS)
                    k += 1
                await asyncio.sleep(0.002)
            return t0, burst_end, server.health()["tick_phase_moves"]

    t0, burst_end, moves = asyncio.run(main())
    assert moves == (1 if lock else 0)  # the health counts the moves: one, then it stays
    ticks = np.array(sink.ticks_ns)
    after = (ticks - burst_end) % P_NS / MS
    return float(np.median(after[(ticks >= t0) & (ticks < t0 + 200 * MS)])), float(np.median(after[ticks > t0 + 1.1e9]))


def test_a_live_server_moves_its_ticks_to_just_after_the_arrivals(monkeypatch):
    before, after = _live_tick_phases(True, monkeypatch)
    assert 3.0 < before < 7.5  # half a period off at the start
    assert after < 2.5  # then just after the last arrival (the loop runs a tick a little late)
    before_off, after_off = _live_tick_phases(False, monkeypatch)
    assert 3.0 < after_off < 7.5  # without the lock the ticks stay where they started


def test_a_stalled_loop_skips_its_missed_ticks_and_keeps_the_phase():
    arena = load_config_with_overrides("thesis", ["server.status_period_s=0", "server.insecure=true",
                                                  "server.tick_phase_lock=false"])

    class Stalling(_TickTimes):
        def publish(self, states) -> None:
            super().publish(states)
            if len(self.ticks_ns) == 20:
                time.sleep(0.0537)  # a tick stalls the loop for five and a third periods

    sink = Stalling()

    async def main():
        server = FusionServer(arena, sinks=[sink], port=0)
        async with server:
            await asyncio.sleep(0.45)
            return server.health()["late_ticks"]

    late = asyncio.run(main())
    ticks = np.array(sink.ticks_ns)
    phase = (ticks - ticks[8] + P_NS // 2) % P_NS - P_NS // 2  # of each tick, from the 9th's (no wrap at 0)
    before, after = np.median(phase[8:20]), np.median(phase[23:])
    assert late >= 1
    # (restarting the grid at the stall's end would put the ticks 3.7 ms off)
    assert abs(before - after) < 1.5 * MS


def test_the_architecture_says_what_the_tick_phase_does():
    text = " ".join(open("docs/architecture.md").read().split())
    assert (f"Every {TP.EVERY_NS / 1e9:g} s the server replays the last {TP.WINDOW_NS / 1e9:g} s of arrivals" in text
            and f"against {TP.CANDIDATES} candidate phases" in text
            and f"a mean age lower by {TP.GAIN_PERIODS:g} of a period" in text and "(`tick_phase_moves`)" in text)


def test_the_architecture_says_the_start_up_heap_is_frozen_while_serving():
    import inspect

    from visionpos.app import demo, serve

    text = " ".join(open("docs/architecture.md").read().split())
    assert "While `visionpos serve` and the demo run, what their start allocated is frozen" in text
    assert "with startup_heap_frozen():" in inspect.getsource(serve.serve)
    assert "with startup_heap_frozen():" in inspect.getsource(demo.run_demo)
