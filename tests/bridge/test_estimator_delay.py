"""The delay advice per estimator, on made-up delays whose statistics are worked out by hand."""

import numpy as np
import pytest

from bridge.estimator_delay import advised_delay


def _delays():
    """100 delays (ms): 96 spread evenly 10.0 .. 29.0 (step 0.2), two at 6 and two at 60 (a late burst). Sorted:
    6, 6, 10.0, 10.2, ... 29.0, 60, 60. numpy's p2 (linear): h = 99 * 0.02 = 1.98, between the 2nd (6) and the
    3rd (10.0): 6 + 0.98 * 4 = 9.92 -> 10. Median: mean of the 50th and 51st values, 10 + 47 * 0.2 = 19.4 and
    19.6: 19.5 -> 20 (round half to even gives 20)."""
    rng = np.random.default_rng(1)
    d = np.concatenate([10.0 + 0.2 * np.arange(96), [6.0, 6.0, 60.0, 60.0]])
    return rng.permutation(d)


def test_ardupilot_wants_about_the_smallest_delay():
    a = advised_delay("ardupilot", _delays())
    assert (a.param, a.value_ms) == ("VISO_DELAY_MS", 10)
    assert "smallest" in a.why


def test_px4_on_arrival_wants_the_median_and_with_timesync_zero():
    a = advised_delay("px4", _delays())
    assert (a.param, a.value_ms) == ("EKF2_EV_DELAY", 20)
    assert "arrival" in a.why
    b = advised_delay("px4", _delays(), px4_timesync_converged=True)
    assert (b.param, b.value_ms) == ("EKF2_EV_DELAY", 0)


def test_constant_delay_gives_that_delay_to_both_and_nothing_without_delays():
    for ap in ("ardupilot", "px4"):
        assert advised_delay(ap, np.full(50, 7.4)).value_ms == 7
    assert advised_delay("ardupilot", np.array([])) is None
    assert advised_delay("px4", np.array([np.nan])) is None
    assert advised_delay(None, np.full(5, 3.0)).param == "VISO_DELAY_MS"


@pytest.mark.parametrize("shift", [0.0, 20.0, 50.0])
def test_an_added_link_delay_moves_both_by_as_much(shift):
    assert advised_delay("ardupilot", _delays() + shift).value_ms == 10 + shift
    assert advised_delay("px4", _delays() + shift).value_ms == 20 + shift


# ------------------------------------------------------------------ PX4's ESTIMATOR_STATUS in words
def test_px4_estimator_status_in_plain_words():
    from bridge.px4_status import ev_fusion_state

    state, why = ev_fusion_state(0x1EF, 0.05, 0.1, 0.02, sending=True)  # what SIH showed fusing EV
    assert state == "using vision" and "0x1ef" in why and "height" in why
    state, why = ev_fusion_state(0x1, 0.3, 2.4, 0.2, sending=True)
    assert state == "rejecting vision" and "height test ratio is 2.40" in why
    state, why = ev_fusion_state(0x1, 0.0, 0.0, 0.0, sending=True)
    assert state == "not using vision" and "MOCAP is never fused" in why and "EKF2_EV_CTRL" in why
    assert ev_fusion_state(0x0, 0.0, 0.0, 0.0, sending=True)[1].startswith("EKF2 has no attitude")
    state, why = ev_fusion_state(0x1, 3.0, 0.0, 0.0, sending=False)  # ratios left over: not a rejection now
    assert state == "not using vision" and "no pose" in why
