import copy

import pytest

from visionpos.config.arena import ConfigError, load_yaml, parse_arena, resolve_config_path
from visionpos.sim.scenario import parse_sim


@pytest.fixture(scope="module")
def raw():
    return load_yaml(resolve_config_path("thesis"))


@pytest.mark.parametrize("where, key, close", [
    ((), "camras", "cameras"),
    (("cameras", 0), "fpss", "fps"),
    (("cameras", 0, "pose"), "look_att", "look_at"),
    (("bodies", 0), "marker_diameterr", "marker_diameter"),
])
def test_unknown_key_in_a_shared_section(raw, where, key, close):
    data = copy.deepcopy(raw)
    node = data
    for w in where:
        node = node[w]
    node[key] = 1
    with pytest.raises(ConfigError, match=f"unknown key \\(did you mean `{close}`\\?\\)"):
        parse_arena(data, "a.yaml")


@pytest.mark.parametrize("sub, key, close", [
    ((), "duraton", "duration"), (("latency_ms",), "meen", "mean"), (("occlusion",), "disc_radus", "disc_radius"),
])
def test_unknown_sim_key(raw, sub, key, close):
    data = copy.deepcopy(raw)
    node = data.setdefault("sim", {})
    for w in sub:
        node = node.setdefault(w, {})
    node[key] = 1
    with pytest.raises(ConfigError, match=f"did you mean `{close}`"):
        parse_sim(parse_arena(data, "a.yaml"))
