"""What the console shows, read from a running fusion server (or a replay): the scene once, the live state per update.

The source is any object with the FusionServer's observable parts (duck-typed, read only):
`arena`, `pipeline` (FusionPipeline: obs, last_px, tracks, models, loose_points, untracked_why,
last_verdict), `last_states` (the newest tick's BodyStates), `health()` and `clock()`. A replay
session (console/replay.py) offers the same.

Nothing here changes the source; reading a camera's newest observation and predicting the
tracked bodies to its capture time (the filter's non-mutating output_at) is all it does, once
per console update (30 Hz), never per packet.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from visionpos.fusion.matching import Projector

# a leftover blob that stays within one cell this long, seen in most updates, looks like a reflection
STATIC_BLOB_S = 5.0
STATIC_CELL_PX = 6.0
STATIC_GAP_S = 1.0  # a cell not seen for this long starts over
STATIC_MAX_CELLS = 64  # per camera: a flood of noise cannot grow the table
STATIC_MASK_MARGIN_PX = 6
# the per-camera residual: exponential average over updates with matched blobs
RESIDUAL_EWMA = 0.1


def _r(x: float, nd: int) -> float | None:
    """JSON-safe rounded float (NaN and inf -> None)."""
    return round(float(x), nd) if math.isfinite(x) else None


def _quat_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrix (3, 3) of a unit quaternion (x, y, z, w) (scipy's from_quat costs more than this whole
    update's arithmetic)."""
    x, y, z, w = q / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def scene(arena: Any) -> dict[str, Any]:
    """The static part: each camera's intrinsics and pose (camera->world), each body's markers, the
    calibration's residuals. Sent once per client."""
    cams = []
    raw_cams = arena.raw.get("cameras") or []
    for i, c in enumerate(arena.cameras):
        m = c.model
        R_c2w = np.asarray(c.R).T
        centre = -R_c2w @ np.asarray(c.t)
        raw = raw_cams[i] if i < len(raw_cams) and isinstance(raw_cams[i], dict) else {}
        cams.append({
            "id": c.id, "name": c.name, "width": m.width, "height": m.height, "fx": m.fx, "fy": m.fy,
            "cx": m.cx, "cy": m.cy, "fps": float(c.fps), "position": [round(float(v), 5) for v in centre],
            "R_c2w": [[round(float(v), 6) for v in row] for row in R_c2w], "station": raw.get("station"),
        })
    bodies = [{"name": b.name, "id": b.id, "markers": [[round(float(v), 5) for v in p] for p in b.markers]}
              for b in arena.bodies]
    return {"type": "scene", "source": arena.source, "cameras": cams, "bodies": bodies,
            "calibration_rms_px": calibration_residuals(arena)}


def calibration_residuals(arena: Any) -> dict[str, float]:
    """Camera name -> reprojection RMS (px) of the wand calibration, where the arena carries its report."""
    cal = arena.raw.get("calibration") or {}
    ext = cal.get("extrinsics") if isinstance(cal, dict) else None
    rms = ext.get("rms_px") if isinstance(ext, dict) else None
    if not isinstance(rms, dict):
        return {}
    return {str(k): float(v) for k, v in rms.items() if isinstance(v, (int, float)) and not isinstance(v, bool)}


@dataclass
class _Cell:
    x: float
    y: float
    first_ns: int
    last_ns: int
    hits: int = 1


@dataclass
class CameraWatch:
    """Per camera, across updates: its live reprojection residual and its static leftover blobs."""

    residual_px: float | None = None
    last_capture_ns: int = 0
    cells: dict[tuple[int, int], _Cell] = field(default_factory=dict)
    updates: int = 0


class ConsoleView:
    """Builds the console's messages from a source (see the module docstring)."""

    def __init__(self, source: Any):
        self.source = source
        arena = source.arena
        self.scene = scene(arena)
        self.cameras = {c.id: c for c in arena.cameras}
        self.projectors = {c.id: Projector(c) for c in arena.cameras}  # compiled, as fusion projects
        sizes = [len(b.markers) for b in arena.bodies]
        self.marker_body = np.repeat(np.arange(len(sizes)), sizes).astype(np.int64)
        self.marker_start = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
        self.body_markers = [np.asarray(b.markers, dtype=float).reshape(-1, 3) for b in arena.bodies]
        self.watch = {c.id: CameraWatch() for c in arena.cameras}

    # ---------------------------------------------------------------- per camera

    def _predicted(self, pipe: Any, t_ns: int) -> list[tuple[int, np.ndarray, np.ndarray]]:
        """(body, markers (M, 3) in the world at t_ns, velocity (3,)) of each tracked body, from its filter:
        one prediction per body and update; each camera shifts it to its own capture time."""
        out = []
        for b, tr in enumerate(pipe.tracks):
            if not tr.tracked or b >= len(self.body_markers):
                continue
            p, q, v = tr.filter.output_at(t_ns)[:3]
            if np.all(np.isfinite(p)) and np.all(np.isfinite(q)) and np.all(np.isfinite(v)):
                out.append((b, self.body_markers[b] @ _quat_matrix(q).T + p, v))
        return out

    def camera_states(self, now_ns: int, watch: bool = False, rays: frozenset[int] = frozenset()
                      ) -> list[dict[str, Any]]:
        """Per camera: blobs [u, v, body (-1 = left over)] and the filter's predicted markers [u, v, body] at
        the frame's capture time, pixels in tenths (integers encode fastest), the frame's age; for the
        cameras in `rays` also each blob's undistorted coordinates [x, y] x 1e5 (its ray). watch: also
        update the residual and static-blob watches (a few times a second is plenty)."""
        pipe = self.source.pipeline
        obs_all = getattr(pipe, "obs", {})
        px_all = getattr(pipe, "last_px", {})
        frames = [(cid, obs_all.get(cid), px_all.get(cid)) for cid in self.cameras]
        newest = max((int(o.capture_ns) for _, o, _ in frames if o is not None), default=now_ns)
        predicted = self._predicted(pipe, newest)
        n_markers = len(self.marker_body)
        out = []
        for cid, o, px in frames:
            if o is None or px is None or len(px) != len(o.label):
                out.append({"id": cid, "blobs": [], "pred": [], "age_ms": None})
                continue
            label = np.asarray(o.label)
            ok = (label >= 0) & (label < n_markers)
            fin = np.isfinite(px[:, :2]).all(axis=1)
            rows = np.empty((len(px), 3), dtype=np.int64)
            rows[fin, :2] = np.rint(px[fin, :2] * 10.0)
            rows[:, 2] = -1
            rows[ok, 2] = self.marker_body[label[ok]]
            d: dict[str, Any] = {"id": cid, "blobs": rows[fin].tolist(), "pred": [],
                                 "age_ms": _r((now_ns - int(o.capture_ns)) * 1e-6, 1)}
            if cid in rays:
                xn = np.asarray(o.xn, dtype=float).reshape(-1, 2)
                good = np.isfinite(xn).all(axis=1)
                d["rays"] = np.rint(xn[good] * 1e5).astype(np.int64).tolist()
            uv = None
            if predicted:
                dt_s = (int(o.capture_ns) - newest) * 1e-9
                world = np.concatenate([m + v * dt_s for _, m, v in predicted])
                uv = self.projectors[cid].project(world)
                seen = np.isfinite(uv).all(axis=1)
                pr = np.empty((int(seen.sum()), 3), dtype=np.int64)
                pr[:, :2] = np.rint(uv[seen] * 10.0)
                pr[:, 2] = np.concatenate([np.full(len(m), b, dtype=np.int64) for b, m, _ in predicted])[seen]
                d["pred"] = pr.tolist()
            if watch:
                self._watch(cid, o, px, label, ok, predicted, uv, now_ns)
            out.append(d)
        return out

    def _watch(self, cid: int, o: Any, px: np.ndarray, label: np.ndarray, ok: np.ndarray, predicted: list,
               uv: np.ndarray | None, now_ns: int) -> None:
        """The residual of each matched blob against the prediction of its own marker; the static leftovers."""
        w = self.watch[cid]
        if o.capture_ns == w.last_capture_ns:
            return
        w.last_capture_ns = int(o.capture_ns)
        if uv is not None:
            rows_of = np.concatenate([np.arange(self.marker_start[b], self.marker_start[b] + len(m))
                                      for b, m, _ in predicted])
            index = np.full(len(self.marker_body) + 1, -1, dtype=np.int64)
            index[rows_of] = np.arange(len(rows_of))
            j = np.flatnonzero(ok)
            k = index[label[j]]
            keep = k >= 0
            d = px[j[keep], :2] - uv[k[keep]]
            d = d[np.isfinite(d).all(axis=1)]
            if len(d):
                rms = math.sqrt(float((d * d).sum()) / len(d))
                w.residual_px = rms if w.residual_px is None else w.residual_px + RESIDUAL_EWMA * (rms - w.residual_px)
        self._watch_static(w, px[label < 0], now_ns)

    def _watch_static(self, w: CameraWatch, left: np.ndarray, now_ns: int) -> None:
        gap_ns = int(STATIC_GAP_S * 1e9)
        for k in [k for k, c in w.cells.items() if now_ns - c.last_ns > gap_ns]:
            del w.cells[k]
        for x, y in left[:, :2]:
            if not (math.isfinite(x) and math.isfinite(y)):
                continue
            k = (int(x // STATIC_CELL_PX), int(y // STATIC_CELL_PX))
            c = w.cells.get(k)
            if c is None:  # a blob jittering across a cell border stays with its cell
                near = STATIC_CELL_PX
                c = next((c for c in w.cells.values() if abs(c.x - x) < near and abs(c.y - y) < near), None)
            if c is not None:
                c.last_ns = now_ns
                c.hits += 1
                c.x += (x - c.x) / c.hits
                c.y += (y - c.y) / c.hits
            elif len(w.cells) < STATIC_MAX_CELLS:
                w.cells[k] = _Cell(float(x), float(y), now_ns, now_ns)
        w.updates += 1

    def static_blobs(self, now_ns: int) -> dict[int, list[dict[str, Any]]]:
        """Per camera: leftover blobs that stayed put for STATIC_BLOB_S or more, with the `ignore`
        rectangle [x0, y0, x1, y1] that would remove them."""
        out: dict[int, list[dict[str, Any]]] = {}
        need_ns = int(STATIC_BLOB_S * 1e9)
        for cid, w in self.watch.items():
            for c in w.cells.values():
                if c.last_ns - c.first_ns >= need_ns:
                    m = STATIC_MASK_MARGIN_PX
                    rect = [int(c.x) - m, int(c.y) - m, int(c.x) + m + 1, int(c.y) + m + 1]
                    out.setdefault(cid, []).append({"x": round(c.x, 1), "y": round(c.y, 1),
                                                    "seconds": round((c.last_ns - c.first_ns) * 1e-9, 1),
                                                    "ignore": rect})
        return out

    # ---------------------------------------------------------------- whole state

    def bodies(self) -> list[dict[str, Any]]:
        pipe = self.source.pipeline
        why = getattr(pipe, "untracked_why", {})
        out = []
        for i, s in enumerate(self.source.last_states or []):
            d: dict[str, Any] = {"name": s.name, "id": s.body_id, "tracked": bool(s.tracked)}
            if s.tracked:
                d.update(p=[_r(v, 5) for v in s.position], q=[_r(v, 6) for v in s.quaternion],
                         n_markers=int(s.n_markers), n_cameras=int(s.n_cameras), residual_mm=_r(s.residual_mm, 3))
            elif i < len(pipe.tracks) and pipe.tracks[i].tracked:  # the filter has it, but no fresh measurement
                d["why"] = ("no measurement within fusion.max_prediction_ms: its cameras' frames are late or "
                            "missing (see the cameras' state and frame age)")
            else:
                d["why"] = why.get(i, "not seen yet")
            out.append(d)
        return out

    def loose_markers(self) -> list[list[float | None]]:
        lp = getattr(self.source.pipeline, "loose_points", None)
        if lp is None:
            return []
        return [[_r(v, 4) for v in p] for p in np.asarray(lp.points).reshape(-1, 3)]

    def state(self, now_ns: int, watch: bool = False, rays: frozenset[int] = frozenset(),
              cameras: bool = True) -> dict[str, Any]:
        """The live message: bodies, loose markers and, with cameras, every camera's blobs and predictions
        (camera_states)."""
        out = {"type": "state", "t_ns": int(now_ns), "bodies": self.bodies(), "markers": self.loose_markers()}
        if cameras:
            out["cameras"] = self.camera_states(now_ns, watch, rays)
        elif watch:
            self.camera_states(now_ns, watch=True)
        return out
