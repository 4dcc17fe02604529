"""Station blob detector against the simulator's renderer (known true centres)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from stations.detector import Detector, DetectorConfig, background_level
from visionpos.messages import FLAG_SATURATED, FLAG_TRUNCATED
from visionpos.sim.render import render_blobs

W, H = 320, 240


def centers_grid(n: int, rng: np.random.Generator, margin: float = 20.0, sep: float = 28.0) -> np.ndarray:
    """n sub-pixel centres at least `sep` apart (jittered grid)."""
    nx = int((W - 2 * margin) // sep)
    cells = rng.choice(nx * int((H - 2 * margin) // sep), n, replace=False)
    base = np.stack([margin + (cells % nx) * sep, margin + (cells // nx) * sep], axis=1)
    return base + rng.uniform(0, sep - 8, (n, 2))


def match(blobs: np.ndarray, truth: np.ndarray, tol: float = 1.5) -> np.ndarray:
    """Errors (M, 2) of truth centres that have a detection within tol px."""
    if not len(blobs):
        return np.zeros((0, 2))
    d = np.linalg.norm(blobs[:, None, :2] - truth[None], axis=2)
    j = d.argmin(axis=0)
    ok = d[j, np.arange(len(truth))] < tol
    return blobs[j[ok], :2] - truth[ok]


@pytest.mark.parametrize("diameter", [2.0, 3.0, 5.0, 8.0])
def test_centroid_bias_and_rms_on_rendered_blobs(diameter):
    rng = np.random.default_rng(int(diameter * 10))
    det = Detector()
    errs, n = [], 0
    for _ in range(12):
        c = centers_grid(8, rng)
        img = render_blobs(W, H, c, np.full(8, diameter), np.full(8, 200.0), rng, read_noise_dn=1.5)
        blobs, flags = det.detect(img)
        assert flags == 0
        e = match(blobs, c)
        errs.append(e)
        n += len(c)
    e = np.concatenate(errs)
    assert len(e) == n, "every blob is found"
    assert np.abs(e.mean(axis=0)).max() <= 0.02
    assert np.sqrt((e**2).mean()) <= 0.05


def test_uneven_background_does_not_bias():
    """A lighting gradient (20 DN across the frame, 10 down) over a high floor."""
    rng = np.random.default_rng(7)
    det = Detector()
    errs = []
    for _ in range(10):
        c = centers_grid(8, rng)
        img = render_blobs(W, H, c, np.full(8, 4.0), np.full(8, 150.0), rng, background=30.0, gradient=(20.0, 10.0))
        errs.append(match(det.detect(img)[0], c))
    e = np.concatenate(errs)
    assert len(e) == 80
    assert np.abs(e.mean(axis=0)).max() <= 0.02
    assert np.sqrt((e**2).mean()) <= 0.05


def test_blob_area_and_peak_reported():
    c = np.array([[100.3, 80.7]])
    img = render_blobs(W, H, c, [6.0], [180.0], None, background=10.0)
    blobs, _ = Detector(DetectorConfig(threshold=60)).detect(img)
    assert blobs.shape == (1, 4) and blobs.dtype == np.float32
    # independent reference: pixel count above threshold and max minus background
    assert blobs[0, 2] == pytest.approx((img > 60).sum(), abs=1)
    assert blobs[0, 3] == pytest.approx(img.max() - 10.0, abs=1.5)


def test_empty_and_noise_only_frames_give_no_blobs():
    rng = np.random.default_rng(1)
    det = Detector()
    assert det.detect(np.zeros((H, W), np.uint8))[0].shape == (0, 4)
    noise = render_blobs(W, H, np.zeros((0, 2)), [], [], rng, background=12.0, read_noise_dn=3.0)
    for _ in range(5):
        assert len(det.detect(noise)[0]) == 0


def test_sunlight_is_capped_and_flagged_keeping_the_brightest():
    rng = np.random.default_rng(2)
    xs, ys = np.meshgrid(np.arange(8, W - 8, 12.0), np.arange(8, H - 8, 12.0))
    c = np.stack([xs.ravel(), ys.ravel()], axis=1) + rng.uniform(-1, 1, (xs.size, 2))
    peaks = np.full(len(c), 60.0)
    bright = rng.choice(len(c), 5, replace=False)
    peaks[bright] = 220.0
    img = render_blobs(W, H, c, np.full(len(c), 3.0), peaks, rng)
    det = Detector(DetectorConfig(max_blobs=10))
    blobs, flags = det.detect(img)
    assert len(c) > 400 and len(blobs) == 10
    assert flags & FLAG_TRUNCATED
    assert det.last_candidates > 100
    got = match(blobs[:5], c[bright])
    assert len(got) == 5, "the five bright markers come first"


def test_roundness_area_filters_and_roi_mask():
    img = np.full((H, W), 8, np.uint8)
    cv2.line(img, (20, 200), (120, 180), 200, 2)  # a reflection streak
    img = np.maximum(img, render_blobs(W, H, [[200.2, 60.6], [260.5, 150.1]], [5.0, 5.0], [200.0, 200.0], None,
                                       background=8.0))
    blobs, _ = Detector(DetectorConfig(threshold=50)).detect(img)
    assert len(blobs) == 2 and np.all(blobs[:, 0] > 150), "streak rejected as not round"
    blobs, _ = Detector(DetectorConfig(threshold=50, min_roundness=0.0, max_area=100)).detect(img)
    assert len(blobs) == 2, "streak rejected by area"
    mask = np.full((H, W), 255, np.uint8)
    mask[:, 230:] = 0
    blobs, _ = Detector(DetectorConfig(threshold=50), mask=mask).detect(img)
    assert len(blobs) == 1 and abs(blobs[0, 0] - 200.2) < 0.1


def test_static_background_subtraction_removes_fixed_reflections():
    rng = np.random.default_rng(3)
    static = render_blobs(W, H, [[50.0, 50.0], [150.0, 120.0]], [6.0, 6.0], [220.0, 220.0], None, background=10.0)
    bg = Detector.learn_background([static] * 3)
    marker = np.array([[250.4, 190.6]])
    frame = np.maximum(static, render_blobs(W, H, marker, [4.0], [200.0], rng, background=10.0))
    assert len(Detector().detect(frame)[0]) == 3
    blobs, _ = Detector(background=bg).detect(frame)
    assert len(blobs) == 1
    assert np.abs(blobs[0, :2] - marker[0]).max() < 0.1


def test_saturation_flag():
    img = render_blobs(W, H, [[100.0, 100.0], [200.0, 100.0]], [8.0, 8.0], [900.0, 900.0], None)
    _, flags = Detector(DetectorConfig(saturated_pixels=20)).detect(img)
    assert flags & FLAG_SATURATED


def test_blobs_at_the_image_border():
    rng = np.random.default_rng(4)
    c = np.array([[2.3, 120.4], [160.2, 1.7], [317.6, 238.2]])
    img = render_blobs(W, H, c, [3.0] * 3, [200.0] * 3, rng)
    blobs, _ = Detector().detect(img)
    e = match(blobs, c, tol=2.0)
    assert len(e) == 3
    assert np.abs(e).max() < 0.6  # cut by the border: found, roughly placed, no crash


def test_background_level_estimate():
    rng = np.random.default_rng(5)
    img = np.clip(np.rint(rng.normal(20.0, 3.0, (H, W))), 0, 255).astype(np.uint8)
    med, sigma = background_level(img, step=2)
    assert med == pytest.approx(20.0, abs=1.0)
    assert sigma == pytest.approx(3.0, rel=0.25)


def test_bad_images_fail_clearly():
    det = Detector()
    with pytest.raises(ValueError, match="uint8 grey image"):
        det.detect(np.zeros((H, W, 3), np.uint8))
    with pytest.raises(ValueError, match="uint8 grey image"):
        det.detect(np.zeros((H, W), np.float32))
    with pytest.raises(ValueError, match="mask is"):
        Detector(mask=np.ones((10, 10), np.uint8)).detect(np.zeros((H, W), np.uint8))


def test_close_markers_do_not_pull_each_other():
    """Two 4 px markers 7 px apart (a drone's markers seen from afar)."""
    rng = np.random.default_rng(8)
    pull = []
    for _ in range(30):
        a = rng.uniform(40, 200, 2)
        ang = rng.uniform(0, 2 * np.pi)
        u = np.array([np.cos(ang), np.sin(ang)])
        c = np.array([a, a + 7.0 * u])
        blobs, _ = Detector().detect(render_blobs(W, H, c, [4.0, 4.0], [200.0, 200.0], rng))
        assert len(blobs) == 2
        d = np.linalg.norm(blobs[:, None, :2] - c[None], axis=2)
        e = blobs[d.argmin(axis=0), :2] - c
        pull += [e[0] @ u, -(e[1] @ u)]  # error component towards the other marker
    assert abs(np.mean(pull)) < 0.04
    assert np.sqrt(np.mean(np.square(pull))) < 0.06


def test_compiled_centroids_equal_the_numpy_reference(monkeypatch):
    """The compiled per-blob loop (used where numba is installed) gives the vectorised numpy
    reference's blobs and flags: windows cut by the border, big blobs, close pairs, lost ones."""
    import stations.detector as D
    from visionpos.jit import COMPILED

    if not COMPILED:
        pytest.skip("numba is not installed: only the numpy reference runs")
    rng = np.random.default_rng(11)
    n_blobs = 0
    for trial in range(120):
        n = int(rng.integers(1, 12))
        edge = trial % 2 == 1
        c = (
            rng.uniform(1.0, [W - 2.0, H - 2.0], (n, 2))
            if edge
            else centers_grid(n, rng, sep=14.0 if trial % 3 else 28.0)
        )
        img = render_blobs(W, H, c, rng.uniform(1.5, 24.0, n), rng.uniform(40, 300, n), rng, read_noise_dn=3.0)
        out = []
        for compiled in (True, False):
            monkeypatch.setattr(D, "COMPILED", compiled)
            out.append(Detector(DetectorConfig()).detect(img))
        (a, fa), (b, fb) = out
        assert fa == fb and a.shape == b.shape
        assert np.isfinite(a).all()
        np.testing.assert_allclose(a, b, rtol=1e-6, atol=1e-4)
        n_blobs += len(a)
    assert n_blobs > 400
