"""A shiny floor: mirror images and merged reflections (fusion/matching.py floor_merge_px, floor_gate; the
acquisition and the tracked fit), and a take-off on it (tests/data/takeoff_two_cameras.yaml: the geometry of
MoCapRasp's real two-camera recording, simulated)."""

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from visionpos.config.arena import load_arena
from visionpos.fusion.acquisition import match_unlabeled
from visionpos.fusion.matching import BELOW_FLOOR_M, MERGE_MAX_PX, floor_gate, floor_merge_px
from visionpos.sim import parse_sim, simulate
from visionpos.sim.capture import SPURIOUS_MIRROR

TAKEOFF = Path(__file__).resolve().parents[1] / "data" / "takeoff_two_cameras.yaml"


def test_the_docs_give_the_floor_figures_the_code_uses():
    doc = (Path(__file__).resolve().parents[2] / "docs" / "calibration.md").read_text(encoding="utf-8")
    section = doc[doc.index("## A shiny floor"):]
    assert f"more than {BELOW_FLOOR_M * 100:.0f} cm under the floor is a mirror image" in " ".join(section.split())
    assert f"less than {MERGE_MAX_PX:.0f} px apart" in " ".join(section.split())


def _down_camera(height_m: float, f_px: float):
    """A camera at (0, 0, height) looking straight down: R (1, 3, 3), t (1, 3), f (1,)."""
    R = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])  # camera z = world -z
    t = -R @ np.array([0.0, 0.0, height_m])
    return R[None], t[None], np.array([f_px])


def test_merge_spread_is_half_the_separation_of_a_marker_and_its_mirror_image():
    R, t, f = _down_camera(2.5, 800.0)
    # a marker 1.2 m off the axis, 1 cm up: its image at f x / (H - h), its mirror image's at f x / (H + h)
    x, h = 1.2, 0.01
    sep = 800.0 * x * (1 / (2.5 - h) - 1 / (2.5 + h))
    assert sep < MERGE_MAX_PX
    assert floor_merge_px(np.array([x, 0.0, h]), R, t, f)[0] == pytest.approx(sep / 2, rel=1e-9)
    # 10 cm up the two images are apart: two blobs, nothing merged
    assert floor_merge_px(np.array([x, 0.0, 0.10]), R, t, f)[0] == 0.0
    # on or under the floor: nothing
    assert floor_merge_px(np.array([x, 0.0, -0.01]), R, t, f)[0] == 0.0
    seen = np.array([True])
    assert floor_gate(np.array([x, 0.0, 1.0]), R, t, f, seen, 2.0) == 2.0  # exactly the gate in the air
    assert floor_gate(np.array([x, 0.0, h]), R, t, f, seen, 2.0) == pytest.approx(np.hypot(2.0, sep / 2))
    assert floor_gate(np.array([x, 0.0, -0.03]), R, t, f, seen, 2.0) < 0  # a mirror image: nothing passes


def _view(cam, X):
    """World points (N, 3) -> normalised coordinates (N, 2) of camera cam."""
    pc = X @ cam.R.T + cam.t
    return pc[:, :2] / pc[:, 2:3]


def test_acquisition_drops_mirror_images_and_keeps_markers_pulled_by_their_reflections():
    arena = load_arena(TAKEOFF)
    cams = list(arena.cameras)
    R = np.array([c.R for c in cams])
    t = np.array([c.t for c in cams])
    f = np.array([np.sqrt(c.model.fx * c.model.fy) for c in cams])
    markers = np.array(arena.bodies[0].markers)
    # in the air: every marker and every mirror image is a blob of its own in both cameras
    air = markers + [0.1, -0.1, 0.6]
    xn = [np.vstack([_view(c, air), _view(c, air * [1, 1, -1])]) for c in cams]
    pts, idx, _ = match_unlabeled(xn, R, t, f, 3.0, 2.0)
    assert pts[:, 2].min() > -0.02  # no mirror image comes back as a point
    assert sorted(idx[:, 0][idx[:, 0] < 4].tolist()) == [0, 1, 2, 3]
    np.testing.assert_allclose(np.sort(pts[:, 2])[-4:], np.sort(air[:, 2]), atol=1e-6)
    # on the floor, 2 cm up: each camera sees one blob per marker, pulled towards its reflection by a
    # different amount in each (the floor reflects each camera at its own angle); the worst case: one camera
    # sees the reflection as bright as the marker (pulled half-way), the other none. Without the allowance one
    # pair of rays misses by more than the 3 px gate and the marker is lost
    floor = markers + [-0.012, -0.133, 0.021]
    mirror = floor * [1, 1, -1]
    xn = [_view(c, floor) + w * (_view(c, mirror) - _view(c, floor)) for c, w in zip(cams, (0.5, 0.0))]
    spread = np.array([floor_merge_px(X, R, t, f) for X in floor])
    assert spread.min() > 1.0  # the pull is real here: px
    pts, idx, rms = match_unlabeled(xn, R, t, f, 3.0, 2.0)
    assert len(pts) == 4 and sorted(idx[:, 0].tolist()) == [0, 1, 2, 3]
    assert np.abs(pts[:, :2] - floor[idx[:, 0], :2]).max() < 0.02


PHASES = (("take-off from the floor", 0.0, 1.8), ("hover at 1 m", 1.8, 3.7), ("landing", 3.7, 5.5),
          ("standing on the floor", 5.6, 7.4), ("take-off", 7.4, 9.1))


def test_a_drone_on_a_shiny_floor_is_tracked_through_its_take_off():
    from visionpos.benchmarks.fusion import replay

    sc = parse_sim(load_arena(TAKEOFF))
    sim = simulate(sc)
    # the reproduction has what the real recording had: markers merged with their mirror images on the
    # floor, and mirror images of their own in the air
    merged = sum(int(tr.merged.sum()) for tr in sim.frame_truth)
    mirrors = sum(int((tr.marker == SPURIOUS_MIRROR).sum()) for tr in sim.frame_truth)
    assert merged > 100 and mirrors > 1000
    rep = replay(sc.arena, sim.frames)
    t = np.asarray(rep.times_ns)
    truth = sc.motion_at("drone", t)
    t_s = (t - sc.start_ns) * 1e-9
    tracked = np.asarray(rep.tracked["drone"], bool)
    d = np.asarray(rep.positions["drone"]) - truth.positions
    q = np.asarray(rep.quaternions["drone"])
    for name, a, b in PHASES:
        m = (t_s >= a) & (t_s < b)
        assert tracked[m].mean() > 0.97, name
        m &= tracked
        # the body itself, never its mirror image (the same x-y, z turned over) or a ghost
        assert np.median(np.linalg.norm(d[m, :2], axis=1)) < 2e-3, name
        assert np.abs(np.median(d[m, 2])) < (10e-3 if name == "standing on the floor" else 3e-3), name
        ang = (Rotation.from_quat(q[m]).inv() * Rotation.from_quat(truth.quaternions[m])).magnitude()
        # standing, the merged reflections tilt the pose by a few degrees (documented)
        assert np.degrees(np.median(ang)) < (5.0 if name == "standing on the floor" else 2.0), name
    # standing, the merged reflections pull the height down (5 mm here, documented); x-y is exact
    m = (t_s >= 5.6) & (t_s < 7.4) & tracked
    assert -10e-3 < np.median(d[m, 2]) < -1e-3

