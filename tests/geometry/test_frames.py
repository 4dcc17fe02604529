"""Frames at the MAVLink edge (geometry/frames.py): hand-worked cases and scipy's Rotation."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from visionpos.geometry.frames import (
    FLU_FRD,
    euler_ned_frd,
    flu_to_frd,
    frd_to_flu,
    ned_to_world,
    quat_ned_frd_to_world_body,
    quat_world_body_to_ned_frd,
    rotation_world_body_to_ned_frd,
    world_to_ned,
    yaw_matrix_ned,
)


def test_vector_frames_hand_worked():
    np.testing.assert_array_equal(world_to_ned([1.0, 2.0, 3.0]), [1.0, -2.0, -3.0])
    np.testing.assert_array_equal(ned_to_world([1.0, -2.0, -3.0]), [1.0, 2.0, 3.0])
    np.testing.assert_array_equal(flu_to_frd([[0.5, 1.0, 2.0]]), [[0.5, -1.0, -2.0]])
    np.testing.assert_array_equal(frd_to_flu([[0.5, -1.0, -2.0]]), [[0.5, 1.0, 2.0]])
    # a point 1 m above the origin is at Down = -1
    assert world_to_ned([0.0, 0.0, 1.0])[2] == -1.0
    np.testing.assert_array_equal(FLU_FRD @ FLU_FRD, np.eye(3))


@pytest.mark.parametrize(
    "axis, deg_world, expect_rpy_ned_deg",
    [
        ("z", 90.0, (0.0, 0.0, -90.0)),  # yawed left (CCW from above) -> NED yaw -90
        ("z", -30.0, (0.0, 0.0, 30.0)),  # yawed right
        ("y", -10.0, (0.0, 10.0, 0.0)),  # nose up (x towards +z) -> positive pitch
        ("x", 20.0, (20.0, 0.0, 0.0)),  # left side up = right wing down -> positive roll
    ],
)
def test_attitude_frames_hand_worked(axis, deg_world, expect_rpy_ned_deg):
    q = Rotation.from_euler(axis, deg_world, degrees=True).as_quat()
    rpy = np.degrees(euler_ned_frd(q))
    np.testing.assert_allclose(rpy, expect_rpy_ned_deg, atol=1e-9)


def test_quaternion_frames_consistent_with_vectors():
    rng = np.random.default_rng(13)
    q = Rotation.random(20, random_state=4).as_quat()
    qn = quat_world_body_to_ned_frd(q)
    v_body = rng.normal(size=(20, 3))
    # rotate a body vector to world then to NED, or to FRD then by the NED/FRD rotation
    a = world_to_ned(Rotation.from_quat(q).apply(v_body))
    b = Rotation.from_quat(qn).apply(flu_to_frd(v_body))
    np.testing.assert_allclose(a, b, atol=1e-12)
    # nose direction: body forward (1,0,0) for a body yawed +90 deg points to world +y = West
    q_yaw = Rotation.from_euler("z", 90, degrees=True).as_quat()
    fwd_ned = Rotation.from_quat(quat_world_body_to_ned_frd(q_yaw)).apply([1.0, 0.0, 0.0])
    np.testing.assert_allclose(fwd_ned, [0.0, -1.0, 0.0], atol=1e-12)  # East = -1: facing West
    back = quat_ned_frd_to_world_body(qn)
    assert np.allclose(np.abs(np.sum(back * q, axis=1)), 1.0)


def test_matrix_and_quaternion_conversions_agree():
    q = Rotation.random(10, random_state=9).as_quat()
    R_ned = rotation_world_body_to_ned_frd(Rotation.from_quat(q).as_matrix())
    np.testing.assert_allclose(R_ned, Rotation.from_quat(quat_world_body_to_ned_frd(q)).as_matrix(), atol=1e-12)


@pytest.mark.parametrize("yaw_deg", [0.0, 30.0, -120.0])
def test_yaw_matrix_is_a_turn_about_down(yaw_deg):
    Y = yaw_matrix_ned(np.radians(yaw_deg))
    np.testing.assert_allclose(Y, Rotation.from_euler("z", yaw_deg, degrees=True).as_matrix(), atol=1e-15)
    # clockwise seen from above: north turns towards east for a positive yaw
    assert np.sign((Y @ [1.0, 0.0, 0.0])[1]) == np.sign(yaw_deg)


def test_euler_ned_frd_matches_scipy_on_the_conjugated_rotation():
    """Reference: scipy's ZYX Euler angles of F R F, F = diag(1, -1, -1) written out here."""
    F = np.diag([1.0, -1.0, -1.0])
    R = Rotation.random(12, random_state=10)
    ref = Rotation.from_matrix(F @ R.as_matrix() @ F).as_euler("ZYX")[:, ::-1]
    np.testing.assert_allclose(euler_ned_frd(R.as_quat()), ref, atol=1e-12)
    np.testing.assert_allclose(euler_ned_frd(R.as_quat()[0]), ref[0], atol=1e-12)  # one quaternion
