"""warm_up_kernels: after it, the fusion path compiles nothing more."""

import sys
from dataclasses import replace

import numpy as np
import pytest

from visionpos.benchmarks.fusion import replay
from visionpos.sim import load_scenario, simulate


def _without(sim, drop):
    """Frames with the blobs for which drop(frame, truth) (N,) bool is True removed."""
    return [replace(f, blobs=f.blobs[~drop(f, tr)]) for f, tr in zip(sim.frames, sim.frame_truth)]


def test_warm_up_compiles_every_kernel_the_fusion_uses():
    """After FusionPipeline's warm-up, a run with acquisition, tracking, loss, reacquisition and
    loose markers compiles nothing more: the server never stalls on numba at its first packets
    (a kernel meeting a new argument type would compile then, for seconds)."""
    from numba.core.registry import CPUDispatcher

    import visionpos.fusion.pipeline  # noqa: F401  (loads every module of the fusion path)
    import visionpos.jit
    from visionpos.fusion.warmup import warm_up_kernels

    if not visionpos.jit.COMPILED:
        pytest.skip("numba is not installed")

    def signatures():
        # every compiled kernel of visionpos, wherever it lives
        out = {}
        for name, mod in list(sys.modules.items()):
            if not name.startswith("visionpos") or mod is None:
                continue
            for attr, obj in vars(mod).items():
                if isinstance(obj, CPUDispatcher) and obj.py_func.__module__ == name and obj.signatures:
                    out[f"{name}.{attr}"] = len(obj.signatures)
        return out

    sc = load_scenario("thesis", session="hover", duration=2.0)
    warm_up_kernels(sc.arena)  # what the first FusionPipeline of a process does
    before = signatures()
    assert sum(before.values()) >= 10  # the kernels Python calls (callees compile inside them)
    for kernel in ("kernels._observe_frame", "kernels._fuse_tracked", "kernels._tracked_motion", "kernels._finite_rows",
                   "measurements.pose_measurement_cov"):
        assert f"visionpos.fusion.{kernel}" in before
    sim = simulate(sc)
    t0 = sim.frames[0].capture_ns
    gap = (t0 + 800_000_000, t0 + 1_100_000_000)
    rep = replay(sc.arena, _without(sim, lambda f, tr: (tr.body == 0) & (gap[0] <= f.capture_ns < gap[1])))
    st = rep.pipeline.stats()
    assert st["lost"] >= 1 and st["acquisitions"] >= 2 and st["measurements"] > 100
    after = signatures()
    assert after == before, {k: (before.get(k), v) for k, v in after.items() if before.get(k) != v}
    # the vehicle's IMU in the filter too (fusion.imu): samples, outputs and two bias windows
    from visionpos.benchmarks.fusion_flights import IMU_FAKE, imu_feeder

    feed, _, _ = imu_feeder(sc, "quad", 1, IMU_FAKE)
    rep = replay(sc.arena, sim.frames, {"imu": {"enabled": True}}, feed_cb=feed)
    imu = rep.pipeline.imu.bodies[0]
    assert imu.stats["used"] > 300 and imu.bias_fits >= 1 and not imu.dropped
    after = signatures()
    assert after == before, {k: (before.get(k), v) for k, v in after.items() if before.get(k) != v}


def _wait(condition, timeout_s=20.0):
    import time

    t0 = time.monotonic()
    while not condition() and time.monotonic() - t0 < timeout_s:
        time.sleep(0.05)
    return condition()


def test_a_cold_start_runs_interpreted_until_the_background_record_appears(tmp_path, monkeypatch):
    """Cold start in a live server: the kernels run as Python until the child's record of a complete cache
    appears; then the kernels it names are loaded and the process switches to them."""
    import pickle

    from visionpos import jit
    from visionpos.fusion import warmup

    if not jit.COMPILED:
        pytest.skip("numba is not installed")
    record = tmp_path / "fusion-warm-up-test.pickle"
    started = []
    monkeypatch.setattr(warmup, "_start_child", lambda rec, settings: started.append(rec))  # returns None
    monkeypatch.setattr(warmup, "_lock_holder", lambda lock: 1)  # "another process compiles"
    monkeypatch.setattr(warmup, "_POLL_S", 0.02)
    assert jit.dot3(np.ones(3), np.ones(3)) == 3.0  # compiled for these types (as by the child's first stage)
    try:
        warmup._background(record, None)
        assert started == [record]
        assert jit.interpreting()
        assert not _wait(lambda: not jit.interpreting(), 0.3)  # no record yet: still interpreted
        from numba.core.registry import CPUDispatcher

        warmup._write_record(warmup._hot_record(record), [jit.dot3])
        assert _wait(lambda: type(jit.dot3) is CPUDispatcher)  # the first stage's kernel runs compiled ...
        assert jit.interpreting() and type(jit.matvec3) is not CPUDispatcher  # ... the others interpreted
        record.write_bytes(pickle.dumps({"visionpos.jit:dot3": [jit.dot3.signatures[0]]}))
        assert _wait(lambda: not jit.interpreting())
    finally:
        jit.use_compiled()


def test_a_failed_background_compilation_falls_back_to_compiling_on_first_use(tmp_path, monkeypatch, caplog):
    import subprocess
    import sys as _sys

    from visionpos import jit
    from visionpos.fusion import warmup

    if not jit.COMPILED:
        pytest.skip("numba is not installed")
    record = tmp_path / "fusion-warm-up-test.pickle"
    monkeypatch.setattr(warmup, "_start_child",
                        lambda rec, settings: subprocess.Popen([_sys.executable, "-c", "raise SystemExit(3)"]))
    monkeypatch.setattr(warmup, "_POLL_S", 0.02)
    try:
        with caplog.at_level("WARNING", logger="visionpos.progress"):
            warmup._background(record, None)
            assert _wait(lambda: not jit.interpreting())
        assert "exit 3" in caplog.text
    finally:
        jit.use_compiled()


def test_the_record_names_every_compiled_kernel_and_loads_back(tmp_path):
    from visionpos import jit
    from visionpos.fusion import warmup

    if not jit.COMPILED:
        pytest.skip("numba is not installed")
    a, b = np.ones(3), np.arange(3.0)
    assert jit.dot3(a, b) == 3.0
    record = tmp_path / "r.pickle"
    warmup._write_record(record)
    assert record.exists() and not list(tmp_path.glob("*.tmp"))
    assert jit.dot3 in warmup._load_record(record)


def test_interpret_while_cold_only_on_a_cold_cache(tmp_path, monkeypatch):
    from visionpos import jit
    from visionpos.fusion import warmup

    if not jit.COMPILED:
        pytest.skip("numba is not installed")
    record = tmp_path / "fusion-warm-up-test.pickle"
    monkeypatch.setattr(warmup, "warm_up_record", lambda: record)
    monkeypatch.setattr(warmup, "_cold", [False])
    monkeypatch.delenv(warmup.COLD_START_ENV, raising=False)
    try:
        monkeypatch.setenv(warmup.COLD_START_ENV, "wait")
        assert not warmup.interpret_while_cold() and not jit.interpreting()
        monkeypatch.delenv(warmup.COLD_START_ENV)
        record.write_bytes(b"")  # a complete cache: the kernels load from it
        assert not warmup.interpret_while_cold() and not jit.interpreting()
        record.unlink()
        assert warmup.interpret_while_cold() and jit.interpreting() and warmup._cold[0]
    finally:
        jit.use_compiled()
