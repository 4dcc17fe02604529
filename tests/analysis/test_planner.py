"""`visionpos plan`: coverage, Cramér-Rao bounds and the added-camera suggestion, against hand-derived values."""

import json
import math
import subprocess
import sys
from dataclasses import replace

import numpy as np

from visionpos.analysis.planner import (
    Volume,
    body_bounds,
    candidate_cameras,
    default_volume,
    marker_coverage,
    suggest_camera,
)
from visionpos.camera.model import Camera
from visionpos.config.arena import load_arena
from visionpos.geometry.triangulation import pose_crb, triangulation_crb

F_PX = 800.0


def _cam(cid: int, position, look_at) -> Camera:
    return Camera.from_dict({"id": cid, "width": 1280, "height": 960, "fx": F_PX, "fy": F_PX, "cx": 640, "cy": 480,
                             "pose": {"position": list(position), "look_at": list(look_at)}})


def test_marker_bound_of_two_orthogonal_cameras_matches_the_hand_derivation():
    # camera A on -x looking +x measures y and z, camera B on -y looking +y measures x and z, each with
    # std s = sigma * d / f metres at the origin: information 1/s^2 on x and y, 2/s^2 on z, so
    # trace CRB = s^2 + s^2 + s^2 / 2
    d, sigma = 3.0, 0.2
    cams = [_cam(1, (-d, 0, 0), (0, 0, 0)), _cam(2, (0, -d, 0), (0, 0, 0))]
    n, std_mm = marker_coverage(cams, np.zeros((1, 3)), sigma)
    s = sigma * d / F_PX
    assert n[0] == 2
    assert math.isclose(std_mm[0], math.sqrt(2.5) * s * 1e3, rel_tol=1e-9)
    # a point only one camera sees has no bound
    _, std1 = marker_coverage(cams, np.array([[0.0, 5.0, 0.0]]), sigma)
    assert not np.isfinite(std1[0])


def test_pose_bound_equals_the_chained_marker_bounds_and_needs_three_markers():
    arena = load_arena("thesis")
    cams, body = list(arena.cameras), arena.bodies[0]
    origin = np.array([0.3, -0.2, 0.9])
    X = origin + body.markers
    vis = np.stack([c.visible(X) for c in cams], 1)
    C = pose_crb(cams, X, origin, 0.2, vis)
    # the same information through each marker's triangulation bound, d X / d pose = [I, -skew(X - origin)]
    F = np.zeros((6, 6))
    for Ci, x in zip(triangulation_crb(cams, X, 0.2, vis), X):
        r = x - origin
        G = np.hstack([np.eye(3), -np.array([[0, -r[2], r[1]], [r[2], 0, -r[0]], [-r[1], r[0], 0]])])
        F += G.T @ np.linalg.inv(Ci) @ G
    np.testing.assert_allclose(C, np.linalg.inv(F), rtol=1e-8)
    # two markers cannot fix the rotation about the line through them
    assert np.isinf(pose_crb(cams, X[:2], origin, 0.2, vis[:2])).all()
    pos_mm, rot_deg = body_bounds(cams, body, origin, 0.2, yaws_deg=(0.0,))
    assert math.isclose(pos_mm, math.sqrt(np.trace(C[:3, :3])) * 1e3, rel_tol=1e-9)
    assert math.isclose(rot_deg, math.degrees(math.sqrt(np.trace(C[3:, 3:]))), rel_tol=1e-9)


def test_the_suggestion_fills_the_side_a_missing_camera_left_open():
    arena = load_arena("thesis")
    vol = default_volume(arena.cameras, 0.5)
    for removed in range(len(arena.cameras)):
        kept = replace(arena, cameras=tuple(c for i, c in enumerate(arena.cameras) if i != removed))
        best = suggest_camera(kept, vol, top=1)[0]
        centre = 0.5 * (vol.lo + vol.hi)
        gone = arena.cameras[removed].center - centre
        got = best.camera.center - centre
        angle = math.degrees(abs(math.atan2(gone[0] * got[1] - gone[1] * got[0], gone[0] * got[0] + gone[1] * got[1])))
        assert angle <= 45.0, (removed, angle)
        assert best.seen_by_2 >= float(np.mean(marker_coverage(list(kept.cameras), vol.grid(), 0.2)[0] >= 2))


def test_candidates_aim_at_the_volume_centre():
    arena = load_arena("thesis")
    vol = Volume(np.array([-1.0, -1.0, 0.2]), np.array([1.0, 1.0, 1.6]), 0.5)
    for c in candidate_cameras(list(arena.cameras), vol):
        centre_px = c.project((0.5 * (vol.lo + vol.hi))[None])[0]
        np.testing.assert_allclose(centre_px, [c.model.cx, c.model.cy], atol=1e-6)


def test_plan_command_prints_and_writes_json_and_png(tmp_path):
    r = subprocess.run([sys.executable, "-m", "visionpos", "plan", "thesis", "--step-m", "0.5", "--suggest", "1",
                        "--out", str(tmp_path)], capture_output=True, text=True, timeout=300)
    out = tmp_path / "plan.json"
    assert r.returncode == 0, r.stderr
    assert "cameras seeing a point" in r.stdout and "suggestion 1:" in r.stdout and "body quad:" in r.stdout
    data = json.loads(out.read_text())
    assert len(data["points"]) == len(data["n_cameras"]) == len(data["marker_std_mm"]) > 0
    assert set(data["bodies"]) == {"quad"}
    assert (tmp_path / "plan.png").stat().st_size > 10_000  # matplotlib is in the test extra
    bad = subprocess.run([sys.executable, "-m", "visionpos", "plan", "thesis", "--volume", "1", "0", "0", "1", "0",
                          "1"], capture_output=True, text=True, timeout=120)
    assert bad.returncode != 0 and "--volume" in bad.stderr
