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


# ------------------------------------------------------------------ health: levels, alerts, the documented keys

class _Pipeline:
    def snapshot(self):
        from visionpos.fusion.snapshot import FusionSnapshot

        return FusionSnapshot({}, (True, False), {1: "not seen by enough cameras: 1 of 4 see blobs"})


class _Source:
    """What HealthView reads of a server: counts that grow by `per_s` between two health() reads 1 s apart."""

    def __init__(self, arena):
        from types import SimpleNamespace

        from visionpos.messages import BodyState

        self.arena, self.pipeline, self.reads = arena, _Pipeline(), 0
        self.settings = SimpleNamespace(output_rate_hz=100.0)

        def state(b, tracked):
            nan = np.full(3, np.nan)
            return BodyState(name=b.name, body_id=b.id, time_ns=0, capture_ns=0, position=np.zeros(3),
                             quaternion=np.array([0.0, 0, 0, 1]), velocity=nan, angular_velocity=nan,
                             covariance=np.eye(6), velocity_covariance=np.eye(3), tracked=tracked, n_markers=4,
                             n_cameras=4, reset_counter=0)
        self.last_states = [state(arena.bodies[0], True), state(arena.bodies[1], False)]

    def health(self):
        k = self.reads
        self.reads += 1
        cams = {c.id: {"state": "streaming", "fps": 100.0 if c.id != 2 else 60.0, "fps_nominal": 100.0,
                       "shed": 40 * k if c.id == 3 else 0, "last_seen_s_ago": 0.004} for c in self.arena.cameras}
        vehicle = {"body": "quad", "sysid": 1, "endpoint": "udpout:127.0.0.1:1", "link_up": True, "rate_hz": 50.0,
                   "signed": False, "autopilot": "ardupilot", "ekf": "using vision", "ekf_detail": "ratios",
                   "delay_ms": 21.5, "delay_detail": "measured"}
        vehicles = {"slow": {**vehicle, "sent": 30 * k},  # 30 of 50 poses/s: amber
                    "starved": {**vehicle, "sysid": 2, "sent": 7},  # nothing more sent: red
                    "blind": {**vehicle, "sysid": 3, "sent": 50 * k, "ekf": "not using vision",
                              "ekf_detail": "the EKF has no relative position"}}  # red, with the reason
        return {"cameras": cams, "bodies_tracked_ticks": {"quad": 60 * k}, "frames_shed": 40 * k,
                "late_ticks": 0, "sinks": {"Bridge": {"vehicles": vehicles}}}


def _health(arena_yaml, reads: int = 2):
    from console.health import HealthView

    data = arena_yaml("thesis")
    data["bodies"].append(GHOST)
    source = _Source(parse_arena(data, "thesis.yaml"))
    view = ConsoleView(source)
    cams = view.scene["cameras"]
    cams[3]["mask"] = {"rois": [], "ignore": [[0, 0, cams[3]["width"], cams[3]["height"]]], "mask_png": None}
    view.static_blobs = lambda now_ns: {1: [{"x": 10.0, "y": 20.0, "seconds": 6.0, "ignore": [4, 14, 17, 27]},
                                            {"x": 90.0, "y": 70.0, "seconds": 9.0, "ignore": [84, 64, 97, 77]}]}
    hv = HealthView(view)
    h = hv.health(0)
    return h if reads == 1 else hv.health(1_000_000_000)


def test_a_rate_not_measured_yet_is_shown_as_none_and_raises_no_alert(arena_yaml):
    h = _health(arena_yaml, reads=1)  # the first read: one sample, no rate yet
    assert [v["rate_hz"] for v in h["vehicles"]] == [None] * 3
    assert h["vehicles"][0]["level"] == "ok" and h["vehicles"][1]["alerts"] == []
    assert h["bodies"][0]["rate_hz"] is None and h["bodies"][0]["level"] == "ok"
    assert h["server"]["shed_per_s"] is None and h["server"]["level"] == "ok"


def test_health_rows_turn_amber_for_a_rate_not_met_and_red_with_the_reason(arena_yaml):
    h = _health(arena_yaml)
    v = {r["name"]: r for r in h["vehicles"]}
    assert v["slow"]["level"] == "warn" and v["slow"]["alerts"] == ["30 poses/s, configured 50"]
    assert v["starved"]["level"] == "bad" and v["starved"]["alerts"] == ["0 poses/s reach it (configured 50)"]
    assert v["blind"]["level"] == "bad"
    assert v["blind"]["alerts"] == ["EKF not using vision: the EKF has no relative position"]
    assert v["blind"]["ekf"] == "not using vision" and v["blind"]["delay_ms"] == 21.5
    b = {r["name"]: r for r in h["bodies"]}
    assert b["quad"]["level"] == "warn" and b["quad"]["alerts"] == ["tracked in 60 of 100 ticks/s"]
    assert b["ghost"]["level"] == "bad" and b["ghost"]["alerts"][0].startswith("not tracked: not seen by enough")
    c = {r["id"]: r for r in h["cameras"]}
    assert c[1]["level"] == "ok" and c[1]["alerts"] == []
    assert c[2]["level"] == "warn" and c[2]["alerts"] == ["60 frames/s, configured 100"]
    assert c[3]["level"] == "warn" and c[3]["shed_per_s"] == 40.0
    assert c[4]["level"] == "bad" and c[4]["searched_share"] == 0.0
    assert c[4]["alerts"] == ["masked over its whole image: its station searches no pixel"]
    assert h["server"]["level"] == "warn" and h["server"]["shed_per_s"] == 40.0
    # the warnings: what stops a flight first (vehicles, bodies, then cameras)
    w = h["warnings"]
    first = lambda prefix: next(i for i, x in enumerate(w) if x.startswith(prefix))  # noqa: E731
    assert first("vehicle starved:") < first("vehicle blind:") < first("body ghost") < first("camera 2 (")
    assert any("masked over its whole image" in x for x in w)
    # camera 1's two reflections: one line, and their rectangles for "mask these"
    lines = [x for x in w if x.startswith("camera 1 (")]
    assert len(lines) == 1 and lines[0].startswith("camera 1 (pi1): 2 bright blobs at (10, 20), (90, 70) px")
    assert "[4, 14, 17, 27], [84, 64, 97, 77]" in lines[0]
    assert h["reflections"] == [{"camera": 1, "ignore": [[4, 14, 17, 27], [84, 64, 97, 77]]}]


def test_every_health_key_the_docs_name_is_in_the_health_json(arena_yaml):
    import re
    from pathlib import Path

    doc = (Path(__file__).resolve().parents[2] / "docs" / "console.md").read_text()
    table = doc[doc.index("The keys of `/api/health`"):doc.index("**When the stream stops**")]
    keys = [k for row in table.splitlines()[4:] if row.startswith("| ") for k in re.findall(r"`([a-z_.\[\]]+)`",
                                                                                           row.split(" | ")[0])]
    assert len(keys) >= 20, keys
    h = _health(arena_yaml)
    for key in keys:
        node = h
        for part in key.split("."):
            if part.endswith("[]"):
                node = node[part[:-2]][0]
            else:
                assert part in node, key
                node = node[part]


def test_the_docs_say_how_often_health_comes():
    from pathlib import Path

    from console.server import HEALTH_PERIOD_S

    doc = (Path(__file__).resolve().parents[2] / "docs" / "console.md").read_text()
    assert "**Health**, once a second" in doc and HEALTH_PERIOD_S == 1.0


def test_the_searched_share_of_an_image_from_rois_and_ignore_rectangles():
    from console.health import searched_share

    assert searched_share(None, 640, 480) is None
    assert searched_share({"rois": [], "ignore": []}, 640, 480) == 1.0
    assert searched_share({"rois": [], "ignore": [[0, 0, 320, 480]]}, 640, 480) == 0.5
    # a 320 x 240 ROI with a 160 x 240 ignore rectangle over half of it: an eighth of the image
    assert searched_share({"rois": [[0, 0, 320, 240]], "ignore": [[160, 0, 640, 480]]}, 640, 480) == 0.125
    assert searched_share({"rois": [[0, 0, 100, 100]], "ignore": [[0, 0, 640, 480]]}, 640, 480) == 0.0


def test_a_tracked_body_carries_its_filter_nis(thesis_log):
    s, view = _replay_view(thesis_log, 1.5)
    quad = view.state(s.clock(), cameras=False)["bodies"][0]
    assert quad["tracked"]
    nis_p, nis_r = quad["nis"]
    # a consistent filter on the simulator's own noise: averages of order 1 (chi-square over its dimension)
    assert 0.05 < nis_p < 20 and 0.05 < nis_r < 20, quad["nis"]
