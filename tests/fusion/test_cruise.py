"""The cruise floors under the position and the rotation noise (fusion.kalman.cruise_*,
adaptation.adapt_noise_scales): they rise on a flight and stay at 1 for a still body, and the docs' word on the still
body's average is what it measures."""

from __future__ import annotations

import numpy as np
import pytest

from visionpos.benchmarks.fusion_replay import replay, static_flight
from visionpos.fusion import layout as L
from visionpos.fusion.adaptation import adapt_noise_scales
from visionpos.fusion.settings import KALMAN
from visionpos.sim import load_scenario, simulate


def _cruise(sc, sim, settings=None, floor_col=L.ADAPT_SCALE_CRUISE, nis_col=L.ADAPT_NIS_CRUISE):
    """(a cruise floor, its NIS average) of body 0 at each output tick after the first second (default: the
    position's)."""
    floor, nis, pipe = [], [], {}

    def at_frame(p):
        pipe["p"] = p

    def at_tick(t_ns, states):
        if "p" in pipe and t_ns > sc.start_ns + 1_000_000_000 and states[0].tracked:
            adapt = pipe["p"].bank.adapt[0]
            floor.append(adapt[floor_col])
            nis.append(adapt[nis_col])

    replay(sc.arena, sim.frames, settings, raw_cb=at_frame, tick_cb=at_tick)
    return np.array(floor), np.array(nis)


@pytest.fixture(scope="module")
def still():
    sc, sim = static_flight(quick=True)
    return sc, sim


@pytest.fixture(scope="module")
def slalom():
    sc = load_scenario("thesis", None, session="slalom", duration=4.0, seed=1)
    return sc, simulate(sc)


def test_a_still_body_keeps_the_hover_floor_and_its_average_is_about_one(still):
    floor, nis = _cruise(*still, {"time_alignment": "motion_compensated"})
    assert len(floor) > 100
    assert floor.max() < 1.5  # never a cruise floor worth the name
    # what the setting's text says of it (docs/configuration.md is made from it)
    text = KALMAN["cruise_nis_threshold"].doc
    assert "a still body's averages ~1.0" in text
    assert 0.9 < np.median(nis) < 1.1
    floor_r, nis_r = _cruise(*still, {"time_alignment": "motion_compensated"}, L.ADAPT_SCALE_CRUISE_R,
                             L.ADAPT_NIS_CRUISE_R)
    assert floor_r.max() < 1.5 and np.median(nis_r) < 1.1  # the rotation's too


@pytest.fixture(scope="module")
def flicks():
    sc = load_scenario("thesis", None, session="dash_sharp", duration=4.0, seed=1)
    return sc, simulate(sc)


def test_attitude_flicks_raise_the_rotation_floor_up_to_its_own_cap(flicks):
    rot = (L.ADAPT_SCALE_CRUISE_R, L.ADAPT_NIS_CRUISE_R)
    floor, nis = _cruise(*flicks, None, *rot)
    assert np.median(nis) > 1.15 and floor.max() > 5.0
    assert floor.max() <= 10.0  # cruise_max_rotation_noise_scale's default, as docs/configuration.md says
    assert KALMAN["cruise_max_rotation_noise_scale"].default == 10.0
    raised, _ = _cruise(*flicks, {"kalman": {"cruise_max_rotation_noise_scale": 30.0}}, *rot)
    assert raised.max() > 10.0 + 1e-9 and raised.max() <= 30.0
    off, _ = _cruise(*flicks, {"kalman": {"cruise_max_rotation_noise_scale": 1.0}}, *rot)
    assert np.all(off == 1.0)


def test_a_flight_raises_the_floor_up_to_its_cap_and_off_means_none(slalom):
    floor, nis = _cruise(*slalom)
    assert np.median(nis) > 1.15 and floor.max() > 10.0 and floor.max() <= 100.0
    capped, _ = _cruise(*slalom, {"kalman": {"max_noise_scale": 20.0}})
    assert capped.max() <= 20.0 + 1e-9 and capped.max() > 10.0  # never above the adaptation's own cap
    off, _ = _cruise(*slalom, {"kalman": {"cruise_max_noise_scale": 1.0}})
    assert np.all(off == 1.0)


@pytest.mark.parametrize("block", ["position", "rotation"])
def test_a_floor_moves_its_logarithm_by_the_rate_times_the_excess_and_only_its_own(block):
    """adapt_noise_scales by hand: the block's NIS held at 1.6 (threshold 1.1, rate 20/s, 1 s average) for 10 ms
    raises its floor by exp(0.01 x 20 x 0.5), the other block's (its NIS at 1.0) stays at 1; held 20 s the floor
    is at its cap (100 for the position, 10 for the rotation), and below the threshold it falls back to 1."""
    from visionpos.fusion.settings import KALMAN_PARAMS, KalmanSettings, pack_params

    position = block == "position"
    nis_col, floor_col, scale_col, other_floor, cap = (
        (L.ADAPT_NIS_CRUISE, L.ADAPT_SCALE_CRUISE, L.ADAPT_SCALE_P, L.ADAPT_SCALE_CRUISE_R, 100.0) if position else
        (L.ADAPT_NIS_CRUISE_R, L.ADAPT_SCALE_CRUISE_R, L.ADAPT_SCALE_R, L.ADAPT_SCALE_CRUISE, 10.0))
    params = pack_params(KALMAN_PARAMS, KalmanSettings())
    adapt = np.ones(L.N_ADAPT)
    adapt[nis_col] = 1.6
    clock = np.zeros(L.N_CLOCK, dtype=np.int64)

    def step(nis):
        adapt_noise_scales(adapt, clock, params, 10_000_000, 0.01, *((nis, 1.0) if position else (1.0, nis)), False,
                           np.zeros(L.N_STATE), np.zeros((L.N_STATE, L.N_STATE)), np.eye(3))  # at rest: no floor

    step(1.6)
    assert adapt[floor_col] == pytest.approx(np.exp(0.01 * 20.0 * 0.5), rel=1e-12)
    assert adapt[scale_col] >= adapt[floor_col] and adapt[other_floor] == 1.0
    for _ in range(2000):
        step(1.6)
    assert adapt[floor_col] == pytest.approx(cap)
    adapt[nis_col] = 0.6
    for _ in range(2000):
        step(0.6)
    assert adapt[floor_col] == 1.0
