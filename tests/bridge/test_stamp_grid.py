"""The poses' stamps: an exact grid, a steady age behind the tick that sends them (bridge/stamp_grid.py).
Expected stamps are worked out by hand from the ticks and captures each test makes."""

from bridge.stamp_grid import StampGrid

MS = 1_000_000
PERIOD = 20 * MS


def run(grid: StampGrid, ticks_captures):
    """Feed (tick, capture) pairs as the vehicle link does; the (stamp, tick) of each pose sent."""
    out = []
    for tick, cap in ticks_captures:
        grid.observe(tick, cap)
        stamp = grid.due(tick, cap)
        if stamp is not None:
            grid.sent(stamp, tick)
            out.append((stamp, tick))
    return out


def test_a_steady_frame_age_gives_stamps_that_age_behind_every_other_tick():
    grid = StampGrid(PERIOD, 100_000)
    sent = run(grid, [(k * 10 * MS, k * 10 * MS - 5 * MS) for k in range(400)])
    # the first stamp is the first capture (-5 ms); every 20 ms after it, each sent at the tick 5 ms later
    assert sent == [(-5 * MS + 20 * MS * i, 20 * MS * i) for i in range(200)]
    assert grid.age_ns == 5 * MS


def test_uneven_ages_keep_an_exact_grid_whose_phase_follows_the_ticks():
    # newest frame 0 / 4 ms old at alternate ticks (asynchronous cameras): the age becomes 4 ms
    grid = StampGrid(PERIOD, 100_000)
    sent = run(grid, [(k * 10 * MS, k * 10 * MS - (4 * MS if k % 2 else 0)) for k in range(300)])
    stamps = [s for s, _ in sent]
    steps = [b - a for a, b in zip(stamps, stamps[1:])]
    # tick 0 sends its capture (age 0 then); from then the next grid point (20, 40, ...) is due 4 ms before
    # a tick at 24, 44, ...: sent at ticks 30, 50, ..., 6 ms of slack. After 25 sends with more than 1 ms of
    # slack, one step is 5.5 ms longer, leaving 0.5 ms
    assert grid.age_ns == 4 * MS  # the 90th percentile of 0 and 4 ms
    assert stamps[:26] == [20 * MS * i for i in range(26)]
    assert [t for _, t in sent[1:26]] == [20 * MS * i + 10 * MS for i in range(1, 26)]
    assert steps[25] == 25_500_000 and all(s == PERIOD for s in steps[26:])
    assert all(t - s == 4_500_000 for s, t in sent[27:])


def test_a_frame_older_than_its_stamp_waits_for_the_next_tick_with_the_same_stamp():
    grid = StampGrid(PERIOD, 100_000, age_ns=5 * MS)
    pairs = [(k * 10 * MS, k * 10 * MS - 5 * MS) for k in range(10)]
    pairs[4] = (40 * MS, 30 * MS)  # at tick 40 the newest frame is 10 ms old: 35 is due but not reached
    sent = run(grid, pairs)
    assert sent[:4] == [(-5 * MS, 0), (15 * MS, 20 * MS), (35 * MS, 50 * MS), (55 * MS, 60 * MS)]
    assert grid.why == "rate"  # the last tick (90) had nothing due: 75 went at 80


def test_a_late_tick_with_an_older_frame_takes_the_grid_point_its_frame_reaches():
    grid = StampGrid(PERIOD, 100_000, age_ns=2 * MS)
    # at 60.5 ms (a tick 10.5 ms late) 58 is at least the age before the tick, but the frame (50) reaches only 38
    sent = run(grid, [(0, -2 * MS), (20 * MS, 18 * MS), (60_500_000, 50 * MS)])
    assert sent == [(-2 * MS, 0), (18 * MS, 20 * MS), (38 * MS, 60_500_000)]


def test_a_fixed_age_is_kept():
    grid = StampGrid(PERIOD, 100_000, age_ns=12 * MS)
    sent = run(grid, [(k * 10 * MS, k * 10 * MS - 2 * MS) for k in range(300)])
    assert grid.age_ns == 12 * MS
    assert all(t - s in (12 * MS, 12 * MS + 500_000) for s, t in sent)  # 0.5 ms once the grid followed the ticks
    assert min(b[0] - a[0] for a, b in zip(sent, sent[1:])) == PERIOD


def test_the_automatic_age_is_the_first_five_seconds_90th_percentile_then_kept():
    grid = StampGrid(PERIOD, 100_000)
    sent = run(grid, [(k * 10 * MS, k * 10 * MS - 5 * MS) for k in range(300)])
    assert grid.age_ns == 5 * MS
    # ticks 300-499 carry 12 ms old frames: the 90th percentile of the first 400 (numpy's linear: the 360th
    # value, of 300 at 5 ms and 100 at 12) is 12, judged at the 400th tick
    sent += run(grid, [(k * 10 * MS, k * 10 * MS - 12 * MS) for k in range(300, 399)])
    assert grid.age_ns == 5 * MS
    sent += run(grid, [(k * 10 * MS, k * 10 * MS - 12 * MS) for k in range(399, 500)])
    assert grid.age_ns == 12 * MS
    # from then it is kept, whatever the frames' age
    sent += run(grid, [(k * 10 * MS, k * 10 * MS - 5 * MS) for k in range(500, 4000)])
    assert grid.age_ns == 12 * MS
    assert min(b[0] - a[0] for a, b in zip(sent, sent[1:])) >= PERIOD


def test_a_stall_after_the_first_five_seconds_leaves_the_age_and_keeps_the_grid():
    grid = StampGrid(PERIOD, 100_000)
    ticks = [(k * 10 * MS, k * 10 * MS - (40 * MS if 700 <= k < 760 else 5 * MS)) for k in range(1000)]
    sent = run(grid, ticks)
    assert grid.age_ns == 5 * MS
    stamps = [s for s, _ in sent]
    # on the grid from -5 ms throughout: the stalled frames (ticks 7000-7590 ms) take the points they reach
    # late; at 7600 ms the fresh frame takes the newest point, 7595 ms: the two before it (7555 and 7575 ms,
    # whose frames never came in time) are skipped rather than sent in a burst
    assert all((s + 5 * MS) % PERIOD == 0 for s in stamps)
    assert [b - a for a, b in zip(stamps, stamps[1:]) if b - a != PERIOD] == [60 * MS] and len(stamps) == 498
    # the stalled poses (sent at ticks 7040-7580) go out 45 ms after their stamps: the frames 40 ms old, the
    # stamps on the grid 5 ms before them
    assert [t - s for s, t in sent if 7000 * MS <= t < 7600 * MS] == [45 * MS] * 28


def test_the_docs_say_how_the_stamp_age_is_chosen():
    from pathlib import Path

    import bridge.stamp_grid as g

    text = " ".join((Path(__file__).parents[2] / "docs" / "autopilot-setup.md").read_text().split())
    assert ("the 90th percentile of the newest frame's age at the first 500 output ticks (5 s at 100 Hz) the body is "
            "tracked, then kept") in text
    assert (g.AGE_PERCENTILE, g.AGES_JUDGED) == (90.0, 500)
    assert "after 25 poses that all went out more than 1 ms after their due time, one step is longer by that less " \
           "0.5 ms" in text
    assert (g.PHASES_KEPT, g.SLACK_MAX_NS, g.SLACK_KEPT_NS) == (25, 1 * MS, MS // 2)


def test_for_px4_the_grid_follows_the_captures():
    # the newest capture at 100 Hz ticks moving by 6 and 14 ms in turn: stamps 20 ms apart from the first
    # capture, one per frame that reached the next grid point (less 0.1 ms), and after a gap the capture itself
    grid = StampGrid(PERIOD, 100_000)
    caps = [k * 10 * MS - (4 * MS if k % 2 else 0) for k in range(20)] + [300 * MS, 310 * MS, 320 * MS]
    sent = []
    for c in caps:
        s = grid.due_on_captures(c)
        if s is not None:
            grid.sent(s, c)
            sent.append(s)
    # captures 0, 6, 20, 26, 40, ...: 20 reaches 20, 40 reaches 40, ...; 300 is a period past 200: itself
    assert sent == [20 * MS * i for i in range(10)] + [300 * MS, 320 * MS]
