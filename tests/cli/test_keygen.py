"""`visionpos keygen`: 32 random bytes, mode 0600, never overwrites without --force, says how to copy it."""

from __future__ import annotations

import stat

from visionpos.cli.main import main


def _mode(path) -> int:
    return stat.S_IMODE(path.stat().st_mode)


def test_keygen_writes_32_bytes_mode_0600_and_refuses_to_overwrite(tmp_path, capsys):
    out = tmp_path / "lab" / "key"
    assert main(["keygen", "--out", str(out)]) == 0
    key = out.read_bytes()
    assert len(key) == 32 and _mode(out) == 0o600 and _mode(out.parent) == 0o700
    said = capsys.readouterr().out
    assert str(out) in said and f"scp -p {out} " in said and f"key_file: {out}" in said
    assert main(["keygen", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "already exists" in err and "--force" in err and err.count("\n") == 1
    assert out.read_bytes() == key  # the refused run changed nothing
    out.chmod(0o644)
    assert main(["keygen", "--out", str(out), "--force"]) == 0
    new = out.read_bytes()
    assert len(new) == 32 and new != key and _mode(out) == 0o600


def test_keygen_default_place_is_the_one_the_configs_read(tmp_path, monkeypatch, capsys):
    from visionpos.config.arena import parse_arena
    from visionpos.server.settings import parse_server

    monkeypatch.delenv("VISIONPOS_KEY_FILE")
    monkeypatch.setenv("HOME", str(tmp_path))
    assert main(["keygen"]) == 0
    path = tmp_path / ".config" / "visionpos" / "key"
    assert len(path.read_bytes()) == 32 and _mode(path) == 0o600
    assert "default place" in capsys.readouterr().out
    s = parse_server(parse_arena({"cameras": [], "bodies": []}, str(tmp_path / "arena.yaml")))
    assert s.key == path.read_bytes()
    # $VISIONPOS_KEY_FILE moves the default for both
    monkeypatch.setenv("VISIONPOS_KEY_FILE", str(tmp_path / "elsewhere.key"))
    assert main(["keygen"]) == 0 and len((tmp_path / "elsewhere.key").read_bytes()) == 32
