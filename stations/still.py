"""Still images and mask updates on a station, on the server's request (docs/protocol.md, "Still images").

Pure helpers shared by the station agent (stations/agent.py) and the demo's simulated stations
(visionpos/app/demo.py); nothing here runs per frame, only when the server asks:

- `StillLimiter`: at most one image per `image_min_interval_s`; a request inside the interval is
  answered by nothing and counted.
- `background_level`: the frame's background, the 99th percentile of the grey levels outside the
  detected blobs (0..255), the number docs/stations.md asks to bring below about 20 with the exposure.
- `encode_still` / `image_chunks`: the frame as a JPEG (downscaled to the requested width) cut into
  IMAGE_CHUNK datagrams.
- `check_rects` / `save_mask`: a MASK_UPDATE's rectangles checked against the image size, and
  written to the station's YAML file (detector.ignore / detector.rois; the rest of the file, comments
  included, kept when the edit can be made in place; the write is atomic).
"""

from __future__ import annotations

import math
import os
import re
import tempfile
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from visionpos import protocol as P

BLOB_MARGIN_PX = 3.0  # pixels around a blob's disc that still count as the blob (its halo)
BACKGROUND_PERCENTILE = 99.0
Rect = tuple[int, int, int, int]


class StillLimiter:
    """At most one still image per min_interval_s; refused requests are counted (no answer is sent)."""

    def __init__(self, min_interval_s: float):
        self.min_interval_ns = int(min_interval_s * 1e9)
        self._last_ns: int | None = None
        self.sent = 0
        self.refused = 0

    def allow(self, now_ns: int) -> bool:
        if self._last_ns is not None and now_ns - self._last_ns < self.min_interval_ns:
            self.refused += 1
            return False
        self._last_ns = now_ns
        self.sent += 1
        return True


def blob_mask(shape: tuple[int, int], blobs: np.ndarray) -> np.ndarray:
    """(H, W) bool, True on the pixels of the blobs (N, >= 3: x, y, area) and BLOB_MARGIN_PX around them."""
    import cv2

    m = np.zeros(shape, np.uint8)
    for x, y, area in np.asarray(blobs, dtype=float).reshape(-1, 4)[:, :3]:
        r = math.sqrt(max(area, 1.0) / math.pi) + BLOB_MARGIN_PX
        cv2.circle(m, (int(round(x)), int(round(y))), int(math.ceil(r)), 255, -1)
    return m > 0


def background_level(image: np.ndarray, blobs: np.ndarray) -> float:
    """The 99th percentile (numpy's linear rule) of the grey levels (0..255) of image (H, W) uint8 outside
    blobs (N, 4), from the histogram: no sort of the whole frame."""
    outside = image[~blob_mask(image.shape, blobs)] if len(blobs) else image.ravel()
    if outside.size == 0:
        return 0.0
    cdf = np.cumsum(np.bincount(outside, minlength=256))
    rank = BACKGROUND_PERCENTILE / 100.0 * (outside.size - 1)
    lo = int(rank)
    v_lo, v_hi = np.searchsorted(cdf, [lo, min(lo + 1, outside.size - 1)], side="right")
    return float(v_lo + (rank - lo) * (v_hi - v_lo))


def encode_still(image: np.ndarray, max_width: int, quality: int) -> tuple[bytes, int, int]:
    """(H, W) uint8 -> (JPEG, width, height), downscaled to at most max_width px wide (0 = as is); quality
    and then size are lowered until the JPEG fits P.MAX_IMAGE_BYTES."""
    import cv2

    img = image
    if max_width and image.shape[1] > max_width:
        h = max(1, round(image.shape[0] * max_width / image.shape[1]))
        img = cv2.resize(image, (max_width, h), interpolation=cv2.INTER_AREA)
    q = int(quality)
    while True:
        ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, q])
        if not ok:
            raise ValueError("cv2.imencode could not make a JPEG of the frame")
        if buf.size <= P.MAX_IMAGE_BYTES:
            return buf.tobytes(), img.shape[1], img.shape[0]
        if q > 30:
            q -= 20
        else:
            img = cv2.resize(img, (max(1, img.shape[1] // 2), max(1, img.shape[0] // 2)),
                             interpolation=cv2.INTER_AREA)


def image_chunks(req: P.ImageRequest, jpeg: bytes, capture_ns: int, width: int, height: int,
                 background: float) -> list[P.ImageChunk]:
    """The IMAGE_CHUNK messages answering req with jpeg."""
    n = P.IMAGE_CHUNK_BYTES
    count = -(-len(jpeg) // n)
    bg = float(min(max(background, 0.0), 255.0))
    return [P.ImageChunk(req.station_id, req.camera_id, req.session, req.request_id, i, count, len(jpeg),
                         int(capture_ns), width, height, bg, jpeg[i * n:(i + 1) * n]) for i in range(count)]


def check_rects(rects: Sequence[Rect], width: int, height: int) -> str | None:
    """Why rectangles [x0, y0, x1, y1] do not fit a width x height image (None: they do)."""
    for x0, y0, x1, y1 in rects:
        if not (0 <= x0 < x1 <= width and 0 <= y0 < y1 <= height):
            return f"rectangle {[x0, y0, x1, y1]} is not inside the {width}x{height} image"
    return None


def _flow(rects: Sequence[Rect]) -> str:
    return "[" + ", ".join("[" + ", ".join(str(int(v)) for v in r) + "]" for r in rects) + "]"


_TOP_DETECTOR = re.compile(r"^detector:\s*(#.*)?$")


def _edit_in_place(text: str, values: dict[str, Sequence[Rect]]) -> str | None:
    """text with detector.<key> lines replaced (or added) as flow lists; None if the file's shape is one this
    line editor does not handle (then the caller rewrites the whole mapping)."""
    lines = text.splitlines(keepends=True)
    if lines and not lines[-1].endswith("\n"):
        lines[-1] += "\n"
    start = next((i for i, ln in enumerate(lines) if _TOP_DETECTOR.match(ln.rstrip("\n"))), None)
    if start is None:
        if any(ln.startswith("detector:") for ln in lines):
            return None  # `detector: {...}` flow style
        return "".join(lines) + "detector:\n" + "".join(f"  {k}: {_flow(v)}\n" for k, v in values.items())
    end = start + 1
    indent = None
    while end < len(lines):
        ln = lines[end]
        if ln.strip() and not ln.startswith((" ", "\t", "#")):
            break
        if indent is None and ln.strip() and not ln.lstrip().startswith("#"):
            indent = ln[: len(ln) - len(ln.lstrip())]
        end += 1
    indent = indent or "  "
    for key, rects in values.items():
        new = f"{indent}{key}: {_flow(rects)}\n"
        at = next((i for i in range(start + 1, end) if lines[i].startswith(f"{indent}{key}:")), None)
        if at is None:
            last = max([i for i in range(start + 1, end) if lines[i].strip()
                        and not lines[i].lstrip().startswith("#")] or [start])
            lines.insert(last + 1, new)
            end += 1
            continue
        stop = at + 1
        while stop < end:  # the old value's continuation lines (a block sequence)
            ln = lines[stop]
            lead = len(ln) - len(ln.lstrip())
            if ln.strip() and (lead > len(indent) or (lead == len(indent) and ln.lstrip().startswith("-"))):
                stop += 1
            else:
                break
        lines[at:stop] = [new]
        end -= stop - at - 1
    return "".join(lines)


def save_mask(path: str | Path, values: dict[str, Sequence[Rect]]) -> None:
    """Set detector.<key> = rects for each of values ("ignore", "rois") in the station YAML file at path,
    keeping the rest of it; written to a temporary file beside it and renamed over it (atomic). Raises
    OSError or ValueError (the file is not a station mapping)."""
    import yaml

    p = Path(path)
    text = p.read_text()
    data = yaml.safe_load(text)
    if not isinstance(data, dict) or not isinstance(data.get("detector") or {}, dict):
        raise ValueError(f"{p} is not a station configuration mapping with a detector section")
    want: dict[str, Any] = dict(data)
    want["detector"] = {**(data.get("detector") or {}), **{k: [list(map(int, r)) for r in v]
                                                            for k, v in values.items()}}
    new = _edit_in_place(text, values)
    if new is None or yaml.safe_load(new) != want:
        new = yaml.safe_dump(want, sort_keys=False, default_flow_style=None)
    fd, tmp = tempfile.mkstemp(prefix=f".{p.name}.", dir=p.parent)
    try:
        with os.fdopen(fd, "w") as f:
            f.write(new)
            f.flush()
            os.fsync(f.fileno())
        try:
            os.chmod(tmp, p.stat().st_mode & 0o7777)
        except OSError:
            pass
        os.replace(tmp, p)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise
