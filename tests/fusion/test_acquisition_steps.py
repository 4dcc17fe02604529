"""Acquisition in steps (visionpos/fusion/steps.py, acquisition.match_unlabeled_steps, rigidbody.identify_steps,
the pipeline's fusion.acquire_step_ms): the same result at any step size, and a large acquisition spread over
fusions without ever starting a track from frames its body has left."""

from __future__ import annotations

import numpy as np
import pytest

from visionpos.fusion import acquisition
from visionpos.fusion.pipeline import FusionPipeline
from visionpos.fusion.rigidbody import identify, identify_steps
from visionpos.fusion.steps import advance, finish


@pytest.fixture(scope="module")
def fleet20():
    """The fleet20 scenario's first 0.3 s (twenty quads of one layout parked in view of twelve cameras) and one
    frame set of it: undistorted blobs per view, R, t, f."""
    from visionpos.camera.model import undistort_points
    from visionpos.sim import load_scenario, simulate

    sc = load_scenario("fleet20", ["sim.duration=0.3"])
    frames = sorted(simulate(sc).frames, key=lambda f: (f.recv_ns, f.camera_id))
    cams = {c.id: c for c in sc.arena.cameras}
    pick = {}
    for f in frames:
        if f.capture_ns >= frames[0].capture_ns + 100_000_000:
            pick.setdefault(f.camera_id, f)
    ids = sorted(pick)
    xs = [undistort_points(cams[i].model, np.asarray(pick[i].blobs[:, :2], float)) for i in ids]
    R = np.array([cams[i].R for i in ids])
    t = np.array([cams[i].t for i in ids])
    f = np.array([np.sqrt(cams[i].model.fx * cams[i].model.fy) for i in ids])
    return sc, frames, (xs, R, t, f)


def _steps(gen):
    """Every yielded estimate of a generator of steps, and its result."""
    costs = []
    while True:
        try:
            costs.append(next(gen))
        except StopIteration as done:
            return costs, done.value


def test_matching_in_steps_gives_the_same_points_bit_for_bit(fleet20):
    _, _, (xs, R, t, f) = fleet20
    whole = acquisition.match_unlabeled(xs, R, t, f, 3.0, 2.0)
    assert len(whole[0]) >= 75  # the fleet's 80 markers, nearly all seen by two cameras or more
    for step_ns in (1.0, 200_000.0, acquisition.STEP_NS):
        costs, stepped = _steps(acquisition.match_unlabeled_steps(xs, R, t, f, 3.0, 2.0, step_ns=step_ns))
        for a, b in zip(whole, stepped):
            assert a.shape == b.shape and np.array_equal(a, b)
        assert len(costs) > 10  # 80 blobs in 12 views: seeds, growth and triangulation each cut
    # steps of about STEP_NS: none of the cut stages' steps is more than twice it
    costs, _ = _steps(acquisition.match_unlabeled_steps(xs, R, t, f, 3.0, 2.0))
    assert sorted(costs)[-2] <= 2 * acquisition.STEP_NS  # the largest is the acceptance, one stage
    assert sum(costs) > 10 * acquisition.STEP_NS


def test_identification_in_steps_gives_identify_s_result(fleet20):
    sc, _, (xs, R, t, f) = fleet20
    from visionpos.fusion.rigidbody import BodyModel

    pts = acquisition.match_unlabeled(xs, R, t, f, 3.0, 2.0)[0]
    models = [BodyModel(b.name, b.id, np.asarray(b.markers, float)) for b in sc.arena.bodies]
    costs, stepped = _steps(identify_steps(pts, models, 0.008, 3))
    whole = identify(pts, models, 0.008, 3)
    assert len(whole) == 20
    assert [(w.body, w.point_index.tolist()) for w in whole] == [(s.body, s.point_index.tolist()) for s in stepped]
    assert all(np.array_equal(w.t, s.t) and np.array_equal(w.R, s.R) for w, s in zip(whole, stepped))
    assert len(costs) == 5  # one step per seed triangle of the four markers, then the acceptance


def test_advance_runs_steps_within_the_budget_and_at_least_one():
    def work(costs):
        for c in costs:
            yield c
        return "done"

    steps = work([1.0, 1.0, 1.0, 5.0, 1.0])
    assert advance(steps, 2.5) == (False, None)  # 1, then 2 + the next taken as 1 more: 3 > 2.5
    assert advance(steps, 2.5) == (False, None)  # 1, then 5: over, but a step runs
    assert advance(steps, 0.0) == (False, None)  # the last 1 (at least one step)
    assert advance(steps, 0.0) == (True, "done")
    assert finish(work([1.0, 2.0])) == "done"


def _run(sc, frames, settings, until_s):
    pipe = FusionPipeline(sc.arena, settings)
    steps = []  # (reference time, the first of its acquisition, the last) of each acquisition step
    orig = pipe._acquire_step

    def step(ref, lost_ns):
        orig(ref, lost_ns)
        steps.append((ref, pipe._acquire_began_ns == ref, pipe._acquiring is None))

    pipe._acquire_step = step
    end = frames[0].capture_ns + int(until_s * 1e9)
    for fr in frames:
        if fr.capture_ns > end:
            break
        pipe.push(fr)
    return pipe, steps


def _jobs(steps):
    """The reference times of each acquisition's steps, from _run's (ref, began, ended) records."""
    jobs = []
    for ref, began, ended in steps:
        if began:
            jobs.append([])
        jobs[-1].append(ref)
    return jobs


def test_a_parked_fleet_s_first_acquisition_goes_on_over_fusions_and_finds_every_quad(fleet20):
    """fleet20's first acquisition is 40 ms of work: with the defaults it runs in steps acquire_interval_ms
    apart (the server's frames fused in between) and finds all twenty where they stand; at acquire_step_ms 0
    it is one step. The same twenty poses either way (the fleet is parked: the steps' frames are as good)."""
    sc, frames, _ = fleet20
    pipe, steps = _run(sc, frames, None, 0.25)
    jobs = _jobs(steps)
    big = [j for j in jobs if len(j) > 1]
    assert len(big) == 1 and len(big[0]) >= 4  # the first acquisition of the twenty, in steps
    assert np.diff(big[0]).min() >= pipe.settings.acquire_interval_ns
    # its rest runs at once where it began 2/3 of the lost timeout ago: it never lasts much longer
    assert big[0][-1] - big[0][0] <= 2 * pipe.settings.kalman.lost_timeout_ns // 3 + pipe.settings.acquire_interval_ns
    at_once, at_once_steps = _run(sc, frames, {"acquire_step_ms": 0}, 0.25)
    assert all(len(j) == 1 for j in _jobs(at_once_steps))
    end = frames[0].capture_ns + 250_000_000
    for p in (pipe, at_once):
        states = {s.name: s for s in p.tick(end)}
        assert all(s.tracked for s in states.values()) and len(states) == 20
        for name, s in states.items():
            true_p, _ = sc.truth_at(name, np.array([end]))
            assert np.linalg.norm(s.position - true_p[0]) < 0.003


def test_bodies_that_move_during_the_steps_are_acquired_again_from_the_newest_frames(two_of_a_kind):
    """Two quads of one layout in the thesis arena, one parked and one on a fast figure-eight, and acquisition
    cut into the smallest steps: the parked one is started from the steps' frames, the moving one is refused
    ("it moved ...") and found by the next acquisition, at once (as every later one), from the newest; no pose is
    ever output from frames the body had left: its outputs are as close to the truth as an acquisition at once's."""
    from visionpos.sim import simulate

    sc = two_of_a_kind({"flying": {"trajectory": "figure8", "center": [0.3, 0.0, 0.9], "size": [0.8, 0.5],
                                   "period": 2.0},
                        "parked": {"trajectory": "static", "position": [-0.4, 0.2, 0.0]}}, 0.8, ["parked", "flying"])
    frames = sorted(simulate(sc).frames, key=lambda f: (f.recv_ns, f.camera_id))
    worst, said = {}, {}
    moved = "it moved while acquisition ran over several frames: acquired again from the newest"
    for step_ms in (0.001, 0.0):
        pipe = FusionPipeline(sc.arena, {"acquire_step_ms": step_ms})
        said[step_ms], worst[step_ms] = set(), {"parked": 0.0, "flying": 0.0}
        steps, orig = [], pipe._acquire_step
        pipe._acquire_step = lambda ref, lost_ns: (orig(ref, lost_ns), steps.append(
            (ref, pipe._acquire_began_ns == ref, pipe._acquiring is None, moved in said[step_ms])))
        for fr in frames:
            pipe.push(fr)
            said[step_ms] |= set(pipe.untracked_why.values())
            if fr.camera_id == frames[0].camera_id:
                for st in pipe.tick(fr.recv_ns):
                    if st.tracked:
                        true_p, _ = sc.truth_at(st.name, np.array([fr.recv_ns]))
                        e = float(np.linalg.norm(st.position - true_p[0]))
                        worst[step_ms][st.name] = max(worst[step_ms][st.name], e)
        assert all(st.tracked for st in pipe.tick(frames[-1].recv_ns))
        if step_ms:  # once a body was refused, every later acquisition (here: of the flying one) runs at once
            after = [(r, b, e) for r, b, e, refused in steps if refused]
            assert after and all(len(j) == 1 for j in _jobs(after[1:]))
    assert moved in said[0.001] and moved not in said[0.0]
    # a track's first outputs carry its unknown velocity (about 2 cm at 2 m/s, at once too), never more
    assert worst[0.001]["flying"] <= worst[0.0]["flying"] + 0.001
    assert worst[0.001]["parked"] < 0.003


def test_a_body_tracked_before_is_acquired_again_at_once(two_of_a_kind):
    """Two quads parked in the thesis arena, acquisition cut into the smallest steps: their first acquisition
    goes on in steps; after 0.3 s without frames (one or both lost) they are found again in one step (a body lost
    after it was tracked is taken to fly)."""
    from visionpos.sim import simulate

    sc = two_of_a_kind({"a": {"trajectory": "static", "position": [0.3, 0.0, 0.0]},
                        "b": {"trajectory": "static", "position": [-0.4, 0.2, 0.0]}}, 1.0)
    frames = sorted(simulate(sc).frames, key=lambda f: (f.recv_ns, f.camera_id))
    cut0, cut1 = frames[0].capture_ns + 400_000_000, frames[0].capture_ns + 700_000_000
    pipe = FusionPipeline(sc.arena, {"acquire_step_ms": 0.001})
    steps, orig = [], pipe._acquire_step

    def step(ref, lost_ns):
        began, some_lost = pipe._acquire_began_ns == ref, len(pipe._tracked) < 2
        orig(ref, lost_ns)
        steps.append((ref, began, some_lost))

    pipe._acquire_step = step
    for fr in frames:
        if not cut0 <= fr.capture_ns < cut1:
            pipe.push(fr)
    jobs = _jobs([(r, b, e) for r, b, e in steps])
    lost_at = {r: lost for r, b, lost in steps if b}  # each job's first step: was a body lost
    before = [j for j in jobs if j[0] < cut0 and lost_at[j[0]]]
    after = [j for j in jobs if j[0] >= cut1 and lost_at[j[0]]]
    assert max(len(j) for j in before) > 3  # the first acquisition, in steps
    assert after and all(len(j) == 1 for j in after)
    assert pipe._stats["lost"] >= 1 and pipe._stats["acquisitions"] == 2 + pipe._stats["lost"]
    assert all(s.tracked for s in pipe.tick(frames[-1].recv_ns))
