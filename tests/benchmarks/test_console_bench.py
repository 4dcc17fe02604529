"""The console benchmark's ratio: each window with the client against its neighbours less the idle console."""

from __future__ import annotations

import pytest

from visionpos.benchmarks.console import window_ratios


def _row(client: bool, cpu: float, own: float) -> dict:
    return {"client": client, "cpu_us_per_packet": cpu, "console_us_per_packet": own}


def test_each_client_window_is_held_against_its_neighbours_less_the_idle_consoles_own_work():
    rows = [_row(False, 400.0, 2.0), _row(True, 420.0, 15.0), _row(False, 404.0, 4.0),
            _row(True, 500.0, 15.0), _row(False, 480.0, 2.0)]
    ratios, off, idle = window_ratios(rows)
    # window 2: neighbours 400 and 404 (mean 402) less their own 2 and 4 (mean 3): 399; window 4: 442 - 3 = 439
    assert off == pytest.approx([399.0, 439.0])
    assert ratios == pytest.approx([420.0 / 399.0, 500.0 / 439.0])
    assert idle == pytest.approx([3.0 / 399.0, 3.0 / 439.0])


def test_a_client_window_without_a_neighbour_on_each_side_is_not_judged():
    rows = [_row(True, 420.0, 15.0), _row(False, 400.0, 2.0), _row(True, 430.0, 15.0)]
    assert window_ratios(rows) == ([], [], [])
