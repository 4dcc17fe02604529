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

import numpy as np

from console.view import ConsoleView

# a camera delivering less than this share of its configured frame rate gets a warning; any configured rate (a
# camera's frames/s, a body's ticks/s, a vehicle's poses/s) met by less than RATE_SHARE turns its row amber
SLOW_FPS_SHARE = 0.9
RATE_SHARE = 0.9
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


def searched_share(mask: dict[str, Any] | None, width: int, height: int) -> float | None:
    """Share (0..1) of a camera's width x height image its station searches for blobs, from the station's `rois`
    (none: the whole image) less its `ignore` rectangles [x0, y0, x1, y1] (px), on a 4 px grid; None without a
    mask (console.stations names no file for it). A station's `mask` image is not read here."""
    if not mask:
        return None
    step = 4
    nx, ny = max(1, -(-width // step)), max(1, -(-height // step))
    rois = mask.get("rois") or []
    searched = np.zeros((ny, nx), bool) if rois else np.ones((ny, nx), bool)

    def cells(r: list[int]) -> tuple[slice, slice]:
        x0, y0, x1, y1 = (int(v) for v in r)
        return slice(max(0, y0 // step), max(0, -(-y1 // step))), slice(max(0, x0 // step), max(0, -(-x1 // step)))

    for r in rois:
        searched[cells(r)] = True
    for r in mask.get("ignore") or []:
        searched[cells(r)] = False
    return float(searched.mean())


def _rate(rates: dict[str, float] | None, key: str) -> float | None:
    """A count's rate per second, rounded; None while not measured yet."""
    return None if rates is None else round(rates.get(key, 0.0), 1)


def _level(bad: list[str], warn: list[str]) -> tuple[str, list[str]]:
    """A row's level ("bad": stops a flight or shows nothing true, "warn": a configured rate not met, "ok") and its
    alerts in words, the bad ones first."""
    return ("bad" if bad else "warn" if warn else "ok"), bad + warn


def _below(rate: float | None, configured: float | None) -> bool:
    return rate is not None and bool(configured) and rate < RATE_SHARE * configured


class HealthView:
    """health(now_ns) -> the JSON of /api/health; keeps the previous counts for rates."""

    def __init__(self, view: ConsoleView):
        self.view = view
        self._prev_ns: int | None = None
        self._prev: dict[str, float] = {}
        self._rates: dict[str, float] | None = None  # None until two samples: no rate is shown as 0

    def _rates_since(self, now_ns: int, counts: dict[str, float]) -> dict[str, float] | None:
        """Per second since the previous sample (taken at most every 0.4 s) of each count (body tracked ticks,
        vehicle messages sent, frames shed, late ticks); a count seen for the first time starts from 0; None before
        the second sample (a rate not measured yet is no reason for an alert)."""
        if self._prev_ns is not None and now_ns - self._prev_ns < 400_000_000:
            return self._rates
        if self._prev_ns is not None:
            dt = (now_ns - self._prev_ns) * 1e-9
            self._rates = {k: (v - self._prev.get(k, 0)) / dt for k, v in counts.items()}
        self._prev_ns, self._prev = now_ns, dict(counts)
        return self._rates

    def health(self, now_ns: int) -> dict[str, Any]:
        src = self.view.source
        try:
            h = src.health()
        except Exception as e:  # the health page must show even when a part of it fails
            h = {"error": repr(e)}
        vehicles_raw = _get(_get(_get(h, "sinks", {}), "Bridge", {}), "vehicles", {}) or {}
        snaps = _get(h, "cameras", {}) or {}
        counts: dict[str, float] = {f"body:{k}": v for k, v in (_get(h, "bodies_tracked_ticks", {}) or {}).items()}
        counts.update({f"sent:{name}": int(_get(v, "sent", 0) or 0) for name, v in vehicles_raw.items()})
        for cid in self.view.cameras:
            counts[f"shed:{cid}"] = int(_get(snaps.get(cid) or snaps.get(str(cid)), "shed", 0) or 0)
        counts["frames_shed"] = int(_get(h, "frames_shed", 0) or 0)
        counts["late_ticks"] = int(_get(h, "late_ticks", 0) or 0)
        rates = self._rates_since(now_ns, counts)
        output_hz = _num(getattr(getattr(src, "settings", None), "output_rate_hz", None))  # the server's ticks/s
        out = {"time_ns": int(now_ns),
               "vehicles": [self._vehicle(name, v, rates) for name, v in vehicles_raw.items()],
               "bodies": self._bodies(rates, output_hz), "cameras": self._cameras(h, now_ns, rates),
               "server": self._server(h, rates, output_hz), "drop_reasons": DROP_REASONS}
        if "error" in h:
            out["error"] = h["error"]
        static = self.view.static_blobs(now_ns)
        out["reflections"] = [{"camera": cid, "ignore": [s["ignore"] for s in found]} for cid, found in static.items()]
        out["warnings"] = warnings(out, static)
        if _get(h, "camera_monitor"):  # which camera moved, by how much, its corrections (fusion/camera_monitor.py)
            out["camera_monitor"] = h["camera_monitor"]
            out["warnings"] += [c["warning"] for c in h["camera_monitor"]["cameras"].values() if _get(c, "warning")]
        return out

    def _vehicle(self, name: str, v: dict[str, Any], rates: dict[str, float] | None) -> dict[str, Any]:
        sent = int(_get(v, "sent", 0) or 0)
        rate, configured = _rate(rates, f"sent:{name}"), _num(_get(v, "rate_hz"))
        ekf, ekf_detail = _get(v, "ekf"), _get(v, "ekf_detail")
        out = {"name": name, "body": _get(v, "body"), "sysid": _get(v, "sysid"), "endpoint": _get(v, "endpoint"),
               "link_up": bool(_get(v, "link_up", False)), "sent": sent, "rate_hz": rate,
               "rate_configured_hz": configured, "signed": bool(_get(v, "signed", False)),
               "timesync_answered": _get(v, "timesync_answered"), "timesync_rtt_ms": _num(_get(v, "timesync_rtt_ms")),
               "heard_s_ago": _num(_get(v, "autopilot_heard_s_ago")), "last_error": _get(v, "last_error"),
               "latency_ms_p50": _num(_get(v, "latency_capture_ms_p50")), "autopilot": _get(v, "autopilot"),
               "ekf": ekf, "ekf_detail": ekf_detail, "delay_ms": _num(_get(v, "delay_ms")),
               "delay_detail": _get(v, "delay_detail")}
        bad, warn = [], []
        bad += [f"identity: {_get(v, 'identity_reason')}"] if _get(v, "identity_binding") not in (None, "bound") else []
        if not out["link_up"]:
            bad.append("link down: nothing heard from the autopilot")
        if rate == 0:
            bad.append(f"0 poses/s reach it (configured {configured or 0:.0f})")
        elif _below(rate, configured):
            warn.append(f"{rate:.0f} poses/s, configured {configured:.0f}")
        if ekf in ("not using vision", "rejecting vision"):
            bad.append(f"EKF {ekf}: {ekf_detail}")
        elif ekf == "unknown" or (ekf is None and out["link_up"]):
            warn.append(f"EKF state unknown: {ekf_detail or 'the bridge reports none'}")
        out["level"], out["alerts"] = _level(bad, warn)
        return out

    def _bodies(self, rates: dict[str, float] | None, output_hz: float | None) -> list[dict[str, Any]]:
        out = []
        for b in self.view.bodies():
            b = dict(b)
            b["rate_hz"] = _rate(rates, f"body:{b['name']}")
            b["rate_configured_hz"] = output_hz
            bad, warn = [], []
            if not b["tracked"]:
                bad.append(f"not tracked: {b.get('why', 'unknown')}")
            elif _below(b["rate_hz"], output_hz):
                warn.append(f"tracked in {b['rate_hz']:.0f} of {output_hz:.0f} ticks/s")
            b["level"], b["alerts"] = _level(bad, warn)
            out.append(b)
        return out

    def _server(self, h: dict[str, Any], rates: dict[str, float] | None, output_hz: float | None) -> dict[str, Any]:
        out = {k: _get(h, k) for k in ("packets", "frames_accepted", "frames_shed", "malformed", "auth_failed",
                                       "unknown", "pipeline_errors", "late_ticks", "ticks", "insecure")}
        out.update(output_rate_hz=output_hz, shed_per_s=_rate(rates, "frames_shed"),
                   late_ticks_per_s=_rate(rates, "late_ticks"))
        warn = []
        if (out["shed_per_s"] or 0) > 0:
            warn.append(f"sheds {out['shed_per_s']:.0f} frames/s: fusion cannot keep up (CPU busy)")
        if (out["late_ticks_per_s"] or 0) > 0:
            warn.append(f"{out['late_ticks_per_s']:.0f} late ticks/s: output ticks run behind")
        out["level"], out["alerts"] = _level([], warn)
        return out

    def _cameras(self, h: dict[str, Any], now_ns: int, rates: dict[str, float] | None) -> list[dict[str, Any]]:
        snaps = _get(h, "cameras", {}) or {}
        calib = self.view.scene.get("calibration_rms_px", {})
        scene_cams = {c["id"]: c for c in self.view.scene["cameras"]}
        out = []
        for cid, cam in self.view.cameras.items():
            c = snaps.get(cid) or snaps.get(str(cid)) or {}
            dropped = {k: int(_get(c, k)) for k in DROP_REASONS if isinstance(_get(c, k), int) and _get(c, k) > 0}
            # configured rate: the station's own (as h-gates' health adds it) or the arena's
            configured = _num(_get(c, "fps_configured")) or _num(_get(c, "fps_nominal")) or float(cam.fps)
            w = self.view.watch[cid]
            sc = scene_cams.get(cid, {})
            row = {
                "id": cid, "name": cam.name, "state": _get(c, "state", "waiting"),
                "station_id": _get(c, "station_id"), "addr": _get(c, "addr"),
                "fps": _num(_get(c, "fps_measured")) or _num(_get(c, "fps")) or 0.0, "fps_configured": configured,
                "latency_ms": _num(_get(c, "latency_ms")), "clock_offset_ms": _num(_get(c, "clock_offset_ms")),
                "clock_uncertainty_us": _num(_get(c, "clock_uncertainty_us")),
                "loss": _num(_get(c, "loss_recent")), "frames": _get(c, "frames", 0),
                "last_seen_s_ago": _num(_get(c, "last_seen_s_ago")),
                "residual_px": None if w.residual_px is None else round(w.residual_px, 3),
                "residual_calibration_px": calib.get(cam.name), "dropped": dropped,
                "dropping": _get(c, "dropping"), "last_drop_reason": _get(c, "last_drop_reason"),
                "shed_per_s": _rate(rates, f"shed:{cid}"),
                "searched_share": searched_share(sc.get("mask"), cam.model.width, cam.model.height),
            }
            row["level"], row["alerts"] = _camera_level(row)
            out.append(row)
        return out


def _camera_level(c: dict[str, Any]) -> tuple[str, list[str]]:
    bad, warn = [], []
    if c["state"] in ("gone", "waiting"):
        bad.append(f"no frames ({c['state']})")
    elif c["state"] == "dropping":
        bad.append(f"frames refused ({c['dropping']})")
    if c["searched_share"] == 0.0:
        bad.append("masked over its whole image: its station searches no pixel")
    if c["state"] == "streaming" and _below(c["fps"], c["fps_configured"]):
        warn.append(f"{c['fps']:.0f} frames/s, configured {c['fps_configured']:.0f}")
    if (c["shed_per_s"] or 0) > 0:
        warn.append(f"{c['shed_per_s']:.0f} frames/s shed: fusion cannot keep up")
    calib, live = c["residual_calibration_px"], c["residual_px"]
    if calib is not None and live is not None and live > max(RESIDUAL_RISE * calib, calib + RESIDUAL_RISE_MIN_PX):
        warn.append(f"residual {live:.2f} px, {calib:.2f} px at calibration")
    return _level(bad, warn)


def warnings(h: dict[str, Any], static: dict[int, list[dict[str, Any]]]) -> list[str]:
    """What the user must fix, in words, from a health dict as HealthView builds it: what stops a flight first
    (vehicles, then bodies, then cameras and the server), the static blobs folded to one line per camera."""
    out = []
    for v in h["vehicles"]:
        if not v["link_up"]:
            out.append(f"vehicle {v['name']} ({v['endpoint']}): link down, nothing heard from the autopilot"
                       + (f" ({v['last_error']})" if v["last_error"] else "") + "; check the endpoint and the cable "
                       "or radio")
        elif v["rate_hz"] == 0:
            out.append(f"vehicle {v['name']}: no pose reaches it (0 of {v['rate_configured_hz'] or 0:.0f} poses/s): "
                       "is its body tracked?")
        if v["ekf"] in ("not using vision", "rejecting vision"):
            out.append(f"vehicle {v['name']}: the autopilot's EKF is {v['ekf']}: {v['ekf_detail']}")
    for b in h["bodies"]:
        if not b["tracked"]:
            out.append(f"body {b['name']} is not tracked: {b.get('why', 'unknown')}")
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
        if c["searched_share"] == 0.0:
            out.append(f"{label}: masked over its whole image (console.stations: its rois and ignore rectangles "
                       "leave no pixel to search); draw a smaller mask")
        calib, live = c["residual_calibration_px"], c["residual_px"]
        if calib is not None and live is not None and live > max(RESIDUAL_RISE * calib, calib + RESIDUAL_RISE_MIN_PX):
            out.append(f"{label}: reprojection residual {live:.2f} px, {calib:.2f} px at calibration: the camera "
                       "may have moved; recalibrate (`visionpos calibrate wand`)")
        found = static.get(c["id"], [])
        if found:
            where = ", ".join(f"({s['x']:.0f}, {s['y']:.0f})" for s in found)
            rects = ", ".join(str(s["ignore"]) for s in found)
            out.append(f"{label}: {len(found)} bright blob{'s' if len(found) > 1 else ''} at {where} px stayed put "
                       f"for {min(s['seconds'] for s in found):.0f} s or more and match no body: reflections? Cover "
                       f"them, or mask them (\"mask these\", or `ignore: [{rects}]` in the station's detector "
                       "section)")
    for a in h["server"]["alerts"]:
        out.append(f"server: {a}")
    return out
