"""`vehicles:` validation: every error names the file and the key; the documented examples parse."""

import re
from pathlib import Path

import pytest
import yaml

from bridge.config import Endpoint, parse_endpoint, parse_vehicles
from visionpos.benchmarks.factories import arena_with_vehicles
from visionpos.config.arena import ConfigError, parse_arena

DOC = Path(__file__).resolve().parents[2] / "docs" / "autopilot-setup.md"


def vehicles(*vs, n_bodies=3):
    return parse_vehicles(arena_with_vehicles(list(vs), n_bodies=n_bodies))


def test_endpoint_forms():
    assert parse_endpoint("udpin:0.0.0.0:14561") == Endpoint("udpin", "0.0.0.0", 14561)
    assert parse_endpoint("udpout:192.168.1.52:14550") == Endpoint("udpout", "192.168.1.52", 14550)
    assert parse_endpoint("tcp:127.0.0.1:5760") == Endpoint("tcp", "127.0.0.1", 5760)
    assert parse_endpoint("serial:/dev/ttyUSB0:921600") == Endpoint("serial", device="/dev/ttyUSB0", baud=921600)
    for bad in ("udp:1.2.3.4:5", "udpin:1.2.3.4", "tcp:host:0", "serial:/dev/ttyUSB0", "14550"):
        with pytest.raises(ValueError, match="udpin:HOST:PORT"):
            parse_endpoint(bad)


def test_defaults():
    (v,) = vehicles({"body": "body2", "endpoint": "udpin:0.0.0.0:14561", "autopilot_address": "10.0.0.2:14550"})
    assert (v.name, v.sysid, v.message, v.rate_hz, v.time_base, v.timesync) == (
        "body2", 2, "vision_position_estimate", 50.0, "boot", True)
    assert v.rate_tolerance_ms == 0.1 and v.stamp_age_ms is None and v.signing_key is None and v.origin is None
    assert v.autopilot_baud is None  # a UDP link: the autopilot port's speed is not known


def test_the_autopilot_baud_is_the_serial_endpoints_unless_given():
    (v,) = vehicles({"body": "body2", "endpoint": "serial:/dev/ttyUSB0:57600"})
    assert v.autopilot_baud == 57600
    (v,) = vehicles({"body": "body2", "endpoint": "udpin:0.0.0.0:14561", "autopilot_address": "10.0.0.2:14550",
                     "autopilot_baud": 921600, "stamp_age_ms": 12})
    assert (v.autopilot_baud, v.stamp_age_ms) == (921600, 12.0)


@pytest.mark.parametrize("vehicle, key, text", [
    ({"body": "nobody", "endpoint": "udpin:0.0.0.0:1"}, r"vehicles\[0\]\.body", "no body named 'nobody'"),
    ({"body": "body1"}, r"vehicles\[0\]\.endpoint", "required"),
    ({"body": "body1", "endpoint": "udp:1.2.3.4:5"}, r"vehicles\[0\]\.endpoint", "unknown link type"),
    ({"body": "body1", "endpoint": "udpin:0.0.0.0:1", "sysid": 300}, r"vehicles\[0\]\.sysid", "<= 255"),
    (
        {"body": "body1", "endpoint": "udpin:0.0.0.0:1", "message": "att_pos_mocap"},
        r"vehicles\[0\]\.message",
        "not one of",
    ),
    ({"body": "body1", "endpoint": "udpin:0.0.0.0:1", "rate_hz": 0}, r"vehicles\[0\]\.rate_hz", ">= 0.1"),
    ({"body": "body1", "endpoint": "udpin:0.0.0.0:1", "pivot_offset": [1, 2]}, r"vehicles\[0\]\.pivot_offset", "shape"),
    (
        {"body": "body1", "endpoint": "udpin:0.0.0.0:1", "origin": {"lat": 95, "lon": 0}},
        r"vehicles\[0\]\.origin\.lat",
        "<= 90",
    ),
    ({"body": "body1", "endpoint": "udpin:0.0.0.0:1", "signing": {"key_file": "/nonexistent/k"}},
     r"vehicles\[0\]\.signing\.key_file", "cannot read"),
    ({"body": "body1", "endpoint": "udpin:0.0.0.0:1", "message": "odometry", "vision_speed": True},
     r"vehicles\[0\]\.vision_speed", "ODOMETRY already carries velocity"),
])
def test_errors_name_file_and_key(vehicle, key, text):
    with pytest.raises(ConfigError, match=rf"test-arena\.yaml: {key}: .*{text}"):
        vehicles(vehicle)


UDPIN1 = {"body": "body1", "sysid": 1, "endpoint": "udpin:0.0.0.0:1", "autopilot_address": "10.0.0.1:1"}
UDPOUT1 = {"body": "body1", "sysid": 1, "endpoint": "udpout:10.0.0.1:1"}


@pytest.mark.parametrize("first, second, what", [
    (UDPIN1, {"body": "body2", "sysid": 1, "endpoint": "udpin:0.0.0.0:2", "autopilot_address": "10.0.0.2:1"}, "sysid"),
    (UDPOUT1, {"body": "body2", "endpoint": "udpout:10.0.0.1:1"}, "endpoint"),
    (UDPIN1, {"body": "body1", "name": "other", "endpoint": "udpin:0.0.0.0:2", "autopilot_address": "10.0.0.2:1"},
     "body"),
    (UDPIN1, {"body": "body2", "endpoint": "udpin:127.0.0.1:1", "autopilot_address": "10.0.0.2:1"},
     "endpoint"),  # same udpin port, other address
])
def test_one_link_and_sysid_per_vehicle(first, second, what):
    with pytest.raises(ConfigError, match=rf"vehicles\[1\]\.{what}"):
        vehicles(first, second)


def test_documented_examples_parse(tmp_path):
    text = DOC.read_text()
    blocks = re.findall(r"```yaml\n(.*?)```", text, re.S)
    assert len(blocks) >= 2
    full, examples = yaml.safe_load(blocks[0]), yaml.safe_load(blocks[1])
    (tmp_path / "keys").mkdir()
    (tmp_path / "keys" / "fleet.key").write_text("a passphrase\n")
    markers = [[0.1, 0, 0], [0, 0.1, 0], [-0.1, -0.05, 0.02]]
    names = ["alpha", "bravo", "charlie", "delta"]
    bodies = [{"name": n, "id": i + 1, "markers": markers} for i, n in enumerate(names)]
    full_v = parse_vehicles(parse_arena({"bodies": bodies, **full}, str(tmp_path / "arena.yaml")))
    assert full_v[0].signing_key is not None and full_v[0].origin.lat == pytest.approx(47.397742)
    ex = parse_vehicles(parse_arena({"bodies": bodies, **examples}, str(tmp_path / "arena.yaml")))
    assert [v.endpoint.kind for v in ex] == ["udpin", "udpout", "tcp", "serial"]
    assert [v.sysid for v in ex] == [1, 2, 3, 4]


def test_misspelt_pose_stream_and_vehicle_keys_are_errors():
    import pytest as _pytest

    from bridge.config import parse_pose_stream, parse_vehicles
    from visionpos.config.arena import ConfigError as _ConfigError
    from visionpos.config.arena import load_yaml as _load
    from visionpos.config.arena import parse_arena as _parse
    from visionpos.config.arena import resolve_config_path as _resolve

    raw = _load(_resolve("thesis"))
    body = raw["bodies"][0]["name"]
    ps = dict(raw, pose_stream={"destinations": ["127.0.0.1:5005"], "formt": "binary"})
    with _pytest.raises(_ConfigError, match="did you mean `format`"):
        parse_pose_stream(_parse(ps, "a.yaml"))
    v = dict(raw, vehicles=[{"body": body, "endpoint": "udpout:127.0.0.1:14550", "signin": {"key_file": "k"}}])
    with _pytest.raises(_ConfigError, match="did you mean `signing`"):
        parse_vehicles(_parse(v, "a.yaml"))
