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
from visionpos.config.schema import register_section
from visionpos.config.settings import Setting, section

ENDPOINT_KINDS = ("udpin", "udpout", "tcp", "serial")
MESSAGES = ("vision_position_estimate", "odometry")
TIME_BASES = ("boot", "epoch")
IMU_RATE_WITH_FUSION_HZ = 200.0  # vehicles[i].imu_rate_hz's default where the filter takes the IMU (issue 29)

ENDPOINT_HELP = (
    "write it as udpin:HOST:PORT (the autopilot sends to us; we answer the address it sent from), "
    "udpout:HOST:PORT (we send to the autopilot), tcp:HOST:PORT (we connect, e.g. SITL's 5760) "
    "or serial:DEVICE:BAUD (e.g. serial:/dev/ttyUSB0:921600)"
)

# Drones fly on our output: an address learned from packets anyone can forge is not used.
UDPIN_UNAUTHENTICATED = (
    "a udpin endpoint without signing would learn where to send the poses from unauthenticated packets, so "
    "anyone who can reach port {port} could divert them; add `signing: {{key_file: ...}}` (recommended: the "
    "bridge then answers only packets signed with the vehicle's key) or `autopilot_address: HOST:PORT` (the "
    "address the autopilot sends from), or use udpout:HOST:PORT or tcp:HOST:PORT "
    "(docs/autopilot-setup.md, Signing)"
)


ORIGIN = section(
    "vehicles[i].origin",
    "Geodetic origin of the local frame, sent to the autopilot as its GPS global origin (and home).",
    Setting("lat", "number", doc="latitude (degrees)", min=-90, max=90),
    Setting("lon", "number", doc="longitude (degrees)", min=-180, max=180),
    Setting("alt", "number", 0.0, "altitude above mean sea level (m)"),
)

SIGNING = section(
    "vehicles[i].signing",
    "MAVLink2 message signing.",
    Setting("key_file", "text", doc="signing key file (relative to the arena file): 64 hex characters, 32 raw "
            "bytes, or a passphrase hashed with SHA-256 as MAVProxy and Mission Planner do"),
    Setting("link_id", "integer", 0, "MAVLink2 signing link id", min=0, max=255),
)

VEHICLE = section(
    "vehicles[i]",
    "One autopilot the bridge feeds with the pose of one body (docs/autopilot-setup.md).",
    Setting("body", "text", doc="name of the body in `bodies`"),
    Setting("name", "text", None, "vehicle name in logs", default_doc="the body's name"),
    Setting("sysid", "integer", None, "MAVLink system id of the autopilot", min=1, max=255,
            default_doc="the body's id"),
    Setting("endpoint", "text", doc="the link: udpin:HOST:PORT, udpout:HOST:PORT, tcp:HOST:PORT or "
            "serial:DEVICE:BAUD"),
    Setting("autopilot_address", "text", None, "udpin only: the HOST:PORT the autopilot sends from; poses go "
            "there only and packets from anywhere else are dropped unread",
            default_doc="(learned from signed packets; udpin needs this or signing)"),
    Setting("message", "text", "vision_position_estimate", "MAVLink message carrying the pose", choices=MESSAGES),
    Setting("vision_speed", "boolean", False, "also send VISION_SPEED_ESTIMATE (vision_position_estimate only)"),
    Setting("rate_hz", "number", 50.0, "poses per second", min=0.1, max=400.0),
    Setting("rate_tolerance_ms", "number", 0.1, "a pose's state may be moved this much past its newest frame "
            "to reach its stamp (capture times jitter by microseconds); at most half a period", min=0.0),
    Setting("stamp_age_ms", "number", None, "each pose is stamped this long before the output tick that sends "
            "it, so the stamp -> arrival delay the autopilot sees is steady", min=0.0, max=1000.0,
            default_doc="auto: the 90th percentile of the newest frame's age at the first 500 ticks the body "
            "is tracked, then kept"),
    Setting("max_age_ms", "number", 200.0, "a pose older than this is not sent", min=1.0),
    Setting("yaw_offset_deg", "number", 0.0, "compass heading of world +x (degrees clockwise from north)",
            min=-360, max=360),
    Setting("pivot_offset", "array", [0.0, 0.0, 0.0], "from the body origin to the vehicle's reference point "
            "(m, body FLU)", shape=(3,)),
    Setting("time_base", "text", "boot", "time stamps in the autopilot's boot time or Unix epoch",
            choices=TIME_BASES),
    Setting("heartbeat_hz", "number", 1.0, "heartbeats per second", min=0.1, max=50.0),
    Setting("timesync", "boolean", True, "estimate the autopilot's boot clock with TIMESYNC"),
    Setting("answer_timesync", "boolean", True, "with timesync, also answer the autopilot's TIMESYNC requests "
            "(PX4 stamps the poses with their time_usec once its estimate has converged, else on arrival)"),
    Setting("quality", "integer", 100, "ODOMETRY quality (-1 = invalid, 0..100)", min=-1, max=100),
    Setting("origin", "section", None, "set the autopilot's GPS global origin", spec=ORIGIN,
            default_doc="(not sent)"),
    Setting("set_home", "boolean", True, "with an origin, also set home there"),
    Setting("origin_interval_s", "number", 5.0, "resend the origin this often", min=0.0),
    Setting("signing", "section", None, "MAVLink2 signing", spec=SIGNING, default_doc="(unsigned)"),
    Setting("reconnect_min_s", "number", 0.5, "first reconnect delay after a link failure", min=0.01),
    Setting("reconnect_max_s", "number", 5.0, "longest reconnect delay (at least reconnect_min_s)",
            default_doc="max(5, reconnect_min_s)"),
    Setting("link_timeout_s", "number", 3.0, "no message from the autopilot for this long: the link is down",
            min=0.1),
    Setting("hold_until_origin", "boolean", True, "with an origin: send no pose while the autopilot is heard but "
            "has not reported the origin back (GPS_GLOBAL_ORIGIN); an EKF that takes vision first settles "
            "centimetres off in height"),
    Setting("origin_confirm_timeout_s", "number", 30.0, "send the poses anyway (with a warning) when the origin is "
            "not confirmed this long after the autopilot was first heard (0 = wait for ever)", min=0.0),
    Setting("telemetry_rate_hz", "number", 50.0, "ask the autopilot for its attitude at this rate "
            "(SET_MESSAGE_INTERVAL) for the identity check and the delay measurement; 0 = ask for nothing (no IMU "
            "either)", min=0.0, max=400.0),
    Setting("imu_rate_hz", "number", None, "ask the autopilot for its IMU (RAW_IMU on ArduPilot, HIGHRES_IMU on "
            "PX4) at this rate, requested apart from the attitude: its gyro for the identity check and the delay "
            "measurement, and with fusion.imu.enabled the filter's input between camera frames (the faster the "
            "better: 50 Hz helps the flights less than 200 Hz)", min=1.0, max=1000.0,
            default_doc="200 with fusion.imu.enabled, else telemetry_rate_hz"),
    Setting("identity_check", "text", "stop", "the autopilot's roll, pitch and body rates against the optical "
            "body's: stop = stop sending on a mismatch (e.g. swapped sysids), warn = only say so, off",
            choices=("stop", "warn", "off")),
    Setting("identity_tolerance_deg", "number", 3.0, "noise of the roll/pitch comparison (1 sigma, deg); a "
            "mismatch is a 1 s window more than 3 sigma off on average", min=0.5, max=30.0),
    Setting("silent_backchannel", "text", "continuity", "a vehicle of a fleet (bodies sharing one marker layout, "
            "bound to its optical body by its back-channel: docs/autopilot-setup.md) whose autopilot goes silent: "
            "continuity = keep sending while its body's track stays continuous and stop after any loss or ambiguity "
            "(no re-binding without telemetry), stop = stop at once", choices=("continuity", "stop")),
    Setting("pad", "array", None, "a fleet vehicle's parking pad on the floor (x, y m, world): a still body of its "
            "layout standing within 10 cm of it is bound to it before take-off, and the binding is checked by its "
            "motion from the first one on (docs/autopilot-setup.md, 'A fleet')", shape=(2,),
            default_doc="none: bound only by its motion"),
    Setting("set_delay", "boolean", False, "write the measured delay to the autopilot (PARAM_SET VISO_DELAY_MS "
            "on ArduPilot, EKF2_EV_DELAY on PX4)"),
    Setting("vision_gap_s", "number", 0.5, "no pose sent to the vehicle for this long (s) after poses went: a "
            "vision gap, said loudly (log, status line, health, STATUSTEXT to the autopilot) until a pose goes "
            "again", min=0.05, max=60.0),
    Setting("autopilot_baud", "integer", None, "the serial speed (bit/s) of the autopilot port this link ends "
            "on: ArduPilot moves each pose's arrival back by the time its bytes take at that speed, which the delay "
            "advice takes off (also behind a UDP-to-serial companion; SITL applies its SERIALn_BAUD to UDP too)",
            min=1200, max=100_000_000, default_doc="the endpoint's baud for serial:, else none known"),
    Setting("autopilot", "text", "auto", "the autopilot's estimator, for the pose message's frame and "
            "estimator_type and the delay advice: auto (from its HEARTBEAT), ardupilot or px4",
            choices=("auto", "ardupilot", "px4")),
)

POSE_STREAM = section(
    "pose_stream",
    "UDP pose stream (docs/pose-stream.md).",
    Setting("enabled", "boolean", True, "false: the section is ignored"),
    Setting("destinations", "any", doc="'HOST:PORT' or a list of them (unicast or a multicast group)",
),
    Setting("destination", "any", None, "the same as destinations, for one HOST:PORT",
            default_doc="(or destinations)"),
    Setting("format", "text", "json", "datagram format", choices=("json", "binary")),
    Setting("rate_hz", "number", 0.0, "datagrams per second per body (0 = every output tick)", min=0.0,
            max=1000.0),
    Setting("multicast_ttl", "integer", 1, "multicast time-to-live", min=0, max=255),
    Setting("multicast_loopback", "boolean", True, "multicast datagrams also reach this host"),
    Setting("multicast_interface", "text", "", "IPv4 address of the interface multicast leaves by "
            "(empty: the system's choice)"),
    Setting("include_untracked", "boolean", True, "also send bodies that are not tracked (NaN pose)"),
    Setting("markers", "boolean", False, "also send the loose markers (points of no body), in datagrams of "
            "their own"),
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
    message: str = VEHICLE["message"].field_default
    vision_speed: bool = VEHICLE["vision_speed"].field_default
    rate_hz: float = VEHICLE["rate_hz"].field_default
    rate_tolerance_ms: float = VEHICLE["rate_tolerance_ms"].field_default
    stamp_age_ms: float | None = None  # None: automatic (bridge/stamp_grid.py)
    autopilot_baud: int | None = None  # None: not known (the delay advice then takes no transfer time off)
    max_age_ms: float = VEHICLE["max_age_ms"].field_default
    yaw_offset_deg: float = VEHICLE["yaw_offset_deg"].field_default
    pivot_offset: tuple[float, float, float] = (0.0, 0.0, 0.0)
    time_base: str = VEHICLE["time_base"].field_default
    heartbeat_hz: float = VEHICLE["heartbeat_hz"].field_default
    timesync: bool = VEHICLE["timesync"].field_default
    answer_timesync: bool = VEHICLE["answer_timesync"].field_default
    quality: int = VEHICLE["quality"].field_default
    origin: Origin | None = None
    set_home: bool = VEHICLE["set_home"].field_default
    origin_interval_s: float = VEHICLE["origin_interval_s"].field_default
    signing_key: bytes | None = None
    signing_link_id: int = 0
    autopilot_address: tuple[str, int] | None = None
    reconnect_min_s: float = VEHICLE["reconnect_min_s"].field_default
    reconnect_max_s: float = VEHICLE["reconnect_max_s"].field_default
    link_timeout_s: float = VEHICLE["link_timeout_s"].field_default
    hold_until_origin: bool = VEHICLE["hold_until_origin"].field_default
    origin_confirm_timeout_s: float = VEHICLE["origin_confirm_timeout_s"].field_default
    telemetry_rate_hz: float = VEHICLE["telemetry_rate_hz"].field_default
    imu_rate_hz: float | None = None  # None: as telemetry_rate_hz (parse_vehicles fills in the default)
    identity_check: str = VEHICLE["identity_check"].field_default
    identity_tolerance_deg: float = VEHICLE["identity_tolerance_deg"].field_default
    silent_backchannel: str = VEHICLE["silent_backchannel"].field_default
    set_delay: bool = VEHICLE["set_delay"].field_default
    vision_gap_s: float = VEHICLE["vision_gap_s"].field_default
    autopilot: str = VEHICLE["autopilot"].field_default
    position_only: bool = False  # its body is a single-marker point body: position-only messages (convert.py)
    pad: tuple[float, float] | None = None  # its parking pad (x, y m, world): bound there before it moves

    @property
    def answers_timesync(self) -> bool:
        """Whether the autopilot's TIMESYNC requests are answered on this link (timesync and answer_timesync)."""
        return self.timesync and self.answer_timesync

    @property
    def period_ns(self) -> int:
        """Spacing of the sent poses' stamps: 1/rate_hz."""
        return int(round(1e9 / self.rate_hz))


@dataclass(frozen=True)
class PoseStreamConfig:
    """UDP pose stream (see docs/pose-stream.md)."""

    destinations: tuple[tuple[str, int], ...]
    format: str = POSE_STREAM["format"].field_default
    rate_hz: float = POSE_STREAM["rate_hz"].field_default
    multicast_ttl: int = POSE_STREAM["multicast_ttl"].field_default
    multicast_loopback: bool = POSE_STREAM["multicast_loopback"].field_default
    multicast_interface: str = POSE_STREAM["multicast_interface"].field_default
    include_untracked: bool = POSE_STREAM["include_untracked"].field_default
    markers: bool = POSE_STREAM["markers"].field_default


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
    bodies = {b.name: b for b in arena.bodies}
    out: list[VehicleConfig] = []
    V = VEHICLE
    for v in arena.items("vehicles"):
        v = V.check(v)
        body = V.read(v, "body")
        if body not in bodies:
            raise v.error("body", f"no body named {body!r} in `bodies`; known: {sorted(bodies)}")
        name = V.read(v, "name", default=body)
        sysid = V.read(v, "sysid", default=bodies[body].id)
        if "endpoint" not in v.data:
            raise v.error("endpoint", f"required; {ENDPOINT_HELP}")
        try:
            endpoint = parse_endpoint(v.data["endpoint"])
        except ValueError as e:
            raise v.error("endpoint", str(e)) from None
        rate = V.read(v, "rate_hz")
        origin = None
        if v.has("origin"):
            o = ORIGIN.check(v.sub("origin"))
            origin = Origin(ORIGIN.read(o, "lat"), ORIGIN.read(o, "lon"), ORIGIN.read(o, "alt"))
        key = None
        link_id = 0
        if v.has("signing"):
            s = SIGNING.check(v.sub("signing"))
            path = Path(SIGNING.read(s, "key_file"))
            if not path.is_absolute():
                path = Path(arena.source).resolve().parent / path
            try:
                key = load_signing_key(path)
            except OSError as e:
                raise s.error("key_file", f"cannot read {path}: {e.strerror or e}") from None
            except ValueError as e:
                raise s.error("key_file", str(e)) from None
            link_id = SIGNING.read(s, "link_id")
        autopilot_address = None
        if v.data.get("autopilot_address") is not None:
            if endpoint.kind != "udpin":
                raise v.error("autopilot_address", f"only for udpin endpoints; a {endpoint.kind} endpoint already "
                              "names where the poses go")
            autopilot_address = _host_port(v, "autopilot_address", v.data["autopilot_address"])
        rmin = V.read(v, "reconnect_min_s")
        point = bodies[body].is_point
        if point:
            _refuse_attitude_options(v)
        out.append(
            VehicleConfig(
                name=name,
                body=body,
                body_id=bodies[body].id,
                sysid=sysid,
                endpoint=endpoint,
                message=V.read(v, "message"),
                vision_speed=V.read(v, "vision_speed"),
                rate_hz=rate,
                rate_tolerance_ms=V.read(v, "rate_tolerance_ms", max=0.5 * 1000.0 / rate),
                stamp_age_ms=V.read(v, "stamp_age_ms"),
                max_age_ms=V.read(v, "max_age_ms"),
                yaw_offset_deg=V.read(v, "yaw_offset_deg"),
                pivot_offset=tuple(float(x) for x in V.read(v, "pivot_offset")),
                time_base=V.read(v, "time_base"),
                heartbeat_hz=V.read(v, "heartbeat_hz"),
                timesync=V.read(v, "timesync"),
                answer_timesync=V.read(v, "answer_timesync"),
                quality=V.read(v, "quality"),
                origin=origin,
                set_home=V.read(v, "set_home"),
                origin_interval_s=V.read(v, "origin_interval_s"),
                signing_key=key,
                signing_link_id=link_id,
                autopilot_address=autopilot_address,
                reconnect_min_s=rmin,
                reconnect_max_s=V.read(v, "reconnect_max_s", default=max(5.0, rmin), min=rmin),
                link_timeout_s=V.read(v, "link_timeout_s"),
                hold_until_origin=V.read(v, "hold_until_origin"),
                origin_confirm_timeout_s=V.read(v, "origin_confirm_timeout_s"),
                telemetry_rate_hz=V.read(v, "telemetry_rate_hz"),
                imu_rate_hz=V.read(v, "imu_rate_hz", default=_default_imu_rate_hz(arena, v)),
                identity_check="off" if point else V.read(v, "identity_check"),
                identity_tolerance_deg=V.read(v, "identity_tolerance_deg"),
                silent_backchannel=V.read(v, "silent_backchannel"),
                set_delay=V.read(v, "set_delay"),
                vision_gap_s=V.read(v, "vision_gap_s"),
                autopilot=V.read(v, "autopilot"),
                autopilot_baud=(V.read(v, "autopilot_baud") if "autopilot_baud" in v.data
                                else endpoint.baud if endpoint.kind == "serial" else None),
                position_only=point,
                pad=None if (pad := V.read(v, "pad")) is None else (float(pad[0]), float(pad[1])),
            )
        )
        if out[-1].message == "odometry" and out[-1].vision_speed:
            raise v.error(
                "vision_speed",
                "ODOMETRY already carries velocity; use vision_speed with message: vision_position_estimate",
            )
        if endpoint.kind == "udpin" and key is None and autopilot_address is None:
            raise v.error("endpoint", UDPIN_UNAUTHENTICATED.format(port=endpoint.port))
    _check_unique(arena.source, out)
    _check_pads(arena.source, out)
    return out


PAD_RADIUS_M = 0.10  # a still body this close (horizontally) to a vehicle's pad stands on it (fleet_binding.py)


def _check_pads(source: str, vehicles: list[VehicleConfig]) -> None:
    """Two pads closer than twice the binding radius could both hold one body: refused, naming the key."""
    for i, v in enumerate(vehicles):
        for j in range(i):
            w = vehicles[j]
            if v.pad is not None and w.pad is not None and math.dist(v.pad, w.pad) < 2 * PAD_RADIUS_M:
                raise ConfigError(source, f"vehicles[{i}].pad", f"{list(v.pad)} is {math.dist(v.pad, w.pad):.2f} m "
                                  f"from vehicles[{j}].pad; pads must be at least {2 * PAD_RADIUS_M:g} m apart")


def _refuse_attitude_options(v) -> None:
    """A vehicle of a single-marker (point) body gets its position only: the options about the optical attitude
    are refused with their key (a lever arm needs the attitude; there is no optical attitude to check)."""
    if VEHICLE.read(v, "message") == "odometry" and VEHICLE.read(v, "autopilot") != "px4":
        raise v.error("message", "its body is a single-marker point body (position only): ODOMETRY without an "
                      "attitude (NaN quaternion) is for PX4 only; write autopilot: px4, or use "
                      "message: vision_position_estimate (ArduPilot)")
    if any(float(x) != 0.0 for x in VEHICLE.read(v, "pivot_offset")):
        raise v.error("pivot_offset", "its body is a single-marker point body (position only): there is no optical "
                      "attitude to carry a lever arm; put the marker on the vehicle's reference point and remove "
                      "pivot_offset")
    for key in ("identity_check", "identity_tolerance_deg"):
        if v.has(key):
            raise v.error(key, "its body is a single-marker point body (position only): there is no optical "
                          "attitude to compare with the autopilot's; remove the key (a fleet of point bodies is "
                          "bound by its accelerations, docs/autopilot-setup.md)")


def _default_imu_rate_hz(arena: ArenaConfig, v: Section) -> float:
    """vehicles[i].imu_rate_hz when not given: 200 Hz where the filter takes the IMU (fusion.imu.enabled), else
    the attitude's rate (0 -> 1: only read where telemetry_rate_hz > 0)."""
    from visionpos.fusion.settings import IMU

    if IMU.read(arena.section("fusion").sub("imu"), "enabled"):
        return IMU_RATE_WITH_FUSION_HZ
    return max(VEHICLE.read(v, "telemetry_rate_hz"), 1.0)


def _check_unique(source: str, vehicles: list[VehicleConfig]) -> None:
    seen: dict[object, int] = {}
    for i, v in enumerate(vehicles):
        for what, key in (
            ("name", v.name),
            ("body", ("body", v.body)),
            ("sysid", ("sysid", v.sysid)),
            ("endpoint", ("ep", str(v.endpoint))),
        ):
            if key in seen:
                raise ConfigError(
                    source,
                    f"vehicles[{i}].{what}",
                    f"same {what} as vehicles[{seen[key]}]; every vehicle needs its own {what} "
                    "(one endpoint and one sysid per vehicle, so no pose goes out on another's link)",
                )
            seen[key] = i
        if v.endpoint.kind == "udpin":
            port_key = ("udpin-port", v.endpoint.port)
            if port_key in seen:
                raise ConfigError(
                    source,
                    f"vehicles[{i}].endpoint",
                    f"udpin port {v.endpoint.port} is already used by vehicles[{seen[port_key]}]",
                )
            seen[port_key] = i


def parse_pose_stream(arena: ArenaConfig) -> PoseStreamConfig | None:
    """Validate `pose_stream:`; None when absent or `enabled: false`."""
    if not arena.given("pose_stream"):
        return None
    s = POSE_STREAM.check(arena.section("pose_stream"))
    P = POSE_STREAM
    if not P.read(s, "enabled"):
        return None
    raw = s.data.get("destinations", s.data.get("destination"))
    if raw is None:
        raise s.error("destinations", "required: a list of 'HOST:PORT' (unicast or multicast group)")
    items = raw if isinstance(raw, list) else [raw]
    dests = tuple(_host_port(s, f"destinations[{i}]", x) for i, x in enumerate(items))
    if not dests:
        raise s.error("destinations", "needs at least one 'HOST:PORT'")
    rate = P.read(s, "rate_hz")
    if rate and not math.isfinite(rate):
        raise s.error("rate_hz", "must be finite")
    iface = P.read(s, "multicast_interface")
    if iface:
        try:
            ipaddress.IPv4Address(iface)
        except ValueError:
            raise s.error(
                "multicast_interface", f"expected the IPv4 address of a local interface, got {iface!r}"
            ) from None
    return PoseStreamConfig(
        destinations=dests,
        format=P.read(s, "format"),
        rate_hz=rate,
        multicast_ttl=P.read(s, "multicast_ttl"),
        multicast_loopback=P.read(s, "multicast_loopback"),
        multicast_interface=iface,
        include_untracked=P.read(s, "include_untracked"),
        markers=P.read(s, "markers"),
    )


def pivot_array(cfg: VehicleConfig) -> np.ndarray:
    return np.asarray(cfg.pivot_offset, dtype=np.float64)

register_section("vehicles", VEHICLE, parse_vehicles)
register_section("pose_stream", POSE_STREAM, parse_pose_stream)
