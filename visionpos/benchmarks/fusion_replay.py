"""The fusion benchmarks' shared instrument: a pipeline run on simulated frames as the server runs it.

replay feeds frames in arrival order and ticks at 100 Hz on the receive clock (Replay: the outputs);
errors scores a body against the simulator's truth; static_flight, static_poses and static_jitter
fly the thesis arena's static body and measure its jitter. Used by benchmarks/fusion.py,
fusion_flights.py, camera_monitor.py and planner.py (and the fusion tests).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from visionpos.analysis.metrics import position_jitter
from visionpos.config.arena import ArenaConfig
from visionpos.fusion.pipeline import FusionPipeline
from visionpos.messages import BlobFrame


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
    monitor=None,
    tick_cb=None,
    feed_cb=None,
) -> Replay:
    """Feed frames to a new pipeline in arrival order and tick it at tick_hz on the receive clock.

    order: 'recv' (what a server sees) or 'capture'. Each tick happens after
    every frame received before it; states are predicted to the tick time.
    raw_cb(pipeline) is called after every push (for raw-pose collection). monitor: a
    fusion.camera_monitor.CameraMonitor fed as the server feeds it (its corrections applied).
    tick_cb(tick_ns, states) is called after every tick with its BodyStates. feed_cb(pipeline, t_ns) is called
    before every push (t_ns: the frame's arrival) and every tick: other inputs that arrived by t_ns (IMU samples).
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
            if feed_cb is not None:
                feed_cb(pipe, key[i])
            if monitor is None or monitor.admits(fr[i].camera_id):  # a knocked camera left out until it agrees
                pipe.push(fr[i])
            if raw_cb is not None:
                raw_cb(pipe)
            if monitor is not None:
                monitor.observe_frame(fr[i])
            i += 1
        if feed_cb is not None:
            feed_cb(pipe, int(tk))
        states = pipe.tick(int(tk))
        if tick_cb is not None:
            tick_cb(int(tk), states)
        if monitor is not None:
            monitor.observe_states(states)
            for c in monitor.step(int(tk)):
                pipe.set_camera_pose(c.camera_id, c.camera)
        for s in states:
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


STATIC_SIGMA_PX = 0.2


def static_flight(quick: bool):
    """The static body of the thesis arena (scenario, simulation): 0.2 px centroid noise, 3 or 10 s."""
    from visionpos.sim import load_scenario, simulate

    sc = load_scenario(
        "thesis",
        [
            "sim.sessions.static.quad.trajectory=static",
            "sim.sessions.static.quad.position=[0.2, -0.1, 0.8]",
            "sim.sessions.static.quad.yaw_deg=25",
        ],
        session="static",
        duration=3.0 if quick else 10.0,
        centroid_noise_px=STATIC_SIGMA_PX,
    )
    return sc, simulate(sc)


def static_poses(sc, sim, settings: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray, Replay]:
    """The static flight through the pipeline with fusion `settings`: the raw poses' times (T,) ns from
    0.5 s after the first, positions (T, 3) m and rotations (T, 3, 3), and the replay (its outputs)."""
    raws: dict[int, tuple] = {}

    def cb(p):
        r = p.last_raw.get(0)
        if r is not None:
            raws[r[0]] = r

    rep = replay(sc.arena, sim.frames, settings, raw_cb=cb)
    t = np.array(sorted(raws))
    t = t[t >= t[0] + 500_000_000]
    return t, np.array([raws[k][1] for k in t]), np.array([raws[k][2] for k in t]), rep


def static_jitter(t: np.ndarray, P: np.ndarray, rep: Replay) -> tuple[float, float]:
    """(raw, output) position jitter (mm per axis) of static_poses' results: second differences of the raw poses
    and of the tracked outputs from the first raw pose on."""
    ok = rep.tracked["quad"] & (rep.times_ns >= t[0])
    return position_jitter(t, P) * 1e3, position_jitter(rep.times_ns[ok], rep.positions["quad"][ok]) * 1e3
