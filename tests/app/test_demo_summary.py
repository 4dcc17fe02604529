"""The demo's collector (app/demo_summary.py): its running statistics against metrics.body_metrics on every pose
kept, and its memory against the number of poses."""

from __future__ import annotations

import tracemalloc

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from visionpos.analysis import metrics as M
from visionpos.app.demo_summary import BATCH_TICKS, HIST_BIN_NS, HOLD_NS, Collector
from visionpos.messages import BodyState

T0 = 5_000_000_000  # window start, server clock
TICK_NS = 10_000_000


def _truth(name: str, t_ns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A circle of 1 m radius at 1 rad/s, yawing with it."""
    s = (np.asarray(t_ns, np.int64) - T0) * 1e-9
    pos = np.stack([np.cos(s), np.sin(s), 1.0 + 0.1 * s], axis=1)
    return pos, Rotation.from_rotvec(np.outer(s, [0.0, 0.0, 1.0])).as_quat()


def _states(n: int, seed: int = 1) -> tuple[list[int], list[BodyState]]:
    """n ticks on a jittered 100 Hz grid; poses a few ms behind with mm noise, 5% untracked, a 0.2 s gap."""
    rng = np.random.default_rng(seed)
    ticks = T0 + np.arange(n, dtype=np.int64) * TICK_NS + rng.integers(0, 400_000, n)
    times = ticks - rng.integers(0, 2_000_000, n)
    tracked = rng.random(n) > 0.05
    tracked[n // 3:n // 3 + 20] = False
    pos, quat = _truth("quad", times)
    pos = pos + rng.normal(0, 1e-3, pos.shape)
    quat = (Rotation.from_rotvec(rng.normal(0, 5e-3, (n, 3))) * Rotation.from_quat(quat)).as_quat()
    latency = rng.gamma(3.0, 2.5e6, n).astype(np.int64)
    z3, z6 = np.zeros(3), np.zeros((6, 6))
    out = [BodyState("quad", 1, int(t), int(tk - lat), p, q, z3, z3, z6, np.zeros((3, 3)), bool(k))
           for t, tk, lat, p, q, k in zip(times, ticks, latency, pos, quat, tracked)]
    return ticks.tolist(), out


def _collect(ticks: list[int], states: list[BodyState], t_end: int) -> Collector:
    clock = iter(ticks)
    c = Collector(["quad"], clock=lambda: next(clock))
    c.start_window(T0, t_end, _truth)
    for s in states:
        c.publish([s])
    return c


def test_running_statistics_equal_the_metrics_on_every_pose():
    n = 3 * BATCH_TICKS + HOLD_NS // TICK_NS + 77  # several folds and the newest ticks still held
    ticks, states = _states(n)
    t_stop = ticks[-40]  # the last ticks are after the window's end
    c = _collect(ticks, states, ticks[-1] + TICK_NS)
    got = c.finish(t_stop)["quad"].metrics(c.ticks, t_stop - T0)

    # the reference: every pose in the window kept, metrics.body_metrics with truth on a 5 ms grid
    keep = [(tk, s) for tk, s in zip(ticks, states) if T0 <= tk <= t_stop]
    assert c.ticks == len(keep)
    tt = np.arange(T0, t_stop + 1, 5_000_000, dtype=np.int64)
    tp, tq = _truth("quad", tt)
    m = M.body_metrics("quad", np.array([s.time_ns for _, s in keep]), np.array([s.tracked for _, s in keep]),
                       np.array([s.position for _, s in keep]), np.array([s.quaternion for _, s in keep]),
                       np.array([tk - s.capture_ns for tk, s in keep]), (tt, tp, tq), n_ticks=len(keep),
                       span_ns=t_stop - T0)
    assert got["tracked_fraction"] == pytest.approx(m.tracked_fraction, rel=1e-12)
    assert got["rate_hz"] == pytest.approx(m.rate_hz, rel=1e-12)
    assert got["position_rmse_mm"] == pytest.approx(m.position_rmse_mm, rel=1e-9)
    assert got["position_max_mm"] == pytest.approx(m.position_max_mm, rel=1e-9)
    assert got["rotation_rmse_deg"] == pytest.approx(m.rotation_rmse_deg, rel=1e-9)
    assert got["jitter_mm"] == pytest.approx(m.position_jitter_mm, rel=1e-9)
    for q in ("p50", "p90", "p99"):  # from a histogram: within one bin
        assert got["pipeline_latency_ms"][q] == pytest.approx(m.latency_ms[q], abs=HIST_BIN_NS * 1e-6)


def test_ticks_outside_the_window_are_not_scored():
    ticks, states = _states(200)
    c = _collect(ticks, states, ticks[99])
    stats = c.finish(ticks[-1])["quad"]
    assert c.ticks == 100 and stats.ticks == 100
    assert c.last["quad"] is states[-1]  # the status line sees the newest state all the same


def test_the_collectors_memory_does_not_grow_with_the_poses():
    """Memory held after 2 000 and after 20 000 ticks: the same (only the bounded buffer and fixed sums)."""
    ticks, states = _states(20_000)

    def held_after(n: int) -> int:
        head_ticks, head_states = ticks[:n], states[:n]  # the inputs, made before the tracing starts
        tracemalloc.start()
        c = _collect(head_ticks, head_states, ticks[-1])
        size = tracemalloc.get_traced_memory()[0]
        tracemalloc.stop()
        assert c.ticks > 0
        return size

    small, large = held_after(2_000), held_after(20_000)
    # keeping every pose (as the demo did) holds over 1 kB per pose: 18 000 more poses would add 18 MB
    assert large - small < 100_000, (small, large)


def _vision_messages(n: int, seed: int = 3) -> list:
    """n VISION_POSITION_ESTIMATE messages as a fake autopilot records them: a 50 Hz grid of stamps on the
    truth's circle (NED: x, -y, -z) with 0.5 mm noise, arriving 5-15 ms after their stamp, one 80 ms hole."""
    from bridge.fake_autopilot import Received

    rng = np.random.default_rng(seed)
    stamps_ns = T0 - 100_000_000 + np.arange(n, dtype=np.int64) * 20_000_000
    stamps_ns[n // 2:] += 60_000_000  # a gap: 80 ms between two stamps
    world, _ = _truth("quad", stamps_ns)
    world = world + rng.normal(0.0, 5e-4, world.shape)
    recv_ns = stamps_ns + rng.integers(5_000_000, 15_000_000, n)
    out = []
    for s, r, p in zip(stamps_ns, recv_ns, world):
        out.append(Received("VISION_POSITION_ESTIMATE", int(r), 1, 197, True,
                            {"usec": int(s) // 1000, "x": p[0], "y": -p[1], "z": -p[2],
                             "roll": 0.0, "pitch": 0.0, "yaw": 0.0}))
    return out, stamps_ns, recv_ns, world


def test_the_autopilot_tally_equals_the_figures_of_every_kept_message():
    from visionpos.app.demo_summary import AutopilotPoses, latency_percentiles_ms

    msgs, stamps_ns, recv_ns, world = _vision_messages(400)
    t_stop = T0 + 5_000_000_000
    got = AutopilotPoses(boot_stamps=True)
    for m in msgs[:3]:  # before the window is known: counted, not scored
        got.on_pose(m)
    got.score(T0, t_stop, lambda t: _truth("quad", t)[0])
    for m in msgs[3:]:
        got.on_pose(m)
    got.flush()  # the poses still waiting to be scored (the demo calls it once the autopilot has closed)
    # the figures straight from every message, as the demo computed them when it kept them all
    assert got.n == 400
    assert got.max_gap_ns == int(np.diff(recv_ns).max())
    inside = (stamps_ns >= T0) & (stamps_ns <= t_stop)
    inside[:3] = False
    e_mm = np.linalg.norm(world[inside] - _truth("quad", stamps_ns[inside])[0], axis=1) * 1e3
    assert got.scored == int(inside.sum())
    assert got.position_rmse_mm() == pytest.approx(np.sqrt(np.mean(e_mm ** 2)), rel=1e-9)
    assert got.err_max_mm == pytest.approx(e_mm.max(), rel=1e-9)
    lat = latency_percentiles_ms([got], (50, 99))
    want = M.percentiles_ms(recv_ns - stamps_ns, (50, 99))
    for k in ("p50", "p99"):
        assert abs(lat[k] - want[k]) <= 2 * HIST_BIN_NS * 1e-6
    # each sample at its bin's centre: the mean within half a bin
    assert abs(lat["mean"] - np.mean(recv_ns - stamps_ns) * 1e-6) <= 0.5 * HIST_BIN_NS * 1e-6


def test_the_demo_keeps_a_bounded_message_log():
    """A fake autopilot given keep_received keeps only its newest messages (the demo's summary needs none)."""
    from bridge.fake_autopilot import FakeAutopilot

    ap = FakeAutopilot("udpout:127.0.0.1:9", keep_received=8)
    msgs, *_ = _vision_messages(50)
    for m in msgs:
        ap.received.append(m)
    assert len(ap.received) == 8 and ap.received[-1] is msgs[-1]
    assert FakeAutopilot("udpout:127.0.0.1:9").received == []  # unbounded (the tests' own autopilots)


@pytest.mark.parametrize("kernels, says", [
    ({"interpreted_at_start": False, "interpreted_at_end": False}, None),
    ({"interpreted_at_start": True, "interpreted_at_end": False}, "ran interpreted until they were ready"),
    ({"interpreted_at_start": True, "interpreted_at_end": True}, "ran interpreted for the whole run"),
])
def test_the_summary_says_when_the_fusion_ran_interpreted(kernels, says):
    """A first demo after installing runs while the kernels compile: its summary must not pass for this host's."""
    from visionpos.app.demo_summary import format_summary

    s = {"scenario": "thesis", "session": "flight", "seed": 1, "duration_s": 10.0, "ticks": 1000,
         "stations": [{"camera_id": 1, "fps": 100.0}], "bodies": [],
         "latency_ms": {"p50": 7.0, "p99": 9.0}, "latency_to_autopilot_ms": {"p2": 6.25, "p50": 8.0, "mean": 8.5},
         "server": {"frames_accepted": 1000, "frames_shed": 0, "malformed": 0}, "late_ticks": 0,
         "wall_s": 10.5, "simulate_s": 0.2, "kernels": kernels}
    text = format_summary(s)
    # the delay each estimator wants (bridge/estimator_delay.py): ArduPilot the smallest, PX4 the mean
    assert "2nd percentile 6.25 ms, mean 8.50 ms (ArduPilot's VISO_DELAY_MS: near the smallest" in text
    assert "PX4's EKF2_EV_DELAY: the mean and 1.35 ms" in text
    if says is None:
        assert "interpreted" not in text
    else:
        assert says in text and "the next run uses the compiled kernels" in text
