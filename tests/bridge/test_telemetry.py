"""bridge/telemetry.py: the rings and the pairing of the autopilot's telemetry on common instants."""

import numpy as np

from bridge.telemetry import Ring, sample_at


def test_sample_at_interpolates_inside_the_span_and_not_across_a_gap():
    t = np.array([0, 10, 20, 200], dtype=np.int64)  # a 180 ns gap after 20
    v = np.array([[0.0, 1.0], [10.0, 1.0], [20.0, 1.0], [200.0, 1.0]])
    ok, out = sample_at(np.array([-5, 0, 5, 20, 50, 200, 250]), t, v, max_gap_ns=100)
    assert ok.tolist() == [False, True, True, True, False, False, False]
    assert out[1:4, 0].tolist() == [0.0, 5.0, 20.0]
    ok, out = sample_at(np.array([5]), t[:1], v[:1], 100)  # one sample: nothing to interpolate
    assert not ok.any() and np.isnan(out).all()


def test_ring_keeps_the_newest_and_reads_back_since_a_time():
    r = Ring(3, 2)
    for k in range(5):
        r.add(k * 10, (k, -k))
    assert len(r) == 3 and r.n == 5 and r.last_t() == 40
    t, v = r.since(30)
    assert t.tolist() == [30, 40] and v.tolist() == [[3.0, -3.0], [4.0, -4.0]]
