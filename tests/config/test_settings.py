import warnings
from pathlib import Path

import pytest

from visionpos.app.config_reference import render
from visionpos.config.arena import ConfigError, Section, load_arena, load_yaml
from visionpos.config.settings import DeprecatedKeyWarning, Setting, section
from visionpos.errors import VisionposError

DOC = Path(__file__).resolve().parents[2] / "docs" / "configuration.md"


def test_reference_doc_is_in_sync():
    assert DOC.read_text() == render(), "run: python -m visionpos.app.config_reference > docs/configuration.md"


def test_reference_names_every_section_and_the_lens_and_pose_forms():
    text = render()
    for path in ("(top level)", "cameras[i]", "cameras[i].pose", "bodies[i]", "fusion", "fusion.kalman", "server",
                 "vehicles[i]", "pose_stream", "sim", "sim.latency_ms", "calibration.wand"):
        assert f"## `{path}`" in text
    for words in ("look_at", "quaternion_xyzw", "Kannala-Brandt", "k1, k2, p1, p2, k3", "nis_time_constant_ms"):
        assert words in text


def test_unknown_key_is_rejected_with_a_suggestion():
    spec = section("demo", "", Setting("window_ms", "number", 1.0))
    with pytest.raises(ConfigError, match=r"demo.windw_ms: unknown key \(did you mean `window_ms`\?\)"):
        spec.check(Section({"windw_ms": 2}, "a.yaml", "demo"))


def test_old_spelling_warns_and_works():
    spec = section("demo", "", Setting("window_ms", "number", 1.0, old_keys=("window",)))
    with pytest.warns(DeprecatedKeyWarning, match="write `window_ms`"):
        values = spec.parse(Section({"window": 2}, "a.yaml", "demo"))
    assert values == {"window_ms": 2.0}
    with pytest.raises(ConfigError, match="also given"), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        spec.check(Section({"window": 2, "window_ms": 3}, "a.yaml", "demo"))


def test_config_error_is_a_visionpos_error_and_a_value_error():
    assert issubclass(ConfigError, VisionposError) and issubclass(ConfigError, ValueError)


def test_non_utf8_file_names_the_file(tmp_path):
    p = tmp_path / "arena.yaml"
    p.write_bytes(b"cameras: []\n# caf\xe9\n")
    with pytest.raises(ConfigError, match=r"arena.yaml: \(file\): not UTF-8"):
        load_yaml(p)


def test_builtin_arenas_load_without_warnings():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        load_arena("thesis")
        load_arena("arena8")
