"""The delay advice per estimator, on made-up delays whose statistics are worked out by hand."""

import math

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


def test_ardupilot_wants_the_smallest_delay_of_its_jitter_window():
    # 100 delays: one window of ArduPilot's JitterCorrection, whose smallest (6) every pose gets
    a = advised_delay("ardupilot", _delays())
    assert (a.param, a.value_ms) == ("VISO_DELAY_MS", 6)
    assert "smallest" in a.why


def test_jitter_corrected_delay_is_the_median_of_each_100_poses_smallest():
    from bridge.estimator_delay import jitter_corrected_delay_ms

    d = np.full(250, 20.0)
    d[10], d[150], d[220] = 5.0, 7.0, 3.0  # windows 0-99, 100-199 and the last 50 (half a window: counted)
    assert jitter_corrected_delay_ms(d) == 5.0  # median of 5, 7, 3
    assert jitter_corrected_delay_ms(d[:240]) == 6.0  # the last 40 are too few: median of 5 and 7
    assert jitter_corrected_delay_ms(np.array([9.0, 4.0, 8.0])) == 4.0  # under one window: the smallest
    # in arrival order: the same values sorted make other windows (minima 3, 20, 20 -> 20)
    assert jitter_corrected_delay_ms(np.sort(d)) == 20.0


def test_px4_on_arrival_wants_the_mean_and_what_ekf2_trails_by_and_with_timesync_zero():
    # _delays(): 96 from 10.0 to 29.0 (sum 96 * 19.5 = 1872) and 6, 6, 60, 60 (132): mean 2004 / 100 = 20.04;
    # EKF2 on the mean trails as if 1.35 ms older on VISION_POSITION_ESTIMATE, and on ODOMETRY as if 1.26 ms
    # younger plus 9.4 % of the mean, at least 0.05 ms and at most 1.93 ms older (docs/autopilot-setup.md, 3.); to
    # 0.1 ms, EKF2_EV_DELAY being a float: 21.39 -> 21.4; 20.04 - 1.26 + 1.88376 = 20.66376 -> 20.7
    from pathlib import Path

    from bridge.estimator_delay import EKF2_ARRIVAL_TRAIL_MS
    assert EKF2_ARRIVAL_TRAIL_MS == {"vision_position_estimate": (1.35, 0.0, 1.35, 1.35),
                                     "odometry": (-1.26, 0.094, 0.05, 1.93)}
    doc = " ".join((Path(__file__).resolve().parents[2] / "docs" / "autopilot-setup.md").read_text().split())
    assert "the bridge advises the **mean** stamp-to-arrival delay, **plus 1.35 ms** on VISION_POSITION_ESTIMATE, " \
           "and on ODOMETRY **0.05 ms** on a direct link, **1.93 ms** through a slow one" in doc
    a = advised_delay("px4", _delays())
    assert (a.param, a.value_ms) == ("EKF2_EV_DELAY", 21.4)
    assert "mean" in a.why and "arrival" in a.why and "+1.35 ms" in a.why
    o = advised_delay("px4", _delays(), message="odometry")
    assert o.value_ms == 20.7 and "+0.62 ms" in o.why and "ODOMETRY" in o.why
    # through a slow link EKF2 on ODOMETRY trails more, at most 1.93 ms: at a mean of 65 ms (-1.26 + 6.11 = 4.85 over
    # the most) 66.93 -> 66.9; on a direct link at least 0.05 ms: at 10.02 ms (-1.26 + 0.94 = -0.32 under the
    # least) 10.07 -> 10.1
    assert advised_delay("px4", np.full(50, 65.0), message="odometry").value_ms == 66.9
    assert advised_delay("px4", np.full(50, 10.02), message="odometry").value_ms == 10.1
    # a long tail (90 poses at 15 ms, 10 at 45 after stalls): the median 15, the mean 18, which EKF2 follows: 19.35
    assert advised_delay("px4", np.r_[np.full(90, 15.0), np.full(10, 45.0)]).value_ms == 19.4
    b = advised_delay("px4", _delays(), px4_timesync_converged=True)
    assert (b.param, b.value_ms) == ("EKF2_EV_DELAY", 0)


def test_constant_delay_gives_that_delay_to_both_and_nothing_without_delays():
    assert advised_delay("ardupilot", np.full(50, 7.4)).value_ms == 7
    assert advised_delay("px4", np.full(50, 7.42)).value_ms == 8.8  # 7.42 + 1.35 = 8.77, to 0.1 ms
    assert advised_delay("ardupilot", np.array([])) is None
    assert advised_delay("px4", np.array([np.nan])) is None
    assert advised_delay(None, np.full(5, 3.0)).param == "VISO_DELAY_MS"


@pytest.mark.parametrize("shift", [0.0, 20.0, 50.0])
def test_an_added_link_delay_moves_both_by_as_much(shift):
    assert advised_delay("ardupilot", _delays() + shift).value_ms == 6 + shift
    assert advised_delay("px4", _delays() + shift).value_ms == pytest.approx(21.4 + shift)


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


def test_ekf3_history_follows_its_largest_delay_in_whole_12_ms_slots():
    # NavEKF3_core::setup_core: floor(M / 12) + 1 samples, the oldest floor(M / 12) steps of >= 12 ms back
    from bridge.estimator_delay import ekf3_history_ms, ekf3_largest_delay_for
    assert ekf3_history_ms(60) == 60
    assert ekf3_history_ms(70) == 60  # 70 // 12 = 5 slots: the D = 50 ms relay's boot value fell short this way
    assert ekf3_history_ms(300) == 240  # the parameters stop at 250: 20 slots
    assert ekf3_largest_delay_for(66) == 72
    assert ekf3_largest_delay_for(72) == 72
    assert ekf3_history_ms(ekf3_largest_delay_for(91.5)) >= 91.5


def test_ardupilot_names_the_buffer_when_poses_outlive_ekf3s_default_history():
    # a direct link's delays: p99 7.4 + half a step 6 = 13.4 ms, well inside EK3_HGT_DELAY's 60 ms: nothing to add
    assert advised_delay("ardupilot", np.full(50, 7.4)).horizon_param is None
    # _delays(): p99 = 60 (h = 99 * 0.99 = 98.01, between the two 60s), + 6 = 66 > 60 -> 12 * ceil(66 / 12) = 72
    a = advised_delay("ardupilot", _delays())
    assert (a.horizon_param, a.horizon_ms) == ("EK3_BCN_DELAY", 72)
    assert "reboot" in a.horizon_why
    # 50 ms more: p99 110 + 6 = 116 -> 120
    assert advised_delay("ardupilot", _delays() + 50.0).horizon_ms == 120
    # 200 ms more: 266 needs 276, past the parameter's 250: the largest, and the link called too slow
    b = advised_delay("ardupilot", _delays() + 200.0)
    assert b.horizon_ms == 250 and "too slow" in b.horizon_why


def test_px4_horizon_holds_the_setting_in_eight_ms_steps_or_the_p99_with_timesync():
    # EKF2_EV_DELAY 21 ms, moved back half an 8 ms step: 25 ms, 4 steps; + the newest and the margin: 6 steps of
    # EKF2_PREDICT_US (10 ms)
    a = advised_delay("px4", _delays())
    assert (a.horizon_param, a.horizon_ms) == ("EKF2_DELAY_MAX", 60)
    # TIMESYNC: the delays' p99, 60 ms (see _delays): 8 steps of 8 ms, + 2: 100 ms
    b = advised_delay("px4", _delays(), px4_timesync_converged=True)
    assert (b.horizon_param, b.horizon_ms) == ("EKF2_DELAY_MAX", 100)


@pytest.mark.parametrize("oldest_ms", [0.0, 3.0, 8.0, 19.0, 24.0, 24.5, 54.0, 69.0, 150.0])
def test_ekf2s_history_reaches_the_oldest_pose_with_a_step_to_spare(oldest_ms):
    """EKF2 keeps ceil(EKF2_DELAY_MAX / 10 ms) IMU steps (EstimatorInterface::initialise_interface); with SIH's
    250 Hz IMU a step is two 4 ms samples, so the history reaches (steps - 1) x 8 ms back. The advised setting
    reaches the pose and a step more; 10 ms less would not."""
    from bridge.estimator_delay import ekf2_horizon_ms

    def reach(setting_ms):
        return (math.ceil(setting_ms / 10.0) - 1) * 8.0

    h = ekf2_horizon_ms(oldest_ms)
    assert h % 10 == 0 and reach(h) >= oldest_ms + 8.0 > reach(h - 10)


def test_the_docs_say_how_the_horizon_is_advised():
    """docs/autopilot-setup.md section 3: the figures of the horizon rule are the code's."""
    from pathlib import Path

    import bridge.estimator_delay as ed
    from visionpos.app.sitl import preflight

    doc = " ".join((Path(__file__).resolve().parents[2] / "docs" / "autopilot-setup.md").read_text().split())
    assert "floor(M / 12 ms) + 1" in doc and ed.EKF3_SLOT_MS == 12
    assert "`EK3_HGT_DELAY`, 60 ms by default" in doc and ed.EKF3_DEFAULT_LARGEST_DELAY_MS == 60
    assert "p99 + 6 ms" in doc and ed.HORIZON_PERCENTILE == 99.0 and ed.EKF3_HALF_STEP_MS == 6.0
    assert "(at most 250)" in doc and ed.EKF3_MAX_DELAY_MS == 250 and ed.EKF3_HORIZON_PARAM == "EK3_BCN_DELAY"
    assert "`delay.horizon_param` and `delay.horizon_ms`" in doc
    assert "10 ms x (ceil(age / 8 ms) + 2)" in doc and (ed.EKF2_PREDICT_MS, ed.EKF2_STEP_MIN_MS) == (10.0, 8.0)
    assert "50 ms for an `EKF2_EV_DELAY` of 16-20 ms" in doc
    assert ed.ekf2_horizon_ms(16 + 4) == ed.ekf2_horizon_ms(20 + 4) == 50 < ed.ekf2_horizon_ms(21 + 4)
    assert "sized for poses up to 40 ms + the link's delay old" in doc and preflight.EXPECTED_LATE_MS == 40.0


def test_ardupilot_takes_the_ports_transfer_time_off_each_arrival():
    from bridge.estimator_delay import ardupilot_transfer_ms

    # 117 payload + 12 framing + 13 signature bytes, 10 bits each, at 921600 bit/s: 1420 / 921600 s
    assert ardupilot_transfer_ms("vision_position_estimate", True, 921_600) == pytest.approx(1.5408, abs=1e-4)
    # ODOMETRY (233 payload bytes in ArduPilot's generated headers, quality included), unsigned, on a 57600
    # radio: 245 bytes -> 42.53 ms
    assert ardupilot_transfer_ms("odometry", False, 57_600) == pytest.approx(42.535, abs=1e-3)
    assert ardupilot_transfer_ms("odometry", True, None) == 0.0
    # a steady 20 ms less 1.54 and the quarter ms of EKF3's stamp flooring and step: 18.21 -> 18
    a = advised_delay("ardupilot", np.full(300, 20.0), transfer_ms=1.5408)
    assert a.value_ms == 18 and "baud" in a.why
    assert advised_delay("px4", np.full(300, 20.0), transfer_ms=1.5408).value_ms == 21.4  # no such move: 20 + 1.35
