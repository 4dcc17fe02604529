"""Single-marker (point) bodies: the position-only filter and association (visionpos/fusion/point_tracks.py), the
config, and the pipeline tracking a fleet of them against the simulator's truth."""

from __future__ import annotations

import numpy as np
import pytest

from visionpos.config.arena import ConfigError, load_yaml, parse_arena, resolve_config_path
from visionpos.fusion import point_tracks as pt


def test_constant_acceleration_prediction_is_exact_for_a_parabola():
    x = np.array([[1.0, 2.0, 3.0, 0.5, -1.0, 0.0, 0.0, 0.0, -2.0]])
    xp, P = pt.predict(x, np.tile(np.eye(9) * 1e-6, (1, 1, 1)), np.array([0.5]), jerk_psd=0.0)
    # z = 3 + 0 * t - 2 / 2 t^2 = 2.75; x = 1 + 0.5 * 0.5; y = 2 - 0.5; vz = -1
    assert xp[0, :3] == pytest.approx([1.25, 1.5, 2.75])
    assert xp[0, 3:6] == pytest.approx([0.5, -1.0, -1.0])
    # F P F^T on x: var p + dt^2 var v + (dt^2 / 2)^2 var a, with 1e-6 each
    assert P[0, 0, 0] == pytest.approx(1e-6 * (1 + 0.25 + 0.125**2))


def test_update_weighs_the_measurement_by_the_variances():
    x = np.zeros((1, 9))
    P = np.tile(np.diag([4e-6] * 3 + [1.0] * 6), (1, 1, 1))
    xu, Pu = pt.update(x, P, np.array([[0.01, 0.0, 0.0]]), np.tile(np.eye(3) * 1e-6, (1, 1, 1)))
    # gain 4 / (4 + 1) = 0.8; posterior variance 4 * 1 / 5 = 0.8e-6
    assert xu[0, 0] == pytest.approx(0.008)
    assert Pu[0, 0, 0] == pytest.approx(0.8e-6)
    assert np.allclose(Pu[0], Pu[0].T)


def test_association_takes_the_best_assignment_within_the_gate():
    pred = np.array([[0.0, 0.0, 1.0], [0.3, 0.0, 1.0], [5.0, 5.0, 1.0]])
    S = np.tile(np.eye(3) * 1e-4, (3, 1, 1))  # 1 cm sigma
    pts = np.array([[0.31, 0.0, 1.0], [0.005, 0.0, 1.0], [0.15, 0.0, 1.0]])
    assert pt.associate(pred, S, pts).tolist() == [1, 0, -1]  # the third prediction has no point near it
    # a point between the two, 15 cm from each, is nobody's
    assert pt.associate(pred[:1], S[:1], pts[2:]).tolist() == [-1]


def test_candidates_are_confirmed_only_by_repeated_sightings():
    cand, hits = np.zeros((0, 3)), np.zeros(0, dtype=np.int64)
    for k in range(pt.CONFIRM_HITS):
        cand, hits = pt.confirm_candidates(cand, hits, np.array([[0.0, 0.0, 0.001 * k], [1.0 + k, 0.0, 0.0]]))
    assert hits.max() == pt.CONFIRM_HITS and cand[np.argmax(hits)] == pytest.approx([0.0, 0.0, 0.004])
    assert sorted(hits.tolist()) == [1, pt.CONFIRM_HITS]  # the point that jumped a metre each time: always new


def test_config_takes_a_point_body_and_refuses_what_is_not_one():
    base = {"bodies": [{"name": "dot", "markers": [[0, 0, 0]]}]}
    arena = parse_arena(base, "a.yaml")
    assert arena.bodies[0].is_point
    with pytest.raises(ConfigError, match=r"bodies\[0\]\.markers.*\[\[0, 0, 0\]\]"):
        parse_arena({"bodies": [{"name": "dot", "markers": [[0.1, 0, 0]]}]}, "a.yaml")
    with pytest.raises(ConfigError, match=r"bodies\[0\]\.markers.*got 2"):
        parse_arena({"bodies": [{"name": "dot", "markers": [[0, 0, 0], [0.1, 0, 0]]}]}, "a.yaml")


def _point_pipeline(n=4, duration_s=None):
    from visionpos.fusion.pipeline import FusionPipeline
    from visionpos.sim import parse_sim
    from visionpos.sim.fleet import point_fleet

    sc = parse_sim(parse_arena(point_fleet(load_yaml(resolve_config_path("thesis")), n, duration_s), "<dots>"))
    return sc, FusionPipeline(sc.arena, warm_up=False)


def test_two_point_tracks_within_the_swap_distance_are_both_unresolved():
    _, pipe = _point_pipeline(3, 1.0)
    p = pipe.points
    for k, pos in enumerate(([0.0, 0.0, 1.0], [0.01, 0.0, 1.0], [1.0, 0.0, 1.0])):
        p.start(k, 0, np.array(pos), 1e-6, 0)
        pipe.identity.state[k] = pipe.identity.state[k].__class__.ACQUIRED
    pipe._identity_with_points(10_000_000)
    assert pipe.snapshot().identity == ("unresolved: two candidates", "unresolved: two candidates",
                                        "unresolved: acquired")


def test_a_fleet_of_point_bodies_is_tracked_apart_through_a_crossing():
    """Four single-marker drones (thesis arena) park in a row, take off one after the other and cross in pairs
    0.28 m apart: each tracked >= 95 % of the time two cameras see it, within a few mm, never on another's
    position, named in parking order."""
    from visionpos.sim import simulate
    from visionpos.sim.fleet import fleet_schedule

    sc, pipe = _point_pipeline(4, fleet_schedule(4)["crossed"] - 0.5)  # past the pairs' closest approach
    sim = simulate(sc)
    frames = sorted(sim.frames, key=lambda f: (f.recv_ns, f.camera_id))
    names = [b.name for b in sc.bodies]
    ticks, states = [], []
    next_tick = frames[0].recv_ns
    for f in frames:
        while f.recv_ns >= next_tick:
            ticks.append(next_tick)
            states.append(pipe.tick(next_tick))
            next_tick += 10_000_000
        pipe.push(f)
    ticks = np.array(ticks)
    truth = np.stack([sc.truth_at(n, ticks)[0] for n in names])  # (B, T, 3)
    d = np.linalg.norm(truth[:, None] - truth[None], axis=-1) + np.eye(len(names))[:, :, None] * 9
    assert d.min() < 0.3  # the crossing happened
    for i, name in enumerate(names):
        st = [s[i] for s in states]
        assert all(s.name == name and (not s.tracked or (s.update_kind, s.n_markers) == ("position", 1)) for s in st)
        tracked = np.array([s.tracked for s in st])
        pos = np.array([s.position for s in st])
        assert np.isnan(np.array([s.quaternion for s in st])).all()  # never an attitude
        seen = sum(c.visible(truth[i]).astype(int) for c in sc.arena.cameras) >= 2  # in two cameras' views
        assert tracked[seen].mean() >= 0.95
        err = np.linalg.norm(pos[tracked] - truth[i, tracked], axis=1)
        assert np.sqrt(np.mean(err**2)) < 0.003
        others = np.delete(truth, i, axis=0)[:, tracked]
        assert np.all(np.linalg.norm(pos[tracked] - others, axis=-1).min(axis=0) > err)  # no swap
    assert pipe.snapshot().identity == ("unresolved: acquired",) * 4
