"""The `server:` section: declared defaults, unknown keys, and the secure defaults (key, insecure, bind)."""

import asyncio
import logging
import os
import subprocess
import sys
from pathlib import Path

import pytest

from visionpos.config.arena import ConfigError, parse_arena
from visionpos.server.settings import SERVER, ServerSettings, parse_server

ROOT = Path(__file__).resolve().parents[2]
KEY = bytes(range(32))


def _arena(server, tmp_path=None, **extra):
    src = str(tmp_path / "arena.yaml") if tmp_path is not None else "a.yaml"
    return parse_arena({"cameras": [], "bodies": [], "server": server, **extra}, src)


def test_defaults_equal_the_declared_ones():
    s = parse_server(_arena({"insecure": True}))
    assert s == ServerSettings(insecure=True)
    assert s.port == SERVER["port"].default and s.shed_backlog_ms == 15.0 and s.bind == "127.0.0.1"


def test_unknown_server_key():
    with pytest.raises(ConfigError, match=r"server.outptu_rate_hz: unknown key \(did you mean `output_rate_hz`"):
        parse_server(_arena({"outptu_rate_hz": 50}))


def test_no_key_and_not_insecure_is_an_error_naming_file_key_and_fix(tmp_path, monkeypatch):
    missing = tmp_path / "nowhere" / "key"
    monkeypatch.setenv("VISIONPOS_KEY_FILE", str(missing))
    with pytest.raises(ConfigError) as ei:
        parse_server(_arena({}, tmp_path))
    e = ei.value
    assert e.source == str(tmp_path / "arena.yaml") and e.key == "server.key_file"
    assert str(missing) in e.message and "visionpos keygen" in e.message and "every station" in e.message
    assert "server.insecure: true" in e.message


def test_default_key_file_env_then_home(tmp_path, monkeypatch):
    (tmp_path / "k").write_bytes(KEY)
    monkeypatch.setenv("VISIONPOS_KEY_FILE", str(tmp_path / "k"))
    s = parse_server(_arena({}, tmp_path))
    assert s.key == KEY and s.key_file == str(tmp_path / "k") and not s.insecure
    monkeypatch.delenv("VISIONPOS_KEY_FILE")
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    (tmp_path / "home" / ".config" / "visionpos").mkdir(parents=True)
    (tmp_path / "home" / ".config" / "visionpos" / "key").write_bytes(KEY[::-1])
    assert parse_server(_arena({}, tmp_path)).key == KEY[::-1]


def test_key_file_relative_to_the_arena_and_in_memory_key(tmp_path):
    (tmp_path / "lab.key").write_bytes(KEY)
    assert parse_server(_arena({"key_file": "lab.key"}, tmp_path)).key == KEY
    # the demo's in-memory key replaces the default file, never a configured choice
    assert parse_server(_arena({}, tmp_path), key=b"m" * 32).key == b"m" * 32
    assert parse_server(_arena({"key_file": "lab.key"}, tmp_path), key=b"m" * 32).key == KEY
    assert parse_server(_arena({"insecure": True}, tmp_path), key=b"m" * 32).key is None


@pytest.mark.parametrize("server, key, what", [
    ({"insecure": True, "key_file": "lab.key"}, "server.insecure", "together with key_file"),
    ({"key_file": "short.key"}, "server.key_file", "holds only 8 bytes"),
    ({"insecure": "yes"}, "server.insecure", "expected"),
    ({"bind": "lab-host"}, "server.bind", "no IP address"),
])
def test_key_and_bind_config_errors(server, key, what, tmp_path):
    (tmp_path / "lab.key").write_bytes(KEY)
    (tmp_path / "short.key").write_bytes(b"password")
    with pytest.raises(ConfigError) as ei:
        parse_server(_arena(server, tmp_path))
    assert ei.value.key == key and what in ei.value.message


def test_settings_in_code_need_a_key_or_insecure():
    with pytest.raises(ValueError, match="key"):
        ServerSettings()
    with pytest.raises(ValueError, match="insecure"):
        ServerSettings(key=KEY, insecure=True)


def test_host_option_must_be_an_address():
    from visionpos.errors import UsageError

    s = ServerSettings(insecure=True)
    assert s.with_bind("0.0.0.0").bind == "0.0.0.0" and not s.with_bind("0.0.0.0").loopback and s.loopback
    with pytest.raises(UsageError, match="--host lab-pc: give an IP address"):
        s.with_bind("lab-pc")


def test_replay_needs_no_key_file_but_checks_a_named_one(tmp_path):
    s = ServerSettings.for_replay(_arena({}, tmp_path))  # no default key file exists in the tests
    assert s.key is None and s.insecure
    (tmp_path / "lab.key").write_bytes(KEY)
    assert ServerSettings.for_replay(_arena({"key_file": "lab.key"}, tmp_path)).key == KEY


def test_insecure_server_warns_at_start_and_in_its_status_line(caplog):
    from visionpos.server.service import FusionServer

    arena = _arena({"insecure": True, "status_period_s": 0}, camera_monitor=NO_MONITOR)

    async def main():
        server = FusionServer(arena, pipeline=_NoFusion(), port=0)
        await server.start()
        try:
            return server.status_line(), server.health()["insecure"]
        finally:
            await server.stop()

    with caplog.at_level(logging.WARNING, logger="visionpos.server.service"):
        line, insecure_in_health = asyncio.run(main())
    warnings = [r for r in caplog.records if r.levelno == logging.WARNING and "INSECURE" in r.getMessage()]
    assert len(warnings) == 1 and "a.yaml" in warnings[0].getMessage()
    assert line.startswith("INSECURE") and insecure_in_health is True


def test_signed_server_status_line_has_no_insecure_mark():
    from visionpos.server.service import FusionServer

    server = FusionServer(_arena({}, camera_monitor=NO_MONITOR), ServerSettings(key=KEY), pipeline=_NoFusion())
    assert "INSECURE" not in server.status_line()


NO_MONITOR = {"enabled": False}  # an arena without cameras has none to watch


class _NoFusion:
    loose_points = None

    def push(self, frame):
        pass

    def tick(self, now_ns):
        return []

    def remove_camera(self, camera_id):
        pass

    def stats(self):
        return {}


@pytest.mark.parametrize("command", ["serve", "record"])
def test_listening_socket_binds_to_server_bind(command, tmp_path, monkeypatch):
    """Without a host argument, serve and record listen on server.bind (default 127.0.0.1), never on
    every interface: the address their socket is bound to is checked."""
    import socket

    from visionpos.app.serve import serve
    from visionpos.server.service import load_config_with_overrides, record_traffic

    arena = load_config_with_overrides("thesis", ["server.insecure=true", "server.port=0",
                                                  "server.status_period_s=0"])
    settings = parse_server(arena)
    assert settings.bind == "127.0.0.1"
    bound = []
    real_bind = socket.socket.bind

    def spy(sock, address):
        bound.append(address)
        return real_bind(sock, address)

    monkeypatch.setattr(socket.socket, "bind", spy)
    names = []
    if command == "serve":
        asyncio.run(serve(arena, settings, duration_s=0.2,
                          on_listening=lambda srv: names.append(srv.ingest.sock.getsockname())))
    else:
        asyncio.run(record_traffic(arena, settings, tmp_path / "r.mcap", duration_s=0.2,
                                   on_listening=lambda port: names.append(("127.0.0.1", port))))
    assert [a[0] for a in bound] == ["127.0.0.1"] and names[0][0] == "127.0.0.1"


def _run(args, tmp_path, timeout=60):
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    return subprocess.run([sys.executable, "-m", "visionpos", *args], cwd=tmp_path, env=env, capture_output=True,
                          text=True, timeout=timeout)


def test_serve_without_a_key_fails_with_one_line(tmp_path):
    (tmp_path / "arena.yaml").write_text("cameras: []\nbodies: []\n")
    r = _run(["serve", "--config", "arena.yaml", "--port", "0", "--duration", "0.5"], tmp_path)
    assert r.returncode == 2 and "Traceback" not in r.stderr
    (line,) = r.stderr.strip().splitlines()
    assert "arena.yaml: server.key_file:" in line and "visionpos keygen" in line and "insecure: true" in line


def test_serve_insecure_warns_says_where_it_listens_and_marks_the_status(tmp_path):
    r = _run(["serve", "--config", "thesis", "--port", "0", "--duration", "0.7", "--set", "server.insecure=true",
              "--set", "server.status_period_s=0.2"], tmp_path)
    assert r.returncode == 0, r.stderr
    assert "WARNING" in r.stderr and "INSECURE: server.insecure is true" in r.stderr
    status = [ln for ln in r.stderr.splitlines() if "visionpos.status" in ln]
    assert status and all("INSECURE" in ln for ln in status)
    assert "listening on udp 127.0.0.1:" in r.stdout and "127.0.0.1 is loopback" in r.stdout
    assert "server.bind" in r.stdout
