"""sitl_px4_delay's reading of its flights (docs/autopilot-setup.md, 3.): three per link delay, their mean held to
the goal, each flight kept beside it."""

import math
from pathlib import Path

import pytest

from visionpos.benchmarks.sitl_px4_delay import FLIGHTS_PER_DELAY, lead_summary


def test_three_flights_per_delay_and_their_mean_is_what_the_goal_reads():
    doc = " ".join((Path(__file__).resolve().parents[2] / "docs" / "autopilot-setup.md").read_text().split())
    assert "`sitl_px4_delay` flies three flights per link delay and holds their mean to the goal, each flight " \
           "shown beside it" in doc
    assert FLIGHTS_PER_DELAY == 3
    s = lead_summary([-1.9, 1.7, -0.8])
    # mean -1.0 / 3 = -0.333; spread: deviations -1.567, 2.033, -0.467 -> squares 2.454, 4.134, 0.218 = 6.807,
    # / 2 = 3.403, sqrt 1.845, / sqrt 3 = 1.065
    assert s["mean"] == pytest.approx(-1.0 / 3) and s["se"] == pytest.approx(1.065, abs=1e-3)
    assert s["worst_abs"] == 1.9 and s["within_2ms"] == 3 and s["flights"] == 3
    # one flight out of 2 ms does not fail the delay: its mean does
    s = lead_summary([-2.5, -0.3, 0.4])
    assert s["mean"] == pytest.approx(-0.8) and s["within_2ms"] == 2 and s["worst_abs"] == 2.5


def test_a_flight_without_a_lead_leaves_the_delay_unmet():
    s = lead_summary([-0.5, None, 0.5])
    assert math.isnan(s["mean"]) and math.isnan(s["worst_abs"]) and s["flights"] == 2
    assert math.isnan(lead_summary([])["mean"])
    assert math.isnan(lead_summary([1.0])["se"]) and lead_summary([1.0])["mean"] == 1.0
