"""warm_up_kernels: after it, the fusion path compiles nothing more."""

import sys
from dataclasses import replace

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
    for kernel in ("_observe_frame", "_fuse_tracked", "_tracked_motion", "_finite_rows", "pose_measurement_cov"):
        assert f"visionpos.fusion.kernels.{kernel}" in before
    sim = simulate(sc)
    t0 = sim.frames[0].capture_ns
    gap = (t0 + 800_000_000, t0 + 1_100_000_000)
    rep = replay(sc.arena, _without(sim, lambda f, tr: (tr.body == 0) & (gap[0] <= f.capture_ns < gap[1])))
    st = rep.pipeline.stats()
    assert st["lost"] >= 1 and st["acquisitions"] >= 2 and st["measurements"] > 100
    after = signatures()
    assert after == before, {k: (before.get(k), v) for k, v in after.items() if before.get(k) != v}
