"""What the console reads from fusion: why a body is not tracked, predicted markers, residuals, static blobs."""

from __future__ import annotations

import copy

import numpy as np

from console.replay import ReplaySession
from console.view import STATIC_BLOB_S, CameraWatch, ConsoleView
from visionpos.config.arena import parse_arena
from visionpos.fusion.rigidbody import BodyModel, identify
from visionpos.recording import RecordingReader

GHOST = {"name": "ghost", "markers": [[0.0, 0.0, 0.0], [0.21, 0.0, 0.0], [0.0, 0.13, 0.0], [0.06, 0.07, 0.05]]}


def test_identify_names_the_bodies_it_refused_as_ambiguous():
    tri = np.array([[0.0, 0.0, 0.0], [0.12, 0.0, 0.0], [0.0, 0.09, 0.0]])
    a = BodyModel("a", 1, tri)
    b = BodyModel("b", 2, np.vstack([tri, [[0.05, 0.05, 0.08]]]))
    seen = tri + [1.0, 2.0, 0.5]  # only the shared triangle is visible: either body fits it
    ambiguous: set[int] = set()
    assert identify(seen, [a, b], 0.004, 3, ambiguous=ambiguous) == []
    assert ambiguous == {0, 1}
    # the whole of b is not ambiguous
    ambiguous.clear()
    found = identify(b.markers + [1.0, 2.0, 0.5], [a, b], 0.004, 3, ambiguous=ambiguous)
    assert [f.body for f in found] == [1] and ambiguous == set()


def test_a_body_never_seen_gets_its_reason_and_a_tracked_one_its_predictions(thesis_log):
    r = RecordingReader(thesis_log)
    data = copy.deepcopy(r.config)
    data["bodies"].append(GHOST)
    arena = parse_arena(data, "recording config")
    s = ReplaySession(arena, list(r.packets_with_source()))
    s.advance_to(s.t0_ns + 1_500_000_000)
    view = ConsoleView(s)
    state = view.state(s.clock(), watch=True, rays=frozenset({2}))
    quad, ghost = state["bodies"]
    assert quad["tracked"] and not ghost["tracked"]
    # the simulator flies no ghost: the leftover blobs are its static reflections, too few to make 3 markers
    assert ghost["why"].startswith("not seen by enough cameras") or "none fits its layout" in ghost["why"], ghost
    for cam in state["cameras"]:
        labelled = [b for b in cam["blobs"] if b[2] == 0]
        assert len(labelled) == 4 and len(cam["pred"]) == 4
        # each matched blob within a pixel or two of the filter's prediction for this frame (tenths of px)
        for u, v, _ in labelled:
            assert min(np.hypot(u - p[0], v - p[1]) for p in cam["pred"]) < 20
        assert ("rays" in cam) == (cam["id"] == 2)
    rays = state["cameras"][1]["rays"]
    assert len(rays) == len(state["cameras"][1]["blobs"]) and all(abs(x) < 1e5 for r in rays for x in r)
    # the live residual, blob against its own predicted marker (the simulator's centroid noise is 0.2 px)
    assert all(0.05 < view.watch[c.id].residual_px < 1.0 for c in arena.cameras)


def test_a_blob_that_stays_put_is_reported_with_the_mask_that_removes_it():
    view = ConsoleView.__new__(ConsoleView)
    view.watch = {7: CameraWatch()}
    w = view.watch[7]
    t = 0
    step = 33_000_000
    rng = np.random.default_rng(1)
    while t <= (STATIC_BLOB_S + 0.5) * 1e9:
        moving = [100 + t * 1e-8, 50.0]  # a marker crossing the image
        view._watch_static(w, np.array([[400.2 + rng.normal(0, 0.1), 300.7 + rng.normal(0, 0.1)], moving]), t)
        t += step
    found = view.static_blobs(t)
    assert list(found) == [7] and len(found[7]) == 1
    s = found[7][0]
    assert abs(s["x"] - 400.2) < 0.2 and abs(s["y"] - 300.7) < 0.2 and s["seconds"] >= STATIC_BLOB_S
    x0, y0, x1, y1 = s["ignore"]
    assert x0 < 400 < x1 and y0 < 300 < y1 and x1 - x0 < 20
    # gone for longer than the gap: forgotten
    view._watch_static(w, np.zeros((0, 2)), t + 2_000_000_000)
    assert view.static_blobs(t + 2_000_000_000) == {}
