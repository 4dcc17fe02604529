import warnings

import pytest

from visionpos.config.arena import ConfigError, apply_overrides, load_yaml, resolve_config_path
from visionpos.config.overrides import set_path
from visionpos.config.settings import DeprecatedKeyWarning, Setting, section


@pytest.fixture(scope="module")
def raw():
    return load_yaml(resolve_config_path("thesis"))


def test_set_changes_a_copy(raw):
    out = apply_overrides(raw, ["fusion.kalman.gate_chi2=30", "bodies.0.marker_diameter=0.02", "sim.cameras.1.fps=60"])
    assert out["fusion"]["kalman"]["gate_chi2"] == 30 and out["bodies"][0]["marker_diameter"] == 0.02
    assert out["sim"]["cameras"]["1"]["fps"] == 60  # string id, as before
    assert "fusion" not in raw or raw["fusion"].get("kalman", {}).get("gate_chi2") != 30


def test_misspelt_section_fails_with_a_suggestion(raw):
    with pytest.raises(ConfigError, match=r"fusoin: unknown key \(did you mean `fusion`\?\)"):
        apply_overrides(raw, ["fusoin.time_alignment=naive"])
    with pytest.raises(ConfigError, match="did you mean `time_alignment`"):
        apply_overrides(raw, ["fusion.time_alignmnt=naive"])


def test_index_out_of_range_names_the_key(raw):
    with pytest.raises(ConfigError, match=r"--set: bodies.5: `bodies` has \d+ items"):
        apply_overrides(raw, ["bodies.5.x=1"])


def test_value_is_not_a_section(raw):
    with pytest.raises(ConfigError, match="single value"):
        apply_overrides(raw, ["fusion.window_ms.x=1"])


def test_old_spelling_warns_and_sets_the_new_key():
    spec = section("t", "", Setting("a", "section", {}, spec=section("t.a", "", Setting("rate_hz", "number", 1.0,
                                                                                         old_keys=("rate",)))))
    data = {"a": {}}
    with pytest.warns(DeprecatedKeyWarning):
        set_path(data, ["a", "rate"], 5, spec, "--set")
    assert data == {"a": {"rate_hz": 5}}


def test_no_warning_for_current_keys(raw):
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        apply_overrides(raw, ["server.port=6000"])


def test_a_number_for_a_text_key_is_the_text_typed(raw):
    """`--set natnet.bitstream=3.1`: YAML reads 3.1 (a float), the key is declared as text: it gets "3.1" as
    typed (3.10 stays "3.10", not the float's repr); numbers and booleans stay what YAML reads elsewhere."""
    import visionpos.app.sections  # noqa: F401  every section registered, natnet's too
    from bridge.natnet import parse_natnet
    from visionpos.config.arena import parse_arena

    out = apply_overrides(raw, ["natnet.bitstream=3.1", "natnet.enabled=true", "fusion.kalman.gate_chi2=30"])
    assert out["natnet"]["bitstream"] == "3.1" and out["natnet"]["enabled"] is True
    assert out["fusion"]["kalman"]["gate_chi2"] == 30
    assert apply_overrides(raw, ["natnet.bitstream= 3.10"])["natnet"]["bitstream"] == "3.10"
    assert parse_natnet(parse_arena(out, "thesis.yaml")).bitstream == (3, 1)
