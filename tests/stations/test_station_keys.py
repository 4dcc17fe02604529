"""A station's key follows the server's rules: key_file, else the default key file, else `insecure: true`."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from stations.config import parse_station
from visionpos.config.arena import ConfigError

ROOT = Path(__file__).resolve().parents[2]
KEY = bytes(range(100, 132))


def _station(tmp_path, **extra):
    data = {"station_id": 1, "camera_id": 2, "server": {"host": "127.0.0.1"}, "source": {"kind": "sim"}, **extra}
    return parse_station(data, str(tmp_path / "station.yaml"), tmp_path)


def test_no_key_and_not_insecure_is_an_error_naming_file_key_and_fix(tmp_path, monkeypatch):
    monkeypatch.setenv("VISIONPOS_KEY_FILE", str(tmp_path / "absent"))
    with pytest.raises(ConfigError) as ei:
        _station(tmp_path)
    e = ei.value
    assert e.source == str(tmp_path / "station.yaml") and e.key == "key_file"
    assert str(tmp_path / "absent") in e.message and "visionpos keygen" in e.message
    assert "insecure: true" in e.message


def test_default_key_file_explicit_key_file_and_insecure(tmp_path, monkeypatch):
    (tmp_path / "k").write_bytes(KEY)
    monkeypatch.setenv("VISIONPOS_KEY_FILE", str(tmp_path / "k"))
    assert _station(tmp_path).key == KEY
    (tmp_path / "other").write_bytes(KEY[::-1])
    assert _station(tmp_path, key_file="other").key == KEY[::-1]  # relative to the station file
    assert _station(tmp_path, insecure=True).key is None


@pytest.mark.parametrize("extra, key, what", [
    ({"insecure": True, "key_file": "k"}, "insecure", "together with key_file"),
    ({"key_file": "short"}, "key_file", "holds only 6 bytes"),
    ({"insecure": 1}, "insecure", "expected"),
])
def test_station_key_config_errors(extra, key, what, tmp_path):
    (tmp_path / "k").write_bytes(KEY)
    (tmp_path / "short").write_bytes(b"secret")
    with pytest.raises(ConfigError) as ei:
        _station(tmp_path, **extra)
    assert ei.value.key == key and what in ei.value.message


def _station_cli(tmp_path, text):
    (tmp_path / "frames").mkdir(exist_ok=True)
    import cv2
    import numpy as np

    cv2.imwrite(str(tmp_path / "frames" / "f0.png"), np.zeros((48, 64), np.uint8))
    (tmp_path / "station.yaml").write_text("station_id: 1\ncamera_id: 2\nserver: {host: 127.0.0.1, port: 9}\n"
                                           "source: {kind: images, path: frames}\n" + text)
    return subprocess.run([sys.executable, "-m", "stations.cli", "--config", str(tmp_path / "station.yaml"),
                           "--check"], cwd=ROOT, capture_output=True, text=True, timeout=60)


def test_station_cli_without_a_key_fails_in_one_line_and_insecure_warns(tmp_path):
    r = _station_cli(tmp_path, "")
    assert r.returncode == 2 and "Traceback" not in r.stderr
    (line,) = r.stderr.strip().splitlines()
    assert "station.yaml: key_file:" in line and "visionpos keygen" in line and "insecure: true" in line
    r = _station_cli(tmp_path, "insecure: true\n")
    assert r.returncode == 0, r.stderr
    assert "WARNING" in r.stderr and "INSECURE" in r.stderr
