"""Cameras without a pose (not calibrated yet): recorded and calibrated, refused where a pose is needed."""

import asyncio

import pytest

from visionpos.config.arena import ConfigError, load_yaml, parse_arena, resolve_config_path
from visionpos.server.settings import parse_server


def _unposed_thesis(tmp_path, keep_first_pose=False):
    data = load_yaml(resolve_config_path("thesis"))
    for k, cam in enumerate(data["cameras"]):
        if not (keep_first_pose and k == 0):
            cam.pop("pose")
    data.setdefault("server", {}).update({"insecure": True, "port": 0, "status_period_s": 0})
    return parse_arena(data, str(tmp_path / "arena.yaml"))


def test_cameras_without_pose_load_and_are_listed(tmp_path):
    arena = _unposed_thesis(tmp_path, keep_first_pose=True)
    assert arena.unposed == tuple(c.id for c in arena.cameras[1:])
    assert len(arena.cameras) == 4


def test_fusion_simulator_and_planner_refuse_them_naming_the_fix(tmp_path):
    from visionpos.fusion.pipeline import FusionPipeline
    from visionpos.sim.scenario import parse_sim

    arena = _unposed_thesis(tmp_path)
    with pytest.raises(ConfigError, match=r"arena.yaml: cameras\[0\].pose: fusion needs every camera's pose.*"
                                          r"visionpos calibrate wand"):
        FusionPipeline(arena)
    with pytest.raises(ConfigError, match="the simulator needs every camera's pose"):
        parse_sim(arena)


def test_record_runs_without_poses(tmp_path):
    from visionpos.server.service import record_traffic

    arena = _unposed_thesis(tmp_path)
    out = tmp_path / "wave.mcap"
    asyncio.run(record_traffic(arena, parse_server(arena), out, duration_s=0.2))
    assert out.stat().st_size > 0


def test_wand_calibration_starts_from_cameras_without_pose(tmp_path):
    import yaml

    from visionpos.cli import main
    from visionpos.config.arena import load_arena

    data = load_yaml(resolve_config_path("thesis"))
    for cam in data["cameras"]:
        cam.pop("pose")
    (tmp_path / "unposed.yaml").write_text(yaml.safe_dump(data))
    out = tmp_path / "cal.yaml"
    assert main(["calibrate", "wand", "--sim", "thesis", "--set", "sim.duration=8", "--config",
                 str(tmp_path / "unposed.yaml"), "--out", str(out), "--no-progress"]) == 0
    cal = load_arena(out)
    assert cal.unposed == () and all("pose" in c for c in yaml.safe_load(out.read_text())["cameras"])
