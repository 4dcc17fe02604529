"""The simulated camera source renders the scenario at the frame's capture time on the shared clock (issue 15)."""

from __future__ import annotations

import numpy as np

from stations.config import SourceConfig
from stations.sources import make_source

S = 1_000_000_000


class FakeClock:
    def __init__(self, t: int):
        self.t = t

    def __call__(self) -> int:
        return self.t


def _source(clock, offset_ns=0, camera_id=1):
    """A realtime simulated camera whose station clock is the shared clock + offset_ns (its sync knows it)."""
    cfg = SourceConfig(kind="sim", scenario="thesis", fps=0.0, realtime=True)
    src = make_source(cfg, clock, camera_id, to_shared=lambda t_local: t_local - offset_ns)
    return src


def test_stations_started_apart_render_the_same_instant_for_the_same_capture_time():
    # two station processes: one starts 3.7 s after the other, on a host whose clock is 250 s ahead
    clock_a, clock_b = FakeClock(100 * S), FakeClock(350 * S + 3_700_000_000)
    a, b = _source(clock_a), _source(clock_b, offset_ns=250 * S)
    a.open()
    b.open()
    a.pacer.period = b.pacer.period = 0.0  # no real-time sleeps in a test
    positions = []
    for shared in (104 * S, 104 * S + 400_000_000, 109 * S):
        clock_a.t, clock_b.t = shared, shared + 250 * S
        img_a, t_a = a.read()
        img_b, t_b = b.read()
        assert t_a == shared and t_b == shared + 250 * S  # stamps stay on each station's own clock
        assert a.last_scenario_ns == b.last_scenario_ns
        ok = np.isfinite(a.last_truth[:, 0])
        assert ok.sum() >= 3
        np.testing.assert_array_equal(a.last_truth, b.last_truth)
        positions.append(a.last_truth[ok])
    # the flight moves between those instants, so agreeing is not trivial
    assert np.abs(positions[0] - positions[1]).max() > 1.0


def test_unsynced_station_renders_at_its_own_clock():
    clock = FakeClock(42 * S)
    cfg = SourceConfig(kind="sim", scenario="thesis", realtime=True)
    src = make_source(cfg, clock, 2, to_shared=lambda t_local: None)
    src.open()
    src.pacer.period = 0.0
    src.read()
    assert src.last_scenario_ns == src.scenario.start_ns + (42 * S) % int(src.scenario.duration_s * 1e9)
