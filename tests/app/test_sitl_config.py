"""`visionpos sitl`'s configuration: the pose message (--message, --set vehicles.0.message) and ArduPilot's
defaults file (copter.parm), found or refused in one line."""

from __future__ import annotations

import argparse

import pytest

from bridge.config import parse_vehicles
from visionpos.app import sitl as S
from visionpos.app.sitl import settings as sitl_settings
from visionpos.app.sitl.settings import find_defaults


def _binary(folder):
    folder.mkdir(parents=True, exist_ok=True)
    b = folder / "arducopter"
    b.write_text("#!/bin/sh\n")
    b.chmod(0o755)
    return b


def test_set_vehicles_message_odometry_works_without_a_vehicles_section():
    """The thesis arena has no `vehicles:`: the demo makes one per body; the override applies to it."""
    arena = S.sitl_arena("thesis", ["vehicles.0.message=odometry", "cameras.0.fps=50"], 60.0)
    v = parse_vehicles(arena)[0]
    assert v.message == "odometry" and v.endpoint.kind == "udpin" and v.signing_key is not None
    assert arena.cameras[0].fps == 50.0
    assert parse_vehicles(S.sitl_arena("thesis", [], 60.0))[0].message == "vision_position_estimate"


def _cli_sets(monkeypatch):
    """`visionpos sitl`'s parser, and a function from its arguments to the overrides it gives the arena."""
    from visionpos.cli import sitl as cli

    p = argparse.ArgumentParser()
    cli.add_arguments(p)
    seen = {}

    def fake_arena(scenario, sets, max_s):
        seen["sets"] = sets
        raise SystemExit(0)

    monkeypatch.setattr(cli, "sitl_arena", fake_arena)

    def sets(*argv):
        with pytest.raises(SystemExit):
            cli.run(p.parse_args(list(argv)))
        return seen["sets"]

    return p, sets


def test_cli_message_flag_is_the_vehicle_override(monkeypatch):
    p, sets = _cli_sets(monkeypatch)
    got = sets("--message", "odometry", "--defaults", "x.parm")
    assert "vehicles.0.message=odometry" in got
    assert any(s.startswith("sitl.defaults=/") and s.endswith("/x.parm") for s in got)
    with pytest.raises(SystemExit):
        p.parse_args(["--message", "att_pos_mocap"])


def test_px4_flies_odometry_unless_told(monkeypatch):
    """`--autopilot px4` sends ODOMETRY (EKF2 fuses its velocity too) unless --message or --set
    vehicles.0.message says otherwise; ArduPilot keeps the arena's message."""
    _, sets = _cli_sets(monkeypatch)

    def messages(*argv):
        return [s for s in sets(*argv) if s.startswith("vehicles.0.message")]

    assert messages("--autopilot", "px4") == ["vehicles.0.message=odometry"]
    assert messages("--autopilot", "px4", "--message", "vision_position_estimate") == [
        "vehicles.0.message=vision_position_estimate"]
    assert messages("--autopilot", "px4", "--set", "vehicles.0.message=vision_position_estimate") == [
        "vehicles.0.message=vision_position_estimate"]
    assert messages() == []


def test_defaults_found_beside_the_binary_and_in_its_ardupilot_tree(tmp_path, monkeypatch):
    monkeypatch.setattr(sitl_settings, "SHARED_SITL_DIR", tmp_path / "shared")
    beside = _binary(tmp_path / "a")
    (tmp_path / "a" / "copter.parm").write_text("FRAME_CLASS 1\n")
    assert find_defaults(beside) == tmp_path / "a" / "copter.parm"
    # a self-built tree: ardupilot/build/sitl/bin/arducopter, ardupilot/Tools/autotest/default_params/copter.parm
    tree = tmp_path / "ardupilot"
    built = _binary(tree / "build" / "sitl" / "bin")
    parm = tree / "Tools" / "autotest" / "default_params" / "copter.parm"
    parm.parent.mkdir(parents=True)
    parm.write_text("FRAME_CLASS 1\n")
    assert find_defaults(built) == parm
    arena = S.sitl_arena("thesis", [], 60.0)
    assert S.parse_sitl(arena, built).defaults == parm


def test_missing_defaults_is_one_clear_line(tmp_path, monkeypatch):
    monkeypatch.setattr(sitl_settings, "SHARED_SITL_DIR", tmp_path / "shared")
    lone = _binary(tmp_path / "lone")
    with pytest.raises(S.SitlError) as e:
        S.parse_sitl(S.sitl_arena("thesis", [], 60.0), lone)
    text = str(e.value)
    assert "\n" not in text and "copter.parm" in text and "--defaults PATH" in text and "sitl.defaults" in text
    # given, it must exist
    from visionpos.config.arena import ConfigError

    with pytest.raises(ConfigError, match="sitl.defaults"):
        S.parse_sitl(S.sitl_arena("thesis", [f"sitl.defaults={tmp_path / 'none.parm'}"], 60.0), lone)
    (tmp_path / "mine.parm").write_text("FRAME_CLASS 1\n")
    cfg = S.parse_sitl(S.sitl_arena("thesis", [f"sitl.defaults={tmp_path / 'mine.parm'}"], 60.0), lone)
    assert cfg.defaults == tmp_path / "mine.parm"
