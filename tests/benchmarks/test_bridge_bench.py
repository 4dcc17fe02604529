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


def test_the_live_demos_outputs_stop_in_the_windows_without_them_and_resume_in_those_with_them():
    """Three windows of one live demo run (without, with, without) with every output and a client each: the
    clients get every tick in the window with the outputs and nothing in those without, while the fusion's
    output ticks and the MAVLink poses to the autopilot go on at their rates in all three."""
    from visionpos.app.demo import demo_arena
    from visionpos.benchmarks.bridge import OUTPUT_SETTLE_S, OUTPUT_SWITCH_S, OUTPUT_WINDOW_S, _demo_run, all_outputs

    overrides, outputs_on, _ = all_outputs()
    duration_s = OUTPUT_SETTLE_S + 3 * (OUTPUT_WINDOW_S + OUTPUT_SWITCH_S + 0.1) + 2.0
    rows, run = _demo_run(demo_arena("thesis", duration_s, 1, overrides), duration_s, 3)
    assert [r["outputs"] for r in rows] == [False, True, False]
    for r in rows:
        assert r["ticks_hz"] == pytest.approx(100.0, abs=2.0)  # the demo's server.output_rate_hz
        assert r["mavlink_hz"] == pytest.approx(50.0, abs=2.0)  # the bridge's default rate
    for k in ("pose_stream", "natnet", "vrpn"):  # a frame per tick (VRPN: per tracked tick)
        assert rows[1]["clients_hz"][k] > 90.0
        assert rows[0]["clients_hz"][k] == 0.0 and rows[2]["clients_hz"][k] == 0.0
    if "foxglove" in outputs_on:  # poses at its rate_hz (30) on the ticks' times: 25/s
        assert rows[1]["clients_hz"]["foxglove"] > 20.0 and rows[2]["clients_hz"]["foxglove"] == 0.0
    assert run["tracked_fraction"] > 0.95
