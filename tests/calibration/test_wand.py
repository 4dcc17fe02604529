"""Wand labelling, time alignment, pairwise init and bundle adjustment against synthetic truth."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from tests.support.calibration import ring_cameras, wand_frames
from visionpos.calibration.pairwise import initial_poses, pair_pose, undistort_wand
from visionpos.calibration.wand import (
    CalibrationError,
    WandSpec,
    collect_wand,
    interpolate_track,
    label_camera,
    label_triples,
    nearest_track,
    static_blob_mask,
)
from visionpos.calibration.wand_solve import calibrate_wand, compare_cameras
from visionpos.messages import BlobFrame

SPEC = WandSpec(0.054, 0.103)


def _project_wand(cam, A, u):
    pts = A[:, None, :] + SPEC.offsets[None, :, None] * u[:, None, :]
    return cam.project(pts.reshape(-1, 3)).reshape(-1, 3, 2)


def test_label_triples_orders_a_b_c_under_perspective_and_shuffling():
    cam = ring_cameras(1)[0]
    rng = np.random.default_rng(3)
    A = rng.uniform([-0.5, -0.5, 0.6], [0.5, 0.5, 1.4], (200, 3))
    u = rng.normal(size=(200, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    pix = _project_wand(cam, A, u)
    xn = cam.model.undistort(pix.reshape(-1, 2)).reshape(-1, 3, 2)
    perm = np.array([rng.permutation(3) for _ in range(200)])
    shuffled = np.take_along_axis(xn, perm[:, :, None], axis=1)
    lab, ok = label_triples(shuffled, SPEC, tol=1e-3, min_length=8 / 720)
    # a wand seen nearly end-on is rejected, everything else must be labelled exactly
    assert ok.mean() > 0.8
    np.testing.assert_allclose(lab[ok], xn[ok], atol=1e-12)


def test_label_triples_rejects_bent_and_symmetric_triples():
    base = np.array([[0.0, 0.0], [0.034, 0.0], [0.1, 0.0]])
    bent = base.copy()
    bent[1, 1] = 0.01  # 10 % of the length off the line
    middle = np.array([[0.0, 0.0], [0.05, 0.0], [0.1, 0.0]])  # 1:1, A and C cannot be told apart
    lab, ok = label_triples(np.stack([base, bent, middle]), SPEC, tol=0.002)
    assert ok.tolist() == [True, False, False]
    np.testing.assert_allclose(lab[0], base)


def test_label_camera_skips_led_rings_and_resolves_a_glint():
    cam = ring_cameras(1)[0]
    rng = np.random.default_rng(0)
    A = np.column_stack([np.linspace(-0.4, 0.4, 300), np.zeros(300), np.full(300, 1.0)])
    u = np.tile([[0.0, 0.6, 0.8]], (300, 1))
    pix = _project_wand(cam, A, u)
    rings = np.array([[100.0, 80.0], [850.0, 560.0]])  # other cameras' LED rings: always there
    frames = []
    for k in range(300):
        xy = np.vstack([pix[k][rng.permutation(3)], rings])
        if k % 10 == 0:  # a one-frame glint far from the wand
            xy = np.vstack([xy, [[400.0, 600.0]]])
        blobs = np.column_stack([xy, np.ones((len(xy), 2))]).astype(np.float32)
        frames.append(BlobFrame(cam.id, k, k * 10_000_000, blobs))
    t, lab, st = label_camera(frames, cam, SPEC)
    assert st.static_blobs == 600
    assert st.labelled == 300
    np.testing.assert_allclose(lab, pix, atol=1e-3)  # float32 blobs
    mask = static_blob_mask([f.blobs[:, :2] for f in frames])
    assert all(m[-2:].all() if len(m) == 5 else m[-3:-1].all() for m in mask)


def test_interpolate_track_linear_motion_and_gaps():
    times = np.array([0, 10, 20, 30, 60, 70], dtype=np.int64) * 1_000_000
    px = (times[:, None, None] / 1e6) * np.ones((1, 3, 2))
    grid = np.array([5, 20, 25, 45, 65, 80], dtype=np.int64) * 1_000_000
    out = interpolate_track(times, px, grid, max_gap_ns=15_000_000)
    np.testing.assert_allclose(out[[0, 1, 2, 4], 0, 0], [5, 20, 25, 65])
    assert np.isnan(out[3]).all()  # 30 -> 60 ms gap is too long
    assert np.isnan(out[5]).all()  # after the last frame
    near = nearest_track(times, px, grid, max_skew_ns=5_000_000)
    np.testing.assert_allclose(near[[0, 1, 4], 0, 0], [10, 20, 70])  # ties go to the later frame
    assert np.isnan(near[3]).all() and np.isnan(near[5]).all()


@pytest.mark.parametrize("seed", [4, 5])
def test_pair_pose_recovers_relative_pose_up_to_the_noise(seed):
    from visionpos.calibration.bundle import bundle_adjust
    from visionpos.calibration.pairwise import initial_wand
    from visionpos.camera.model import Camera, CameraModel

    cams = ring_cameras(4)
    frames = wand_frames(cams[:2], 10.0, SPEC, noise_px=0.2, seed=seed, time_offsets_s=np.zeros(2))
    data = collect_wand(frames, cams[:2], SPEC)
    xn = undistort_wand(data)
    both = data.seen.all(axis=1)
    R, t, good, lam, flat = pair_pose(xn[both, 0], xn[both, 1], SPEC, threshold=2 / 720)
    R_true = cams[1].R @ cams[0].R.T
    t_true = cams[1].t - R_true @ cams[0].t
    # the noise level: the two-view optimum reached from the *true* pose on the same data
    unit = CameraModel("pinhole", 1, 1, 1.0, 1.0, 0.0, 0.0)
    Rs, ts = np.stack([np.eye(3), R_true]), np.stack([np.zeros(3), t_true])
    obs = np.stack([xn[both, 0], xn[both, 1]], axis=1)
    A0, u0, ok = initial_wand(obs, Rs, ts, SPEC)
    two = [Camera(0, "i", unit, Rs[0], ts[0]), Camera(1, "j", unit, Rs[1], ts[1])]
    opt, *_ = bundle_adjust(obs[ok], two, Rs, ts, A0[ok], u0[ok], SPEC, f_scale=2 / 720)
    noise_ang = np.degrees(Rotation.from_matrix(opt[1].R @ R_true.T).magnitude())
    ang_to_opt = np.degrees(Rotation.from_matrix(R @ opt[1].R.T).magnitude())
    assert ang_to_opt < max(noise_ang, 0.02)  # init from a 300-frame subset: within the noise of the optimum
    assert np.linalg.norm(t - opt[1].t) < 1e-2
    # and the noise level itself is small: a fraction of a degree, a few mm on a 4 m baseline
    assert np.degrees(Rotation.from_matrix(R @ R_true.T).magnitude()) < 0.3
    assert abs(np.linalg.norm(t) / np.linalg.norm(t_true) - 1) < 5e-3
    assert flat > 0.1


def test_bundle_adjustment_recovers_poses_asynchronous_cameras_with_led_rings():
    cams = ring_cameras(4)
    frames = wand_frames(cams, 6.0, SPEC, noise_px=0.2, seed=1, static_blobs=2)  # ~300 steps at 50 Hz
    cal = calibrate_wand(frames, cams, SPEC)
    assert 250 <= len(cal.data.times_ns) <= 301
    ce, re, s = compare_cameras(cal.cameras, cams)
    assert ce.max() < 2e-3
    assert re.max() < 0.05
    assert abs(s - 1) < 2e-3  # metric scale from the wand lengths
    # reference camera keeps the identity pose (the world until the ground step)
    np.testing.assert_allclose(cal.cameras[0].R, np.eye(3), atol=1e-12)
    stats = cal.camera_stats()
    assert all(0.1 < st["rms_px"] < 0.4 for st in stats)
    L = cal.length_stats()
    assert abs(L["ac_mean_err"]) < 5e-4 and L["ac_std"] < 2e-3


def test_partial_overlap_chain():
    # six narrow-view cameras on a ring, each aimed off-centre: each sees only part of the wand's path
    from dataclasses import replace

    from visionpos.camera.model import Camera, look_at_rotation

    base = ring_cameras(1)[0].model
    narrow = replace(base, fx=1500.0, fy=1500.0)
    cams = []
    for i in range(6):
        a = 2 * np.pi * i / 6
        C = np.array([4.0 * np.cos(a), 4.0 * np.sin(a), 2.2])
        target = np.array([0.7 * np.cos(a + np.pi / 2), 0.7 * np.sin(a + np.pi / 2), 1.0])
        R = look_at_rotation(C, target)
        cams.append(Camera(i + 1, f"cam{i + 1}", narrow, R, -R @ C))
    frames = wand_frames(cams, 10.0, SPEC, seed=2, extent=(4.0, 4.0, 0.8))
    data = collect_wand(frames, cams, SPEC)
    seen = data.seen
    assert (seen.sum(axis=1) < 6).mean() > 0.3  # genuinely partial overlap
    cal = calibrate_wand(frames, cams, SPEC)
    ce, re, _ = compare_cameras(cal.cameras, cams)
    assert ce.max() < 3e-3 and re.max() < 0.05


def test_too_few_frames_names_the_camera():
    cams = ring_cameras(3)
    frames = wand_frames(cams, 4.0, SPEC)
    frames = [f for f in frames if f.camera_id != 2 or f.seq < 20]
    with pytest.raises(CalibrationError, match=r"'cam2' \(id 2\): \d+ wand frames"):
        calibrate_wand(frames, cams, SPEC)


def test_camera_without_overlap_is_named():
    cams = ring_cameras(3)
    frames = wand_frames(cams, 4.0, SPEC)
    # camera 3 saw the wand, but never at the same time as the others
    shifted = [
        BlobFrame(f.camera_id, f.seq, f.capture_ns + 100_000_000_000, f.blobs) for f in frames if f.camera_id == 3
    ]
    frames = [f for f in frames if f.camera_id != 3] + shifted
    with pytest.raises(CalibrationError, match=r"cam3 cannot be connected"):
        calibrate_wand(frames, cams, SPEC)


def test_planar_wand_motion_is_reported():
    cams = ring_cameras(3)
    frames = wand_frames(cams, 6.0, SPEC, planar=True)
    with pytest.raises(CalibrationError, match="degenerate wand motion"):
        calibrate_wand(frames, cams, SPEC)


def test_small_volume_is_reported():
    cams = ring_cameras(3)
    frames = wand_frames(cams, 6.0, SPEC, extent=(0.08, 0.08, 0.08))
    with pytest.raises(CalibrationError, match="degenerate wand motion"):
        calibrate_wand(frames, cams, SPEC)


def test_initial_poses_in_reference_frame():
    cams = ring_cameras(3)
    frames = wand_frames(cams, 5.0, SPEC, seed=5)
    data = collect_wand(frames, cams, SPEC)
    R, t, pairs = initial_poses(data, SPEC, ref=1)
    np.testing.assert_allclose(R[1], np.eye(3))
    # camera 0 seen from camera 1: R_01 = R0 R1^T
    R_true = cams[0].R @ cams[1].R.T
    assert np.degrees(Rotation.from_matrix(R[0] @ R_true.T).magnitude()) < 0.3
    assert len(pairs) == 2


def test_two_cameras():
    cams = ring_cameras(2, radius=3.5)
    frames = wand_frames(cams, 8.0, SPEC, seed=3)
    cal = calibrate_wand(frames, cams, SPEC)
    ce, re, s = compare_cameras(cal.cameras, cams)
    assert ce.max() < 2e-3 and re.max() < 0.05
    # the metric baseline comes from the wand alone
    base_est = np.linalg.norm(cal.cameras[1].center - cal.cameras[0].center)
    base_true = np.linalg.norm(cams[1].center - cams[0].center)
    assert abs(base_est / base_true - 1) < 1e-3
