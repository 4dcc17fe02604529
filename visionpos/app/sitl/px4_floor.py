"""The floor PX4 SIH sets for any vision: the scripted flight of `visionpos sitl --autopilot px4` with SIH's own
true state (its display link's HIL_STATE_QUATERNION, as Px4Gcs keeps it) sent at 50 Hz, on arrival, in place of
the cameras, fusion and bridge, as the message the flight it is set beside sends: VISION_POSITION_ESTIMATE, or
ODOMETRY with the true velocity (in the body frame, as the bridge sends it) and no covariance, so that EKF2 takes
its noise floors.

SIH's IMU carries its vibration model in flight (accelerometer noise 0.5/1.7/1.4 m/s^2, gyro 0.14/0.07/0.03
rad/s on x/y/z, src/modules/simulation/simulator_sih/sih.cpp), which EKF2's output predictor integrates between
fusions: the EKF's error against the truth that this flight measures is what EKF2 on that IMU reaches with a
vision that is exact and on time. The `sitl_px4` bench sets the flight on visionpos's vision beside it.
"""

from __future__ import annotations

import asyncio
import socket
import threading
import time
from pathlib import Path
from typing import Any, TextIO

import numpy as np
from scipy.spatial.transform import Rotation

from bridge.convert import MAV_FRAME_LOCAL_NED, MavlinkState, odometry_fields
from visionpos.app.sitl.flight import FlightPlan
from visionpos.app.sitl.px4 import Px4Gcs, Px4Process, free_px4_instance, px4_parameters, px4_ports
from visionpos.app.sitl.px4_run import OUR_MODES, clock_rate_summary, fly_px4
from visionpos.app.sitl.report import flight_summary, say_to
from visionpos.app.sitl.settings import SITL, SitlError
from visionpos.app.sitl.truth import TruthTrack, truth_now
from visionpos.config.arena import ArenaConfig
from visionpos.geometry.frames import euler_ned_frd, quat_world_body_to_ned_frd, world_to_ned

TRUTH_VISION_HZ = 50.0
TRUTH_EV_DELAY_MS = 1  # the truth's own transit: display link out, our send back, both on loopback


class TruthVision:
    """A thread sending the true pose to PX4's Onboard link at rate_hz, as VISION_POSITION_ESTIMATE (NED, FRD
    roll/pitch/yaw, no covariance) or ODOMETRY (message "odometry": the bridge's frames, bridge/convert.py, with the
    true velocity and no covariance); nothing inside a cut(start_ns, end_ns) window."""

    def __init__(self, truth: TruthTrack, port: int, rate_hz: float = TRUTH_VISION_HZ,
                 message: str = "vision_position_estimate"):
        from pymavlink.dialects.v20 import common as mavlink2

        self.truth = truth
        self.odometry = message == "odometry"
        self.mav = mavlink2.MAVLink(None, srcSystem=200, srcComponent=197)  # MAVLink 2, whatever MAVLINK20 says
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.target = ("127.0.0.1", port)
        self.period_s = 1.0 / rate_hz
        self.sent = 0
        self.last_sent_ns = 0
        self._cuts: list[tuple[int, int]] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="px4-truth-vision", daemon=True)

    def start(self) -> TruthVision:
        self._thread.start()
        return self

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2.0)
        self.sock.close()

    def cut(self, start_ns: int, end_ns: int) -> None:
        self._cuts.append((start_ns, end_ns))

    def sending(self) -> bool:
        return time.monotonic_ns() - self.last_sent_ns < 200_000_000

    def _run(self) -> None:
        nan = float("nan")
        while not self._stop.wait(self.period_s):
            now = time.monotonic_ns()
            t_ns, _ = truth_now(self.truth)
            if t_ns == 0 or any(a <= now <= b for a, b in self._cuts):
                continue
            # the pose at this instant: the newest sample carried forward on its velocity and rate (<= 20 ms)
            pos, vel, _, rot = self.truth.sample(np.array([now], dtype=np.int64))
            ned = world_to_ned(pos[0])
            if self.odometry:
                state = _truth_state(ned, world_to_ned(vel[0]), rot.as_quat()[0])
                # LOCAL_NED, as the bridge sends PX4
                msg = self.mav.odometry_encode(**odometry_fields(state, now // 1000, 0, 100, MAV_FRAME_LOCAL_NED))
            else:
                roll, pitch, yaw = euler_ned_frd(rot.as_quat()[0])
                msg = self.mav.vision_position_estimate_encode(now // 1000, *ned, roll, pitch, yaw, [nan] * 21, 0)
            # counted before the send: a reader woken by this datagram must already see it counted
            self.sent += 1
            self.last_sent_ns = now
            try:
                self.sock.sendto(msg.pack(self.mav), self.target)
            except OSError:
                return


def _truth_state(position_ned: np.ndarray, velocity_ned: np.ndarray, q_world_flu: np.ndarray) -> MavlinkState:
    """The true pose and velocity (NED m, m/s; body->world quaternion x y z w) in MavlinkState's frames, rates and
    covariances unknown."""
    q_nf = quat_world_body_to_ned_frd(q_world_flu)
    R_nf = Rotation.from_quat(q_nf).as_matrix()
    nan3 = np.full(3, np.nan)
    return MavlinkState(position_ned, q_nf, euler_ned_frd(q_world_flu), velocity_ned, R_nf.T @ velocity_ned, nan3,
                        None, None, None)


def run_px4_truth_vision(arena: ArenaConfig, build: Path, plan: FlightPlan, out: TextIO | None,
                         message: str = "vision_position_estimate") -> dict[str, Any]:
    """Start PX4 SIH with the vision-only EKF2 (EKF2_EV_DELAY 1 ms) set for message, fly the plan on SIH's truth
    as the vision sent as that message, the summary dict (flight_summary's, with no `vision` statistics of ours)."""
    sec = SITL.check(arena.section("sitl"))
    home = tuple(float(x) for x in SITL.read(sec, "home"))
    instance = SITL.read(sec, "instance") or free_px4_instance()
    params = px4_parameters(message, TRUTH_EV_DELAY_MS, SITL.read(sec, "viso_pos_m_nse"),
                            SITL.read(sec, "viso_yaw_m_nse"), instance + 1)
    say = say_to(out)
    truth = TruthTrack(home[:3])
    record: dict[str, Any] = {"viso_delay_ms": TRUTH_EV_DELAY_MS, "delay_param": "EKF2_EV_DELAY"}
    t0 = time.monotonic()
    with Px4Process(build, instance, params, home) as proc:
        ports = px4_ports(instance)
        gcs = Px4Gcs(ports, truth, on_text=lambda text: say(f"  PX4: {text}"))
        vision: TruthVision | None = None
        try:
            gcs.connect(30.0, proc)
            gcs.check_params(params)
            vision = TruthVision(truth, ports["onboard"], message=message).start()
            say(f"PX4 SIH instance {instance}: SIH's true state sent as the vision ({message}) at "
                f"{TRUTH_VISION_HZ:g} Hz")
            try:
                asyncio.run(fly_px4(gcs, plan, record, say, vision, vision.sending, lambda: None))
            except SitlError as e:
                record["error"] = str(e)
                say(f"flight failed: {e}")
        finally:
            if vision is not None:
                vision.close()
            gcs.close()
    wall = time.monotonic() - t0
    summary = flight_summary(gcs, truth, {"duration_s": wall}, record, plan, wall, our_modes=OUR_MODES)
    summary["vision"] = {"poses_sent": vision.sent if vision is not None else 0, "source": "SIH's true state"}
    summary["real_time"] = {"frames_made": 0, "frames_late_fraction": 0.0, "frames_not_fused_fraction": 0.0}
    summary["delay_param"] = "EKF2_EV_DELAY"
    summary["px4_log"] = proc.log_timing
    summary["px4_clock_rate"] = clock_rate_summary(gcs)
    return summary


