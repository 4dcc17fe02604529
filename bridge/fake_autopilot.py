"""A simulated autopilot on a MAVLink link, for tests, benchmarks and `visionpos demo`.

It plays the vehicle's side of one bridge endpoint:
- endpoint 'udpout:HOST:PORT' sends to the bridge's udpin port (the usual
  "point the autopilot at the MAVLink port" set-up);
- 'udpin:HOST:PORT' listens for a bridge configured with udpout (port 0
  picks a free port: read .port after start());
- 'tcpin:HOST:PORT' listens for a bridge configured with tcp.
It sends HEARTBEAT as an autopilot and TIMESYNC requests (like PX4), answers
TIMESYNC requests with its boot clock at the packet's arrival (like ArduPilot),
signs and verifies MAVLink2 signatures when given a key, and records every
VISION_POSITION_ESTIMATE, ODOMETRY and VISION_SPEED_ESTIMATE with its
receive time. report() says what an EKF would see.

Given the vehicle's true motion (`truth`, e.g. `trajectory_truth` of a
simulated body), it also plays the autopilot's sensors and EKF on the streams
asked for with SET_MESSAGE_INTERVAL (or `telemetry_hz` from the start):
ATTITUDE, ATTITUDE_QUATERNION, HIGHRES_IMU (gyro from the true body rate, accel
from the true acceleration less gravity, FRD), RAW_IMU (ArduPilot's mrad/s and
mG), LOCAL_POSITION_NED and EKF_STATUS_REPORT, stamped on its own boot clock.
It keeps an origin set with SET_GPS_GLOBAL_ORIGIN (once `origin_ready_s` after
boot: an EKF not yet running drops it, as ArduPilot's does) and reports it
(GPS_GLOBAL_ORIGIN, also on MAV_CMD_REQUEST_MESSAGE); takes MAV_CMD_DO_SET_HOME
(refused before the origin, as ArduPilot does; ArduPilot ignores
SET_HOME_POSITION) and keeps it as it gets it (COMMAND_INT's int32 degE7; COMMAND_LONG's
float32 degrees, rounded as they came), reporting it with HOME_POSITION (on a change and on
request); answers PARAM_SET and PARAM_REQUEST_READ with PARAM_VALUE; says "EKF3 IMU0 is
using external nav data" on its first accepted pose (STATUSTEXT). delay_ms
holds every received packet that long before handling it (a slow link or
autopilot: the pose reaches its EKF that much later); reboot() restarts its
clock and forgets origin, home and streams. gyro_filter_hz plays ArduPilot's
INS_GYRO_FILTER (reported as that parameter): the gyro and the ATTITUDE rates it
sends trail the motion by the group delay of that 2-pole low-pass. Its IMU (imu_reading) adds white noise
(gyro_noise_rad_s, accel_noise_m_s2 per sample) and constant biases drawn from `seed` (the gyro's with std
gyro_noise_rad_s, the accelerometer's with std accel_bias_m_s2, none by default) to the truth's.

    with FakeAutopilot("udpout:127.0.0.1:14561", sysid=1) as ap:
        ...
        print(ap.report())
"""

from __future__ import annotations

import collections
import math
import selectors
import socket
import threading
import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mavlink2  # common + EKF_STATUS_REPORT
from scipy.spatial.transform import Rotation

from bridge.convert import param_from_wire, param_to_wire
from bridge.fake_px4 import (
    FLAGS_ATTITUDE_ONLY,
    FLAGS_EV_FUSED,
    POSE_FRESH_NS,
    PX4_INT_PARAMS,
    PX4_PARAMS,
    Px4State,
    pose_refusal,
)
from visionpos.geometry.frames import quat_world_body_to_ned_frd
from visionpos.server.netstamps import ANC_SIZE, enable_kernel_stamps, kernel_stamp_ns

POSE_TYPES = ("VISION_POSITION_ESTIMATE", "ODOMETRY")
RECORDED = POSE_TYPES + ("VISION_SPEED_ESTIMATE", "HEARTBEAT", "TIMESYNC", "SET_GPS_GLOBAL_ORIGIN", "SET_HOME_POSITION",
                         "COMMAND_LONG", "COMMAND_INT", "PARAM_SET", "STATUSTEXT", "SET_POSITION_TARGET_LOCAL_NED")
AUTOPILOTS = {"ardupilot": mavlink2.MAV_AUTOPILOT_ARDUPILOTMEGA, "px4": mavlink2.MAV_AUTOPILOT_PX4}
SIGNING_EPOCH_S = 1420070400
GRAVITY = 9.80665
TELEMETRY = {30: "ATTITUDE", 31: "ATTITUDE_QUATERNION", 105: "HIGHRES_IMU", 27: "RAW_IMU", 32: "LOCAL_POSITION_NED",
             193: "EKF_STATUS_REPORT", 230: "ESTIMATOR_STATUS"}
EKF_USING_VISION = 1 | 2 | 4 | 8 | 32  # attitude, velocities, relative horizontal and vertical position
EKF_NO_POSITION = 1 | 128  # attitude only, constant position mode
EXT_NAV_TEXT = "EKF3 IMU0 is using external nav data"
MAV_CMD_DO_SET_HOME = 179
MAV_CMD_SET_MESSAGE_INTERVAL = 511
MAV_CMD_REQUEST_MESSAGE = 512
MSG_GPS_GLOBAL_ORIGIN = 49
MSG_HOME_POSITION = 242


@dataclass(frozen=True)
class Truth:
    """A vehicle's true motion at some times: position (T, 3) m world z-up, quaternion (T, 4) xyzw body FLU ->
    world, velocity (T, 3) m/s world, angular_velocity (T, 3) rad/s body FLU, acceleration (T, 3) m/s^2 world."""

    position: np.ndarray
    quaternion: np.ndarray
    velocity: np.ndarray
    angular_velocity: np.ndarray
    acceleration: np.ndarray


TRUTH_GRID_NS = 1_000_000  # trajectory_truth's grid for single times
TRUTH_CHUNK = 256  # grid samples per call of the trajectory (a quarter second)
TRUTH_LEAD = 32  # of them before the asked time (the filtered gyro asks a little into the past)


def trajectory_truth(trajectory, start_ns: int) -> Callable[[np.ndarray], Truth]:
    """A `truth` for FakeAutopilot from a visionpos.sim trajectory whose time 0 is start_ns on the server clock.

    Several times are sampled exactly. A single time (the autopilot's telemetry asks for one per wake-up) comes
    from a chunk of TRUTH_CHUNK samples every TRUTH_GRID_NS, made in one call of the trajectory, interpolated:
    linearly, the attitude by normalised lerp. A call costs about a millisecond of Python whatever its length,
    held on the GIL that the server's loop shares in the demo; the interpolation is off by a * h^2 / 8 (1 um at
    8 m/s^2) in position and by less than the IMU's noise in the rates.
    """
    chunk: list = [None, None]  # [grid start ns, Truth on the grid]

    def exact(times_ns: np.ndarray) -> Truth:
        t = (np.asarray(times_ns, dtype=np.int64) - np.int64(start_ns)).astype(np.float64) * 1e-9
        m = trajectory(t)
        _, _, acc = trajectory.kinematics(t)
        return Truth(m.positions, m.quaternions, m.velocities, m.angular_velocities, acc)

    def truth(times_ns: np.ndarray) -> Truth:
        times_ns = np.asarray(times_ns, dtype=np.int64).reshape(-1)
        if len(times_ns) != 1:
            return exact(times_ns)
        t = int(times_ns[0])
        g0, grid = chunk
        if g0 is None or not g0 <= t < g0 + (TRUTH_CHUNK - 1) * TRUTH_GRID_NS:
            g0 = start_ns + ((t - start_ns) // TRUTH_GRID_NS - TRUTH_LEAD) * TRUTH_GRID_NS
            grid = exact(g0 + np.arange(TRUTH_CHUNK, dtype=np.int64) * TRUTH_GRID_NS)
            chunk[:] = [g0, grid]
        k, rem = divmod(t - g0, TRUTH_GRID_NS)
        a = rem / TRUTH_GRID_NS
        lerp = lambda x: (x[k] * (1.0 - a) + x[k + 1] * a)[None]  # noqa: E731
        q0, q1 = grid.quaternion[k], grid.quaternion[k + 1]
        q = q0 * (1.0 - a) + (q1 if q0 @ q1 >= 0 else -q1) * a
        return Truth(lerp(grid.position), (q / np.linalg.norm(q))[None], lerp(grid.velocity),
                     lerp(grid.angular_velocity), lerp(grid.acceleration))

    return truth


def imu_from_truth(tr: Truth) -> tuple[np.ndarray, np.ndarray]:
    """What a perfect IMU reads: gyro (T, 3) rad/s FRD and accelerometer (T, 3) m/s^2 FRD (specific force:
    the acceleration less gravity, so a vehicle at rest reads -g on z down)."""
    R = Rotation.from_quat(tr.quaternion)
    f_world = np.asarray(tr.acceleration, float) + np.array([0.0, 0.0, GRAVITY])
    f_flu = R.inv().apply(f_world)
    flip = np.array([1.0, -1.0, -1.0])
    return np.asarray(tr.angular_velocity, float) * flip, f_flu * flip


def imu_reading(gyro_frd: np.ndarray, accel_frd: np.ndarray, gyro_bias: np.ndarray, accel_bias: np.ndarray,
                gyro_noise_rad_s: float, accel_noise_m_s2: float,
                rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """What a MEMS IMU reads of the perfect readings (imu_from_truth's, (T, 3) FRD): each plus its constant bias
    (3,) and white noise of the given std per axis and sample, drawn from rng (gyro first, then accel)."""
    g = gyro_frd + gyro_bias + rng.normal(0.0, gyro_noise_rad_s, np.shape(gyro_frd))
    return g, accel_frd + accel_bias + rng.normal(0.0, accel_noise_m_s2, np.shape(accel_frd))


@dataclass
class Received:
    """One message as the autopilot got it. fields: msg.to_dict() (incl. 'mavpackettype')."""

    type: str
    recv_ns: int
    src_system: int
    src_component: int
    signed: bool
    fields: dict = field(default_factory=dict)


def decode_pose(r: Received) -> dict:
    """What an EKF reads from one pose message.

    Returns usec, position_ned (3,), euler (3,) roll pitch yaw rad,
    quaternion_ned_frd (4,) xyzw, reset_counter; ODOMETRY adds
    velocity_frd (3,), angular_velocity_frd (3,).
    """
    f = r.fields
    if r.type == "VISION_POSITION_ESTIMATE":
        euler = np.array([f["roll"], f["pitch"], f["yaw"]])
        q = Rotation.from_euler("ZYX", euler[::-1]).as_quat()
        return dict(usec=f["usec"], position_ned=np.array([f["x"], f["y"], f["z"]]), euler=euler,
                    quaternion_ned_frd=q, reset_counter=f.get("reset_counter", 0))
    if r.type == "ODOMETRY":
        w, x, y, z = f["q"]
        q = np.array([x, y, z, w])
        euler = Rotation.from_quat(q).as_euler("ZYX")[::-1]
        return dict(usec=f["time_usec"], position_ned=np.array([f["x"], f["y"], f["z"]]), euler=euler,
                    quaternion_ned_frd=q, reset_counter=f["reset_counter"],
                    velocity_frd=np.array([f["vx"], f["vy"], f["vz"]]),
                    angular_velocity_frd=np.array([f["rollspeed"], f["pitchspeed"], f["yawspeed"]]))
    raise ValueError(f"{r.type} is not a pose message")


class FakeAutopilot:
    """Simulated autopilot (sysid, component 1) on one link; see the module docstring.

    signing_key: 32 bytes; when set, everything it sends is signed and
    anything unsigned or signed with another key is rejected (counted in
    rejected_signature, not recorded). duration_s: stop by itself after it.
    source_port (udpout): send from this local port (0: any free one), e.g. the
    port a bridge's `autopilot_address` names.
    """

    def __init__(self, endpoint: str, sysid: int = 1, *, autopilot: str = "ardupilot",
                 signing_key: bytes | None = None, heartbeat_hz: float = 1.0, timesync_hz: float = 1.0,
                 duration_s: float | None = None, clock_ns=time.monotonic_ns, source_port: int = 0,
                 truth: Callable[[np.ndarray], Truth] | None = None, telemetry_hz: float = 0.0,
                 delay_ms: float = 0.0, boot_ns: int | None = None, origin_ready_s: float = 0.0,
                 ekf: str = "accept", gyro_noise_rad_s: float = 0.003, attitude_noise_deg: float = 0.2,
                 seed: int | None = None, gyro_filter_hz: float = 0.0, keep_received: int | None = None,
                 on_pose: Callable[[Received], None] | None = None, reject_params: tuple[str, ...] = (),
                 accel_noise_m_s2: float = 0.02, accel_bias_m_s2: float = 0.0):
        kind, _, rest = endpoint.partition(":")
        host, _, port = rest.rpartition(":")
        if kind not in ("udpout", "udpin", "tcpin") or not host or not port.isdigit():
            raise ValueError(
                f"fake autopilot endpoint {endpoint!r}: use udpout:HOST:PORT, udpin:HOST:PORT or tcpin:HOST:PORT"
            )
        if autopilot not in AUTOPILOTS:
            raise ValueError(f"autopilot {autopilot!r}: one of {sorted(AUTOPILOTS)}")
        self.kind, self.host, self.port = kind, host, int(port)
        self.sysid = sysid
        self.autopilot = autopilot
        self.clock_ns = clock_ns
        self.heartbeat_hz, self.timesync_hz = heartbeat_hz, timesync_hz
        self.duration_s = duration_s
        self.source_port = source_port
        self.mav = mavlink2.MAVLink(self, srcSystem=sysid, srcComponent=1)
        self.mav.robust_parsing = True
        if signing_key is not None:
            s = self.mav.signing
            s.secret_key, s.sign_outgoing, s.link_id = signing_key, True, 1
            s.allow_unsigned_callback = None
            s.timestamp = int((time.time() - SIGNING_EPOCH_S) * 1e5)
        if ekf not in ("accept", "reject"):
            raise ValueError(f"ekf {ekf!r}: 'accept' or 'reject'")
        self.truth = truth
        self.delay_ns = int(round(delay_ms * 1e6))
        self.boot_ns = boot_ns  # server-clock time of its boot (None: at start())
        self.origin_ready_ns = int(origin_ready_s * 1e9)
        self.ekf = ekf
        self.gyro_noise = gyro_noise_rad_s
        self.attitude_noise = math.radians(attitude_noise_deg)
        self.rng = np.random.default_rng(sysid if seed is None else seed)
        self.gyro_bias = self.rng.normal(0.0, gyro_noise_rad_s, 3)
        # the accelerometer's bias, drawn (std accel_bias_m_s2 per axis) only when asked for: the draws after it move
        self.accel_bias = self.rng.normal(0.0, accel_bias_m_s2, 3) if accel_bias_m_s2 > 0 else np.zeros(3)
        self.accel_noise = accel_noise_m_s2
        self._telemetry_default_ns = int(1e9 / telemetry_hz) if telemetry_hz > 0 else 0
        self.intervals_ns: dict[int, int] = {}  # message id -> interval (SET_MESSAGE_INTERVAL)
        self._next_tx: dict[int, int] = {}
        self.origin: tuple[int, int, int] | None = None  # lat, lon (1e7 deg), alt (mm)
        self.origin_dropped = 0  # SET_GPS_GLOBAL_ORIGIN before origin_ready_s: dropped
        # home as it keeps it: lat, lon (int32 degE7, as COMMAND_INT carries them; COMMAND_LONG's float32 params
        # rounded to the nearest degE7), alt (m)
        self.home: tuple[int, int, float] | None = None
        self.params: dict[str, float] = {"INS_GYRO_FILTER": float(gyro_filter_hz)} if autopilot == "ardupilot" else {}
        # as PX4 (bridge/fake_px4.py): its pose rules, its commander, its parameters; reject_params go unanswered
        self.px4 = Px4State() if autopilot == "px4" else None
        if self.px4 is not None:
            self.params = {k: v for k, v in PX4_PARAMS.items() if k not in reject_params}
        self.dropped_poses: collections.deque[str] = collections.deque(maxlen=100)  # PX4: why each was not fused
        # the filter's group delay at low frequency, sqrt(2) / (2 pi fc) (no filter: 0)
        self.gyro_lag_ns = int(math.sqrt(2.0) / (2.0 * math.pi * gyro_filter_hz) * 1e9) if gyro_filter_hz > 0 else 0
        self.statustexts: list[str] = []
        self.timesync_requests_answered = 0
        self._said_ext_nav = False
        self._last_pose_ns = 0
        self._pending: collections.deque[tuple[int, bytes]] = collections.deque()  # (due ns, datagram)
        self._kernel_stamps = False
        # every recorded message (keep_received: only the newest that many, for a long run's bounded memory)
        self.received: list[Received] | collections.deque[Received] = (
            [] if keep_received is None else collections.deque(maxlen=keep_received))
        self.on_pose = on_pose  # called from this autopilot's thread with each pose message
        self.timesync_samples: list[tuple[int, int]] = []  # (rtt_ns, offset_ns: bridge clock - ours)
        self.rejected_signature = 0
        self.bad_packets = 0
        self.sent = 0
        self._sock: socket.socket | None = None
        self._listen: socket.socket | None = None
        self._peer = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._ts_sent: set[int] = set()

    # ------------------------------------------------------------ lifecycle
    def start(self) -> "FakeAutopilot":
        if self.boot_ns is None:
            self.boot_ns = self.clock_ns()
        self._reset_streams()
        if self.kind == "tcpin":
            ls = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            ls.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            ls.bind((self.host, self.port))
            ls.listen(1)
            ls.setblocking(False)
            self.port = ls.getsockname()[1]
            self._listen = ls
        else:
            s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            if self.kind == "udpin":
                s.bind((self.host, self.port))
                self.port = s.getsockname()[1]
            else:
                s.bind(("127.0.0.1" if self.host.startswith("127.") else "0.0.0.0", self.source_port))
                self._peer = (socket.gethostbyname(self.host), self.port)
            s.setblocking(False)
            self._sock = s
            # arrival on the kernel's stamp (as ArduPilot stamps a packet's first byte): a busy test machine
            # then delays when we get round to a packet, not when it counts as arrived
            self._kernel_stamps = self.clock_ns is time.monotonic_ns and enable_kernel_stamps(s)
        self._thread = threading.Thread(target=self._run, name=f"fake-autopilot-{self.sysid}", daemon=True)
        self._thread.start()
        return self

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(2.0)
            self._thread = None
        for s in (self._sock, self._listen):
            if s is not None:
                s.close()
        self._sock = self._listen = None

    def boot_time_ns(self, now_ns: int | None = None) -> int:
        """Its own clock: ns since its boot. Never negative: reboot() from another thread can move the boot past a
        `now` its loop took just before (which once sent a negative time_boot_ms and killed the loop)."""
        return max(0, (self.clock_ns() if now_ns is None else now_ns) - self.boot_ns)

    def reboot(self) -> None:
        """Restart its clock; forget the origin, home and the streams asked for (as a real reboot does)."""
        self.boot_ns = self.clock_ns()
        self.origin = None
        self.home = None
        self._said_ext_nav = False
        self._reset_streams()

    def _reset_streams(self) -> None:
        self.intervals_ns = {}
        if self._telemetry_default_ns:
            for mid in TELEMETRY:
                self.intervals_ns[mid] = self._telemetry_default_ns if mid not in (193, 230) else 500_000_000
        self._next_tx = {}

    def true_delay_ms(self, window_s: float | None = None, percentile: float = 50.0) -> float:
        """Median (or that percentile of the) delay from a pose's stamp to its arrival here, with the added delay
        (the stamps are on the server clock); over the poses of the last window_s seconds (None: all)."""
        poses = self.messages(POSE_TYPES)
        if window_s is not None and poses:
            poses = [p for p in poses if p.recv_ns >= poses[-1].recv_ns - window_s * 1e9]
        if not poses:
            return float("nan")
        return float(np.percentile([p.recv_ns - decode_pose(p)["usec"] * 1000 for p in poses], percentile)) * 1e-6

    def __enter__(self) -> "FakeAutopilot":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()

    # ------------------------------------------------------------ I/O thread
    def write(self, buf: bytes) -> None:  # mav.send() writes here
        if self._sock is None or self._peer is None:
            return
        try:
            if self.kind == "tcpin":
                self._sock.sendall(buf)
            else:
                self._sock.sendto(buf, self._peer)
            self.sent += 1
        except OSError:
            pass

    def _run(self) -> None:
        sel = selectors.DefaultSelector()
        if self._listen is not None:
            sel.register(self._listen, selectors.EVENT_READ, "listen")
        else:
            sel.register(self._sock, selectors.EVENT_READ, "data")
        t_end = None if self.duration_s is None else self.clock_ns() + int(self.duration_s * 1e9)
        next_hb = next_ts = self.clock_ns()
        try:
            while not self._stop.is_set():
                now = self.clock_ns()
                if t_end is not None and now >= t_end:
                    break
                while self._pending and self._pending[0][0] <= now:
                    self._handle(*reversed(self._pending.popleft()))
                linked = self._peer is not None and self._sock is not None
                if linked and (self.truth is not None or self.px4 is not None):
                    self._telemetry(now)
                if self._peer is not None and self._sock is not None:
                    lost = self.px4.failsafe(now) if self.px4 is not None else None
                    if lost is not None:
                        self._statustext(mavlink2.MAV_SEVERITY_CRITICAL, lost)
                    if self.heartbeat_hz > 0 and now >= next_hb:
                        base, custom = ((self.px4.base_mode(), self.px4.custom_mode()) if self.px4 is not None
                                        else (0, 0))
                        self.mav.send(self.mav.heartbeat_encode(
                            mavlink2.MAV_TYPE_QUADROTOR, AUTOPILOTS[self.autopilot], base, custom,
                            mavlink2.MAV_STATE_STANDBY))
                        next_hb = now + int(1e9 / self.heartbeat_hz)
                    if self.timesync_hz > 0 and now >= next_ts:
                        ts1 = self.clock_ns()
                        self._ts_sent.add(ts1)
                        self.mav.send(self.mav.timesync_encode(0, ts1))
                        next_ts = now + int(1e9 / self.timesync_hz)
                wake = [now + 20_000_000]
                if self._pending:
                    wake.append(self._pending[0][0])
                if self._next_tx:
                    wake.append(min(self._next_tx.values()))
                for key, _ in sel.select(max(0.0, (min(wake) - self.clock_ns()) * 1e-9)):
                    if key.data == "listen":
                        self._accept(sel)
                    else:
                        self._read(sel)
        finally:
            sel.close()

    def _accept(self, sel: selectors.BaseSelector) -> None:
        try:
            conn, addr = self._listen.accept()
        except BlockingIOError:
            return
        if self._sock is not None:
            sel.unregister(self._sock)
            self._sock.close()
        conn.setblocking(False)
        self._sock, self._peer = conn, addr
        sel.register(conn, selectors.EVENT_READ, "data")

    def _read(self, sel: selectors.BaseSelector) -> None:
        while self._sock is not None:
            try:
                if self.kind == "tcpin":
                    data, addr = self._sock.recv(65536), self._peer
                    if not data:  # bridge went away: wait for the next connection
                        sel.unregister(self._sock)
                        self._sock.close()
                        self._sock = self._peer = None
                        return
                elif self._kernel_stamps:
                    data, anc, _, addr = self._sock.recvmsg(65535, ANC_SIZE)
                    stamp = kernel_stamp_ns(anc)
                    arrived = stamp - (time.time_ns() - time.monotonic_ns()) if stamp else self.clock_ns()
                else:
                    data, addr = self._sock.recvfrom(65535)
            except (BlockingIOError, InterruptedError):
                return
            except OSError:
                return
            if self.kind == "udpin":
                self._peer = addr  # answer the bridge where it sends from
            if not self._kernel_stamps or self.kind == "tcpin":
                arrived = self.clock_ns()
            if self.delay_ns > 0:
                self._pending.append((arrived + self.delay_ns, data))
            else:
                self._handle(data, arrived)

    def _handle(self, data: bytes, now: int) -> None:
        """Handle a datagram as arrived at now (its arrival plus the added delay)."""
        for m in self.mav.parse_buffer(data) or []:
            t = m.get_type()
            if t == "BAD_DATA":
                if "signature" in str(getattr(m, "reason", "")).lower():
                    self.rejected_signature += 1
                else:
                    self.bad_packets += 1
                continue
            if t == "TIMESYNC":
                if m.tc1 == 0:  # a request: our clock at its arrival (ArduPilot stamps the receive time)
                    self.timesync_requests_answered += 1
                    self.mav.send(self.mav.timesync_encode(self.boot_time_ns(now), m.ts1))
                    continue
                if m.ts1 in self._ts_sent:
                    self._ts_sent.discard(m.ts1)
                    self.timesync_samples.append((now - m.ts1, m.tc1 - (m.ts1 + now) // 2))
            elif t in POSE_TYPES:
                refused = pose_refusal(t, m.to_dict()) if self.px4 is not None else None
                if refused is None:
                    self._on_pose(now)
                else:
                    self.dropped_poses.append(refused)
            elif t == "HEARTBEAT" and self.px4 is not None and m.type == mavlink2.MAV_TYPE_GCS:
                self.px4.last_gcs_ns = now
            elif t == "MANUAL_CONTROL" and self.px4 is not None and m.target == self.sysid:
                self.px4.last_manual_ns = now
            elif t == "SET_GPS_GLOBAL_ORIGIN" and m.target_system == self.sysid:
                if self.boot_time_ns(now) < self.origin_ready_ns:
                    self.origin_dropped += 1  # the EKF is not running yet
                elif self.origin is None:  # kept once set, as ArduPilot does
                    self.origin = (m.latitude, m.longitude, m.altitude)
                    self._send_origin()
            elif t in ("COMMAND_LONG", "COMMAND_INT") and m.target_system == self.sysid:
                self._command(m, t)
            elif t == "SET_HOME_POSITION" and self.autopilot == "px4" and m.target_system == self.sysid:
                self.home = (m.latitude, m.longitude, m.altitude * 1e-3)
            elif t == "PARAM_SET" and m.target_system == self.sysid:
                pid = m.param_id.rstrip("\0") if isinstance(m.param_id, str) else str(m.param_id)
                if self.px4 is None or pid in self.params:  # PX4 does not answer a name it does not have
                    self.params[pid] = param_from_wire(m.param_value, self._param_type(pid), self.px4 is not None)
                    self._send_param(pid, 1)
            elif t == "PARAM_REQUEST_READ" and m.target_system == self.sysid:
                pid = m.param_id.rstrip("\0") if isinstance(m.param_id, str) else str(m.param_id)
                if pid in self.params:
                    self._send_param(pid, len(self.params))
            if t in RECORDED:
                rec = Received(t, now, m.get_srcSystem(), m.get_srcComponent(), bool(m.get_signed()), m.to_dict())
                self.received.append(rec)
                if self.on_pose is not None and t in POSE_TYPES:
                    self.on_pose(rec)

    def _on_pose(self, now: int) -> None:
        self._last_pose_ns = now
        if self.ekf == "accept" and not self._said_ext_nav and self.px4 is None:
            self._said_ext_nav = True
            self._statustext(mavlink2.MAV_SEVERITY_INFO, EXT_NAV_TEXT)

    def _statustext(self, severity: int, text: str) -> None:
        self.statustexts.append(text)
        self.mav.send(self.mav.statustext_encode(severity, text.encode()))

    def _param_type(self, pid: str) -> int:
        return mavlink2.MAV_PARAM_TYPE_INT32 if self.px4 is not None and pid in PX4_INT_PARAMS \
            else mavlink2.MAV_PARAM_TYPE_REAL32

    def _send_param(self, pid: str, count: int) -> None:
        """PARAM_VALUE as this autopilot encodes it: PX4's integers bytewise, ArduPilot's as floats."""
        kind = self._param_type(pid)
        value = param_to_wire(self.params[pid], kind, self.px4 is not None)
        self.mav.send(self.mav.param_value_encode(pid.encode(), value, kind, count, 0))

    def _send_origin(self) -> None:
        if self.origin is not None:
            lat, lon, alt = self.origin
            self.mav.send(self.mav.gps_global_origin_encode(lat, lon, alt, self.boot_time_ns() // 1000))

    def ev_fused(self, now: int) -> bool:
        """Its EKF fuses the vision: it accepts it and a pose it could read arrived lately."""
        return self.ekf == "accept" and now - self._last_pose_ns < POSE_FRESH_NS

    def _command(self, m, kind: str) -> None:
        cmd = m.command
        result = mavlink2.MAV_RESULT_UNSUPPORTED
        if self.px4 is not None and kind == "COMMAND_LONG":
            now = self.clock_ns()
            px4_result, text = self.px4.command(cmd, m.param1, m.param2, now, self.ev_fused(now), m.param3)
            if text is not None:
                self._statustext(mavlink2.MAV_SEVERITY_CRITICAL, text)
            if px4_result >= 0:
                self.mav.send(self.mav.command_ack_encode(cmd, px4_result))
                return
        if cmd == MAV_CMD_SET_MESSAGE_INTERVAL:
            mid, us = int(m.param1), float(m.param2)
            if mid in TELEMETRY:
                if us > 0:
                    self.intervals_ns[mid] = int(us * 1000)
                else:
                    self.intervals_ns.pop(mid, None)
                result = mavlink2.MAV_RESULT_ACCEPTED
        elif cmd == MAV_CMD_REQUEST_MESSAGE and int(m.param1) == MSG_GPS_GLOBAL_ORIGIN:
            result = mavlink2.MAV_RESULT_ACCEPTED if self.origin is not None else mavlink2.MAV_RESULT_FAILED
            self._send_origin()
        elif cmd == MAV_CMD_REQUEST_MESSAGE and int(m.param1) == MSG_HOME_POSITION:
            result = mavlink2.MAV_RESULT_ACCEPTED if self.home is not None else mavlink2.MAV_RESULT_FAILED
            self._send_home()
        elif cmd == MAV_CMD_DO_SET_HOME:
            if self.origin is None and self.autopilot == "ardupilot":
                result = mavlink2.MAV_RESULT_FAILED  # ArduPilot needs its origin first
            else:
                if kind == "COMMAND_INT":
                    self.home = (m.x, m.y, float(m.z))
                else:
                    self.home = (int(round(m.param5 * 1e7)), int(round(m.param6 * 1e7)), float(m.param7))
                result = mavlink2.MAV_RESULT_ACCEPTED
                self._send_home()  # as ArduPilot does on a change of home
        self.mav.send(self.mav.command_ack_encode(cmd, result))

    def _send_home(self) -> None:
        if self.home is not None:
            lat, lon, alt = self.home
            self.mav.send(self.mav.home_position_encode(lat, lon, int(round(alt * 1000)), 0.0, 0.0, 0.0,
                                                        [1.0, 0.0, 0.0, 0.0], 0.0, 0.0, 0.0,
                                                        self.boot_time_ns() // 1000))

    def _telemetry(self, now: int) -> None:
        """Send the streams that are due, from the truth at now (server clock), stamped on our clock."""
        due = [mid for mid, iv in self.intervals_ns.items() if now >= self._next_tx.get(mid, 0)]
        if not due:
            return
        for mid in due:
            iv = self.intervals_ns[mid]
            nxt = self._next_tx.get(mid, now) + iv
            self._next_tx[mid] = nxt if nxt > now else now + iv
        if self.truth is None:  # PX4 with no motion to play: only the estimator's status
            for mid in due:
                if mid in (193, 230):
                    self.mav.send(self._status(mid, now))
            return
        tr = self.truth(np.array([now], dtype=np.int64))
        t_boot = self.boot_time_ns(now)
        gyro, acc = imu_from_truth(tr)
        if self.gyro_lag_ns:  # the filtered gyro: the motion of gyro_lag_ns ago
            gyro, _ = imu_from_truth(self.truth(np.array([now - self.gyro_lag_ns], dtype=np.int64)))
        gyro, acc = imu_reading(gyro[0], acc[0], self.gyro_bias, self.accel_bias, self.gyro_noise, self.accel_noise,
                                self.rng)
        q_nf = quat_world_body_to_ned_frd(tr.quaternion[0])
        att_err = Rotation.from_rotvec(self.rng.normal(0.0, self.attitude_noise, 3))
        r_nf = Rotation.from_quat(q_nf) * att_err
        yaw, pitch, roll = r_nf.as_euler("ZYX")
        x, y, z, w = r_nf.as_quat()
        ms = t_boot // 1_000_000
        for mid in due:
            if mid == 30:
                msg = self.mav.attitude_encode(ms, roll, pitch, yaw, *gyro)
            elif mid == 31:
                msg = self.mav.attitude_quaternion_encode(ms, w, x, y, z, *gyro)
            elif mid == 105:
                msg = self.mav.highres_imu_encode(t_boot // 1000, *acc, *gyro, 0.0, 0.0, 0.0, 1013.0, 0.0, 0.0, 20.0,
                                                  0x3F)
            elif mid == 27:
                mg = np.clip(np.round(acc / GRAVITY * 1000), -32768, 32767).astype(int)
                mrad = np.clip(np.round(gyro * 1000), -32768, 32767).astype(int)
                msg = self.mav.raw_imu_encode(t_boot // 1000, *mg, *mrad, 0, 0, 0)
            elif mid == 32:
                p = tr.position[0] * np.array([1.0, -1.0, -1.0])
                v = tr.velocity[0] * np.array([1.0, -1.0, -1.0])
                msg = self.mav.local_position_ned_encode(ms, *p, *v)
            else:
                msg = self._status(mid, now)
            self.mav.send(msg)

    def _status(self, mid: int, now: int):
        """EKF_STATUS_REPORT (193, ArduPilot's) or ESTIMATOR_STATUS (230, PX4's): from what it fuses, no truth."""
        if mid != 230:
            return self._ekf_status(now)
        fused = self.ev_fused(now)
        ratio = 0.05 if fused else (2.5 if self.ekf == "reject" and now - self._last_pose_ns < POSE_FRESH_NS else 0.0)
        return self.mav.estimator_status_encode(self.boot_time_ns(now) // 1000, FLAGS_EV_FUSED if fused else
                                                FLAGS_ATTITUDE_ONLY, ratio, ratio, ratio, 0.0, 0.0, 0.0, 0.01, 0.01)

    def _ekf_status(self, now: int):
        fresh = now - self._last_pose_ns < 500_000_000
        if self.ekf == "accept" and fresh:
            flags, ratio = EKF_USING_VISION, 0.05
        elif self.ekf == "reject" and fresh:
            flags, ratio = EKF_NO_POSITION, 2.5
        else:
            flags, ratio = EKF_NO_POSITION, 0.0
        return self.mav.ekf_status_report_encode(flags, ratio, ratio, ratio, 0.0, 0.0)

    # ------------------------------------------------------------ queries
    def messages(self, type_: str | tuple[str, ...]) -> list[Received]:
        types = (type_,) if isinstance(type_, str) else type_
        return [r for r in list(self.received) if r.type in types]

    def wait_for(self, type_: str | tuple[str, ...], n: int = 1, timeout_s: float = 5.0) -> bool:
        """Block until n messages of the type(s) arrived or timeout_s passed."""
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            if len(self.messages(type_)) >= n:
                return True
            time.sleep(0.002)
        return len(self.messages(type_)) >= n

    def report(self) -> dict:
        """What an EKF would see: rates, gaps, the last decoded NED pose, timesync, identities."""
        poses = self.messages(POSE_TYPES)
        out: dict = {"pose_messages": len(poses), "rejected_signature": self.rejected_signature,
                     "bad_packets": self.bad_packets}
        if len(poses) >= 2:
            recv = np.array([p.recv_ns for p in poses], dtype=np.int64)
            usec = np.array([decode_pose(p)["usec"] for p in poses], dtype=np.int64)
            gaps_ms = np.diff(recv) * 1e-6
            du_ms = np.diff(usec) * 1e-3
            out.update(
                rate_hz=(len(poses) - 1) / ((recv[-1] - recv[0]) * 1e-9) if recv[-1] > recv[0] else float("nan"),
                max_gap_ms=float(gaps_ms.max()),
                gaps_over_20ms=int((gaps_ms > 20.0).sum()),
                gaps_over_400ms=int((gaps_ms > 400.0).sum()),
                stamp_interval_min_ms=float(du_ms.min()),
                stamps_closer_than_20ms=int((du_ms < 20.0).sum()),  # ArduPilot EKF3 would drop these
                stamps_not_increasing=int((du_ms <= 0).sum()),
            )
        if poses:
            last = decode_pose(poses[-1])
            out["last_pose"] = {k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in last.items()}
        hbs = self.messages("HEARTBEAT")
        out["heartbeats"] = len(hbs)
        out["heartbeat_identities"] = sorted({(h.src_system, h.src_component, h.fields["type"], h.fields["autopilot"])
                                              for h in hbs})
        out["speed_messages"] = len(self.messages("VISION_SPEED_ESTIMATE"))
        if self.timesync_samples:
            a = np.array(self.timesync_samples, dtype=np.float64)
            out["timesync_replies"] = len(a)
            out["timesync_rtt_ms_median"] = float(np.median(a[:, 0]) * 1e-6)
            out["timesync_offset_ms_median"] = float(np.median(a[:, 1]) * 1e-6)
        else:
            out["timesync_replies"] = 0
        return out
