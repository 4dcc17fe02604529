"""The Foxglove scene's geometry and its fast encoders, against independent computations."""

from __future__ import annotations

import numpy as np
import pytest

from visionpos.camera.model import CameraModel
from visionpos.foxglove import scene
from visionpos.foxglove.protobuf import encode, time_msg


def test_camera_frame_maps_camera_points_to_the_world(look_at_camera):
    model = CameraModel("pinhole", 640, 480, 500.0, 500.0, 319.5, 239.5)
    cam = look_at_camera(np.array([2.0, -3.0, 2.5]), np.array([0.0, 0.5, 0.0]), model)
    tr, q = scene.camera_in_world(cam.R, cam.t)
    x, y, z, w = q
    # the quaternion's rotation matrix, written out (not the code under test's conversion)
    Rq = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                   [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                   [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
    world = np.array([[0.3, -0.2, 1.0], [1.0, 1.0, 0.0], [-2.0, 0.5, 0.7]])
    in_cam = cam.to_camera(world)
    np.testing.assert_allclose(in_cam @ Rq.T + tr, world, atol=1e-12)  # parent <- child, as FrameTransform
    np.testing.assert_allclose(tr, [2.0, -3.0, 2.5], atol=1e-12)


def test_frustum_corners_project_to_the_image_corners():
    model = CameraModel("pinhole", 800, 600, 700.0, 710.0, 401.3, 297.8)
    seg = scene.frustum_segments(model.K, 800, 600, depth_m=0.4)
    assert seg.shape == (16, 3)
    far = seg[1::4]
    np.testing.assert_allclose(far[:, 2], 0.4)
    uv = far[:, :2] / far[:, 2:] * [700.0, 710.0] + [401.3, 297.8]
    np.testing.assert_allclose(uv, [[-0.5, -0.5], [799.5, -0.5], [799.5, 599.5], [-0.5, 599.5]], atol=1e-9)
    np.testing.assert_array_equal(seg[0::4], 0.0)  # each edge from the centre


def test_grid_covers_the_box_on_whole_steps():
    seg = scene.grid_segments(np.array([-1.2, 0.3]), np.array([2.1, 1.0]), 1.0)
    a, b = seg[0::2], seg[1::2]
    vertical = a[:, 0] == b[:, 0]
    assert sorted(a[vertical, 0]) == [-2.0, -1.0, 0.0, 1.0, 2.0, 3.0]  # x lines from y 0 to 1
    assert sorted(a[~vertical, 1]) == [0.0, 1.0] and (seg[:, 2] == 0).all()
    assert {(p[1], q[1]) for p, q in zip(a[vertical], b[vertical])} == {(0.0, 1.0)}


def test_blob_circles_use_foxglove_pixel_coordinates():
    c, d = scene.blob_circles(np.array([[0.0, 0.0, np.pi * 25, 200], [10.0, 5.0, 1.0, 90]], dtype=np.float32))
    np.testing.assert_array_equal(c, [[0.5, 0.5], [10.5, 5.5]])  # centre of pixel (0, 0) is (0.5, 0.5)
    np.testing.assert_allclose(d, [10.0, scene.MIN_BLOB_DIAMETER_PX], rtol=1e-6)


@pytest.mark.parametrize("n", [0, 1, 7, 88])
def test_fast_annotations_are_the_generic_encoding(n):
    rng = np.random.default_rng(n)
    blobs = (rng.random((n, 4)) * [640, 480, 60, 255]).astype(np.float32)
    if n > 1:
        blobs[0, 2] = 0.0  # no area
        blobs[1, :2] = -0.5  # a centre at Foxglove's 0: proto3 leaves it out
    want = encode("foxglove.ImageAnnotations", scene.image_annotations(-3_000_000_123, blobs))
    assert scene.encode_image_annotations(-3_000_000_123, blobs) == want


def test_time_messages_normalise_nanos():
    assert time_msg(-1) == {"seconds": -1, "nanos": 999_999_999}
    assert time_msg(12_000_000_005) == {"seconds": 12, "nanos": 5}


def test_calibration_distortion_models():
    pin5 = CameraModel("pinhole", 640, 480, 500.0, 500.0, 319.5, 239.5, np.array([0.1, -0.2, 0.0, 0.001, 0.05]))
    fish = CameraModel("fisheye", 640, 480, 300.0, 300.0, 319.5, 239.5, np.array([0.01, 0.02, -0.003, 0.0004]))
    from visionpos.camera.model import Camera

    a = scene.camera_calibration(5, Camera(2, "a", pin5, np.eye(3), np.zeros(3)))
    b = scene.camera_calibration(5, Camera(3, "b", fish, np.eye(3), np.zeros(3)))
    assert (a["distortion_model"], a["D"]) == ("plumb_bob", [0.1, -0.2, 0.0, 0.001, 0.05])
    assert (b["distortion_model"], b["D"]) == ("kannala_brandt", [0.01, 0.02, -0.003, 0.0004])
    assert a["P"] == [500.0, 0.0, 319.5, 0.0, 0.0, 500.0, 239.5, 0.0, 0.0, 0.0, 1.0, 0.0]
    assert a["frame_id"] == "camera_2"
    rat = CameraModel("pinhole", 640, 480, 500.0, 500.0, 319.5, 239.5, np.arange(1, 9) * 0.01)
    c = scene.camera_calibration(5, Camera(4, "c", rat, np.eye(3), np.zeros(3)))
    assert (c["distortion_model"], len(c["D"])) == ("rational_polynomial", 8)
