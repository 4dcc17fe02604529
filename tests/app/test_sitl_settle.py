"""The waypoint wait that ArduPilot's and PX4's scripted flights share (app/sitl/truth.py until_settled)."""

from __future__ import annotations

import asyncio
import time

import numpy as np

from visionpos.app.sitl.truth import until_settled


class _Truth:
    """A stand-in TruthTrack: the vehicle at `start` until arrive_s after creation, then at `end`."""

    def __init__(self, start, end, arrive_s):
        self.t0, self.start, self.end, self.arrive_s = time.monotonic(), np.array(start), np.array(end), arrive_s

    def snapshot(self):
        x = np.zeros((1, 13))
        x[0, :3] = self.end if time.monotonic() - self.t0 >= self.arrive_s else self.start
        return np.array([time.monotonic_ns()]), x


def test_settled_after_half_a_second_within_5_cm_and_the_setpoint_resent():
    sent = []
    truth = _Truth([0, 0, 0], [1.0, 2.0, 1.46], arrive_s=0.3)  # arrives 4 cm from the target
    t0 = time.monotonic()
    got = asyncio.run(until_settled(truth, np.array([1.0, 2.0, 1.5]), 5.0, lambda: sent.append(time.monotonic())))
    waited = time.monotonic() - t0
    assert got is None
    assert 0.8 <= waited < 3.0  # 0.3 s to arrive, then 0.5 s held
    assert len(sent) >= 3 and np.all(np.diff(sent) > 0.2)  # every 0.25 s (5 polls of 50 ms)


def test_not_reached_gives_the_last_true_position_at_the_timeout():
    truth = _Truth([0, 0, 0], [1.0, 2.0, 1.44], arrive_s=0.0)  # 6 cm off: never settles
    t0 = time.monotonic()
    got = asyncio.run(until_settled(truth, np.array([1.0, 2.0, 1.5]), 0.6))
    assert time.monotonic() - t0 >= 0.6
    assert got is not None and np.allclose(got, [1.0, 2.0, 1.44])
