"""What the console reads from fusion: why a body is not tracked, predicted markers, residuals, static blobs."""

from __future__ import annotations

import copy
import json

import numpy as np
import pytest

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


def _replay_view(thesis_log, at_s):
    r = RecordingReader(thesis_log)
    s = ReplaySession(parse_arena(r.config, "recording config"), list(r.packets_with_source()))
    s.advance_to(s.t0_ns + int(at_s * 1e9))
    view = ConsoleView(s)
    return s, view


def test_a_camera_view_is_built_again_only_when_its_camera_sent_something_new(thesis_log):
    s, view = _replay_view(thesis_log, 1.5)
    calls = lambda: dict(view.builds)  # noqa: E731
    first = view.state(s.clock())
    assert calls() == {c.id: 1 for c in s.arena.cameras}
    # a paused replay: no camera sent anything; the views are the same, only their frames' age grew
    later = view.state(s.clock() + 40_000_000)
    assert calls() == {c.id: 1 for c in s.arena.cameras}
    for a, b in zip(first["cameras"], later["cameras"]):
        assert (a["blobs"], a["pred"]) == (b["blobs"], b["pred"]) and len(a["pred"]) == 4
        assert b["age_ms"] == pytest.approx(a["age_ms"] + 40.0, abs=0.11)
    # a tab asks for camera 2's rays: only that view is built again
    view.state(s.clock(), rays=frozenset({2}))
    assert calls() == {c.id: 1 + (c.id == 2) for c in s.arena.cameras}
    # new frames from every camera: every view is built again
    s.advance_to(s.clock() + 50_000_000)
    view.state(s.clock(), rays=frozenset({2}))
    assert calls() == {c.id: 2 + (c.id == 2) for c in s.arena.cameras}


def test_a_camera_view_is_built_again_when_its_frames_labels_change(thesis_log):
    s, view = _replay_view(thesis_log, 1.5)
    cam = s.arena.cameras[0].id
    before = view.state(s.clock())["cameras"][0]
    o = s.pipeline.obs[cam]
    o.label[:] = -1  # fusion relabels a stored frame when it acquires a body
    after = view.state(s.clock())["cameras"][0]
    assert view.builds[cam] == 2
    assert any(b[2] == 0 for b in before["blobs"]) and all(b[2] == -1 for b in after["blobs"])


def test_the_state_text_is_the_state(thesis_log):
    s, view = _replay_view(thesis_log, 1.5)
    for cameras in (True, False):
        text = view.state_json(s.clock(), rays=frozenset({3}), cameras=cameras, extra={"replay": {"speed": 2.0}})
        assert text.startswith('{"type": "state"')
        want = view.state(s.clock(), rays=frozenset({3}), cameras=cameras)
        want["replay"] = {"speed": 2.0}
        assert json.loads(text) == want
