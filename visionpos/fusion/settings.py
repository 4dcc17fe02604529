"""The `fusion:` section of the arena YAML: validated, in SI units (see pipeline.py for what each key does)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from visionpos.config.arena import ArenaConfig, Section
from visionpos.fusion.timealign import MODES, MOTION_COMPENSATED
from visionpos.fusion.tracking import KalmanSettings


@dataclass(frozen=True)
class FusionSettings:
    """Validated `fusion:` section (SI units; see the module docstring)."""

    time_alignment: str = MOTION_COMPENSATED
    window_ns: int = 0
    grid_ns: int = 0
    max_clock_lead_ns: int = 30_000_000
    match_gate_px: float = 12.0
    max_residual_px: float = 2.0
    acquire_ray_distance: float = 0.01
    identify_tolerance: float = 0.008
    min_markers: int = 3
    loose_points: bool = True
    acquire_interval_ns: int = 10_000_000
    min_fusion_interval_ns: int = 2_000_000
    loose_points_interval_ns: int = 50_000_000
    marker_sigma: float = 0.0001
    kalman: KalmanSettings = field(default_factory=KalmanSettings)
    reset_after_ns: int = 60_000_000
    max_prediction_ns: int = 50_000_000
    lost_timeout_ns: int = 150_000_000


def _expand_dotted(d: dict[str, Any]) -> dict[str, Any]:
    """{'kalman.gate_chi2': 20} -> {'kalman': {'gate_chi2': 20}} (nested dicts pass through)."""
    out: dict[str, Any] = {}
    for k, v in d.items():
        parts = str(k).split(".")
        node = out
        for p in parts[:-1]:
            node = node.setdefault(p, {})
        if isinstance(v, dict):
            v = _expand_dotted(v)
            if isinstance(node.get(parts[-1]), dict):
                node[parts[-1]] = _merge(node[parts[-1]], v)
                continue
        node[parts[-1]] = v
    return out


def _merge(base: dict[str, Any], over: dict[str, Any]) -> dict[str, Any]:
    out = dict(base)
    for k, v in over.items():
        if isinstance(v, dict) and isinstance(out.get(k), dict):
            out[k] = _merge(out[k], v)
        else:
            out[k] = v
    return out


def parse_fusion_settings(arena: ArenaConfig, settings: dict[str, Any] | None = None) -> FusionSettings:
    """Read `fusion:` from the arena, overridden by `settings` (nested, dotted or {'fusion': {...}})."""
    base = arena.raw.get("fusion") or {}
    if not isinstance(base, dict):
        arena.section("fusion")  # raises a ConfigError naming the key
    data = _expand_dotted(dict(base))
    source = arena.source
    if settings:
        over = _expand_dotted(dict(settings))
        if isinstance(over.get("fusion"), dict):  # `--set fusion.x=y` style keys
            inner = over.pop("fusion")
            over = _merge(over, inner)
        data = _merge(data, over)
        source = f"{arena.source} (+ overrides)"
    s = Section(data, source, "fusion")
    known = {
        "time_alignment", "window_ms", "naive_grid_hz", "max_clock_lead_ms", "match_gate_px", "max_residual_px",
        "acquire_ray_distance_m", "identify_tolerance_m", "min_markers", "loose_points", "loose_points_interval_ms", "acquire_interval_ms", "min_fusion_interval_ms",
        "kalman",
    }  # fmt: skip
    for k in data:
        if k not in known:
            raise s.error(str(k), f"unknown setting; known keys are {sorted(known)}")
    k = s.sub("kalman")
    kknown = {
        "jerk_psd", "angular_accel_psd", "max_noise_scale", "nis_time_constant_ms", "marker_sigma_m", "gate_chi2",
        "reset_after_ms", "max_prediction_ms", "lost_timeout_ms",
    }  # fmt: skip
    for key in k.data:
        if key not in kknown:
            raise k.error(str(key), f"unknown setting; known keys are {sorted(kknown)}")
    fps = [c.fps for c in arena.cameras] or [100.0]
    window_ms = s.number("window_ms", 0.0, min=0.0, max=1000.0)
    if window_ms == 0.0:
        window_ms = 1.2e3 / min(fps)
    grid_hz = s.number("naive_grid_hz", 0.0, min=0.0, max=10000.0)
    if grid_hz == 0.0:
        grid_hz = max(fps)
    ks = KalmanSettings(
        jerk_psd=k.number("jerk_psd", 0.1, min=1e-12),
        angular_accel_psd=k.number("angular_accel_psd", 1.0, min=1e-12),
        max_noise_scale=k.number("max_noise_scale", 1e4, min=1.0),
        nis_time_constant=k.number("nis_time_constant_ms", 15.0, min=0.1) * 1e-3,
        gate_chi2=k.number("gate_chi2", 40.0, min=1.0),
    )
    lost = k.number("lost_timeout_ms", 150.0, min=1.0)
    return FusionSettings(
        time_alignment=s.string("time_alignment", MOTION_COMPENSATED, choices=MODES),
        window_ns=int(window_ms * 1e6),
        grid_ns=int(1e9 / grid_hz),
        max_clock_lead_ns=int(s.number("max_clock_lead_ms", 30.0, min=0.1) * 1e6),
        match_gate_px=s.number("match_gate_px", 12.0, min=0.1),
        max_residual_px=s.number("max_residual_px", 2.0, min=0.01),
        acquire_ray_distance=s.number("acquire_ray_distance_m", 0.01, min=1e-5),
        identify_tolerance=s.number("identify_tolerance_m", 0.008, min=1e-5),
        min_markers=s.integer("min_markers", 3, min=3),
        loose_points=s.boolean("loose_points", True),
        acquire_interval_ns=int(s.number("acquire_interval_ms", 10.0, min=0.0) * 1e6),
        min_fusion_interval_ns=int(s.number("min_fusion_interval_ms", 2.0, min=0.0) * 1e6),
        loose_points_interval_ns=int(s.number("loose_points_interval_ms", 50.0, min=0.0) * 1e6),
        marker_sigma=k.number("marker_sigma_m", 0.0001, min=1e-7),
        kalman=ks,
        reset_after_ns=int(k.number("reset_after_ms", 60.0, min=0.0) * 1e6),
        max_prediction_ns=int(k.number("max_prediction_ms", 50.0, min=0.0) * 1e6),
        lost_timeout_ns=int(lost * 1e6),
    )
