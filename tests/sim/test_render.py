"""IR blob renderer: exact sub-pixel centroids, blob size, sensor noise model."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import integrate

from visionpos.camera.model import Camera, CameraModel, look_at_rotation
from visionpos.sim.render import blurred_disc_profile, render_blobs, render_camera_frame


def _centroid(img: np.ndarray, background: float = 0.0) -> np.ndarray:
    f = img.astype(np.float64) - background
    ys, xs = np.mgrid[: f.shape[0], : f.shape[1]]
    return np.array([(f * xs).sum(), (f * ys).sum()]) / f.sum()


def _second_moment(img: np.ndarray, c: np.ndarray) -> float:
    f = img.astype(np.float64)
    ys, xs = np.mgrid[: f.shape[0], : f.shape[1]]
    return float((f * ((xs - c[0]) ** 2 + (ys - c[1]) ** 2)).sum() / f.sum() / 2)  # per axis


def test_profile_matches_direct_integration():
    # disc (R) * Gaussian (s) at distance rho, by brute-force 2-D quadrature
    R, s = 2.5, 0.7
    for rho in (0.0, 1.0, 2.5, 3.3):
        f = lambda y, x: np.exp(-((x - rho) ** 2 + y**2) / (2 * s * s)) / (2 * np.pi * s * s)  # noqa: E731
        val, _ = integrate.dblquad(
            f, -R, R, lambda x: -np.sqrt(R * R - x * x), lambda x: np.sqrt(R * R - x * x), epsabs=1e-10
        )
        assert blurred_disc_profile(np.array([rho]), R, s)[0] == pytest.approx(val, abs=1e-7)


@pytest.mark.parametrize("diameter", [3.0, 5.0, 8.0, 14.0])
def test_noiseless_blob_centroid_is_the_true_centre(diameter):
    rng = np.random.default_rng(int(diameter * 10))
    worst_float = worst_u8 = 0.0
    for _ in range(12):
        c = rng.uniform(30.0, 34.0, 2)
        f = render_blobs(64, 64, c[None], [diameter], [200.0], None, background=0.0, quantize=False)
        worst_float = max(worst_float, np.abs(_centroid(f) - c).max())
        u8 = render_blobs(64, 64, c[None], [diameter], [200.0], None, background=0.0)
        worst_u8 = max(worst_u8, np.abs(_centroid(u8) - c).max())
    assert worst_float < 1e-4
    if diameter >= 5:  # 8-bit rounding of a small blob moves the centroid a few thousandths
        assert worst_u8 < 0.005


def test_blob_size_follows_diameter():
    # second moment of a blurred, pixel-integrated disc: R^2/4 + sigma^2 + 1/12 per axis
    for d in (4.0, 8.0, 16.0):
        c = np.array([40.3, 39.8])
        f = render_blobs(80, 80, c[None], [d], [100.0], None, background=0.0, blur_px=0.6, quantize=False)
        var = _second_moment(f, c)
        assert 2 * np.sqrt(var - 0.36 - 1 / 12) * 2 == pytest.approx(d, rel=0.01)
        assert f.sum() == pytest.approx(100.0 * np.pi * d * d / 4, rel=1e-3)  # energy = peak x disc area


def _pinhole_cam() -> Camera:
    m = CameraModel("pinhole", 640, 480, 600.0, 600.0, 319.5, 239.5)
    R = look_at_rotation(np.array([0.0, 0.0, 0.0]), np.array([0.0, 0.0, 1.0]), np.array([0.0, -1.0, 0.0]))
    return Camera(1, "c", m, R, -R @ np.zeros(3))


def test_camera_frame_blob_scales_with_marker_diameter_and_distance():
    cam = _pinhole_cam()
    sizes = {}
    for D, Z in ((0.014, 1.5), (0.014, 3.0), (0.028, 3.0)):
        p = np.array([[0.02, -0.01, Z]])
        img, centres = render_camera_frame(cam, p, D, None, peak_at_1m=200 * Z * Z, background=0.0, quantize=False)
        assert np.allclose(centres, cam.project(p))
        var = _second_moment(img, centres[0])
        sizes[(D, Z)] = 2 * 2 * np.sqrt(var - 0.36 - 1 / 12)
        assert sizes[(D, Z)] == pytest.approx(600.0 * D / Z, rel=0.02)
        assert np.abs(_centroid(img) - centres[0]).max() < 1e-3
    assert sizes[(0.014, 1.5)] / sizes[(0.014, 3.0)] == pytest.approx(2.0, rel=0.02)
    assert sizes[(0.028, 3.0)] / sizes[(0.014, 3.0)] == pytest.approx(2.0, rel=0.02)


def test_out_of_view_markers_have_no_centre_and_no_light():
    cam = _pinhole_cam()
    p = np.array([[0.0, 0.0, 2.0], [5.0, 0.0, 1.0], [0.0, 0.0, -2.0]])
    img, centres = render_camera_frame(cam, p, 0.014, None, background=0.0)
    assert np.isfinite(centres[0]).all() and np.isnan(centres[1:]).all()
    # only the one visible marker lit anything: all light is within a few px of it
    ys, xs = np.nonzero(img)
    assert np.hypot(xs - centres[0, 0], ys - centres[0, 1]).max() < 8


def test_sensor_noise_background_gradient_and_saturation():
    for model in ("gaussian", "poisson"):
        rng = np.random.default_rng(0)
        img = render_blobs(400, 300, np.array([[200.0, 150.0]]), [20.0], [2000.0], rng, noise_model=model,
                           background=20.0, electrons_per_dn=4.0, read_noise_dn=1.5)  # fmt: skip
        assert img.dtype == np.uint8 and img.shape == (300, 400)
        bg = img[:, :100].astype(float)
        assert bg.mean() == pytest.approx(20.0, abs=0.1)
        assert bg.std() == pytest.approx(np.sqrt(20.0 / 4.0 + 1.5**2 + 1 / 12), rel=0.05)
        assert (img[145:156, 195:206] == 255).all()  # a bright marker saturates flat
    g = render_blobs(400, 300, np.zeros((0, 2)), [], [], None, background=10.0, gradient=(40.0, 0.0), quantize=False)
    assert g[:, -1].mean() - g[:, 0].mean() == pytest.approx(40.0 * 399 / 400)
    # determinism from the generator
    a = render_blobs(50, 40, np.array([[20.0, 20.0]]), [5.0], [150.0], np.random.default_rng(3))
    b = render_blobs(50, 40, np.array([[20.0, 20.0]]), [5.0], [150.0], np.random.default_rng(3))
    assert np.array_equal(a, b)


def test_bad_input_is_rejected():
    with pytest.raises(ValueError, match="diameters"):
        render_blobs(10, 10, np.array([[5.0, 5.0]]), [-1.0], [100.0])
    with pytest.raises(ValueError, match="image size"):
        render_blobs(0, 10, np.zeros((0, 2)), [], [])


def test_sim_frame_image_has_its_blobs_where_the_truth_says():
    from visionpos.sim import load_scenario, simulate
    from visionpos.sim.render import render_sim_frame

    sc = load_scenario("thesis", duration=0.05, centroid_noise_px=0.0)
    res = simulate(sc)
    f, tr = next((f, tr) for f, tr in zip(res.frames, res.frame_truth) if len(f.blobs) >= 4)
    img = render_sim_frame(sc, f, tr, None, background=0.0, quantize=False).astype(float)
    assert img.shape == (640, 960)
    for j in np.nonzero(~tr.merged)[0]:
        x, y = tr.true_xy[j]
        r = int(np.ceil(np.sqrt(f.blobs[j, 2] / np.pi) + 4))
        x0, y0 = int(round(x)) - r, int(round(y)) - r
        win = img[max(y0, 0) : y0 + 2 * r + 1, max(x0, 0) : x0 + 2 * r + 1]
        ys, xs = np.mgrid[: win.shape[0], : win.shape[1]]
        c = np.array([(win * xs).sum(), (win * ys).sum()]) / win.sum() + [max(x0, 0), max(y0, 0)]
        assert np.abs(c - tr.true_xy[j]).max() < 0.01
