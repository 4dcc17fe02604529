"""Shared fixtures: the built-in arenas, cameras aimed at a point, a short simulated recording."""

from __future__ import annotations

import os

# One BLAS thread per test process: on the 2-core CI host OpenBLAS's threads spin against the other process's
# work (a calibration's least squares ran 4x slower under load); set before numpy loads, inherited by children.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import copy  # noqa: E402
from pathlib import Path

import numpy as np
import pytest

import visionpos.app.sections  # noqa: F401  every section of the arena file registered, as in the CLI
from visionpos.camera.model import Camera, CameraModel, look_at_rotation
from visionpos.config.arena import load_yaml, resolve_config_path

REPO = Path(__file__).resolve().parents[1]
_YAML_CACHE: dict[str, dict] = {}


def _arena_yaml(name: str = "thesis") -> dict:
    if name not in _YAML_CACHE:
        _YAML_CACHE[name] = load_yaml(resolve_config_path(name))
    return copy.deepcopy(_YAML_CACHE[name])


def _camera_looking_at(center, target, model: CameraModel, camera_id: int = 1, name: str = "c",
                      up=(0.0, 0.0, 1.0), **kwargs) -> Camera:
    """A Camera at `center` (m, world) whose optical axis passes through `target`, no roll."""
    center = np.asarray(center, float)
    R = look_at_rotation(center, np.asarray(target, float), np.asarray(up, float))
    return Camera(camera_id, name, model, R, -R @ center, **kwargs)


@pytest.fixture(autouse=True)
def _no_default_key(monkeypatch, tmp_path_factory):
    """Hermetic keys: the default key file is one that does not exist, never the developer's
    ~/.config/visionpos/key; a test that builds a server gives it a key or says insecure."""
    monkeypatch.setenv("VISIONPOS_KEY_FILE", str(tmp_path_factory.getbasetemp() / "no-default-key"))


@pytest.fixture
def arena_yaml():
    """arena_yaml(name='thesis') -> a fresh, mutable copy of a built-in arena's YAML mapping."""
    return _arena_yaml


@pytest.fixture
def look_at_camera():
    """look_at_camera(center, target, model, camera_id=1, name='c', up=(0, 0, 1), **kw) -> Camera, no roll."""
    return _camera_looking_at


@pytest.fixture(scope="session")
def thesis_log(tmp_path_factory) -> Path:
    """A 3 s simulated thesis-arena recording (seed 5), written once per test session."""
    from visionpos.sim.write import write_recording

    path = tmp_path_factory.mktemp("rec") / "thesis3.mcap"
    write_recording("thesis", path, duration_s=3.0, seed=5)
    return path
