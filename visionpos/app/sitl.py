"""`visionpos sitl`: a real ArduPilot (SITL) flown on visionpos alone, closed loop, on loopback.

    ArduPilot SITL (arducopter: the real flight code and EKF3, its own physics)
      SERIAL0 tcp:127.0.0.1:5760+10*I  <-> our GCS link: parameters, signing key, EKF origin and home,
                                            SIM_STATE (the true pose, 100 Hz), flight commands, telemetry
      SERIAL1 udpclient --> the bridge's udpin endpoint: the signed vision stream comes back on it
    SIM_STATE -> TruthTrack -> LiveTrajectory (the simulated body follows the vehicle)
      -> the demo's simulated stations (live frames: noise, latency, asynchrony)
      -> FusionServer -> Bridge (VISION_POSITION_ESTIMATE or ODOMETRY) -> SITL's EKF3

SITL runs in a fresh temporary folder (its eeprom.bin, logs), on an instance (-I) whose ports
are free, and is killed when the run ends, however it ends. Its SERIAL0 takes one TCP client and
waits for it again after a reboot; the binary takes `--serialN=udpclient:HOST:PORT` (MAVProxy's
`--out` is not a SITL option), which points SERIAL1 at the bridge's udpin endpoint. The vision
link is signed with the vehicle's key (installed by SETUP_SIGNING over SERIAL0), so the bridge
learns SITL's address from signed packets only. The demo's fake autopilot is not started: it
would answer on the same link as the same system.

Order of the set-up, which matters to EKF3 (see docs/autopilot-setup.md):
parameters (GPS and compass off, external nav on) -> reboot -> signing key -> EKF origin sent
until SITL reports GPS_GLOBAL_ORIGIN, and home (MAV_CMD_DO_SET_HOME) -> only then the cameras
start: a vision stream that reaches EKF3 before its origin leaves the height off by centimetres
for the whole flight. The origin is the SITL home, so EKF NED = the arena's world turned by
visionpos/geometry/frames.py (N = x, E = -y, D = -z).

Truth: SIM_STATE carries the vehicle's attitude (quaternion), NED velocity and body rates at
full precision, but latitude/longitude only in 1e-7 degrees (about 1.1 cm) and the altitude in
whole centimetres (ArduPilot's Location), so the position is the integral of the velocity, pulled
slowly (TRUTH_BLEND_S) towards the quantised one: cameras rendering the raw steps would see a body
jump 1 cm in one frame. Samples are stamped with their arrival time (SITL's wait to send them, loopback,
the reader thread's wake-up); SitlClock measures that age on SITL's own clock for the delay benchmark.
Cameras expose at their own times:
the body's pose there is interpolated between samples (cubic Hermite in position with the
velocities, slerp in attitude) or, for the newest few milliseconds, extrapolated with the last
velocity and body rate.
"""

from __future__ import annotations

import asyncio
import dataclasses
import logging
import math
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any, AsyncIterator, Callable, TextIO

import numpy as np
from scipy.spatial.transform import Rotation

from visionpos.config.arena import ArenaConfig, ConfigError
from visionpos.config.schema import register_section
from visionpos.config.settings import Setting, section
from visionpos.errors import UsageError, VisionposError
from visionpos.geometry.frames import euler_ned_frd, frd_to_flu, ned_to_world, quat_ned_frd_to_world_body, world_to_ned
from visionpos.messages import BlobFrame
from visionpos.sim.trajectories import Trajectory

log = logging.getLogger(__name__)

SITL_ENV = "VISIONPOS_SITL"
REPO_ROOT = Path(__file__).resolve().parents[2]


def _shared_binary() -> Path:
    """../shared/sitl/arducopter beside the checkout (for a git worktree: beside its main checkout)."""
    root = REPO_ROOT
    dotgit = root / ".git"
    if dotgit.is_file():  # a worktree: "gitdir: MAIN/.git/worktrees/NAME"
        text = dotgit.read_text(errors="replace").strip()
        if text.startswith("gitdir:") and "/.git/worktrees/" in text:
            root = Path(text.split(":", 1)[1].strip().split("/.git/worktrees/")[0])
    return root.parent / "shared" / "sitl" / "arducopter"


SHARED_BINARY = _shared_binary()  # a checkout beside ../shared (tests, CI)

SITL = section(
    "sitl",
    "ArduPilot SITL for `visionpos sitl` (docs/autopilot-setup.md, \"Try it in SITL first\").",
    Setting("binary", "text", None, "the arducopter SITL binary (relative to the arena file)",
            default_doc="--sitl PATH, else $VISIONPOS_SITL, else ../shared/sitl/arducopter beside the checkout"),
    Setting("defaults", "text", None, "SITL parameter defaults file (--defaults)",
            default_doc="copter.parm beside the binary, when there"),
    Setting("model", "text", "+", "SITL frame model (--model)"),
    Setting("instance", "integer", None, "SITL instance (-I): ports 5760 + 10*I ...", min=0, max=200,
            default_doc="the first whose ports are free from 1"),
    Setting("home", "array", [-35.363261, 149.165230, 584.0, 0.0], "SITL home and EKF origin: lat, lon (deg), "
            "alt (m AMSL), heading (deg)", shape=(4,)),
    Setting("viso_delay_ms", "number", None, "VISO_DELAY_MS to set", min=0.0, max=250.0,
            default_doc="measured: the bridge's pose stamp -> send p50 once the vision flows"),
    Setting("viso_pos_m_nse", "number", 0.01, "VISO_POS_M_NSE: ArduPilot's floor on the position noise (m)",
            min=0.001, max=10.0),
    Setting("viso_yaw_m_nse", "number", 0.02, "VISO_YAW_M_NSE: floor on the yaw noise (rad)", min=0.001, max=1.0),
    Setting("viso_vel_m_nse", "number", 0.05, "VISO_VEL_M_NSE: floor on the velocity noise (m/s; ODOMETRY and "
            "VISION_SPEED_ESTIMATE)", min=0.001, max=5.0),
)

# mavlink ids used here (ardupilotmega dialect)
MAV_CMD_SET_MESSAGE_INTERVAL = 511
MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN = 246
MAV_CMD_DO_SET_HOME = 179
MAV_CMD_DO_SET_MODE = 176
MAV_CMD_COMPONENT_ARM_DISARM = 400
MAV_CMD_NAV_TAKEOFF = 22
MSG_SIM_STATE = 108
MSG_SYSTEM_TIME = 2
MSG_RAW_IMU = 27
COPTER_MODES = {"STABILIZE": 0, "GUIDED": 4, "LOITER": 5, "RTL": 6, "LAND": 9}
MODE_NAMES = {v: k for k, v in COPTER_MODES.items()}

TRUTH_RATE_HZ = 100.0
TELEMETRY_RATE_HZ = 50.0
TRUTH_BLEND_S = 1.0  # time constant pulling the integrated truth to the quantised position
LATLON_TO_M = 0.011131884502145034  # ArduPilot's metres per 1e-7 degree of latitude
LIVE_WINDOW_NS = 40_000_000  # cameras' frames are made 40 ms at a time (a call's cost is mostly fixed) ...
LIVE_MAKE_AT = (0.25, 0.75)  # ... between a quarter and three quarters into the window, cameras spread over it
# (one camera's window costs a few ms of the server's loop: made all at once they would hold up the fusion)
EXTNAV_TEXT = "is using external nav data"
LATE_NS = 50_000_000  # a camera frame made this long after it should have reached the server is late


class SitlError(VisionposError):
    """SITL did not start, did not answer, or refused what the run needs."""


# ---------------------------------------------------------------- finding and running the binary


def default_sitl_binary() -> Path | None:
    """$VISIONPOS_SITL, else ../shared/sitl/arducopter beside the checkout; None when neither is a file."""
    env = os.environ.get(SITL_ENV)
    if env:
        return Path(env) if Path(env).is_file() else None
    return SHARED_BINARY if SHARED_BINARY.is_file() else None


def find_sitl_binary(cli_path: str | None, arena: ArenaConfig | None = None) -> Path:
    """The SITL binary: --sitl PATH, else the arena's sitl.binary, else $VISIONPOS_SITL, else ../shared/sitl."""
    if cli_path:
        p = Path(cli_path)
        if not p.is_file() or not os.access(p, os.X_OK):
            raise UsageError(f"--sitl {cli_path}: no executable file there")
        return p
    if arena is not None:
        sec = SITL.check(arena.section("sitl"))
        configured = SITL.read(sec, "binary")
        if configured:
            p = Path(configured)
            if not p.is_absolute():
                p = Path(arena.source).resolve().parent / p
            if not p.is_file() or not os.access(p, os.X_OK):
                raise ConfigError(arena.source, "sitl.binary", f"{configured!r}: no executable file at {p}; give "
                                  "the path of ArduPilot's arducopter built with `./waf configure --board sitl && "
                                  "./waf copter`")
            return p
    env = os.environ.get(SITL_ENV)
    if env:
        if not Path(env).is_file() or not os.access(env, os.X_OK):
            raise UsageError(f"{SITL_ENV}={env}: no executable file there")
        return Path(env)
    if SHARED_BINARY.is_file():
        return SHARED_BINARY
    raise UsageError("no ArduPilot SITL binary: give --sitl PATH, set sitl.binary in the arena file or "
                     f"{SITL_ENV}=PATH (build it from ArduPilot with `./waf configure --board sitl && ./waf copter`; "
                     "the binary is build/sitl/bin/arducopter)")


@dataclasses.dataclass(frozen=True)
class SitlSettings:
    binary: Path
    defaults: Path | None
    model: str
    instance: int | None
    home: tuple[float, float, float, float]
    viso_delay_ms: float | None
    viso_pos_m_nse: float
    viso_yaw_m_nse: float
    viso_vel_m_nse: float


def parse_sitl(arena: ArenaConfig, binary: Path) -> SitlSettings:
    """The validated `sitl:` section; binary: the SITL executable (find_sitl_binary)."""
    sec = SITL.check(arena.section("sitl"))
    defaults = SITL.read(sec, "defaults")
    if defaults:
        dp = Path(defaults)
        dp = dp if dp.is_absolute() else Path(arena.source).resolve().parent / dp
        if not dp.is_file():
            raise ConfigError(arena.source, "sitl.defaults", f"{defaults!r}: no file at {dp}")
    else:
        dp = binary.parent / "copter.parm"
        dp = dp if dp.is_file() else None
    home = tuple(float(x) for x in SITL.read(sec, "home"))
    if not (-90 <= home[0] <= 90 and -180 <= home[1] <= 180):
        raise ConfigError(arena.source, "sitl.home", f"{list(home)}: give [lat (-90..90), lon (-180..180), "
                          "alt m, heading deg]")
    return SitlSettings(binary, dp, SITL.read(sec, "model"), SITL.read(sec, "instance"),
                        home, SITL.read(sec, "viso_delay_ms"), SITL.read(sec, "viso_pos_m_nse"),
                        SITL.read(sec, "viso_yaw_m_nse"), SITL.read(sec, "viso_vel_m_nse"))


register_section("sitl", SITL, parse_sitl)


def _ports_free(instance: int) -> bool:
    for port in (5760, 5762, 5763, 5501):
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
            try:
                s.bind(("127.0.0.1", port + 10 * instance))
            except OSError:
                return False
    return True


def free_instance() -> int:
    for i in range(1, 200):
        if _ports_free(i):
            return i
    raise SitlError("no free SITL instance: ports 5770-7763 are all taken")


class SitlProcess:
    """ArduPilot SITL in a fresh temporary working directory; close() kills it and removes the folder."""

    def __init__(self, cfg: SitlSettings, instance: int, serial1: str | None = None):
        self.instance = instance
        self.gcs_port = 5760 + 10 * self.instance
        self.folder = tempfile.mkdtemp(prefix="visionpos-sitl-")
        lat, lon, alt, hdg = cfg.home
        # --speedup 1: the cameras, the fusion and the bridge run on the wall clock
        self.args = [str(cfg.binary), "--model", cfg.model, "--speedup", "1", "-I", str(self.instance),
                     "--home", f"{lat:.7f},{lon:.7f},{alt:.2f},{hdg:g}"]
        if serial1 is not None:  # e.g. udpclient:HOST:PORT (SITL's own syntax; MAVProxy's --out is not one)
            self.args.append(f"--serial1={serial1}")
        if cfg.defaults is not None:
            self.args += ["--defaults", str(cfg.defaults.resolve())]
        self.log_path = os.path.join(self.folder, "sitl.log")
        self._log = open(self.log_path, "wb")
        try:
            self.proc = subprocess.Popen(self.args, cwd=self.folder, stdout=self._log, stderr=subprocess.STDOUT,
                                         stdin=subprocess.DEVNULL, start_new_session=True)
        except OSError as e:
            self.close()
            raise SitlError(f"could not start {cfg.binary}: {e}") from e

    def alive(self) -> bool:
        return self.proc.poll() is None

    def log_tail(self, n: int = 15) -> str:
        try:
            return "\n".join(Path(self.log_path).read_text(errors="replace").splitlines()[-n:])
        except OSError:
            return ""

    def close(self) -> None:
        proc = getattr(self, "proc", None)
        if proc is not None and proc.poll() is None:
            proc.terminate()
            try:
                proc.wait(3.0)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(3.0)
        self._log.close()
        shutil.rmtree(self.folder, ignore_errors=True)

    def __enter__(self) -> "SitlProcess":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


# ---------------------------------------------------------------- the true pose


class TruthTrack:
    """SITL's true pose, sample by sample, in the arena's world frame (z up, body FLU); thread-safe.

    home: (lat deg, lon deg, alt m): the origin (world 0 = NED 0 = home)."""

    def __init__(self, home: tuple[float, float, float]):
        self.lat0_e7 = int(round(home[0] * 1e7))
        self.lon0_e7 = int(round(home[1] * 1e7))
        self.alt0 = float(home[2])
        self.lon_scale = math.cos(math.radians(home[0]))
        self._lock = threading.Lock()
        self._cap = 0
        self.n = 0
        self._t = np.zeros(0, np.int64)
        self._x = np.zeros((0, 13))  # world position (3), velocity (3), quaternion xyzw (4), body rate FLU (3)
        self._ned_prev: np.ndarray | None = None
        self._v_prev = np.zeros(3)

    def add(self, recv_ns: int, m: Any) -> None:
        """One SIM_STATE message (pymavlink) received at recv_ns (server clock)."""
        v_ned = np.array([m.vn, m.ve, m.vd], dtype=float)
        meas = np.array([(m.lat_int - self.lat0_e7) * LATLON_TO_M,
                         (m.lon_int - self.lon0_e7) * LATLON_TO_M * self.lon_scale, -(m.alt - self.alt0)])
        if self._ned_prev is None or self.n == 0:
            ned = meas
        else:
            dt = max((recv_ns - int(self._t[self.n - 1])) * 1e-9, 0.0)
            ned = self._ned_prev + 0.5 * (self._v_prev + v_ned) * dt
            ned += (meas - ned) * min(1.0, dt / TRUTH_BLEND_S)
        self._ned_prev, self._v_prev = ned, v_ned
        q = quat_ned_frd_to_world_body(np.array([m.q2, m.q3, m.q4, m.q1], dtype=float))
        row = np.concatenate([ned_to_world(ned), ned_to_world(v_ned), q,
                              frd_to_flu(np.array([m.xgyro, m.ygyro, m.zgyro], dtype=float))])
        with self._lock:
            if self.n == self._cap:
                self._cap = max(1024, 2 * self._cap)
                t, x = np.zeros(self._cap, np.int64), np.zeros((self._cap, 13))
                t[: self.n], x[: self.n] = self._t[: self.n], self._x[: self.n]
                self._t, self._x = t, x
            if self.n and recv_ns <= self._t[self.n - 1]:
                recv_ns = int(self._t[self.n - 1]) + 1
            self._t[self.n], self._x[self.n] = recv_ns, row
            self.n += 1

    def snapshot(self) -> tuple[np.ndarray, np.ndarray]:
        with self._lock:
            return self._t[: self.n], self._x[: self.n]

    def sample(self, times_ns: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, Rotation]:
        """Positions, velocities, accelerations (T, 3) and body->world rotations (T,) at server-clock times."""
        t, x = self.snapshot()
        times_ns = np.asarray(times_ns, dtype=np.int64)
        T = len(times_ns)
        if len(t) == 0:
            return np.zeros((T, 3)), np.zeros((T, 3)), np.zeros((T, 3)), Rotation.identity(T)
        i = np.clip(np.searchsorted(t, times_ns, side="right") - 1, 0, len(t) - 1)
        j = np.minimum(i + 1, len(t) - 1)
        inside = (times_ns >= t[0]) & (j > i)
        h = np.where(inside, (t[j] - t[i]) * 1e-9, 1.0)
        dt = (times_ns - t[i]) * 1e-9
        p0, v0, p1, v1 = x[i, 0:3], x[i, 3:6], x[j, 0:3], x[j, 3:6]
        s = np.where(inside, dt / h, 0.0)[:, None]
        hh = h[:, None]
        # position: cubic Hermite with the velocities; velocity and acceleration from SITL's velocities
        # (the position samples carry the slow pull to the quantised lat/lon, which is not motion)
        h00, h10, h01, h11 = 2 * s**3 - 3 * s**2 + 1, s**3 - 2 * s**2 + s, -2 * s**3 + 3 * s**2, s**3 - s**2
        pos_in = h00 * p0 + h10 * hh * v0 + h01 * p1 + h11 * hh * v1
        vel_in = v0 + (v1 - v0) * s
        acc_in = (v1 - v0) / hh
        before = times_ns < t[0]
        ext = np.where(before, 0.0, dt)[:, None]  # after the newest sample: constant velocity and body rate
        pos_out = p0 + v0 * ext
        vel_out = np.where(before[:, None], 0.0, v0)
        m = inside[:, None]
        pos = np.where(m, pos_in, pos_out)
        vel = np.where(m, vel_in, vel_out)
        acc = np.where(m, acc_in, 0.0)
        r0 = Rotation.from_quat(x[i, 6:10])
        r1 = Rotation.from_quat(x[j, 6:10])
        rel = (r0.inv() * r1).as_rotvec()
        step = np.where(m, rel * s, x[i, 10:13] * ext)
        return pos, vel, acc, r0 * Rotation.from_rotvec(step)


@dataclasses.dataclass(frozen=True)
class LiveTrajectory(Trajectory):
    """A trajectory read from a TruthTrack: t (s) since the scenario start, which is origin_ns[0] on the
    server clock (set when the run starts)."""

    truth: TruthTrack
    origin_ns: list  # [server-clock ns of t = 0]: filled in by LiveArena.frames

    def _times(self, t: np.ndarray) -> np.ndarray:
        return self.origin_ns[0] + np.round(np.asarray(t, dtype=np.float64) * 1e9).astype(np.int64)

    def kinematics(self, t):
        p, v, a, _ = self.truth.sample(self._times(t))
        return p, v, a

    def attitude(self, t):
        return self.truth.sample(self._times(t))[3]

    def pose(self, t):
        p, _, _, r = self.truth.sample(self._times(np.atleast_1d(t)))
        return p, r


class LiveArena:
    """The demo's live source (app/demo.py LiveSource): the vehicle's body follows SITL's truth.

    Each camera's frames are made window by window (LIVE_WINDOW_NS), a quarter to three quarters into
    the window on the server clock (the cameras spread over it): a frame's pose is at most three
    quarters of a window plus the truth's age ahead of the newest SIM_STATE (extrapolated for those
    ms), and a frame exposed early in the window leaves late (more latency, which VISO_DELAY_MS
    absorbs; its capture stamp stays true).
    cut(start_ns, end_ns) hides the body from every camera for a while (the frames still go out,
    without its markers: an occlusion, not a dead station)."""

    def __init__(self, body: str, truth: TruthTrack):
        self.body = body
        self.truth = truth
        self.origin_ns = [0]
        self.stopped_ns: int | None = None
        self.scenario: Any = None
        self.cuts: list[tuple[int, int]] = []
        self.frames_made = 0
        self.frames_late = 0  # made more than LATE_NS after their receive time: the host fell behind real time

    def prepare(self, scenario: Any) -> Any:
        bodies = tuple(dataclasses.replace(b, trajectory=LiveTrajectory(self.truth, self.origin_ns))
                       if b.name == self.body else b for b in scenario.bodies)
        if not any(b.name == self.body for b in bodies):
            raise UsageError(f"the arena has no simulated body {self.body!r}")
        self.scenario = scenario.with_changes(bodies=bodies)
        return self.scenario

    def stop(self) -> None:
        if self.stopped_ns is None:
            self.stopped_ns = time.monotonic_ns()

    def cut(self, start_ns: int, end_ns: int) -> None:
        self.cuts.append((int(start_ns), int(end_ns)))

    def _hidden(self, capture_ns: int) -> bool:
        return any(a <= capture_ns < b for a, b in self.cuts)

    async def frames(self, camera_index: int, shift_ns: int) -> AsyncIterator[BlobFrame]:
        from visionpos.sim.capture import window_frames

        sc = self.scenario
        self.origin_ns[0] = sc.start_ns + shift_ns
        body_index = next(i for i, b in enumerate(sc.bodies) if b.name == self.body)
        lo, hi = LIVE_MAKE_AT
        make_at = lo + (hi - lo) * camera_index / max(1, len(sc.cameras) - 1)
        w = 0
        while self.stopped_ns is None:
            opens = self.origin_ns[0] + int((w + make_at) * LIVE_WINDOW_NS)
            wait = (opens - time.monotonic_ns()) * 1e-9
            if wait > 0:
                await asyncio.sleep(wait)
            for f, tr in window_frames(sc, camera_index, w, w * LIVE_WINDOW_NS, (w + 1) * LIVE_WINDOW_NS):
                f = dataclasses.replace(f, capture_ns=f.capture_ns + shift_ns, recv_ns=f.recv_ns + shift_ns)
                if self._hidden(f.capture_ns):
                    f = dataclasses.replace(f, blobs=f.blobs[tr.body != body_index])
                self.frames_made += 1
                if time.monotonic_ns() - f.recv_ns > LATE_NS:
                    self.frames_late += 1
                yield f
            w += 1


# ---------------------------------------------------------------- the GCS link


class SitlClock:
    """SITL's clock against ours; thread-safe appends (the GCS reader, the intake probe's threads).

    SITL's clock is its simulation time, stopped at each physics step while its loop runs (AP_HAL_SITL), so
    everything it stamps in one loop carries that step's time. Three records:
    - truth: (arrival here, SITL time) for each SIM_STATE, the SITL time being RAW_IMU's time_usec sent in the
      same message bucket (both asked for at TRUTH_RATE_HZ on the GCS link; SITL sends RAW_IMU, SIM_STATE,
      SYSTEM_TIME together; RAW_IMU is stamped when sent, to the microsecond, i.e. the physics step SIM_STATE
      reports; SYSTEM_TIME's time_boot_ms, whole milliseconds, only cross-checks the bucket);
    - intake: (our send time s1, SITL's tc1) for TIMESYNC requests sent into the vision link's port (SERIAL1)
      from the relay's socket (IntakeProbe): tc1 is SITL's receive time of the datagram (the UART's receive
      timestamp, which ArduPilot also gives a vision message), so tc1 - s1 is how late on SITL's clock a
      datagram the relay sends now is taken in;
    - timesync: the same on the GCS link (SERIAL0), for comparison.
    median(arrival - SITL time) + median(tc1 - s1) = how old SIM_STATE's physics is when it arrives here plus
    how late SITL takes a datagram in, on SITL's clock: the two clocks' offset cancels."""

    TIMESYNC_EVERY_NS = 250_000_000
    BUCKET_NS = 1_000_000  # messages of one bucket arrive together (one TCP write)
    MIN_TIMESYNCS = 5

    def __init__(self) -> None:
        self.truth: list[tuple[int, int]] = []
        self.intake: list[tuple[int, int]] = []
        self.timesync: list[tuple[int, int]] = []
        self.pending: dict[int, int] = {}
        self.bucket_checks = 0
        self.bucket_mismatches = 0  # SYSTEM_TIME ms != floor(RAW_IMU us / 1000): not one bucket
        self._imu: tuple[int, int] | None = None  # (arrival, SITL ns) of the last RAW_IMU
        self._last_imu: tuple[int, int] | None = None  # the same, for the SYSTEM_TIME check

    def on_system_time(self, now: int, time_boot_ms: int) -> None:
        """SITL sends it after RAW_IMU and SIM_STATE in their bucket: it checks the RAW_IMU before it."""
        imu = self._last_imu
        if imu is not None and now - imu[0] < self.BUCKET_NS:
            self.bucket_checks += 1
            self.bucket_mismatches += int(int(time_boot_ms) != imu[1] // 1_000_000)
            self._last_imu = None

    def on_raw_imu(self, now: int, time_usec: int) -> None:
        self._imu = self._last_imu = (now, int(time_usec) * 1000)

    def on_sim_state(self, now: int) -> None:
        imu = self._imu
        if imu is not None and now - imu[0] < self.BUCKET_NS:
            self.truth.append((now, imu[1]))
        self._imu = None  # one pair per bucket

    def on_timesync(self, tc1: int, ts1: int) -> None:
        """A TIMESYNC answer on the GCS link (ts1: our request's send time)."""
        s1 = self.pending.pop(ts1, None)
        if s1 is not None and tc1 > 0:
            self.timesync.append((s1, tc1))

    def summary(self, since_ns: int, until_ns: int | None = None) -> dict[str, Any]:
        """The records since since_ns (our clock), in ms: sitl_term (SIM_STATE's age plus SITL's intake of the
        vision link's datagrams, the term the true delay gains; None with too few records) and
        sitl_term_serial0 (the same with the GCS link's intake, for comparison)."""
        def rows(records: list) -> np.ndarray:
            end = until_ns if until_ns is not None else np.iinfo(np.int64).max
            return np.array([r for r in list(records) if since_ns <= r[0] <= end], dtype=np.int64).reshape(-1, 2)

        tr, ts1, ts0 = rows(self.truth), rows(self.intake), rows(self.timesync)
        out: dict[str, Any] = {"truth_pairs": len(tr), "intake_timesyncs": len(ts1), "gcs_timesyncs": len(ts0),
                               "sitl_term_ms": None, "sitl_term_serial0_ms": None, "intake_ms": None,
                               "bucket_mismatch_fraction": self.bucket_mismatches / max(1, self.bucket_checks)}
        if len(tr) < 10:
            return out
        if len(ts1) >= self.MIN_TIMESYNCS:
            out["intake_ms"] = float(np.median(ts1[:, 1] - ts1[:, 0])) * 1e-6  # offset-laden
        age = float(np.median(tr[:, 0] - tr[:, 1]))  # offset-laden: our arrival less SITL's time
        for key, ts in (("sitl_term_ms", ts1), ("sitl_term_serial0_ms", ts0)):
            if len(ts) >= self.MIN_TIMESYNCS:  # offset-laden the other way: SITL's intake less our send
                out[key] = (age + float(np.median(ts[:, 1] - ts[:, 0]))) * 1e-6
        return out


class IntakeProbe:
    """TIMESYNC requests into SITL's vision port (SERIAL1) from the relay's own socket, every
    SitlClock.TIMESYNC_EVERY_NS on a thread of its own, signed with the vehicle's key (SITL takes only signed
    messages there) on a link id of its own; the answers are picked out of the relay's datagrams from SITL
    (DelayRelay.tap) into clock.intake."""

    LINK_ID = 7

    def __init__(self, relay: Any, key: bytes, clock: SitlClock):
        from pymavlink.dialects.v20 import ardupilotmega as mav2

        self.relay = relay
        self.clock = clock
        self.enc = mav2.MAVLink(None, srcSystem=255, srcComponent=191)
        self.enc.signing.secret_key = key
        self.enc.signing.link_id = self.LINK_ID
        self.enc.signing.sign_outgoing = True
        self.enc.signing.timestamp = int((time.time() - 1420070400) * 1e5)  # 10 us since 2015-01-01
        self.rx = mav2.MAVLink(None)
        self.rx.robust_parsing = True
        self._pending: dict[int, int] = {}
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="sitl-intake-probe", daemon=True)

    def __enter__(self) -> "IntakeProbe":
        self.relay.tap = self.tap
        self._thread.start()
        return self

    def __exit__(self, *exc: Any) -> None:
        self._stop.set()
        self._thread.join(2.0)
        self.relay.tap = None

    def _run(self) -> None:
        while not self._stop.wait(SitlClock.TIMESYNC_EVERY_NS * 1e-9):
            ts1 = time.monotonic_ns()  # an identifier: the send time is the relay's clock read at its write
            s1 = self.relay.send_to_autopilot(self.enc.timesync_encode(0, ts1).pack(self.enc))
            if s1 is not None:
                with self._lock:
                    self._pending[ts1] = s1
                    while len(self._pending) > 64:
                        self._pending.pop(next(iter(self._pending)))

    def tap(self, read_ns: int, data: bytes) -> None:
        if b"\x6f\x00\x00" not in data:  # TIMESYNC's message id (111, 3 bytes): parse only those datagrams
            return
        try:
            msgs = self.rx.parse_buffer(data) or []
        except Exception:  # noqa: BLE001  a datagram that is not MAVLink: not ours
            return
        for m in msgs:
            if m.get_type() == "TIMESYNC" and m.tc1 > 0:
                with self._lock:
                    s1 = self._pending.pop(m.ts1, None)
                if s1 is not None:
                    self.clock.intake.append((s1, int(m.tc1)))


class Gcs:
    """Our ground-station link to SITL's SERIAL0 (tcp), with a reader thread keeping what SITL reports.

    Every record carries its arrival time on the server clock (time.monotonic_ns)."""

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
        self.heartbeats = 0
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
        elif kind == "HEARTBEAT" and m.get_srcSystem() == 1 and m.get_srcComponent() == 1:
            self.heartbeats += 1
            self.armed = bool(m.base_mode & 128)
            if m.custom_mode != self.mode:
                self.mode = m.custom_mode
                self.modes.append((now, m.custom_mode))
        elif kind == "PARAM_VALUE":
            self.params[m.param_id] = m.param_value
        elif kind == "COMMAND_ACK":
            self.acks[m.command] = (m.result, now)
        elif kind == "GPS_GLOBAL_ORIGIN":
            self.origin = (now, m)

    def request_streams(self) -> None:
        # SYSTEM_TIME and RAW_IMU at SIM_STATE's rate share its message bucket: they stamp it (SitlClock)
        for msg_id, rate in ((MSG_SIM_STATE, TRUTH_RATE_HZ), (MSG_SYSTEM_TIME, TRUTH_RATE_HZ),
                             (MSG_RAW_IMU, TRUTH_RATE_HZ), (32, TELEMETRY_RATE_HZ), (30, TELEMETRY_RATE_HZ),
                             (193, 10.0), (49, 1.0)):  # LOCAL_POSITION_NED, ATTITUDE, EKF_STATUS_REPORT, ORIGIN
            self.conn.mav.command_long_send(1, 1, MAV_CMD_SET_MESSAGE_INTERVAL, 0, msg_id, 1e6 / rate,
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
        self.conn.mav.param_set_send(1, 1, name.encode(), float(value), mavutil.mavlink.MAV_PARAM_TYPE_REAL32)

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
        self.conn.mav.command_long_send(1, 1, cmd, 0, *p)

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


def vision_parameters(cfg: SitlSettings, message: str, vision_speed: bool) -> dict[str, float]:
    """The vision-only parameters of docs/autopilot-setup.md (GPS and compass off, external nav on)."""
    vel = 6.0 if (message == "odometry" or vision_speed) else 0.0
    return {
        "VISO_TYPE": 1, "SERIAL1_PROTOCOL": 2, "SERIAL1_BAUD": 921,
        "EK3_SRC1_POSXY": 6, "EK3_SRC1_POSZ": 6, "EK3_SRC1_VELXY": vel, "EK3_SRC1_VELZ": vel, "EK3_SRC1_YAW": 6,
        "GPS1_TYPE": 0, "COMPASS_USE": 0, "COMPASS_USE2": 0, "COMPASS_USE3": 0, "COMPASS_ENABLE": 0,
    }


def sitl_arena(scenario: str, overrides: list[str], max_duration_s: float) -> ArenaConfig:
    from visionpos.app.demo import demo_arena

    arena = demo_arena(scenario, max_duration_s, None, overrides)
    if len(arena.bodies) < 1:
        raise UsageError(f"{arena.source}: the arena has no body to fly")
    return arena


@dataclasses.dataclass
class FlightPlan:
    altitude_m: float = 1.0
    side_m: float = 1.0
    hold_s: float = 4.0
    square: bool = True
    cut_s: float = 0.0  # vision hidden this long mid-hover (0: no cut)
    timeout_s: float = 240.0
    # the vision link through a DelayRelay holding each direction this long (None: SERIAL1 straight to the bridge)
    link_delay_ms: float | None = None
    # yaw rate swung sinusoidally (rad/s amplitude, YAW_SWING_PERIOD_S) during the hold: the rotation the
    # back-channel's gyro/optical correlation needs to measure the delay (0: hold still)
    yaw_swing_rad_s: float = 0.0


def _vehicle_cfg(arena: ArenaConfig) -> Any:
    """The arena's first vehicle (bridge.config.VehicleConfig), signed: SITL flies over a signed link."""
    from bridge.config import parse_vehicles

    vehicles = parse_vehicles(arena)
    if vehicles[0].signing_key is None:
        raise ConfigError(arena.source, "vehicles[0].signing", "SITL flies over a signed link: give "
                          "signing: {key_file: ...}")
    return vehicles[0]


def run_sitl(arena: ArenaConfig, binary: Path, plan: FlightPlan, out: TextIO | None) -> dict[str, Any]:
    """Start SITL, set it up for vision-only flight, fly the plan on the live arena; the summary dict.

    With plan.link_delay_ms, SITL's SERIAL1 talks to a DelayRelay (visionpos/app/linkdelay.py) that holds
    each datagram that long each way on its way to and from the bridge, and the summary's "link_delay"
    compares the back-channel's measured capture-to-autopilot delay with the true one (delay_record)."""
    from visionpos.app.linkdelay import DelayRelay

    if plan.link_delay_ms is None:
        return _run_sitl(arena, binary, plan, out, None)
    vision_port = _vehicle_cfg(_one_vehicle(arena)).endpoint.port
    with DelayRelay(("127.0.0.1", vision_port), plan.link_delay_ms, lifetime_s=plan.timeout_s + 180.0) as relay:
        return _run_sitl(arena, binary, plan, out, relay)


def _run_sitl(arena: ArenaConfig, binary: Path, plan: FlightPlan, out: TextIO | None,
              relay: Any) -> dict[str, Any]:
    from visionpos.app.demo import run_demo

    cfg = parse_sitl(arena, binary)
    instance = cfg.instance if cfg.instance is not None else free_instance()
    arena = _one_vehicle(arena)
    veh = _vehicle_cfg(arena)
    body, key, vision_port = veh.body, veh.signing_key, veh.endpoint.port
    say = (lambda text: (out.write(text + "\n"), out.flush())) if out is not None else (lambda text: None)
    truth = TruthTrack(cfg.home[:3])
    t0 = time.monotonic()
    old_switch = sys.getswitchinterval()
    sys.setswitchinterval(0.001)  # the GCS reader stamps truth on arrival: let it run promptly
    serial1_port = vision_port if relay is None else relay.port
    with SitlProcess(cfg, instance, f"udpclient:127.0.0.1:{serial1_port}") as proc:
        gcs = Gcs(proc.gcs_port, truth, on_text=lambda text: say(f"  SITL: {text}"))
        probe: IntakeProbe | None = None
        try:
            say(f"SITL instance {proc.instance} in {proc.folder}: GCS on SERIAL0 tcp:127.0.0.1:{proc.gcs_port}, "
                f"SERIAL1 udpclient:127.0.0.1:{serial1_port} -> "
                + ("" if relay is None else f"a relay holding each direction {plan.link_delay_ms:g} ms -> ")
                + f"the bridge ({veh.endpoint}, signed)")
            gcs.connect(30.0, proc)
            params = vision_parameters(cfg, veh.get("message", "vision_position_estimate"),
                                       bool(veh.get("vision_speed", False)))
            gcs.set_params(params)
            say(f"parameters set and read back ({len(params)}); rebooting SITL")
            gcs.command(MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN, 1)
            time.sleep(0.1)
            gcs.close()
            time.sleep(2.0)
            gcs.connect(30.0, proc)
            noise = {"VISO_POS_M_NSE": cfg.viso_pos_m_nse, "VISO_YAW_M_NSE": cfg.viso_yaw_m_nse,
                     "VISO_VEL_M_NSE": cfg.viso_vel_m_nse}
            if cfg.viso_delay_ms is not None:
                noise["VISO_DELAY_MS"] = round(cfg.viso_delay_ms)
            gcs.set_params(noise)
            _setup_signing(gcs, key)
            _set_origin(gcs, cfg, say)
            if relay is not None:  # SITL's intake of the vision link's datagrams, for the true delay
                probe = IntakeProbe(relay, key, gcs.clock).__enter__()
            say(f"set-up done in {time.monotonic() - t0:.1f} s; cameras start")
            live = LiveArena(body, truth)
            record: dict[str, Any] = {}

            async def during(ctx: Any) -> None:
                try:
                    await fly(ctx, gcs, live, plan, cfg, body, record, say, relay)
                except SitlError as e:  # the flight failed: still summarise what happened (and why)
                    record["error"] = str(e)
                    say(f"flight failed: {e}")
                finally:
                    live.stop()

            demo = asyncio.run(run_demo(arena, plan.timeout_s + 60.0, None, during=during, live=live))
        finally:
            if probe is not None:
                probe.__exit__()
            gcs.close()
            sys.setswitchinterval(old_switch)
    summary = flight_summary(gcs, truth, demo, record, plan, time.monotonic() - t0)
    if "link_delay" in record:
        summary["link_delay"] = record["link_delay"]
    made = max(live.frames_made, 1)
    summary["real_time"] = {"frames_made": live.frames_made, "frames_late_fraction": live.frames_late / made,
                            "frames_not_fused_fraction": (summary["vision"]["frames_not_fused"] or 0) / made}
    return summary


def _one_vehicle(arena: ArenaConfig) -> ArenaConfig:
    """The arena with its first vehicle only (SITL is one copter, system 1)."""
    from visionpos.config.arena import parse_arena

    data = arena.to_dict()
    vehicles = data.get("vehicles") or []
    if not vehicles:
        raise ConfigError(arena.source, "vehicles", "SITL flies the first vehicle: add one (docs/autopilot-setup.md)")
    if int(vehicles[0].get("sysid", 1)) != 1:
        raise UsageError(f"vehicles[0].sysid {vehicles[0].get('sysid')}: SITL is system 1; fly a body with sysid 1")
    data["vehicles"] = vehicles[:1]
    return parse_arena(data, arena.source)


def _setup_signing(gcs: Gcs, key: bytes) -> None:
    """Install the vision link's key with SETUP_SIGNING on SERIAL0 (channel 0, which ArduPilot lets through
    unsigned): SITL then signs on SERIAL1 and takes only signed vision there, as a real signed set-up, and
    the bridge's udpin endpoint learns SITL's address from signed packets only."""
    stamp = int((time.time() - 1420070400) * 1e5)  # 10 us since 2015-01-01
    gcs.conn.mav.setup_signing_send(1, 1, key, stamp)


def _set_origin(gcs: Gcs, cfg: SitlSettings, say: Callable[[str], None]) -> None:
    """SET_GPS_GLOBAL_ORIGIN until SITL reports GPS_GLOBAL_ORIGIN (EKF3 drops it until it runs), then
    MAV_CMD_DO_SET_HOME at the same place (ArduCopter 4.3+ ignores SET_HOME_POSITION)."""
    lat, lon, alt, _ = cfg.home
    end = time.monotonic() + 60.0
    while gcs.origin is None:
        if time.monotonic() > end:
            raise SitlError("SITL never reported GPS_GLOBAL_ORIGIN: EKF3 did not take the origin")
        gcs.conn.mav.set_gps_global_origin_send(1, int(lat * 1e7), int(lon * 1e7), int(alt * 1000),
                                                int(time.time() * 1e6))
        for _ in range(50):
            if gcs.origin is not None:
                break
            time.sleep(0.02)
    m = gcs.origin[1]
    say(f"EKF origin confirmed by SITL: {m.latitude * 1e-7:.7f}, {m.longitude * 1e-7:.7f}, {m.altitude * 1e-3:.2f} m")
    gcs.command(MAV_CMD_DO_SET_HOME, 0, 0, 0, 0, lat, lon, alt)
    gcs.wait(lambda: MAV_CMD_DO_SET_HOME in gcs.acks, 5.0, "COMMAND_ACK for MAV_CMD_DO_SET_HOME")
    if gcs.acks[MAV_CMD_DO_SET_HOME][0] != 0:
        say(f"note: SITL refused MAV_CMD_DO_SET_HOME (MAV_RESULT {gcs.acks[MAV_CMD_DO_SET_HOME][0]}); it sets home "
            "itself when it arms")


async def fly(ctx: Any, gcs: Gcs, live: LiveArena, plan: FlightPlan, cfg: SitlSettings, body: str,
              record: dict[str, Any], say: Callable[[str], None], relay: Any = None) -> None:
    """The scripted flight: EKF on vision, VISO_DELAY_MS, GUIDED, arm, take off, hold (cut, yaw swing),
    square, land. With a relay, record["link_delay"] gets delay_record at the end of the hold."""
    end = time.monotonic() + plan.timeout_s
    left = lambda: max(1.0, end - time.monotonic())  # noqa: E731
    await Gcs.until(gcs.ekf_using_vision, min(60.0, left()), f"STATUSTEXT '{EXTNAV_TEXT}'")
    record["extnav_ns"] = time.monotonic_ns()
    link = ctx.bridge.vehicle(body)
    if cfg.viso_delay_ms is None:
        await asyncio.sleep(2.0)  # a couple of seconds of poses for the latency figure
        delay = link.stats()["latency_stamp_ms_p50"] + (plan.link_delay_ms or 0.0)
        delay_ms = int(round(delay)) if np.isfinite(delay) else 10
        await gcs.set_params_async({"VISO_DELAY_MS": delay_ms})
        say(f"EKF3 uses the vision; VISO_DELAY_MS = {delay_ms} (the bridge's pose stamp -> send p50"
            + (f" + the relay's {plan.link_delay_ms:g} ms" if plan.link_delay_ms else "") + "; loopback adds nothing)")
    record["viso_delay_ms"] = gcs.params.get("VISO_DELAY_MS")
    await gcs.command_async(MAV_CMD_DO_SET_MODE, 1, COPTER_MODES["GUIDED"], what="GUIDED mode")
    arm_end = time.monotonic() + min(45.0, left())
    while True:  # pre-arm checks pass once the EKF has settled on the vision
        gcs.command(MAV_CMD_COMPONENT_ARM_DISARM, 1)
        try:
            await Gcs.until(lambda: gcs.armed, 1.5, "arming")
            break
        except SitlError:
            if time.monotonic() > arm_end:
                late = live.frames_late / max(1, live.frames_made)
                raise SitlError("SITL would not arm; last messages: " + "; ".join(t for _, _, t in gcs.texts[-5:])
                                + f". {100 * late:.0f}% of the camera frames so far were made more than "
                                f"{LATE_NS // 1_000_000} ms late" + (": this host is not keeping real time, and "
                                "'VisOdom: not healthy' means gaps of over 300 ms in the vision" if late > 0.02
                                else ""))
    record["armed_ns"] = time.monotonic_ns()
    say("armed in GUIDED")
    await gcs.command_async(MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, plan.altitude_m, what="takeoff")

    def height() -> float:
        t, x = truth_now(gcs.truth)
        return x[2] if t else 0.0

    await Gcs.until(lambda: height() >= plan.altitude_m - 0.05, min(30.0, left()), f"climb to {plan.altitude_m} m")
    record["airborne_ns"] = time.monotonic_ns()
    x0, y0, z0 = gcs.local[-1][1:4]
    say(f"at {height():.2f} m; holding" + (f", yaw swinging +-{plan.yaw_swing_rad_s:g} rad/s"
                                             if plan.yaw_swing_rad_s > 0 else ""))
    await _hold(gcs, plan, x0, y0, plan.hold_s / 2)
    if plan.cut_s > 0:
        now = time.monotonic_ns()
        live.cut(now, now + int(plan.cut_s * 1e9))
        record["cut"] = (now, now + int(plan.cut_s * 1e9), (x0, y0, z0))
        say(f"vision cut for {plan.cut_s:g} s (the body hidden from every camera)")
        await asyncio.sleep(plan.cut_s)
    await _hold(gcs, plan, x0, y0, plan.hold_s / 2)
    if relay is not None:
        record["link_delay"] = delay_record(link.bc, relay, plan.link_delay_ms or 0.0, gcs.truth, clock=gcs.clock)
        d = record["link_delay"]
        say(f"link delay {d['added_ms']:g} ms: back-channel measured {_fmt(d['measured_ms'])} ms, true "
            f"{_fmt(d['true_ms'])} ms ({d['detail']})")
    if plan.square:
        s = plan.side_m
        for dx, dy in ((s, 0.0), (s, s), (0.0, s), (0.0, 0.0)):
            await _goto(gcs, x0 + dx, y0 + dy, -plan.altitude_m, min(20.0, left()))
            say(f"  corner N {dx:+.1f} E {dy:+.1f} m reached")
            await asyncio.sleep(1.0)
    record["land_ns"] = time.monotonic_ns()
    await gcs.command_async(MAV_CMD_DO_SET_MODE, 1, COPTER_MODES["LAND"], what="LAND mode")
    await Gcs.until(lambda: not gcs.armed, min(40.0, left()), "landing and disarm")
    record["disarmed_ns"] = time.monotonic_ns()
    record["completed"] = True
    say("landed and disarmed")


YAW_SWING_PERIOD_S = 2.0


async def _hold(gcs: Gcs, plan: FlightPlan, north: float, east: float, duration_s: float) -> None:
    """Hold the position for duration_s: still, or (plan.yaw_swing_rad_s) turning back and forth about the
    vertical with a sinusoidal yaw rate (SET_POSITION_TARGET_LOCAL_NED: position and yaw rate)."""
    if plan.yaw_swing_rad_s <= 0:
        await asyncio.sleep(duration_s)
        return
    t0 = time.monotonic()
    while (t := time.monotonic() - t0) < duration_s:
        rate = plan.yaw_swing_rad_s * math.sin(2 * math.pi * t / YAW_SWING_PERIOD_S)
        gcs.conn.mav.set_position_target_local_ned_send(0, 1, 1, 1, 0b0000_0101_1111_1000, north, east,
                                                        -plan.altitude_m, 0, 0, 0, 0, 0, 0, 0, rate)
        await asyncio.sleep(0.05)


def _fmt(v: float | None) -> str:
    return "-" if v is None else f"{v:.2f}"


def delay_record(bc: Any, relay: Any, added_ms: float, truth: TruthTrack | None = None,
                 window_ns: int | None = None, clock: SitlClock | None = None) -> dict[str, Any]:
    """The back-channel's measured capture-to-autopilot delay against the true one, for a link through relay.

    True delay, on SITL's clock (the one VISO_DELAY_MS is on): the SITL time at which SITL takes in a pose,
    less the SITL time of the physics the pose shows. Its parts, each the median over the back-channel's
    measurement window (the optical span of its last figure, bc.delay_window_ns; else the newest window_ns,
    DELAY_WINDOW_NS):
    - the bridge's write to its socket less the pose's stamp (our clock);
    - the relay's hold of the datagrams towards SITL (our clock; loopback adds microseconds);
    - with clock (SitlClock): SIM_STATE's age, our arrival time less its SITL time (the cameras render the
      truth as of its arrival, so a pose stamped t shows SITL's physics of that much earlier), plus how late
      SITL takes in a datagram the relay sends on the vision link (its receive time in TIMESYNC's tc1 less the
      relay's send time; IntakeProbe): their sum cancels both clocks' offsets.
    Without clock (or too few records) the last part is missing and true_ms is None. Not in it: the
    bridge's write to the relay's read (loopback and the relay thread's wake-up, a median under 0.1 ms), and
    the poses' own lag behind the motion they render (the fusion's), which the back-channel counts.
    true_motion_ms counts it: the SITL time of the intake less the SITL time of the motion the poses show
    (their body rates correlated with SIM_STATE's at the SITL times of its buckets), so error_motion_ms is
    the back-channel's own error (its gyro filter model and TIMESYNC).
    Left out: RAW_IMU's own timing (stamped when sent, at the step of its loop, which is the instant its gyro
    describes, bar the gyro filter's lag that the back-channel removes). optical_lag_ms, for diagnosis: how far
    the poses' body rates trail SIM_STATE's as stamped here (the fusion's lag; a bias of the optics, which the
    measurement sees and the true delay does not)."""
    from bridge.backchannel import DELAY_WINDOW_NS
    from visionpos.analysis.autopilot import theil_sen_at

    now = time.monotonic_ns()
    since = now - (window_ns if window_ns is not None else DELAY_WINDOW_NS)
    until = now
    win = getattr(bc, "delay_window_ns", None)
    if window_ns is None and win is not None:  # the span the measurement used: the link's figures drift
        since, until = win
    sends = np.array([r[1] for r in list(bc.sends.d) if since <= r[0] <= until], dtype=float)  # list(): a copy
    hold_ms = relay.hold_ms_median("to_autopilot", since, until)
    lag_ms = _optical_lag_ms(bc, truth, since) if truth is not None else None
    sitl = clock.summary(since, until) if clock is not None else {}
    sitl_ms = sitl.get("sitl_term_ms")
    true_ms = (float(np.median(sends)) * 1e-6 + hold_ms + sitl_ms
               if len(sends) and hold_ms is not None and sitl_ms is not None else None)
    measured = bc.delay_ms
    shown = _shown_lag_ms(bc, truth, clock, since) if truth is not None and clock is not None else None
    intake = np.array([r for r in list(clock.intake) if r[0] >= since], dtype=np.int64).reshape(-1, 2) \
        if clock is not None else np.zeros((0, 2), np.int64)
    motion_ms = None
    if true_ms is not None and shown is not None and len(intake) >= SitlClock.MIN_TIMESYNCS:
        # the intake at the instant the correlation stands for: SITL's clock drifts from ours
        fwd_ms = theil_sen_at(intake[:, 0], (intake[:, 1] - intake[:, 0]).astype(float), shown[1]) * 1e-6
        motion_ms = true_ms - sitl_ms + fwd_ms - shown[0]
    shown_ms = shown[0] if shown is not None else None
    return {"added_ms": float(added_ms), "measured_ms": measured, "true_ms": true_ms,
            "true_motion_ms": motion_ms, "shown_lag_ms": shown_ms,
            "error_motion_ms": measured - motion_ms if measured is not None and motion_ms is not None else None,
            "error_ms": measured - true_ms if measured is not None and true_ms is not None else None,
            "send_minus_stamp_ms_p50": float(np.median(sends)) * 1e-6 if len(sends) else None,
            "relay_hold_ms_p50": hold_ms, "relay_hold_back_ms_p50": relay.hold_ms_median("to_bridge", since),
            "sitl_clock_ms": sitl_ms, "sitl_clock_serial0_ms": sitl.get("sitl_term_serial0_ms"),
            "sitl_clock_records": (sitl.get("truth_pairs"), sitl.get("intake_timesyncs"), sitl.get("gcs_timesyncs")),
            "sitl_bucket_mismatch_fraction": sitl.get("bucket_mismatch_fraction"),
            "optical_lag_ms": lag_ms,
            "correlation": float(bc.delay_correlation) if np.isfinite(bc.delay_correlation) else None,
            "gyro_source": bc.gyro_source or None, "detail": bc.delay_reason}


def _shown_lag_ms(bc: Any, truth: TruthTrack, clock: SitlClock, since_ns: int) -> tuple[float, float] | None:
    """The SITL time of the motion a pose shows less the pose's stamp (ms, offset-laden like SitlClock's
    records), and the instant (server clock, ns) it stands for: the poses' body rates (from their attitudes)
    correlated with SIM_STATE's body rates at the SITL times of their buckets; None without enough rotation
    or records."""
    from visionpos.analysis.autopilot import body_rates_from_attitudes, estimate_lag, weighted_time_ns
    from visionpos.geometry.frames import flu_to_frd

    pairs = np.array([r for r in list(clock.truth) if r[0] >= since_ns], dtype=np.int64).reshape(-1, 2)
    rows = [r for r in list(bc.opt.d) if r[0] >= since_ns]
    t_true, x = truth.snapshot()
    keep = t_true >= since_ns
    if len(rows) < 50 or len(pairs) < 50 or keep.sum() < 50:
        return None
    off = pairs[:, 1] - pairs[:, 0]  # SITL time less arrival, per SIM_STATE: interpolated onto the track's
    t_sitl = t_true[keep] + np.round(np.interp(t_true[keep], pairs[:, 0], off)).astype(np.int64)
    to, rates = body_rates_from_attitudes(np.array([r[0] for r in rows], dtype=np.int64),
                                          np.array([r[6:10] for r in rows], dtype=float))
    est = estimate_lag(to, rates, t_sitl, flu_to_frd(x[keep, 10:13]), float(np.median(off)), 60e6, step_ns=1e6)
    if est is None or est.correlation <= 0.8:
        return None
    return est.lag_ns * 1e-6, weighted_time_ns(to, rates)


def _optical_lag_ms(bc: Any, truth: TruthTrack, since_ns: int) -> float | None:
    """How far the bridge's poses trail SITL's truth (ms, server clock): the lag of the body rates from the
    poses' attitudes (as the back-channel derives them) behind SIM_STATE's body rates, since since_ns;
    None without enough rotation to correlate."""
    from visionpos.analysis.autopilot import body_rates_from_attitudes, estimate_lag
    from visionpos.geometry.frames import flu_to_frd

    rows = [r for r in list(bc.opt.d) if r[0] >= since_ns]
    t_true, x = truth.snapshot()
    keep = t_true >= since_ns
    if len(rows) < 50 or keep.sum() < 50:
        return None
    to, rates = body_rates_from_attitudes(np.array([r[0] for r in rows], dtype=np.int64),
                                          np.array([r[6:10] for r in rows], dtype=float))
    est = estimate_lag(t_true[keep], flu_to_frd(x[keep, 10:13]), to, rates, 0.0, 50e6, step_ns=1e6)
    return est.lag_ns * 1e-6 if est is not None and est.correlation > 0.8 else None


def truth_now(truth: TruthTrack) -> tuple[int, np.ndarray]:
    t, x = truth.snapshot()
    return (int(t[-1]), x[-1]) if len(t) else (0, np.zeros(13))


async def _goto(gcs: Gcs, north: float, east: float, down: float, timeout_s: float) -> None:
    """SET_POSITION_TARGET_LOCAL_NED (position only) until the true position is within 5 cm of it."""
    target_world = ned_to_world(np.array([north, east, down]))
    end = time.monotonic() + timeout_s
    ok_since = None
    while True:
        gcs.conn.mav.set_position_target_local_ned_send(0, 1, 1, 1, 0b0000_1111_1111_1000, north, east, down,
                                                        0, 0, 0, 0, 0, 0, 0, 0)
        for _ in range(5):
            await asyncio.sleep(0.05)
            _, x = truth_now(gcs.truth)
            if np.linalg.norm(x[:3] - target_world) < 0.05:
                ok_since = ok_since or time.monotonic()
                if time.monotonic() - ok_since > 0.5:
                    return
            else:
                ok_since = None
        if time.monotonic() > end:
            raise SitlError(f"the vehicle did not reach N {north:.2f} E {east:.2f} D {down:.2f} within "
                            f"{timeout_s:g} s (true position {x[:3].round(3).tolist()} in the world frame)")


# ---------------------------------------------------------------- the summary


def _pcts(v: np.ndarray) -> dict[str, float | None]:
    if len(v) == 0:
        return {"p50": None, "p99": None, "max": None}
    return {"p50": float(np.percentile(v, 50)), "p99": float(np.percentile(v, 99)), "max": float(v.max())}


FAILSAFE_WORDS = ("failsafe", "ekf variance", "lane switch", "ekf primary changed", "position lost", "crash")


def flight_summary(gcs: Gcs, truth: TruthTrack, demo: dict[str, Any], record: dict[str, Any], plan: FlightPlan,
                   wall_s: float) -> dict[str, Any]:
    """EKF and vision against SITL's truth, EKF test ratios, every STATUSTEXT, failsafes."""
    a = record.get("armed_ns")
    b = record.get("disarmed_ns") or time.monotonic_ns()
    out: dict[str, Any] = {"completed": bool(record.get("completed")), "error": record.get("error"), "wall_s": wall_s,
                           "viso_delay_ms": record.get("viso_delay_ms")}
    if a is not None:
        loc = np.array([r for r in gcs.local if a <= r[0] <= b], dtype=float).reshape(-1, 4)
        if len(loc):
            p, _, _, _ = truth.sample(loc[:, 0].astype(np.int64))
            ned_true = world_to_ned(p)
            err = loc[:, 1:4] - ned_true
            out["ekf_horizontal_error_mm"] = _pcts(np.hypot(err[:, 0], err[:, 1]) * 1e3)
            out["ekf_vertical_error_mm"] = _pcts(np.abs(err[:, 2]) * 1e3)
        att = np.array([r for r in gcs.attitude if a <= r[0] <= b], dtype=float).reshape(-1, 4)
        if len(att):
            _, _, _, rot = truth.sample(att[:, 0].astype(np.int64))
            yaw_true = euler_ned_frd(rot.as_quat())[:, 2]
            dyaw = np.angle(np.exp(1j * (att[:, 3] - yaw_true)))
            out["ekf_yaw_error_deg"] = _pcts(np.degrees(np.abs(dyaw)))
        ekf = np.array([r for r in gcs.ekf if a <= r[0] <= b], dtype=float).reshape(-1, 6)
        if len(ekf):
            out["ekf_test_ratios"] = {name: {"max": float(ekf[:, k].max()), "p99": float(np.percentile(ekf[:, k], 99))}
                                      for k, name in ((2, "velocity"), (3, "position_horizontal"),
                                                      (4, "position_vertical"), (5, "compass"))}
        if "cut" in record:
            c0, c1, hold = record["cut"]
            t, x = truth.snapshot()
            sel = (t >= c0) & (t <= c1 + 2_000_000_000)
            hold_world = ned_to_world(np.array(hold))
            dev = np.linalg.norm(x[sel, :2] - hold_world[:2], axis=1) * 1e3 if sel.any() else np.zeros(0)
            out["cut"] = {"seconds": plan.cut_s, "max_drift_from_hold_mm": float(dev.max()) if len(dev) else None}
            after = loc[(loc[:, 0] >= c1 + 1_000_000_000) & (loc[:, 0] <= c1 + 3_000_000_000)] if len(loc) else loc
            if len(after):
                p, _, _, _ = truth.sample(after[:, 0].astype(np.int64))
                e = np.hypot(*(after[:, 1:3] - world_to_ned(p)[:, :2]).T) * 1e3
                out["cut"]["ekf_horizontal_error_1_to_3_s_after_mm"] = _pcts(e)
    texts = [t for _, _, t in gcs.texts]
    out["statustext"] = texts
    out["failsafe_or_lane_switch"] = [t for t in texts if any(w in t.lower() for w in FAILSAFE_WORDS)]
    ours = {COPTER_MODES["GUIDED"], COPTER_MODES["LAND"]}
    out["mode_changes_not_ours"] = [MODE_NAMES.get(m, m) for t, m in gcs.modes
                                    if a is not None and a <= t <= b and m not in ours]
    vb = next((x for x in demo.get("bodies", [])), {})
    out["vision"] = {k: vb.get(k) for k in ("position_rmse_mm", "position_max_mm", "rotation_rmse_deg",
                                            "tracked_fraction", "latency_ms")}
    sent = (vb.get("bridge") or {}).get("sent") or 0
    out["vision"]["poses_sent"] = sent
    out["vision"]["poses_per_s"] = sent / demo["duration_s"] if demo.get("duration_s") else None
    out["vision"]["frames_not_fused"] = (demo.get("server") or {}).get("frames_shed")
    out["truth_samples"] = truth.n
    h = out.get("ekf_horizontal_error_mm", {})
    out["ok"] = bool(out["completed"] and h.get("p99") is not None and h["p99"] <= 20.0
                     and not out["failsafe_or_lane_switch"] and not out["mode_changes_not_ours"])
    return out


def format_flight(s: dict[str, Any]) -> str:
    f = lambda v, spec=".1f": "-" if v is None else format(v, spec)  # noqa: E731
    h = s.get("ekf_horizontal_error_mm", {})
    v = s.get("ekf_vertical_error_mm", {})
    y = s.get("ekf_yaw_error_deg", {})
    vis = s["vision"]
    lines = [
        f"visionpos sitl: flight {'completed' if s['completed'] else 'NOT completed'} "
        f"({s['wall_s']:.0f} s wall, VISO_DELAY_MS {f(s.get('viso_delay_ms'), '.0f')})"
        + (f": {s['error']}" if s.get("error") else ""),
        f"  EKF position vs SITL truth (armed to disarmed): horizontal p50 {f(h.get('p50'))} mm, p99 {f(h.get('p99'))}"
        f" mm, max {f(h.get('max'))} mm; vertical p99 {f(v.get('p99'))} mm",
        f"  EKF yaw vs truth: p50 {f(y.get('p50'), '.2f')} deg, p99 {f(y.get('p99'), '.2f')} deg, "
        f"max {f(y.get('max'), '.2f')} deg",
        f"  vision (fusion output) vs truth: RMS {f(vis.get('position_rmse_mm'), '.2f')} mm, max "
        f"{f(vis.get('position_max_mm'), '.2f')} mm, rotation RMS {f(vis.get('rotation_rmse_deg'), '.3f')} deg; "
        f"{vis['poses_sent']} poses sent to SITL ({f(vis.get('poses_per_s'))} per s); "
        f"{vis.get('frames_not_fused') or 0} camera frames queued too long to fuse",
    ]
    for name, r in (s.get("ekf_test_ratios") or {}).items():
        lines.append(f"  EKF test ratio {name}: max {r['max']:.2f}, p99 {r['p99']:.2f}")
    if "cut" in s:
        c = s["cut"]
        e = c.get("ekf_horizontal_error_1_to_3_s_after_mm") or {}
        lines.append(f"  vision cut {c['seconds']:g} s: true drift from the hold point max "
                     f"{f(c['max_drift_from_hold_mm'])} mm; EKF error 1-3 s after: p99 {f(e.get('p99'))} mm")
    if "link_delay" in s:
        d = s["link_delay"]
        lines.append(f"  link delay {d['added_ms']:g} ms each way: capture->autopilot delay measured by the "
                     f"back-channel {_fmt(d['measured_ms'])} ms, true {_fmt(d['true_ms'])} ms (send-stamp "
                     f"{_fmt(d['send_minus_stamp_ms_p50'])} + relay {_fmt(d['relay_hold_ms_p50'])} + SITL's truth "
                     f"age and intake {_fmt(d.get('sitl_clock_ms'))}), difference "
                     f"{_fmt(d['error_ms'])} ms; poses behind SITL's truth {_fmt(d['optical_lag_ms'])} ms; "
                     f"{d['detail']}")
    lines.append(f"  failsafe / lane switch messages: {s['failsafe_or_lane_switch'] or 'none'}; "
                 f"mode changes not commanded: {s['mode_changes_not_ours'] or 'none'}")
    lines.append("  STATUSTEXT: " + " | ".join(s["statustext"]))
    rt = s.get("real_time") or {}
    if rt:
        lines.append(f"  real time: {rt['frames_made']} camera frames made, {100 * rt['frames_late_fraction']:.1f}% "
                     f"more than {LATE_NS // 1_000_000} ms late, {100 * rt['frames_not_fused_fraction']:.1f}% not "
                     "fused (queued too long): above a few % this host could not keep up, and the figures above "
                     "measure the host, not the EKF")
    lines.append(f"  target (EKF horizontal p99 <= 20 mm, no failsafe): {'met' if s['ok'] else 'NOT met'}")
    return "\n".join(lines)
