"""The freshness bench's bookkeeping (the live run itself is `visionpos bench --only freshness`)."""

from types import SimpleNamespace

import numpy as np

from visionpos.benchmarks.freshness import _AgeSink, ages


def _state(t_ns, capture_ns, tracked=True):
    return SimpleNamespace(time_ns=t_ns, capture_ns=capture_ns, tracked=tracked)


def test_the_sink_records_tracked_states_only_while_the_stations_stream():
    aligner = SimpleNamespace(newest_ns=95, last_fused_ns=90)
    sink = _AgeSink(SimpleNamespace(pipeline=SimpleNamespace(aligner=aligner)))
    sink.publish([_state(100, 94)])
    assert sink.rows == []  # not recording yet
    sink.recording, sink.until_ns = True, 200
    sink.publish([_state(100, 94), _state(100, 50, tracked=False)])
    sink.publish([_state(200, 194)])
    sink.publish([_state(210, 194)])  # after the last frame was sent: no new frame could reach it
    assert sink.rows == [(100, 94, 95, 90), (200, 194, 95, 90)]


def test_ages_are_tick_minus_capture_and_a_late_tick_is_placed_by_its_stage():
    period_ms = 10.0
    ms = 1_000_000
    rows = [(100 * ms, 95 * ms, 99 * ms, 99 * ms)] * 98  # 5 ms old, everything fresh
    rows += [(200 * ms, 185 * ms, 186 * ms, 186 * ms)]  # 15 ms: nothing newer was admitted
    rows += [(300 * ms, 288 * ms, 299 * ms, 288 * ms)]  # 12 ms: a newer frame was admitted but not fused
    a = ages(rows, period_ms)
    assert a["ticks"] == 100 and a["age_ms_p50"] == 5.0 and a["age_ms_max"] == 15.0
    assert a["late_fraction"] == 0.02 and a["late_not_admitted"] == 0.5 and a["late_not_fused"] == 0.5
    assert np.isclose(a["age_p99_periods"], np.percentile([5.0] * 98 + [15.0, 12.0], 99) / period_ms)
