"""The console's health view and GET /api/health: per camera, per body, per vehicle, and warnings in words.

Everything comes from what the server already tracks (`FusionServer.health()`: the ingest's
per-camera snapshots, the pipeline's stats, each sink's stats) plus the console's own watches
(console/view.py: live residual per camera, static blobs). The fields of those dictionaries are
read here and only here (`_get`), defensively: a field another part of visionpos renames or
adds later shows as missing, it never breaks the page.
"""

from __future__ import annotations

import math
from typing import Any

from console.view import ConsoleView

# a camera delivering less than this share of its configured frame rate gets a warning
SLOW_FPS_SHARE = 0.9
# live residual above max(RESIDUAL_RISE x calibration, calibration + RESIDUAL_RISE_MIN_PX) gets a warning
RESIDUAL_RISE = 2.0
RESIDUAL_RISE_MIN_PX = 0.5

# the per-camera counters of frames dropped, with the reason each stands for
DROP_REASONS = {
    "lost": "lost on the network (sequence gaps)",
    "duplicates": "duplicates",
    "reordered": "arrived out of order",
    "replayed": "replayed (older than the last accepted)",
    "clock_jumps_future": "capture time in the future (clock jump)",
    "clock_jumps_stale": "capture time too old (clock jump)",
    "clock_jumps_backwards": "capture time went backwards",
    "before_start": "before the trigger time",
    "unregistered": "camera not registered",
    "wrong_session": "another station or session",
    "wrong_address": "from another address than registered",
    "shed": "shed: queued too long in the server",
    "station_frames_dropped": "dropped by the station itself",
}


def _get(d: Any, key: str, default: Any = None) -> Any:
    """d[key] when d is a dict that has it, else default (fields may come and go)."""
    return d.get(key, default) if isinstance(d, dict) else default


def _num(x: Any) -> float | None:
    if isinstance(x, bool) or not isinstance(x, (int, float)):
        return None
    return float(x) if math.isfinite(x) else None


class HealthView:
    """health(now_ns) -> the JSON of /api/health; keeps the previous counts for rates."""

    def __init__(self, view: ConsoleView):
        self.view = view
        self._prev_ns: int | None = None
        self._prev_tracked: dict[str, int] = {}
        self._prev_sent: dict[str, int] = {}
        self._rates: tuple[dict[str, float], dict[str, float]] = ({}, {})

    def _rates_since(self, now_ns: int, tracked: dict[str, int], sent: dict[str, int]) -> None:
        """Body output rates (tracked ticks/s) and vehicle send rates (msgs/s) since the previous call (>= 0.5 s)."""
        if self._prev_ns is not None and now_ns - self._prev_ns < 400_000_000:
            return
        if self._prev_ns is not None:
            dt = (now_ns - self._prev_ns) * 1e-9
            self._rates = ({k: (v - self._prev_tracked.get(k, 0)) / dt for k, v in tracked.items()},
                           {k: (v - self._prev_sent.get(k, 0)) / dt for k, v in sent.items()})
        self._prev_ns, self._prev_tracked, self._prev_sent = now_ns, dict(tracked), dict(sent)

    def health(self, now_ns: int) -> dict[str, Any]:
        src = self.view.source
        try:
            h = src.health()
        except Exception as e:  # the health page must show even when a part of it fails
            h = {"error": repr(e)}
        cameras = self._cameras(h, now_ns)
        vehicles_raw = _get(_get(_get(h, "sinks", {}), "Bridge", {}), "vehicles", {}) or {}
        tracked_ticks = _get(h, "bodies_tracked_ticks", {}) or {}
        sent = {name: int(_get(v, "sent", 0) or 0) for name, v in vehicles_raw.items()}
        self._rates_since(now_ns, tracked_ticks, sent)
        body_rates, send_rates = self._rates
        bodies = []
        for b in self.view.bodies():
            b = dict(b)
            b["rate_hz"] = round(body_rates.get(b["name"], 0.0), 1)
            bodies.append(b)
        vehicles = []
        for name, v in vehicles_raw.items():
            vehicles.append({
                "name": name, "body": _get(v, "body"), "sysid": _get(v, "sysid"), "endpoint": _get(v, "endpoint"),
                "link_up": bool(_get(v, "link_up", False)), "sent": sent[name],
                "rate_hz": round(send_rates.get(name, 0.0), 1), "rate_configured_hz": _get(v, "rate_hz"),
                "signed": bool(_get(v, "signed", False)), "timesync_answered": _get(v, "timesync_answered"),
                "timesync_rtt_ms": _num(_get(v, "timesync_rtt_ms")),
                "heard_s_ago": _num(_get(v, "autopilot_heard_s_ago")), "last_error": _get(v, "last_error"),
                "latency_ms_p50": _num(_get(v, "latency_capture_ms_p50")),
            })
        server = {k: _get(h, k) for k in ("packets", "frames_accepted", "frames_shed", "malformed", "auth_failed",
                                          "unknown", "pipeline_errors", "late_ticks", "ticks", "insecure")}
        out = {"time_ns": int(now_ns), "cameras": cameras, "bodies": bodies, "vehicles": vehicles, "server": server,
               "drop_reasons": DROP_REASONS}
        if "error" in h:
            out["error"] = h["error"]
        out["warnings"] = warnings(out, self.view.static_blobs(now_ns))
        if _get(h, "camera_monitor"):  # which camera moved, by how much, its corrections (fusion/camera_monitor.py)
            out["camera_monitor"] = h["camera_monitor"]
            out["warnings"] += [c["warning"] for c in h["camera_monitor"]["cameras"].values() if _get(c, "warning")]
        return out

    def _cameras(self, h: dict[str, Any], now_ns: int) -> list[dict[str, Any]]:
        snaps = _get(h, "cameras", {}) or {}
        calib = self.view.scene.get("calibration_rms_px", {})
        out = []
        for cid, cam in self.view.cameras.items():
            c = snaps.get(cid) or snaps.get(str(cid)) or {}
            dropped = {k: int(_get(c, k)) for k in DROP_REASONS if isinstance(_get(c, k), int) and _get(c, k) > 0}
            # configured rate: the station's own (as h-gates' health adds it) or the arena's
            configured = _num(_get(c, "fps_configured")) or _num(_get(c, "fps_nominal")) or float(cam.fps)
            w = self.view.watch[cid]
            out.append({
                "id": cid, "name": cam.name, "state": _get(c, "state", "waiting"),
                "station_id": _get(c, "station_id"), "addr": _get(c, "addr"),
                "fps": _num(_get(c, "fps_measured")) or _num(_get(c, "fps")) or 0.0, "fps_configured": configured,
                "latency_ms": _num(_get(c, "latency_ms")), "clock_offset_ms": _num(_get(c, "clock_offset_ms")),
                "clock_uncertainty_us": _num(_get(c, "clock_uncertainty_us")),
                "loss": _num(_get(c, "loss_recent")), "frames": _get(c, "frames", 0),
                "residual_px": None if w.residual_px is None else round(w.residual_px, 3),
                "residual_calibration_px": calib.get(cam.name), "dropped": dropped,
                "dropping": _get(c, "dropping"), "last_drop_reason": _get(c, "last_drop_reason"),
            })
        return out


def warnings(h: dict[str, Any], static: dict[int, list[dict[str, Any]]]) -> list[str]:
    """What the user must fix, in words, from a health dict as HealthView builds it."""
    out = []
    for c in h["cameras"]:
        label = f"camera {c['id']} ({c['name']})"
        if c["state"] == "streaming" and c["fps_configured"] and c["fps"] < SLOW_FPS_SHARE * c["fps_configured"]:
            out.append(f"{label} delivers {c['fps']:.0f} frames/s, configured {c['fps_configured']:.0f}: the "
                       "station is slower than configured (exposure too long, CPU busy, or a lower camera "
                       "mode); fusion waits for frames that do not come")
        elif c["state"] == "dropping":
            out.append(f"{label}: frames arrive but are refused ({c['dropping']})")
        elif c["state"] in ("gone", "waiting"):
            out.append(f"{label}: no frames ({c['state']}); is its station running and pointed at this server?")
        calib, live = c["residual_calibration_px"], c["residual_px"]
        if calib is not None and live is not None and live > max(RESIDUAL_RISE * calib, calib + RESIDUAL_RISE_MIN_PX):
            out.append(f"{label}: reprojection residual {live:.2f} px, {calib:.2f} px at calibration: the camera "
                       "may have moved; recalibrate (`visionpos calibrate wand`)")
        for s in static.get(c["id"], []):
            out.append(f"{label}: a bright blob at ({s['x']:.0f}, {s['y']:.0f}) px has stayed put for "
                       f"{s['seconds']:.0f} s and matches no body; it looks like a reflection. Cover it, or add "
                       f"`ignore: [{s['ignore']}]` to the station's detector section")
    for b in h["bodies"]:
        if not b["tracked"]:
            out.append(f"body {b['name']} is not tracked: {b.get('why', 'unknown')}")
    for v in h["vehicles"]:
        if not v["link_up"]:
            out.append(f"vehicle {v['name']} ({v['endpoint']}): link down, nothing heard from the autopilot"
                       + (f" ({v['last_error']})" if v["last_error"] else "") + "; check the endpoint and the cable "
                       "or radio")
    return out
