"""Compile the fusion kernels before the first camera frame arrives, or run without them until they are.

numba compiles a kernel on its first call for each argument type; the first
compilation after an install or an update takes one to two minutes of CPU,
which done lazily would stall the server on its first packets. The first
FusionPipeline of a process therefore runs a synthetic hover through a
throwaway pipeline (warm_up_kernels), so every kernel of the fusion path
meets the argument types it will see; with numba's disk cache filled that
takes a second or two.

Cold start (no cache for these sources): by default the pipeline waits for
the compilation (replays, benchmarks and tests want the compiled kernels from
the first frame), and so do `serve` and `sitl`, whose poses go to autopilots (an
interpreted fusion sheds most frames). The demo must not wait a minute for its first
pose: after interpret_while_cold() (the CLI calls it for the demo only) the
kernels run interpreted (jit.interpret(): the same numbers, several times
slower) and the pipeline's warm-up starts a child process that compiles them
into the cache; when the child is done the kernels are loaded from the cache
and this process switches to them (jit.use_compiled()). The child compiles the
hottest kernel first (_hot_kernels, for the argument types interpreted callers
give it), and the parent runs that one compiled as soon as it is. The child
finishes filling the cache even if this process ends first, so the next start
is warm. What it compiled is recorded next to the cache (warm_up_record: every
kernel's argument types), which is also how a later start knows the cache is
complete. VISIONPOS_COLD_START=wait makes the demo wait for the compilation
instead.
"""

from __future__ import annotations

import json
import logging
import os
import pickle
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from visionpos import jit
from visionpos.config.arena import ArenaConfig
from visionpos.fusion.matching import Projector
from visionpos.jit import COMPILED
from visionpos.messages import BlobFrame

progress_log = logging.getLogger("visionpos.progress")  # shown by default by the CLI
log = logging.getLogger(__name__)
_warm = [False]  # kernels compiled (or loaded) in this process: warm_up_once has run

COLD_START_ENV = "VISIONPOS_COLD_START"  # "wait": a live server waits for the compilation on a cold cache
_cold = [False]  # interpret_while_cold() found the cache cold: the warm-up compiles in the background
_POLL_S = 0.5  # how often a background start looks whether the child is done
_LOCK_STALE_S = 1200.0  # a lock file older than this is left by a process that died


def warm_up_kernels(arena: ArenaConfig, settings: dict[str, Any] | None = None) -> None:
    """Compile every kernel of the fusion path (or load it from numba's disk cache) now.

    The first compilation after an install takes one to two minutes; done lazily
    it would stall the server on its first packets. A throwaway pipeline over
    a synthetic hover of the first body, in front of the arena's cameras,
    runs the real code path, so each kernel meets exactly the argument types
    it will see. With no body visible to two cameras the rest compiles on
    first use.
    """
    if not arena.bodies:
        return
    cams = list(arena.cameras)
    # the point closest to every optical axis: where the cameras look
    A = np.zeros((3, 3))
    rhs = np.zeros(3)
    for c in cams:
        d = c.R[2]  # optical axis, world
        M = np.eye(3) - np.outer(d, d)
        A += M
        rhs += M @ (-c.R.T @ c.t)
    try:
        centre = np.linalg.solve(A, rhs)
    except np.linalg.LinAlgError:
        return
    markers = np.asarray(arena.bodies[0].markers, dtype=np.float64) + centre
    from visionpos.fusion.pipeline import FusionPipeline  # here: pipeline.py imports this module

    pipe = FusionPipeline(arena, settings, warm_up=False)
    step = [0]  # warm-up frames done
    done = threading.Event()

    def report() -> None:  # says nothing when the kernels load from numba's cache (well under 2 s)
        waited, interval = 0.0, 2.0
        while not done.wait(interval):
            if not waited:
                progress_log.info("compiling the fusion kernels (first run after install or update, one to two "
                                  "minutes; later runs load them from numba's cache)")
            waited, interval = waited + interval, 5.0
            progress_log.info("compiling the fusion kernels: warm-up frame %d/12, %.0f s so far", step[0] + 1, waited)
        if waited:
            progress_log.info("fusion kernels compiled and cached")

    threading.Thread(target=report, name="warm-up progress", daemon=True).start()
    views = []
    for c in cams:
        uv = Projector(c).project(markers)
        uv = uv[np.isfinite(uv[:, 0])]
        views.append(np.column_stack([uv, np.full(len(uv), 12.0), np.full(len(uv), 200.0)]).astype(np.float32))
    try:
        for k in range(12):
            step[0] = k
            for i, (c, blobs) in enumerate(zip(cams, views)):
                pipe.push(BlobFrame(c.id, k, 1_000_000_000 + k * 10_000_000 + i * 1_000_000, blobs))
            pipe.tick(1_000_000_000 + k * 10_000_000 + 9_000_000)
        from visionpos.fusion.camera_monitor import warm_up_monitor_kernels
        from visionpos.fusion.imu import warm_up_imu_kernels

        warm_up_monitor_kernels(arena, markers)
        warm_up_imu_kernels(pipe.bank)
    finally:
        done.set()


# ------------------------------------------------------------------ the record of a complete cache
def warm_up_record() -> Path:
    """Where the argument types of every kernel a warm-up compiled are kept (a pickle, written once the
    cache holds them all), under numba's cache root and keyed like the fusion kernels' cache."""
    import hashlib

    import visionpos.fusion.acquisition  # noqa: F401  (acquisition's kernels, which the pipeline calls from Python)
    import visionpos.fusion.camera_monitor  # noqa: F401  (the camera monitor's kernels, warmed up too)
    import visionpos.fusion.imu  # noqa: F401  (the IMU sample's kernel, warmed up too)
    import visionpos.fusion.kernels  # noqa: F401  (the fusion path's kernels and their dependencies)
    import visionpos.geometry.resection  # noqa: F401

    # the monitor calls its resection kernel, and the pipeline acquisition's, through plain functions, which
    # module_key does not follow
    key = "".join(jit.module_key(m) for m in ("visionpos.fusion.kernels", "visionpos.fusion.camera_monitor",
                                               "visionpos.geometry.resection", "visionpos.fusion.acquisition",
                                               "visionpos.fusion.imu"))
    return jit.cache_base() / f"fusion-warm-up-{hashlib.sha1(key.encode()).hexdigest()[:16]}.pickle"


def _kernel_name(d) -> str:
    return f"{d.py_func.__module__}:{d.py_func.__qualname__}"


def _write_record(path: Path, kernels: list | None = None) -> None:
    """Record every kernel's (or only `kernels`') compiled argument types at `path` (written whole, then
    renamed)."""
    sigs = {_kernel_name(d): list(d.signatures) for d in (jit._kernels if kernels is None else kernels)
            if d.signatures}
    tmp = path.with_name(f"{path.name}.{os.getpid()}.tmp")
    try:
        tmp.write_bytes(pickle.dumps(sigs))
        os.replace(tmp, path)
    except OSError as e:  # read-only cache: every start is a cold start, as numba says
        log.debug("cannot write %s: %s", path, e)


def _load_record(path: Path) -> list:
    """Load (from numba's cache) every kernel the record at `path` names with its argument types, so that
    no call compiles; returns those kernels."""
    sigs = pickle.loads(path.read_bytes())
    loaded = []
    for d in list(jit._kernels):
        for sig in sigs.get(_kernel_name(d), ()):
            d.compile(sig)
        if sigs.get(_kernel_name(d)):
            loaded.append(d)
    return loaded


def _hot_record(record: Path) -> Path:
    """The record of the first stage (_hot_kernels compiled for interpreted callers), beside `record` (named
    apart from it: the record alone says the cache is complete)."""
    return record.with_name(record.name.replace("fusion-warm-up-", "fusion-first-stage-"))


def _hot_kernels() -> list:
    """The kernels that take most of the interpreted fusion's time (the single-view update's 18x18 Joseph
    form: about 70 % of it): compiled first, so the interpreted fusion gets faster early."""
    from visionpos.fusion.tracking import filter_update_view

    return [filter_update_view]


# ------------------------------------------------------------------ the background compilation
def _lock_holder(lock: Path) -> int | None:
    """The pid of a live process compiling into this cache (its lock file), else None."""
    try:
        if time.time() - lock.stat().st_mtime > _LOCK_STALE_S:
            return None  # a compilation takes minutes: this lock outlived its process (and its pid may be reused)
        pid = int(lock.read_text().strip() or 0)
        os.kill(pid, 0)
        return pid
    except (OSError, ValueError):
        return None


def _start_child(record: Path, settings: dict[str, Any] | None) -> subprocess.Popen | None:
    """Start `python -m visionpos.fusion.warmup` to fill the cache, unless a live process already does
    (then None). It runs in a session of its own, so it finishes even when this process ends."""
    lock = record.with_suffix(".lock")
    if _lock_holder(lock) is not None:
        return None
    try:
        settings_json = json.dumps(settings or {})
    except (TypeError, ValueError):
        settings_json = "{}"  # settings only choose values, never argument types: the defaults do
    logfile = record.with_suffix(".log")
    try:
        record.parent.mkdir(parents=True, exist_ok=True)
        err = open(logfile, "w")
    except OSError:
        err = subprocess.DEVNULL
    try:
        proc = subprocess.Popen([sys.executable, "-m", "visionpos.fusion.warmup", settings_json],
                                stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=err,
                                start_new_session=True)
    finally:
        if err is not subprocess.DEVNULL:
            err.close()
    try:
        lock.write_text(str(proc.pid))
    except OSError:
        pass
    return proc


def _background(record: Path, settings: dict[str, Any] | None) -> None:
    """Run interpreted now; a child compiles into the cache; switch to the compiled kernels once it is done."""
    proc = _start_child(record, settings)
    jit.interpret()  # (done already by interpret_while_cold; here too for a caller that did not)
    progress_log.info("the fusion kernels are not compiled yet (first run after install or update): a "
                      "background process compiles them (one to two minutes of one core); until then the "
                      "fusion runs interpreted, slower")

    def watch() -> None:
        t0 = time.monotonic()
        next_note = 10.0
        hot = _hot_record(record)
        hot_done = False
        while not record.exists():
            if not hot_done and hot.exists():
                hot_done = True
                try:
                    kernels = _load_record(hot)
                except Exception as e:  # noqa: BLE001  (a broken record: wait for the whole compilation)
                    log.warning("loading the first compiled fusion kernels failed (%s)", e)
                    kernels = []
                jit.use_compiled_for(kernels)
                progress_log.info("compiling the fusion kernels in the background: after %.0f s the hottest "
                                  "(%s) runs compiled, the rest interpreted until the rest is compiled",
                                  time.monotonic() - t0, ", ".join(d.py_func.__name__ for d in kernels))
            if proc is not None and proc.poll() is not None and not record.exists():
                progress_log.warning("the background compilation of the fusion kernels failed (exit %s, see %s): "
                                     "they compile on first use here", proc.returncode, record.with_suffix(".log"))
                jit.use_compiled()
                return
            if proc is None and _lock_holder(record.with_suffix(".lock")) is None and not record.exists():
                proc_gone = "the process compiling them ended without finishing"
                progress_log.warning("%s: the fusion kernels compile on first use here", proc_gone)
                jit.use_compiled()
                return
            time.sleep(_POLL_S)
            if time.monotonic() - t0 >= next_note:
                progress_log.info("compiling the fusion kernels in the background: %.0f s so far (the fusion "
                                  "runs interpreted until then)", time.monotonic() - t0)
                next_note += 10.0
        try:
            n = len(_load_record(record))
        except Exception as e:  # noqa: BLE001  (a broken record must not stop the server: compile lazily)
            log.warning("loading the compiled fusion kernels failed (%s): they compile on first use", e)
            n = 0
        jit.use_compiled()
        progress_log.info("fusion kernels compiled after %.0f s (%d loaded): the fusion runs compiled from now on",
                          time.monotonic() - t0, n)

    threading.Thread(target=watch, name="kernel compilation watch", daemon=True).start()


def interpret_while_cold() -> bool:
    """For a live server, before anything calls a kernel: when the cache holds no complete warm-up for these
    sources, run every kernel interpreted from now on, and have the first pipeline's warm-up compile them in
    a child process (module docstring). Returns whether it did; VISIONPOS_COLD_START=wait says never."""
    if not COMPILED or os.environ.get(COLD_START_ENV) == "wait" or warm_up_record().exists():
        return False
    _cold[0] = True
    jit.interpret()
    return True


def warm_up_once(arena: ArenaConfig, settings: dict[str, Any] | None = None) -> None:
    """warm_up_kernels on the first call in this process (when the kernels are compiled), else nothing.

    After interpret_while_cold() found the cache cold, the compilation runs in a child process and this
    process runs interpreted until it is done (module docstring)."""
    if not COMPILED or _warm[0]:
        return
    _warm[0] = True
    record = warm_up_record()
    if _cold[0] and not record.exists():
        _background(record, settings)
        return
    jit.use_compiled()  # (the record appeared since interpret_while_cold)
    warm_up_kernels(arena, settings)
    if not record.exists():
        _write_record(record)


def _child_main(argv: list[str]) -> int:
    """The background compilation: warm up on the thesis arena with the parent's fusion settings, record."""
    from visionpos.config.arena import load_yaml, parse_arena, resolve_config_path

    record = warm_up_record()
    settings = json.loads(argv[0]) if argv else {}
    path = resolve_config_path("thesis")
    arena = parse_arena(load_yaml(path), str(path))
    try:
        from visionpos.fusion.settings import parse_fusion

        parse_fusion(arena, settings or None)
    except Exception:  # noqa: BLE001  (settings of another arena: the defaults give the same argument types)
        settings = {}
    # first stage: the hottest kernels, compiled for the argument types the interpreted callers give them
    # (what the parent runs meanwhile), then the whole fusion path compiled as in any warm-up
    hot = _hot_kernels()
    jit.interpret()
    jit.use_compiled_for(hot)
    warm_up_kernels(arena, settings or None)
    _write_record(_hot_record(record), hot)
    jit.use_compiled()
    warm_up_kernels(arena, settings or None)
    _write_record(record)
    try:
        record.with_suffix(".lock").unlink()
    except OSError:
        pass
    return 0


if __name__ == "__main__":
    from visionpos.fusion.warmup import _child_main as main  # the module pipeline.py imports, not a second copy

    sys.exit(main(sys.argv[1:]))
