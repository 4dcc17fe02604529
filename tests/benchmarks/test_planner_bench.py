"""The planner bench's instruments: the simulated triangulation and the issue room's suggested set-up."""

import numpy as np

from visionpos.benchmarks.planner import room_layout, simulated_marker_rms_mm
from visionpos.config.arena import load_arena
from visionpos.geometry.triangulation import CameraRig, triangulation_crb


def test_simulated_marker_rms_reaches_the_cramer_rao_bound_of_a_point_two_cameras_see():
    cams = list(load_arena("thesis").cameras)[:2]
    X = np.array([[0.1, -0.2, 0.9]])
    vis = np.ones((1, 2), bool)
    got = simulated_marker_rms_mm(cams, X, vis, 4000, np.random.default_rng(0))
    crb = triangulation_crb(CameraRig(cams), X, 0.2, vis)
    assert abs(got[0] / (np.sqrt(np.trace(crb[0])) * 1e3) - 1.0) < 0.05


def test_the_room_layout_adds_the_suggestion_inside_the_walls(tmp_path):
    path, best, vol, cams = room_layout(tmp_path)
    layout = load_arena(path).cameras
    assert len(cams) == 6 and len(layout) == 7
    added = layout[-1]
    np.testing.assert_allclose(added.center, best.camera.center, atol=1e-9)
    np.testing.assert_allclose(added.R, best.camera.R, atol=1e-9)
    assert (np.abs(added.center[:2]) <= 3.0).all() and 0.0 <= added.center[2] <= 3.0
    assert np.isfinite(best.marker_rms_mm) and (vol.lo == [-2, -2, 0.2]).all()
