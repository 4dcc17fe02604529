"""SITL's true pose, and the live arena it drives.

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

LiveArena makes the demo's simulated cameras render that pose live (app/demo.py's LiveSource).
"""

from __future__ import annotations

import asyncio
import dataclasses
import math
import threading
import time
from typing import Any, AsyncIterator, Callable

import numpy as np
from scipy.spatial.transform import Rotation

from visionpos.errors import UsageError
from visionpos.geometry.frames import frd_to_flu, ned_to_world, quat_ned_frd_to_world_body
from visionpos.messages import BlobFrame
from visionpos.sim.trajectories import Trajectory

TRUTH_BLEND_S = 1.0  # time constant pulling the integrated truth to the quantised position
LATLON_TO_M = 0.011131884502145034  # ArduPilot's metres per 1e-7 degree of latitude
LIVE_WINDOW_NS = 40_000_000  # cameras' frames are made 40 ms at a time (a call's cost is mostly fixed) ...
LIVE_MAKE_AT = (0.25, 0.75)  # ... between a quarter and three quarters into the window, cameras spread over it
# (one camera's window costs a few ms of the server's loop: made all at once they would hold up the fusion)
LATE_NS = 50_000_000  # a camera frame made this long after it should have reached the server is late


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
        # the simulation's seconds per ours: PX4 SIH's lockstep clock falls behind ours while the host is loaded,
        # and its velocities and rates are per its own second (set by Px4Gcs from TIMESYNC; 1: the same clock)
        self.rate = 1.0

    def add(self, recv_ns: int, m: Any) -> None:
        """One SIM_STATE message (pymavlink) received at recv_ns (server clock): its velocities and rates taken to
        our clock by self.rate."""
        k = self.rate
        v_ned = np.array([m.vn, m.ve, m.vd], dtype=float) * k
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
                              frd_to_flu(np.array([m.xgyro, m.ygyro, m.zgyro], dtype=float)) * k])
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
    """The demo's live source (app/demo.py LiveSource): the vehicle's body follows SITL's truth (several
    vehicles' bodies, each its own SITL's: `visionpos sitl --vehicles N`, tracks {body: TruthTrack}).

    Each camera's frames are made window by window (LIVE_WINDOW_NS), a quarter to three quarters into
    the window on the server clock (the cameras spread over it): a frame's pose is at most three
    quarters of a window plus the truth's age ahead of the newest SIM_STATE (extrapolated for those
    ms), and a frame exposed early in the window leaves late (more latency, which VISO_DELAY_MS
    absorbs; its capture stamp stays true).
    cut(start_ns, end_ns) hides the live bodies from every camera for a while (the frames still go out,
    without its markers: an occlusion, not a dead station)."""

    def __init__(self, body: str, truth: TruthTrack, more: dict[str, TruthTrack] | None = None):
        self.body = body
        self.truth = truth
        self.tracks = {body: truth, **(more or {})}
        self.origin_ns = [0]
        self.stopped_ns: int | None = None
        self.scenario: Any = None
        self.cuts: list[tuple[int, int]] = []
        self.frames_made = 0
        self.frames_late = 0  # made more than LATE_NS after their receive time: the host fell behind real time

    def prepare(self, scenario: Any) -> Any:
        bodies = tuple(dataclasses.replace(b, trajectory=LiveTrajectory(self.tracks[b.name], self.origin_ns))
                       if b.name in self.tracks else b for b in scenario.bodies)
        missing = set(self.tracks) - {b.name for b in bodies}
        if missing:
            raise UsageError(f"the arena has no simulated body {sorted(missing)[0]!r}")
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
        live_index = np.array([i for i, b in enumerate(sc.bodies) if b.name in self.tracks])
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
                    f = dataclasses.replace(f, blobs=f.blobs[~np.isin(tr.body, live_index)])
                self.frames_made += 1
                if time.monotonic_ns() - f.recv_ns > LATE_NS:
                    self.frames_late += 1
                yield f
            w += 1


# ---------------------------------------------------------------- the GCS link


def truth_now(truth: TruthTrack) -> tuple[int, np.ndarray]:
    t, x = truth.snapshot()
    return (int(t[-1]), x[-1]) if len(t) else (0, np.zeros(13))


SETTLE_RADIUS_M = 0.05  # a waypoint is reached when the true position stays this close ...
SETTLE_S = 0.5  # ... for this long


async def until_settled(truth: TruthTrack, target_world: np.ndarray, timeout_s: float,
                        nudge: Callable[[], None] | None = None,
                        radius_m: float = SETTLE_RADIUS_M) -> np.ndarray | None:
    """Poll the true position every 50 ms (calling nudge(), e.g. a setpoint resent, every 0.25 s) until it
    stays within radius_m of target_world (3,) m, world frame, for SETTLE_S: None then; else, once
    timeout_s has passed, the last true position (3,) m, for the error message."""
    end = time.monotonic() + timeout_s
    ok_since = None
    polls = 0
    while True:
        if nudge is not None and polls % 5 == 0:
            nudge()
        polls += 1
        await asyncio.sleep(0.05)
        _, x = truth_now(truth)
        if np.linalg.norm(x[:3] - target_world) < radius_m:
            ok_since = ok_since or time.monotonic()
            if time.monotonic() - ok_since > SETTLE_S:
                return None
        else:
            ok_since = None
        if time.monotonic() > end:
            return x[:3]

