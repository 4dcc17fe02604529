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


@pytest.fixture
def frozen_heap():
    """The test's start-up heap out of the collector's reach while it runs, as `visionpos serve` holds its own
    (app/serve.py startup_heap_frozen): for tests that judge gaps in a live stream, which a full collection of
    this process's heap (70-90 ms measured on the 2-core host) would otherwise open."""
    from visionpos.app.serve import startup_heap_frozen

    with startup_heap_frozen():
        yield


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


# ------------------------------------------------------------------ a cold kernel cache (a fresh clone, CI)
# The fusion kernels compile once per checkout: about two minutes of one core (fusion/warmup.py). On a cold
# cache a child process compiles them, at a lower priority, while the test folders that start no fusion run
# first; the first test of the other folders waits for the child's record and then loads the kernels from the
# cache instead of compiling them again. On 2 cores that takes the compilation off the suite's wall time.
# A test of an early folder that does use a kernel compiles it itself, as it would without this.
_FUSION_FREE = ("bridge", "calibration", "camera", "cli", "config", "data", "geometry", "sim", "stations",
                "support")  # folders under tests/ whose tests start no fusion and no server (measured) ...
_FUSION_USERS = ("bridge/test_foxglove_live.py", "bridge/test_mavlink_security.py", "config/test_unposed_cameras.py",
                 "stations/test_hello.py")  # ... but for these files, which do
_RATE_TESTS = ("bridge/test_natnet.py", "bridge/test_vrpn.py", "bridge/test_pose_stream.py")  # third-party clients
# count their frames per second: not beside the compilation (a NatNet client got 5 or fewer of 0.2 s of frames
# within 5 s beside it, in a fresh clone's run)
_compile_child: list = []  # the child compiling the kernels (a Popen; None: another process holds the lock)


def _fusion_free(item) -> bool:
    parts = Path(str(item.fspath)).relative_to(REPO / "tests").parts
    return len(parts) > 1 and parts[0] in _FUSION_FREE and "/".join(parts) not in _FUSION_USERS + _RATE_TESTS


def pytest_collection_modifyitems(session, config, items):
    from visionpos.fusion import warmup
    from visionpos.jit import COMPILED

    record = warmup.warm_up_record() if COMPILED else None
    if record is None or record.exists() or not any(not _fusion_free(i) for i in items):
        return
    items[:] = [i for i in items if _fusion_free(i)] + [i for i in items if not _fusion_free(i)]
    proc = warmup._start_child(record, None)  # None: another process compiles them already (a demo just run)
    pid = proc.pid if proc is not None else warmup._lock_holder(record.with_suffix(".lock"))
    if pid:
        try:
            os.setpriority(os.PRIO_PROCESS, pid, 10)  # the early tests' live servers come first
        except OSError:
            pass
    _compile_child.append(proc)


def pytest_runtest_setup(item):
    if not _compile_child or _fusion_free(item):
        return
    import time

    from visionpos.fusion import warmup

    proc = _compile_child.pop()
    record = warmup.warm_up_record()
    lock = record.with_suffix(".lock")
    t0 = time.monotonic()
    while (not record.exists() and time.monotonic() - t0 < 900.0
           and (proc.poll() is None if proc is not None else warmup._lock_holder(lock) is not None)):
        time.sleep(0.2)
