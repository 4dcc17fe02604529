"""The bridge's MAVLink side as the server sees it: Bridge, one sink for every configured vehicle.

The server calls Bridge.publish(states) on its asyncio loop at every output tick: each state goes
into its vehicle's single-slot mailbox (bridge/vehicle_link.py: VehicleLink, one endpoint, sysid
and sender thread per vehicle; signing in bridge/signing.py) and to the optional UDP pose stream;
it never waits on a socket. Every report_interval_s it prints each vehicle's latencies and the
autopilot delay to set (bridge/link_stats.py: delay_advice).

Vehicles whose bodies share one marker layout (a fleet of identical drones) get the optical body their
back-channel binds them to, not the one named `body` (bridge/fleet_binding.py); the pipeline's
IdentityBook, handed over by the server (use_identity), says whether each track stayed continuous.
"""

from __future__ import annotations

import math
import sys
import time
from typing import Callable

import numpy as np

from bridge.config import parse_pose_stream, parse_vehicles
from bridge.fleet_binding import FleetBinding
from bridge.link_stats import delay_advice
from bridge.vehicle_link import VehicleLink
from visionpos.config.arena import ArenaConfig
from visionpos.messages import BodyState
from visionpos.server.sinks import Sink

__all__ = ["Bridge", "VehicleLink", "delay_advice"]


class Bridge(Sink):
    """Every configured vehicle's MAVLink link plus the optional UDP pose stream.

    settings (runtime, not YAML): clock_ns (callable -> int ns; default
    time.monotonic_ns, the server clock), pose_stream (bool, default True:
    run the arena's pose_stream section if present), report_interval_s
    (float, default 30; 0 = never: how often to print the latency advice),
    report (callable(str), default print to stderr).
    """

    def __init__(self, arena: ArenaConfig, settings: dict | None = None):
        settings = dict(settings or {})
        self.clock_ns: Callable[[], int] = settings.get("clock_ns", time.monotonic_ns)
        self.vehicles: list[VehicleLink] = [VehicleLink(v, self.clock_ns) for v in parse_vehicles(arena)]
        for v in self.vehicles:  # to tell another of our autopilots on a vehicle's link (a crossed link)
            v.cross.other_keys = {w.cfg.sysid: w.cfg.signing_key for w in self.vehicles
                            if w is not v and w.cfg.signing_key is not None}
        self._by_body: dict[str, VehicleLink] = {v.cfg.body: v for v in self.vehicles}
        self.pose_stream = None
        ps_cfg = parse_pose_stream(arena)
        if ps_cfg is not None and settings.get("pose_stream", True):
            from bridge.pose_stream import PoseStream

            self.pose_stream = PoseStream(ps_cfg, clock_ns=self.clock_ns)
        self.report_interval_ns = int(float(settings.get("report_interval_s", 30.0)) * 1e9)
        self._report: Callable[[str], None] = settings.get("report", lambda s: print(s, file=sys.stderr))
        self._next_report = 0
        self._started = False
        self.fleet = _fleet_binding(arena, self.vehicles)
        self._identity_book = None  # the pipeline's IdentityBook (use_identity), read and told on the loop
        self._last_bound: dict[str, str] = {}  # fleet vehicle -> the body it was last bound to
        self._pad_moving: set[str] = set()  # fleet vehicles seen moving on an unconfirmed pad binding
        self._body_resets: dict[str, int] = {}  # each body's newest reset counter (the shared counter's sum)
        self._several = len(self.vehicles) > 1
        self._shared: int | None = None
        self._by_name = {v.cfg.name: v for v in self.vehicles}

    def use_identity(self, book) -> None:
        """The pipeline's IdentityBook (visionpos/fusion/identity.py): each body's identity state is read at every
        publish and a body bound here is told to it (bind). Called on the server's loop, before any publish."""
        self._identity_book = book

    def imu_sources(self) -> list:
        """The vehicles' IMU samples for the pipeline (bridge/imu_feed.py), each to the body bound to it."""
        from bridge.imu_feed import BridgeImu

        return [BridgeImu(self)]  # called as drain(push); its optical_pose gets the triangulated attitudes

    def vehicle(self, name: str) -> VehicleLink:
        for v in self.vehicles:
            if v.cfg.name == name or v.cfg.body == name:
                return v
        raise KeyError(f"no vehicle or body named {name!r}; have {[v.cfg.name for v in self.vehicles]}")

    def start(self) -> None:
        for v in self.vehicles:
            v.start()
        if self.pose_stream is not None:
            self.pose_stream.start()
        self._next_report = self.clock_ns() + self.report_interval_ns
        self._started = True

    def publish(self, states: list[BodyState]) -> None:
        """Hand each state to its vehicle's mailbox and the pose stream. Never blocks."""
        by_body = self._by_body
        fleet = self.fleet
        if fleet is not None:
            self._bind(states)
        if self._several:  # one reset counter for every vehicle: any body's reset or bridge reset
            resets = self._body_resets
            for st in states:
                resets[st.name] = st.reset_counter
            shared = int(sum(resets.values()) + sum(v.local_resets for v in self.vehicles)) % 256
            if shared != self._shared:
                self._shared = shared
                for v in self.vehicles:
                    v.reset_shared = shared
        for st in states:
            if fleet is not None and st.name in fleet.bodies:
                name = fleet.vehicle_of(st.name)
                v = self._by_name[name] if name is not None else None
                if v is not None and fleet.vehicles[name].on_pad and v.bc.armed and (
                        name in self._pad_moving or v.bc.moving()):
                    # moving on the operator's word: nothing until its motion confirms the pad's binding (an EKF
                    # fed another drone's still pose in its climb learns a wrong climb and flies away)
                    self._pad_moving.add(name)
                    v.held_unconfirmed += 1
                    v.not_sent_why = "held: it moves on its pad's binding, until its motion confirms it"
                    continue
            else:
                v = by_body.get(st.name)
            if v is not None:
                v.offer(st)
        if self.pose_stream is not None:
            self.pose_stream.publish(states)
        if self.report_interval_ns > 0 and self.vehicles:
            now = self.clock_ns()
            if now >= self._next_report:
                self._next_report = now + self.report_interval_ns
                self._report(self.latency_report())

    def _bind(self, states: list[BodyState]) -> None:
        """The fleet's bindings: dropped at once when a track breaks, evaluated every BIND_EVERY_NS."""
        book = self._identity_book
        identity = None
        if book is not None:
            identity = {name: s.value for name, s in zip(book.names, book.state)}
        stop = self.fleet.observe(states, identity)
        now = self.clock_ns()
        made: list[tuple[str, str]] = []
        evaluated = self.fleet.due(now)
        if evaluated:
            telemetry = {name: self._by_name[name].bc.attitude_on_server_clock() for name in self.fleet.vehicles}
            positions = {name: (self._by_name[name].bc.local_position_ns, self._by_name[name].bc.local_position)
                         for name in self.fleet.vehicles}
            more, made = self.fleet.evaluate(now, telemetry, self.fleet.accel_telemetry(self._by_name), positions)
            stop += more
        for name in stop:
            v = self._by_name[name]
            with v._lock:  # a state of the body it no longer gets may wait in its mailbox: never sent
                v._slot = None
            v.bc.optical_epoch += 1
        for name in stop:
            self._pad_moving.discard(name)
        if evaluated or stop:  # the identities change only there: what a vision-gap warning says of an unbound one
            bound = self.fleet.bound
            for name, ident in self.fleet.vehicles.items():
                if ident.body is None or bound.get(ident.body) != name:
                    self._by_name[name].not_sent_why = f"identity {ident.state}: {ident.reason}"
        for body, name in made:
            self._pad_moving.discard(name)
            if self._last_bound.get(name, body) != body:  # another body's poses: the autopilot resets to them
                self._by_name[name].reset()
            self._last_bound[name] = body
            self._by_name[name].bc.optical_epoch += 1
            if book is not None and body in book.names:
                book.bind(book.names.index(body))

    def publish_markers(self, lp) -> None:
        """Loose markers (LoosePoints) go to the pose stream only (autopilots get bodies)."""
        if self.pose_stream is not None:
            self.pose_stream.publish_markers(lp)

    def flush(self, timeout_s: float = 1.0) -> bool:
        """Wait until every vehicle has handled what is in its mailbox (tests, shutdown)."""
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            if not any(v.pending() for v in self.vehicles):
                return True
            time.sleep(0.0005)
        return not any(v.pending() for v in self.vehicles)

    def status_line(self) -> str:
        """Every vehicle's part of the server's status line (a fleet vehicle without a bound body: why)."""
        parts = []
        for v in self.vehicles:
            part = v.status_part()
            b = self.fleet.vehicles.get(v.cfg.name) if self.fleet is not None else None
            if b is not None and b.state != "bound":
                part += f" ({v.cfg.name}: identity {b.state}: {b.reason})"
            parts.append(part)
        return " | ".join(parts)

    def identity(self, name: str) -> dict:
        """A fleet vehicle's binding: {'identity': bound | unresolved | unknown | stopped, 'identity_reason',
        'bound_body'}; {} for a vehicle whose layout is unique (its configured body names it)."""
        b = self.fleet.vehicles.get(name) if self.fleet is not None else None
        if b is None:
            return {}
        return {"identity_binding": b.state, "identity_reason": b.reason, "bound_body": b.body}

    def health(self) -> dict:
        """{vehicle name: VehicleLink.health() and, for a fleet vehicle, its binding (identity)}."""
        return {v.cfg.name: {**v.health(), **self.identity(v.cfg.name)} for v in self.vehicles}

    def latency_report(self) -> str:
        return "\n".join("bridge: " + delay_advice(v.stats()) for v in self.vehicles)

    def stats(self) -> dict:
        out = {"vehicles": {v.cfg.name: {**v.stats(), **self.identity(v.cfg.name)} for v in self.vehicles}}
        if self.fleet is not None:
            out["fleet_binding"] = self.fleet.stats()
        if self.pose_stream is not None:
            out["pose_stream"] = self.pose_stream.stats()
        return out

    def close(self) -> None:
        for v in self.vehicles:
            v.close()
        if self.pose_stream is not None:
            self.pose_stream.close()
        if self._started and self.vehicles and self.report_interval_ns > 0:
            self._report(self.latency_report())
        self._started = False


def _fleet_binding(arena: ArenaConfig, vehicles: list[VehicleLink]) -> FleetBinding | None:
    """The binding of the vehicles whose bodies share one marker layout (None when no two do)."""
    first: dict[bytes, list[str]] = {}
    for b in arena.bodies:
        first.setdefault(np.asarray(b.markers, np.float64).tobytes(), []).append(b.name)
    groups = [names for names in first.values() if len(names) > 1]
    fleet = FleetBinding(groups, {v.cfg.name: v.cfg.body for v in vehicles},
                         {v.cfg.name: math.radians(v.cfg.identity_tolerance_deg) for v in vehicles},
                         {v.cfg.name: v.cfg.silent_backchannel for v in vehicles},
                         frozenset(b.name for b in arena.bodies if b.is_point),
                         {v.cfg.name: v.cfg.pad for v in vehicles if v.cfg.pad is not None},
                         {v.cfg.name: math.radians(v.cfg.yaw_offset_deg) for v in vehicles})
    return fleet if fleet.groups else None
