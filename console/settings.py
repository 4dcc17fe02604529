"""The `console:` section of the arena YAML: the operator console's web server (docs/console.md).

Reference table: docs/configuration.md (generated from CONSOLE below).
"""

from __future__ import annotations

import ipaddress
import re
import secrets
from dataclasses import dataclass, replace
from pathlib import Path

from visionpos.config.arena import ArenaConfig
from visionpos.config.schema import register_section
from visionpos.config.settings import Setting, section
from visionpos.errors import UsageError

DEFAULT_PORT = 8080
MIN_TOKEN_CHARS = 16
_HOST_NAME = re.compile(r"[A-Za-z0-9]([A-Za-z0-9.-]{0,252})")

CONSOLE = section(
    "console",
    "The operator console: a web page with the arena in 3D, every camera's view and the system's health, "
    "served by `visionpos serve`, `demo`, `record` and `replay --view` (docs/console.md). On loopback "
    "(the default) no token is needed; bound to any other address every request must carry the token "
    "(`token`, or a fresh one printed at start).",
    Setting("enabled", "boolean", True, "false: no console (as `--no-console`)"),
    Setting("bind", "text", "127.0.0.1", "address to serve the console on; another than loopback needs the "
            "token in every request; `--console-bind` overrides it"),
    Setting("port", "integer", DEFAULT_PORT, "TCP port of the console (0 = any free port); `--console-port` "
            "overrides it", min=0, max=65535),
    Setting("max_clients", "integer", 4, "browser tabs connected at once; more are refused", min=1, max=64),
    Setting("update_rate_hz", "number", 30.0, "live updates sent to each browser per second", min=1.0,
            max=120.0),
    Setting("camera_view_rate_hz", "number", 10.0, "of those, how many per second carry the camera views (blobs "
            "and predicted markers of every camera: most of an update's cost); at most update_rate_hz", min=1.0,
            max=120.0),
    Setting("stations", "any", [], "station YAML files (relative to the arena file) whose detector `mask`, `rois` "
            "and `ignore` the camera views show, matched to cameras by their camera_id", default_doc="[] (none)"),
    Setting("hosts", "any", [], "host names (besides localhost and this host's IP addresses) the console answers "
            "to, e.g. [mocap.lab]: a request naming any other host is refused (DNS rebinding)",
            default_doc="[] (none)"),
    Setting("token", "text", None, f"access token (at least {MIN_TOKEN_CHARS} characters) for a console bound "
            "to an address other than loopback", default_doc="a fresh one, printed at start"),
)


@dataclass(frozen=True)
class ConsoleSettings:
    """The arena's `console:` section (see CONSOLE for each key).

    token: None on loopback without a configured token (none needed); otherwise every HTTP and
    WebSocket request must carry it. token_generated: it was made at start (print it).
    """

    enabled: bool = True
    bind: str = "127.0.0.1"
    port: int = DEFAULT_PORT
    max_clients: int = 4
    update_rate_hz: float = 30.0
    camera_view_rate_hz: float = 10.0
    token: str | None = None
    token_generated: bool = False
    stations: tuple[str, ...] = ()  # station YAML paths, resolved against the arena file
    hosts: tuple[str, ...] = ()  # extra host names a request may name (lower case)

    def with_address(self, bind: str | None = None, port: int | None = None) -> "ConsoleSettings":
        """--console-bind / --console-port applied (UsageError for a bad address or port)."""
        out = self
        if bind is not None:
            try:
                ipaddress.ip_address(bind)
            except ValueError:
                raise UsageError(f"--console-bind {bind}: give an IP address (127.0.0.1, this host's address, "
                                 "or 0.0.0.0 for every interface)") from None
            out = replace(out, bind=bind)
        if port is not None:
            if not 0 <= int(port) <= 65535:
                raise UsageError(f"--console-port {port}: give 0 to 65535")
            out = replace(out, port=int(port))
        return out.with_token()

    def with_token(self) -> "ConsoleSettings":
        """A fresh token when the console is reachable from other hosts and none was configured."""
        if self.token is None and not self.loopback:
            return replace(self, token=secrets.token_urlsafe(24), token_generated=True)
        return self

    @property
    def loopback(self) -> bool:
        return ipaddress.ip_address(self.bind).is_loopback


def parse_console(arena: ArenaConfig) -> ConsoleSettings:
    """The validated `console:` section (station paths resolved against the arena file)."""
    s = CONSOLE.check(arena.section("console"))
    values = CONSOLE.parse(s)
    try:
        ipaddress.ip_address(values["bind"])
    except ValueError:
        raise s.error("bind", f"{values['bind']!r} is no IP address; give 127.0.0.1 (this computer only), "
                              "this host's address on the lab network, or 0.0.0.0 for every interface") from None
    if values["camera_view_rate_hz"] > values["update_rate_hz"]:
        raise s.error("camera_view_rate_hz", f"{values['camera_view_rate_hz']:g} camera views per second "
                      f"cannot ride on {values['update_rate_hz']:g} updates per second; give at most "
                      "update_rate_hz, or raise update_rate_hz")
    token = values["token"]
    if token is not None and (len(token) < MIN_TOKEN_CHARS or not token.isprintable() or " " in token):
        raise s.error("token", f"give at least {MIN_TOKEN_CHARS} printable characters without spaces (e.g. "
                               "the output of `python -c \"import secrets; print(secrets.token_urlsafe())\"`)")
    stations = s.data.get("stations", [])
    if not isinstance(stations, list) or not all(isinstance(p, str) and p for p in stations):
        raise s.error("stations", "give a list of station YAML paths, e.g. [station1.yaml, station2.yaml]")
    hosts = s.data.get("hosts", [])
    if not isinstance(hosts, list) or not all(isinstance(h, str) and _HOST_NAME.fullmatch(h) for h in hosts):
        raise s.error("hosts", "give a list of host names without port or scheme, e.g. [mocap.lab, arena-pc]")
    values["hosts"] = tuple(h.lower() for h in hosts)
    base = Path(arena.source).parent
    values["stations"] = tuple(str(p if Path(p).is_absolute() else base / p) for p in stations)
    return ConsoleSettings(**values).with_token()


register_section("console", CONSOLE, parse_console)
