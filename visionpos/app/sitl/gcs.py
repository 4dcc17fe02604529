"""Our ground-station link to SITL's SERIAL0: a reader thread keeping what SITL reports (its true pose into
a TruthTrack, its clock into a SitlClock, telemetry, texts, acks), parameters and commands.
"""

from __future__ import annotations

import asyncio
import threading
import time
from typing import Any, Callable

from bridge.convert import param_from_wire
from visionpos.app.sitl.clock import SitlClock
from visionpos.app.sitl.process import SitlProcess
from visionpos.app.sitl.settings import SitlError
from visionpos.app.sitl.truth import TruthTrack

# mavlink ids used here (ardupilotmega dialect)
MAV_CMD_SET_MESSAGE_INTERVAL = 511
MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN = 246
MAV_CMD_DO_SET_HOME = 179
MAV_CMD_DO_SET_MODE = 176
MAV_CMD_COMPONENT_ARM_DISARM = 400
MAV_CMD_NAV_TAKEOFF = 22
MAV_CMD_REQUEST_MESSAGE = 512
MAV_FRAME_GLOBAL = 0
MSG_HOME_POSITION = 242
MSG_SIM_STATE = 108
MSG_SYSTEM_TIME = 2
MSG_RAW_IMU = 27
COPTER_MODES = {"STABILIZE": 0, "GUIDED": 4, "LOITER": 5, "RTL": 6, "LAND": 9}
MODE_NAMES = {v: k for k, v in COPTER_MODES.items()}

TRUTH_RATE_HZ = 100.0
TELEMETRY_RATE_HZ = 50.0
EXTNAV_TEXT = "is using external nav data"


class Gcs:
    """Our ground-station link to SITL's SERIAL0 (tcp), with a reader thread keeping what SITL reports.

    Every record carries its arrival time on the server clock (time.monotonic_ns)."""

    param_bytewise = False  # ArduPilot casts integer parameters into PARAM_VALUE's float (bridge/convert.py)

    def __init__(self, port: int, truth: TruthTrack, on_text: Callable[[str], None] | None = None):
        self.port = port
        self.truth = truth
        self.on_text = on_text
        self.conn: Any = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.params: dict[str, float] = {}
        self.acks: dict[int, tuple[int, int]] = {}  # command -> (result, recv_ns)
        self.texts: list[tuple[int, int, str]] = []
        self.local: list[tuple[int, float, float, float]] = []
        self.attitude: list[tuple[int, float, float, float]] = []
        self.ekf: list[tuple[int, int, float, float, float, float]] = []  # flags, vel, pos_h, pos_v, compass ratios
        self.armed = False
        self.mode = -1
        self.modes: list[tuple[int, int]] = []  # (recv_ns, custom_mode) at each change
        self.origin: tuple[int, Any] | None = None
        self.home: tuple[int, Any] | None = None  # (recv_ns, HOME_POSITION)
        self.heartbeats = 0
        self.autopilot_type: int | None = None  # HEARTBEAT.autopilot (MAV_AUTOPILOT_*)
        self.target = 1  # the autopilot's sysid
        self.clock = SitlClock()

    # -- connection
    def connect(self, timeout_s: float = 30.0, proc: SitlProcess | None = None) -> None:
        from pymavlink import mavutil

        end = time.monotonic() + timeout_s
        last: Exception | None = None
        while time.monotonic() < end:
            if proc is not None and not proc.alive():
                raise SitlError(f"SITL exited (code {proc.proc.returncode}):\n{proc.log_tail()}")
            try:
                self.conn = mavutil.mavlink_connection(f"tcp:127.0.0.1:{self.port}", source_system=255,
                                                       source_component=190, dialect="ardupilotmega",
                                                       retries=0, autoreconnect=False)
                break
            except (OSError, ConnectionError) as e:
                last = e
                time.sleep(0.3)
        else:
            raise SitlError(f"could not connect to SITL on tcp:127.0.0.1:{self.port} within {timeout_s:g} s "
                            f"({last})" + (f":\n{proc.log_tail()}" if proc is not None else ""))
        self.heartbeats = 0
        self._stop.clear()
        self._thread = threading.Thread(target=self._read, name="sitl-gcs", daemon=True)
        self._thread.start()
        self.wait(lambda: self.heartbeats > 0, timeout_s, "a HEARTBEAT from SITL")
        self.request_streams()

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(2.0)
            self._thread = None
        if self.conn is not None:
            try:
                self.conn.close()
            except OSError:
                pass
            self.conn = None

    def _read(self) -> None:
        conn = self.conn
        next_ts = 0
        while not self._stop.is_set():
            try:
                if time.monotonic_ns() >= next_ts:
                    next_ts = time.monotonic_ns() + SitlClock.TIMESYNC_EVERY_NS
                    s1 = time.monotonic_ns()
                    self.clock.pending[s1] = s1  # ts1 is our send time: SITL echoes it
                    if len(self.clock.pending) > 64:
                        self.clock.pending.pop(next(iter(self.clock.pending)))
                    conn.mav.timesync_send(0, s1)
                msg = conn.recv_match(blocking=True, timeout=0.1)
            except (OSError, ConnectionError):
                return  # SITL rebooted or exited; connect() again
            if msg is not None:
                self._handle(msg, time.monotonic_ns())

    def _handle(self, m: Any, now: int) -> None:
        kind = m.get_type()
        if kind == "SIM_STATE":
            self.truth.add(now, m)
            self.clock.on_sim_state(now)
        elif kind == "RAW_IMU":
            self.clock.on_raw_imu(now, m.time_usec)
        elif kind == "SYSTEM_TIME":
            self.clock.on_system_time(now, m.time_boot_ms)
        elif kind == "TIMESYNC":
            self.clock.on_timesync(m.tc1, m.ts1)
        elif kind == "LOCAL_POSITION_NED":
            self.local.append((now, m.x, m.y, m.z))
        elif kind == "ATTITUDE":
            self.attitude.append((now, m.roll, m.pitch, m.yaw))
        elif kind == "EKF_STATUS_REPORT":
            self.ekf.append((now, m.flags, m.velocity_variance, m.pos_horiz_variance, m.pos_vert_variance,
                             m.compass_variance))
        elif kind == "STATUSTEXT":
            self.texts.append((now, m.severity, m.text))
            if self.on_text is not None:
                self.on_text(m.text)
        elif kind == "HEARTBEAT" and m.get_srcSystem() == self.target and m.get_srcComponent() == 1:
            self.heartbeats += 1
            self.autopilot_type = m.autopilot
            self.armed = bool(m.base_mode & 128)
            if m.custom_mode != self.mode:
                self.mode = m.custom_mode
                self.modes.append((now, m.custom_mode))
        elif kind == "PARAM_VALUE":
            self.params[m.param_id] = param_from_wire(m.param_value, m.param_type, self.param_bytewise)
        elif kind == "COMMAND_ACK":
            self.acks[m.command] = (m.result, now)
        elif kind == "GPS_GLOBAL_ORIGIN":
            self.origin = (now, m)
        elif kind == "HOME_POSITION":
            self.home = (now, m)

    def request_streams(self) -> None:
        # SYSTEM_TIME and RAW_IMU at SIM_STATE's rate share its message bucket: they stamp it (SitlClock)
        for msg_id, rate in ((MSG_SIM_STATE, TRUTH_RATE_HZ), (MSG_SYSTEM_TIME, TRUTH_RATE_HZ),
                             (MSG_RAW_IMU, TRUTH_RATE_HZ), (32, TELEMETRY_RATE_HZ), (30, TELEMETRY_RATE_HZ),
                             (193, 10.0), (49, 1.0)):  # LOCAL_POSITION_NED, ATTITUDE, EKF_STATUS_REPORT, ORIGIN
            self.conn.mav.command_long_send(self.target, 1, MAV_CMD_SET_MESSAGE_INTERVAL, 0, msg_id, 1e6 / rate,
                                            0, 0, 0, 0, 0)

    # -- waiting (blocking and async)
    @staticmethod
    def wait(cond: Callable[[], bool], timeout_s: float, what: str) -> None:
        end = time.monotonic() + timeout_s
        while not cond():
            if time.monotonic() > end:
                raise SitlError(f"no {what} within {timeout_s:g} s")
            time.sleep(0.02)

    @staticmethod
    async def until(cond: Callable[[], bool], timeout_s: float, what: str) -> None:
        end = time.monotonic() + timeout_s
        while not cond():
            if time.monotonic() > end:
                raise SitlError(f"no {what} within {timeout_s:g} s")
            await asyncio.sleep(0.02)

    # -- parameters and commands
    def send_param(self, name: str, value: float) -> None:
        from pymavlink import mavutil

        self.params.pop(name, None)
        self.conn.mav.param_set_send(self.target, 1, name.encode(), float(value), mavutil.mavlink.MAV_PARAM_TYPE_REAL32)

    def param_confirmed(self, name: str, value: float) -> bool:
        got = self.params.get(name)
        if got is None:
            return False
        if abs(got - value) > 1e-4 * max(1.0, abs(value)):
            raise SitlError(f"SITL set {name} to {got:g}, not {value:g} (out of its range?)")
        return True

    def set_params(self, values: dict[str, float], timeout_s: float = 5.0) -> None:
        """PARAM_SET each, then read back: every PARAM_VALUE must echo the value."""
        for name, value in values.items():
            for attempt in range(3):
                self.send_param(name, value)
                try:
                    self.wait(lambda: self.param_confirmed(name, value), timeout_s / 3, f"PARAM_VALUE for {name}")
                    break
                except SitlError:
                    if attempt == 2:
                        raise SitlError(f"SITL did not confirm {name} = {value:g}: it has no such parameter, or "
                                        "it did not answer") from None

    async def set_params_async(self, values: dict[str, float], timeout_s: float = 5.0) -> None:
        for name, value in values.items():
            self.send_param(name, value)
            await self.until(lambda: self.param_confirmed(name, value), timeout_s, f"PARAM_VALUE for {name}")

    def command(self, cmd: int, *params: float) -> None:
        self.acks.pop(cmd, None)
        p = list(params) + [0.0] * (7 - len(params))
        self.conn.mav.command_long_send(self.target, 1, cmd, 0, *p)

    def command_int(self, cmd: int, lat_deg: float, lon_deg: float, alt_m: float, *params: float,
                    frame: int = MAV_FRAME_GLOBAL) -> None:
        """A command with a position as COMMAND_INT: latitude and longitude as int32 degE7 (1.1 cm). COMMAND_LONG's
        float32 parameters keep 24 bits: ~1e-5 deg at 149 deg, a home half a metre off."""
        self.acks.pop(cmd, None)
        p = list(params) + [0.0] * (4 - len(params))
        self.conn.mav.command_int_send(self.target, 1, frame, cmd, 0, 0, *p, int(round(lat_deg * 1e7)),
                                       int(round(lon_deg * 1e7)), float(alt_m))

    async def command_async(self, cmd: int, *params: float, timeout_s: float = 5.0, what: str = "") -> None:
        self.command(cmd, *params)
        await self.until(lambda: cmd in self.acks, timeout_s, f"COMMAND_ACK for {what or cmd}")
        result = self.acks[cmd][0]
        if result != 0:
            raise SitlError(f"SITL refused {what or cmd} (MAV_RESULT {result}); last messages: "
                            + "; ".join(t for _, _, t in self.texts[-5:]))

    def ekf_using_vision(self) -> bool:
        return any(EXTNAV_TEXT in t for _, _, t in self.texts)


# ---------------------------------------------------------------- the run
