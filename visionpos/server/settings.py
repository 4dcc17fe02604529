"""The `server:` section of the arena YAML, validated."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from visionpos import protocol as P
from visionpos.config.arena import ArenaConfig


@dataclass(frozen=True)
class ServerSettings:
    """The arena's `server:` section (every key optional).

    port: UDP port stations send to. key_file: shared HMAC key (path relative to the
    arena file); with a key every packet must be signed. output_rate_hz: BodyState
    ticks per second. start_delay_s: trigger time = server start + this.
    vanish_periods / vanish_min_s: silence before a camera counts as gone.
    max_future_ms / max_age_ms: accepted window of (receive - capture) time; outside
    it a frame is a clock jump (or a replay) and is dropped. resync_after: that many
    clock-jump drops in a row make the server ask the station to register again.
    status_period_s: period of the status log line (0 = off).
    shed_backlog_ms: load shedding. A frame that waited longer than this in the server's
    receive queue (from the kernel's arrival stamp to its turn) is checked, counted and
    recorded but not fused: a host too slow for its cameras then fuses the freshest frames at
    the rate it can sustain instead of falling ever further behind. Only the server's own
    backlog counts, never a station's or the network's latency (a steady slow link is used).
    0 = off. Replays have no backlog and never shed.
    """

    port: int = P.DEFAULT_PORT
    key: bytes | None = None
    key_file: str | None = None
    output_rate_hz: float = 100.0
    start_delay_s: float = 0.0
    duration_s: float = 0.0
    vanish_periods: float = 10.0
    vanish_min_s: float = 0.1
    max_future_ms: float = 50.0
    max_age_ms: float = 500.0
    resync_after: int = 10
    status_period_s: float = 5.0
    shed_backlog_ms: float = 15.0

    @classmethod
    def from_arena(cls, arena: ArenaConfig) -> "ServerSettings":
        s = arena.section("server")
        known = {"port", "key_file", "output_rate_hz", "start_delay_s", "duration_s", "vanish_periods",
                 "vanish_min_s", "max_future_ms", "max_age_ms", "resync_after", "status_period_s", "shed_backlog_ms"}
        for k in s.data:
            if k not in known:
                raise s.error(str(k), f"unknown key; the server section takes {sorted(known)}")
        key = None
        key_file = None
        if s.has("key_file"):
            key_file = s.string("key_file")
            p = Path(key_file).expanduser()
            if not p.is_absolute() and Path(arena.source).parent.exists():
                p = Path(arena.source).parent / p
            try:
                key = p.read_bytes()
            except OSError as e:
                raise s.error("key_file", f"cannot read {p}: {e.strerror or e}; give the shared key file "
                                          "the stations use") from None
            if not key:
                raise s.error("key_file", f"{p} is empty; the shared HMAC key needs at least 1 byte (use 32 random)")
            key_file = str(p)
        return cls(
            port=s.integer("port", P.DEFAULT_PORT, min=0, max=65535),
            key=key,
            key_file=key_file,
            output_rate_hz=s.number("output_rate_hz", 100.0, min=1.0, max=2000.0),
            start_delay_s=s.number("start_delay_s", 0.0, min=0.0, max=3600.0),
            duration_s=s.number("duration_s", 0.0, min=0.0),
            vanish_periods=s.number("vanish_periods", 10.0, min=2.0),
            vanish_min_s=s.number("vanish_min_s", 0.1, min=0.0),
            max_future_ms=s.number("max_future_ms", 50.0, min=0.0),
            max_age_ms=s.number("max_age_ms", 500.0, min=1.0),
            shed_backlog_ms=s.number("shed_backlog_ms", 15.0, min=0.0),
            resync_after=s.integer("resync_after", 10, min=1),
            status_period_s=s.number("status_period_s", 5.0, min=0.0),
        )

    def with_port(self, port: int) -> "ServerSettings":
        from dataclasses import replace

        return replace(self, port=int(port))
