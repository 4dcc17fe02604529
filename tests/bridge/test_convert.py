"""BodyState -> MAVLink field conversion against hand-computed values (no sockets)."""

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from bridge.convert import (
    back_propagate,
    convert_state,
    mavlink_upper_triangle,
    odometry_fields,
    param_from_wire,
    param_to_wire,
    vision_position_fields,
    vision_speed_fields,
)
from visionpos.benchmarks.factories import body_state
from visionpos.geometry.rotations import euler_rate_matrix

S45 = math.sqrt(0.5)
YAW_LEFT_90 = (0.0, 0.0, S45, S45)  # body x -> world +y (turned 90 deg left, counter-clockwise from above)


def conv(st, pivot=(0, 0, 0), yaw_offset_deg=0.0):
    return convert_state(st, np.asarray(pivot, float), math.radians(yaw_offset_deg))


def test_position_and_yaw_to_ned():
    c = conv(body_state(position=(1, 2, 3), quaternion=YAW_LEFT_90))
    np.testing.assert_allclose(c.position_ned, [1, -2, -3], atol=1e-12)
    np.testing.assert_allclose(c.euler, [0, 0, -math.pi / 2], atol=1e-12)  # facing world +y = west of north x
    np.testing.assert_allclose(c.quaternion_ned_frd, [0, 0, -S45, S45], atol=1e-12)


def test_roll_pitch_signs():
    # nose up 10 deg in FLU is a rotation of -10 deg about body y (left); in FRD pitch +10 deg
    q = Rotation.from_euler("y", -10, degrees=True).as_quat()
    np.testing.assert_allclose(conv(body_state(quaternion=q)).euler, [0, math.radians(10), 0], atol=1e-12)
    # right wing down: rotation +10 deg about forward x in FLU (y axis goes up) -> FRD roll +10 deg
    q = Rotation.from_euler("x", 10, degrees=True).as_quat()
    np.testing.assert_allclose(conv(body_state(quaternion=q)).euler, [math.radians(10), 0, 0], atol=1e-12)


def test_odometry_body_velocities():
    st = body_state(position=(1, 2, 3), quaternion=YAW_LEFT_90, velocity=(1, 0, 0), angular_velocity=(0.1, 0.2, 0.3))
    c = conv(st)
    # facing world +y, moving along world +x = moving to its right: FRD (0, 1, 0)
    np.testing.assert_allclose(c.velocity_frd, [0, 1, 0], atol=1e-12)
    np.testing.assert_allclose(c.velocity_ned, [1, 0, 0], atol=1e-12)
    np.testing.assert_allclose(c.angular_velocity_frd, [0.1, -0.2, -0.3], atol=1e-12)
    f = odometry_fields(c, usec=123, reset_counter=4, quality=100)
    assert (f["frame_id"], f["child_frame_id"], f["estimator_type"]) == (20, 12, 2)
    np.testing.assert_allclose(f["q"], [S45, 0, 0, -S45], atol=1e-12)  # w first
    assert (f["vx"], f["vy"], f["vz"]) == pytest.approx((0, 1, 0), abs=1e-12)
    assert f["time_usec"] == 123 and f["reset_counter"] == 4


def test_back_propagation_to_capture_time():
    # state valid 20 ms after capture, moving 1 m/s along x, turning 0.5 rad/s left
    st = body_state(position=(1, 2, 3), velocity=(1, 0, 0), angular_velocity=(0, 0, 0.5), dt_ns=20_000_000)
    c = conv(st)
    np.testing.assert_allclose(c.position_ned, [0.98, -2, -3], atol=1e-12)
    np.testing.assert_allclose(c.euler[2], -(-0.5 * 0.02), atol=1e-12)  # world yaw -0.01 rad -> NED yaw +0.01


def test_velocity_and_position_moved_to_the_stamp_on_the_filters_acceleration():
    """A state 20 ms after its stamp, at 1 m/s along x and accelerating 2 m/s^2 along y (a turn): at the stamp
    the velocity was (1, -0.04, 0) and the position 0.4 mm less along y than the constant velocity says; a state
    without an acceleration (a point body, a recording) keeps the constant velocity."""
    import dataclasses

    from bridge.convert import convert_position_only

    st = dataclasses.replace(body_state(position=(1, 2, 3), velocity=(1, 0, 0), dt_ns=20_000_000),
                             acceleration=np.array([0.0, 2.0, 0.0]))
    c = conv(st)
    np.testing.assert_allclose(c.velocity_ned, [1, 0.04, 0], atol=1e-12)  # world y -> NED -y
    np.testing.assert_allclose(c.position_ned, [0.98, -(2 + 0.0004), -3], atol=1e-12)
    p = convert_position_only(st, 0.0)
    np.testing.assert_allclose(p.velocity_ned, c.velocity_ned, atol=1e-12)
    np.testing.assert_allclose(p.position_ned, c.position_ned, atol=1e-12)
    plain = conv(body_state(position=(1, 2, 3), velocity=(1, 0, 0), dt_ns=20_000_000))
    np.testing.assert_allclose(plain.velocity_ned, [1, 0, 0], atol=1e-12)


def test_pivot_and_yaw_offset():
    # reference point 0.1 m ahead of the marker centroid; vehicle faces world +y
    c = conv(body_state(position=(1, 2, 3), quaternion=YAW_LEFT_90), pivot=(0.1, 0, 0))
    np.testing.assert_allclose(c.position_ned, [1, -2.1, -3], atol=1e-12)
    # world +x is due east (heading 90): world (1, 0, 0) is (N 0, E 1); facing +x is yaw +90
    c = conv(body_state(position=(1, 0, 0)), yaw_offset_deg=90)
    np.testing.assert_allclose(c.position_ned, [0, 1, 0], atol=1e-12)
    np.testing.assert_allclose(c.euler, [0, 0, math.pi / 2], atol=1e-12)


def test_pivot_velocity_from_rotation():
    # turning left at 1 rad/s with the reference point 0.2 m ahead: it moves left at 0.2 m/s
    c = conv(body_state(angular_velocity=(0, 0, 1.0)), pivot=(0.2, 0, 0))
    np.testing.assert_allclose(c.velocity_ned, [0, -0.2, 0], atol=1e-12)  # world +y = NED -E


def test_covariance_layout_and_signs():
    C = np.diag([1e-4, 2e-4, 3e-4, 4e-4, 5e-4, 6e-4])
    C[0, 1] = C[1, 0] = 0.5e-4  # x-y
    C[0, 2] = C[2, 0] = 0.25e-4  # x-z
    C[1, 2] = C[2, 1] = 0.125e-4  # y-z
    f = vision_position_fields(conv(body_state(covariance=C)), usec=1, reset_counter=0)
    cov = np.array(f["covariance"])
    assert len(cov) == 21
    # row-major upper triangle: 0..5 row 0, 6..10 row 1, 11..14 row 2, 15..17 row 3, 18..19 row 4, 20 row 5
    np.testing.assert_allclose(cov[[0, 6, 11, 15, 18, 20]], [1e-4, 2e-4, 3e-4, 4e-4, 5e-4, 6e-4], atol=1e-15)
    assert cov[1] == pytest.approx(-0.5e-4)  # N-E = x-(-y)
    assert cov[2] == pytest.approx(-0.25e-4)  # N-D = x-(-z)
    assert cov[7] == pytest.approx(0.125e-4)  # E-D = (-y)(-z)
    assert np.count_nonzero(np.abs(cov) > 1e-18) == 9


def test_attitude_covariance_follows_heading():
    # facing world +y: error about world y is roll, about world x is pitch
    C = np.diag([1e-6, 1e-6, 1e-6, 1e-4, 4e-4, 9e-4])
    P = conv(body_state(quaternion=YAW_LEFT_90, covariance=C)).pose_cov
    np.testing.assert_allclose(np.diag(P)[3:], [4e-4, 1e-4, 9e-4], rtol=1e-12)


def test_euler_jacobian_matches_finite_differences():
    rng = np.random.default_rng(3)
    q = Rotation.from_euler("ZYX", [0.7, 0.3, -0.4]).as_quat()  # NED-FRD attitude
    e0 = Rotation.from_quat(q).as_euler("ZYX")[::-1]
    Einv = np.linalg.inv(euler_rate_matrix(e0))
    for _ in range(5):
        d = rng.normal(size=3) * 1e-6
        e1 = (Rotation.from_rotvec(d) * Rotation.from_quat(q)).as_euler("ZYX")[::-1]
        np.testing.assert_allclose(e1 - e0, Einv @ d, atol=1e-11)


def test_speed_fields_and_unknown_covariance():
    Cv = np.array([[1.0, 0.1, 0.2], [0.1, 2.0, 0.3], [0.2, 0.3, 3.0]]) * 1e-3
    f = vision_speed_fields(conv(body_state(velocity=(1, 2, 3), velocity_covariance=Cv)), usec=5, reset_counter=2)
    assert (f["x"], f["y"], f["z"]) == pytest.approx((1, -2, -3))
    np.testing.assert_allclose(
        f["covariance"], np.array([1, -0.1, -0.2, -0.1, 2, 0.3, -0.2, 0.3, 3]) * 1e-3, atol=1e-15
    )
    f = vision_position_fields(conv(body_state(covariance=np.full((6, 6), np.nan))), usec=1, reset_counter=0)
    assert math.isnan(f["covariance"][0])


def test_upper_triangle_order():
    m = np.arange(36.0).reshape(6, 6)
    assert mavlink_upper_triangle(m).tolist() == [
        0, 1, 2, 3, 4, 5, 7, 8, 9, 10, 11, 14, 15, 16, 17, 21, 22, 23, 28, 29, 35
    ]


def test_back_propagation_matches_scipy_composition():
    rng = np.random.default_rng(7)
    for _ in range(5):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        w = rng.normal(size=3)
        _, q_back = back_propagate(np.zeros(3), q, np.zeros(3), w, 0.02)
        expect = Rotation.from_quat(q) * Rotation.from_rotvec(-w * 0.02)
        assert (Rotation.from_quat(q_back) * expect.inv()).magnitude() < 1e-12


def test_param_values_on_the_wire_as_each_autopilot_encodes_them():
    """PX4 puts an INT32 parameter's bytes in PARAM_VALUE's float; ArduPilot casts. The bit patterns below are
    written out by hand: 11 as int32 is 0x0000000b, the float with those bits 11 * 2**-149."""
    bytewise_11 = 11 * 2.0 ** -149
    assert param_to_wire(11, 6, bytewise=True) == bytewise_11  # MAV_PARAM_TYPE_INT32
    assert param_from_wire(bytewise_11, 6, bytewise=True) == 11
    assert param_from_wire(-1.0, 6, bytewise=True) == -1082130432  # 0xbf800000 read as int32
    assert param_from_wire(bytewise_11, 9, bytewise=True) == bytewise_11  # REAL32: the float itself
    assert param_from_wire(11.0, 6, bytewise=False) == 11.0 and param_to_wire(11, 6, bytewise=False) == 11.0
    assert param_from_wire(param_to_wire(200, 1, True), 1, True) == 200  # UINT8 in the lowest byte
