"""`visionpos-station --snapshot DIR`: save camera frames for intrinsics calibration, on the station itself.

With `--chessboard NxM` (inner corners) a frame is kept only when the whole board is found in it and it
differs from every kept frame (the board moved by more than a twentieth of the image diagonal, or tilted),
so one person waving a board in front of the camera gets a useful set without a second person pressing a
key; each kept frame prints how much of the image the board's corners have covered so far (a 4 x 4 grid of
cells), because the distortion near the edges is only measured where the board has been.
Frames are written losslessly (PNG) as `<camera>_<n>.png` for `visionpos calibrate intrinsics --images DIR`.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np

from stations.sources import EndOfStream, FrameSource

GRID_CELLS = 4  # the coverage grid is GRID_CELLS x GRID_CELLS cells of the image
NEW_VIEW_FRACTION = 0.05  # a board outline that moved less than this part of the diagonal is a duplicate


def board_outline(image: np.ndarray, inner_corners: tuple[int, int]) -> np.ndarray | None:
    """(N, 2) chessboard inner corners in pixels, or None when the whole board is not in the image."""
    ok, corners = cv2.findChessboardCorners(image, inner_corners,
                                            flags=cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
                                            | cv2.CALIB_CB_FAST_CHECK)
    return corners.reshape(-1, 2).astype(np.float64) if ok else None


def _outline_key(corners: np.ndarray, inner_corners: tuple[int, int]) -> np.ndarray:
    """The board's four outer corners (8,): where it is, how large and how tilted."""
    nx, ny = inner_corners
    return corners[[0, nx - 1, nx * ny - 1, nx * (ny - 1)]].ravel()


def snapshot(source: FrameSource, out_dir: str | Path, count: int, interval_s: float,
             inner_corners: tuple[int, int] | None = None, prefix: str = "cam",
             say: Callable[[str], None] = print, max_seconds: float | None = None) -> list[Path]:
    """Save up to `count` frames of an open `source` into out_dir, at least interval_s apart; with
    inner_corners, only frames with a new view of that chessboard. Stops at the count, at the end of a
    file source, or after max_seconds. Returns the files written."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    written: list[Path] = []
    kept: list[np.ndarray] = []
    covered = np.zeros((GRID_CELLS, GRID_CELLS), bool)
    t_start = time.monotonic()
    last_save = -np.inf
    diag = None
    while len(written) < count:
        if max_seconds is not None and time.monotonic() - t_start > max_seconds:
            say(f"stopped after {max_seconds:g} s with {len(written)} of {count} frames")
            break
        try:
            img, _ = source.read()
        except EndOfStream:
            say(f"end of the source after {len(written)} of {count} frames")
            break
        now = time.monotonic()
        if now - last_save < interval_s:
            continue
        note = ""
        if inner_corners is not None:
            corners = board_outline(img, inner_corners)
            if corners is None:
                continue
            diag = diag or float(np.hypot(*img.shape[:2]))
            key = _outline_key(corners, inner_corners) / diag
            if any(np.abs(key - k).max() < NEW_VIEW_FRACTION for k in kept):
                continue
            kept.append(key)
            h, w = img.shape[:2]
            cells = np.clip((corners / [w, h] * GRID_CELLS).astype(int), 0, GRID_CELLS - 1)
            covered[cells[:, 1], cells[:, 0]] = True
            note = (f", board found; image covered {100 * covered.mean():.0f} %"
                    + ("" if covered.all() else f" (missing: {_missing(covered)})"))
        path = out / f"{prefix}_{len(written):03d}.png"
        if not cv2.imwrite(str(path), img):
            raise OSError(f"cannot write {path}")
        written.append(path)
        last_save = now
        say(f"saved {path} ({len(written)}/{count}{note})")
    return written


def _missing(covered: np.ndarray) -> str:
    """The uncovered cells in words: 'top left, bottom right, ...' (rows top to bottom)."""
    rows = ["top", "upper middle", "lower middle", "bottom"] if GRID_CELLS == 4 else [str(i) for i in range(GRID_CELLS)]
    cols = ["left", "centre-left", "centre-right", "right"] if GRID_CELLS == 4 else [str(i) for i in range(GRID_CELLS)]
    return ", ".join(f"{rows[r]} {cols[c]}" for r, c in zip(*np.nonzero(~covered)))
