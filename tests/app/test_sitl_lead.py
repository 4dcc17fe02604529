"""Timing the EKF against SITL's truth (issue 31): the circle flown for it, the fit with each turn's drift taken
out, PX4's clock rate in the truth, PX4's log read on the circle, EKF2_EV_DELAY set to the advice in flight."""

from __future__ import annotations

import asyncio
import math
import types

import numpy as np
import pytest

from visionpos.app import sitl as S
from visionpos.app.sitl.flight import CIRCLE_PERIOD_S, CIRCLE_RADIUS_M, circle_at, fly_circle

HOME = (-35.363261, 149.165230, 584.0)
W = 2 * math.pi / 3.0  # the circle's rate: 3 s a turn


def test_the_circle_starts_north_of_its_centre_and_turns_east_at_a_steady_speed():
    assert (CIRCLE_RADIUS_M, CIRCLE_PERIOD_S) == (0.5, 3.0)
    assert circle_at(0.0) == pytest.approx((0.5, 0.0, 0.0, 0.5 * W))
    assert circle_at(0.75) == pytest.approx((0.0, 0.5, -0.5 * W, 0.0), abs=1e-12)  # a quarter turn: east
    assert circle_at(1.5) == pytest.approx((-0.5, 0.0, 0.0, -0.5 * W), abs=1e-12)


def test_fly_circle_sends_the_setpoints_and_records_the_span_after_the_first_turn():
    sent = []
    record: dict = {}
    asyncio.run(fly_circle(lambda *x: sent.append(x), (2.0, 3.0), 3.6, record, lambda text: None))
    a, b = record["circle"]
    assert (b - a) * 1e-9 == pytest.approx(0.6, abs=0.1)  # 3.6 s less the first 3 s turn
    x = np.array(sent)
    assert len(x) >= 50 and np.allclose(np.hypot(x[:, 0] - 2.0, x[:, 1] - 3.0), 0.5)
    assert np.allclose(np.hypot(x[:, 2], x[:, 3]), 0.5 * W)
    # the velocity is the setpoint's own rate: tangent, turning east from the north point
    assert np.allclose((x[:, 0] - 2.0) * x[:, 2] + (x[:, 1] - 3.0) * x[:, 3], 0.0, atol=1e-9)
    assert x[0, :2] == pytest.approx((2.5, 3.0), abs=0.01) and x[0, 3] > 0


def test_moving_mean_by_hand():
    from visionpos.app.sitl.report import minus_moving_mean

    t = np.arange(7) * 10
    y = np.array([[0.0], [1.0], [2.0], [3.0], [4.0], [5.0], [12.0]])
    got, whole = minus_moving_mean(t, y, 20)  # each sample with its two neighbours
    assert got[3, 0] == pytest.approx(3.0 - (2.0 + 3.0 + 4.0) / 3)
    assert got[5, 0] == pytest.approx(5.0 - (4.0 + 5.0 + 12.0) / 3)
    assert got[0, 0] == pytest.approx(0.0 - 0.5)  # one-sided at the ends ...
    assert whole.tolist() == [False, True, True, True, True, True, False]  # ... and marked so


def test_the_detrended_fit_sees_through_a_drift_that_moves_the_plain_one():
    """A 1.05 m/s circle for 26 s; the 'EKF' 3 ms ahead of it plus a drift of a few cm wandering over seconds
    (SIH's IMU): the fit with each turn's mean taken out finds the 3 ms, the plain one is thrown off."""
    from visionpos.app.sitl.report import time_shift_fit

    t = np.arange(0, 26.0, 0.01)
    pos = lambda s: 0.5 * np.column_stack([np.cos(W * s), np.sin(W * s)])  # noqa: E731
    vel = 0.5 * W * np.column_stack([-np.sin(W * t), np.cos(W * t)])
    drift = np.column_stack([0.05 * np.sin(2 * np.pi * t / 12 + 1.0), 0.04 * np.cos(2 * np.pi * t / 15.6)])
    err = pos(t + 0.003) - pos(t) + drift + 0.02 * t[:, None] / 26
    t_ns = (t * 1e9).astype(np.int64)
    lead, se, n = time_shift_fit(t_ns, err, vel, detrend_ns=3_000_000_000)
    assert lead == pytest.approx(3.0, abs=0.2) and se < 1.0 and n == np.sum((t >= 1.5) & (t <= t[-1] - 1.5))
    plain, plain_se, _ = time_shift_fit(t_ns, err, vel)
    assert abs(plain - 3.0) > 0.8 and plain_se > 4 * se


def test_clock_rate_is_the_slope_of_the_timesync_answers():
    from visionpos.app.sitl.clock import clock_rate

    rng = np.random.default_rng(4)
    ours = 5_000_000_000 + np.arange(0, 12_000_000_000, 250_000_000)
    theirs = 77_000_000_000 + 0.985 * (ours - ours[0]) + rng.uniform(0, 600_000, len(ours))  # one-way jitter
    pairs = np.column_stack([ours, theirs]).astype(np.int64)
    assert clock_rate(pairs, 10_000_000_000, 5_000_000_000) == pytest.approx(0.985, abs=2e-4)
    assert clock_rate(pairs[:12], 10_000_000_000, 5_000_000_000) is None  # 2.75 s: too short a span


def test_px4_gcs_follows_px4s_clock_into_the_truth():
    from visionpos.app.ports import free_port
    from visionpos.app.sitl import px4 as P

    gcs = P.Px4Gcs({"gcs": free_port(), "onboard": 0, "truth": free_port()}, S.TruthTrack(HOME))
    for k in range(30):  # 7.25 s of answers from a clock running 1.5 % slow
        s1 = 1_000_000_000 + k * 250_000_000
        gcs.clock.pending[s1] = s1
        gcs._handle(types.SimpleNamespace(get_type=lambda: "TIMESYNC", tc1=int(9e9 + 0.985 * (s1 - 1e9)), ts1=s1),
                    s1 + 100_000)
    assert gcs.truth.rate == pytest.approx(0.985, abs=1e-6) and len(gcs.clock_rates) >= 1
    gcs._handle(types.SimpleNamespace(get_type=lambda: "TIMESYNC", tc1=int(1e15), ts1=123), 0)  # not ours: ignored
    assert gcs.truth.rate == pytest.approx(0.985, abs=1e-6)


def _state(north, v_north):
    lat_e7 = int(round(HOME[0] * 1e7)) + int(round(north / S.LATLON_TO_M))
    return types.SimpleNamespace(lat_int=lat_e7, lon_int=int(round(HOME[1] * 1e7)), alt=HOME[2] + 1.0, vn=v_north,
                                 ve=0.0, vd=0.0, q1=1.0, q2=0.0, q3=0.0, q4=0.0, xgyro=0.0, ygyro=0.0, zgyro=0.3)


@pytest.mark.parametrize("told_rate, worst_mm", [(0.985, 1.5), (1.0, None)])
def test_the_truth_runs_on_our_clock_when_told_the_simulations_rate(told_rate, worst_mm):
    """A simulation whose clock runs 1.5 % slow of ours: 1 m/s north on its clock is 0.985 m/s on ours. Told the
    rate, the track's velocities, rates and positions are ours; not told, the positions run ahead (the
    integration at 1 m/s pulled back only slowly to the centimetre-quantised latitude)."""
    track = S.TruthTrack(HOME)
    track.rate = told_rate
    t0, dt_ns = 10_000_000_000, 10_000_000
    for k in range(1000):
        sim_s = 0.985 * k * dt_ns * 1e-9
        track.add(t0 + k * dt_ns, _state(1.0 * sim_s, 1.0))
    times = t0 + np.arange(500, 999) * dt_ns + 5_000_000
    pos, vel, _, _ = track.sample(times)
    true_north = 0.985 * (times - t0) * 1e-9  # world x = north
    err_mm = np.abs(pos[:, 0] - true_north) * 1e3
    if worst_mm is None:
        assert err_mm.mean() > 5.0  # the lead the flights measured before the rate was followed
    else:
        assert err_mm.max() < worst_mm and np.allclose(vel[:, 0], 0.985)
        assert np.allclose(track.snapshot()[1][-1, 12], 0.985 * -0.3)  # yaw rate, FRD down -> FLU up, our clock


def _log_circle(vision_age_s, output_lead_s, hover_s=10.0, circle_s=26.0):
    """PX4's log made up: a hover, then the circle (3 s a turn, 0.5 m); the vision samples stamped on arrival,
    vision_age_s after the position they carry, 20 ms apart, plus an offset of the vision's frame; EKF2's output
    output_lead_s ahead of the truth, every 8 ms; SIH's truth at 250 Hz. Times in us."""
    def truth(s):
        on = np.clip(s - hover_s, 0.0, None) * (s > hover_s)
        p = 0.5 * np.column_stack([np.cos(W * on), np.sin(W * on)])
        v = 0.5 * W * np.column_stack([-np.sin(W * on), np.cos(W * on)]) * (s > hover_s)[:, None]
        return p, v

    end = hover_s + circle_s
    tt = np.arange(0, int(end * 1e6), 4_000)
    ev_t = np.arange(1_000_000, int(end * 1e6), 20_000)
    out_t = np.arange(1_000_000, int(end * 1e6), 8_000)
    gp, gv = truth(tt * 1e-6)
    return (ev_t, truth(ev_t * 1e-6 - vision_age_s)[0] + [0.2, -0.1], out_t, truth(out_t * 1e-6 + output_lead_s)[0],
            tt, gp, gv)


def test_px4_log_on_the_circle_gives_the_outputs_lead_and_the_visions_age():
    from visionpos.app.sitl.px4_log import circle_leads, circle_span

    ev_t, ev_xy, out_t, out_xy, tt, gp, gv = _log_circle(0.021, -0.004)
    a, b = circle_span(tt * 1000, gv)
    assert a * 1e-9 == pytest.approx(10.0 + 3.0, abs=0.01) and b * 1e-9 == pytest.approx(36.0, abs=0.01)
    got = circle_leads(ev_t, ev_xy, out_t, out_xy, tt, gp, gv)
    assert got["output_lead_circle_ms"] == pytest.approx(-4.0, abs=0.1)
    assert got["vision_delay_circle_ms"] == pytest.approx(21.0, abs=0.1)
    # a flight without its circle: nothing
    ev_t, ev_xy, out_t, out_xy, tt, gp, gv = _log_circle(0.021, -0.004, circle_s=2.0)
    assert circle_leads(ev_t, ev_xy, out_t, out_xy, tt, gp, gv) == {}


class _StubGcs:
    def __init__(self, horizon_ms):
        self.params = {"EKF2_DELAY_MAX": horizon_ms}
        self.set: list[dict] = []

    async def set_params_async(self, values):
        self.set.append(values)


@pytest.mark.parametrize("advised, horizon_needed, booted, sets", [
    (19, 50, 60, True),   # differs and fits: set in flight
    (15, 50, 60, False),  # the value already set
    (31, 70, 60, False),  # needs more history than PX4 started with: kept, and said
])
def test_ev_delay_follows_the_advice_in_flight_within_the_booted_horizon(advised, horizon_needed, booted, sets):
    from bridge.estimator_delay import DelayAdvice
    from visionpos.app.sitl.px4_run import set_advised_ev_delay

    gcs, said = _StubGcs(booted), []
    record = {"viso_delay_ms": 15}
    advice = DelayAdvice("EKF2_EV_DELAY", advised, "the mean", "EKF2_DELAY_MAX", horizon_needed, "why")
    asyncio.run(set_advised_ev_delay(gcs, advice, record, said.append))
    assert (gcs.set == [{"EKF2_EV_DELAY": float(advised)}]) is sets
    assert record["viso_delay_ms"] == (advised if sets else 15)
    assert ("ev_delay_set_ns" in record) is sets
    if advised == 31:
        assert "EKF2_DELAY_MAX=70" in said[0] and "started with 60" in said[0]
    asyncio.run(set_advised_ev_delay(gcs, None, record, said.append))  # no advice yet: nothing
    assert len(gcs.set) == int(sets)


def test_ev_delay_follows_each_renewed_advice_while_circling(monkeypatch):
    """docs/autopilot-setup.md section 0: the flight sets the advice each time it is renewed while circling."""
    from pathlib import Path

    from bridge.backchannel import DELAY_EVERY_NS
    from bridge.estimator_delay import DelayAdvice
    from visionpos.app.sitl import px4_run
    assert px4_run.ADVICE_EVERY_S == DELAY_EVERY_NS * 1e-9 == 5.0
    monkeypatch.setattr(px4_run, "ADVICE_EVERY_S", 0.01)
    advices = iter([17, 17, 19, 19, 18] + [18] * 1000)
    gcs, said = _StubGcs(60), []
    record = {"viso_delay_ms": 17, "circle_ev_delays_ms": [17]}

    async def circle():
        task = asyncio.create_task(px4_run._follow_advice(
            gcs, lambda: DelayAdvice("EKF2_EV_DELAY", next(advices), "mean", "EKF2_DELAY_MAX", 50, "why"), record,
            said.append))
        await asyncio.sleep(0.3)
        task.cancel()

    asyncio.run(circle())
    assert gcs.set[:2] == [{"EKF2_EV_DELAY": 19.0}, {"EKF2_EV_DELAY": 18.0}] and len(gcs.set) == 2
    assert record["circle_ev_delays_ms"] == [17, 19, 18] and record["viso_delay_ms"] == 18
    doc = " ".join((Path(__file__).resolve().parents[2] / "docs" / "autopilot-setup.md").read_text().split())
    assert "again before the circle and each time the back-channel renews it while circling (every 5 s)" in doc

    # PX4 does not echo one: said, kept, and the next advice still goes
    class _Refuses(_StubGcs):
        async def set_params_async(self, values):
            if not self.set:
                self.set.append(None)
                raise S.SitlError("no PARAM_VALUE")
            self.set.append(values)

    advices = iter([19, 20] + [20] * 1000)
    gcs, said = _Refuses(60), []
    record = {"viso_delay_ms": 17, "circle_ev_delays_ms": [17]}
    asyncio.run(circle())
    assert gcs.set[:2] == [None, {"EKF2_EV_DELAY": 20.0}] and record["circle_ev_delays_ms"] == [17, 20]
    assert any("not changed in flight: no PARAM_VALUE" in x for x in said)


def test_the_px4_keepalive_streams_the_velocity_feed_forward():
    """Px4Gcs's offboard setpoint with the circle's velocity: SET_POSITION_TARGET_LOCAL_NED's type mask takes
    position and velocity (bits 3-5 clear), the rest ignored; without it, position only."""
    import time

    from bridge.fake_autopilot import FakeAutopilot
    from visionpos.app.ports import free_port
    from visionpos.app.sitl import px4 as P

    ap = FakeAutopilot("udpin:127.0.0.1:0", sysid=1, autopilot="px4", heartbeat_hz=10).start()
    gcs = P.Px4Gcs({"gcs": ap.port, "onboard": 0, "truth": free_port()}, S.TruthTrack(HOME))
    try:
        gcs.connect(5.0)
        gcs.setpoint, gcs.velocity = (1.0, 2.0, -1.0), (0.3, -0.4, 0.0)
        time.sleep(0.3)
        gcs.velocity = None
        time.sleep(0.3)
    finally:
        gcs.close()
        ap.close()
    sp = [r.fields for r in ap.received if r.type == "SET_POSITION_TARGET_LOCAL_NED"]
    with_v = [m for m in sp if m["type_mask"] == 0b1111_1100_0000]
    assert with_v and (with_v[0]["vx"], with_v[0]["vy"]) == pytest.approx((0.3, -0.4))
    assert (with_v[0]["x"], with_v[0]["y"], with_v[0]["z"]) == pytest.approx((1.0, 2.0, -1.0))
    assert sp[-1]["type_mask"] == 0b1111_1111_1000 and sp[-1]["vx"] == 0.0


def test_the_flight_summary_prints_the_circles_lead():
    from visionpos.app.sitl.report import format_flight

    s = {"completed": True, "wall_s": 80.0, "vision": {"poses_sent": 10}, "ekf_lead_circle_ms": -1.23,
         "ekf_lead_circle_se_ms": 0.71, "ekf_lead_circle_samples": 2900, "failsafe_or_lane_switch": [],
         "mode_changes_not_ours": [], "statustext": [], "ok": True}
    assert "on the circle: EKF ahead of the truth by -1.2 ms +- 0.7 (2900 samples after the first turn" in \
        format_flight(s)


def test_sitl_cli_checks_the_circle(capsys):
    from visionpos.cli import main

    assert main(["sitl", "--circle", "200"]) == 2
    assert "--circle 200.0: give 0 to 120 s" in capsys.readouterr().err
    assert main(["sitl", "--circle", "10", "--vehicles", "2"]) == 2
    assert "--circle: one vehicle only" in capsys.readouterr().err


def test_the_docs_say_what_the_px4_flight_does_with_the_circle_and_the_delay():
    """docs/autopilot-setup.md section 0 and 3: the circle, the room EKF2's history is booted with, the advice set
    in flight; the figures are the code's."""
    from pathlib import Path

    from visionpos.app.sitl import px4_run
    from visionpos.app.sitl.flight import CIRCLE_SPEED_M_S

    doc = " ".join((Path(__file__).resolve().parents[2] / "docs" / "autopilot-setup.md").read_text().split())
    assert "with `--circle S` flies S seconds round a 0.5 m circle (3 s a turn, 1.05 m/s)" in doc
    assert (CIRCLE_RADIUS_M, CIRCLE_PERIOD_S, round(CIRCLE_SPEED_M_S, 2)) == (0.5, 3.0, 1.05)
    assert "`EKF2_DELAY_MAX` sized (section 3) for `EKF2_EV_DELAY` + 10 ms" in doc
    assert px4_run.ADVICE_HEADROOM_MS == 10.0 and px4_run.FIRST_EV_DELAY_MS == 15.0
    assert "Otherwise PX4 starts with 15 ms (plus the link delay), and the flight sets the value the bridge " \
           "advises" in doc
    assert "the bridge advises the **mean** stamp-to-arrival delay" in doc
