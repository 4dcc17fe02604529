"""Clock-sync estimator against a simulated station clock with offset, drift
and asymmetric, jittery network delays."""

from __future__ import annotations

import numpy as np
import pytest

from stations.clocksync import ClockEstimator, ClockSync, exchange_offset_delay
from visionpos.protocol import SyncReply


def simulate(est: ClockEstimator, offset_ns: int, drift_ppm: float, n: int, period_s: float,
             fwd_ns: float, back_ns: float, jitter_ns: float, rng: np.random.Generator, t0: int = 5 * 10**9,
             back_jitter_ns: float | None = None):
    """Station clock = server + offset + drift * (server - t0). Exchanges every
    period_s; each leg has a fixed delay plus exponential queueing jitter.
    Returns the true (server - station) offset function."""

    def station(server_ns):
        return int(server_ns + offset_ns + drift_ppm * 1e-6 * (server_ns - t0))

    for k in range(n):
        s1 = t0 + int(k * period_s * 1e9)  # server-clock instant of the request send
        t1 = station(s1)
        t2 = s1 + int(fwd_ns + rng.exponential(jitter_ns))
        t3 = t2 + 20_000  # server turnaround
        bj = jitter_ns if back_jitter_ns is None else back_jitter_ns
        t4 = station(t3 + int(back_ns + (rng.exponential(bj) if bj > 0 else 0)))
        est.add(t1, t2, t3, t4)

    def true_offset_at_station(station_ns):
        # invert station(): server = (station - offset + drift*t0) / (1 + drift)
        d = drift_ppm * 1e-6
        server = (station_ns - offset_ns + d * t0) / (1 + d)
        return server - station_ns

    return station, true_offset_at_station


def test_exchange_formula():
    # station 1000 ns behind the server, 300 ns each way
    off, delay = exchange_offset_delay(t1=0, t2=1300, t3=1400, t4=700)
    assert (off, delay) == (1000, 600)


def test_offset_with_large_absolute_clocks_is_exact():
    est = ClockEstimator(min_samples=1)
    base = 1_700_000_000_000_000_000  # realtime-sized numbers, beyond float64's ns resolution
    est.add(base, base + 123_456_789 + 50_000, base + 123_456_789 + 60_000, base + 110_000)
    assert est.estimate.offset_ns == 123_456_789


@pytest.mark.parametrize("drift_ppm", [0.0, 35.0, -80.0])
def test_offset_and_drift_with_asymmetric_jittery_delays(drift_ppm):
    rng = np.random.default_rng(3)
    est = ClockEstimator(window=64)
    fwd, back = 300_000.0, 150_000.0  # asymmetric legs: irreducible bias (fwd - back) / 2 = 75 us
    station, true_off = simulate(est, offset_ns=-3_210_987_654, drift_ppm=drift_ppm, n=64, period_s=1.0,
                                 fwd_ns=fwd, back_ns=back, jitter_ns=500_000, rng=rng)
    e = est.estimate
    assert e is not None and e.samples == 64
    t_now = station(5 * 10**9 + 64 * 10**9)
    err = e.offset_at(t_now) - true_off(t_now)
    # bias from asymmetry is (fwd - back) / 2 = +75 us (NTP cannot see it); the 0.5 ms mean
    # queueing jitter per leg must be filtered out (a plain mean is off by ~0.5 ms)
    assert abs(err - (fwd - back) / 2) < 150_000, err
    assert abs(e.drift_ppm - (-drift_ppm / (1 + drift_ppm * 1e-6))) < 5.0
    # the reported 1-sigma uncertainty covers the real error
    assert abs(err) < 3 * e.uncertainty_ns
    # to_server maps station stamps onto the server clock
    server_true = 5 * 10**9 + 63 * 10**9
    assert abs(e.to_server(station(server_true)) - server_true) < 150_000


def test_min_delay_filter_beats_the_plain_mean():
    # the station's own frame stream queues its requests: jitter on the uplink only,
    # which biases a plain mean of offsets by half the mean queueing delay (2.5 ms)
    rng = np.random.default_rng(4)
    est = ClockEstimator(window=64)
    station, true_off = simulate(est, offset_ns=10**9, drift_ppm=0.0, n=64, period_s=0.5, fwd_ns=100_000,
                                 back_ns=100_000, jitter_ns=5_000_000, rng=rng, back_jitter_ns=0.0)
    s = np.array(est._samples)
    plain = np.mean(s[:, 1]) - true_off(station(5 * 10**9))
    ours = est.estimate.offset_ns - true_off(station(5 * 10**9))
    assert abs(ours) < 300_000
    assert abs(ours) < abs(plain) / 3


def test_not_valid_before_min_samples_and_rejects_implausible():
    est = ClockEstimator(min_samples=4)
    for k in range(3):
        est.add(k * 10**8, k * 10**8 + 5, k * 10**8 + 6, k * 10**8 + 11)
    assert est.estimate is None
    assert not est.add(0, 10, 20, 5)  # negative round trip: clock stepped
    assert est.rejected == 1
    est.add(4 * 10**8, 4 * 10**8 + 5, 4 * 10**8 + 6, 4 * 10**8 + 11)
    assert est.valid
    est.reset()
    assert est.estimate is None


def test_clocksync_matches_replies_to_requests():
    cs = ClockSync(1, 2, burst=2, burst_interval_s=0.1, interval_s=2.0)
    assert cs.due(0)
    r = cs.request(1000)
    assert not cs.due(1000 + 50_000_000) and cs.due(1000 + 100_000_000)
    assert not cs.reply(SyncReply(1, 2, 999, 5000, 5100, r.counter), 2000)  # wrong t1: forged/late
    assert cs.reply(SyncReply(1, 2, 1000, 5000, 5100, r.counter), 2000)
    assert not cs.reply(SyncReply(1, 2, 1000, 5000, 5100, r.counter), 2000)  # duplicate
    r2 = cs.request(200_000_000)
    assert cs.reply(SyncReply(1, 2, r2.t1_ns, 200_004_000, 200_004_100, r2.counter), 200_001_000)
    # burst done: next request only after interval_s
    assert not cs.due(200_000_000 + 10**9) and cs.due(200_000_000 + 2 * 10**9)
