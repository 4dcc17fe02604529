"""Which optical body feeds which vehicle, where the vehicles' bodies share one marker layout (a fleet).

Geometry cannot tell identical marker sets apart: the tracker names them by continuity
(visionpos/fusion/identity.py, IdentityBook), and the name of an optical body says nothing about which drone it
is. So for the vehicles of one layout group the bridge does not send by the configured `body`: every
BIND_EVERY_NS it compares each vehicle's back-channel (the autopilot's roll, pitch and body rates, on the server
clock) with each optical body's, on one grid of shared instants (the same instants and count for every pair),
sums the squared normalised residuals of each pair (visionpos.analysis.autopilot.identity_residuals: the
per-vehicle identity check's noise model), adds the accelerometers' (accel_costs: the optical track's
acceleration in the body with gravity, against the IMU's specific force from bridge/imu_samples.py, both
low-passed alike, each pair's bias estimated; a vertical climb has no attitude signal but a strong one
here, so drones that take off in turn are bound at their own take-off) where every vehicle of the group sends
its IMU, and assigns bodies to vehicles (assign_identities: Hungarian, a chi-square reject cost per body, the
margin each binding wins by). A body is bound when its margin is at least AMBIGUITY (2 ln 1000: odds of a
thousand to one); the pipeline is told (IdentityBook.bind: its state turns tracked-by-continuity).

- Only a bound body feeds a vehicle; until then the vehicle gets nothing and its state says why
  ("identity unresolved: two candidates (quad3, quad4)", "no motion yet: still vehicles cannot be told
  apart").
- A binding holds while the body's identity stays tracked-by-continuity; after a loss or an ambiguous
  crossing it is dropped at once (the body's samples too: they may be another drone's) and made again
  from fresh samples.
- A held binding is checked at every evaluation: its pair cost over the reject cost, another vehicle's
  cost for its body lower by AMBIGUITY, or the assignment made without the held bindings giving its body
  another vehicle by a margin of AMBIGUITY (a thousand to one: another autopilot moves like it), and the
  output stops first, then the body is bound again.
- A vehicle whose back-channel is silent (no attitude for TELEMETRY_STALE_NS) has identity "unknown"; its
  output follows `silent_backchannel` (bridge/config.py): continuity keeps a held binding while the track
  stays continuous (a loss or ambiguity drops it, and there is nothing to bind again with), stop drops it.

Still vehicles have level attitudes, no rates and no accelerations: every pairing fits and nothing is bound
until they move (docs/autopilot-setup.md, "A fleet": how identity is established before take-off).
Without an IdentityBook (a bridge fed by something else) a body's continuity is its `tracked` flag.
"""

from __future__ import annotations

import collections
import math
from dataclasses import dataclass

import numpy as np
from scipy.stats import chi2

from bridge.backchannel import IDENTITY_RATE_NOISE_RAD_S, IDENTITY_RATE_REL, MAX_PAIR_GAP_NS, TELEMETRY_STALE_NS
from bridge.config import PAD_RADIUS_M
from bridge.point_binding import point_accel_costs
from bridge.position_binding import POSITION_STALE_NS, REBIND_WITHIN_NS, rebind_by_position, vehicle_position_world
from bridge.telemetry import sample_at
from visionpos.analysis.autopilot import (
    accel_residuals,
    assign_identities,
    gaussian_kernel,
    identity_residuals,
    lowpass,
    optical_specific_force,
)
from visionpos.fusion.identity import IdentityState
from visionpos.geometry.frames import quat_world_body_to_ned_frd

BIND_EVERY_NS = 250_000_000  # evaluations of every group's assignment
PAD_MAX_HEIGHT_M = 0.3  # a body standing on a pad (within config.PAD_RADIUS_M) is below this height (on the floor)
PAD_STILL_M = 0.02  # ... and has moved less than this over its samples (it stands there)
WINDOW_NS = 1_000_000_000  # the newest this much of shared instants
MIN_SPAN_NS = 300_000_000  # a body (or vehicle) needs this much history to take part
GRID_NS = 20_000_000  # the shared instants, 50 Hz: near the telemetry's rate, so samples are not repeated
AMBIGUITY = 2.0 * math.log(1000.0)  # margin (summed squared normalised residuals) a binding must win by
REJECT_P = 1e-3  # a true pair's cost exceeds the reject cost this rarely (chi-square, 5 per instant)
STILL_RATE_RAD_S = 0.05  # a window whose optical rates all stay under this: no motion to tell vehicles apart
RING = 256  # optical samples kept per body (at 100 Hz output: 2.5 s)
SAY_DROP_NS = 1_000_000_000  # why a binding was dropped stays the vehicle's reason this long
ACCEL_LOWPASS_S = 0.035  # the Gaussian low-pass of both accelerations (sigma): what the optical track resolves
ACCEL_EVERY = 5  # accelerations compared every 5th shared instant (100 ms): the low-passed samples between are
# not independent, and counting them would overstate the evidence
ACCEL_NOISE_M_S2 = 0.3  # the low-passed optical acceleration's error at rest ...
ACCEL_REL = 0.15  # ... plus this fraction of the body's acceleration (the filter's lag, the clocks' timing)
ACCEL_BIAS_M_S2 = 0.5  # the accelerometer bias an IMU may have (the prior's sigma: a calibrated one has less)
ACCEL_MIN_INSTANTS = 2
STILL_ACCEL_M_S2 = 0.3  # and whose low-passed accelerations all stay under this
RATE_PER_ATT_S = 100.0  # the optical rates' error per axis per radian of attitude uncertainty over the usual
# (fleet20: rate errors of 0.75 rad/s median, 1.34 p90 (norm) where the attitude's sigma was 0.7-1.0 deg against
# a usual 0.25: about 80 per radian per axis at p90)
QUALITY_SPREAD = 2  # shared instants (40 ms) either side a glitch's rate error is allowed for

BOUND, UNRESOLVED, UNKNOWN, STOPPED = "bound", "unresolved", "unknown", "stopped"


def optical_attitude(q_world_flu: np.ndarray, w_flu: np.ndarray) -> np.ndarray:
    """Roll, pitch and body rates as an autopilot reports them: (N, 5) roll, pitch rad (FRD in NED), p, q, r
    rad/s FRD, from quaternions (N, 4) xyzw body FLU -> world z-up and body rates (N, 3) rad/s FLU."""
    q = quat_world_body_to_ned_frd(np.asarray(q_world_flu, float).reshape(-1, 4))
    x, y, z, w = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    roll = np.arctan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
    pitch = np.arcsin(np.clip(2 * (w * y - z * x), -1.0, 1.0))
    rates = np.asarray(w_flu, float).reshape(-1, 3) * np.array([1.0, -1.0, -1.0])
    return np.column_stack([roll, pitch, rates])


def pair_costs(optical: np.ndarray, telemetry: np.ndarray, sigma_att_rad: np.ndarray,
               optical_rate_noise_rad_s: np.ndarray | None = None) -> np.ndarray:
    """Summed squared normalised residuals (B, V) of every (optical body, vehicle) pair over the same M
    instants: optical (B, M, 5) and telemetry (V, M, 5) roll, pitch rad, p, q, r rad/s FRD; sigma_att_rad (V,)
    each vehicle's roll/pitch noise (its identity_tolerance_deg); optical_rate_noise_rad_s (B, M): the optical
    rates' own extra error per axis at each instant (optical_rate_noise; None: none), added to the rate noise."""
    B, M, _ = optical.shape
    V = telemetry.shape[0]
    o = np.broadcast_to(optical[:, None], (B, V, M, 5)).reshape(-1, 5)
    a = np.broadcast_to(telemetry[None], (B, V, M, 5)).reshape(-1, 5)
    extra = (np.zeros((B, M)) if optical_rate_noise_rad_s is None else np.asarray(optical_rate_noise_rad_s, float))
    sigma_rate = IDENTITY_RATE_NOISE_RAD_S + np.broadcast_to(extra[:, None], (B, V, M)).reshape(-1, 1)
    r = identity_residuals(a[:, :2], a[:, 2:], o[:, :2], o[:, 2:], 1.0, sigma_rate, IDENTITY_RATE_REL)
    r[:, :2] /= np.repeat(np.broadcast_to(np.asarray(sigma_att_rad, float)[None], (B, V)).reshape(-1), M)[:, None]
    return (r * r).reshape(B, V, M * 5).sum(axis=2)


def attitude_sigma_rad(covariance: np.ndarray) -> float:
    """The filter's attitude uncertainty of one BodyState: the root of the trace of its covariance's rotation
    block (6, 6: [x, y, z, rx, ry, rz] m^2, rad^2), rad."""
    return float(np.sqrt(max(np.trace(np.asarray(covariance, float)[3:6, 3:6]), 0.0)))


def optical_rate_noise(sigma_att_rad: np.ndarray, usual_rad: np.ndarray) -> np.ndarray:
    """The optical body rates' extra error per axis, rad/s (B, M), from the filter's attitude uncertainty
    sigma_att_rad (B, M) rad (attitude_sigma_rad on the shared instants) over each body's usual one usual_rad
    (B,) rad: RATE_PER_ATT_S per radian of excess, the largest within QUALITY_SPREAD instants either side (a
    glitch's rate error outlasts the covariance's peak a little). Where markers of two bodies merge in some
    cameras, or a body is seen by few, its attitude is less certain and its filtered rates err by up to
    1-2 rad/s: those instants must not count against the binding as a disagreement would."""
    s = np.asarray(sigma_att_rad, float)
    excess = np.maximum(np.nan_to_num(s - np.asarray(usual_rad, float)[:, None], nan=0.0), 0.0)
    k = QUALITY_SPREAD
    pad = np.pad(excess, ((0, 0), (k, k)), mode="edge")
    widened = np.max(np.stack([pad[:, i:i + excess.shape[1]] for i in range(2 * k + 1)]), axis=0)
    return RATE_PER_ATT_S * widened


def reject_cost(instants: int, accel_dof: int = 0) -> float:
    """The cost over `instants` shared instants (5 residuals each) plus accel_dof acceleration residuals
    (accel_costs) a true pair exceeds with probability REJECT_P, by the chi-square law."""
    return float(chi2.isf(REJECT_P, 5 * instants + accel_dof))


def accel_costs(grid_ns: np.ndarray, optical: list[np.ndarray], imu: list[tuple[np.ndarray, np.ndarray]]
                ) -> tuple[np.ndarray, int, float] | None:
    """The accelerometers' part of the pair costs: (cost (B, V), degrees of freedom, the largest low-passed
    optical acceleration m/s^2), or None where fewer than ACCEL_MIN_INSTANTS instants are shared.

    grid_ns (G,) uniform GRID_NS apart; optical: per body its ring (N, 12) (t ns, q xyzw FLU -> world, w, p m);
    imu: per vehicle (times (M,) ns server clock, (M, 3) specific force m/s^2 FRD). Both sides are sampled on
    the grid, low-passed alike (gaussian_kernel, ACCEL_LOWPASS_S), compared every ACCEL_EVERY instants where
    every body and vehicle has a value (accel_residuals: each pair's accelerometer bias estimated, with a prior of
    ACCEL_BIAS_M_S2).
    """
    dt_s = GRID_NS * 1e-9
    kernel = gaussian_kernel(ACCEL_LOWPASS_S, dt_s)
    f_opt, mag = [], []
    for a in optical:
        good, val = sample_at(grid_ns, a[:, 0], a[:, 1:], MAX_PAIR_GAP_NS)
        val[~good] = np.nan
        f, m = optical_specific_force(val[:, 7:10], val[:, 0:4], dt_s, kernel)
        f_opt.append(f)
        mag.append(m)
    f_ap = []
    for t, acc in imu:
        good, val = sample_at(grid_ns, t.astype(np.float64), np.asarray(acc, np.float64), MAX_PAIR_GAP_NS)
        val[~good] = np.nan
        f_ap.append(lowpass(val, kernel))
    known = np.all([np.isfinite(f).all(axis=1) for f in f_opt + f_ap], axis=0)
    at = np.nonzero(known)[0][::-1][::ACCEL_EVERY][::-1]  # every ACCEL_EVERY-th, counted from the newest
    if len(at) < ACCEL_MIN_INSTANTS:
        return None
    fo, m, fa = np.array(f_opt)[:, at], np.array(mag)[:, at], np.array(f_ap)[:, at]  # (B, n, 3), (B, n), (V, n, 3)
    r = accel_residuals(fa[None], fo[:, None], m[:, None], ACCEL_NOISE_M_S2, ACCEL_REL, ACCEL_BIAS_M_S2)
    return (r * r).sum(axis=(2, 3)), 3 * len(at), float(m.max())


@dataclass
class VehicleIdentity:
    """What the bridge says of one fleet vehicle: state (bound, unresolved, unknown, stopped), reason in words,
    the optical body it gets (None: nothing) and the margin of its last binding."""

    state: str = UNRESOLVED
    reason: str = "no optical body bound yet"
    body: str | None = None
    margin: float = float("nan")
    said_until_ns: int = 0  # a dropped binding's reason is said this long before the next one replaces it
    on_pad: bool = False  # bound on its pad, not yet confirmed by its motion (Bridge holds it once armed)


class FleetBinding:
    """Binding of optical bodies to vehicles for the layout groups of a fleet (module docstring).

    groups: per layout group, the body names sharing the layout; vehicle_body: {vehicle name: its configured
    body} (the vehicles of a group are those whose body is in it); sigma_att_rad and silent_policy: per
    vehicle, its identity_tolerance_deg in rad and its silent_backchannel.
    """

    def __init__(self, groups: list[list[str]], vehicle_body: dict[str, str], sigma_att_rad: dict[str, float],
                 silent_policy: dict[str, str], point_bodies: frozenset[str] = frozenset(),
                 pads: dict[str, tuple[float, float]] | None = None, yaw_offset_rad: dict[str, float] | None = None):
        self.groups = [(list(bodies), [v for v, b in vehicle_body.items() if b in bodies]) for bodies in groups]
        self.groups = [(bs, vs) for bs, vs in self.groups if len(vs) > 0 and len(bs) > 1]
        self.bodies = {b for bs, _ in self.groups for b in bs}
        self.vehicles = {v: VehicleIdentity() for _, vs in self.groups for v in vs}
        self.sigma_att_rad = sigma_att_rad
        self.silent_policy = silent_policy
        # (t ns, q xyzw, w FLU, p m, the attitude's sigma rad: attitude_sigma_rad)
        self.rings = {b: collections.deque(maxlen=RING) for b in self.bodies}
        self.bound: dict[str, str] = {}  # optical body -> vehicle
        self.identity: dict[str, str] = {b: IdentityState.LOST.value for b in self.bodies}
        self._next_ns = 0
        self._accel: dict = {}  # the evaluation's accelerations (evaluate)
        self._now_ns = 0
        self.binds = 0  # bindings made
        self.drops = 0  # bindings dropped (loss, ambiguity, disagreement, silence)
        self.disagreements = 0
        self.point_bodies = point_bodies  # single-marker bodies: bound by their accelerations (point_binding.py)
        self.pads = dict(pads or {})  # vehicle -> its parking pad (x, y m, world): _bind_on_pads
        self.pad_refuted: set[str] = set()  # vehicles whose pad binding its motion contradicted: by motion only
        self.yaw_offset_rad = dict(yaw_offset_rad or {})  # vehicle -> its vision frame's yaw (position_binding.py)
        self._lost_ns: dict[str, int] = {}  # vehicle -> when its binding was dropped for a track loss
        self._positions: dict = {}  # the evaluation's {vehicle: (receive ns, LOCAL_POSITION_NED (3,) m)}
        self._group_bodies: list[str] = []

    def vehicle_of(self, body: str) -> str | None:
        """The vehicle that gets this optical body's states now (None: nobody)."""
        return self.bound.get(body)

    def observe(self, states, identity: dict[str, str] | None) -> list[str]:
        """Every output tick: the states' samples and each body's identity state (IdentityState values; None:
        from the tracked flags). Drops the bindings whose track is no longer continuous; returns their
        vehicles (their output stops now)."""
        dropped = []
        for st in states:
            b = st.name
            if b not in self.bodies:
                continue
            was = self.identity[b]
            now = identity.get(b, was) if identity is not None else self._own_identity(b, st.tracked)
            self.identity[b] = now
            # a track lost and acquired again between two ticks goes from continuity to acquired directly
            lost = now == IdentityState.LOST.value or (now == IdentityState.ACQUIRED.value and
                                                      was == IdentityState.CONTINUITY.value)
            if (now in (IdentityState.LOST.value, IdentityState.AMBIGUOUS.value) and was != now) or lost:
                self.rings[b].clear()  # from here on the track may follow another drone
            if b in self.bound and now != IdentityState.CONTINUITY.value:
                v = self._drop(b, "track lost: binding dropped, binding again when it moves or where its EKF says "
                               "it is" if lost else f"identity {now}: binding dropped, binding again when it moves",
                               st.time_ns)
                if lost:
                    self._lost_ns[v] = st.time_ns
                dropped.append(v)
            if st.tracked:
                self.rings[b].append((st.time_ns, *st.quaternion, *st.angular_velocity, *st.position,
                                      attitude_sigma_rad(st.covariance)))
        return dropped

    def _own_identity(self, body: str, tracked: bool) -> str:
        if not tracked:
            return IdentityState.LOST.value
        was = self.identity[body]
        return IdentityState.ACQUIRED.value if was == IdentityState.LOST.value else was

    def _drop(self, body: str, reason: str, now_ns: int, state: str = UNRESOLVED) -> str:
        v = self.bound.pop(body)
        self._lost_ns.pop(v, None)  # an earlier loss no longer counts: only the caller's own loss (observe) does
        self.vehicles[v] = VehicleIdentity(state, reason, said_until_ns=now_ns + SAY_DROP_NS)
        self.drops += 1
        return v

    def accel_telemetry(self, links: dict) -> dict[str, tuple[np.ndarray, np.ndarray] | None]:
        """{vehicle: its accelerometer on the server clock (bridge/imu_samples.py), None before its clock is
        mapped} from the bridge's links {vehicle name: VehicleLink}, mapped as its attitude is. Runs on the
        publishing thread while each link's thread appends: the samples and the clock offsets are copied before
        they are read (iterating the deque itself raised "deque mutated during iteration" in a live fleet demo)."""
        return {v: links[v].bc.accel.on_server_clock(links[v].bc.ap_to_server_ns) for v in self.vehicles}

    def due(self, now_ns: int) -> bool:
        return now_ns >= self._next_ns

    def evaluate(self, now_ns: int, telemetry: dict[str, tuple[np.ndarray, np.ndarray] | None],
                 accel: dict[str, tuple[np.ndarray, np.ndarray] | None] | None = None,
                 positions: dict[str, tuple[int, tuple[float, float, float] | None]] | None = None
                 ) -> tuple[list[str], list[tuple[str, str]]]:
        """Every BIND_EVERY_NS: telemetry {vehicle: (times (N,) ns server clock, (N, 5) roll, pitch, p, q, r) or
        None}; accel {vehicle: (times (M,) ns server clock, (M, 3) specific force m/s^2 FRD) or None} (a group
        uses the accelerations only where every live vehicle of it has some); positions {vehicle: (receive time ns
        server clock, its LOCAL_POSITION_NED (3,) m or None)} (position_binding.py). Returns (vehicles whose binding
        was dropped: stop their output, new bindings [(body, vehicle)]: tell the pipeline)."""
        self._next_ns = now_ns + BIND_EVERY_NS
        self._accel = accel or {}
        self._positions = positions or {}
        dropped: list[str] = []
        made: list[tuple[str, str]] = []
        for bodies, vehicles in self.groups:
            live = self._live_vehicles(now_ns, vehicles, telemetry, dropped)
            self._now_ns, self._group_bodies = now_ns, bodies
            d, m = self._evaluate_group(now_ns, bodies, live, telemetry)
            dropped += d
            made += m
        for b, v in made:
            self.identity[b] = IdentityState.CONTINUITY.value
        return dropped, made

    def _live_vehicles(self, now_ns: int, vehicles: list[str], telemetry: dict, dropped: list[str]) -> list[str]:
        """The vehicles with fresh telemetry; the silent ones get identity 'unknown' and their policy."""
        live = []
        for v in vehicles:
            tel = telemetry.get(v)
            age = (now_ns - int(tel[0][-1])) * 1e-9 if tel is not None and len(tel[0]) else None
            if age is not None and age * 1e9 <= TELEMETRY_STALE_NS:
                live.append(v)
                continue
            silent = ("the back-channel is silent: no attitude from the autopilot" +
                      (f" for {age:.1f} s" if age is not None else " yet"))
            body = next((b for b, x in self.bound.items() if x == v), None)
            stop = self.silent_policy.get(v, "continuity") == "stop"
            if body is None:
                then = "; poses stopped (silent_backchannel: stop)" if stop else \
                    "; nothing to bind it with, nothing sent"
                self.vehicles[v] = VehicleIdentity(UNKNOWN, silent + then)
            elif stop:
                dropped.append(self._drop(body, silent + "; poses stopped (silent_backchannel: stop)", now_ns, UNKNOWN))
            else:
                self.vehicles[v] = VehicleIdentity(UNKNOWN, silent + f"; poses from {body} go on while its track stays "
                                                   "continuous (silent_backchannel: continuity)", body)
        return live

    def _evaluate_group(self, now_ns: int, bodies: list[str], vehicles: list[str], telemetry: dict
                        ) -> tuple[list[str], list[tuple[str, str]]]:
        rows = [b for b in bodies if self.identity[b] != IdentityState.LOST.value and len(self.rings[b]) > 1
                and self.rings[b][-1][0] - self.rings[b][0][0] >= MIN_SPAN_NS]
        if not rows or not vehicles:
            return self._say_unresolved(bodies, vehicles, "no optical body with enough history yet"), []
        ring_arrays = {b: np.array(self.rings[b], dtype=np.float64) for b in rows}
        t_end = min(min(a[-1, 0] for a in ring_arrays.values()), min(float(telemetry[v][0][-1]) for v in vehicles))
        t_start = max(t_end - WINDOW_NS, max(a[0, 0] for a in ring_arrays.values()))
        grid = np.arange(t_end, t_start, -GRID_NS)[::-1]
        if rows[0] in self.point_bodies:
            return self._point_costs(rows, vehicles, grid, ring_arrays, telemetry)
        ok = np.ones(len(grid), bool)
        opt = np.zeros((len(rows), len(grid), 5))
        att_sigma = np.zeros((len(rows), len(grid)))
        for i, b in enumerate(rows):
            a = ring_arrays[b]
            good, val = sample_at(grid, a[:, 0], np.column_stack([optical_attitude(a[:, 1:5], a[:, 5:8]), a[:, 11]]),
                                  MAX_PAIR_GAP_NS)
            ok &= good
            opt[i], att_sigma[i] = val[:, :5], val[:, 5]
        tel = np.zeros((len(vehicles), len(grid), 5))
        for j, v in enumerate(vehicles):
            t, val = telemetry[v]
            good, tel[j] = sample_at(grid, t.astype(np.float64), val, MAX_PAIR_GAP_NS)
            ok &= good
        n = int(ok.sum())
        if n * GRID_NS < MIN_SPAN_NS:
            return self._say_unresolved(bodies, vehicles, "too few shared instants of optics and telemetry yet"), []
        usual = np.array([np.nanmedian(ring_arrays[b][:, 11]) for b in rows])
        noise = optical_rate_noise(att_sigma, usual)[:, ok]
        cost = pair_costs(opt[:, ok], tel[:, ok],
                          np.array([self.sigma_att_rad.get(v, math.radians(3.0)) for v in vehicles]), noise)
        uncertain = noise[:, -(BIND_EVERY_NS // GRID_NS):].max(axis=1) > IDENTITY_RATE_NOISE_RAD_S
        imu = [self._accel.get(v) for v in vehicles]
        acc = None
        if all(x is not None and len(x[0]) > 1 for x in imu):
            acc = accel_costs(grid, [ring_arrays[b] for b in rows], imu)
        still = bool(np.abs(opt[:, ok, 2:]).max() < STILL_RATE_RAD_S) and (acc is None or acc[2] < STILL_ACCEL_M_S2)
        if acc is not None:
            cost = cost + acc[0]
        return self._assign(rows, vehicles, cost, reject_cost(n, acc[1] if acc is not None else 0), still, uncertain)

    def _point_costs(self, rows: list[str], vehicles: list[str], grid: np.ndarray, ring_arrays: dict,
                     telemetry: dict) -> tuple[list[str], list[tuple[str, str]]]:
        """A group of single-marker bodies: the accelerations' costs only (point_binding.py), then _assign."""
        imu = [self._accel.get(v) for v in vehicles]
        if not all(x is not None and len(x[0]) > 1 for x in imu):
            return self._say_unresolved(rows, vehicles, "single-marker bodies are bound by their accelerations: "
                                        "no accelerometer samples from every vehicle yet"), []
        acc = point_accel_costs(grid, [(a[:, 0], a[:, 8:11]) for a in (ring_arrays[b] for b in rows)],
                                [telemetry[v] for v in vehicles], imu, MAX_PAIR_GAP_NS, ACCEL_LOWPASS_S, ACCEL_EVERY,
                                ACCEL_NOISE_M_S2, ACCEL_REL, ACCEL_BIAS_M_S2, ACCEL_MIN_INSTANTS)
        if acc is None:
            return self._say_unresolved(rows, vehicles, "too few shared instants of optics and accelerometers yet"), []
        return self._assign(rows, vehicles, acc[0], reject_cost(0, acc[1]), acc[2] < STILL_ACCEL_M_S2,
                            np.zeros(len(rows), bool))

    def _assign(self, rows: list[str], vehicles: list[str], cost: np.ndarray, reject: float, still: bool,
                uncertain: np.ndarray) -> tuple[list[str], list[tuple[str, str]]]:
        """The assignment of the group's bodies `rows` to its live vehicles from their pair costs (B, V);
        uncertain (B,): bodies whose optical attitude was unreliable since the last check (their bindings are in
        doubt when another binding of the group disagrees)."""
        # a held binding is known by continuity: its body and its vehicle are no one else's, so the others are
        # assigned among themselves (the last still one of a fleet is bound by elimination)
        held = cost.copy()
        for i, b in enumerate(rows):
            v = self.bound.get(b)
            if v in vehicles:
                j = vehicles.index(v)
                held[i, :], held[:, j] = np.nan, np.nan
                held[i, j] = cost[i, j]
            elif v is not None:  # bound to a silent vehicle: not a candidate for the others
                held[i, :] = np.nan
        res = assign_identities(held, reject, AMBIGUITY)
        # the held bindings are checked against the assignment free of them: one that gives a held body another
        # vehicle with confidence says the track followed another drone (a swap the tracker did not see)
        free = assign_identities(cost, reject, AMBIGUITY) if self.bound else res
        return self._apply(rows, vehicles, cost, reject, res, still, free, uncertain)

    def _say_unresolved(self, bodies: list[str], vehicles: list[str], reason: str) -> list[str]:
        for v in vehicles:
            if v not in self.bound.values():
                self._say(v, reason)
        return []

    def _say(self, vehicle: str, reason: str) -> None:
        """An unbound vehicle's reason (after a dropped binding's has been said for SAY_DROP_NS)."""
        if self._now_ns >= self.vehicles[vehicle].said_until_ns:
            self.vehicles[vehicle] = VehicleIdentity(UNRESOLVED, reason)

    def _apply(self, rows: list[str], vehicles: list[str], cost: np.ndarray, reject: float, res, still: bool,
               free, uncertain: np.ndarray | None = None) -> tuple[list[str], list[tuple[str, str]]]:
        """Check the held bindings (a disagreement stops the output first), then make the confident new ones.
        uncertain (len(rows),): the bodies whose optical rates counted less since the last evaluation (None:
        none)."""
        dropped: list[str] = []
        disagreed: set[str] = set()
        col = {v: j for j, v in enumerate(vehicles)}
        for i, b in enumerate(rows):
            v = self.bound.get(b)
            if v is None or v not in col:
                continue  # a silent vehicle's binding: its policy decides (_live_vehicles)
            mine = cost[i, col[v]]
            others = np.delete(cost[i], col[v])
            better = others[np.isfinite(others)].min() if np.isfinite(others).any() else np.inf
            chosen = int(free.vehicle[i])
            other = chosen >= 0 and vehicles[chosen] != v and free.margin[i] >= AMBIGUITY
            if mine > reject or mine > better + AMBIGUITY or other:
                self.disagreements += 1
                self.rings[b].clear()
                alt = np.where(np.isfinite(cost[i]), cost[i], np.inf)
                alt[col[v]] = np.inf
                j = chosen if other else int(np.argmin(alt))
                why = (f"{b} no longer moves like it (cost {mine:.0f} over the reject {reject:.0f})" if mine > reject
                       else f"{b} moves like {vehicles[j]} (cost {cost[i, j]:.0f} against its {mine:.0f})")
                if self.vehicles[v].on_pad:  # the operator's pad was wrong: no pad binds it again
                    self.pad_refuted.add(v)
                    why += f"; its pad {list(self.pads[v])} is not where it stands: bound by its motion only now"
                dropped.append(self._drop(b, f"binding disagreed: {why}: poses stopped, binding again", self._now_ns,
                                          STOPPED))
                disagreed.add(b)
        # a pad binding that passed its check is confirmed by motion once the assignment free of the held
        # bindings gives its body the same vehicle by the margin (the vehicles' motions tell them apart)
        for i, b in enumerate(rows):
            v = self.bound.get(b)
            if v is None or b in disagreed or not self.vehicles[v].on_pad or still:
                continue
            chosen = int(free.vehicle[i])
            if chosen >= 0 and vehicles[chosen] == v and free.margin[i] >= AMBIGUITY:
                self.vehicles[v] = VehicleIdentity(BOUND, f"bound to {b}: on its pad, confirmed by its motion "
                                                   f"(margin {min(free.margin[i], 1e6):.0f})", b,
                                                   float(free.margin[i]))
        # a swap has two sides: a held body whose optical rates counted less since the last evaluation (its
        # attitude uncertain: optical_rate_noise) cannot vouch for its binding by its own check; when another
        # binding of its group disagrees, it may be the other side, and when in doubt it stops too
        first = next(iter(disagreed), None) if uncertain is not None else None
        for k, c in enumerate(rows):
            if first is not None and c not in disagreed and self.bound.get(c) in col and uncertain[k]:
                self.disagreements += 1
                self.rings[c].clear()
                dropped.append(self._drop(c, f"binding in doubt: {first}'s binding disagreed and {c}'s attitude is "
                                             "uncertain (the other side of a swap?): poses stopped, binding again",
                                          self._now_ns, STOPPED))
                disagreed.add(c)
        made = []
        # this evaluation's assignment held the bindings just dropped: they are made again from fresh samples only
        taken = set(self.bound.values()) | set(dropped)
        for i, b in enumerate(rows):
            if b in self.bound or b in disagreed:
                continue
            j = int(res.vehicle[i])
            if j < 0:
                continue
            v = vehicles[j]
            if res.margin[i] >= AMBIGUITY and v not in taken and self.identity[b] != IdentityState.LOST.value:
                self.bound[b] = v
                taken.add(v)
                self.vehicles[v] = VehicleIdentity(BOUND, f"bound to {b} (margin {min(res.margin[i], 1e6):.0f})", b,
                                                   float(res.margin[i]))
                self.binds += 1
                made.append((b, v))
        if self.pads:
            made += self._bind_on_pads(rows, vehicles, taken, disagreed, cost, reject)
        if self._lost_ns:
            made += self._bind_by_position(rows, vehicles, taken, disagreed, cost, reject)
        for v in vehicles:
            if v not in taken:
                self._say(v, self._why(v, vehicles, rows, cost, reject, still))
        return dropped, made

    def _bind_on_pads(self, rows: list[str], vehicles: list[str], taken: set[str], disagreed: set[str],
                      cost: np.ndarray, reject: float) -> list[tuple[str, str]]:
        """Each unbound live vehicle with a pad gets the one unbound body standing still on it (within PAD_RADIUS_M
        horizontally, below PAD_MAX_HEIGHT_M, moved less than PAD_STILL_M over its samples, on no other vehicle's
        pad) whose motion does not contradict it (pair cost under the reject). Its motion checks the binding from
        the first one on (_apply: a body that does not move like it is dropped and stopped)."""
        made = []
        free = [b for b in rows if b not in self.bound and b not in disagreed
                and self.identity[b] != IdentityState.LOST.value]
        where = {}
        for b in free:
            p = np.array(self.rings[b], dtype=float)[:, 8:11]
            if np.abs(p - p[-1]).max() <= PAD_STILL_M:
                where[b] = p[-1]

        def on(p: np.ndarray, pad: tuple[float, float]) -> bool:
            return math.hypot(p[0] - pad[0], p[1] - pad[1]) <= PAD_RADIUS_M and p[2] <= PAD_MAX_HEIGHT_M

        for v in vehicles:
            pad = self.pads.get(v)
            if pad is None or v in taken or v in self.pad_refuted:
                continue
            j = vehicles.index(v)
            here = [b for b in where if b not in self.bound and on(where[b], pad) and cost[rows.index(b), j] <= reject]
            if len(here) != 1 or any(on(where[here[0]], p) for w, p in self.pads.items() if w != v):
                continue
            b = here[0]
            self.bound[b] = v
            taken.add(v)
            self.vehicles[v] = VehicleIdentity(BOUND, f"bound to {b}: standing on its pad {list(pad)} (its motion "
                                               "checks the binding from the first one on)", b, on_pad=True)
            self.binds += 1
            made.append((b, v))
        return made

    def _bind_by_position(self, rows: list[str], vehicles: list[str], taken: set[str], disagreed: set[str],
                          cost: np.ndarray, reject: float) -> list[tuple[str, str]]:
        """Each live vehicle whose binding a track loss dropped lately is bound again to the one body reacquired
        where its EKF says it is (position_binding.py), where its motion does not contradict it (pair cost under
        the reject). Bodies are compared by their origins: a pivot_offset of a few cm is within NEAR_M."""
        now = self._now_ns
        fresh = {}
        for v in vehicles:
            t, ned = self._positions.get(v, (0, None))
            if ned is not None and 0 <= now - t <= POSITION_STALE_NS:
                fresh[v] = vehicle_position_world(np.array(ned, float), self.yaw_offset_rad.get(v, 0.0))
        candidates = {v: p for v, p in fresh.items() if v not in taken and v not in self.bound.values()
                      and now - self._lost_ns.get(v, -(1 << 62)) <= REBIND_WITHIN_NS}
        if not candidates:
            return []
        newest = {b: np.array(self.rings[b][-1][8:11], float) for b in self._group_bodies
                  if self.rings[b] and self.identity[b] != IdentityState.LOST.value}
        free = {b: newest[b] for b in rows if b in newest and b not in self.bound and b not in disagreed}
        made = []
        for b, v, d in rebind_by_position(candidates, fresh, free,
                                          {b: p for b, p in newest.items() if b not in free}):
            if cost[rows.index(b), vehicles.index(v)] > reject:
                continue
            self.bound[b] = v
            taken.add(v)
            age = (now - self._lost_ns.pop(v)) * 1e-9
            self.vehicles[v] = VehicleIdentity(BOUND, f"bound to {b}: reacquired {d * 1e3:.0f} mm from where its "
                                               f"EKF says it is, {age:.1f} s after the loss (its motion checks the "
                                               "binding from the first one on)", b)
            self.binds += 1
            made.append((b, v))
        return made

    def _why(self, v: str, vehicles: list[str], rows: list[str], cost: np.ndarray, reject: float, still: bool) -> str:
        """Why vehicle v has no body, in words (the candidates: the unbound bodies whose cost is under reject)."""
        if still:
            return "no motion yet: still vehicles cannot be told apart (docs/autopilot-setup.md, 'A fleet')"
        j = vehicles.index(v)
        fits = [rows[i] for i in range(len(rows)) if cost[i, j] <= reject and rows[i] not in self.bound]
        if not fits:
            return "no optical body moves like it (every pair over the reject cost)"
        near = sorted(fits, key=lambda b: cost[rows.index(b), j])[:4]
        if len(fits) == 1:
            return f"identity unresolved: one candidate ({near[0]}), not yet by a margin of {AMBIGUITY:.1f}"
        words = {2: "two", 3: "three", 4: "four"}.get(len(fits), str(len(fits)))
        return f"identity unresolved: {words} candidates ({', '.join(near)}{', ...' if len(fits) > 4 else ''})"

    def stats(self) -> dict:
        return {"binds": self.binds, "drops": self.drops, "disagreements": self.disagreements,
                "bound": dict(self.bound)}
