"""N-view triangulation (geometry/triangulation.py) against ground truth and independent references.

References never come from visionpos itself: projections come from OpenCV
(cv2.projectPoints / cv2.fisheye.projectPoints), Cramer-Rao bounds from an
explicit Fisher-information sum over finite-difference Jacobians of those OpenCV
projections.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from visionpos.camera.model import Camera, CameraModel, look_at_rotation
from visionpos.geometry.triangulation import (
    CameraRig,
    pose_crb,
    triangulate_normalized,
    triangulate_pixels,
    triangulation_crb,
)

V2_NOIR = [  # thesis Table 4.1, V2 NoIR cameras 1-4 at 960x640
    CameraModel("fisheye", 960, 640, 720.313, 719.521, 481.014, 360.991, [0.396, 0.634, -2.417, 2.111]),
    CameraModel("fisheye", 960, 640, 768.113, 767.935, 472.596, 350.978, [0.369, 1.501, -7.941, 11.917]),
    CameraModel("fisheye", 960, 640, 728.237, 729.419, 459.854, 351.59, [0.276, 2.095, -9.980, 14.192]),
    CameraModel("fisheye", 960, 640, 750.149, 748.903, 492.144, 350.213, [0.401, 1.160, -7.103, 11.415]),
]
PINHOLE = CameraModel("pinhole", 1280, 800, 800.0, 810.0, 650.0, 390.0, [-0.32, 0.12, 0.0015, -0.001, -0.015])


def thesis_rig() -> list[Camera]:
    """Four V2 NoIR cameras 2.6 m high at the corners of a 4.24 m x 4.82 m rectangle, aimed at the centre."""
    cams = []
    for i, (sx, sy) in enumerate([(-1, -1), (1, -1), (1, 1), (-1, 1)]):
        C = np.array([sx * 4.24 / 2, sy * 4.82 / 2, 2.6])
        R = look_at_rotation(C, np.zeros(3))
        cams.append(Camera(i, f"cam{i}", V2_NOIR[i], R, -R @ C))
    return cams


def random_rig(rng: np.random.Generator, n_cams: int) -> list[Camera]:
    """n cameras on a ring around the origin, aimed near it, with random roll; mixed models."""
    cams = []
    for i in range(n_cams):
        az = 2 * np.pi * i / n_cams + rng.uniform(-0.3, 0.3)
        rad = rng.uniform(2.0, 4.5)
        C = np.array([rad * np.cos(az), rad * np.sin(az), rng.uniform(1.0, 3.2)])
        R = look_at_rotation(C, rng.uniform(-0.4, 0.4, 3) + [0, 0, 0.8])
        roll = Rotation.from_rotvec([0, 0, rng.uniform(-0.3, 0.3)]).as_matrix()
        R = roll @ R
        model = V2_NOIR[i % 4] if rng.random() < 0.5 else PINHOLE
        cams.append(Camera(i, f"c{i}", model, R, -R @ C))
    return cams


def cv2_project(cam: Camera, X: np.ndarray) -> np.ndarray:
    """Independent projection (N, 3) world -> (N, 2) pixels through OpenCV; NaN behind or off-sensor."""
    rv, _ = cv2.Rodrigues(cam.R)
    m = cam.model
    if m.kind == "fisheye":
        uv, _ = cv2.fisheye.projectPoints(X.reshape(-1, 1, 3), rv, cam.t.reshape(3, 1), m.K, m.dist)
    else:
        uv, _ = cv2.projectPoints(X.reshape(-1, 1, 3), rv, cam.t, m.K, m.dist)
    uv = uv.reshape(-1, 2)
    z = X @ cam.R[2] + cam.t[2]
    cone = np.arccos(np.clip(z / np.linalg.norm(X @ cam.R.T + cam.t, axis=1), -1, 1)) < 0.95 * m.max_theta
    inside = (uv[:, 0] > 0) & (uv[:, 0] < m.width - 1) & (uv[:, 1] > 0) & (uv[:, 1] < m.height - 1)
    uv[~((z > 0.05) & cone & inside)] = np.nan
    return uv


def observe(cams, X):
    """(P, V, 2) pixels from OpenCV, NaN where not seen."""
    return np.stack([cv2_project(c, X) for c in cams], axis=1)


def fisher_reference(cams, X, vis, sigma, h=1e-6):
    """Independent CRB: Fisher information sum_v J_v^T J_v / sigma^2 with J_v from central
    differences of the OpenCV projection. Returns (P, 3, 3) covariance bound."""
    F = np.zeros((len(X), 3, 3))
    for v, cam in enumerate(cams):
        J = np.empty((len(X), 2, 3))
        for k in range(3):
            d = np.zeros(3)
            d[k] = h
            rv, _ = cv2.Rodrigues(cam.R)
            m = cam.model
            def proj(P):
                if m.kind == "fisheye":
                    uv, _ = cv2.fisheye.projectPoints(P.reshape(-1, 1, 3), rv, cam.t.reshape(3, 1), m.K, m.dist)
                else:
                    uv, _ = cv2.projectPoints(P.reshape(-1, 1, 3), rv, cam.t, m.K, m.dist)
                return uv.reshape(-1, 2)
            J[:, :, k] = (proj(X + d) - proj(X - d)) / (2 * h)
        J[~vis[:, v]] = 0.0
        F += np.einsum("pia,pib->pab", J, J) / sigma**2
    return np.linalg.inv(F)


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n_cams=st.integers(2, 8))
def test_noiseless_triangulation_is_exact(seed, n_cams):
    rng = np.random.default_rng(seed)
    cams = random_rig(rng, n_cams)
    X = rng.uniform([-1.0, -1.0, 0.1], [1.0, 1.0, 1.8], (60, 3))
    px = observe(cams, X)
    px[rng.random(px.shape[:2]) < 0.15] = np.nan  # occlusions
    seen = np.isfinite(px).all(axis=2).sum(axis=1)
    res = triangulate_pixels(cams, px)
    assert np.array_equal(res.n_views, seen)
    ok = seen >= 2
    assert np.isnan(res.points[~ok]).all()
    assert np.abs(res.points[ok] - X[ok]).max() < 1e-9
    assert np.nanmax(res.residuals[ok], initial=0.0) < 1e-6
    assert np.array_equal(np.isnan(res.residuals[ok]), ~np.isfinite(px[ok]).all(axis=2))
    # the same observations through normalised coordinates (undistorted independently by OpenCV)
    xn = np.full(px.shape, np.nan)
    for v, c in enumerate(cams):
        f = np.isfinite(px[:, v]).all(axis=1)
        if not f.any():
            continue
        crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-15)
        if c.model.kind == "fisheye":
            u = cv2.fisheye.undistortPoints(px[f, v].reshape(-1, 1, 2), c.model.K, c.model.dist, criteria=crit)
        else:
            u = cv2.undistortPoints(px[f, v].reshape(-1, 1, 2), c.model.K, c.model.dist, criteria=crit)
        xn[f, v] = u.reshape(-1, 2)
    # OpenCV's undistortion stops at its own tolerance; use where it reproduces the truth
    xt = np.stack([(X @ c.R.T + c.t) for c in cams], axis=1)
    xt = xt[..., :2] / xt[..., 2:]
    good = np.abs(xn - xt).max(axis=2) < 1e-12
    xn[~good] = np.nan
    resn = triangulate_normalized(xn, np.stack([c.R for c in cams]), np.stack([c.t for c in cams]))
    okn = good.sum(axis=1) >= 2
    assert np.abs(resn.points[okn] - X[okn]).max() < 1e-9


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_camera_rig_projection_and_undistortion_match_opencv(seed):
    rng = np.random.default_rng(seed)
    cams = random_rig(rng, 6)  # mixed pinhole / fisheye
    rig = CameraRig(cams)
    X = rng.uniform([-1.0, -1.0, 0.1], [1.0, 1.0, 1.8], (50, 3))
    ref = observe(cams, X)
    ok = np.isfinite(ref)
    np.testing.assert_allclose(rig.project(X)[ok], ref[ok], atol=1e-6)
    xt = np.stack([(X @ c.R.T + c.t) for c in cams], axis=1)
    xt = xt[..., :2] / xt[..., 2:]
    xn = rig.undistort(ref)
    assert np.abs(xn[ok] - xt[ok]).max() < 1e-10


def test_rig_and_camera_list_give_the_same_result_and_linear_start_is_close():
    rng = np.random.default_rng(11)
    cams = thesis_rig()
    X = rng.uniform([-1.0, -1.0, 0.2], [1.0, 1.0, 1.8], (100, 3))
    px = observe(cams, X) + rng.normal(0, 0.3, (100, 4, 2))
    a = triangulate_pixels(cams, px)
    b = triangulate_pixels(CameraRig(cams), px)
    np.testing.assert_array_equal(a.points, b.points)
    lin = triangulate_pixels(cams, px, refine=False)
    ok = a.n_views >= 2
    # the linear estimate is sub-centimetre, the refinement moves it by much less than that
    assert np.abs(lin.points[ok] - X[ok]).max() < 0.01
    # ML refinement never increases the summed squared pixel residual
    assert np.all(np.nansum(a.residuals**2, axis=1) <= np.nansum(lin.residuals**2, axis=1) + 1e-9)


def test_triangulation_rms_matches_cramer_rao_bound():
    """>= 2000 points, 0.3 px noise on the thesis arena: RMS 3-D error within 20 % of the CRB."""
    rng = np.random.default_rng(2024)
    cams = thesis_rig()
    sigma = 0.3
    X = rng.uniform([-1.5, -1.5, 0.1], [1.5, 1.5, 2.0], (3000, 3))
    px_true = observe(cams, X)
    vis = np.isfinite(px_true).all(axis=2)
    keep = vis.sum(axis=1) >= 2
    X, px_true, vis = X[keep], px_true[keep], vis[keep]
    assert len(X) >= 2000
    crb_ref = fisher_reference(cams, X, vis, sigma)
    crb = triangulation_crb(cams, X, sigma, visible=vis)
    # the library's bound agrees with the independent one (finite differences ~1e-6 relative)
    assert np.abs(crb - crb_ref).max() < 1e-4 * np.abs(crb_ref).max()
    px = px_true + rng.normal(0, sigma, px_true.shape)
    res = triangulate_pixels(cams, px)
    err = res.points - X
    rms = np.sqrt(np.mean(np.sum(err**2, axis=1)))
    rms_crb = np.sqrt(np.mean(np.trace(crb_ref, axis1=1, axis2=2)))
    assert 0.8 < rms / rms_crb < 1.2, (rms, rms_crb)
    # shape of the error too: Mahalanobis distance under the bound is chi^2 with 3 dof
    m2 = np.einsum("pi,pij,pj->p", err, np.linalg.inv(crb_ref), err)
    # (tight enough that the linear estimate without ML refinement, ~1.13, fails)
    assert 0.92 * 3 < m2.mean() < 1.08 * 3
    # residuals are in pixels: their mean square per view is sigma^2 (1 - 3 / (2 n_views))
    n = res.n_views
    dof_ratio = np.nansum(res.residuals**2) / (sigma**2 * np.sum(2 * n - 3))
    assert 0.9 < dof_ratio < 1.1


def test_crb_default_visibility_and_degenerate_points():
    cams = thesis_rig()
    X = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 50.0]])  # the second is above every camera
    crb = triangulation_crb(cams, X, 0.5)
    assert np.isfinite(crb[0]).all() and np.isnan(crb[1]).all()
    # the bound scales with sigma^2
    np.testing.assert_allclose(triangulation_crb(cams, X[:1], 1.0), 4 * triangulation_crb(cams, X[:1], 0.5))


@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 2**32 - 1))
def test_motion_compensated_triangulation_recovers_point(seed):
    rng = np.random.default_rng(seed)
    cams = random_rig(rng, 5)
    X = rng.uniform([-0.8, -0.8, 0.3], [0.8, 0.8, 1.6], (40, 3))
    # each camera captured at its own time: the marker had moved by offsets[p, v] (up to ~5 cm)
    offsets = rng.normal(0, 0.02, (40, 5, 3))
    px = np.stack([cv2_project(c, X + offsets[:, v]) for v, c in enumerate(cams)], axis=1)
    res = triangulate_pixels(cams, px, offsets=offsets)
    ok = res.n_views >= 2
    assert ok.sum() > 10
    assert np.abs(res.points[ok] - X[ok]).max() < 1e-9
    assert np.nanmax(res.residuals[ok]) < 1e-6
    # ignoring the motion leaves centimetre errors and large residuals: the offsets matter
    naive = triangulate_pixels(cams, px)
    assert np.nanmax(naive.residuals[ok]) > 1.0


def test_per_point_translation_in_normalized_triangulation():
    rng = np.random.default_rng(4)
    cams = thesis_rig()
    X = rng.uniform([-1, -1, 0.3], [1, 1, 1.5], (20, 3))
    offs = rng.normal(0, 0.03, (20, 4, 3))
    R = np.stack([c.R for c in cams])
    t = np.stack([c.t for c in cams])
    Xc = np.einsum("vij,pvj->pvi", R, X[:, None, :] + offs) + t
    xn = Xc[..., :2] / Xc[..., 2:]
    t_eff = t + np.einsum("vij,pvj->pvi", R, offs)
    res = triangulate_normalized(xn, R, t_eff)
    assert np.abs(res.points - X).max() < 1e-9


def test_missing_views_outliers_and_shapes():
    cams = thesis_rig()
    X = np.array([[0.1, 0.2, 0.9], [0.3, -0.2, 1.2], [0.0, 0.0, 0.5]])
    px = observe(cams, X)
    px[1, 1:] = np.nan  # seen once: no point
    px[2, 0] += [25.0, -10.0]  # one bad observation shows in its residual
    res = triangulate_pixels(cams, px)
    assert res.n_views.tolist() == [4, 1, 4]
    assert np.isnan(res.points[1]).all() and np.isnan(res.residuals[1]).all()
    assert np.nanargmax(res.residuals[2]) == 0 and res.residuals[2, 0] > 5.0
    empty = triangulate_pixels(cams, np.zeros((0, 4, 2)))
    assert empty.points.shape == (0, 3) and empty.residuals.shape == (0, 4)
    with pytest.raises(ValueError, match="pixels"):
        triangulate_pixels(cams, np.zeros((3, 3, 2)))
    with pytest.raises(ValueError, match="offsets"):
        triangulate_pixels(cams, px, offsets=np.zeros((3, 4, 2)))
    with pytest.raises(ValueError, match="t must"):
        triangulate_normalized(np.zeros((3, 4, 2)), np.stack([np.eye(3)] * 4), np.zeros((4, 2)))


def test_refined_point_is_a_stationary_point_of_the_pixel_reprojection_error():
    """ML check independent of the library's Jacobians: the gradient of the summed squared
    pixel error (OpenCV projection, central differences) vanishes at the returned point."""
    rng = np.random.default_rng(21)
    cams = random_rig(rng, 5)
    X = rng.uniform([-1.0, -1.0, 0.2], [1.0, 1.0, 1.6], (40, 3))
    px = observe(cams, X)
    px = px + rng.normal(0, 0.5, px.shape)
    res = triangulate_pixels(cams, px)
    ok = res.n_views >= 3
    Xh = res.points[ok]
    obs = px[ok]

    def cost(P):
        pred = observe(cams, P)
        d = np.where(np.isfinite(obs), pred - obs, 0.0)
        return np.sum(d**2, axis=(1, 2))

    h = 1e-6
    grad = np.stack([(cost(Xh + h * e) - cost(Xh - h * e)) / (2 * h) for e in np.eye(3)], axis=1)
    # a point 1 um away from the optimum would show |grad| ~ 2 |J|^2 1e-6 ~ 1 px^2/m here
    assert np.abs(grad).max() < 0.05
    # and the library's residuals are the OpenCV pixel residuals at that point
    pred = observe(cams, Xh)
    np.testing.assert_allclose(res.residuals[ok], np.linalg.norm(pred - obs, axis=2), atol=1e-6)
    # pre-undistorted input gives the same answer
    again = triangulate_pixels(CameraRig(cams), px, normalized=CameraRig(cams).undistort(px))
    np.testing.assert_allclose(again.points[ok], res.points[ok], atol=1e-9)


def _pose_fixture():
    from visionpos.sim import load_scenario

    sc = load_scenario("thesis", session="hover", duration=0.1)
    markers = np.array(sc.arena.bodies[0].markers, float)
    R = Rotation.from_euler("zyx", [25, 4, -3], degrees=True).as_matrix()
    p = np.array([0.2, -0.1, 0.8])
    return list(sc.cameras), markers @ R.T + p, p


def test_pose_crb_equals_the_triangulated_bound_when_every_marker_has_two_views():
    """Marker by marker, the views' information is the triangulated point's (triangulation_crb): chained
    through d marker / d pose the two bounds must agree."""
    cams, mw, p = _pose_fixture()
    visible = np.ones((len(mw), len(cams)), bool)
    visible[0, 1] = visible[2, 3] = False
    C_tri = triangulation_crb(cams, mw, 0.2, visible)
    F = np.zeros((6, 6))
    for Ci, x in zip(C_tri, mw):
        r = x - p
        G = np.hstack([np.eye(3), -np.array([[0, -r[2], r[1]], [r[2], 0, -r[0]], [-r[1], r[0], 0]])])
        F += G.T @ np.linalg.inv(Ci) @ G
    np.testing.assert_allclose(pose_crb(cams, mw, p, 0.2, visible), np.linalg.inv(F), rtol=1e-6)


def test_pose_crb_of_one_camera():
    cams, mw, p = _pose_fixture()
    one = np.zeros((len(mw), len(cams)), bool)
    one[:, 0] = True
    C = pose_crb(cams, mw, p, 0.2, one)
    assert np.isfinite(C).all() and np.allclose(C, C.T)
    # four views determine it better than one; noise scales the bound by sigma^2
    assert np.trace(C[:3, :3]) > 10 * np.trace(pose_crb(cams, mw, p, 0.2, np.ones_like(one))[:3, :3])
    np.testing.assert_allclose(pose_crb(cams, mw, p, 0.4, one), 4 * C, rtol=1e-9)
    # the uncertainty is mostly depth along camera 0's axis
    axis = cams[0].R[2]
    assert axis @ C[:3, :3] @ axis > 0.8 * np.trace(C[:3, :3])
    # two markers in one camera, or one marker in two, leave the pose undetermined
    two = np.zeros_like(one)
    two[:2, 0] = True
    assert np.isinf(pose_crb(cams, mw, p, 0.2, two)).all()
    dual = np.zeros_like(one)
    dual[0, :2] = True
    assert np.isinf(pose_crb(cams, mw, p, 0.2, dual)).all()
    with pytest.raises(ValueError, match="shape"):
        pose_crb(cams, mw, p, 0.2, one[:, :2])


def test_pose_crb_bounds_a_monte_carlo_pose_fit():
    """The ML pose from one camera's noisy pixels (scipy least squares): its spread matches the bound."""
    from scipy.optimize import least_squares

    cams, mw, p = _pose_fixture()
    cam = cams[0]
    local = mw - p  # body frame = world-aligned at the true pose
    sigma = 0.2
    C = pose_crb([cam], mw, p, sigma, np.ones((len(mw), 1), bool))
    rng = np.random.default_rng(3)
    truth_px = cam.project(mw)

    def residual(q, obs):
        X = local @ Rotation.from_rotvec(q[3:]).as_matrix().T + p + q[:3]
        return (cam.project(X) - obs).ravel()

    est = np.array([least_squares(residual, np.zeros(6), args=(truth_px + rng.normal(0, sigma, truth_px.shape),),
                                  x_scale=[0.01] * 3 + [0.01] * 3).x for _ in range(300)])
    mse = (est[:, :3] ** 2).sum(1).mean()
    assert 0.75 * np.trace(C[:3, :3]) < mse < 1.35 * np.trace(C[:3, :3])
