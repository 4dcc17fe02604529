"""The camera monitor bench's measure of the pose a corrected camera is left with."""

import math

import numpy as np

from visionpos.benchmarks.camera_monitor import pose_left
from visionpos.config.arena import load_arena
from visionpos.fusion.camera_monitor import apply_correction


def test_pose_left_is_zero_for_the_true_pose_and_grows_with_a_turn():
    cam = load_arena("thesis").cameras[1]
    centre = cam.center + 2.5 * cam.R[2]  # 2.5 m in front of it, on its optical axis
    assert pose_left(cam, cam, centre) == (0.0, 0.0)
    turned = apply_correction(cam, np.array([math.radians(0.5), 0, 0, 0, 0, 0]))
    deg, px = pose_left(turned, cam, centre)
    assert math.isclose(deg, 0.5, rel_tol=1e-6)
    # a 0.5 deg turn moves the image by about fy tan(0.5 deg) px near the centre
    f = cam.model.fy
    assert 0.9 * f * math.tan(math.radians(0.5)) < px < 1.2 * f * math.tan(math.radians(0.5))
