"""The steps of a calibration session around the solvers: captures in, arena YAML out.

`visionpos calibrate` strings these together: the frames of a capture (a recording, or the
simulator for a dry run), the wand and ground-frame geometry from the arena or the command
line, and the calibrated cameras written back into a copy of the arena.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Sequence

import numpy as np

from visionpos.calibration.wand import CalibrationError, WandSpec
from visionpos.config.arena import ArenaConfig, dump_yaml, load_arena, parse_arena
from visionpos.messages import BlobFrame

# ground frames looked up by name in the arena's bodies and sim.props, in this order
GROUND_FRAME_NAMES = ("lframe", "ground", "triangle", "ground_frame")


def read_recording(path: str | Path) -> tuple[list[BlobFrame], dict[str, Any]]:
    """BlobFrames and the arena config stored in a recording."""
    from visionpos.protocol import ProtocolError, decode
    from visionpos.recording import RecordingReader

    reader = RecordingReader(path)
    frames: list[BlobFrame] = []
    bad = 0
    for recv_ns, data in reader.packets():
        try:
            msg = decode(data, recv_ns=recv_ns)
        except ProtocolError:
            bad += 1
            continue
        if isinstance(msg, BlobFrame):
            frames.append(msg)
    if not frames:
        raise CalibrationError(f"{path}: the recording holds no camera frames ({bad} undecodable packets)")
    return frames, reader.config


def capture_frames(recording: str | None, sim: str | None, session: str, overrides: Sequence[str] = (),
                   config: str | None = None) -> tuple[list[BlobFrame], ArenaConfig, list | None]:
    """(frames, arena with the cameras' intrinsics, the true cameras or None) of one capture.

    Exactly one of recording (an MCAP file) or sim (a scenario simulated with `session` and
    `overrides`) is given; config, when given, replaces the arena the capture carries.
    """
    if (recording is None) == (sim is None):
        raise CalibrationError("give either a RECORDING or --sim SCENARIO")
    truth = None
    if sim is not None:
        from visionpos.sim import load_scenario, simulate

        sc = load_scenario(sim, list(overrides), session=session)
        frames = simulate(sc).frames
        arena = sc.arena
        truth = list(sc.cameras)
    else:
        frames, cfg = read_recording(recording)
        arena = parse_arena(cfg, f"{recording} (embedded config)")
    if config is not None:
        arena = load_arena(config)
    return frames, arena, truth


def wand_settings(arena: ArenaConfig, ab: float | None = None, bc: float | None = None, known: str | None = None,
                  max_clock_offset_ms: float | None = None) -> tuple[WandSpec, float]:
    """(the wand, the largest clock offset to search for (ms)): given values, else calibration.wand in the
    arena, else the defaults. Unknown keys and values out of bounds raise ConfigError naming the key."""
    from visionpos.config.sections import CALIBRATION, WAND

    sec = WAND.check(CALIBRATION.check(arena.section("calibration")).sub("wand"))
    ab = ab if ab is not None else WAND.read(sec, "ab")
    bc = bc if bc is not None else WAND.read(sec, "bc")
    known = known if known is not None else WAND.read(sec, "known")
    mx = max_clock_offset_ms if max_clock_offset_ms is not None else WAND.read(sec, "max_clock_offset_ms")
    return WandSpec(ab, bc, known), float(mx)


def write_arena(arena: ArenaConfig, cameras: Sequence[Any], out: str | Path, extra: dict[str, Any]) -> None:
    """A copy of the arena with these cameras and `extra` merged into its calibration section."""
    raw = arena.to_dict()
    raw["cameras"] = [c.to_dict() for c in cameras]
    cal = raw.get("calibration") if isinstance(raw.get("calibration"), dict) else {}
    cal.update(extra)
    raw["calibration"] = cal
    dump_yaml(raw, out)


def wand_section(cal: Any, max_offset_ms: float, ref: int = 0) -> dict[str, Any]:
    """The `calibration:` keys a wand solve (a bundle.WandCalibration) writes into the arena: the wand and the
    extrinsics' figures of merit (residuals px, wand length error mm, clock offsets ms, warnings)."""
    spec = cal.spec
    L = cal.length_stats()
    stats = cal.camera_stats()
    return {
        "wand": {"ab": spec.ab, "bc": spec.bc, "known": spec.known, "max_clock_offset_ms": max_offset_ms},
        "extrinsics": {
            "frame": f"camera {cal.cameras[ref].name}",
            "time_steps": len(cal.data.times_ns),
            "rms_px": {s["name"]: round(s["rms_px"], 4) for s in stats},
            "wand_ac_std_mm": round(L["ac_std"] * 1000, 4),
            "wand_ac_mean_err_mm": round(L["ac_mean_err"] * 1000, 4),
            "clock_offset_ms": {s["name"]: round(s["offset_ms"], 4) for s in stats},
            "wand_ratio_measured": round(cal.check.ratio, 6) if cal.check else None,
            "warnings": list(cal.warnings),
        },
    }


def solve_wand_to_file(frames: Sequence[BlobFrame], arena: ArenaConfig, spec: WandSpec, max_offset_ms: float,
                       out: str | Path) -> dict[str, Any]:
    """The wand solve of `frames` (a wand wave) with the arena's intrinsics, written as a calibrated copy of the
    arena to `out`; returns what the console shows (JSON-ready): {"out", "time_steps", "cameras": [{"id", "name",
    "rms_px", "max_px", "views", "offset_ms"}], "wand_ac_mean_err_mm", "wand_ac_std_mm", "warnings", "seconds"}.
    Raises CalibrationError (what to capture or fix) when the frames cannot give a calibration."""
    import time

    from visionpos.calibration.wand_solve import calibrate_wand

    t0 = time.perf_counter()
    cal = calibrate_wand(frames, list(arena.cameras), spec, max_offset_ms=max_offset_ms)
    write_arena(arena, cal.cameras, out, wand_section(cal, max_offset_ms))
    L = cal.length_stats()

    def num(x: float, nd: int) -> float | None:
        return round(float(x), nd) if np.isfinite(x) else None

    return {
        "out": str(out),
        "time_steps": len(cal.data.times_ns),
        "cameras": [{"id": s["id"], "name": s["name"], "rms_px": num(s["rms_px"], 3), "max_px": num(s["max_px"], 3),
                     "views": s["views"], "offset_ms": num(s["offset_ms"], 3)} for s in cal.camera_stats()],
        "wand_ac_mean_err_mm": num(L["ac_mean_err"] * 1000, 3),
        "wand_ac_std_mm": num(L["ac_std"] * 1000, 3),
        "warnings": list(cal.warnings),
        "seconds": round(time.perf_counter() - t0, 2),
    }


def ground_layout(arena: ArenaConfig, frame: str | None = None, markers: str | None = None,
                  marker_height: float | None = None) -> tuple[np.ndarray, float]:
    """(marker layout (M, 3) in m, marker centre height above the floor) of the ground frame.

    markers: 'X,Y,Z;X,Y,Z;...' given by hand; else the body or sim prop named `frame`; else
    calibration.lframe in the arena; else the first body or prop named one of GROUND_FRAME_NAMES.
    """
    if markers:
        try:
            layout = np.array([[float(v) for v in p.split(",")] for p in markers.split(";") if p.strip()])
        except ValueError:
            raise CalibrationError(f"--markers '{markers}': expected X,Y,Z;X,Y,Z;... in metres") from None
        if layout.ndim != 2 or layout.shape[1] != 3:
            raise CalibrationError(f"--markers '{markers}': every marker needs 3 numbers")
        return layout, 0.007 if marker_height is None else marker_height
    if not frame:
        from visionpos.config.sections import CALIBRATION, LFRAME

        cal = CALIBRATION.check(arena.section("calibration"))
        if cal.has("lframe"):
            lf = LFRAME.check(cal.sub("lframe"))
            layout = LFRAME.read(lf, "markers")
            if len(layout) < 3:
                raise lf.error("markers", "needs at least 3 markers")
            h = marker_height if marker_height is not None else LFRAME.read(lf, "marker_diameter") / 2
            return np.asarray(layout, float), h
    candidates = [frame] if frame else list(GROUND_FRAME_NAMES)
    from visionpos.sim.scenario import sim_props

    entries = [*arena.bodies, *sim_props(arena)]
    for name in candidates:
        for e in entries:
            if e.name == name:
                return np.asarray(e.markers, float), e.marker_diameter / 2 if marker_height is None else marker_height
    raise CalibrationError(
        f"{arena.source}: no ground frame named {' or '.join(candidates)} in bodies or sim.props; "
        "give --frame NAME or --markers X,Y,Z;..."
    )
