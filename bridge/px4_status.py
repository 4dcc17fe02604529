"""PX4's ESTIMATOR_STATUS in plain words: is EKF2 fusing the external vision, and if not, why.

ESTIMATOR_STATUS.flags are EKF2's solution flags (ESTIMATOR_STATUS_FLAGS: 1 attitude, 2/4 horizontal/vertical
velocity, 8 relative horizontal position, 32 vertical position ...); its pos_horiz_ratio, pos_vert_ratio and
vel_ratio are the innovation test ratios of the aiding sources (over 1: the measurement fails EKF2's gate and is
rejected). With GPS off, a relative horizontal position can only come from the vision. Against PX4 SIH fusing EV
the flags read 0x1ef (../shared/sitl-px4/README.md).
"""

from __future__ import annotations

ESTIMATOR_ATTITUDE = 1
ESTIMATOR_POS_HORIZ_REL = 8
ESTIMATOR_POS_VERT_ABS = 32
EV_CHECKS = ("EKF2_EV_CTRL (bit 0 horizontal, 1 vertical position, 3 yaw), EKF2_HGT_REF=3, the ODOMETRY frame "
             "(LOCAL_NED / LOCAL_FRD) and estimator_type (VISION; MOCAP is never fused), EKF2_EV_QMIN against the "
             "quality sent")


def ev_fusion_state(flags: int, pos_horiz_ratio: float, pos_vert_ratio: float, vel_ratio: float,
                    sending: bool) -> tuple[str, str]:
    """('using vision' | 'rejecting vision' | 'not using vision', the reason in words) from one ESTIMATOR_STATUS
    (flags, test ratios) and whether poses are going to the vehicle (sending)."""
    ratios = f"test ratios position {pos_horiz_ratio:.2f}, height {pos_vert_ratio:.2f}, velocity {vel_ratio:.2f}"
    worst = max(pos_horiz_ratio, pos_vert_ratio, vel_ratio)
    if sending and worst > 1.0:
        which = max((("position", pos_horiz_ratio), ("height", pos_vert_ratio), ("velocity", vel_ratio)),
                    key=lambda kv: kv[1])[0]
        return "rejecting vision", (f"EKF2 rejects the vision: its {which} test ratio is {worst:.2f} (over 1 fails "
                                    f"the innovation gate; {ratios}): the poses disagree with its IMU: check "
                                    "yaw_offset_deg and the frame, EKF2_EV_DELAY (section 3), EKF2_EVP_NOISE")
    if not flags & ESTIMATOR_ATTITUDE:
        return "not using vision", f"EKF2 has no attitude yet (flags 0x{flags:x}): it has not started"
    if flags & ESTIMATOR_POS_HORIZ_REL:
        vert = "and height " if flags & ESTIMATOR_POS_VERT_ABS else ""
        return "using vision", f"EKF2 fuses the vision: relative position {vert}valid (flags 0x{flags:x}; {ratios})"
    if not sending:
        return "not using vision", f"no relative position (flags 0x{flags:x}) and no pose is going to it"
    return "not using vision", (f"EKF2 does not fuse the vision: no relative position although poses go "
                                f"(flags 0x{flags:x}); check {EV_CHECKS}")
