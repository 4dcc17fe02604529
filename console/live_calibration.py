"""The calibration panel of a running fusion server (`visionpos serve` and `visionpos demo`): a wand wave
gathered from the live stations, its solve compared with the calibration the server runs on, and the
apply after the operator confirmed it (docs/calibration.md, "Applying a solve to the running server").

"wave" {"on": true} starts gathering (every frame Ingest accepts goes to the fusion and to the assistant:
one list append), {"on": false} stops it. "solve" runs the wand solve in a child process, as in
`record`'s console (console/calibration.py), then aligns the solved cameras to the running world (the
rigid transform that best maps their centres onto the running cameras', so tracked bodies keep their
place) and scores both calibrations on the same wand frames (`wand_residuals`: every wand point
triangulated from all cameras, each camera's reprojection RMS, and the A-C length error).

"apply_calibration" swaps the solved poses into the running pipeline between two frames
(FusionServer.set_cameras) and writes them, with the solve's report, into the arena file after a backup
(console/arena_file.py). "ground" gathers GROUND_S seconds of the ground frame lying still and finds
it (calibration/ground.py: calibrate_ground on the running cameras), "apply_ground" applies the floor
transform the same way. Every apply is refused with the reason, changing nothing (`refusal`): no
result, one applied already, a solve not better than the running calibration, a result older than
MAX_AGE_S, the running cameras changed since (scene_id: a camera monitor's correction, another apply),
an arena that is no file or is built in.
"""

from __future__ import annotations

import asyncio
import logging
import time
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np
from scipy.spatial.transform import Rotation

from console.arena_file import writable_arena, write_camera_poses
from console.calibration import MAX_FRAMES, CalibrationAssistant
from console.view import scene
from visionpos.calibration.coverage import Thresholds
from visionpos.camera.model import Camera
from visionpos.messages import BlobFrame

log = logging.getLogger(__name__)

MAX_AGE_S = 600.0  # a result older than this is not applied: the cameras may have been touched since
MIN_GAIN = 0.05  # the new solve's px RMS over all cameras must be this share below the running calibration's
WAND_SLACK_MM = 0.5  # and its wand-length error no more than this larger (mm)
GROUND_S = 2.0  # seconds of the ground frame lying still (by the frames' capture times)


# ---------------------------------------------------------------- pure functions (run in the solve's child too)

def align_cameras(solved: Sequence[Camera], running: Sequence[Camera]) -> tuple[list[Camera], np.ndarray, np.ndarray]:
    """The solved cameras (the wand solve's world: its reference camera) in the running cameras' world: (cameras,
    R (3, 3), t (3,)) with X_running = R X_solved + t, the rigid transform that best maps the solved centres (m)
    onto the running ones (Kabsch; two cameras: the rotation from their orientations). The wand keeps the scale."""
    from visionpos.calibration.ground import apply_world
    from visionpos.geometry.alignment import kabsch_svd
    from visionpos.geometry.rotations import average_rotations

    Cs = np.array([c.center for c in solved])
    Cr = np.array([c.center for c in running])
    if len(Cs) >= 3:
        R, t = kabsch_svd(Cs, Cr)
    else:  # camera R_s = R_r R: the world turn from each camera's orientation
        R = average_rotations(np.stack([r.R.T @ s.R for s, r in zip(solved, running)]))
        t = Cr.mean(axis=0) - R @ Cs.mean(axis=0)
    return apply_world(solved, R, t), R, t


def wand_residuals(cameras: Sequence[Camera], pixels: np.ndarray, ac_m: float) -> dict[str, Any]:
    """A calibration scored on wand frames: pixels (F, V, 3, 2) distorted px of the wand's A, B, C (NaN: not seen;
    the solve's aligned frames); each point seen by two cameras or more is triangulated from all of them.
    Returns {"cameras": [{"id", "name", "rms_px", "max_px"}], "rms_px" (all views), "worst_rms_px",
    "wand_ac_err_mm" (mean |AC| - ac_m), "wand_ac_std_mm", "points"}; None where nothing was measured."""
    from visionpos.geometry.triangulation import triangulate_pixels

    F, V = pixels.shape[:2]
    tri = triangulate_pixels(list(cameras), pixels.transpose(0, 2, 1, 3).reshape(F * 3, V, 2))
    ok = tri.n_views >= 2
    res = np.where(ok[:, None], tri.residuals, np.nan)  # (F * 3, V) px
    cams = []
    for v, c in enumerate(cameras):
        r = res[:, v][np.isfinite(res[:, v])]
        cams.append({"id": c.id, "name": c.name, "rms_px": _num(np.sqrt(np.mean(r ** 2))) if len(r) else None,
                     "max_px": _num(r.max()) if len(r) else None})
    every = res[np.isfinite(res)]
    P = tri.points.reshape(F, 3, 3)
    ac = np.linalg.norm(P[:, 2] - P[:, 0], axis=1)
    ac = ac[ok.reshape(F, 3).all(axis=1) & np.isfinite(ac)]
    worst = [c["rms_px"] for c in cams if c["rms_px"] is not None]
    return {"cameras": cams, "rms_px": _num(np.sqrt(np.mean(every ** 2))) if len(every) else None,
            "worst_rms_px": max(worst) if worst else None,
            "wand_ac_err_mm": _num((ac.mean() - ac_m) * 1e3) if len(ac) else None,
            "wand_ac_std_mm": _num(ac.std() * 1e3) if len(ac) else None, "points": int(ok.sum())}


def verdict(current: dict[str, Any], new: dict[str, Any]) -> str | None:
    """Why the new calibration is not better than the current one (wand_residuals of each on the same frames),
    or None when it is: its px RMS over all cameras MIN_GAIN lower, its worst camera's RMS no higher, and its
    wand-length error at most WAND_SLACK_MM larger."""
    a, b = current, new
    if b["rms_px"] is None or a["rms_px"] is None:
        return "no wand point seen by two cameras to compare them on"
    if not b["rms_px"] <= (1.0 - MIN_GAIN) * a["rms_px"]:
        return (f"the new solve is not better: {b['rms_px']:.3f} px RMS against the running calibration's "
                f"{a['rms_px']:.3f} px on the same wand frames (it must be {100 * MIN_GAIN:.0f} % lower)")
    if not b["worst_rms_px"] <= a["worst_rms_px"]:
        return (f"the new solve's worst camera is worse: {b['worst_rms_px']:.3f} px against "
                f"{a['worst_rms_px']:.3f} px")
    ea, eb = abs(a["wand_ac_err_mm"] or 0.0), abs(b["wand_ac_err_mm"] or 0.0)
    if eb > ea + WAND_SLACK_MM:
        return f"the new solve's wand length is further off: {eb:.2f} mm against {ea:.2f} mm"
    return None


def solve_and_compare(frames: Sequence[BlobFrame], arena: Any, running: Sequence[Camera], spec: Any,
                      max_offset_ms: float, out: str) -> tuple[dict[str, Any], list[Camera], dict[str, Any]]:
    """The wand solve of frames (the solve's child process): (the console's result, as solve_wand_to_file's plus
    "current", "new" (wand_residuals on the solve's frames), "refused" (verdict) and "moved" (per camera: the
    rotation, deg, and shift, mm, from the running pose); the solved cameras in the running world; the
    `calibration.extrinsics` report). The aligned calibration is written to out as an arena file."""
    from visionpos.calibration.wand_solve import calibrate_wand
    from visionpos.calibration.workflow import wand_section, write_arena

    t0 = time.perf_counter()
    cal = calibrate_wand(list(frames), list(arena.cameras), spec, max_offset_ms=max_offset_ms)
    aligned, _, _ = align_cameras(cal.cameras, running)
    report = wand_section(cal, max_offset_ms)["extrinsics"]
    report["frame"] = "the running world (the solve aligned to the cameras it replaced)"
    write_arena(arena, aligned, out, {"extrinsics": report})
    current = wand_residuals(running, cal.data.pixels, spec.ac)
    new = wand_residuals(aligned, cal.data.pixels, spec.ac)
    L = cal.length_stats()
    moved = [{"id": a.id, "name": a.name,
              "rotation_deg": _num(np.degrees(Rotation.from_matrix(a.R @ r.R.T).magnitude()), 3),
              "shift_mm": _num(np.linalg.norm(a.center - r.center) * 1e3, 1)} for a, r in zip(aligned, running)]
    result = {
        "out": str(out), "time_steps": len(cal.data.times_ns),
        "cameras": [{"id": s["id"], "name": s["name"], "rms_px": _num(s["rms_px"]), "max_px": _num(s["max_px"]),
                     "views": s["views"], "offset_ms": _num(s["offset_ms"])} for s in cal.camera_stats()],
        "wand_ac_mean_err_mm": _num(L["ac_mean_err"] * 1000), "wand_ac_std_mm": _num(L["ac_std"] * 1000),
        "warnings": list(cal.warnings), "seconds": round(time.perf_counter() - t0, 2),
        "current": current, "new": new, "refused": verdict(current, new), "moved": moved,
    }
    return result, aligned, report


def live_out(arena_source: str) -> Path:
    """Where a live Solve writes: beside the arena file (ARENA.yaml -> ARENA.calibrated.yaml), or in the working
    directory for a built-in arena (NAME.calibrated.yaml)."""
    from console.arena_file import BUILTIN

    p = Path(arena_source).resolve()
    if p.is_file() and BUILTIN not in p.parents:
        return p.with_name(p.stem + ".calibrated.yaml")
    return Path.cwd() / (Path(arena_source).stem + ".calibrated.yaml")


def _num(x: float, nd: int = 3) -> float | None:
    return round(float(x), nd) if np.isfinite(x) else None


# ---------------------------------------------------------------- the live assistant

class _Tee:
    """What Ingest pushes into while a wave or the ground frame is gathered: the fusion's feed, then the
    assistant (one append)."""

    def __init__(self, feed: Any, sink: Callable[[BlobFrame], None]):
        self.feed, self.sink = feed, sink

    def push(self, frame: BlobFrame) -> None:
        self.feed.push(frame)
        self.sink(frame)

    def remove_camera(self, camera_id: int) -> None:
        self.feed.remove_camera(camera_id)


class LiveCalibration(CalibrationAssistant):
    """The calibration panel of a FusionServer's console (see the module docstring). out_path: where Solve writes
    the aligned calibration (an arena file); pool: the solve's executor (None: a spawned child process)."""

    commands = ("solve", "wave", "apply_calibration", "ground", "apply_ground")
    live = True

    def __init__(self, server: Any, out_path: str | Path, thresholds: Thresholds = Thresholds(),
                 max_frames: int = MAX_FRAMES, pool: Any = None, clock: Callable[[], float] = time.monotonic):
        super().__init__(server.arena, out_path, thresholds, max_frames, pool)
        self.server = server
        self.clock = clock
        self.gathering = False
        self.applied: dict[str, Any] | None = None  # the last apply: what, file, backup
        self.ground: dict[str, Any] = {"state": "idle", "result": None, "error": None}
        self._solved: dict[str, Any] | None = None  # cameras, report, scene_id, time of the result to apply
        self._grounded: dict[str, Any] | None = None
        self._ground_frames: list[BlobFrame] = []
        self._ground_t0: int | None = None
        self._ground_task: asyncio.Task | None = None

    # ---------------------------------------------------------------- the running cameras

    def running_cameras(self) -> list[Camera]:
        """The cameras the pipeline fuses with now, in the arena's order."""
        cams = self.server.pipeline.cameras
        return [cams[c.id] for c in self.server.arena.cameras]

    def scene_id(self) -> str:
        """The running scene's id (console/view.py scene_id over the running cameras and the bodies)."""
        return scene(self.server.arena.with_cameras(self.running_cameras()))["scene_id"]

    def _feed(self, on: bool) -> None:
        ingest = self.server.ingest
        teed = isinstance(ingest.pipeline, _Tee)
        if on and not teed:
            ingest.pipeline = _Tee(ingest.pipeline, self._take)
        elif not on and teed:
            ingest.pipeline = ingest.pipeline.feed

    def _take(self, frame: BlobFrame) -> None:
        if self.gathering:
            self.push(frame)
        if self.ground["state"] == "gathering":
            self._ground_frames.append(frame)
            self._ground_t0 = frame.capture_ns if self._ground_t0 is None else self._ground_t0
            if frame.capture_ns - self._ground_t0 >= GROUND_S * 1e9:
                self.ground = {"state": "solving", "result": None, "error": None}
                self.version += 1
                self._feed(self.gathering)
                self._ground_task = asyncio.get_running_loop().create_task(self._solve_ground(),
                                                                           name="visionpos-ground")

    # ---------------------------------------------------------------- the console's face

    def state(self) -> dict[str, Any]:
        done = {k: bool(b and b.get("applied")) for k, b in (("solve", self._solved), ("ground", self._grounded))}
        return {**super().state(), "live": True, "gathering": self.gathering, "applied": self.applied,
                "ground": dict(self.ground), "applied_results": done}

    async def stop(self) -> None:
        self._feed(False)
        if self._ground_task is not None:
            self._ground_task.cancel()
        await super().stop()

    async def command(self, msg: dict[str, Any]) -> dict[str, Any]:
        cmd = msg.get("cmd")
        if cmd == "solve":
            basis = {"scene_id": self.scene_id(), "time": self.clock()}
            reply = await super().command(msg)  # refused: nothing changed
            self._solved = basis  # before its result: the solve's task has not run yet
            if self.gathering:  # the frames the solve took are fixed: the wave ends here
                self.gathering = False
                self._feed(self.ground["state"] == "gathering")
            return reply
        if cmd == "wave":
            if set(msg) != {"cmd", "on"} or not isinstance(msg["on"], bool):
                raise ValueError('wave: expected {"cmd": "wave", "on": true or false}')
            if msg["on"] and not self.gathering:
                self.reset()
            self.gathering = msg["on"]
            self._feed(self.gathering or self.ground["state"] == "gathering")
            self.version += 1
            return {"wave": "gathering" if self.gathering else "stopped", "frames": len(self.frames)}
        if set(msg) != {"cmd"}:
            raise ValueError(f'{cmd}: expected {{"cmd": "{cmd}"}}')
        if cmd == "ground":
            if self.ground["state"] in ("gathering", "solving"):
                raise ValueError("ground: the ground frame is being found; wait for its result")
            self.ground = {"state": "gathering", "result": None, "error": None}
            self._ground_frames, self._ground_t0, self._grounded = [], None, None
            self._feed(True)
            self.version += 1
            return {"ground": "gathering", "seconds": GROUND_S}
        if cmd == "apply_calibration":
            return self._apply_solve()
        return self._apply_ground()

    # ---------------------------------------------------------------- solve and ground

    def _job(self, frames: list[BlobFrame]) -> tuple[Any, ...]:
        return (solve_and_compare, frames, self.arena, self.running_cameras(), self.spec, self.max_offset_ms,
                str(self.out_path))

    def _accept(self, result: Any) -> dict[str, Any]:
        shown, cameras, report = result
        if self._solved is not None:
            self._solved.update(cameras=cameras, report=report)
        return shown

    async def _solve_ground(self) -> None:
        from visionpos.calibration.ground import calibrate_ground
        from visionpos.calibration.wand import CalibrationError
        from visionpos.calibration.workflow import ground_layout

        frames, running = self._ground_frames, self.running_cameras()
        basis = {"scene_id": self.scene_id(), "time": self.clock()}
        try:
            layout, height = ground_layout(self.arena)
            g = await asyncio.get_running_loop().run_in_executor(None, lambda: calibrate_ground(
                frames, running, layout, marker_height=height))
        except CalibrationError as e:
            self.ground = {"state": "failed", "result": None, "error": str(e)}
        except Exception as e:  # said on the page, logged with its traceback
            log.exception("calibration assistant: the ground step failed")
            self.ground = {"state": "failed", "result": None, "error": f"{type(e).__name__}: {e}"}
        else:
            turn = Rotation.from_matrix(g.R).magnitude()
            tilt = np.degrees(np.arccos(np.clip(g.R[2, 2], -1.0, 1.0)))
            result = {"rotation_deg": _num(np.degrees(turn)), "tilt_deg": _num(tilt),
                      "shift_mm": _num(np.linalg.norm(g.t) * 1e3, 1), "R": np.round(g.R, 6).tolist(),
                      "t_m": np.round(g.t, 5).tolist(), "fit_mm": _num(g.fit_rms * 1e3),
                      "markers_m": np.round(g.markers, 4).tolist(), "frames": len(frames),
                      "heights_m": {c.name: _num(c.center[2]) for c in g.cameras}}
            self.ground = {"state": "found", "result": result, "error": None}
            self._grounded = {**basis, "cameras": g.cameras}
        self._ground_frames = []
        self.version += 1

    # ---------------------------------------------------------------- apply

    def refusal(self, what: str, basis: dict[str, Any] | None) -> str | None:
        """Why the result in basis (scene_id, time, cameras) cannot be applied now, or None."""
        if basis is None or basis.get("cameras") is None:
            return f"{what}: nothing to apply yet" + (" (Solve first)" if what == "apply" else " (set ground first)")
        if basis.get("applied"):
            return f"{what}: this result is applied already"
        age = self.clock() - basis["time"]
        if age > MAX_AGE_S:
            return (f"{what}: the result is {age / 60:.0f} min old (over {MAX_AGE_S / 60:.0f} min): the cameras may "
                    "have been touched since; gather and solve again")
        if basis["scene_id"] != self.scene_id():
            return (f"{what}: the running cameras changed since the result was made (a camera monitor correction or "
                    "another apply); gather and solve again")
        return None

    def _apply_solve(self) -> dict[str, Any]:
        if self.solve["running"]:
            raise ValueError("apply: a solve is running; wait for its result")
        why = self.refusal("apply", self._solved)
        result = self.solve["result"]
        if why is None and result is not None and result.get("refused"):
            why = f"apply: {result['refused']}"
        if why is not None:
            raise ValueError(why)
        return self._apply("apply", self._solved, self._solved["report"])

    def vehicles_sending(self) -> list[str]:
        """The vehicles the running server's bridge sends poses to now (its sinks' `vehicles`: sending_state)."""
        return [v.cfg.name for sink in self.server.sinks for v in getattr(sink, "vehicles", ())
                if v.sending_state() == "sending"]

    def _apply_ground(self) -> dict[str, Any]:
        why = self.refusal("ground", self._grounded)
        flying = self.vehicles_sending() if why is None else []
        if flying:  # the floor moves the world frame: a flying autopilot would see its position jump
            why = (f"ground: {', '.join(flying)} receive(s) poses now, and the floor moves the world they fly in; "
                   "land and stop their output first")
        if why is not None:
            raise ValueError(why)
        return self._apply("ground", self._grounded, None)

    def _apply(self, what: str, basis: dict[str, Any], report: dict[str, Any] | None) -> dict[str, Any]:
        """The file first (the step that can fail: then nothing changed), then the running pipeline."""
        cameras: list[Camera] = basis["cameras"]
        path = writable_arena(self.server.arena.source, what)
        backup = write_camera_poses(path, {c.id: c.to_dict()["pose"] for c in cameras}, report, what=what)
        self.server.set_cameras(cameras)
        basis["applied"] = True
        self.arena = self.server.arena
        self.applied = {"what": "wand solve" if what == "apply" else "ground frame", "file": str(path),
                        "backup": str(backup)}
        log.warning("console: %s applied to the running server and written to %s (the old file: %s)",
                    self.applied["what"], path, backup)
        self.version += 1
        return {"applied": self.applied["what"], "file": str(path), "backup": str(backup)}
