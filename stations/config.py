"""Station configuration (one YAML file per station / camera), validated at load.

Example (docs/stations.md has the full list):

    station_id: 1
    camera_id: 0
    server: {host: 192.168.1.10, port: 5600}
    key_file: /etc/visionpos/key      # shared HMAC key (default: $VISIONPOS_KEY_FILE, else
                                      # ~/.config/visionpos/key); `insecure: true` runs without one
    source: {kind: picamera2, width: 960, height: 640, fps: 100, exposure_us: 1500, gain: 2.0}
    camera: {kind: pinhole, name: imx219 noir}
    detector: {threshold: auto, max_blobs: 64, min_roundness: 0.3}
    clock: {sync: true}               # false when PTP/chrony disciplines the host clock

Every error names the file, the key and what would be right (ConfigError). The key rules are
the server's (visionpos.config.keys): with neither key_file nor `insecure: true` the default key
file must exist.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from stations.detector import DetectorConfig
from visionpos.config.arena import ConfigError, Section, load_yaml
from visionpos.config.keys import resolve_key
from visionpos.protocol import CAMERA_KINDS, DEFAULT_PORT, MAX_BLOBS_PER_PACKET

SOURCE_KINDS = ("opencv", "picamera2", "video", "images", "sim")


@dataclass(frozen=True)
class SourceConfig:
    """kind: one of SOURCE_KINDS. device: V4L2 index or path, or a GStreamer
    pipeline (opencv). path: video file or image folder. width/height/fps:
    requested mode (0 = source default). exposure_us / gain: manual settings
    (None = leave as is); auto_exposure False turns it off where supported.
    loop: restart files at their end. realtime: pace files/sim at fps.
    scenario: sim arena ('thesis', 'arena8' or a path). timestamp_offset_ms:
    subtracted from read-time stamps (opencv/video/images) to account for the
    mid-exposure-to-read latency."""

    kind: str
    device: str | int = 0
    path: str = ""
    width: int = 0
    height: int = 0
    fps: float = 0.0
    exposure_us: float | None = None
    gain: float | None = None
    auto_exposure: bool = False
    loop: bool = True
    realtime: bool = True
    scenario: str = "thesis"
    seed: int = 0
    timestamp_offset_ms: float = 0.0


@dataclass(frozen=True)
class StationConfig:
    station_id: int
    camera_id: int
    server_host: str
    server_port: int
    source: SourceConfig
    detector: DetectorConfig
    camera_kind: str = "unknown"
    camera_name: str = ""
    key: bytes | None = None  # None only when the config says `insecure: true`
    clock_sync: bool = True
    heartbeat_s: float = 1.0
    link_timeout_s: float = 3.5
    retry_max_s: float = 30.0
    image_min_interval_s: float = 1.0
    mask_path: str = ""
    rois: tuple[tuple[int, int, int, int], ...] = ()
    ignore: tuple[tuple[int, int, int, int], ...] = ()
    background_path: str = ""
    background_frames: int = 0
    source_file: str = "<station>"
    raw: dict[str, Any] = field(default_factory=dict)


def _only(sec: Section, known: set[str]) -> None:
    for k in sec.data:
        if k not in known:
            raise sec.error(str(k), f"unknown key; expected one of {sorted(known)}")


def _rects(sec: Section, key: str) -> tuple[tuple[int, int, int, int], ...]:
    if not sec.has(key):
        return ()
    a = sec.array(key, (None, 4))
    if (a[:, 2] <= a[:, 0]).any() or (a[:, 3] <= a[:, 1]).any() or (a < 0).any():
        raise sec.error(key, "each rectangle is [x0, y0, x1, y1] px with x1 > x0 >= 0 and y1 > y0 >= 0")
    return tuple(tuple(int(v) for v in r) for r in a)


def parse_station(data: dict[str, Any], source: str = "<station>", base_dir: str | Path = ".") -> StationConfig:
    """Validate a station mapping. base_dir resolves relative file paths."""
    top = Section(data, source, "")
    _only(top, {"station_id", "camera_id", "server", "key_file", "insecure", "source", "camera", "detector",
                "clock", "heartbeat_s", "link_timeout_s", "retry_max_s", "image_min_interval_s"})
    base = Path(base_dir)
    srv = top.sub("server")
    _only(srv, {"host", "port"})
    src = top.sub("source")
    _only(src, {f for f in SourceConfig.__dataclass_fields__})
    kind = src.string("kind", choices=SOURCE_KINDS)
    dev: str | int = 0
    if src.has("device"):
        v = src.data["device"]
        if isinstance(v, bool) or not isinstance(v, (int, str)):
            raise src.error("device", f"expected a V4L2 index, a device path or a GStreamer pipeline, got {v!r}")
        dev = v
    path = src.string("path", "")
    if kind in ("video", "images"):
        if not path:
            raise src.error(
                "path", f"required for kind '{kind}' (the {'video file' if kind == 'video' else 'image folder'})"
            )
        p = Path(path) if Path(path).is_absolute() else base / path
        if not p.exists():
            raise src.error("path", f"{p} does not exist")
        path = str(p)
    exposure = src.number("exposure_us", min=1.0) if src.has("exposure_us") else None
    gain = src.number("gain", min=0.0) if src.has("gain") else None
    scfg = SourceConfig(
        kind=kind,
        device=dev,
        path=path,
        width=src.integer("width", 0, min=0, max=65535),
        height=src.integer("height", 0, min=0, max=65535),
        fps=src.number("fps", 0.0, min=0.0, max=10000.0),
        exposure_us=exposure,
        gain=gain,
        auto_exposure=src.boolean("auto_exposure", False),
        loop=src.boolean("loop", True),
        realtime=src.boolean("realtime", True),
        scenario=src.string("scenario", "thesis"),
        seed=src.integer("seed", 0, min=0),
        timestamp_offset_ms=src.number("timestamp_offset_ms", 0.0, min=0.0, max=1000.0),
    )
    det = top.sub("detector")
    _only(det, set(DetectorConfig.__dataclass_fields__) | {"mask", "rois", "ignore", "background", "background_frames"})
    thr: float | None = None
    if det.has("threshold") and det.data["threshold"] not in (None, "auto"):
        thr = det.number("threshold", min=1.0, max=254.0)
    dcfg = DetectorConfig(
        threshold=thr,
        auto_k=det.number("auto_k", 8.0, min=1.0),
        min_contrast=det.number("min_contrast", 20.0, min=1.0, max=250.0),
        auto_every=det.integer("auto_every", 8, min=1),
        min_area=det.integer("min_area", 1, min=1),
        max_area=det.integer("max_area", 5000, min=1),
        min_roundness=det.number("min_roundness", 0.3, min=0.0, max=1.0),
        max_blobs=det.integer("max_blobs", 64, min=1, max=MAX_BLOBS_PER_PACKET),
        pad=det.number("pad", 1.0, min=0.5, max=10.0),
        iterations=det.integer("iterations", 2, min=1, max=10),
        saturated_pixels=det.integer("saturated_pixels", 30, min=0),
    )
    if dcfg.max_area < dcfg.min_area:
        raise det.error("max_area", f"must be >= min_area ({dcfg.min_area})")
    mask_path = det.string("mask", "")
    bg_path = det.string("background", "")
    for key, p in (("mask", mask_path), ("background", bg_path)):
        if p and not (Path(p) if Path(p).is_absolute() else base / p).exists():
            raise det.error(key, f"image file {p} does not exist")
    cam = top.sub("camera")
    _only(cam, {"kind", "name"})
    clock = top.sub("clock")
    _only(clock, {"sync"})
    return StationConfig(
        station_id=top.integer("station_id", min=0, max=65535),
        camera_id=top.integer("camera_id", min=0, max=65535),
        server_host=srv.string("host", "127.0.0.1"),
        server_port=srv.integer("port", DEFAULT_PORT, min=1, max=65535),
        source=scfg,
        detector=dcfg,
        camera_kind=cam.string("kind", "unknown", choices=CAMERA_KINDS),
        camera_name=cam.string("name", ""),
        key=resolve_key(top, base)[0],
        clock_sync=clock.boolean("sync", True),
        heartbeat_s=top.number("heartbeat_s", 1.0, min=0.05, max=60.0),
        link_timeout_s=top.number("link_timeout_s", 3.5, min=0.2, max=600.0),
        retry_max_s=top.number("retry_max_s", 30.0, min=0.1, max=3600.0),
        image_min_interval_s=top.number("image_min_interval_s", 1.0, min=0.1, max=3600.0),
        mask_path=str(base / mask_path) if mask_path and not Path(mask_path).is_absolute() else mask_path,
        rois=_rects(det, "rois"),
        ignore=_rects(det, "ignore"),
        background_path=str(base / bg_path) if bg_path and not Path(bg_path).is_absolute() else bg_path,
        background_frames=det.integer("background_frames", 0, min=0, max=1000),
        source_file=source,
        raw=data,
    )


def load_station(path: str | Path) -> StationConfig:
    """Read and validate a station YAML file."""
    p = Path(path)
    return parse_station(load_yaml(p), str(p), p.parent)


def build_mask(cfg: StationConfig, width: int, height: int) -> np.ndarray | None:
    """ROI mask (H, W) uint8 from the mask image, `rois` (search only there)
    and `ignore` rectangles; None when nothing restricts the search."""
    import cv2

    if not (cfg.mask_path or cfg.rois or cfg.ignore):
        return None
    if cfg.mask_path:
        m = cv2.imread(cfg.mask_path, cv2.IMREAD_GRAYSCALE)
        if m is None:
            raise ConfigError(cfg.source_file, "detector.mask", f"cannot read {cfg.mask_path} as an image")
        if m.shape != (height, width):
            raise ConfigError(cfg.source_file, "detector.mask",
                              f"mask is {m.shape[1]}x{m.shape[0]} px, frames are {width}x{height}")
        mask = np.where(m > 0, 255, 0).astype(np.uint8)
    elif cfg.rois:
        mask = np.zeros((height, width), np.uint8)
    else:
        mask = np.full((height, width), 255, np.uint8)
    for x0, y0, x1, y1 in cfg.rois:
        mask[y0:y1, x0:x1] = 255
    for x0, y0, x1, y1 in cfg.ignore:
        mask[y0:y1, x0:x1] = 0
    return mask


def load_background(cfg: StationConfig, width: int, height: int) -> np.ndarray | None:
    """Static background image (H, W) uint8 from detector.background, or None."""
    import cv2

    if not cfg.background_path:
        return None
    b = cv2.imread(cfg.background_path, cv2.IMREAD_GRAYSCALE)
    if b is None:
        raise ConfigError(cfg.source_file, "detector.background", f"cannot read {cfg.background_path} as an image")
    if b.shape != (height, width):
        raise ConfigError(cfg.source_file, "detector.background",
                          f"background is {b.shape[1]}x{b.shape[0]} px, frames are {width}x{height}")
    return b
