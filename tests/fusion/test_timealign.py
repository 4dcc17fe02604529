"""TimeAligner: which frames are fused together, at what reference time, and which are dropped."""

import pytest

from visionpos.fusion.timealign import (
    CLOCK_JUMP,
    LATE,
    MODES,
    MOTION_COMPENSATED,
    NAIVE,
    REORDERED,
    Group,
    Rejection,
    TimeAligner,
    TimeAlignment,
)

MS = 1_000_000


def _mc(window_ms: float = 12, max_lead_ms: float = 30, **kw) -> TimeAligner:
    return TimeAligner("motion_compensated", window_ns=int(window_ms * MS), grid_ns=10 * MS,
                       max_lead_ns=int(max_lead_ms * MS), **kw)


def _push(al: TimeAligner, camera_id: int, capture_ns: int) -> tuple[list[Group], list[Group]]:
    """Admit (must pass) and add one frame."""
    assert al.admit(camera_id, capture_ns) is None
    return al.add(camera_id, capture_ns)


def test_modes_are_an_enum_equal_to_their_yaml_strings():
    assert MOTION_COMPENSATED == "motion_compensated" and NAIVE == "naive"
    assert MODES == ("motion_compensated", "naive") and all(type(m) is str for m in MODES)
    assert TimeAligner("naive", 12 * MS, 10 * MS, 30 * MS).mode is TimeAlignment.NAIVE
    assert _mc().mode == "motion_compensated"
    assert CLOCK_JUMP == "clock_jump" and isinstance(LATE, Rejection)
    with pytest.raises(ValueError, match="spline"):
        TimeAligner("spline", 12 * MS, 10 * MS, 30 * MS)


def test_group_is_every_camera_within_the_window_of_the_new_frame():
    al = _mc(window_ms=5)
    _push(al, 1, 100 * MS)
    _, after = _push(al, 2, 103 * MS)
    assert after == [Group((1, 2), 103 * MS, True)]
    _, after = _push(al, 3, 109 * MS)  # camera 2's 103 ms is 6 ms before: outside
    assert after == [Group((3,), 109 * MS, True)]
    _, after = _push(al, 2, 114 * MS)  # camera 3's 109 ms exactly on the window's edge: inside
    assert after == [Group((2, 3), 114 * MS, True)]


def test_reference_is_the_newest_frame_of_the_group():
    al = _mc(window_ms=12)
    _push(al, 1, 100 * MS)
    _push(al, 2, 110 * MS)
    _, after = _push(al, 1, 106 * MS)  # arrives after camera 2's newer frame
    assert after[0].cameras == (1, 2) and after[0].ref_ns == 110 * MS
    assert al.newest_ns == 110 * MS


def test_naive_bins_to_the_nearest_grid_point_and_fuses_a_bin_when_the_next_starts():
    nv = TimeAligner("naive", window_ns=12 * MS, grid_ns=10 * MS, max_lead_ns=30 * MS)
    before, after = _push(nv, 1, 104_900_000)  # nearest grid point 100 ms
    assert before == [] and after == []
    before, after = _push(nv, 2, 105 * MS)  # nearest grid point 110 ms: closes the 100 ms bin
    assert before == [Group((1,), 104_900_000, False)] and after == []
    before, _ = _push(nv, 1, 112 * MS)  # same bin as 105 ms
    assert before == []
    before, _ = _push(nv, 2, 115 * MS)  # 120 ms bin: the 110 ms bin is fused at its mean capture time
    assert before == [Group((1, 2), 108_500_000, False)]
    assert nv.admit(1, 114 * MS) == LATE  # newer than camera 1's last frame, but in a bin already fused


def test_clock_lead_beyond_max_lead_is_a_jump_only_while_other_cameras_talk():
    al = _mc(max_lead_ms=30)
    _push(al, 1, 100 * MS)
    _push(al, 2, 103 * MS)
    assert al.admit(1, 133 * MS) is None  # exactly max_lead ahead of the newest: allowed
    assert al.admit(1, 134 * MS) == CLOCK_JUMP
    assert al.newest_ns == 103 * MS  # a refused frame does not move the clock
    alone = _mc(max_lead_ms=30)
    _push(alone, 1, 100 * MS)
    assert alone.admit(1, 500 * MS) is None  # the only camera: nobody to disagree with


def test_removed_camera_leaves_the_groups():
    al = _mc(window_ms=12)
    _push(al, 1, 100 * MS)
    _push(al, 2, 102 * MS)
    al.remove(2)
    _, after = _push(al, 1, 104 * MS)
    assert after == [Group((1,), 104 * MS, True)]


def test_time_aligner_rules():
    al = TimeAligner("motion_compensated", window_ns=12 * MS, grid_ns=10 * MS, max_lead_ns=30 * MS)
    assert al.admit(1, 100 * MS) is None
    _, after = al.add(1, 100 * MS)
    assert after[0].cameras == (1,) and after[0].ref_ns == 100 * MS
    assert al.admit(2, 103 * MS) is None
    _, after = al.add(2, 103 * MS)
    assert after[0].cameras == (1, 2) and after[0].ref_ns == 103 * MS and after[0].compensate
    assert al.admit(2, 103 * MS) == REORDERED  # duplicate
    assert al.admit(1, 160 * MS) == CLOCK_JUMP  # 57 ms ahead of camera 2
    assert al.admit(2, 80 * MS) == REORDERED
    assert al.admit(3, 85 * MS) == LATE  # older than the window behind the newest
    # a camera alone for longer than the trust span is a real gap, not a jump
    t = 160 * MS
    verdicts = []
    for _ in range(30):
        verdicts.append(al.admit(1, t))
        t += 10 * MS
    assert verdicts[0] == CLOCK_JUMP and verdicts[-1] is None
    # every camera silent for 100 ms (a stall): the first camera back is held as a possible jump,
    # the second one agrees on the new time, so the gap is real and both are used
    ga = TimeAligner("motion_compensated", window_ns=12 * MS, grid_ns=10 * MS, max_lead_ns=30 * MS)
    for cam, tc in ((1, 100 * MS), (2, 103 * MS), (3, 106 * MS)):
        ga.add(cam, tc)
    assert ga.admit(1, 210 * MS) == CLOCK_JUMP
    assert ga.admit(2, 213 * MS) is None
    ga.add(2, 213 * MS)
    assert ga.admit(3, 216 * MS) is None and ga.admit(1, 220 * MS) is None

    # naive: frames binned on the grid, a bin fused when the next one starts, at its mean time
    nv = TimeAligner("naive", window_ns=12 * MS, grid_ns=10 * MS, max_lead_ns=30 * MS)
    for cam, tc in ((1, 99 * MS), (2, 102 * MS)):
        assert nv.admit(cam, tc) is None
        before, after = nv.add(cam, tc)
        assert before == [] and after == []
    before, _ = nv.add(1, 109 * MS)
    assert before[0].cameras == (1, 2) and before[0].ref_ns == 100_500_000 and not before[0].compensate

    # rate limit: skip when the last fusion is recent and another camera is due soon
    rl = TimeAligner(
        "motion_compensated", 12 * MS, 10 * MS, 30 * MS, periods_ns={1: 10 * MS, 2: 10 * MS}, min_interval_ns=2 * MS
    )
    rl.add(1, 100 * MS)
    rl.add(2, 105 * MS)
    _, a = rl.add(1, 110 * MS)  # 5 ms after the last fusion: fuse
    assert a
    _, a = rl.add(2, 110_500_000)  # 0.5 ms after, camera 1's next frame is 9.5 ms away: fuse
    assert a
    rl2 = TimeAligner(
        "motion_compensated", 12 * MS, 10 * MS, 30 * MS, periods_ns={1: 10 * MS, 2: 10 * MS}, min_interval_ns=2 * MS
    )
    rl2.add(2, 99 * MS)
    rl2.add(1, 100 * MS)
    _, a = rl2.add(2, 109 * MS)  # fused at 100 ms: 9 ms ago -> fuse
    assert a
    _, a = rl2.add(1, 109_200_000)  # 0.2 ms after the last fusion; camera 2 next due at 119 ms -> fuse
    assert a
    rl3 = TimeAligner(
        "motion_compensated",
        12 * MS,
        10 * MS,
        30 * MS,
        periods_ns={1: 10 * MS, 2: 10 * MS, 3: 10 * MS},
        min_interval_ns=2 * MS,
    )
    for cam, tc in ((1, 100 * MS), (2, 100_500_000), (3, 101 * MS)):
        rl3.add(cam, tc)
    _, a = rl3.add(1, 110 * MS)  # last fusion 9 ms ago: fuse
    assert a
    _, a = rl3.add(2, 110_500_000)  # 0.5 ms after a fusion and camera 3 due at 111 ms: wait for it
    assert a == []
    _, a = rl3.add(3, 111 * MS)  # end of the burst: one fusion with all three
    assert a and a[0].cameras == (1, 2, 3)


def test_a_deferred_fusion_is_taken_by_the_tick_when_its_burst_never_ends():
    # three cameras nearly in phase: camera 2's frame waits for camera 3's, due 0.5 ms later; that frame is lost,
    # so the next tick must fuse camera 2's frame instead of leaving it to the next burst a frame period later
    al2 = TimeAligner("motion_compensated", 12 * MS, 10 * MS, 30 * MS, periods_ns={1: 10 * MS, 2: 10 * MS, 3: 10 * MS},
                      min_interval_ns=2 * MS)
    for cam, tc in ((1, 100 * MS), (2, 100_500_000), (3, 101 * MS)):
        al2.add(cam, tc)
    al2.add(1, 110 * MS)
    _, a = al2.add(2, 110_500_000)  # camera 3 due at 111 ms: deferred
    assert a == []
    g = al2.take_deferred()  # camera 3's frame does not come: the tick fuses 1 and 2 at camera 2's time
    assert g is not None and g.cameras == (1, 2, 3) and g.ref_ns == 110_500_000 and g.compensate
    assert al2.take_deferred() is None  # once
    _, a = al2.add(3, 111 * MS)  # late after all: it is fused (0.5 ms after the tick's fusion, nothing else due)
    assert a and a[0].cameras == (1, 2, 3)
    # a later fusion takes the deferred frame: nothing is left for the tick
    al2.add(1, 120 * MS)
    _, a = al2.add(2, 120_500_000)
    assert a == [] and al2.deferred is not None
    _, a = al2.add(3, 121 * MS)
    assert a and al2.take_deferred() is None
