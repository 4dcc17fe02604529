"""Pure conversions from a BodyState to MAVLink fields (no I/O).

World is z-up (x, y, z), body is FLU; MAVLink wants NED / FRD. The turn is
visionpos.geometry.frames' (N = x, E = -y, D = -z; body likewise), followed by a
yaw about the down axis (yaw_offset: compass heading of world +x).
Covariances are rotated with the same Jacobians; the attitude block is
converted from the small world-frame rotation-vector error of BodyState to
roll/pitch/yaw (ZYX Euler) through the Euler-rate matrix.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

import numpy as np

from visionpos.geometry.frames import (
    FLU_FRD,
    flu_to_frd,
    quat_world_body_to_ned_frd,
    world_to_ned,
    yaw_matrix_ned,
)
from visionpos.geometry.rotations import (
    euler_rate_matrix_inverse,
    euler_zyx_from_matrix,
    matrix_from_quat,
    quat_from_rotvec,
    quat_multiply,
    skew,
)
from visionpos.jit import cross3
from visionpos.messages import BodyState

UT6 = np.triu_indices(6)  # MAVLink's upper-triangle, row-major order: (0,0) (0,1) .. (0,5) (1,1) ..
UT3 = np.triu_indices(3)


def back_propagate(position: np.ndarray, quaternion: np.ndarray, velocity: np.ndarray,
                   angular_velocity: np.ndarray, dt_s: float,
                   acceleration: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Move a state valid at t back by dt_s seconds with constant velocities (and a constant acceleration where
    given: the filter's model).

    position, velocity: (3,) world; quaternion: (4,) xyzw body->world;
    angular_velocity: (3,) rad/s body; acceleration: (3,) m/s^2 world. Returns (position (3,), quaternion (4,))
    at t - dt_s.
    """
    p = np.asarray(position, float) - np.asarray(velocity, float) * dt_s
    if acceleration is not None:
        p = p + 0.5 * dt_s * dt_s * acceleration
    q = quat_multiply(np.asarray(quaternion, float), quat_from_rotvec(-np.asarray(angular_velocity, float) * dt_s))
    return p, q / np.sqrt(q @ q)


def mavlink_upper_triangle(m: np.ndarray) -> np.ndarray:
    """(6, 6) -> (21,) row-major upper triangle; (3, 3) -> (6,)."""
    m = np.asarray(m, float)
    return m[UT6] if m.shape == (6, 6) else m[UT3]


def nan_covariance(n: int) -> list[float]:
    """MAVLink's 'unknown covariance': NaN in the first element."""
    return [float("nan")] + [0.0] * (n - 1)


@dataclass(slots=True)
class MavlinkState:
    """A BodyState in MAVLink's frames (local NED, body FRD) at one time: what the messages carry.

    position_ned: (3,) m of the vehicle's reference point. quaternion_ned_frd: (4,) x y z w, body FRD ->
    NED (w >= 0). euler: (3,) roll, pitch, yaw rad (ZYX). velocity_ned: (3,) m/s of the reference point;
    velocity_frd: (3,) the same in the body frame. angular_velocity_frd: (3,) rad/s, body frame.
    pose_cov: (6, 6) over [x y z roll pitch yaw] (m^2, rad^2), None when unknown. velocity_cov_ned,
    velocity_cov_frd: (3, 3) m^2/s^2, None when unknown.
    """

    position_ned: np.ndarray
    quaternion_ned_frd: np.ndarray
    euler: np.ndarray
    velocity_ned: np.ndarray
    velocity_frd: np.ndarray
    angular_velocity_frd: np.ndarray
    pose_cov: np.ndarray | None
    velocity_cov_ned: np.ndarray | None
    velocity_cov_frd: np.ndarray | None


def _acceleration(state: BodyState) -> np.ndarray:
    """The state's world acceleration (3,) m/s^2; zero where unknown (NaN: a point body, a state without one)."""
    a = np.asarray(state.acceleration, float)
    return a if np.isfinite(a).all() else np.zeros(3)


def pose_at(state: BodyState, at_ns: int) -> tuple[np.ndarray, np.ndarray]:
    """The state's pose at at_ns (server clock, ns), moved from its time_ns with the filter's own model (its
    velocity, body angular velocity and world acceleration): (position (3,) m world, quaternion (4,) xyzw
    body->world). Every output that stamps a pose with a capture time (MAVLink, VRPN, NatNet) sends this."""
    return back_propagate(state.position, state.quaternion, state.velocity, state.angular_velocity,
                          (state.time_ns - at_ns) * 1e-9, _acceleration(state))


def convert_state(state: BodyState, pivot_offset: np.ndarray, yaw_offset_rad: float,
                  at_ns: int | None = None) -> MavlinkState:
    """BodyState -> NED / FRD quantities at time at_ns (default: the state's capture time).

    The state is valid at time_ns; the message's usec carries at_ns, so the
    pose is moved back to at_ns with the state's velocities first, then
    shifted to the vehicle reference point (pivot_offset (3,) m, body FLU) and
    turned into NED / FRD.
    """
    at = state.capture_ns if at_ns is None else at_ns
    dt = (state.time_ns - at) * 1e-9
    w_body = np.asarray(state.angular_velocity, float)
    a_w = _acceleration(state)
    p_w, q_w = pose_at(state, at)
    R_wb = matrix_from_quat(q_w)
    o = np.asarray(pivot_offset, float)
    lever = R_wb @ o  # world-frame lever arm body origin -> reference point
    p_ref = p_w + lever
    # the velocity at at_ns, as the position: ODOMETRY states both at its stamp (on a 1.05 m/s circle the
    # velocity of the send time, 15 ms later, is 3 cm/s off, which PX4's EKF2 fuses at 1 cm/s and leads by)
    v_ref = np.asarray(state.velocity, float) - a_w * dt + R_wb @ cross3(w_body, o)

    Y = yaw_matrix_ned(yaw_offset_rad)
    J = Y @ FLU_FRD  # world z-up -> offset NED, for vectors and small rotations
    p_ned = Y @ world_to_ned(p_ref)
    v_ned = Y @ world_to_ned(v_ref)
    q_yaw = np.array([0.0, 0.0, np.sin(0.5 * yaw_offset_rad), np.cos(0.5 * yaw_offset_rad)])
    q_nf = quat_multiply(q_yaw, quat_world_body_to_ned_frd(q_w))
    if q_nf[3] < 0:
        q_nf = -q_nf
    R_nf = matrix_from_quat(q_nf)
    euler = euler_zyx_from_matrix(R_nf)
    v_frd = R_nf.T @ v_ned

    pose_cov = None
    C = np.asarray(state.covariance, float)
    if C.shape == (6, 6) and np.isfinite(C).all():
        # reference point error: dp_ref = dp + dtheta x lever = dp - [lever]x dtheta
        T = np.eye(6)
        T[:3, 3:] = -skew(lever)
        Einv = euler_rate_matrix_inverse(euler)
        A = np.zeros((6, 6))
        A[:3, :3] = J
        A[3:, 3:] = Einv @ J
        pose_cov = A @ T @ C @ T.T @ A.T
    vcov_ned = vcov_frd = None
    Cv = np.asarray(state.velocity_covariance, float)
    if Cv.shape == (3, 3) and np.isfinite(Cv).all():
        vcov_ned = J @ Cv @ J.T
        vcov_frd = R_nf.T @ vcov_ned @ R_nf
    return MavlinkState(p_ned, q_nf, euler, v_ned, v_frd, flu_to_frd(w_body), pose_cov, vcov_ned, vcov_frd)


def convert_position_only(state: BodyState, yaw_offset_rad: float, at_ns: int | None = None) -> MavlinkState:
    """A point body's BodyState (no attitude) -> NED quantities at at_ns (default: its capture time): the position
    moved back with the velocity, the velocity and their covariances; the attitude, the body-frame velocity and
    the rates NaN (unknown), the pose covariance's rotation rows and columns NaN."""
    dt = (state.time_ns - (state.capture_ns if at_ns is None else at_ns)) * 1e-9
    a_w = _acceleration(state)
    v_w = np.asarray(state.velocity, float) - a_w * dt
    Y = yaw_matrix_ned(yaw_offset_rad)
    J = Y @ FLU_FRD  # world z-up -> offset NED
    nan3 = np.full(3, np.nan)
    C = np.asarray(state.covariance, float)
    pose_cov = None
    if C.shape == (6, 6) and np.isfinite(C[:3, :3]).all():
        pose_cov = np.full((6, 6), np.nan)
        pose_cov[:3, :3] = J @ C[:3, :3] @ J.T
    Cv = np.asarray(state.velocity_covariance, float)
    vcov_ned = J @ Cv @ J.T if Cv.shape == (3, 3) and np.isfinite(Cv).all() else None
    p_w = np.asarray(state.position, float) - (v_w + 0.5 * a_w * dt) * dt  # v_w is the velocity at at_ns
    return MavlinkState(Y @ world_to_ned(p_w), np.full(4, np.nan),
                        nan3, Y @ world_to_ned(v_w), nan3.copy(), nan3.copy(), pose_cov, vcov_ned, None)


def vision_position_fields(c: MavlinkState, usec: int, reset_counter: int) -> dict:
    """Fields of VISION_POSITION_ESTIMATE. Without an attitude (a point body: euler NaN) roll, pitch and yaw are
    0 and the covariance unknown (NaN first): ArduPilot takes the position with VISO_POS_M_NSE and reads the
    attitude only for EK3_SRC1_YAW = 6 (docs/autopilot-setup.md, single-marker drones)."""
    x, y, z = (float(a) for a in c.position_ned)
    if not np.isfinite(c.euler).all():
        return dict(usec=usec, x=x, y=y, z=z, roll=0.0, pitch=0.0, yaw=0.0, covariance=nan_covariance(21),
                    reset_counter=reset_counter)
    cov = nan_covariance(21) if c.pose_cov is None else mavlink_upper_triangle(c.pose_cov).tolist()
    roll, pitch, yaw = (float(a) for a in c.euler)
    return dict(usec=usec, x=x, y=y, z=z, roll=roll, pitch=pitch, yaw=yaw, covariance=cov, reset_counter=reset_counter)


def vision_speed_fields(c: MavlinkState, usec: int, reset_counter: int) -> dict:
    """Fields of VISION_SPEED_ESTIMATE (NED velocity, full 3x3 row-major covariance)."""
    cov = nan_covariance(9) if c.velocity_cov_ned is None else c.velocity_cov_ned.ravel().tolist()
    x, y, z = (float(a) for a in c.velocity_ned)
    return dict(usec=usec, x=x, y=y, z=z, covariance=cov, reset_counter=reset_counter)


MAV_FRAME_LOCAL_NED = 1
MAV_FRAME_LOCAL_FRD = 20
MAV_FRAME_BODY_FRD = 12
MAV_ESTIMATOR_TYPE_VISION = 2


def odometry_fields(c: MavlinkState, usec: int, reset_counter: int, quality: int,
                    frame_id: int = MAV_FRAME_LOCAL_FRD) -> dict:
    """Fields of ODOMETRY: pose in frame_id (our NED: LOCAL_FRD, which ArduPilot takes; PX4 reads LOCAL_FRD as a
    frame of unknown heading and never aligns its yaw, so it is sent LOCAL_NED, our NED being north-aligned through
    yaw_offset_deg), velocities in BODY_FRD, q w-first. Without an attitude
    (a point body) q is NaN first (MAVLink: unknown), the body-frame velocities and rates NaN with an unknown
    velocity covariance, and the pose covariance's rotation entries NaN."""
    pose_cov = nan_covariance(21) if c.pose_cov is None else mavlink_upper_triangle(c.pose_cov).tolist()
    if not np.isfinite(c.quaternion_ned_frd).all():
        x, y, z = (float(a) for a in c.position_ned)
        nan = float("nan")
        return dict(
            time_usec=usec, frame_id=frame_id, child_frame_id=MAV_FRAME_BODY_FRD,
            x=x, y=y, z=z, q=[nan, 0.0, 0.0, 0.0], vx=nan, vy=nan, vz=nan, rollspeed=nan, pitchspeed=nan, yawspeed=nan,
            pose_covariance=pose_cov, velocity_covariance=nan_covariance(21),
            reset_counter=reset_counter, estimator_type=MAV_ESTIMATOR_TYPE_VISION, quality=quality,
        )
    if c.velocity_cov_frd is None:
        vel_cov = nan_covariance(21)
    else:
        # angular-rate variances are not estimated: NaN there, linear block known
        V = np.full((6, 6), np.nan)
        V[:3, :3] = c.velocity_cov_frd
        V[:3, 3:] = np.nan
        vel_cov = mavlink_upper_triangle(V).tolist()
    qx, qy, qz, qw = (float(a) for a in c.quaternion_ned_frd)
    x, y, z = (float(a) for a in c.position_ned)
    vx, vy, vz = (float(a) for a in c.velocity_frd)
    wr, wp, wy = (float(a) for a in c.angular_velocity_frd)
    return dict(
        time_usec=usec, frame_id=frame_id, child_frame_id=MAV_FRAME_BODY_FRD,
        x=x, y=y, z=z, q=[qw, qx, qy, qz], vx=vx, vy=vy, vz=vz,
        rollspeed=wr, pitchspeed=wp, yawspeed=wy,
        pose_covariance=pose_cov, velocity_covariance=vel_cov,
        reset_counter=reset_counter, estimator_type=MAV_ESTIMATOR_TYPE_VISION, quality=quality,
    )


# PARAM_VALUE / PARAM_SET carry every parameter in a float32. ArduPilot casts integers to it (C_CAST); PX4 puts
# the integer's own bytes there (MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE): 11 reads 1.5e-44 as a float.
PARAM_INT_FORMATS = {1: "<B", 2: "<b", 3: "<H", 4: "<h", 5: "<I", 6: "<i"}  # MAV_PARAM_TYPE_(U)INT8..32


def param_from_wire(value: float, param_type: int, bytewise: bool) -> float:
    """The parameter's number from PARAM_VALUE's param_value (float32) and param_type; bytewise for PX4."""
    fmt = PARAM_INT_FORMATS.get(param_type)
    if not bytewise or fmt is None:
        return float(value)
    raw = struct.pack("<f", value)
    return float(struct.unpack(fmt, raw[:struct.calcsize(fmt)])[0])


def param_to_wire(number: float, param_type: int, bytewise: bool) -> float:
    """param_value to send for the number as param_type (the inverse of param_from_wire)."""
    fmt = PARAM_INT_FORMATS.get(param_type)
    if not bytewise or fmt is None:
        return float(number)
    raw = struct.pack(fmt, int(round(number))).ljust(4, b"\0")
    return struct.unpack("<f", raw)[0]
