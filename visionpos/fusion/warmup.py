"""Compile the fusion kernels before the first camera frame arrives.

numba compiles a kernel on its first call for each argument type; the first
compilation after an install takes tens of seconds, which done lazily would
stall the server on its first packets. The first FusionPipeline of a process
therefore runs a synthetic hover through a throwaway pipeline (warm_up_once),
so every kernel of the fusion path meets the argument types it will see.
"""

from __future__ import annotations

import logging
import threading
from typing import Any

import numpy as np

from visionpos.config.arena import ArenaConfig
from visionpos.fusion.matching import Projector
from visionpos.jit import COMPILED
from visionpos.messages import BlobFrame

progress_log = logging.getLogger("visionpos.progress")  # shown by default by the CLI
_warm = [False]  # kernels compiled (or loaded) in this process: warm_up_once has run


def warm_up_kernels(arena: ArenaConfig, settings: dict[str, Any] | None = None) -> None:
    """Compile every kernel of the fusion path (or load it from numba's disk cache) now.

    The first compilation after an install takes tens of seconds; done lazily
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
                progress_log.info("compiling the fusion kernels (first run after install, about a minute; later "
                                  "runs load them from numba's cache)")
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
    finally:
        done.set()


def warm_up_once(arena: ArenaConfig, settings: dict[str, Any] | None = None) -> None:
    """warm_up_kernels on the first call in this process (when the kernels are compiled), else nothing."""
    if COMPILED and not _warm[0]:
        _warm[0] = True
        warm_up_kernels(arena, settings)
