"""The `server:` section of the arena YAML: declared once here, validated.

Reference table: docs/configuration.md (generated from SERVER below).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from visionpos import protocol as P
from visionpos.config.arena import ArenaConfig
from visionpos.config.schema import register_section
from visionpos.config.settings import Setting, section

SERVER = section(
    "server",
    "The fusion server: network, output rate, and which frames it accepts. Why the timing keys exist:\n\n"
    "- `max_future_ms` / `max_age_ms` bound the accepted (receive - capture) time; outside it a frame is a "
    "clock jump (or a replay) and is dropped, and `resync_after` such drops in a row make the server ask the "
    "station to resync its clock (in the reply to its next heartbeat).\n"
    "- `shed_backlog_ms` is load shedding: a frame that waited longer than this in the server's receive queue "
    "(from the kernel's arrival stamp to its turn) is checked, counted and recorded but not fused. A host too "
    "slow for its cameras then fuses the freshest frames at the rate it can sustain instead of falling ever "
    "further behind. Only the server's own backlog counts, never a station's or the network's latency (a "
    "steady slow link is used). Replays have no backlog and never shed.",
    Setting("port", "integer", P.DEFAULT_PORT, "UDP port the stations send to", min=0, max=65535),
    Setting("key_file", "text", None, "shared HMAC key file (relative to the arena file); with a key every "
            "packet must be signed", default_doc="(no signing)"),
    Setting("output_rate_hz", "number", 100.0, "BodyState ticks per second", min=1.0, max=2000.0),
    Setting("start_delay_s", "number", 0.0, "trigger time = server start + this", min=0.0, max=3600.0),
    Setting("duration_s", "number", 0.0, "stop after this long (0 = run until stopped)", min=0.0),
    Setting("vanish_periods", "number", 10.0, "frame periods of silence before a camera counts as gone", min=2.0),
    Setting("vanish_min_s", "number", 0.1, "and at least this long", min=0.0),
    Setting("max_future_ms", "number", 50.0, "a frame captured more than this after its receive time is dropped",
            min=0.0),
    Setting("max_age_ms", "number", 500.0, "a frame received more than this after its capture is dropped",
            min=1.0),
    Setting("resync_after", "integer", 10, "clock-jump drops in a row before the station is asked to resync its "
            "clock", min=1),
    Setting("status_period_s", "number", 5.0, "period of the status log line (0 = off)", min=0.0),
    Setting("shed_backlog_ms", "number", 15.0, "frames that waited longer than this in the receive queue are "
            "not fused (0 = off)", min=0.0),
)


@dataclass(frozen=True)
class ServerSettings:
    """The arena's `server:` section (every key optional; see SERVER for the meaning of each).

    key: the bytes of key_file (None: no signing); key_file: its resolved path.
    """

    port: int = SERVER["port"].field_default
    key: bytes | None = None
    key_file: str | None = None
    output_rate_hz: float = SERVER["output_rate_hz"].field_default
    start_delay_s: float = SERVER["start_delay_s"].field_default
    duration_s: float = SERVER["duration_s"].field_default
    vanish_periods: float = SERVER["vanish_periods"].field_default
    vanish_min_s: float = SERVER["vanish_min_s"].field_default
    max_future_ms: float = SERVER["max_future_ms"].field_default
    max_age_ms: float = SERVER["max_age_ms"].field_default
    resync_after: int = SERVER["resync_after"].field_default
    status_period_s: float = SERVER["status_period_s"].field_default
    shed_backlog_ms: float = SERVER["shed_backlog_ms"].field_default

    @classmethod
    def from_arena(cls, arena: ArenaConfig) -> "ServerSettings":
        s = SERVER.check(arena.section("server"))
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
        values = SERVER.parse(s)
        values.pop("key_file")
        return cls(key=key, key_file=key_file, **values)

    def with_port(self, port: int) -> "ServerSettings":
        from dataclasses import replace

        return replace(self, port=int(port))

register_section("server", SERVER)
