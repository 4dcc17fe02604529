"""Camera models: round trips, agreement with OpenCV, capture-mode rescaling, YAML, errors."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from visionpos.camera.model import Camera, CameraModel, CameraModelError, look_at_rotation

# Thesis Table 4.1, V2 NoIR camera 1 at 960x640 (Kannala-Brandt)
V2_NOIR = CameraModel("fisheye", 960, 640, 720.313, 719.521, 481.014, 360.991, [0.396, 0.634, -2.417, 2.111])
# the other three V2 cameras of Table 4.1 (stronger higher-order terms)
V2_NOIR_OTHERS = [
    CameraModel("fisheye", 960, 640, 768.113, 767.935, 472.596, 350.978, [0.369, 1.501, -7.941, 11.917]),
    CameraModel("fisheye", 960, 640, 728.237, 729.419, 459.854, 351.59, [0.276, 2.095, -9.980, 14.192]),
    CameraModel("fisheye", 960, 640, 750.149, 748.903, 492.144, 350.213, [0.401, 1.160, -7.103, 11.415]),
]
# a wide pinhole with strong barrel + tangential distortion (about 90 x 56 deg)
STRONG_PINHOLE = CameraModel("pinhole", 1280, 800, 800.0, 810.0, 650.0, 390.0, [-0.32, 0.12, 0.0015, -0.001, -0.015])
# rational (8-coefficient) pinhole model
RATIONAL_PINHOLE = CameraModel(
    "pinhole", 1280, 800, 800.0, 810.0, 650.0, 390.0, [0.25, -0.1, 0.001, 0.002, 0.01, 0.1, 0.02, 0.001]
)
ALL_MODELS = [V2_NOIR, *V2_NOIR_OTHERS, STRONG_PINHOLE, RATIONAL_PINHOLE]


def _pixel_grid(m: CameraModel, nx: int = 97, ny: int = 65) -> np.ndarray:
    """(N, 2) pixels covering the whole sensor, edges included."""
    u, v = np.meshgrid(np.linspace(-0.5, m.width - 0.5, nx), np.linspace(-0.5, m.height - 0.5, ny))
    return np.column_stack([u.ravel(), v.ravel()])


@pytest.mark.parametrize("m", ALL_MODELS, ids=lambda m: f"{m.kind}-{m.dist[:2]}")
def test_undistort_then_project_round_trip_across_image(m):
    px = _pixel_grid(m)
    xn = m.undistort(px)
    assert np.isfinite(xn).all(), "every pixel of these sensors lies inside the model's field of view"
    err = np.linalg.norm(m.distort(xn) - px, axis=1)
    assert err.max() < 1e-6


@pytest.mark.parametrize("m", ALL_MODELS, ids=lambda m: f"{m.kind}-{m.dist[:2]}")
def test_project_then_undistort_round_trip_up_to_fov(m):
    # rays spread over the model's whole valid cone (beyond the sensor for the fisheye)
    rng = np.random.default_rng(3)
    theta = rng.uniform(0, m.max_theta * 0.999, 4000)
    phi = rng.uniform(-np.pi, np.pi, 4000)
    theta = np.concatenate([theta, np.linspace(0, m.max_theta * 0.999, 200)])
    phi = np.concatenate([phi, np.full(200, 0.7)])
    depth = rng.uniform(0.2, 20.0, len(theta))
    pc = np.column_stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)]) * depth[:, None]
    px = m.project_camera(pc)
    xn = m.undistort(px)
    # compare in pixels: the normalised error scaled by the local pixel density is
    # what undistort->project would show; compare both ways
    err_px = np.linalg.norm(m.distort(xn) - px, axis=1)
    assert err_px.max() < 1e-6
    ray_err = np.linalg.norm(xn - pc[:, :2] / pc[:, 2:], axis=1) / (1 + np.linalg.norm(xn, axis=1) ** 2)
    assert (ray_err * m.fx).max() < 1e-6


def test_undistort_outside_model_domain_is_nan_not_wrong():
    # this lens folds over (r(theta) stops increasing) well inside its 1280x800 sensor:
    # corner pixels have no valid ray and must come back NaN
    m = CameraModel("pinhole", 1280, 800, 800.0, 810.0, 650.0, 390.0, [-0.38, 0.18, 0.002, -0.0015, -0.04])
    xn = m.undistort(_pixel_grid(m))
    assert np.isnan(xn).any()
    ok = np.isfinite(xn).all(axis=1)
    assert np.linalg.norm(m.distort(xn[ok]) - _pixel_grid(m)[ok], axis=1).max() < 1e-6


def _random_world_points_in_view(m: CameraModel, R, t, n, rng, max_theta=None):
    theta = rng.uniform(0, max_theta if max_theta is not None else 0.9 * m.max_theta, n)
    phi = rng.uniform(-np.pi, np.pi, n)
    depth = rng.uniform(0.5, 8.0, n)
    pc = np.column_stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)]) * depth[:, None]
    return (pc - t) @ R  # world points: R^T (pc - t)


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**32 - 1))
def test_pinhole_matches_cv2_project_points(seed):
    rng = np.random.default_rng(seed)
    dist = np.array([-0.32, 0.12, 0.0015, -0.001, -0.015]) * rng.uniform(0.2, 1.0)
    if rng.random() < 0.5:
        dist = np.concatenate([dist, rng.uniform(-0.05, 0.05, 3)])
    m = CameraModel("pinhole", 1280, 800, *rng.uniform(600, 900, 2), *rng.uniform([600, 360], [680, 420]), dist)
    rv = Rotation.random(random_state=rng.integers(1 << 31)).as_rotvec()
    R = Rotation.from_rotvec(rv).as_matrix()
    t = rng.normal(0, 2.0, 3)
    X = _random_world_points_in_view(m, R, t, 200, rng, max_theta=np.radians(45))
    ours = m.project(X, R, t)
    ref, _ = cv2.projectPoints(X.reshape(-1, 1, 3), rv, t, m.K, m.opencv_dist)
    assert np.abs(ours - ref.reshape(-1, 2)).max() < 1e-6


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), which=st.integers(0, 3))
def test_fisheye_matches_cv2_fisheye_project_points(seed, which):
    rng = np.random.default_rng(seed)
    m = [V2_NOIR, *V2_NOIR_OTHERS][which]
    rv = Rotation.random(random_state=rng.integers(1 << 31)).as_rotvec()
    R = Rotation.from_rotvec(rv).as_matrix()
    t = rng.normal(0, 2.0, 3)
    X = _random_world_points_in_view(m, R, t, 200, rng)
    ours = m.project(X, R, t)
    ref, _ = cv2.fisheye.projectPoints(X.reshape(-1, 1, 3), rv.reshape(3, 1), t.reshape(3, 1), m.K, m.opencv_dist)
    assert np.abs(ours - ref.reshape(-1, 2)).max() < 1e-6


def test_undistort_matches_cv2_undistort_points():
    for m in (STRONG_PINHOLE, V2_NOIR):
        # inner part of the sensor where cv2's fixed-iteration solver has converged
        px = _pixel_grid(m, 21, 15)
        px = px[np.linalg.norm((px - [m.cx, m.cy]) / [m.width, m.height], axis=1) < 0.3]
        if m.kind == "pinhole":
            ref = cv2.undistortPoints(
                px.reshape(-1, 1, 2),
                m.K,
                m.opencv_dist,
                criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-14),
            )
        else:
            ref = cv2.fisheye.undistortPoints(
                px.reshape(-1, 1, 2),
                m.K,
                m.opencv_dist,
                criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-14),
            )
        assert np.abs(m.undistort(px) - ref.reshape(-1, 2)).max() < 1e-7


def _render_blobs(width, height, centres, sigma):
    """Float image of Gaussian blobs sampled at integer pixel centres (OpenCV convention)."""
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    img = np.zeros((height, width))
    for cu, cv in centres:
        img += np.exp(-((u - cu) ** 2 + (v - cv) ** 2) / (2 * sigma**2))
    return img


def _centroids(img, approx, radius):
    out = []
    v, u = np.mgrid[0 : img.shape[0], 0 : img.shape[1]].astype(np.float64)
    for au, av in approx:
        w = img * (((u - au) ** 2 + (v - av) ** 2) < radius**2)
        out.append([(w * u).sum() / w.sum(), (w * v).sum() / w.sum()])
    return np.array(out)


@pytest.mark.parametrize(
    "W, H, V",
    [(480, 320, 0), (400, 320, 0), (480, 300, 20), (320, 240, 0), (300, 200, 40), (720, 480, 0)],
)
def test_rescale_crop_matches_resized_image(W, H, V):
    """Eq. 2.7: project through the rescaled model == find the blob in the resized, cropped image.

    The full image is resized to height H + V (width by the same factor), then
    cropped to W x H, removing half the excess from each side."""
    m = V2_NOIR
    scaled_h = H + V
    s = scaled_h / m.height
    scaled_w = int(round(m.width * s))
    m2 = m.rescale(W, H, crop=(scaled_w - W, V))
    rng = np.random.default_rng(7)
    pc = np.column_stack([rng.uniform(-0.35, 0.35, 12), rng.uniform(-0.25, 0.25, 12), np.ones(12)])
    full = m.project_camera(pc)
    img = _render_blobs(m.width, m.height, full, sigma=6.0)
    small = cv2.resize(img, (scaled_w, scaled_h), interpolation=cv2.INTER_AREA)
    x0 = (scaled_w - W) // 2
    y0 = int(V) // 2
    cropped = small[y0 : y0 + H, x0 : x0 + W]
    expect = m2.project_camera(pc)
    found = _centroids(cropped, expect, radius=6.0 * s * 4)
    assert m2.width == W and m2.height == H
    assert np.abs(found - expect).max() < 0.02


def test_rescale_refuses_aspect_change():
    with pytest.raises(CameraModelError, match="aspect"):
        V2_NOIR.rescale(640, 640)


def test_rescale_full_sensor_mode_is_identity_and_binning_halves():
    assert V2_NOIR.rescale(960, 640) == V2_NOIR
    assert V2_NOIR.rescale(480, 320) != V2_NOIR
    assert len({V2_NOIR, V2_NOIR.rescale(960, 640)}) == 1  # hashable by value
    b = V2_NOIR.rescale(480, 320)
    assert b.fx == pytest.approx(V2_NOIR.fx / 2)
    # pixel-centre convention: full-res pixel centres 0 and 1 average to binned pixel 0
    assert b.cx == pytest.approx((V2_NOIR.cx - 0.5) / 2)


@pytest.mark.parametrize("m", ALL_MODELS, ids=lambda m: f"{m.kind}-{m.dist[:2]}")
def test_model_yaml_round_trip(m):
    text = yaml.safe_dump(m.to_dict())
    back = CameraModel.from_dict(yaml.safe_load(text))
    assert back.kind == m.kind and (back.width, back.height) == (m.width, m.height)
    assert (back.fx, back.fy, back.cx, back.cy) == (m.fx, m.fy, m.cx, m.cy)
    assert np.array_equal(back.dist, m.dist)


def test_camera_yaml_round_trip_pose():
    rng = np.random.default_rng(1)
    C = np.array([2.12, -2.41, 2.6])
    R = look_at_rotation(C, np.zeros(3))
    cam = Camera(3, "corner", V2_NOIR, R, -R @ C, fps=90.0)
    back = Camera.from_dict(yaml.safe_load(yaml.safe_dump(cam.to_dict())))
    assert back.id == 3 and back.name == "corner" and back.fps == 90.0
    assert np.abs(back.R - R).max() < 1e-12 and np.abs(back.center - C).max() < 1e-12
    X = rng.uniform(-1, 1, (20, 3))
    assert np.abs(back.project(X) - cam.project(X)).max() < 1e-9


def test_look_at_points_the_optical_axis_at_the_target(look_at_camera):
    C = np.array([-2.12, 2.41, 2.6])
    cam = look_at_camera(C, [0.0, 0.0, 0.5], V2_NOIR, camera_id=0)
    R = cam.R
    uv = cam.project(np.array([[0.0, 0.0, 0.5]]))[0]
    assert np.allclose(uv, [V2_NOIR.cx, V2_NOIR.cy], atol=1e-9)
    # image 'up' (-y of the camera) points towards world +z
    assert (R.T @ np.array([0.0, -1.0, 0.0]))[2] > 0
    assert np.isclose(np.linalg.det(R), 1.0)


def test_points_behind_camera_are_nan_and_not_visible():
    pc = np.array([[0.1, 0.1, -1.0], [0.0, 0.0, 2.0]])
    uv = V2_NOIR.project_camera(pc)
    assert np.isnan(uv[0]).all() and np.isfinite(uv[1]).all()
    assert V2_NOIR.visible(pc).tolist() == [False, True]


def test_project_jacobian_matches_cv2_jacobian():
    rng = np.random.default_rng(5)
    rv = np.zeros(3)
    t = np.zeros(3)
    pc = np.column_stack([rng.uniform(-0.5, 0.5, (30, 2)), rng.uniform(1, 4, 30)])
    J = V2_NOIR.project_jacobian(pc)
    # cv2.fisheye columns: f(2) c(2) k(4) rvec(3) tvec(3) skew(1); d pixel / d tvec with
    # R = I is d pixel / d camera-frame point
    _, jac = cv2.fisheye.projectPoints(pc.reshape(-1, 1, 3), rv.reshape(3, 1), t.reshape(3, 1), V2_NOIR.K, V2_NOIR.dist)
    Jcv = jac[:, 11:14].reshape(-1, 2, 3)
    assert np.abs(J - Jcv).max() < 1e-6 * np.abs(Jcv).max()
    # the pinhole model against central differences of OpenCV's projection
    h = 1e-7
    fd = np.stack([(cv2.projectPoints(pc + h * e, rv, t, STRONG_PINHOLE.K, STRONG_PINHOLE.dist)[0]
                    - cv2.projectPoints(pc - h * e, rv, t, STRONG_PINHOLE.K, STRONG_PINHOLE.dist)[0]).reshape(-1, 2)
                   / (2 * h) for e in np.eye(3)], axis=2)
    assert np.abs(STRONG_PINHOLE.project_jacobian(pc) - fd).max() < 1e-5 * np.abs(fd).max()
    assert np.isnan(V2_NOIR.project_jacobian([[0.1, 0.2, -1.0]])).all()


@pytest.mark.parametrize(
    "d, msg",
    [
        ({"model": "fishy", "width": 960, "height": 640, "fx": 1, "fy": 1, "cx": 0, "cy": 0}, "unknown"),
        (
            {"model": "pinhole", "width": 960, "height": 640, "fx": 1, "fy": 1, "cx": 0, "cy": 0, "dist": [1, 2, 3]},
            "coefficients",
        ),
        (
            {
                "model": "fisheye", "width": 960, "height": 640, "fx": 1, "fy": 1, "cx": 0, "cy": 0,
                "dist": [1, 2, 3, 4, 5],
            },
            "fisheye dist",
        ),
        ({"model": "pinhole", "width": 960, "height": 640, "fx": -700, "fy": 700, "cx": 0, "cy": 0}, "focal"),
        ({"model": "pinhole", "width": 0, "height": 640, "fx": 700, "fy": 700, "cx": 0, "cy": 0}, "image size"),
        (
            {"model": "pinhole", "width": 960, "height": 640, "fx": 700, "fy": 700, "cx": float("nan"), "cy": 0},
            "principal point",
        ),
        (
            {
                "model": "pinhole", "width": 960, "height": 640, "fx": 700, "fy": 700, "cx": 0, "cy": 0,
                "dist": [0, float("inf"), 0, 0],
            },
            "finite",
        ),
        ({"model": "pinhole", "width": 960, "height": 640, "fx": "seven", "fy": 700, "cx": 0, "cy": 0}, "numbers"),
        ({"model": "pinhole", "width": 960, "height": 640, "fy": 700, "cx": 0, "cy": 0}, "fx"),
        ([1, 2, 3], "mapping"),
    ],
)
def test_bad_intrinsics_fail_with_clear_message(d, msg):
    with pytest.raises(CameraModelError, match=msg) as e:
        CameraModel.from_dict(d, where="arena.yaml:cameras[2]")
    assert "arena.yaml:cameras[2]" in str(e.value)


def test_bad_pose_fails_with_clear_message():
    base = V2_NOIR.to_dict() | {"id": 1}
    with pytest.raises(CameraModelError, match="pose"):
        Camera.from_dict(base, "cam1")
    with pytest.raises(CameraModelError, match="quaternion"):
        Camera.from_dict(base | {"pose": {"position": [0, 0, 1], "quaternion_xyzw": [0, 0, 0, 0]}}, "cam1")
    with pytest.raises(CameraModelError, match="coincides"):
        Camera.from_dict(base | {"pose": {"position": [0, 0, 1], "look_at": [0, 0, 1]}}, "cam1")
    with pytest.raises(CameraModelError, match="id"):
        Camera.from_dict(V2_NOIR.to_dict() | {"pose": {"position": [0, 0, 1], "look_at": [0, 0, 0]}}, "cam1")
