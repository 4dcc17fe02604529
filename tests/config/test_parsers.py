"""One parser convention: every registered section has its parse_<key>(arena, ...) beside its declaration,
and parse_section dispatches to it."""

import importlib

import pytest

from visionpos.config.arena import ConfigError, load_arena, parse_arena
from visionpos.config.schema import parse_section, register_section, registered_sections
from visionpos.config.settings import Setting, section

# every stage-owned section of the arena file (visionpos/app/sections.py imports their modules)
SECTIONS = ["fusion", "camera_monitor", "server", "vehicles", "pose_stream", "vrpn", "natnet", "foxglove", "sim",
            "sitl", "console", "plan"]


def test_every_section_is_registered_with_its_parse_function():
    reg = registered_sections()
    assert sorted(reg) == sorted(SECTIONS)
    for key, (_, parse) in reg.items():
        assert parse.__name__ == f"parse_{key}"
        assert getattr(importlib.import_module(parse.__module__), f"parse_{key}") is parse


def test_a_parser_named_otherwise_is_refused():
    def read_demo(arena):
        return None

    with pytest.raises(ValueError, match="parse_demo"):
        register_section("demo", section("demo", "demo", Setting("x", "number", 1.0)), read_demo)
    assert "demo" not in registered_sections()


def test_parse_section_returns_the_parsed_settings():
    arena = load_arena("thesis")
    assert parse_section(arena, "fusion").kalman.gate_chi2 == 40.0
    assert parse_section(arena, "vrpn") is None  # absent: off
    assert parse_section(arena, "sim", session="hover").session == "hover"
    with pytest.raises(KeyError, match="no parser registered"):
        parse_section(arena, "nothing")


def test_an_optional_server_is_on_only_when_its_section_is_given():
    base = {"cameras": [], "bodies": []}
    assert parse_section(parse_arena({**base, "vrpn": None}, "a.yaml"), "vrpn") is None
    assert parse_section(parse_arena({**base, "natnet": None}, "a.yaml"), "natnet") is None
    assert parse_section(parse_arena({**base, "vrpn": {}}, "a.yaml"), "vrpn").port == 3883
    with pytest.raises(ConfigError, match="a.yaml: vrpn.prot: unknown key"):
        parse_section(parse_arena({**base, "vrpn": {"prot": 1}}, "a.yaml"), "vrpn")
