"""PX4 SITL with SIH (PX4's own physics inside the px4 process) for `visionpos sitl --autopilot px4`: where the
build is, its EKF2 parameters (set at start with PX4_PARAM_ environment variables), the process, our ground-station
link (Px4Gcs) and the steps of the set-up: the parameters read back, EKF2 fusing the vision, arming in Position mode.
../shared/sitl-px4/README.md has what was learned against a real build; docs/autopilot-setup.md section 0 the use.

Ports of instance i (all loopback): PX4's GCS link listens on 18570+i (we send first: udpout), its Onboard link on
14580+i (the bridge's vehicle, udpout, unsigned: PX4 does not sign with our key) and its SIH display link sends
HIL_STATE_QUATERNION (the true state) to 19410+i, where Px4Gcs listens. MAV_SYS_ID is i+1.
"""

from __future__ import annotations

import os
import socket
import threading
import time
import types
from pathlib import Path
from typing import Any

import numpy as np

from bridge.estimator_delay import ekf2_arrival_horizon_ms
from visionpos.app.sitl.clock import clock_rate
from visionpos.app.sitl.gcs import Gcs
from visionpos.app.sitl.process import ChildProcess
from visionpos.app.sitl.settings import SHARED_SITL_DIR, SITL, SitlError
from visionpos.config.arena import ArenaConfig, ConfigError
from visionpos.errors import UsageError

PX4_ENV = "VISIONPOS_PX4_SITL"
SHARED_PX4_DIR = SHARED_SITL_DIR.parent / "sitl-px4" / "build"  # a build beside the checkout (tests, CI)
MAV_AUTOPILOT_PX4 = 12
MAV_AUTOPILOT_ARDUPILOTMEGA = 3
POSCTL, AUTO, OFFBOARD = 3, 4, 6  # PX4 main modes (custom_mode = main << 16, sub << 24)
AUTO_LAND = 6  # sub mode of AUTO
ESTIMATOR_POS_HORIZ_REL = 8
MANUAL_HZ, GCS_HEARTBEAT_HZ, SETPOINT_HZ = 10.0, 1.0, 20.0
# PX4's lockstep clock against ours: a line through the newest 10 s of TIMESYNC answers (4 a second: a loopback's
# 0.1-1 ms of one-way jitter puts the slope within about 1e-4), once they span 5 s; a rate outside the bounds is
# not a clock (PX4 restarted)
CLOCK_RATE_WINDOW_NS, CLOCK_RATE_MIN_SPAN_NS, CLOCK_RATE_PAIRS = 10_000_000_000, 5_000_000_000, 64
CLOCK_RATE_BOUNDS = (0.5, 1.5)
# SIH's display link streams HIL_STATE_QUATERNION at 25 Hz (px4-rc.mavlink): the cameras would render the body
# from a truth up to 40 ms old, carried forward on its velocity. SIH steps its physics at 250 Hz (sih.cpp), so the
# truth is asked for at that rate (SET_MESSAGE_INTERVAL on the display link itself), until it comes at least at
# TRUTH_MIN_HZ.
TRUTH_HZ, TRUTH_MIN_HZ = 250.0, 200.0
SIH_ACC_NOISE_M_S2, SIH_GYR_NOISE_RAD_S = 1.0, 0.1  # EKF2's IMU noise for SIH's vibrating IMU (px4_parameters)
# EKF2's own floor on the vision velocity's noise (m/s; ev_vel.h): above it the ODOMETRY's covariance rules
EV_VEL_NOISE_FLOOR_M_S = 0.01
# What `visionpos sitl --autopilot px4` and its benches send unless told: EKF2 fuses ODOMETRY's velocity too
# (EKF2_EV_CTRL 15). Its position noise cannot go under 1 cm (ev_pos_control.cpp), ten times a motion-capture
# system's, so on position alone it leans on the IMU; a velocity good to ~1 cm/s holds it (PX4 SIH, one flight
# each: EKF horizontal p99 23-25 mm on VISION_POSITION_ESTIMATE, 19 mm on ODOMETRY, 15.5 with EKF2_EVV_NOISE at
# its floor).
PX4_MESSAGE = "odometry"


def is_px4_dir(p: Path) -> bool:
    return (p / "bin" / "px4").is_file() and (p / "etc").is_dir()


def check_build_kind(path: Path, autopilot: str) -> None:
    """One clear line when the build given does not match --autopilot (PX4's folder for ardupilot, a file for px4)."""
    if autopilot == "px4" and path.is_file() and not (path.name == "px4" and path.parent.name == "bin"):
        raise UsageError(f"{path} is a file (ArduPilot's arducopter?); --autopilot px4 takes PX4's build folder "
                         "holding bin/px4 and etc/ (for arducopter, use --autopilot ardupilot)")
    if autopilot == "ardupilot" and path.is_dir() and is_px4_dir(path):
        raise UsageError(f"{path} is a PX4 build (bin/px4, etc/): fly it with --autopilot px4")


def find_px4_dir(cli_path: str | None, arena: ArenaConfig | None = None) -> Path:
    """PX4's SITL build folder (bin/px4 and etc/): --sitl PATH, the arena's sitl.px4_dir, $VISIONPOS_PX4_SITL, or
    ../shared/sitl-px4/build beside the checkout. PATH may also be the px4 binary in it."""
    def usable(p: Path) -> Path | None:
        if p.is_file() and p.name == "px4" and p.parent.name == "bin":
            p = p.parent.parent
        return p if is_px4_dir(p) else None

    if cli_path:
        check_build_kind(Path(cli_path), "px4")
        p = usable(Path(cli_path))
        if p is None:
            raise UsageError(f"--sitl {cli_path}: no PX4 build there (a folder holding bin/px4 and etc/)")
        return p
    if arena is not None:
        configured = SITL.read(SITL.check(arena.section("sitl")), "px4_dir")
        if configured:
            q = Path(configured)
            q = q if q.is_absolute() else Path(arena.source).resolve().parent / q
            p = usable(q)
            if p is None:
                raise ConfigError(arena.source, "sitl.px4_dir", f"{configured!r}: no PX4 build at {q} (a folder "
                                  "holding bin/px4 and etc/ of a `make px4_sitl` build)")
            return p
    env = os.environ.get(PX4_ENV)
    if env:
        p = usable(Path(env))
        if p is None:
            raise UsageError(f"{PX4_ENV}={env}: no PX4 build there (a folder holding bin/px4 and etc/)")
        return p
    if is_px4_dir(SHARED_PX4_DIR):
        return SHARED_PX4_DIR
    raise UsageError(f"no PX4 SITL build: give --sitl DIR, set sitl.px4_dir in the arena file or {PX4_ENV}=DIR, DIR "
                     "holding bin/px4 and etc/ (PX4-Autopilot's build/px4_sitl_default after `make px4_sitl`)")


def default_px4_dir() -> Path | None:
    """$VISIONPOS_PX4_SITL or ../shared/sitl-px4/build when it is a PX4 build; None otherwise."""
    env = os.environ.get(PX4_ENV)
    p = Path(env) if env else SHARED_PX4_DIR
    return p if is_px4_dir(p) else None


def px4_parameters(message: str, ev_delay_ms: float, pos_noise_m: float, yaw_noise_rad: float,
                   sysid: int, headroom_ms: float = 0.0) -> dict[str, float]:
    """EKF2 for vision only (docs/autopilot-setup.md, PX4): EV position, height and yaw (and velocity with
    ODOMETRY), height reference vision, GPS and magnetometer off and not required, the message covariance with the
    noise floors lowered to motion-capture accuracy, the delay; MAV_SYS_ID the vehicle's sysid.
    - Barometer and range finder off (EKF2_BARO_CTRL 0, EKF2_RNG_CTRL 0): one on at boot becomes EKF2's height
      before the vision comes, and the vision's height then gets a bias following that sensor (PX4 SIH: the
      EKF 10-25 cm from the vision's height while fusing it).
    - The delayed horizon (EKF2_DELAY_MAX, default 200 ms; EKF2 raises it to the largest sensor delay, so the
      unused airspeed's and GPS's delays go to 0) just past the vision's delay (ekf2_arrival_horizon_ms; headroom_ms
      more where the delay is to be set again in flight), and the output
      predictor's time constants at their minimum (EKF2_TAU_POS, EKF2_TAU_VEL 0.1 s): the output is the
      delayed state carried forward on the IMU, and the less of the (vibrating) IMU it carries, the closer
      it stays to the vision (PX4 SIH hover: EKF horizontal p99 116 mm with the defaults, 31 mm with these).
    - The IMU noise EKF2 predicts with at SIH's (EKF2_ACC_NOISE 1.0 m/s^2, EKF2_GYR_NOISE 0.1 rad/s, both their
      maxima): SIH adds 0.5/1.7/1.4 m/s^2 and 0.14/0.07/0.03 rad/s of white noise in flight (sih.cpp), where the
      defaults (0.35, 0.015) suit a well-damped IMU. Told the IMU is better than it is, EKF2 corrects its tilt and
      velocity too little from the vision: horizontal p99 29-32 mm with the defaults (3 flights), 21-23 mm with
      these in 6 flights of 7, the seventh 32 mm from its 1 s vision cut (issue 31)."""
    return {
        "EKF2_EV_CTRL": 15.0 if message == "odometry" else 11.0, "EKF2_HGT_REF": 3.0, "EKF2_GPS_CTRL": 0.0,
        "SYS_HAS_GPS": 0.0, "SENS_EN_GPSSIM": 0.0, "EKF2_MAG_TYPE": 5.0, "SYS_HAS_MAG": 0.0,
        "EKF2_BARO_CTRL": 0.0, "EKF2_RNG_CTRL": 0.0, "EKF2_EV_DELAY": float(ev_delay_ms),
        "EKF2_DELAY_MAX": float(ekf2_arrival_horizon_ms(ev_delay_ms + headroom_ms)),
        "EKF2_ASP_DELAY": 0.0, "EKF2_GPS_DELAY": 0.0,
        "EKF2_TAU_POS": 0.1, "EKF2_TAU_VEL": 0.1,
        "EKF2_ACC_NOISE": SIH_ACC_NOISE_M_S2, "EKF2_GYR_NOISE": SIH_GYR_NOISE_RAD_S,
        "EKF2_EV_NOISE_MD": 0.0, "EKF2_EVP_NOISE": float(pos_noise_m), "EKF2_EVA_NOISE": float(yaw_noise_rad),
        "EKF2_EVV_NOISE": EV_VEL_NOISE_FLOOR_M_S,
        "MAV_SYS_ID": float(sysid),
    }


def px4_env(params: dict[str, float]) -> dict[str, str]:
    """PX4_PARAM_<NAME>=<value>: rcS applies them after the airframe's defaults and before ekf2 starts, so the
    reboot-required ones take effect too (../shared/sitl-px4/README.md). Whole numbers as integers (PX4's INT32)."""
    return {f"PX4_PARAM_{k}": (str(int(v)) if float(v).is_integer() else repr(float(v))) for k, v in params.items()}


def px4_ports(instance: int) -> dict[str, int]:
    return {"gcs": 18570 + instance, "onboard": 14580 + instance, "truth": 19410 + instance,
            "display": 19450 + instance}


def free_px4_instance() -> int:
    for i in range(1, 10):  # above 9 PX4's Onboard link sends to 14549 for every instance
        ports = [*px4_ports(i).values(), 14540 + i, 14280 + i, 13030 + i]
        if all(_udp_free(p) for p in ports):
            return i
    raise SitlError("no free PX4 SITL instance: the UDP ports of instances 1-9 are taken")


def _udp_free(port: int) -> bool:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        try:
            s.bind(("127.0.0.1", port))
        except OSError:
            return False
    return True


class Px4Process(ChildProcess):
    """PX4 SITL (SIH) in a fresh temporary working directory (parameters.bson, logs); close() kills it."""

    term_wait_s = 5.0

    def __init__(self, build: Path, instance: int, params: dict[str, float], home: tuple[float, ...],
                 model: str = "sihsim_quadx"):
        self.instance = instance
        self.log_timing: dict[str, Any] = {"error": "PX4 has not stopped yet"}
        env = dict(os.environ, PX4_SIM_MODEL=model, PX4_HOME_LAT=f"{home[0]:.7f}", PX4_HOME_LON=f"{home[1]:.7f}",
                   PX4_HOME_ALT=f"{home[2]:.2f}", **px4_env(params))
        self._start([str(build / "bin" / "px4"), "-i", str(instance), "-d", str(build / "etc")], "visionpos-px4-",
                    "px4.log", env)

    def before_removal(self) -> None:
        """EKF2's own timing from PX4's flight log (px4_log.py), once PX4 has stopped writing it."""
        from visionpos.app.sitl.px4_log import read_px4_log

        self.log_timing = read_px4_log(self.folder)

    def close(self) -> None:
        super().close()
        try:
            os.unlink(f"/tmp/px4-sock-{self.instance}")  # left behind by a killed px4
        except OSError:
            pass


def hil_state_as_sim_state(m: Any) -> Any:
    """HIL_STATE_QUATERNION (SIH's true state: degE7, mm, cm/s, q w-first, rad/s FRD) in SIM_STATE's fields, as
    TruthTrack.add reads them."""
    w, x, y, z = m.attitude_quaternion
    return types.SimpleNamespace(lat_int=m.lat, lon_int=m.lon, alt=m.alt * 1e-3, vn=m.vx * 1e-2, ve=m.vy * 1e-2,
                                 vd=m.vz * 1e-2, q1=w, q2=x, q3=y, q4=z, xgyro=m.rollspeed, ygyro=m.pitchspeed,
                                 zgyro=m.yawspeed)


class Px4Gcs(Gcs):
    """Our ground-station link to PX4's GCS port (udpout: we talk first), on Gcs's reader (texts, parameters, acks,
    LOCAL_POSITION_NED, ATTITUDE, heartbeats and modes), plus ESTIMATOR_STATUS into `ekf`, SIH's true state (the
    display link's HIL_STATE_QUATERNION) into the TruthTrack, and a keep-alive thread: the GCS HEARTBEAT PX4 needs
    to arm, MANUAL_CONTROL (centred sticks) while `manual`, and the offboard `setpoint` (N, E, D m; with
    `yaw_rate` rad/s and the `velocity` feed-forward where set) while set."""

    param_bytewise = True  # PX4 puts an integer parameter's bytes in PARAM_VALUE's float

    def __init__(self, ports: dict[str, int], truth: Any, on_text: Any = None):
        super().__init__(ports["gcs"], truth, on_text)
        self.ports = ports
        self.target = 0  # learned from PX4's first HEARTBEAT (MAV_SYS_ID)
        self.estimator: Any = None  # the newest ESTIMATOR_STATUS
        self.manual = False
        self.setpoint: tuple[float, float, float] | None = None
        self.yaw_rate: float | None = None  # rad/s with the setpoint (a yaw swing); None: PX4 holds its heading
        self.velocity: tuple[float, float, float] | None = None  # N, E, D m/s feed-forward with the setpoint
        self._keep = threading.Event()
        self._threads: list[threading.Thread] = []
        self._truth_sock: socket.socket | None = None
        self.clock_rates: list[tuple[int, float]] = []

    def connect(self, timeout_s: float = 30.0, proc: Any = None) -> None:
        from pymavlink import mavutil

        self._truth_sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._truth_sock.bind(("127.0.0.1", self.ports["truth"]))
        self._truth_sock.settimeout(0.1)
        self.conn = mavutil.mavlink_connection(f"udpout:127.0.0.1:{self.port}", source_system=255,
                                               source_component=190, dialect="common")
        self._stop.clear()
        self._keep.clear()
        self._threads = [threading.Thread(target=f, name=n, daemon=True) for f, n in
                         ((self._read, "px4-gcs"), (self._keepalive, "px4-keepalive"), (self._read_truth, "px4-truth"))]
        for t in self._threads:
            t.start()
        end = time.monotonic() + timeout_s
        while self.heartbeats == 0:
            if proc is not None and not proc.alive():
                raise SitlError(f"PX4 exited (code {proc.proc.returncode}):\n{proc.log_tail()}")
            if time.monotonic() > end:
                raise SitlError(f"no HEARTBEAT from PX4 on udp 127.0.0.1:{self.port} within {timeout_s:g} s"
                                + (f":\n{proc.log_tail()}" if proc is not None else ""))
            time.sleep(0.05)
        if self.autopilot_type != MAV_AUTOPILOT_PX4:
            raise SitlError(f"the autopilot on 127.0.0.1:{self.port} is not PX4 (HEARTBEAT autopilot "
                            f"{self.autopilot_type}{': ArduPilot' if self.autopilot_type == 3 else ''}); "
                            "--autopilot px4 flies PX4 only")
        self.request_streams()

    def close(self) -> None:
        self._keep.set()
        super().close()
        for t in self._threads:
            t.join(2.0)
        self._threads = []
        if self._truth_sock is not None:
            self._truth_sock.close()
            self._truth_sock = None

    def _handle(self, m: Any, now: int) -> None:
        kind = m.get_type()
        if kind == "TIMESYNC" and m.tc1 > 0:
            super()._handle(m, now)
            self._follow_clock()
            return
        if kind == "HEARTBEAT" and self.target == 0 and m.get_srcComponent() == 1 and m.autopilot != 8:
            self.target = m.get_srcSystem()  # 8: MAV_AUTOPILOT_INVALID (a companion, not the autopilot)
        if kind == "ESTIMATOR_STATUS":
            self.estimator = m
            self.ekf.append((now, m.flags, m.vel_ratio, m.pos_horiz_ratio, m.pos_vert_ratio, m.mag_ratio))
        super()._handle(m, now)

    def request_streams(self) -> None:
        # LOCAL_POSITION_NED asked for faster than EKF2 publishes: PX4 then sends each estimate as it comes, not
        # the newest one at 50 Hz (up to 20 ms old on arrival: the EKF would read as trailing the truth)
        for msg_id, rate in ((32, TRUTH_HZ), (30, 50.0), (230, 2.0)):  # LOCAL_POSITION_NED, ATTITUDE, ESTIMATOR_STATUS
            self.conn.mav.command_long_send(self.target, 1, 511, 0, msg_id, 1e6 / rate, 0, 0, 0, 0, 0)
        self._ask_truth_rate()

    def _ask_truth_rate(self) -> None:
        """HIL_STATE_QUATERNION (115) at TRUTH_HZ on the display link: the command goes to that link's own port."""
        from pymavlink.dialects.v20 import common as mavlink2

        sock, port = self._truth_sock, self.ports.get("display")
        if sock is None or port is None or not self.target:
            return
        mav = mavlink2.MAVLink(None, srcSystem=255, srcComponent=190)
        msg = mav.command_long_encode(self.target, 1, 511, 0, 115, 1e6 / TRUTH_HZ, 0, 0, 0, 0, 0)
        try:
            sock.sendto(msg.pack(mav), ("127.0.0.1", port))
        except OSError:
            pass

    def truth_rate_hz(self) -> float:
        """HIL_STATE_QUATERNION per second over the newest second of the truth (0 before two samples)."""
        t, _ = self.truth.snapshot()
        if len(t) < 2:
            return 0.0
        recent = t[t >= t[-1] - 1_000_000_000]
        span = (recent[-1] - recent[0]) * 1e-9
        return (len(recent) - 1) / span if span > 0 else 0.0

    def _follow_clock(self) -> None:
        """PX4's clock rate against ours (clock_rate over CLOCK_RATE_WINDOW_NS of the GCS link's TIMESYNC
        answers) into the TruthTrack, and each estimate into `clock_rates` (our ns, rate)."""
        rate = clock_rate(np.array(self.clock.timesync[-CLOCK_RATE_PAIRS:], dtype=np.int64).reshape(-1, 2),
                          CLOCK_RATE_WINDOW_NS, CLOCK_RATE_MIN_SPAN_NS)
        if rate is not None and CLOCK_RATE_BOUNDS[0] < rate < CLOCK_RATE_BOUNDS[1]:
            self.truth.rate = rate
            self.clock_rates.append((time.monotonic_ns(), rate))

    def _keepalive(self) -> None:
        next_hb = next_manual = next_sp = 0.0
        while not self._keep.is_set():
            now = time.monotonic()
            try:
                if now >= next_hb:
                    next_hb = now + 1.0 / GCS_HEARTBEAT_HZ
                    self.conn.mav.heartbeat_send(6, 8, 0, 0, 4)  # MAV_TYPE_GCS, MAV_AUTOPILOT_INVALID, ACTIVE
                    if self.truth_rate_hz() < TRUTH_MIN_HZ:
                        self._ask_truth_rate()
                if self.manual and now >= next_manual and self.target:
                    next_manual = now + 1.0 / MANUAL_HZ
                    self.conn.mav.manual_control_send(self.target, 0, 0, 500, 0, 0)  # centred: hold
                sp, rate, vel = self.setpoint, self.yaw_rate, self.velocity
                if sp is not None and now >= next_sp and self.target:
                    next_sp = now + 1.0 / SETPOINT_HZ
                    mask = 0b0000_1111_1111_1000 if rate is None else 0b0000_0101_1111_1000  # position (+ yaw rate)
                    mask &= ~0b111_000 if vel is not None else ~0  # + the velocity feed-forward
                    self.conn.mav.set_position_target_local_ned_send(0, self.target, 1, 1, mask, *sp,
                                                                     *(vel or (0, 0, 0)), 0, 0, 0, 0, rate or 0.0)
            except OSError:
                return
            time.sleep(0.01)

    def _read_truth(self) -> None:
        from pymavlink.dialects.v20 import common as mavlink2

        parser = mavlink2.MAVLink(None)
        parser.robust_parsing = True
        while not self._keep.is_set() and self._truth_sock is not None:
            try:
                data = self._truth_sock.recv(65535)
            except (socket.timeout, OSError):
                continue
            now = time.monotonic_ns()
            for m in parser.parse_buffer(data) or []:
                if m.get_type() == "HIL_STATE_QUATERNION":
                    self.truth.add(now, hil_state_as_sim_state(m))

    # -- the set-up's steps
    def check_params(self, params: dict[str, float], timeout_s: float = 6.0) -> None:
        """Read each parameter back (PARAM_REQUEST_READ): PX4 must have it, at the value given at start. Which one
        and why, in one SitlError, otherwise."""
        self.params.clear()
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            missing = [k for k in params if k not in self.params]
            if not missing:
                break
            for k in missing:
                self.conn.mav.param_request_read_send(self.target, 1, k.encode(), -1)
            again = time.monotonic() + 0.5  # ask again for those still missing after this
            while time.monotonic() < again and any(k not in self.params for k in missing):
                time.sleep(0.02)
        missing = [k for k in params if k not in self.params]
        if missing:
            raise SitlError(f"PX4 did not answer for {', '.join(missing)}: this firmware has no such parameter "
                            "(an older PX4?); docs/autopilot-setup.md lists what the vision-only set-up needs")
        wrong = [f"{k} = {self.params[k]:g}, not {v:g}" for k, v in params.items()
                 if abs(self.params[k] - v) > 1e-4 * max(1.0, abs(v))]
        if wrong:
            raise SitlError("PX4 rejected parameters given at start: it has " + "; ".join(wrong)
                            + " (out of its range, or renamed in this firmware)")

    def ev_fused(self) -> bool:
        m = self.estimator
        return m is not None and bool(m.flags & ESTIMATOR_POS_HORIZ_REL)
