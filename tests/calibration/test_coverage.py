"""The calibration assistant's counts (visionpos/calibration/coverage.py) against hand-counted blob frames."""

from __future__ import annotations

import numpy as np

from visionpos.calibration.coverage import (
    Thresholds,
    WandCoverage,
    components,
    coverage_grid,
    covered_fraction,
    shared_steps,
    verdict,
)
from visionpos.calibration.wand import WandSpec
from visionpos.camera.model import Camera, CameraModel
from visionpos.messages import BlobFrame

MS = 1_000_000
MODEL = CameraModel("pinhole", 640, 480, 500.0, 500.0, 320.0, 240.0)  # no distortion: pixels stay collinear


def _cam(cid: int) -> Camera:
    return Camera(cid, f"c{cid}", MODEL, np.eye(3), np.zeros(3))


def _wand_frame(cid: int, t_ns: int, y_px: float, extra=()) -> BlobFrame:
    """A wand lying along x: A (100, y), B (154, y), C (257, y): AB 54 px, BC 103 px (the wand's 54:103)."""
    blobs = [[100.0, y_px, 5, 200], [154.0, y_px, 5, 200], [257.0, y_px, 5, 200], *extra]
    return BlobFrame(cid, 0, t_ns, np.array(blobs, np.float32))


def test_coverage_grid_counts_each_marker_in_its_cell_and_ignores_the_rest():
    # 80 x 60 image in 4 x 3 cells of 20 x 20 px
    px = np.array([[[5, 5], [25, 5], [79.9, 59.9]],
                   [[5, 5], [np.nan, np.nan], [-1, 10]]])
    counts = coverage_grid(px, 80, 60, 4, 3)
    want = np.zeros((3, 4), int)
    want[0, 0] = 2  # (5, 5) twice
    want[0, 1] = 1  # (25, 5)
    want[2, 3] = 1  # (79.9, 59.9): the last cell; NaN and (-1, 10) outside
    np.testing.assert_array_equal(counts, want)
    assert covered_fraction(counts, 1) == 3 / 12
    assert covered_fraction(counts, 2) == 1 / 12


def test_shared_steps_and_components_by_hand():
    seen = np.array([[1, 1, 0, 0],
                     [1, 0, 1, 0],
                     [1, 1, 1, 0],
                     [0, 0, 1, 1]], bool)
    s = shared_steps(seen)
    assert s.tolist() == [[3, 2, 2, 0], [2, 2, 1, 0], [2, 1, 3, 1], [0, 0, 1, 1]]
    assert components(s, 2) == [[0, 1, 2], [3]]
    assert components(s, 1) == [[0, 1, 2, 3]]
    assert components(s, 3) == [[0], [1], [2], [3]]


def test_the_verdict_names_what_is_missing_and_flips_when_the_thresholds_are_met():
    th = Thresholds(min_camera_frames=10, min_steps=8, min_pair_frames=5, min_coverage=0.5)
    names = ["a", "b", "c"]
    shared = np.array([[12, 6, 0], [6, 12, 4], [0, 4, 12]])
    missing = verdict(names, np.array([12, 9, 12]), np.array([0.6, 0.6, 0.3]), shared, 7, th)
    assert missing == [
        "camera b has 9 wand frames, want 10",
        "camera c covers 30 % of its image, want 50 %: wave the wand where it sees little yet (its heat map)",
        "7 time steps see the wand in two or more cameras, want 8",
        "camera(s) c not connected to the others: the best pair c-b shares 4 frames, want 5 (wave where their "
        "views overlap)",
    ]
    shared[1, 2] = shared[2, 1] = 5
    assert verdict(names, np.array([12, 10, 12]), np.array([0.6, 0.6, 0.5]), shared, 8, th) == []


def test_live_counts_of_hand_built_wand_frames():
    """Camera 1 sees the wand in 10 frames at 0, 10, ..., 90 ms, moving 7 px down each; camera 2 in 6 frames at
    3, 13, ..., 53 ms. The solver's 50 Hz grid takes the first stamp of each 20 ms bin: 0, 20, 40, 60, 80 ms.
    Camera 1 has a frame at each; camera 2 is interpolated at 20 (13..23) and 40 (33..43) only: 0 lies before its
    first frame, 60 and 80 after its last. So the pair shares 2 steps, and 2 steps see the wand in two cameras."""
    cams = [_cam(1), _cam(2)]
    cov = WandCoverage(cams, WandSpec(), Thresholds(min_cell_markers=3))
    one = [_wand_frame(1, i * 10 * MS, 10 + 7 * i) for i in range(10)]
    two = [_wand_frame(2, (3 + i * 10) * MS, 10 + 7 * i) for i in range(6)]
    blank = BlobFrame(2, 0, 70 * MS, np.zeros((0, 4), np.float32))
    cov.add_frames(one[:5] + two[:3])  # two chunks: the counts add up
    cov.add_frames(one[5:] + two[3:] + [blank, BlobFrame(9, 0, 0, np.zeros((0, 4), np.float32))])
    s = cov.summary()
    c1, c2 = s["cameras"]
    assert (c1["frames"], c1["labelled"], c2["frames"], c2["labelled"]) == (10, 10, 7, 6)
    # 640 x 480 in 8 x 6 cells of 80 px: A (100) and B (154) in column 1, C (257) in column 3; y 10..73 in row 0
    grid1 = np.zeros((6, 8), int)
    grid1[0, 1], grid1[0, 3] = 20, 10
    np.testing.assert_array_equal(c1["grid"], grid1)
    grid2 = np.zeros((6, 8), int)
    grid2[0, 1], grid2[0, 3] = 12, 6
    np.testing.assert_array_equal(c2["grid"], grid2)
    assert c1["coverage"] == round(2 / 48, 4)
    assert s["pairs"] == [{"a": 1, "b": 2, "frames": 2}]
    assert s["steps"] == 2
    assert not s["enough"] and not s["solvable"]


def test_a_triple_among_static_blobs_is_still_the_wand():
    """A fixed reflection in every frame is the solver's static blob: removed, the three wand blobs labelled."""
    cov = WandCoverage([_cam(1)], WandSpec(), Thresholds())
    frames = [_wand_frame(1, i * 10 * MS, 10 + 7 * i, extra=[[600.0, 400.0, 5, 250]]) for i in range(10)]
    cov.add_frames(frames)
    c = cov.summary()["cameras"][0]
    assert c["labelled"] == 10
    assert c["grid"][5][7] == 0  # the reflection's cell
