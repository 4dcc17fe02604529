"""The `server:` section of the arena YAML: declared once here, validated.

Reference table: docs/configuration.md (generated from SERVER below).
"""

from __future__ import annotations

import ipaddress
from dataclasses import dataclass, replace
from pathlib import Path

from visionpos import protocol as P
from visionpos.config.arena import ArenaConfig, Section
from visionpos.config.keys import resolve_key
from visionpos.config.schema import register_section
from visionpos.config.settings import Setting, section
from visionpos.errors import UsageError

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
    "steady slow link is used). Replays have no backlog and never shed.\n"
    "- `pause_views_backlog_ms` relieves the load before it comes to that: while the queue is behind, every "
    "frame is still fused, but triangulated bodies skip their per-frame single-view updates (server/load.py; "
    "counted in `frames_without_view_updates`).\n"
    "- Authentication is on by default: with neither `key_file` nor `insecure: true` the server reads the "
    "default key file and refuses to start without one (docs/security.md).",
    Setting("port", "integer", P.DEFAULT_PORT, "UDP port the stations send to", min=0, max=65535),
    Setting("bind", "text", "127.0.0.1", "address of this host's interface to listen on: the lab network's "
            "(e.g. 192.168.1.10) for real stations, 0.0.0.0 for every interface; `--host` overrides it"),
    Setting("key_file", "text", None, "shared HMAC key file (relative to the arena file); every packet must be "
            "signed with it. Make one with `visionpos keygen` and copy it to every station",
            default_doc="`$VISIONPOS_KEY_FILE`, else `~/.config/visionpos/key`"),
    Setting("insecure", "boolean", False, "run without a key: packets are neither signed nor checked (a "
            "WARNING at start, INSECURE in the status line); not together with key_file"),
    Setting("output_rate_hz", "number", 100.0, "BodyState ticks per second", min=1.0, max=2000.0),
    Setting("start_delay_s", "number", 0.0, "trigger time = server start + this", min=0.0, max=3600.0),
    Setting("duration_s", "number", 0.0, "stop after this long (0 = run until stopped)", min=0.0),
    Setting("vanish_periods", "number", 10.0, "frame periods of silence before a camera counts as gone (its "
            "announced period, or its measured one when it delivers fewer frames)", min=2.0),
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
    Setting("pause_views_backlog_ms", "number", 5.0, "load relief before shedding: once a frame waited longer "
            "than this in the receive queue, triangulated bodies take no per-frame single-view updates (as "
            "fusion.single_view.mode occlusion) until a frame waits less than a fifth of it (0 = off)", min=0.0),
    Setting("tick_phase_lock", "boolean", True, "move the output tick's phase to just after the cameras' frames "
            "arrive, so each tick carries the freshest frame (server/tick_phase.py; one tick interval grows by "
            "less than a period when it moves, none shrinks)"),
)


@dataclass(frozen=True)
class ServerSettings:
    """The arena's `server:` section (every key optional; see SERVER for the meaning of each).

    key: the shared HMAC key; key_file: where it was read from (None: given in memory).
    insecure: no key, by explicit choice. Exactly one of key and insecure: a server without a
    key must have been asked to run without one.
    """

    port: int = SERVER["port"].field_default
    bind: str = SERVER["bind"].field_default
    key: bytes | None = None
    key_file: str | None = None
    insecure: bool = False
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
    pause_views_backlog_ms: float = SERVER["pause_views_backlog_ms"].field_default
    tick_phase_lock: bool = SERVER["tick_phase_lock"].field_default

    def __post_init__(self) -> None:
        if self.key is None and not self.insecure:
            raise ValueError("ServerSettings without a key: give key=<shared key bytes> or insecure=True")
        if self.key is not None and self.insecure:
            raise ValueError("ServerSettings with a key and insecure=True: give one of them")

    @classmethod
    def for_replay(cls, arena: ArenaConfig) -> "ServerSettings":
        """Settings to re-run recorded packets, which are trusted local files: signatures are checked
        only with a key_file the arena names (as the live server did); no default key file is needed."""
        s = SERVER.check(arena.section("server"))
        if s.has("key_file") and not s.data.get("insecure"):
            return parse_server(arena)
        values = SERVER.parse(s)
        values.update(key=None, key_file=None, insecure=True)
        return cls(**values)

    def with_port(self, port: int) -> "ServerSettings":
        return replace(self, port=int(port))

    def with_bind(self, address: str) -> "ServerSettings":
        """This address to listen on (the `--host` option); UsageError when it is no IP address."""
        try:
            ipaddress.ip_address(address)
        except ValueError:
            raise UsageError(f"--host {address}: give an IP address of this host (e.g. 192.168.1.10, "
                             "127.0.0.1, or 0.0.0.0 for every interface)") from None
        return replace(self, bind=address)

    @property
    def loopback(self) -> bool:
        """The server listens on loopback only: stations on other hosts cannot reach it."""
        return ipaddress.ip_address(self.bind).is_loopback


def parse_server(arena: ArenaConfig, key: bytes | None = None) -> ServerSettings:
    """The validated `server:` section with its key read (visionpos.config.keys.resolve_key).

    key: used instead of the default key file when the section names neither key_file nor
    insecure (the demo's in-memory key). Raises ConfigError naming the file, the key and the fix.
    """
    s = SERVER.check(arena.section("server"))
    values = SERVER.parse(s)
    _check_bind(s, values["bind"])
    base = Path(arena.source).parent if Path(arena.source).parent.exists() else None
    values["key"], values["key_file"] = resolve_key(s, base, key, insecure_hint="server.insecure: true")
    return ServerSettings(**values)


def _check_bind(s: Section, address: str) -> None:
    try:
        ipaddress.ip_address(address)
    except ValueError:
        raise s.error("bind", f"{address!r} is no IP address; give the address of this host's interface on the "
                              "stations' network (e.g. 192.168.1.10), 127.0.0.1, or 0.0.0.0 for every "
                              "interface") from None


register_section("server", SERVER, parse_server)
