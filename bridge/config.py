"""The arena's `vehicles:` and `pose_stream:` sections, validated.

Every error is a visionpos.config.arena.ConfigError naming the file, the key path
(e.g. `vehicles[1].endpoint`) and what would be right. The schema is
documented in docs/autopilot-setup.md (vehicles) and docs/pose-stream.md.
"""

from __future__ import annotations

import hashlib
import ipaddress
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from visionpos.config.arena import ArenaConfig, ConfigError, Section

ENDPOINT_KINDS = ("udpin", "udpout", "tcp", "serial")
MESSAGES = ("vision_position_estimate", "odometry")
TIME_BASES = ("boot", "epoch")

ENDPOINT_HELP = (
    "write it as udpin:HOST:PORT (the autopilot sends to us; we answer the address it sent from), "
    "udpout:HOST:PORT (we send to the autopilot), tcp:HOST:PORT (we connect, e.g. SITL's 5760) "
    "or serial:DEVICE:BAUD (e.g. serial:/dev/ttyUSB0:921600)"
)


@dataclass(frozen=True)
class Endpoint:
    """One MAVLink link. kind udpin/udpout/tcp: host, port; serial: device, baud."""

    kind: str
    host: str = ""
    port: int = 0
    device: str = ""
    baud: int = 0

    def __str__(self) -> str:
        if self.kind == "serial":
            return f"serial:{self.device}:{self.baud}"
        return f"{self.kind}:{self.host}:{self.port}"


def parse_endpoint(text: str) -> Endpoint:
    """'udpin:0.0.0.0:14561' -> Endpoint. Raises ValueError with the accepted forms."""
    if not isinstance(text, str) or ":" not in text:
        raise ValueError(f"{text!r} is not an endpoint; {ENDPOINT_HELP}")
    kind, rest = text.split(":", 1)
    if kind not in ENDPOINT_KINDS:
        raise ValueError(f"unknown link type {kind!r} in {text!r}; {ENDPOINT_HELP}")
    if kind == "serial":
        device, _, baud = rest.rpartition(":")
        if not device or not baud.isdigit() or int(baud) <= 0:
            raise ValueError(f"{text!r}: a serial endpoint needs a device and a baud rate; {ENDPOINT_HELP}")
        return Endpoint(kind, device=device, baud=int(baud))
    host, _, port = rest.rpartition(":")
    if not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise ValueError(f"{text!r}: needs HOST:PORT with a port in 1..65535; {ENDPOINT_HELP}")
    return Endpoint(kind, host=host, port=int(port))


def load_signing_key(path: str | Path) -> bytes:
    """The 32-byte MAVLink2 signing key from a file.

    Accepted: 64 hex characters; exactly 32 raw bytes; or a passphrase
    (one line of text), hashed with SHA-256 the way MAVProxy's
    `signing setup PASSPHRASE` and Mission Planner derive their key.
    """
    data = Path(path).read_bytes()
    text = data.strip()
    try:
        if len(text) == 64:
            return bytes.fromhex(text.decode("ascii"))
    except (UnicodeDecodeError, ValueError):
        pass
    if len(data) == 32:
        return data
    try:
        phrase = text.decode("ascii")
    except UnicodeDecodeError:
        raise ValueError(
            f"{path}: not a signing key: give 64 hex characters, 32 raw bytes or an ASCII passphrase"
        ) from None
    if not phrase:
        raise ValueError(f"{path}: the signing key file is empty")
    return hashlib.sha256(phrase.encode("ascii")).digest()


@dataclass(frozen=True)
class Origin:
    """Geodetic origin of the local frame: degrees, metres above mean sea level."""

    lat: float
    lon: float
    alt: float


@dataclass(frozen=True)
class VehicleConfig:
    """One autopilot fed by the bridge (see docs/autopilot-setup.md).

    pivot_offset: (3,) m, body FLU, from the marker body's origin to the
    vehicle's reference point (the point the autopilot's VISO_POS_* /
    EKF2_EV_POS_* are measured from is then the body origin shifted by it).
    yaw_offset_deg: compass heading of world +x (degrees clockwise from north).
    """

    name: str
    body: str
    body_id: int
    sysid: int
    endpoint: Endpoint
    message: str = "vision_position_estimate"
    vision_speed: bool = False
    rate_hz: float = 50.0
    rate_tolerance_ms: float = 0.1
    max_age_ms: float = 200.0
    yaw_offset_deg: float = 0.0
    pivot_offset: tuple[float, float, float] = (0.0, 0.0, 0.0)
    time_base: str = "boot"
    heartbeat_hz: float = 1.0
    timesync: bool = True
    quality: int = 100
    origin: Origin | None = None
    set_home: bool = True
    origin_interval_s: float = 5.0
    signing_key: bytes | None = None
    signing_link_id: int = 0
    reconnect_min_s: float = 0.5
    reconnect_max_s: float = 5.0
    link_timeout_s: float = 3.0

    @property
    def period_ns(self) -> int:
        """Spacing of the sent poses' stamps: 1/rate_hz."""
        return int(round(1e9 / self.rate_hz))

    @property
    def min_interval_ns(self) -> int:
        """Capture time after the last sent stamp from which the next pose goes out: 1/rate_hz
        less the tolerance (camera capture times jitter by microseconds around an exact
        2-frame spacing); the pose is then stamped on the grid (mavlink.VehicleLink._next_stamp)."""
        return int(round(1e9 / self.rate_hz - self.rate_tolerance_ms * 1e6))


@dataclass(frozen=True)
class PoseStreamConfig:
    """UDP pose stream (see docs/pose-stream.md)."""

    destinations: tuple[tuple[str, int], ...]
    format: str = "json"
    rate_hz: float = 0.0  # 0: every output tick
    multicast_ttl: int = 1
    multicast_loopback: bool = True
    multicast_interface: str = ""
    include_untracked: bool = True
    markers: bool = False  # also send the loose markers (points of no body), in datagrams of their own


def _host_port(s: Section, key: str, value: object) -> tuple[str, int]:
    if not isinstance(value, str) or ":" not in value:
        raise s.error(key, f"expected 'HOST:PORT' (e.g. '127.0.0.1:5005' or '239.255.42.99:5005'), got {value!r}")
    host, _, port = value.rpartition(":")
    if not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise s.error(key, f"expected 'HOST:PORT' with a port in 1..65535, got {value!r}")
    return host, int(port)


def is_multicast(host: str) -> bool:
    try:
        return ipaddress.ip_address(host).is_multicast
    except ValueError:
        return False


def parse_vehicles(arena: ArenaConfig) -> list[VehicleConfig]:
    """Validate `vehicles:` against the arena's bodies. Empty list when absent."""
    top = Section(arena.raw, arena.source, "")
    bodies = {b.name: b for b in arena.bodies}
    out: list[VehicleConfig] = []
    for v in top.items("vehicles"):
        body = v.string("body")
        if body not in bodies:
            raise v.error("body", f"no body named {body!r} in `bodies`; known: {sorted(bodies)}")
        name = v.string("name", body)
        sysid = v.integer("sysid", bodies[body].id, min=1, max=255)
        if "endpoint" not in v.data:
            raise v.error("endpoint", f"required; {ENDPOINT_HELP}")
        try:
            endpoint = parse_endpoint(v.data["endpoint"])
        except ValueError as e:
            raise v.error("endpoint", str(e)) from None
        rate = v.number("rate_hz", 50.0, min=0.1, max=400.0)
        origin = None
        if v.has("origin"):
            o = v.sub("origin")
            origin = Origin(o.number("lat", min=-90, max=90), o.number("lon", min=-180, max=180), o.number("alt", 0.0))
        key = None
        link_id = 0
        if v.has("signing"):
            s = v.sub("signing")
            path = Path(s.string("key_file"))
            if not path.is_absolute():
                path = Path(arena.source).resolve().parent / path
            try:
                key = load_signing_key(path)
            except OSError as e:
                raise s.error("key_file", f"cannot read {path}: {e.strerror or e}") from None
            except ValueError as e:
                raise s.error("key_file", str(e)) from None
            link_id = s.integer("link_id", 0, min=0, max=255)
        rmin = v.number("reconnect_min_s", 0.5, min=0.01)
        out.append(
            VehicleConfig(
                name=name,
                body=body,
                body_id=bodies[body].id,
                sysid=sysid,
                endpoint=endpoint,
                message=v.string("message", "vision_position_estimate", choices=MESSAGES),
                vision_speed=v.boolean("vision_speed", False),
                rate_hz=rate,
                rate_tolerance_ms=v.number("rate_tolerance_ms", 0.1, min=0.0, max=0.5 * 1000.0 / rate),
                max_age_ms=v.number("max_age_ms", 200.0, min=1.0),
                yaw_offset_deg=v.number("yaw_offset_deg", 0.0, min=-360, max=360),
                pivot_offset=tuple(float(x) for x in v.array("pivot_offset", (3,), [0.0, 0.0, 0.0])),
                time_base=v.string("time_base", "boot", choices=TIME_BASES),
                heartbeat_hz=v.number("heartbeat_hz", 1.0, min=0.1, max=50.0),
                timesync=v.boolean("timesync", True),
                quality=v.integer("quality", 100, min=-1, max=100),
                origin=origin,
                set_home=v.boolean("set_home", True),
                origin_interval_s=v.number("origin_interval_s", 5.0, min=0.0),
                signing_key=key,
                signing_link_id=link_id,
                reconnect_min_s=rmin,
                reconnect_max_s=v.number("reconnect_max_s", max(5.0, rmin), min=rmin),
                link_timeout_s=v.number("link_timeout_s", 3.0, min=0.1),
            )
        )
        if out[-1].message == "odometry" and out[-1].vision_speed:
            raise v.error("vision_speed", "ODOMETRY already carries velocity; use vision_speed with message: vision_position_estimate")
    _check_unique(top, out)
    return out


def _check_unique(top: Section, vehicles: list[VehicleConfig]) -> None:
    seen: dict[object, int] = {}
    for i, v in enumerate(vehicles):
        for what, key in (("name", v.name), ("body", ("body", v.body)), ("sysid", ("sysid", v.sysid)), ("endpoint", ("ep", str(v.endpoint)))):
            if key in seen:
                raise ConfigError(
                    top.source,
                    f"vehicles[{i}].{what}",
                    f"same {what} as vehicles[{seen[key]}]; every vehicle needs its own {what} "
                    "(one endpoint and one sysid per vehicle, so no pose goes out on another's link)",
                )
            seen[key] = i
        if v.endpoint.kind == "udpin":
            port_key = ("udpin-port", v.endpoint.port)
            if port_key in seen:
                raise ConfigError(top.source, f"vehicles[{i}].endpoint", f"udpin port {v.endpoint.port} is already used by vehicles[{seen[port_key]}]")
            seen[port_key] = i


def parse_pose_stream(arena: ArenaConfig) -> PoseStreamConfig | None:
    """Validate `pose_stream:`; None when absent or `enabled: false`."""
    if "pose_stream" not in arena.raw:
        return None
    s = arena.section("pose_stream")
    if not s.boolean("enabled", True):
        return None
    raw = s.data.get("destinations", s.data.get("destination"))
    if raw is None:
        raise s.error("destinations", "required: a list of 'HOST:PORT' (unicast or multicast group)")
    items = raw if isinstance(raw, list) else [raw]
    dests = tuple(_host_port(s, f"destinations[{i}]", x) for i, x in enumerate(items))
    if not dests:
        raise s.error("destinations", "needs at least one 'HOST:PORT'")
    rate = s.number("rate_hz", 0.0, min=0.0, max=1000.0)
    if rate and not math.isfinite(rate):
        raise s.error("rate_hz", "must be finite")
    iface = s.string("multicast_interface", "")
    if iface:
        try:
            ipaddress.IPv4Address(iface)
        except ValueError:
            raise s.error("multicast_interface", f"expected the IPv4 address of a local interface, got {iface!r}") from None
    return PoseStreamConfig(
        destinations=dests,
        format=s.string("format", "json", choices=("json", "binary")),
        rate_hz=rate,
        multicast_ttl=s.integer("multicast_ttl", 1, min=0, max=255),
        multicast_loopback=s.boolean("multicast_loopback", True),
        multicast_interface=iface,
        include_untracked=s.boolean("include_untracked", True),
        markers=s.boolean("markers", False),
    )


def pivot_array(cfg: VehicleConfig) -> np.ndarray:
    return np.asarray(cfg.pivot_offset, dtype=np.float64)
