"""The flights bench's reference told the manoeuvre (benchmarks/fusion_flights.told_the_manoeuvre): the rotation
scale it sets follows the simulator's true angular jerk, and the flight it tells is followed closer at the ticks."""

from __future__ import annotations

import numpy as np

from visionpos.benchmarks.fusion_flights import fly, told_the_manoeuvre
from visionpos.benchmarks.fusion_replay import replay, static_flight


def test_told_nothing_on_a_still_body_and_much_through_flicks():
    sc, sim = static_flight(quick=True)
    hook = told_the_manoeuvre(0.1)(sc)
    scales = []

    def watch(pipe):
        hook(pipe)
        if pipe.tracks[0].tracked:
            scales.append(pipe.tracks[0].filter.scale_r)

    replay(sc.arena, sim.frames, None, raw_cb=watch)
    assert len(scales) > 100 and max(scales) == 1.0  # no jerk: the floor


def test_a_filter_told_the_flicks_follows_the_rotation_closer_at_the_ticks():
    plain = fly("dash_sharp", 4.0, 1)
    told = fly("dash_sharp", 4.0, 1, told=told_the_manoeuvre(0.03))
    assert told["tick_rot_rmse_deg"] < 0.95 * plain["tick_rot_rmse_deg"], (told, plain)
    assert np.isfinite(told["tick_pos_rmse_mm"]) and told["tracked_fraction"] == 1.0
