"""The demo memory benchmark's logic (visionpos/benchmarks/demo_memory.py): the growth fit, and a short run."""

from __future__ import annotations

import numpy as np
import pytest

from visionpos.benchmarks.demo_memory import growth_mb_per_min, measure


def test_growth_is_the_slope_after_start_up_in_mb_per_minute():
    t = np.arange(0.0, 120.0, 1.0)
    # start-up: 100 MB in the first 10 s, then 17 MB/min (the collector that kept every pose) with page noise
    rss = np.where(t < 10, 1e7 * t, 1e8 + (t - 10) * 17e6 / 60) + np.random.default_rng(1).normal(0, 2e5, len(t))
    assert growth_mb_per_min(t, rss) == pytest.approx(17.0, abs=0.2)
    assert growth_mb_per_min(t, np.full(len(t), 3e8)) == pytest.approx(0.0, abs=1e-9)
    # a short run: the settle time is at most half of it
    assert growth_mb_per_min(t[:10], 1e8 + t[:10] * 1e6) == pytest.approx(60.0)
    assert np.isnan(growth_mb_per_min(t[:2], t[:2]))


@pytest.mark.slow
def test_a_short_demo_is_sampled_every_second():
    m = measure(8.0)  # the growth is fitted over the second half: 4 samples
    assert 7 <= len(m["rss_bytes"]) <= 10
    assert (m["rss_bytes"] > 50e6).all()  # a demo with numpy, scipy and numba loaded
    assert np.isfinite(m["growth_mb_per_min"])
    assert m["tracked_fraction"] > 0.8
