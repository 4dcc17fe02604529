"""Bad values in an arena file: a wrong type anywhere, a key given twice, a misspelt key. Each is one
ConfigError naming the file and the key, and through the CLI one line on stderr with exit code 2."""

from __future__ import annotations

import copy

import pytest
import yaml

from visionpos.cli.main import main
from visionpos.config.arena import ConfigError, load_arena, load_yaml, resolve_config_path


@pytest.fixture(scope="module")
def thesis() -> dict:
    return load_yaml(resolve_config_path("thesis"))


def _write(tmp_path, data: dict, name: str = "arena.yaml"):
    path = tmp_path / name
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def _set(data: dict, path: tuple, value) -> dict:
    out = copy.deepcopy(data)
    node = out
    for k in path[:-1]:
        if isinstance(node, dict) and node.get(k) is None:
            node[k] = {}
        node = node[k]
    node[path[-1]] = value
    return out


# (place, wrong value, the key the error names): one per section a stage reads, the shared ones first
WRONG_TYPES = [
    (("cameras", 0, "fps"), "1OO", "cameras[0].fps"),
    (("cameras", 0, "id"), "one", "cameras[0].id"),
    (("cameras", 0, "name"), 7, "cameras[0].name"),
    (("cameras", 0, "station"), 1.5, "cameras[0].station"),
    (("cameras", 0, "pose", "position"), [1, 2], "cameras[0].pose.position"),
    (("cameras", 0, "pose", "quaternion_xyzw"), "abc", "cameras[0].pose.quaternion_xyzw"),
    (("bodies", 0, "marker_diameter"), "14mm", "bodies[0].marker_diameter"),
    (("bodies", 0, "occlusion", "disc_radius"), "wide", "bodies[0].occlusion.disc_radius"),
    (("fusion", "match_gate_px"), "12px", "fusion.match_gate_px"),
    (("fusion", "kalman", "gate_chi2"), [40], "fusion.kalman.gate_chi2"),
    (("fusion", "single_view", "enabled"), "yes", "fusion.single_view.enabled"),
    (("server", "output_rate_hz"), "fast", "server.output_rate_hz"),
    (("vehicles",), {"body": "quad"}, "vehicles"),
    (("pose_stream",), ["udp"], "pose_stream"),
    (("vrpn", "port"), "3883a", "vrpn.port"),
    (("sim", "duration"), "long", "sim.duration"),
    (("sim", "latency_ms", "mean"), "4ms", "sim.latency_ms.mean"),
    (("sim", "props", 0, "occlusion", "disc_radius"), "none", "sim.props[0].occlusion.disc_radius"),
    (("sitl", "instance"), "first", "sitl.instance"),
    (("calibration", "wand", "ab"), "54mm", "calibration.wand.ab"),
    (("console", "port"), "http", "console.port"),
    (("camera_monitor", "enabled"), "on", "camera_monitor.enabled"),
]


@pytest.mark.parametrize("where, value, key", WRONG_TYPES, ids=[k for _, _, k in WRONG_TYPES])
def test_a_wrong_type_fails_at_load_naming_the_key(tmp_path, thesis, where, value, key):
    path = _write(tmp_path, _set(thesis, where, value))
    with pytest.raises(ConfigError) as e:
        load_arena(path)
    assert e.value.source == str(path) and e.value.key == key
    assert "expected" in e.value.message


def test_the_cli_prints_one_line_and_exits_2_for_a_wrong_type(tmp_path, thesis, capsys):
    path = _write(tmp_path, _set(thesis, ("cameras", 0, "fps"), "1OO"))
    assert main(["plan", str(path)]) == 2
    err = capsys.readouterr().err
    assert err == f"visionpos plan: error: {path}: cameras[0].fps: expected a number, got '1OO'\n"


DUPLICATE = """\
cameras: []
bodies:
  - name: quad
    markers: [[0, 0, 0], [0.1, 0, 0], [0, 0.1, 0]]
    marker_diameter: 0.014
    marker_diameter: 0.02
"""


def test_a_key_given_twice_is_an_error_naming_the_key_and_its_lines(tmp_path):
    path = tmp_path / "dup.yaml"
    path.write_text(DUPLICATE)
    with pytest.raises(ConfigError) as e:
        load_yaml(path)
    assert e.value.source == str(path) and e.value.key == "bodies[0].marker_diameter"
    assert "line 5 and line 6" in e.value.message


def test_a_top_level_section_given_twice_is_an_error(tmp_path):
    path = tmp_path / "dup.yaml"
    path.write_text("fusion: {match_gate_px: 10}\nbodies: []\nfusion: {match_gate_px: 12}\n")
    with pytest.raises(ConfigError, match=r"dup.yaml: fusion: given twice \(line 1 and line 3\)"):
        load_arena(path)


def test_the_same_key_in_two_mappings_and_merges_are_fine(tmp_path):
    path = tmp_path / "ok.yaml"
    path.write_text("base: &b {x: 1, y: 2}\na: {x: 1}\nb: {x: 2}\nc: {<<: *b, x: 3}\n")
    assert load_yaml(path)["c"] == {"x": 3, "y": 2}


def test_the_cli_prints_one_line_and_exits_2_for_a_key_given_twice(tmp_path, thesis, capsys):
    text = yaml.safe_dump(thesis, sort_keys=False).replace("sim:\n", "sim:\n  seed: 1\n", 1)
    path = tmp_path / "arena.yaml"
    path.write_text(text)
    assert main(["plan", str(path)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"{path}: sim.seed: given twice" in err


@pytest.mark.parametrize("where, close", [
    (("cameras", 0, "fpss"), "fps"),
    (("fusion", "kalman", "gate_chi"), "gate_chi2"),
    (("sim", "durration"), "duration"),
    (("server", "output_rate_hz_"), "output_rate_hz"),
    (("calibration", "wand", "abb"), "ab"),
])
def test_a_misspelt_key_keeps_its_did_you_mean(tmp_path, thesis, capsys, where, close):
    path = _write(tmp_path, _set(thesis, where, 1))
    with pytest.raises(ConfigError, match=f"unknown key \\(did you mean `{close}`\\?\\)"):
        load_arena(path)
    assert main(["plan", str(path)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"did you mean `{close}`" in err


def test_a_removed_key_says_what_to_write_instead_at_load_and_in_set(tmp_path, thesis):
    path = _write(tmp_path, _set(thesis, ("fusion", "acquire_ray_distance_m"), 0.01))
    with pytest.raises(ConfigError, match="fusion.acquire_ray_distance_m: removed: .*acquire_ray_gate_px"):
        load_arena(path)
    from visionpos.config.arena import apply_overrides

    with pytest.raises(ConfigError, match="fusion.acquire_ray_distance_m: removed: "):
        apply_overrides(thesis, ["fusion.acquire_ray_distance_m=0.01"])
