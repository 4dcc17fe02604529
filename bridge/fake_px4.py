"""What the fake autopilot does differently as PX4 (FakeAutopilot(autopilot="px4")), after PX4's
mavlink_receiver, EKF2 and commander as ../shared/sitl-px4/README.md found them against PX4 SIH:

- ODOMETRY reaches EKF2 only with estimator_type VISION, VIO, UNKNOWN or NAIVE (MOCAP goes to a topic EKF2 never
  reads) and frame_id LOCAL_NED, LOCAL_FRD, LOCAL_ENU or LOCAL_FLU; anything else is dropped (`dropped_poses`,
  with the reason). VISION_POSITION_ESTIMATE is always taken (NED).
- Arming (MAV_CMD_COMPONENT_ARM_DISARM) needs a GCS HEARTBEAT (MAV_TYPE_GCS) within the last 3 s, MANUAL_CONTROL
  within the last 0.5 s, Position mode (MAV_CMD_DO_SET_MODE 1, 3) and the vision fused; refused otherwise with
  a STATUSTEXT (at most 50 characters) that says which, worded by this fake, not as PX4 words it.
- ESTIMATOR_STATUS (230) on request, with the flags EKF2 showed fusing EV (0x1ef) or attitude only.
- PARAM_SET answered for the parameters PX4 has (PX4_PARAMS; an unknown name gets no answer, as PX4's), except
  those given as `reject_params` (no answer either: a firmware without them).
"""

from __future__ import annotations

import dataclasses

from pymavlink.dialects.v20 import ardupilotmega as mavlink2

EV_ESTIMATOR_TYPES = (0, 1, 2, 3)  # UNKNOWN, NAIVE, VISION, VIO (MAV_ESTIMATOR_TYPE_MOCAP = 6 is not fused)
EV_FRAMES = (1, 20, 4, 21)  # LOCAL_NED, LOCAL_FRD, LOCAL_ENU, LOCAL_FLU
FLAGS_EV_FUSED = 0x1EF  # what ESTIMATOR_STATUS showed with EV fused in SIH (README)
FLAGS_ATTITUDE_ONLY = 0x1
POSCTL = 3  # PX4's main mode Position (custom_mode = main << 16)
GCS_TIMEOUT_NS = 3_000_000_000
MANUAL_TIMEOUT_NS = 500_000_000
POSE_FRESH_NS = 500_000_000
RC_LOSS_NS = 500_000_000  # COM_RC_LOSS_T's default
AUTO, OFFBOARD, AUTO_LAND = 4, 6, 6  # main modes, and AUTO's land sub mode
# the EV-only set-up's parameters and PX4's defaults for them (docs/autopilot-setup.md, PX4)
PX4_PARAMS = {"EKF2_EV_CTRL": 15.0, "EKF2_HGT_REF": 1.0, "EKF2_GPS_CTRL": 7.0, "EKF2_EV_DELAY": 0.0,
              "EKF2_EV_NOISE_MD": 0.0, "EKF2_EVP_NOISE": 0.1, "EKF2_EVA_NOISE": 0.1, "EKF2_EVV_NOISE": 0.1,
              "EKF2_EV_QMIN": 0.0, "EKF2_MAG_TYPE": 0.0, "EKF2_BARO_CTRL": 1.0, "SYS_HAS_GPS": 1.0,
              "SYS_HAS_MAG": 1.0, "SENS_EN_GPSSIM": 1.0, "EKF2_EV_POS_X": 0.0, "EKF2_EV_POS_Y": 0.0,
              "EKF2_EV_POS_Z": 0.0, "MAV_SYS_ID": 1.0, "COM_RC_IN_MODE": 0.0, "EKF2_RNG_CTRL": 1.0,
              "EKF2_DELAY_MAX": 200.0, "EKF2_ASP_DELAY": 100.0, "EKF2_GPS_DELAY": 110.0, "EKF2_TAU_POS": 0.25,
              "EKF2_TAU_VEL": 0.25}
# those PX4 declares INT32: PARAM_VALUE carries their bytes, not their value as a float (bridge/convert.py)
PX4_INT_PARAMS = frozenset({"EKF2_EV_CTRL", "EKF2_HGT_REF", "EKF2_GPS_CTRL", "EKF2_EV_NOISE_MD", "EKF2_EV_QMIN",
                            "EKF2_MAG_TYPE", "EKF2_BARO_CTRL", "SYS_HAS_GPS", "SYS_HAS_MAG", "SENS_EN_GPSSIM",
                            "MAV_SYS_ID", "COM_RC_IN_MODE", "EKF2_RNG_CTRL"})


def pose_refusal(t: str, fields: dict) -> str | None:
    """Why PX4's EKF2 would not see this pose message (None: it would)."""
    if t != "ODOMETRY":
        return None
    if fields["estimator_type"] not in EV_ESTIMATOR_TYPES:
        return (f"ODOMETRY estimator_type {fields['estimator_type']}: PX4 sends it to vehicle_mocap_odometry, "
                "which EKF2 does not read")
    if fields["frame_id"] not in EV_FRAMES:
        return f"ODOMETRY frame_id {fields['frame_id']}: PX4 drops the position (LOCAL_NED/FRD/ENU/FLU only)"
    return None


@dataclasses.dataclass
class Px4State:
    """The commander's side of the fake PX4: the GCS and manual control it has heard, its mode, armed."""

    last_gcs_ns: int = -(1 << 62)
    last_manual_ns: int = -(1 << 62)
    main_mode: int = 4  # AUTO (Hold) at boot, as PX4
    sub_mode: int = 0
    armed: bool = False

    def custom_mode(self) -> int:
        return (self.main_mode << 16) | (self.sub_mode << 24)

    def failsafe(self, now: int) -> str | None:
        """Manual control lost while armed in Position or Offboard (COM_RCL_EXCEPT 0: no mode is excepted):
        PX4 lands where it is (no global position for a return). The STATUSTEXT to say, once; None otherwise."""
        if self.armed and self.main_mode in (POSCTL, OFFBOARD) and now - self.last_manual_ns > RC_LOSS_NS:
            self.main_mode, self.sub_mode = AUTO, AUTO_LAND
            return "Failsafe activated"
        return None

    def base_mode(self) -> int:
        return mavlink2.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | (mavlink2.MAV_MODE_FLAG_SAFETY_ARMED if self.armed
                                                            else 0)

    def arm_refusal(self, now: int, ev_fused: bool) -> str | None:
        """Why arming is refused now (None: it arms)."""
        if now - self.last_gcs_ns > GCS_TIMEOUT_NS:
            return "Arming denied: no GCS heartbeat"
        if now - self.last_manual_ns > MANUAL_TIMEOUT_NS:
            return "Arming denied: no manual control"
        if self.main_mode != POSCTL:
            return "Arming denied: not in Position mode"
        if not ev_fused:
            return "Arming denied: no position estimate (EV)"
        return None

    def command(self, cmd: int, p1: float, p2: float, now: int, ev_fused: bool,
                p3: float = 0.0) -> tuple[int, str | None]:
        """(MAV_RESULT, STATUSTEXT to say) for MAV_CMD_DO_SET_MODE and MAV_CMD_COMPONENT_ARM_DISARM; (-1, None) for
        any other command."""
        if cmd == mavlink2.MAV_CMD_DO_SET_MODE:
            if int(p1) & mavlink2.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED and 1 <= int(p2) <= 8:
                self.main_mode, self.sub_mode = int(p2), int(p3) if int(p2) == AUTO else 0
                return mavlink2.MAV_RESULT_ACCEPTED, None
            return mavlink2.MAV_RESULT_DENIED, None
        if cmd == mavlink2.MAV_CMD_COMPONENT_ARM_DISARM:
            if p1 < 0.5:
                self.armed = False
                return mavlink2.MAV_RESULT_ACCEPTED, None
            why = self.arm_refusal(now, ev_fused)
            if why is not None:
                return mavlink2.MAV_RESULT_DENIED, why
            self.armed = True
            return mavlink2.MAV_RESULT_ACCEPTED, None
        return -1, None
