import pytest

from visionpos.config.arena import ConfigError, parse_arena
from visionpos.server.settings import SERVER, ServerSettings


def test_defaults_equal_the_declared_ones():
    s = ServerSettings.from_arena(parse_arena({"cameras": [], "bodies": []}, "a.yaml"))
    assert s == ServerSettings()
    assert s.port == SERVER["port"].default and s.shed_backlog_ms == 15.0


def test_unknown_server_key():
    with pytest.raises(ConfigError, match=r"server.outptu_rate_hz: unknown key \(did you mean `output_rate_hz`"):
        ServerSettings.from_arena(parse_arena({"server": {"outptu_rate_hz": 50}}, "a.yaml"))
