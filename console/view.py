"""What the console shows, read from a running fusion server (or a replay): the scene once, the live state per update.

The source is any object with the FusionServer's observable parts (read only): `arena`,
`pipeline.snapshot()` (a visionpos.fusion.snapshot.FusionSnapshot: each camera's newest frame as
fused, which body the filters hold and why one is not tracked, the loose markers), `last_states`
(the newest tick's BodyStates), `health()` and `clock()`. A replay session (console/replay.py) and
`visionpos record`'s stand-in (app/console.py RecordSource) offer the same.

Nothing here changes the source: it reads each camera's newest observation (its blobs, their
labels, and where fusion predicted the tracked markers when it matched the frame), once per
console update (30 Hz), never per packet.
"""

from __future__ import annotations

import hashlib
import json
import math
from dataclasses import dataclass, field
from math import isfinite
from typing import Any

import numpy as np

from visionpos.fusion.layout import ADAPT_NIS_P, ADAPT_NIS_R
from visionpos.fusion.snapshot import CameraFrame, FusionSnapshot

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


def _rounded(values: list[float], nd: int) -> list[float | None]:
    """_r over a list: one finiteness check for the whole list (the usual case), per value only when it fails."""
    if isfinite(sum(values)):
        return [round(v, nd) for v in values]
    return [_r(v, nd) for v in values]


def _age_ms(now_ns: int, capture_ns: int | None) -> float | None:
    return None if capture_ns is None else _r((now_ns - capture_ns) * 1e-6, 1)


@dataclass(frozen=True)
class _CameraView:
    """One camera's built view: what it was built from (key) and its blobs, pred and rays (data)."""

    key: tuple
    data: dict[str, Any]


_EMPTY_VIEW = _CameraView((), {"blobs": [], "pred": []})


def scene(arena: Any, name: str | None = None, mode: str = "live") -> dict[str, Any]:
    """The static part: each camera's intrinsics and pose (camera->world), each body's markers, the
    calibration's residuals, what the header names (name: a replay's file; default the arena's source) and the
    mode ("live", or "replay": the page leaves out what a replay cannot do). Sent once per client."""
    cams = []
    stations = arena.camera_stations()
    for c in arena.cameras:
        m = c.model
        R_c2w = np.asarray(c.R).T
        centre = -R_c2w @ np.asarray(c.t)
        cams.append({
            "id": c.id, "name": c.name, "width": m.width, "height": m.height, "fx": m.fx, "fy": m.fy,
            "cx": m.cx, "cy": m.cy, "fps": float(c.fps), "position": [round(float(v), 5) for v in centre],
            "R_c2w": [[round(float(v), 6) for v in row] for row in R_c2w], "station": stations[c.id],
        })
    bodies = [{"name": b.name, "id": b.id, "markers": [[round(float(v), 5) for v in p] for p in b.markers]}
              for b in arena.bodies]
    return {"type": "scene", "source": name or arena.source, "mode": mode, "cameras": cams, "bodies": bodies,
            "calibration_rms_px": calibration_residuals(arena), "scene_id": scene_id(cams, bodies),
            "volume": capture_volume(arena)}


def capture_volume(arena: Any) -> dict[str, list[float]] | None:
    """The planner's flight volume (`plan.volume`, analysis/planner.py) as {"min_m", "max_m"} (world, m), drawn
    as a box in the 3D view; None when the arena has none."""
    if not arena.given("plan"):
        return None
    from visionpos.analysis.planner import parse_plan

    vol = parse_plan(arena).volume
    if vol is None:
        return None
    return {"min_m": [round(float(v), 4) for v in vol.lo], "max_m": [round(float(v), 4) for v in vol.hi]}


def scene_id(cameras: list[dict[str, Any]], bodies: list[dict[str, Any]]) -> str:
    """A short hash of the cameras (ids, names, intrinsics, poses) and bodies: a page that reconnects to a scene
    with another id (the server restarted into another arena) builds its views again."""
    text = json.dumps([cameras, bodies], sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def calibration_residuals(arena: Any) -> dict[str, float]:
    """Camera name -> reprojection RMS (px) of the wand calibration, where the arena carries its report."""
    ext = arena.section("calibration").data.get("extrinsics")  # the report `calibrate extrinsics` wrote
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
        self.scene = scene(arena, getattr(source, "source_name", None), getattr(source, "console_mode", "live"))
        self.cameras = {c.id: c for c in arena.cameras}
        sizes = [len(b.markers) for b in arena.bodies]
        self.marker_body = np.repeat(np.arange(len(sizes)), sizes).astype(np.int64)
        self.watch = {c.id: CameraWatch() for c in arena.cameras}
        self._body_of_label_list = self.marker_body.tolist()
        self._built: dict[int, _CameraView] = {}
        self.builds = {c.id: 0 for c in arena.cameras}  # camera views built, per camera (the rest were reused)

    # ---------------------------------------------------------------- per camera

    def _views(self, now_ns: int, watch: bool, rays: frozenset[int], snap: FusionSnapshot | None = None
               ) -> list[tuple[int, int | None, _CameraView]]:
        """(camera, capture_ns or None, its view) per camera, from snap (the pipeline's snapshot; None: take one).
        A camera's view is built only when something it shows changed since its last build (its frame, the
        frame's labels, its rays) or a watch wants a frame it has not seen; otherwise the last one is reused (a
        camera slower than the updates, a stalled one, a paused replay cost nothing)."""
        frames = (snap if snap is not None else self.source.pipeline.snapshot()).cameras
        out: list[tuple[int, int | None, _CameraView]] = []
        build: list[tuple[int, CameraFrame, np.ndarray, tuple]] = []
        for cid in self.cameras:
            o = frames.get(cid)
            px = None if o is None else o.px
            if o is None or len(px) != len(o.label):
                out.append((cid, None, _EMPTY_VIEW))
                continue
            t = int(o.capture_ns)
            key = (t, id(o.label), id(px), np.asarray(o.label).tobytes(), cid in rays)
            old = self._built.get(cid)
            if old is None or old.key != key or (watch and self.watch[cid].last_capture_ns != t):
                build.append((cid, o, px, key))
                out.append((cid, t, _EMPTY_VIEW))  # filled below
            else:
                out.append((cid, t, old))
        if build:
            built = self._build(build, now_ns, watch, rays)
            out = [(cid, t, built.get(cid, v)) for cid, t, v in out]
        return out

    def _build(self, todo: list[tuple[int, CameraFrame, np.ndarray, tuple]], now_ns: int, watch: bool,
               rays: frozenset[int]) -> dict[int, _CameraView]:
        """The views of the cameras in todo. The predicted markers are fusion's own (CameraFrame.pred_px: where
        the filters expected the markers when the frame was matched), so nothing is predicted or projected here.
        A frame has a few dozen blobs at most: plain Python over their lists costs less than the fixed price of
        the numpy calls it replaces (the numpy version of this was slower)."""
        n_markers = len(self.marker_body)
        body_of = self._body_of_label_list
        out: dict[int, _CameraView] = {}
        for cid, o, px, key in todo:
            label = o.label.tolist() if isinstance(o.label, np.ndarray) else list(o.label)
            blobs = [[round(u * 10.0), round(v * 10.0), body_of[lb] if 0 <= lb < n_markers else -1]
                     for (u, v, *_), lb in zip(px.tolist(), label) if isfinite(u) and isfinite(v)]
            pred_px, pred_rows = o.pred_px, o.pred_rows
            pred: list[tuple[float, float, int]] = []
            if pred_px is not None and pred_rows is not None:
                pred = [(u, v, r) for (u, v), r in zip(pred_px.tolist(), pred_rows.tolist())
                        if isfinite(u) and isfinite(v) and 0 <= r < n_markers]
            d: dict[str, Any] = {"blobs": blobs,
                                 "pred": [[round(u * 10.0), round(v * 10.0), body_of[r]] for u, v, r in pred]}
            if cid in rays:
                xn = np.asarray(o.xn, dtype=float).reshape(-1, 2)
                good = np.isfinite(xn).all(axis=1)
                d["rays"] = np.rint(xn[good] * 1e5).astype(np.int64).tolist()
            out[cid] = self._built[cid] = _CameraView(key, d)
            self.builds[cid] += 1
            if watch:
                self._watch(cid, o, px, label, pred, now_ns)
        return out

    def camera_states(self, now_ns: int, watch: bool = False, rays: frozenset[int] = frozenset(),
                      snap: FusionSnapshot | None = None) -> list[dict[str, Any]]:
        """Per camera: blobs [u, v, body (-1 = left over)] and the filter's predicted markers [u, v, body] at
        the frame's capture time, pixels in tenths (integers encode fastest), the frame's age; for the
        cameras in `rays` also each blob's undistorted coordinates [x, y] x 1e5 (its ray). watch: also
        update the residual and static-blob watches (twice a second is plenty)."""
        return [{"id": cid, **v.data, "age_ms": _age_ms(now_ns, t)}
                for cid, t, v in self._views(now_ns, watch, rays, snap)]

    def _watch(self, cid: int, o: CameraFrame, px: np.ndarray, label: list[int], pred: list[tuple[float, float, int]],
               now_ns: int) -> None:
        """The residual of each matched blob against fusion's prediction of its own marker (pred: [(u, v, marker
        row)]); the static leftovers."""
        w = self.watch[cid]
        if o.capture_ns == w.last_capture_ns:
            return
        w.last_capture_ns = int(o.capture_ns)
        where = {r: (u, v) for u, v, r in pred}
        sq, n = 0.0, 0
        for (u, v, *_), lb in zip(px.tolist(), label):
            p = where.get(lb)
            if p is not None:
                du, dv = u - p[0], v - p[1]
                if isfinite(du) and isfinite(dv):
                    sq += du * du + dv * dv
                    n += 1
        if n:
            rms = math.sqrt(sq / n)
            w.residual_px = rms if w.residual_px is None else w.residual_px + RESIDUAL_EWMA * (rms - w.residual_px)
        self._watch_static(w, px[np.asarray(label) < 0], now_ns)

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

    def bodies(self, snap: FusionSnapshot | None = None) -> list[dict[str, Any]]:
        """Per body: name, id, tracked and its pose, or why it is not tracked; snap: the pipeline's snapshot (None:
        take one)."""
        snap = snap if snap is not None else self.source.pipeline.snapshot()
        out = []
        for i, s in enumerate(self.source.last_states or []):
            d: dict[str, Any] = {"name": s.name, "id": s.body_id, "tracked": bool(s.tracked)}
            if s.tracked:
                d.update(p=_rounded(np.asarray(s.position).tolist(), 5),
                         q=_rounded(np.asarray(s.quaternion).tolist(), 6),
                         n_markers=int(s.n_markers), n_cameras=int(s.n_cameras), residual_mm=_r(s.residual_mm, 3),
                         nis=self._nis(i))
            elif i < len(snap.filter_tracked) and snap.filter_tracked[i]:  # the filter has it, no fresh measurement
                d["why"] = ("no measurement within fusion.max_prediction_ms: its cameras' frames are late or "
                            "missing (see the cameras' state and frame age)")
            else:
                d["why"] = snap.untracked_why.get(i, "not seen yet")
            out.append(d)
        return out

    def _nis(self, i: int) -> list[float | None] | None:
        """Body i's filter consistency: its normalised innovation squared averages [position, rotation] (about 1
        when the filter's covariance is right), from the filter bank's adaptive-noise row; None where the source
        has no filter bank (`record`)."""
        try:
            row = self.source.pipeline.bank.adapt[i]
            return [_r(row[ADAPT_NIS_P], 3), _r(row[ADAPT_NIS_R], 3)]
        except (AttributeError, IndexError, TypeError):
            return None

    def loose_markers(self, snap: FusionSnapshot | None = None) -> list[list[float | None]]:
        lp = (snap if snap is not None else self.source.pipeline.snapshot()).loose_points
        if lp is None:
            return []
        return [_rounded(p, 4) for p in np.asarray(lp.points).reshape(-1, 3).tolist()]

    def state(self, now_ns: int, watch: bool = False, rays: frozenset[int] = frozenset(),
              cameras: bool = True) -> dict[str, Any]:
        """The live message: bodies, loose markers and, with cameras, every camera's blobs and predictions
        (camera_states)."""
        snap = self.source.pipeline.snapshot()  # one per update: its parts below read the same frames
        out = {"type": "state", "t_ns": int(now_ns), "bodies": self.bodies(snap), "markers": self.loose_markers(snap)}
        if cameras:
            out["cameras"] = self.camera_states(now_ns, watch, rays, snap)
        elif watch:
            self._views(now_ns, True, frozenset(), snap)
        return out

    def state_json(self, now_ns: int, watch: bool = False, rays: frozenset[int] = frozenset(),
                   cameras: bool = True, extra: dict[str, Any] | None = None) -> str:
        """state with `extra`'s members, as JSON text (one encoder call for the whole message)."""
        out = self.state(now_ns, watch, rays, cameras)
        out.update(extra or {})
        return json.dumps(out)
