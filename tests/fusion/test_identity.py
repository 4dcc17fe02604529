"""Bodies that share a marker layout (visionpos/fusion/identity.py, rigidbody.identify with a shared layout)."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from visionpos.fusion.identity import IdentityBook, IdentityState, layout_groups, parking_order
from visionpos.fusion.rigidbody import BodyModel, Identification, identify, layout_ambiguities

QUAD = np.array([[0.086, 0.073, 0.030], [-0.051, 0.104, 0.008], [-0.079, -0.089, 0.003], [0.026, -0.091, 0.054]])
OTHER = np.array([[0.101, 0.096, 0.007], [-0.067, 0.038, 0.018], [-0.069, -0.100, 0.032], [0.124, -0.062, 0.019]])


def _fleet(n=3, other=True):
    models = [BodyModel(f"quad{i + 1}", i + 1, QUAD.copy()) for i in range(n)]
    return models + ([BodyModel("solo", 9, OTHER)] if other else [])


def _book(models):
    # one camera 3 m above the origin with a 700 px focal length and a 10 px gate: 43 mm at 3 m
    return IdentityBook(models, np.array([[0.0, 0.0, 3.0]]), np.array([700.0]), 10.0)


def _filters(positions, var_m2=1e-8, velocities=None):
    """Filter states (B, 18) at positions (B, 3) m (velocities (B, 3) m/s, default 0) and covariances
    (B, 18, 18) with var_m2 per position axis."""
    positions = np.asarray(positions, float)
    x = np.zeros((len(positions), 18))
    x[:, :3] = positions
    if velocities is not None:
        x[:, 3:6] = velocities
    return x, np.tile(np.eye(18) * var_m2, (len(positions), 1, 1))


def _ident(body, t):
    return Identification(body, np.arange(4), np.eye(3), np.asarray(t, float), 0.0005)


def test_layout_groups_and_the_config_check():
    models = _fleet(3)
    assert layout_groups(models) == [0, 0, 0, 3]
    assert layout_ambiguities(models, 0.004) == []  # the same markers in the same order: a fleet
    shuffled = BodyModel("shuffled", 7, QUAD[[2, 0, 3, 1]])  # the same layout listed in another order
    assert layout_groups([models[0], shuffled]) == [0, 1]
    assert any("same marker layout" in p for p in layout_ambiguities([models[0], shuffled], 0.004))


def test_identify_finds_every_copy_of_a_shared_layout_even_from_three_markers():
    models = _fleet(2, other=False)
    rng = np.random.default_rng(4)
    poses = [(Rotation.from_euler("z", 30, degrees=True).as_matrix(), np.array([0.0, 0.0, 1.0])),
             (Rotation.from_euler("z", -60, degrees=True).as_matrix(), np.array([0.8, 0.1, 1.1]))]
    pts = np.vstack([QUAD @ R.T + t for R, t in poses]) + rng.normal(0, 3e-4, (8, 3))
    found = identify(pts, models, 0.008, 3)
    assert sorted(f.body for f in found) == [0, 1]
    centres = sorted(tuple(np.round(f.t, 1)) for f in found)
    assert centres == sorted(tuple(np.round(t, 1)) for _, t in poses)
    # one marker of each hidden: a 3-marker fit of a shared layout is not "ambiguous" with its twin
    ambiguous: set[int] = set()
    three = identify(pts[[0, 1, 2, 4, 5, 6]], models, 0.008, 3, ambiguous=ambiguous)
    assert len(three) == 2 and not ambiguous


def test_parking_order_is_rows_along_y_each_along_x():
    pts = np.array([[1.0, 0.02, 0], [-1.0, 0.0, 0], [0.0, 1.01, 0], [0.0, -0.01, 0], [-0.5, 0.98, 0]])
    assert parking_order(pts).tolist() == [1, 3, 0, 4, 2]


def test_first_acquisition_takes_the_parking_order_and_reacquisition_the_nearest_last_position():
    models = _fleet(3)
    book = _book(models)
    assert book.shared and book.state[3] is IdentityState.UNIQUE
    # identify() named them in body order; the parking order along x says otherwise
    found = book.acquired([_ident(0, [1.0, 0, 0]), _ident(1, [-1.0, 0, 0]), _ident(2, [0.0, 0, 0]),
                           _ident(3, [0, 2, 0])], [0, 1, 2, 3])
    named = {f.body: f.t[0] for f in found}
    assert named == {0: -1.0, 1: 0.0, 2: 1.0, 3: 0.0}
    assert all(book.state[b] is IdentityState.ACQUIRED for b in range(3))
    assert book.describe(0) == "quad1: identity unresolved: acquired (first seen: parking order)"
    partial = _book(models)  # two of three seen at first: named in order, and it says the order may be off
    partial.acquired([_ident(0, [1.0, 0, 0]), _ident(1, [-1.0, 0, 0])], [0, 1, 2, 3])
    assert "2 of the 3 never seen" in partial.describe(0) and partial.state[2] is IdentityState.LOST
    assert not book.trusted(0) and book.trusted(3)
    # quad2 and quad3 lost where they were; whichever identify() calls them, they come back by position
    book.after_fusion(0, (0, 3), *_filters([[-1.0, 0, 1], [0.0, 0, 1], [1.0, 0, 1], [0, 2, 1]]))
    assert book.state[1] is IdentityState.LOST and book.state[2] is IdentityState.LOST
    again = book.acquired([_ident(1, [1.05, 0, 1]), _ident(2, [0.05, 0, 1])], [1, 2])
    assert {f.body: f.t[0] for f in again} == {2: 1.05, 1: 0.05}
    # lost by the pipeline before the book's next check: still named among the lost, never another body
    book.bind(0)
    back = book.acquired([_ident(0, [-1.02, 0, 1])], [0])
    assert [f.body for f in back] == [0] and book.state[0] is IdentityState.ACQUIRED


def test_two_tracks_of_one_layout_within_the_swap_distance_are_both_unresolved():
    models = _fleet(3)
    book = _book(models)
    book.acquired([_ident(b, [b * 1.0, 0, 0]) for b in range(3)], [0, 1, 2, 3])
    for b in range(3):
        assert book.bind(b)
    assert book.trusted(0) and book.state[0] is IdentityState.CONTINUITY
    assert not book.bind(3)  # a unique layout needs no binding
    # 0.3 m apart (beyond the 43 mm gate at 3 m): continuity holds
    pos = np.array([[0.0, 0, 0], [0.3, 0, 0], [2.0, 0, 0], [0.02, 0, 0]])
    book.after_fusion(0, (0, 1, 2, 3), *_filters(pos))
    assert [book.state[b] for b in range(3)] == [IdentityState.CONTINUITY] * 3  # the solo body is no candidate
    # 3 cm apart: quad1 and quad2 could have swapped
    pos[1] = [0.03, 0, 0]
    book.after_fusion(2_000_000, (0, 1, 2, 3), *_filters(pos))  # within the check interval: not looked at yet
    assert book.state[0] is IdentityState.CONTINUITY
    book.after_fusion(6_000_000, (0, 1, 2, 3), *_filters(pos))
    assert book.state[0] is IdentityState.AMBIGUOUS and book.state[1] is IdentityState.AMBIGUOUS
    assert book.state[2] is IdentityState.CONTINUITY
    assert book.describe(0) == "quad1: identity unresolved: two candidates (quad1 or quad2)"
    # apart again: still unresolved until bound
    pos[1] = [0.5, 0, 0]
    book.after_fusion(12_000_000, (0, 1, 2, 3), *_filters(pos))
    assert book.state[1] is IdentityState.AMBIGUOUS and book.swaps_suspected == 1
    # a wide position uncertainty widens the distance: 0.3 m apart with 5 cm std each is ambiguous
    book2 = _book(models)
    book2.acquired([_ident(b, [b * 1.0, 0, 0]) for b in range(3)], [0, 1, 2])
    book2.after_fusion(0, (0, 1, 2), *_filters([[0.0, 0, 0], [0.3, 0, 0], [2.0, 0, 0], [9, 9, 9]], 0.05**2 / 3))
    assert book2.state[0] is IdentityState.AMBIGUOUS
    # and so does closing speed: 6 cm apart, closing at 4 m/s (2 cm until the next check)
    book3 = _book(models)
    book3.acquired([_ident(b, [b * 1.0, 0, 0]) for b in range(3)], [0, 1, 2])
    apart = [[0.0, 0, 0], [0.06, 0, 0], [2.0, 0, 0], [9, 9, 9]]
    book3.after_fusion(0, (0, 1, 2), *_filters(apart))
    assert book3.state[0] is IdentityState.ACQUIRED
    closing = [[2.0, 0, 0], [-2.0, 0, 0], [0] * 3, [0] * 3]
    book3.after_fusion(10_000_000, (0, 1, 2), *_filters(apart, velocities=closing))
    assert book3.state[0] is IdentityState.AMBIGUOUS


def test_pipeline_tracks_two_copies_of_a_layout_and_says_how_it_knows(two_of_a_kind):
    """End to end (thesis arena): two quads with the same layout parked 0.6 m apart along x, the second then
    flying a figure-eight; both tracked under the names of the parking order, unresolved until bound."""
    from visionpos.fusion.pipeline import FusionPipeline
    from visionpos.sim import simulate

    sc = two_of_a_kind({"left": {"trajectory": "static", "position": [-0.3, 0.0, 0.0]},
                        "right": {"trajectory": "figure8", "center": [0.3, 0.0, 0.9], "size": [0.4, 0.3],
                                  "period": 3.0}}, 1.0)
    sim = simulate(sc)
    pipe = FusionPipeline(sc.arena)
    for f in sorted(sim.frames, key=lambda f: (f.recv_ns, f.camera_id)):
        pipe.push(f)
    end = max(f.recv_ns for f in sim.frames)
    states = {s.name: s for s in pipe.tick(end)}
    for name in ("left", "right"):
        assert states[name].tracked
        true_p, _ = sc.truth_at(name, np.array([end]))
        assert np.linalg.norm(states[name].position - true_p[0]) < 0.01  # its own body, not the other
    assert pipe.snapshot().identity == ("unresolved: acquired", "unresolved: acquired")
    assert pipe.stats()["bodies"]["left"]["identity"] == "unresolved: acquired"
    assert pipe.identity.bind(0) and pipe.snapshot().identity[0] == "tracked-by-continuity"
