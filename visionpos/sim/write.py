"""A simulated session written as a recording, the library behind `visionpos sim`.

The recording is what `visionpos record` would have captured from real
stations (protocol version 2): one accepted Hello per camera (its control
counter 1; a live server records only the HELLO that carried a valid cookie,
and replay trusts recorded registrations), then every frame as its protocol
datagram in that station's session, stamped with its receive time, in
receive order; plus the arena config (with
the overrides applied), the bodies' ground truth at sim.truth_rate Hz
on /sim/truth, and optionally every frame's blob labels on /sim/frame_truth.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from visionpos.config.arena import apply_overrides, load_yaml, parse_arena, resolve_config_path
from visionpos.sim.capture import iter_frames
from visionpos.sim.scenario import Scenario, parse_sim

TOPIC_FRAME_TRUTH = "/sim/frame_truth"
TOPIC_SIM_INFO = "/sim/info"


@dataclass
class SimRecording:
    """What write_recording wrote: the scenario, its config file, per-camera counts and the time it took."""

    path: Path
    scenario: Scenario
    config_path: Path
    per_camera: dict[int, dict[str, int]]  # camera id -> frames, blobs, spurious (blobs of no marker)
    wall_s: float


def write_recording(scenario: str | Path, out: str | Path, *, duration_s: float | None = None,
                    seed: int | None = None, session: str | None = None, overrides: Sequence[str] = (),
                    key: bytes | None = None, frame_truth: bool = False) -> SimRecording:
    """Simulate `scenario` (built-in name or arena YAML with a sim section) and write it to `out`.

    duration_s, seed, session: replace sim.duration, sim.seed, sim.session; overrides: any
    `key=value` config changes. key: HMAC key the packets are signed with. frame_truth: also
    record every frame's blob labels and true pixels.
    """
    from visionpos import protocol as P
    from visionpos.recording import RecordingWriter

    path = resolve_config_path(scenario)
    data = load_yaml(path)
    sim_over = [f"sim.duration={duration_s}"] if duration_s is not None else []
    if seed is not None:
        sim_over.append(f"sim.seed={seed}")
    if session is not None:
        sim_over.append(f"sim.session={session}")
    data = apply_overrides(data, list(overrides) + sim_over)
    arena = parse_arena(data, str(path))
    sc = parse_sim(arena)

    out = Path(out)
    meta = {
        "source": "visionpos sim",
        "scenario": str(path),
        "session": sc.session,
        "seed": sc.seed,
        "duration_s": sc.duration_s,
        "start_ns": sc.start_ns,
        "overrides": list(overrides),
        "signed": key is not None,
    }
    t_wall = time.perf_counter()
    per_cam: dict[int, dict[str, int]] = {t.camera_id: {"frames": 0, "blobs": 0, "spurious": 0} for t in sc.timings}
    with RecordingWriter(out, data, meta) as rec:
        rec.write_json(TOPIC_SIM_INFO, sc.start_ns, _sim_info(sc))
        first_recv = sc.start_ns
        sessions: dict[int, int] = {}
        for t, cam in zip(sc.timings, sc.cameras):
            sessions[cam.id] = _session(t.station_id)
            hello = P.Hello(
                station_id=t.station_id,
                camera_id=cam.id,
                session=sessions[cam.id],
                width=cam.model.width,
                height=cam.model.height,
                fps=float(t.fps),
                camera_kind=cam.model.kind,
                camera_name=cam.name,
                software="visionpos-sim",
                counter=1,
            )
            rec.write_packet(first_recv, P.encode(hello, key), _source(t.station_id))
        for frame, truth in iter_frames(sc, order="recv", with_truth=True):
            wire = dataclasses.replace(frame, session=sessions[frame.camera_id])
            rec.write_packet(frame.recv_ns, P.encode_frame(wire, key), _source(frame.station_id))
            c = per_cam[frame.camera_id]
            c["frames"] += 1
            c["blobs"] += len(frame.blobs)
            c["spurious"] += int(np.count_nonzero(truth.body < 0))
            if frame_truth:
                rec.write_json(
                    TOPIC_FRAME_TRUTH,
                    frame.recv_ns,
                    {
                        "camera_id": truth.camera_id,
                        "seq": truth.seq,
                        "true_ns": truth.true_ns,
                        "station_ns": truth.station_ns,
                        "body": truth.body.tolist(),
                        "marker": truth.marker.tolist(),
                        "true_xy": np.round(truth.true_xy, 6).tolist(),
                        "merged": truth.merged.tolist(),
                        "exposure_ns": truth.exposure_ns.tolist(),
                    },
                )
        step = int(round(1e9 / sc.truth_rate_hz))
        times = np.arange(sc.start_ns, sc.end_ns + 1, step, dtype=np.int64)
        for b in sc.bodies:
            pos, quat = sc.truth_at(b.name, times)
            for ti, p, q in zip(times, pos, quat):
                rec.write_truth(int(ti), b.name, p, q)
    return SimRecording(out, sc, path, per_cam, time.perf_counter() - t_wall)


def _session(station_id: int) -> int:
    """The simulated station's session number (fixed: the recording is deterministic)."""
    return 0x5100 + station_id


def _source(station_id: int) -> tuple[str, int]:
    """A made-up sender address per station, as the recorder would log it."""
    return (f"10.0.0.{10 + station_id % 240}", 5601)


def _sim_info(sc) -> dict:
    """Per-camera timing and per-station clock truth, for analysis of a recording."""
    return {
        "session": sc.session,
        "seed": sc.seed,
        "bodies": [{"name": b.name, "id": b.id, "tracked": b.tracked} for b in sc.bodies],
        "cameras": [
            {
                "camera_id": t.camera_id,
                "station_id": t.station_id,
                "fps": t.fps,
                "phase_ns": t.phase_ns,
                "period_ns": t.period_ns,
                "jitter_ns": t.jitter_ns,
                "drop_probability": t.drop_probability,
                "rolling_shutter_ns": t.readout_ns,
            }
            for t in sc.timings
        ],
        "stations": [
            {
                "station_id": c.station_id,
                "offset_ns": c.offset_ns,
                "drift_ppm": c.drift_ppm,
                "residual_bias_ns": c.bias_ns,
                "residual_bound_ns": c.residual_bound_ns,
            }
            for c in sc.clocks.values()
        ],
    }
