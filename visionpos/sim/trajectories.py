"""Rigid-body trajectories for the simulator: pure functions of time.

Every trajectory maps times t (T,) in seconds (from the scenario start) to a
`Motion`: positions (T, 3) m world, quaternions (T, 4) xyzw body->world,
velocities (T, 3) m/s world and angular velocities (T, 3) rad/s in the body
frame. Positions, velocities and accelerations are analytic. Drone attitude
follows from the acceleration the way a quadrotor must tilt to produce it
(thrust along body z, differential flatness), with a commanded yaw; the body
rate is then the exact derivative of that attitude, taken as a central
difference over +-10 us (relative error ~1e-9, far below anything measured).

Kinds (the `trajectory:` key of a session entry in the `sim` section):
  hover       small smooth drift and yaw wobble around `center`
  square      the thesis flight: a `side` m square at the height of `center`,
              smooth legs between corners (stops at each corner)
  figure8     a lemniscate of Gerono, yaw along the path by default
  aggressive  a tilted circle at exactly `peak_speed` m/s peak with fast yaw
  slalom      an indoor MAV weaving along x: Lissajous path at exactly
              `peak_speed` m/s peak (default 2), lateral swings of ~5 m/s^2
              (roll reversals of +-30 deg), height bob, yaw swinging at up to
              `peak_yaw_rate_deg` deg/s (default 180)
  dash        an indoor MAV flying point to point between `waypoints` the way
              a multirotor does: acceleration ramped to `max_accel` (5 m/s^2)
              within `ramp` (0.2 s), i.e. pitch/roll flicks of ~27 deg, coast
              at `peak_speed` (2 m/s), brake as hard; the heading turns by up
              to 180 deg per leg at up to `peak_yaw_rate_deg` (180 deg/s),
              yaw rate ramped as fast; `pause` s of hover at each waypoint
  wand_wave   hand-waved calibration wand: smooth random 6-DoF motion sweeping
              a box, pointing in widely varied directions
  static      a fixed pose (L-frame on the floor, parked drone)
  fleet       drone `slot` of a fleet of `count` (visionpos/sim/fleet.py): take-off from a row on the floor,
              crossings and overtakings within 0.3 m of a neighbour, a tight hover, landing
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np
from scipy.spatial.transform import Rotation

from visionpos.config.arena import Section

GRAVITY = 9.80665
_OMEGA_STEP_S = 1e-5  # central-difference step for the body rate
_MAX_TILT_DEG = 70.0  # past ~70 deg a quadrotor cannot hold height; the flat attitude map is singular at 90

KINDS = ("hover", "square", "figure8", "aggressive", "slalom", "dash", "wand_wave", "static", "fleet")


@dataclass(frozen=True)
class Motion:
    """Sampled motion of one rigid body.

    positions (T, 3) m world; quaternions (T, 4) xyzw, body->world;
    velocities (T, 3) m/s world; angular_velocities (T, 3) rad/s body frame.
    """

    positions: np.ndarray
    quaternions: np.ndarray
    velocities: np.ndarray
    angular_velocities: np.ndarray

    @property
    def rotations(self) -> Rotation:
        return Rotation.from_quat(self.quaternions)


def _as_times(t: Any) -> np.ndarray:
    return np.atleast_1d(np.asarray(t, dtype=np.float64))


@dataclass(frozen=True)
class Trajectory(ABC):
    """Base class: subclasses give kinematics(t) and attitude(t)."""

    @abstractmethod
    def kinematics(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """t (T,) s -> positions, velocities, accelerations, each (T, 3)."""

    @abstractmethod
    def attitude(self, t: np.ndarray) -> Rotation:
        """t (T,) s -> body->world rotations (T,)."""

    def __call__(self, t: Any) -> Motion:
        """Sample at t (T,) seconds since the scenario start."""
        t = _as_times(t)
        p, v, _ = self.kinematics(t)
        rot = self.attitude(t)
        h = _OMEGA_STEP_S
        r_minus, r_plus = self.attitude(t - h), self.attitude(t + h)
        # body rate: R(t-h)^T R(t+h) = exp([w]x 2h) to third order in h
        omega = (r_minus.inv() * r_plus).as_rotvec() / (2 * h)
        return Motion(p, rot.as_quat(), v, omega)

    def pose(self, t: Any) -> tuple[np.ndarray, Rotation]:
        """Positions (T, 3) and body->world rotations (T,) only (cheaper than __call__)."""
        t = _as_times(t)
        return self.kinematics(t)[0], self.attitude(t)

    def sample_ns(self, times_ns: Any, start_ns: int) -> Motion:
        """Sample at int64 times (T,) ns on the server clock given the scenario start."""
        t = (np.asarray(times_ns, dtype=np.int64) - np.int64(start_ns)).astype(np.float64) * 1e-9
        return self(t)


def _flat_attitude(acc: np.ndarray, yaw: np.ndarray) -> Rotation:
    """Quadrotor attitude (T,) whose thrust axis (body z) produces acc (T, 3) with heading yaw (T,)."""
    zb = acc + np.array([0.0, 0.0, GRAVITY])
    zb /= np.linalg.norm(zb, axis=1, keepdims=True)
    xc = np.column_stack([np.cos(yaw), np.sin(yaw), np.zeros_like(yaw)])
    yb = np.cross(zb, xc)
    yb /= np.linalg.norm(yb, axis=1, keepdims=True)
    xb = np.cross(yb, zb)
    return Rotation.from_matrix(np.stack([xb, yb, zb], axis=2))


@dataclass(frozen=True)
class _Sines:
    """Sum of sinusoids per axis: value, first and second derivative.

    amp, freq_hz, phase: (K, D) arrays; value(t) (T, D).
    """

    amp: np.ndarray
    freq_hz: np.ndarray
    phase: np.ndarray

    @staticmethod
    def random(rng: np.random.Generator, dims: int, k: int, fmin: float, fmax: float, amp: np.ndarray) -> "_Sines":
        """k components per axis in [fmin, fmax] Hz; peak sum per axis equals amp (D,)."""
        a = rng.uniform(0.5, 1.0, (k, dims))
        a = a / a.sum(axis=0, keepdims=True) * np.asarray(amp, float).reshape(1, dims)
        return _Sines(a, rng.uniform(fmin, fmax, (k, dims)), rng.uniform(0, 2 * np.pi, (k, dims)))

    def eval(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        w = 2 * np.pi * self.freq_hz  # (K, D)
        arg = t[:, None, None] * w[None] + self.phase[None]  # (T, K, D)
        s, c = np.sin(arg), np.cos(arg)
        return (
            (self.amp * s).sum(axis=1),
            (self.amp * w * c).sum(axis=1),
            (-self.amp * w * w * s).sum(axis=1),
        )


# ---------------------------------------------------------------- trajectories
@dataclass(frozen=True)
class Hover(Trajectory):
    """Hold `center` with a smooth drift of about `drift` m per axis and +-`yaw_wobble` rad."""

    center: np.ndarray
    yaw: float = 0.0
    drift: _Sines = field(default_factory=lambda: _Sines(np.zeros((1, 3)), np.zeros((1, 3)), np.zeros((1, 3))))
    yaw_wobble: _Sines = field(default_factory=lambda: _Sines(np.zeros((1, 1)), np.zeros((1, 1)), np.zeros((1, 1))))

    def kinematics(self, t):
        p, v, a = self.drift.eval(t)
        return p + self.center, v, a

    def attitude(self, t):
        _, _, a = self.drift.eval(t)
        return _flat_attitude(a, self.yaw + self.yaw_wobble.eval(t)[0][:, 0])


def hover(center, yaw_deg: float = 0.0, drift_m: float = 0.02, yaw_wobble_deg: float = 3.0, rng=None) -> Hover:
    rng = np.random.default_rng(0) if rng is None else rng
    return Hover(
        np.asarray(center, float),
        np.radians(yaw_deg),
        _Sines.random(rng, 3, 3, 0.05, 0.5, np.full(3, drift_m)),
        _Sines.random(rng, 1, 2, 0.05, 0.3, np.full(1, np.radians(yaw_wobble_deg))),
    )


def _smooth_step(tau: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Septic 0->1 profile s(tau) with zero velocity, acceleration and jerk at both
    ends (so a flat quadrotor's body rate stays continuous), and ds/dtau, d2s/dtau2."""
    tau = np.clip(tau, 0.0, 1.0)
    u = 1 - tau
    s = tau**4 * (35 - 84 * tau + 70 * tau**2 - 20 * tau**3)
    ds = 140 * tau**3 * u**3
    dds = 420 * tau**2 * u**2 * (1 - 2 * tau)
    return s, ds, dds


@dataclass(frozen=True)
class Square(Trajectory):
    """Fly a horizontal square of side `side` around `center` (its height is the
    flight height), counter-clockwise from the (-x, -y) corner; each leg takes
    `edge_time` s with a smooth septic profile, then `pause` s at the corner."""

    center: np.ndarray
    side: float = 0.5
    edge_time: float = 2.5
    pause: float = 0.5
    yaw: float = 0.0

    def _corners(self) -> np.ndarray:
        h = self.side / 2
        xy = np.array([[-h, -h], [h, -h], [h, h], [-h, h], [-h, -h]])
        return np.column_stack([xy, np.zeros(5)]) + self.center

    def kinematics(self, t):
        leg = self.edge_time + self.pause
        tm = np.mod(t, 4 * leg)
        k = np.minimum((tm // leg).astype(int), 3)
        s, ds, dds = _smooth_step((tm - k * leg) / self.edge_time)
        c = self._corners()
        d = c[k + 1] - c[k]
        return c[k] + d * s[:, None], d * (ds / self.edge_time)[:, None], d * (dds / self.edge_time**2)[:, None]

    def attitude(self, t):
        return _flat_attitude(self.kinematics(t)[2], np.full(len(t), self.yaw))

    @property
    def peak_speed(self) -> float:
        return 2.1875 * self.side / self.edge_time  # max of ds/dtau is 35/16


@dataclass(frozen=True)
class Figure8(Trajectory):
    """Lemniscate of Gerono around `center`: x = a sin(wt), y = (b/2) sin(2wt),
    size = (2a, b) m, one loop per `period` s; yaw along the velocity unless
    `heading` is False (then fixed `yaw`)."""

    center: np.ndarray
    size: tuple[float, float] = (1.6, 1.0)
    period: float = 8.0
    heading: bool = True
    yaw: float = 0.0

    def kinematics(self, t):
        a, b = self.size[0] / 2, self.size[1]
        w = 2 * np.pi / self.period
        s1, c1, s2, c2 = np.sin(w * t), np.cos(w * t), np.sin(2 * w * t), np.cos(2 * w * t)
        z = np.zeros_like(t)
        p = np.column_stack([a * s1, b / 2 * s2, z]) + self.center
        v = np.column_stack([a * w * c1, b * w * c2, z])
        acc = np.column_stack([-a * w * w * s1, -2 * b * w * w * s2, z])
        return p, v, acc

    def attitude(self, t):
        _, v, acc = self.kinematics(t)
        yaw = np.arctan2(v[:, 1], v[:, 0]) if self.heading else np.full(len(t), self.yaw)
        return _flat_attitude(acc, yaw)


@dataclass(frozen=True)
class Aggressive(Trajectory):
    """Circle of `radius` around `center` with a vertical wave of +-`height_amp`
    at the lap rate w, chosen so the speed peaks at exactly `peak_speed`
    (|v|^2 = w^2 (R^2 + h^2 cos^2 wt)); the body spins in yaw at `yaw_rate`
    rad/s independently of the path. The thrust axis tilts up to
    `max_tilt_deg` into the turn (from_config refuses settings above 70 deg)."""

    center: np.ndarray
    radius: float = 1.0
    peak_speed: float = 3.0
    height_amp: float = 0.3
    yaw_rate: float = 3.0

    @property
    def omega(self) -> float:
        return self.peak_speed / np.hypot(self.radius, self.height_amp)

    @property
    def max_tilt_deg(self) -> float:
        """Largest angle between body z and world z: centripetal R w^2 against g - h w^2."""
        w2 = self.omega**2
        lift = GRAVITY - self.height_amp * w2
        return float(np.degrees(np.arctan2(self.radius * w2, lift)))

    def kinematics(self, t):
        w, r, h = self.omega, self.radius, self.height_amp
        c, s = np.cos(w * t), np.sin(w * t)
        p = np.column_stack([r * c, r * s, h * s]) + self.center
        v = np.column_stack([-r * w * s, r * w * c, h * w * c])
        acc = np.column_stack([-r * w * w * c, -r * w * w * s, -h * w * w * s])
        return p, v, acc

    def attitude(self, t):
        return _flat_attitude(self.kinematics(t)[2], self.yaw_rate * t)


@dataclass(frozen=True)
class Slalom(Trajectory):
    """An indoor MAV weaving along x around `center`: x = a sin(wt),
    y = b sin(3wt), z = h sin(2wt), yaw = yaw_amp sin(2wt + pi/2).

    All three velocity terms peak together at t = 0 (cosines), so the speed
    peaks at exactly `peak_speed`: w = peak_speed / sqrt(a^2 + 9 b^2 + 4 h^2).
    The yaw amplitude is chosen so the yaw rate peaks at exactly
    `peak_yaw_rate` rad/s (2 w yaw_amp). The lateral swing accelerates at up
    to 9 b w^2 (5.6 m/s^2 with the defaults at 2 m/s: roll reversals of about
    +-30 deg at 1 Hz, roll rates of ~200 deg/s); body rates are the sum of
    the yaw and tilt rates."""

    center: np.ndarray
    length: float = 2.0
    swing: float = 0.3
    height_amp: float = 0.2
    peak_speed: float = 2.0
    peak_yaw_rate: float = np.pi

    @property
    def omega(self) -> float:
        a, b, h = self.length / 2, self.swing, self.height_amp
        return self.peak_speed / float(np.sqrt(a * a + 9 * b * b + 4 * h * h))

    @property
    def yaw_amp(self) -> float:
        return self.peak_yaw_rate / (2 * self.omega)

    @property
    def max_tilt_deg(self) -> float:
        """Upper bound of the tilt: the largest horizontal acceleration against g minus the largest drop."""
        w2 = self.omega**2
        horiz = w2 * np.hypot(self.length / 2, 9 * self.swing)
        return float(np.degrees(np.arctan2(horiz, GRAVITY - 4 * self.height_amp * w2)))

    def kinematics(self, t):
        w, a, b, h = self.omega, self.length / 2, self.swing, self.height_amp
        s1, c1 = np.sin(w * t), np.cos(w * t)
        s2, c2 = np.sin(2 * w * t), np.cos(2 * w * t)
        s3, c3 = np.sin(3 * w * t), np.cos(3 * w * t)
        p = np.column_stack([a * s1, b * s3, h * s2]) + self.center
        v = np.column_stack([a * w * c1, 3 * b * w * c3, 2 * h * w * c2])
        acc = -w * w * np.column_stack([a * s1, 9 * b * s3, 4 * h * s2])
        return p, v, acc

    def attitude(self, t):
        yaw = self.yaw_amp * np.cos(2 * self.omega * t)
        return _flat_attitude(self.kinematics(t)[2], yaw)


def _step_integrals(u: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The septic step s(u) held at 0 before u = 0 and at 1 after u = 1, with its first and
    second integrals from 0 (which keep growing past u = 1: u - 1/2 and so on)."""
    c = np.clip(u, 0.0, 1.0)
    over = np.maximum(u - 1.0, 0.0)
    s = c**4 * (35 - 84 * c + 70 * c**2 - 20 * c**3)
    i1 = c**5 * (7 - 14 * c + 10 * c**2 - 2.5 * c**3) + over
    i2 = c**6 * (7 / 6 - 2 * c + 1.25 * c**2 - 2.5 / 9 * c**3) + 0.5 * over + 0.5 * over**2
    return s, i1, i2


@dataclass(frozen=True)
class _BangCoastBang:
    """A jerk-limited rest-to-rest move over `distance` (1-D): the second derivative
    ramps to +`accel` over `ramp` s (septic step), holds, ramps back to 0, the
    first derivative coasts at `speed`, then the mirror image brakes to rest.
    Built from four shifted septic steps, so value, rate and acceleration are
    exact and the jerk is continuous."""

    accel: float
    ramp: float
    speed: float
    distance: float

    @staticmethod
    def make(distance: float, speed: float, accel: float, ramp: float) -> "_BangCoastBang":
        """Move `distance` at up to `speed`; lowers the speed when the move is too short to reach it."""
        if distance < speed * (ramp + speed / accel):  # no coast: solve distance = v (ramp + v / accel)
            speed = accel * (-ramp + np.sqrt(ramp * ramp + 4 * distance / accel)) / 2
        return _BangCoastBang(accel, ramp, speed, distance)

    @property
    def hold(self) -> float:
        return self.speed / self.accel - self.ramp

    @property
    def duration(self) -> float:
        t_acc = self.ramp + self.speed / self.accel  # ramp up, hold, ramp down
        return t_acc + self.distance / self.speed  # accelerating, coasting, braking

    def eval(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """t (T,) s since the start -> value, rate, acceleration (T,) each."""
        r, h = self.ramp, self.hold
        brake = self.duration - 2 * r - h
        x = np.zeros_like(t)
        v = np.zeros_like(t)
        a = np.zeros_like(t)
        for start, sign in ((0.0, 1.0), (r + h, -1.0), (brake, -1.0), (brake + r + h, 1.0)):
            s, i1, i2 = _step_integrals((t - start) / r)
            a += sign * s
            v += sign * r * i1
            x += sign * r * r * i2
        return x * self.accel, v * self.accel, a * self.accel


@dataclass(frozen=True)
class Dash(Trajectory):
    """An indoor MAV dashing from waypoint to waypoint (a closed loop through
    `waypoints` (K, 3), m world), hovering `pause` s at each.

    Each leg is flown the way a multirotor does it: the acceleration ramps to
    `max_accel` m/s^2 within `ramp` s (with the defaults the drone pitches/rolls
    27 deg into the leg in 0.2 s), holds until `peak_speed` m/s, coasts upright,
    then brakes as hard, tilting back the other way (_BangCoastBang:
    jerk-limited, so the body rate is continuous but changes fast: tilt rates
    of ~300 deg/s, angular accelerations of ~4000 deg/s^2).
    Meanwhile the heading turns by up to 180 deg, left on even legs and right
    on odd ones, with the yaw rate ramping to `peak_yaw_rate` rad/s within
    `ramp` s."""

    waypoints: np.ndarray
    peak_speed: float = 2.0
    max_accel: float = 5.0
    ramp: float = 0.2
    peak_yaw_rate: float = np.pi
    pause: float = 0.3

    @property
    def legs(self) -> list[tuple[_BangCoastBang, _BangCoastBang | None, float]]:
        """Per leg: its move, its heading turn (None when it turns by 0) and the turn's sign."""
        d = np.linalg.norm(np.roll(self.waypoints, -1, axis=0) - self.waypoints, axis=1)
        out = []
        for k, dk in enumerate(d):
            move = _BangCoastBang.make(float(dk), self.peak_speed, self.max_accel, self.ramp)
            turn = min(self.peak_yaw_rate * (move.duration - 2 * self.ramp), np.pi)
            yaw = None
            if turn > 0 and self.peak_yaw_rate > 0:
                yaw = _BangCoastBang.make(turn, self.peak_yaw_rate, self.peak_yaw_rate / self.ramp, self.ramp)
            out.append((move, yaw, 1.0 if k % 2 == 0 else -1.0))
        return out

    def _phases(self, t: np.ndarray):
        """Loop count (T,), leg index (T,), time into the leg (T,) and the leg starts (K + 1,)."""
        legs = self.legs
        starts = np.concatenate([[0.0], np.cumsum([m.duration + self.pause for m, _, _ in legs])])
        loop = np.floor(t / starts[-1])
        tm = t - loop * starts[-1]
        k = np.clip(np.searchsorted(starts, tm, side="right") - 1, 0, len(legs) - 1)
        return legs, loop, k, tm - starts[k]

    def kinematics(self, t):
        legs, _, k, tl = self._phases(t)
        w = self.waypoints
        d = np.roll(w, -1, axis=0) - w
        unit = d / np.linalg.norm(d, axis=1, keepdims=True)
        p, v, a = w[k].copy(), np.zeros((len(t), 3)), np.zeros((len(t), 3))
        for j, (move, _, _) in enumerate(legs):
            on = k == j
            x, dx, ddx = move.eval(tl[on])
            p[on] += unit[j] * x[:, None]
            v[on] = unit[j] * dx[:, None]
            a[on] = unit[j] * ddx[:, None]
        return p, v, a

    def attitude(self, t):
        legs, loop, k, tl = self._phases(t)
        turns = np.array([sign * (yaw.distance if yaw is not None else 0.0) for _, yaw, sign in legs])
        heading = np.concatenate([[0.0], np.cumsum(turns)])  # heading[-1]: the net turn of one loop
        yaw = loop * heading[-1] + heading[k]
        for j, (_, turn, sign) in enumerate(legs):
            on = k == j
            if turn is not None:
                yaw[on] += sign * turn.eval(tl[on])[0]
        return _flat_attitude(self.kinematics(t)[2], yaw)

    @property
    def max_tilt_deg(self) -> float:
        """Largest tilt: the horizontal part of max_accel against g minus its downward part, over the legs."""
        d = np.roll(self.waypoints, -1, axis=0) - self.waypoints
        frac = d / np.linalg.norm(d, axis=1, keepdims=True)
        horiz = self.max_accel * np.linalg.norm(frac[:, :2], axis=1)
        down = self.max_accel * np.abs(frac[:, 2])
        return float(np.degrees(np.max(np.arctan2(horiz, np.maximum(GRAVITY - down, 1e-6)))))


DASH_WAYPOINTS = ((-0.9, -0.8, 0.8), (0.9, -0.5, 1.2), (0.5, 0.9, 0.7), (-0.8, 0.6, 1.3))


@dataclass(frozen=True)
class WandWave(Trajectory):
    """A calibration wand waved by hand: position sweeps the box `center` +-
    extent/2 with smooth random sinusoids (0.03-0.25 Hz), and the attitude is
    a smooth random rotation vector of up to ~pi per axis, so the wand axis
    (body x) points in widely varied directions over a minute."""

    center: np.ndarray
    path: _Sines
    spin: _Sines

    def kinematics(self, t):
        p, v, a = self.path.eval(t)
        return p + self.center, v, a

    def attitude(self, t):
        return Rotation.from_rotvec(self.spin.eval(t)[0])


def wand_wave(center, extent, rng=None, max_angle_deg: float = 170.0) -> WandWave:
    rng = np.random.default_rng(0) if rng is None else rng
    ext = np.asarray(extent, float)
    return WandWave(
        np.asarray(center, float),
        _Sines.random(rng, 3, 3, 0.03, 0.25, ext / 2),
        _Sines.random(rng, 3, 3, 0.02, 0.15, np.full(3, np.radians(max_angle_deg))),
    )


@dataclass(frozen=True)
class Static(Trajectory):
    """A fixed pose: position (3,), rotation quaternion xyzw (4,)."""

    position: np.ndarray
    quaternion: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, 0.0, 1.0]))

    def kinematics(self, t):
        n = len(t)
        return np.tile(self.position, (n, 1)), np.zeros((n, 3)), np.zeros((n, 3))

    def attitude(self, t):
        return Rotation.from_quat(np.tile(self.quaternion, (len(t), 1)))

    def __call__(self, t: Any) -> Motion:
        t = _as_times(t)
        p, v, _ = self.kinematics(t)
        return Motion(p, self.attitude(t).as_quat(), v, np.zeros((len(t), 3)))


# --------------------------------------------------------------------- config
def from_config(s: Section, rng: np.random.Generator) -> Trajectory:
    """Build a trajectory from one session entry, e.g.
    `{trajectory: square, center: [0, 0, 0.8], side: 0.5, edge_time: 2.5}`.

    Keys per kind (all optional but `trajectory`):
      hover:      center, yaw_deg, drift (m), yaw_wobble_deg
      square:     center, side, edge_time, pause, yaw_deg
      figure8:    center, size [x, y], period, heading (bool), yaw_deg
      aggressive: center, radius, peak_speed, height_amp, yaw_rate (rad/s)
      slalom:     center, length, swing, height_amp (m), peak_speed (m/s), peak_yaw_rate_deg (deg/s)
      dash:       waypoints [[x, y, z], ...] (m, at least 2), peak_speed (m/s), max_accel (m/s^2), ramp (s),
                  peak_yaw_rate_deg (deg/s), pause (s)
      wand_wave:  center, extent [x, y, z] (m, full size of the swept box), max_angle_deg
      static:     position (or center), yaw_deg or quaternion_xyzw
      fleet:      slot (0-based), count, height (m), yaw_deg
    rng seeds the random parts (hover drift, wand motion).
    """
    kind = s.string("trajectory", choices=KINDS)
    center = s.array("center", (3,), [0.0, 0.0, 0.8])
    build, keys = _FROM_CONFIG[kind]
    out = build(s, center, rng)
    known = {"trajectory", "center"} | keys
    extra = sorted(set(s.data) - known - {"occlusion"})
    if extra:
        raise s.error(extra[0], f"unknown key for a '{kind}' trajectory; known keys: {sorted(known)}")
    return out


def _hover_from(s: Section, center: np.ndarray, rng: np.random.Generator) -> Trajectory:
    return hover(
        center,
        s.number("yaw_deg", 0.0),
        s.number("drift", 0.02, min=0.0, max=1.0),
        s.number("yaw_wobble_deg", 3.0, min=0.0, max=90.0),
        rng,
    )


def _square_from(s: Section, center: np.ndarray, rng: np.random.Generator) -> Trajectory:
    return Square(
        center,
        s.number("side", 0.5, min=0.01),
        s.number("edge_time", 2.5, min=0.1),
        s.number("pause", 0.5, min=0.0),
        np.radians(s.number("yaw_deg", 0.0)),
    )


def _figure8_from(s: Section, center: np.ndarray, rng: np.random.Generator) -> Trajectory:
    size = s.array("size", (2,), [1.6, 1.0])
    if np.any(size <= 0):
        raise s.error("size", f"both sizes must be positive, got {size.tolist()}")
    return Figure8(
        center,
        (float(size[0]), float(size[1])),
        s.number("period", 8.0, min=0.5),
        s.boolean("heading", True),
        np.radians(s.number("yaw_deg", 0.0)),
    )


def _aggressive_from(s: Section, center: np.ndarray, rng: np.random.Generator) -> Trajectory:
    out = Aggressive(
        center,
        s.number("radius", 1.0, min=0.05),
        s.number("peak_speed", 3.0, min=0.01, max=50.0),
        s.number("height_amp", 0.3, min=0.0),
        s.number("yaw_rate", 3.0),
    )
    if out.max_tilt_deg > _MAX_TILT_DEG:
        raise s.error(
            "peak_speed",
            f"{out.peak_speed} m/s on a {out.radius} m circle (height_amp {out.height_amp} m) would tilt "
            f"the drone {out.max_tilt_deg:.0f} deg; lower peak_speed or height_amp, or raise radius",
        )
    return out


def _slalom_from(s: Section, center: np.ndarray, rng: np.random.Generator) -> Trajectory:
    out = Slalom(
        center,
        s.number("length", 2.0, min=0.0),
        s.number("swing", 0.3, min=0.0),
        s.number("height_amp", 0.2, min=0.0),
        s.number("peak_speed", 2.0, min=0.01, max=50.0),
        np.radians(s.number("peak_yaw_rate_deg", 180.0, min=0.0, max=3600.0)),
    )
    if out.length + out.swing + out.height_amp <= 0:
        raise s.error("length", "length, swing and height_amp are all 0: the path is a point")
    if out.max_tilt_deg > _MAX_TILT_DEG:
        raise s.error(
            "peak_speed",
            f"{out.peak_speed} m/s would tilt the drone up to {out.max_tilt_deg:.0f} deg; lower peak_speed "
            f"or swing, or raise length",
        )
    return out


def _dash_from(s: Section, center: np.ndarray, rng: np.random.Generator) -> Trajectory:
    wp = s.array("waypoints", (None, 3), DASH_WAYPOINTS)
    if len(wp) < 2:
        raise s.error("waypoints", f"need at least 2 waypoints, got {len(wp)}")
    legs = np.linalg.norm(np.roll(wp, -1, axis=0) - wp, axis=1)
    if np.any(legs < 1e-3):
        raise s.error("waypoints", f"waypoint {int(np.argmin(legs))} repeats the next one (legs must be > 1 mm)")
    out = Dash(
        wp,
        s.number("peak_speed", 2.0, min=0.01, max=50.0),
        s.number("max_accel", 5.0, min=0.01, max=100.0),
        s.number("ramp", 0.2, min=0.005, max=10.0),
        np.radians(s.number("peak_yaw_rate_deg", 180.0, min=0.0, max=3600.0)),
        s.number("pause", 0.3, min=0.0),
    )
    if out.ramp * out.max_accel > out.peak_speed:
        raise s.error("ramp", f"ramping to {out.max_accel} m/s^2 over {out.ramp} s overshoots peak_speed "
                      f"{out.peak_speed} m/s; shorten ramp or lower max_accel")
    short = float(legs.min())
    if short < 2 * out.max_accel * out.ramp**2:
        raise s.error("waypoints", f"the shortest leg ({short:.3f} m) is too short to ramp the acceleration "
                      f"up and down (needs {2 * out.max_accel * out.ramp**2:.3f} m); space the waypoints out")
    if out.max_tilt_deg > _MAX_TILT_DEG:
        raise s.error(
            "peak_speed",
            f"{out.max_accel} m/s^2 would tilt the drone {out.max_tilt_deg:.0f} deg; lower max_accel",
        )
    return out


def _wand_wave_from(s: Section, center: np.ndarray, rng: np.random.Generator) -> Trajectory:
    ext = s.array("extent", (3,), [1.4, 1.4, 0.7])
    if np.any(ext < 0):
        raise s.error("extent", f"sizes must be >= 0, got {ext.tolist()}")
    return wand_wave(center, ext, rng, s.number("max_angle_deg", 170.0, min=0.0, max=180.0))


def _static_from(s: Section, center: np.ndarray, rng: np.random.Generator) -> Trajectory:
    pos = s.array("position", (3,), center)
    if s.has("quaternion_xyzw"):
        q = s.array("quaternion_xyzw", (4,))
        if np.linalg.norm(q) < 1e-9:
            raise s.error("quaternion_xyzw", "must not be all zero")
        q = q / np.linalg.norm(q)
    else:
        q = Rotation.from_euler("z", s.number("yaw_deg", 0.0), degrees=True).as_quat()
    return Static(pos, q)


def _fleet_from(s: Section, center: np.ndarray, rng: np.random.Generator) -> Trajectory:
    from visionpos.sim.fleet import fleet_route  # fleet.py builds on this module's Trajectory

    count = s.integer("count", min=1, max=100)
    slot = s.integer("slot", min=0, max=99)
    if slot >= count:
        raise s.error("slot", f"slot {slot} is not in 0..{count - 1} (count {count})")
    return fleet_route(slot, count, s.number("height", 1.0, min=0.3, max=3.0), s.number("yaw_deg", 0.0),
                       s.integer("laps", 1, min=1, max=1000))


# each kind's builder and the keys it reads (beside trajectory and center)
_FROM_CONFIG: dict[str, tuple[Callable[[Section, np.ndarray, np.random.Generator], Trajectory], set[str]]] = {
    "hover": (_hover_from, {"yaw_deg", "drift", "yaw_wobble_deg"}),
    "square": (_square_from, {"side", "edge_time", "pause", "yaw_deg"}),
    "figure8": (_figure8_from, {"size", "period", "heading", "yaw_deg"}),
    "aggressive": (_aggressive_from, {"radius", "peak_speed", "height_amp", "yaw_rate"}),
    "slalom": (_slalom_from, {"length", "swing", "height_amp", "peak_speed", "peak_yaw_rate_deg"}),
    "dash": (_dash_from, {"waypoints", "peak_speed", "max_accel", "ramp", "peak_yaw_rate_deg", "pause"}),
    "wand_wave": (_wand_wave_from, {"extent", "max_angle_deg"}),
    "static": (_static_from, {"position", "yaw_deg", "quaternion_xyzw"}),
    "fleet": (_fleet_from, {"slot", "count", "height", "yaw_deg", "laps"}),
}
