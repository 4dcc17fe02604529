"""The outputs benchmark's windows: each window with the outputs against its two neighbours without them, and the
switch that takes the outputs out of the server and puts them back."""

from __future__ import annotations

from types import SimpleNamespace

import pytest

from visionpos.benchmarks.bridge import _switch_outputs, neighbour_ratios


def _row(outputs: bool, cpu: float) -> dict:
    return {"outputs": outputs, "cpu_us_per_packet": cpu}


def test_each_window_with_the_outputs_is_held_against_the_mean_of_its_neighbours():
    rows = [_row(False, 400.0), _row(True, 420.0), _row(False, 404.0), _row(True, 500.0), _row(False, 480.0)]
    # window 1: neighbours 400 and 404 (mean 402); window 3: 404 and 480 (mean 442)
    assert neighbour_ratios(rows, "cpu_us_per_packet") == pytest.approx({1: 420.0 / 402.0, 3: 500.0 / 442.0})


def test_a_window_without_a_neighbour_without_outputs_on_each_side_is_not_judged():
    rows = [_row(True, 420.0), _row(False, 400.0), _row(True, 430.0), _row(True, 440.0), _row(False, 400.0)]
    assert neighbour_ratios(rows, "cpu_us_per_packet") == {}


def test_the_switch_takes_the_network_outputs_out_of_ticks_and_taps_and_restores_the_order():
    bridge, pose, natnet, recorder = "bridge", "pose", "natnet", "recorder"
    taps = ("fox-tap",)
    server = SimpleNamespace(sinks=[bridge, pose, natnet, recorder], ingest=SimpleNamespace(taps=taps))
    all_sinks = list(server.sinks)
    _switch_outputs(server, all_sinks, [pose, natnet], taps, on=False)
    assert server.sinks == [bridge, recorder] and server.ingest.taps == ()
    _switch_outputs(server, all_sinks, [pose, natnet], taps, on=True)
    assert server.sinks == [bridge, pose, natnet, recorder] and server.ingest.taps == taps
