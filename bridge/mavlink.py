"""The bridge's MAVLink side as the server sees it: Bridge, one sink for every configured vehicle.

The server calls Bridge.publish(states) on its asyncio loop at every output tick: each state goes
into its vehicle's single-slot mailbox (bridge/vehicle_link.py: VehicleLink, one endpoint, sysid
and sender thread per vehicle; signing in bridge/signing.py) and to the optional UDP pose stream;
it never waits on a socket. Every report_interval_s it prints each vehicle's latencies and the
autopilot delay to set (bridge/link_stats.py: delay_advice).
"""

from __future__ import annotations

import sys
import time
from typing import Callable

from bridge.config import parse_pose_stream, parse_vehicles
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
        for st in states:
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
        """Every vehicle's part of the server's status line."""
        return " | ".join(v.status_part() for v in self.vehicles)

    def health(self) -> dict:
        """{vehicle name: VehicleLink.health()}."""
        return {v.cfg.name: v.health() for v in self.vehicles}

    def latency_report(self) -> str:
        return "\n".join("bridge: " + delay_advice(v.stats()) for v in self.vehicles)

    def stats(self) -> dict:
        out = {"vehicles": {v.cfg.name: v.stats() for v in self.vehicles}}
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
