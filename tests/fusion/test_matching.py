"""Cross-view matching, association and the fast triangulation (visionpos/fusion/matching.py, acquisition.py)."""

import numpy as np
import pytest

from visionpos.camera.model import undistort_points
from visionpos.config.arena import load_arena
from visionpos.fusion.acquisition import match_unlabeled
from visionpos.fusion.matching import Projector, associate, min_cost_assignment, triangulate
from visionpos.geometry.triangulation import triangulate_normalized


@pytest.fixture(scope="module")
def rig():
    arena = load_arena("thesis")
    cams = list(arena.cameras)
    R = np.array([c.R for c in cams])
    t = np.array([c.t for c in cams])
    f = np.array([np.sqrt(c.model.fx * c.model.fy) for c in cams])
    return cams, R, t, f


def _normalized(cams, X):
    """(P, 3) world -> (P, V, 2) exact normalised coordinates."""
    out = []
    for c in cams:
        pc = X @ c.R.T + c.t
        out.append(pc[:, :2] / pc[:, 2:3])
    return np.stack(out, axis=1)


def test_undistort_points_agrees_with_camera_model():
    for name in ("thesis", "arena8"):
        for cam in load_arena(name).cameras:
            rng = np.random.default_rng(cam.id)
            px = rng.uniform([50, 50], [cam.model.width - 50, cam.model.height - 50], (20, 2))
            ref = cam.model.undistort(px)
            got = undistort_points(cam.model, px)
            # back through the model's own distortion: the pixel must come back
            assert np.abs(cam.model.distort(got) - px).max() < 1e-6
            assert np.abs(got - ref).max() * cam.model.fx < 1e-6
    # a strongly distorted lens, pixels well beyond the sensor: NaN exactly where the model's own
    # undistortion finds no pre-image (the fold of the distortion), the same values elsewhere
    from visionpos.camera.model import CameraModel

    for m in (CameraModel("pinhole", 960, 640, 500.0, 500.0, 480.0, 320.0, np.array([-0.45, 0.2, 0.001, 0.0, -0.04])),
              CameraModel("fisheye", 960, 640, 300.0, 300.0, 480.0, 320.0, np.array([0.1, -0.05, 0.01, -0.002]))):
        px = np.random.default_rng(3).uniform([-1500, -1500], [2500, 2000], (4000, 2))
        ref, got = m.undistort(px), undistort_points(m, px)
        assert np.array_equal(np.isnan(ref[:, 0]), np.isnan(got[:, 0]))
        assert 0 < np.isnan(got[:, 0]).sum() < len(px)
        ok = ~np.isnan(got[:, 0])
        assert np.abs(got[ok] - ref[ok]).max() * m.fx < 1e-6


def test_triangulate_exact_missing_views_and_offsets(rig):
    cams, R, t, f = rig
    rng = np.random.default_rng(0)
    X = rng.uniform([-0.8, -0.8, 0.3], [0.8, 0.8, 1.6], (10, 3))
    xn = _normalized(cams, X)
    xn[0, 1:] = np.nan  # one view only: no point
    xn[1, :2] = np.nan  # two views left
    Y, rms, nv = triangulate(xn, R, t, f)
    assert np.isnan(Y[0]).all() and nv[0] == 1
    assert np.abs(Y[1:] - X[1:]).max() < 1e-9
    assert rms[1:].max() < 1e-6
    # motion compensation: view v saw the point displaced by offsets[p, v]
    off = rng.normal(0, 0.02, (10, 4, 3))
    xo = np.stack([_normalized([c], X + off[:, v])[:, 0] for v, c in enumerate(cams)], axis=1)
    Y, rms, _ = triangulate(xo, R, t, f, off)
    assert np.abs(Y - X).max() < 1e-9
    # without compensation the same data is inconsistent
    _, rms_naive, _ = triangulate(xo, R, t, f)
    assert rms_naive.min() > 1.0


def test_triangulate_matches_maximum_likelihood_of_geometry(rig):
    """Noisy views: the reweighted linear solution lands on geometry's LM (ML) point."""
    cams, R, t, f = rig
    rng = np.random.default_rng(1)
    X = rng.uniform([-0.8, -0.8, 0.3], [0.8, 0.8, 1.6], (50, 3))
    xn = _normalized(cams, X) + rng.normal(0, 0.3, (50, 4, 2)) / f[None, :, None]
    Y, rms, _ = triangulate(xn, R, t, f)
    ref = triangulate_normalized(xn, R, t, refine=True)
    err = np.linalg.norm(Y - X, axis=1)
    d = np.linalg.norm(Y - ref.points, axis=1)
    assert np.median(d) < 0.05 * np.median(err)  # same point, up to a small fraction of the noise
    assert 0.1 < np.median(rms) < 0.5


def test_associate_with_spurious_and_missing():
    pred = np.array([[100.0, 100.0], [200.0, 120.0], [300.0, 300.0], [np.nan, np.nan]])
    blobs = np.array(
        [
            [301.5, 299.0],  # marker 2
            [500.0, 500.0],  # spurious
            [101.0, 99.5],  # marker 0
            [150.0, 100.0],  # spurious, outside every gate
        ]
    )  # marker 1 missing, marker 3 not visible
    a = associate(pred, blobs, gate=10.0)
    assert a.tolist() == [2, -1, 0, -1]


def test_associate_ambiguity_resolved_jointly():
    # both predictions are nearest to blob 0; the joint assignment gives each its own blob
    pred = np.array([[100.0, 100.0], [104.0, 100.0]])
    blobs = np.array([[102.5, 100.0], [108.0, 100.0]])
    a = associate(pred, blobs, gate=8.0)
    assert a.tolist() == [0, 1]
    # one blob for two predictions: only one gets it
    a = associate(pred, blobs[:1], gate=8.0)
    assert sorted(a.tolist()) == [-1, 0]


def test_min_cost_assignment_is_optimal():
    """Against scipy's linear_sum_assignment (an independent solver) on random rectangular costs."""
    from scipy.optimize import linear_sum_assignment

    rng = np.random.default_rng(4)
    for _ in range(300):
        n = int(rng.integers(1, 7))
        m = int(rng.integers(n, 9))
        C = rng.uniform(0, 100, (n, m))
        C[rng.random((n, m)) < 0.3] = 1e5  # gated-out pairs
        col = min_cost_assignment(C)
        assert len(set(col.tolist())) == n and (col >= 0).all()
        r, c = linear_sum_assignment(C)
        assert C[np.arange(n), col].sum() == pytest.approx(C[r, c].sum(), rel=1e-12)


@pytest.mark.parametrize("kind, dist", [("pinhole", [0.1, -0.2, 0.001, -0.002, 0.05, 0.01, -0.02, 0.03]),
                                        ("pinhole", [-0.3, 0.1, 0.0, 0.0]), ("fisheye", [0.05, -0.01, 0.002, -0.001])])
def test_projector_matches_opencv(kind, dist):
    """The compiled projection equals cv2.projectPoints / cv2.fisheye.projectPoints (an
    independent implementation of the same lens models) and hides what is off the sensor."""
    import cv2

    from visionpos.camera.model import Camera, CameraModel, look_at_rotation

    m = CameraModel(kind, 960, 640, 600.0, 602.0, 480.0, 320.0, np.array(dist))
    c = np.array([3.0, -2.0, 2.5])
    R = look_at_rotation(c, np.zeros(3))
    cam = Camera(1, "c", m, R, -R @ c)
    X = np.random.default_rng(5).normal(0, 1.5, (2000, 3))
    uv = Projector(cam).project(X, margin=8.0)
    rvec = cv2.Rodrigues(R)[0]
    if kind == "fisheye":
        ref = cv2.fisheye.projectPoints(X.reshape(-1, 1, 3), rvec, cam.t, m.K, m.dist)[0].reshape(-1, 2)
    else:
        ref = cv2.projectPoints(X, rvec, cam.t, m.K, m.dist)[0].reshape(-1, 2)
    pc = X @ R.T + cam.t
    on = (pc[:, 2] > 0.2) & (ref > -8.5).all(1) & (ref[:, 0] < 967.5) & (ref[:, 1] < 647.5)
    on &= np.arctan2(np.linalg.norm(pc[:, :2], axis=1), pc[:, 2]) < m.max_theta
    assert 500 < on.sum() < 2000
    assert np.array_equal(np.isfinite(uv[:, 0]), on)
    assert np.abs(uv[on] - ref[on]).max() < 1e-9


def test_match_unlabeled_spurious_and_missing(rig):
    cams, R, t, f = rig
    rng = np.random.default_rng(2)
    X = rng.uniform([-0.6, -0.6, 0.5], [0.6, 0.6, 1.4], (8, 3))
    xn = _normalized(cams, X) + rng.normal(0, 0.2, (8, 4, 2)) / f[None, :, None]
    seen = np.ones((8, 4), bool)
    seen[0, [1, 2]] = False  # two views
    seen[1, 3] = False  # three views
    seen[2, 1:] = False  # only one view: cannot be triangulated
    views, truth = [], []
    for v in range(4):
        pts = xn[seen[:, v], v]
        ids = np.nonzero(seen[:, v])[0]
        junk = rng.uniform(-0.6, 0.6, (3, 2))  # spurious blobs
        allp = np.vstack([pts, junk])
        order = rng.permutation(len(allp))
        views.append(allp[order])
        truth.append(np.concatenate([ids, -np.ones(3, int)])[order])
    P, idx, rms = match_unlabeled(views, R, t, f, ray_gate_px=3.0, max_residual_px=2.0)
    found = {}
    for q in range(len(P)):
        labels = {int(truth[v][idx[q, v]]) for v in range(4) if idx[q, v] >= 0}
        assert len(labels) == 1, "a matched point mixes blobs of different markers"
        label = labels.pop()
        if label == -1:
            # two junk rays that happen to cross are geometrically a valid 2-view
            # point; a third view must never confirm junk
            assert (idx[q] >= 0).sum() == 2
            continue
        found[label] = P[q]
    assert set(found) == {0, 1, 3, 4, 5, 6, 7}
    for k, p in found.items():
        assert np.linalg.norm(p - X[k]) < 0.003


def _pinhole(look_at_camera, centers, target):
    from visionpos.camera.model import CameraModel

    model = CameraModel("pinhole", 960, 640, 740.0, 740.0, 480.0, 320.0, np.zeros(5))
    cams = [look_at_camera(c, target, model, camera_id=i + 1) for i, c in enumerate(centers)]
    R = np.array([c.R for c in cams])
    t = np.array([c.t for c in cams])
    return cams, R, t, np.array([740.0, 740.0])


def test_acquisition_gate_scales_with_range_far_pair_accepted(look_at_camera):
    # two cameras 3 m apart, a marker 8.5 m away; camera 2 is off by 1.3 px across the epipolar
    # lines (calibration): its ray misses by 1.3 px x 11.5 mm/px = 15 mm, more than the old 10 mm
    # gate, yet the pair triangulates to well under a pixel of RMS residual
    X = np.array([[0.0, 8.0, 0.0]])
    cams, R, t, f = _pinhole(look_at_camera, [(-1.5, 0.0, 2.6), (1.5, 0.0, 2.6)], X[0])
    xn = _normalized(cams, X)
    xn[0, 1, 1] += 1.3 / 740.0
    r = np.linalg.norm(X[0] - np.array([1.5, 0.0, 2.6]))
    assert 1.3 * r / 740.0 > 0.012  # the rays do pass more than 1 cm apart
    P, idx, rms = match_unlabeled([xn[:, 0], xn[:, 1]], R, t, f, 3.0, 2.0)
    assert len(P) == 1 and rms[0] < 1.0
    assert np.linalg.norm(P[0] - X[0]) < 0.05


def test_acquisition_gate_is_tighter_up_close(look_at_camera):
    # cameras 1.1 m from a marker: a blob 8 mm above it in camera 2 (another marker) gives rays
    # that pass ~8 mm apart, which the old 10 mm gate paired; 3 px at 1.1 m is ~6 mm
    X = np.array([[0.0, 1.0, 1.0]])
    cams, R, t, f = _pinhole(look_at_camera, [(-0.5, 0.0, 1.0), (0.5, 0.0, 1.0)], X[0])
    right = _normalized(cams, X)
    wrong = _normalized(cams, X + [0.0, 0.0, 0.008])
    # a rough calibration's loose residual gate: the seed gate is what refuses the wrong pair
    P, _, _ = match_unlabeled([right[:, 0], wrong[:, 1]], R, t, f, 3.0, 4.0)
    assert len(P) == 0
    P, _, rms = match_unlabeled([right[:, 0], right[:, 1]], R, t, f, 3.0, 4.0)
    assert len(P) == 1 and rms[0] < 1e-6 and np.linalg.norm(P[0] - X[0]) < 1e-6


def test_refine_in_pixels_reaches_the_exact_point_through_fisheye_lenses():
    """Noise-free pixels of the thesis cameras (fisheye), views moved by offsets, a start 2 cm off: the refined
    point is the true one and its residual is zero; a view that sees the point from behind gives NaN."""
    from visionpos.camera.model import lens_arrays
    from visionpos.fusion.matching import refine_in_pixels

    cams = load_arena("thesis").cameras
    rng = np.random.default_rng(3)
    X = rng.uniform([-0.5, -0.5, 0.4], [0.5, 0.5, 1.6], (50, 3))
    off = rng.normal(0.0, 0.01, (50, len(cams), 3))
    px = np.stack([c.project(X + off[:, v]) for v, c in enumerate(cams)], axis=1)
    px[:, 0] = np.nan  # one view left out, as the monitor leaves the camera under test out
    lenses = [lens_arrays(c.model) for c in cams]
    args = (np.array([c.R for c in cams]), np.array([c.t for c in cams]), np.array([x[0] for x in lenses]),
            np.array([x[1] for x in lenses]), np.array([x[2] for x in lenses]))
    start = X + rng.normal(0.0, 0.02, X.shape)
    points, rms = refine_in_pixels(start, px, off, True, *args, 5)
    np.testing.assert_allclose(points, X, atol=1e-9)
    assert np.abs(rms).max() < 1e-6
    # one pixel off in one view: the residual says so (RMS over the 3 views of the error's length)
    px[0, 1, 0] += 1.0
    _, rms = refine_in_pixels(start, px, off, True, *args, 5)
    assert 0.2 < rms[0] < 1.0 / np.sqrt(3) + 1e-6
    behind = X[:1] - 2.0 * (X[:1] - cams[1].center)  # mirrored through camera 1's centre: behind it
    points, rms = refine_in_pixels(behind, px[:1], off[:1], True, *args, 5)
    assert np.isnan(points).all() and np.isnan(rms).all()


def _crowded_views(rig, seed):
    """Many markers close together in the thesis rig's four views, with spurious blobs and two blobs in a view
    at exactly the same place (a tie): normalised coordinates per view."""
    cams, R, t, f = rig
    rng = np.random.default_rng(seed)
    X = rng.uniform([-0.5, -0.5, 0.0], [0.5, 0.5, 1.2], (40, 3))
    xn = _normalized(cams, X) + rng.normal(0, 0.3, (40, 4, 2)) / f[None, :, None]
    views = []
    for v in range(4):
        seen = xn[rng.random(40) > 0.1, v]
        views.append(np.vstack([seen, rng.uniform(-0.5, 0.5, (6, 2)), seen[:1]]))
    return views


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_seeds_and_growth_are_the_brute_force_ones(rig, seed):
    """_seed_pairs keeps every pair of rays that passes the gate at its ranges (above the floor, in the views'
    pair order), and _grow_seeds gives each seed, in each view it lacks, the nearest blob within 3 x
    max_residual_px (the lowest index among equally near ones): both against every pair and every blob tried
    here in Python."""
    from visionpos.fusion import acquisition as M

    cams, R, t, f = rig
    views = _crowded_views(rig, seed)
    V = len(views)
    start = np.concatenate([[0], np.cumsum([len(x) for x in views])]).astype(np.int64)
    pts = np.ascontiguousarray(np.vstack(views))
    centres = np.array([-c.R.T @ c.t for c in cams])
    rays = [x_ @ np.eye(3)[:2] + np.eye(3)[2] for x_ in views]  # camera-frame directions (x, y, 1)
    rays = [(r @ c.R) / np.linalg.norm(r, axis=1)[:, None] for r, c in zip(rays, cams)]  # world
    gate_px = 3.0
    want = []
    for a in range(V):
        for b in range(a + 1, V):
            for i, d1 in enumerate(rays[a]):
                for j, d2 in enumerate(rays[b]):
                    # closest approach of the two rays: s, u along each from its centre
                    A = np.array([[d1 @ d1, -d1 @ d2], [d1 @ d2, -d2 @ d2]])
                    s, u = np.linalg.solve(A, [(centres[b] - centres[a]) @ d1, (centres[b] - centres[a]) @ d2])
                    p1, p2 = centres[a] + s * d1, centres[b] + u * d2
                    if s <= 0 or u <= 0 or (p1 + p2)[2] / 2 < -0.02:
                        continue
                    px = np.linalg.norm(p1 - p2) / np.hypot(s / f[a], u / f[b])
                    if px < gate_px - 1e-6:
                        want.append((a, i, b, j))
                    elif px < gate_px + 1e-6 or 0 < (p1 + p2)[2] / 2 < 0.5:
                        want.append(None)  # on the gate, or near the floor (its merge widening): either way
    pairs, X0 = M._seed_pairs(start, centres, np.ascontiguousarray(np.vstack(rays)), R, t, f, gate_px, 0, V)
    idx = M._seed_table(pairs, V)
    got = [tuple(int(k) for v in range(V) if idx[s, v] >= 0 for k in (v, idx[s, v])) for s in range(len(idx))]
    definite = [w for w in want if w is not None]
    assert set(definite) <= set(got) and len(got) <= len(want)
    assert got == sorted(got, key=lambda g: (g[0], g[2], g[1], g[3])), "in the views' pairs' order, then blobs'"
    assert len(got) > 3 * 40  # a crowded scene: many seeds, most of them ghosts

    max_residual_px = 2.0
    grown = idx.copy()
    M._grow_seeds(pts, start, R, t, f, max_residual_px, grown, X0, 0, V)
    for s in range(len(idx)):
        for v in range(V):
            if idx[s, v] >= 0:
                assert grown[s, v] == idx[s, v]
                continue
            pc = cams[v].R @ X0[s] + cams[v].t
            if pc[2] <= 0:
                assert grown[s, v] == -1
                continue
            d = np.linalg.norm(views[v] - pc[:2] / pc[2], axis=1) * f[v]
            near = np.nonzero(d <= d.min() + 1e-9)[0]
            if d.min() < 3 * max_residual_px - 1e-9:
                assert grown[s, v] in near and (len(near) == 1 or grown[s, v] == near[0])
            elif d.min() > 3 * max_residual_px + 1e-9:
                assert grown[s, v] == -1
    assert (grown >= 0).sum() > (idx >= 0).sum()  # it grew


def test_a_grown_seed_is_kept_once():
    """_first_of_each keeps the first of identical grown seeds, in order, and every distinct one."""
    from visionpos.fusion.acquisition import _first_of_each

    rows = np.array([[0, 1, -1], [2, -1, 3], [0, 1, -1], [0, 1, 2], [2, -1, 3], [-1, -1, -1], [0, 1, -1]])
    assert _first_of_each(rows).tolist() == [[0, 1, -1], [2, -1, 3], [0, 1, 2], [-1, -1, -1]]
    rng = np.random.default_rng(5)
    many = rng.integers(-1, 3, (500, 4))
    want = [list(r) for i, r in enumerate(many.tolist()) if r not in many.tolist()[:i]]
    assert _first_of_each(many).tolist() == want
