"""IR blob detector: threshold -> connected blobs -> background-removed sub-pixel centroids.

Designed for the memory-bound floor on one core: the full frame is touched
only by one cv2.threshold pass and one contour trace (both SIMD/C loops
over uint8); everything after works on small windows around the candidates,
vectorised over all blobs of the frame at once. No full-frame float copies.

Centroid: intensity weights w = I - b over a square aperture around each
blob (not only the thresholded pixels), b the blob's local background from a
robust mean of the window's outer ring. The aperture has fractional pixel
coverage at its edges and is re-centred on the estimate a few times, so a
constant error in b pulls the centroid nowhere (the aperture is symmetric
about the estimate at convergence) and the pixel grid does not bias it.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from visionpos.jit import COMPILED, njit
from visionpos.messages import FLAG_SATURATED, FLAG_TRUNCATED

_COMMON_HALF = 8  # blobs whose aperture fits this half-size share one vectorised gather
_warm = [False]  # compiled centroid kernel ready in this process


@dataclass(frozen=True)
class DetectorConfig:
    """threshold: fixed threshold on the 0..255 scale, or None for automatic
    (background median + auto_k * robust sigma, at least min_contrast above
    the median), re-estimated every auto_every frames from a strided subsample.
    min_area/max_area: thresholded pixel count limits. min_roundness: minor /
    major axis ratio from the weighted second moments (1 = round); applied
    to blobs of at least 5 px. max_blobs: cap per frame (keeps the brightest
    by flux, sets FLAG_TRUNCATED). pad: aperture margin around the thresholded
    extent, px. saturated_pixels: FLAG_SATURATED when more pixels of the kept
    blobs sit at 255."""

    threshold: float | None = None
    auto_k: float = 8.0
    min_contrast: float = 20.0
    auto_every: int = 8
    min_area: int = 1
    max_area: int = 5000
    min_roundness: float = 0.3
    max_blobs: int = 64
    pad: float = 1.0
    iterations: int = 2
    saturated_pixels: int = 30


def background_level(image: np.ndarray, step: int = 8) -> tuple[float, float]:
    """Robust background (median) and pixel noise sigma of a uint8 image, from
    every step-th row and column. The sigma comes from differences of
    horizontally adjacent pixels (1.4826 MAD / sqrt 2), so lighting gradients
    and vignetting do not inflate it. image: (H, W) uint8 -> (median, sigma)."""
    a = np.ascontiguousarray(image[::step, 0:-1:step])
    b = np.ascontiguousarray(image[::step, 1::step][:, : a.shape[1]])
    med = _hist_median(a)
    mad = _hist_median(cv2.absdiff(a[:, : b.shape[1]], b))
    # integer images: MAD of 0 happens at very low noise; 0.5 DN is the quantisation floor
    return med, 1.4826 * max(mad, 0.5) / np.sqrt(2.0)


def _hist_median(u8: np.ndarray) -> float:
    """Median of a uint8 array via its histogram (lower median)."""
    cdf = np.cumsum(cv2.calcHist([u8], [0], None, [256], [0, 256]).ravel())
    return float(np.searchsorted(cdf, cdf[-1] / 2.0))


def auto_threshold(image: np.ndarray, k: float, min_contrast: float) -> float:
    """Threshold = median + max(k * sigma, min_contrast), capped at 254."""
    med, sigma = background_level(image)
    return float(min(med + max(k * sigma, min_contrast), 254.0))


class Detector:
    """Stateful per-camera detector (keeps the automatic threshold, mask and background).

    mask: optional (H, W) uint8/bool, nonzero = pixels to search (ROI).
    background: optional (H, W) uint8 static background subtracted (saturating)
    before detection, e.g. the median of frames without markers.
    """

    def __init__(
        self,
        config: DetectorConfig | None = None,
        mask: np.ndarray | None = None,
        background: np.ndarray | None = None,
    ):
        self.config = config or DetectorConfig()
        self.mask = None if mask is None else np.where(np.asarray(mask) != 0, 255, 0).astype(np.uint8)
        self.background = None if background is None else np.ascontiguousarray(background, dtype=np.uint8)
        self.threshold = self.config.threshold
        self._frames = 0
        self._bin: np.ndarray | None = None
        self._sub: np.ndarray | None = None
        self.last_candidates = 0  # connected components before filtering and cap
        if COMPILED and not _warm[0]:
            # compile (first run after install) or load from the cache now, not on the first frame
            _warm[0] = True
            _centroids_compiled(np.zeros((9, 9), np.uint8), np.full((1, 2), 4.0), np.ones(1), np.ones(1, np.int64), 2)

    def set_background(self, background: np.ndarray | None) -> None:
        self.background = None if background is None else np.ascontiguousarray(background, dtype=np.uint8)

    @staticmethod
    def learn_background(frames: list[np.ndarray]) -> np.ndarray:
        """Per-pixel median of frames (K x (H, W) uint8) -> (H, W) uint8 static background."""
        return np.median(np.stack(frames), axis=0).astype(np.uint8)

    def _check(self, image: np.ndarray) -> np.ndarray:
        if not isinstance(image, np.ndarray) or image.ndim != 2 or image.dtype != np.uint8:
            what = f"{image.dtype} {image.shape}" if isinstance(image, np.ndarray) else type(image).__name__
            raise ValueError(f"detector needs a (H, W) uint8 grey image, got {what}")
        if self.mask is None and self.background is None:
            return image if image.flags.c_contiguous else np.ascontiguousarray(image)
        for name, ref in (("mask", self.mask), ("background", self.background)):
            if ref is not None and ref.shape != image.shape:
                raise ValueError(f"detector {name} is {ref.shape[::-1]} px but the frame is {image.shape[::-1]} px")
        return np.ascontiguousarray(image)

    def _contours(self, img: np.ndarray) -> tuple:
        if self._bin is None or self._bin.shape != img.shape:
            self._bin = np.empty_like(img)
        binary = self._bin
        cv2.threshold(img, float(self.threshold), 255, cv2.THRESH_BINARY, dst=binary)
        if self.mask is not None:
            cv2.bitwise_and(binary, self.mask, dst=binary)
        contours, _ = cv2.findContours(binary, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
        return contours

    def detect(self, image: np.ndarray) -> tuple[np.ndarray, int]:
        """image: (H, W) uint8 -> (blobs (N, 4) float32 [x, y, area, peak], flags).

        x, y: sub-pixel centroid, pixel centres at integer coordinates.
        area: thresholded pixel count. peak: brightest pixel above the local
        background. Sorted by flux, brightest first.
        """
        cfg = self.config
        img = self._check(image)
        if self.background is not None:
            if self._sub is None or self._sub.shape != img.shape:
                self._sub = np.empty_like(img)
            cv2.subtract(img, self.background, dst=self._sub)
            img = self._sub
        fresh = False
        if cfg.threshold is None and (self.threshold is None or self._frames % max(cfg.auto_every, 1) == 0):
            self.threshold = auto_threshold(img, cfg.auto_k, cfg.min_contrast)
            fresh = True
        self._frames += 1
        contours = self._contours(img)
        if cfg.threshold is None and not fresh and len(contours) > 2 * cfg.max_blobs:
            # the scene changed since the threshold was estimated (lights on): redo it now
            self.threshold = auto_threshold(img, cfg.auto_k, cfg.min_contrast)
            contours = self._contours(img)
        self.last_candidates = len(contours)
        if not contours:
            return np.zeros((0, 4), np.float32), 0
        flags = 0
        # Sunlight / reflections: hundreds of contours. Pre-select by contour
        # length (cheap) so the per-contour loop stays bounded.
        limit = 4 * cfg.max_blobs
        if len(contours) > limit:
            lengths = np.fromiter((len(c) for c in contours), np.int64, len(contours))
            keep = np.argpartition(-lengths, limit)[:limit]
            contours = [contours[i] for i in keep]
            flags |= FLAG_TRUNCATED
        # per contour: bounding box and pixel count (Pick's theorem on the
        # traced boundary pixel centres: area + boundary / 2 + 1; a lone pixel is 1)
        rows = []
        for c in contours:
            area = cv2.contourArea(c) + 0.5 * len(c) + 1.0 if len(c) > 1 else 1.0
            if cfg.min_area <= area <= cfg.max_area:
                rows.append((*cv2.boundingRect(c), area))
        if not rows:
            return np.zeros((0, 4), np.float32), flags
        st = np.array(rows)
        half = np.maximum(st[:, 2], st[:, 3]) * 0.5
        c0 = st[:, :2] + (st[:, 2:4] - 1.0) * 0.5  # bounding-box centres
        # aperture half-width per blob; one gather size for all normal blobs
        # (vectorised), big ones (sunlight, near objects) in groups of their own
        aperture = half + cfg.pad
        if len(st) > 1:
            # keep each aperture off its neighbours' thresholded pixels (close
            # markers would pull each other's centroids); shrinking stays
            # symmetric about the blob, so it costs noise, not bias
            diff = c0[:, None, :] - c0[None, :, :]
            d = np.sqrt((diff * diff).sum(axis=2))
            d.flat[:: len(st) + 1] = np.inf  # not its own neighbour
            room = (d - half[None, :]).min(axis=1) - 1.0
            aperture = np.maximum(np.minimum(aperture, room), 1.0)
        size = np.ceil(aperture).astype(np.int64)
        smax = int(size.max())
        if COMPILED:  # one compiled loop over the blobs; window sizes as the vectorised path groups them
            size[size <= _COMMON_HALF] = min(smax, _COMMON_HALF)
            out = _centroids_compiled(img, c0, aperture, size, cfg.iterations)
        elif smax <= _COMMON_HALF:
            out = _centroids(img, c0, aperture, smax, cfg.iterations)
        else:
            size[size <= _COMMON_HALF] = _COMMON_HALF
            out = np.empty((len(st), 6))  # x, y, flux, peak, roundness, saturated px
            for r in np.unique(size).tolist():
                sel = np.flatnonzero(size == r)
                out[sel] = _centroids(img, c0[sel], aperture[sel], r, cfg.iterations)
        good = out[:, 2] > 0  # NaN-safe: lost apertures have NaN flux
        if cfg.min_roundness > 0:
            good &= (out[:, 4] >= cfg.min_roundness) | (st[:, 4] < 5)
        order = np.flatnonzero(good)
        if len(order) > 1:
            order = order[np.argsort(-out[order, 2], kind="stable")]
        if len(order) > cfg.max_blobs:
            order = order[: cfg.max_blobs]
            flags |= FLAG_TRUNCATED
        if out[order, 5].sum() > cfg.saturated_pixels:
            flags |= FLAG_SATURATED
        blobs = np.empty((len(order), 4), np.float32)
        blobs[:, :2] = out[order, :2]
        blobs[:, 2] = st[order, 4]
        blobs[:, 3] = out[order, 3]
        return blobs, flags


_RING: dict[int, np.ndarray] = {}


def _ring_index(S: int) -> np.ndarray:
    """Flat indices of the outer ring of an S x S window (cached per size)."""
    idx = _RING.get(S)
    if idx is None:
        k = np.arange(S * S).reshape(S, S)
        idx = _RING[S] = np.concatenate([k[0], k[-1], k[1:-1, 0], k[1:-1, -1]])
    return idx


def _centroids(img: np.ndarray, c0: np.ndarray, aperture: np.ndarray, r: int, iterations: int) -> np.ndarray:
    """Aperture centroids of M blobs gathered in windows of one size.

    img: (H, W) uint8; c0: (M, 2) initial x, y; aperture: (M,) half-widths
    (px, <= r); r: window half-size. Returns (M, 6): x, y, flux (sum of
    background-removed weights in the aperture), peak above background,
    roundness (minor/major axis), count of pixels at 255. x is NaN where the
    aperture holds no signal.

    x and y are handled together as axis 1 of (M, 2, ...) arrays: this runs per
    frame, and numpy's per-call cost, not arithmetic, is what it spends.
    """
    H, W = img.shape
    S = 2 * r + 3  # one spare pixel each side so the aperture can move by +-1 px
    M = len(c0)
    centre_px = np.rint(c0).astype(np.int64)  # (M, 2) window centres
    XY = centre_px[:, :, None] + np.arange(-(r + 1), r + 2)  # (M, 2, S) pixel columns / rows of each window
    corners = (XY[:, :, 0]).tolist()  # window top-left x, y
    edge = any(x < 0 or y < 0 or x + S > W or y + S > H for x, y in corners)
    if edge:  # rare: windows cut by the image border get a validity mask
        xs, ys = XY[:, 0], XY[:, 1]
        vx = (xs >= 0) & (xs < W)
        vy = (ys >= 0) & (ys < H)
        valid = vy[:, :, None] & vx[:, None, :]
        win = img[np.clip(ys, 0, H - 1)[:, :, None], np.clip(xs, 0, W - 1)[:, None, :]].astype(np.float64)
        sat = ((win == 255) & valid).sum(axis=(1, 2))
        # local background: interquartile mean of the window's outer ring (robust
        # to a neighbouring blob's tail, unbiased for symmetric noise)
        ring_i = _ring_index(S)
        ring = np.sort(np.where(valid.reshape(M, -1)[:, ring_i], win.reshape(M, -1)[:, ring_i], np.inf), axis=1)
        nv = valid.reshape(M, -1)[:, ring_i].sum(axis=1)
        rank = np.arange(ring.shape[1])[None, :]
        mid = (rank >= (nv // 4)[:, None]) & (rank < np.maximum(nv - nv // 4, nv // 4 + 1)[:, None])
        bg = np.where(mid, ring, 0.0).sum(axis=1) / mid.sum(axis=1)
        wts = np.where(valid, win - bg[:, None, None], 0.0)
    else:  # slice copies beat fancy indexing for a handful of small windows
        win = np.empty((M, S, S))
        for k, (x, y) in enumerate(corners):
            win[k] = img[y : y + S, x : x + S]
        sat = (win == 255).sum(axis=(1, 2)) if win.max() >= 255 else np.zeros(M)
        ring = win.reshape(M, -1)[:, _ring_index(S)]
        ring.sort(axis=1)
        L = ring.shape[1]
        bg = ring[:, L // 4 : L - L // 4].sum(axis=1) * (1.0 / (L - 2 * (L // 4)))
        wts = win - bg[:, None, None]
    peak = wts.max(axis=(1, 2))
    F = XY.astype(np.float64)  # (M, 2, S)
    C = np.asarray(c0, np.float64)  # (M, 2) current estimate
    R = (np.asarray(aperture, np.float64) + 0.5)[:, None, None]
    with np.errstate(invalid="ignore", divide="ignore"):
        for _ in range(max(iterations, 1)):
            # pixel coverage of the aperture [c - R + 0.5, c + R - 0.5] per column (x) and row (y)
            A = np.minimum(np.maximum(R - np.abs(F - C[:, :, None]), 0.0), 1.0)  # (M, 2, S)
            # aperture-weighted column sums (x) and row sums (y), (M, 2, S)
            WS = np.stack([np.matmul(A[:, 1:2], wts)[:, 0], np.matmul(wts, A[:, 0, :, None])[:, :, 0]], axis=1) * A
            flux = WS[:, 0].sum(axis=1)
            N = (WS * F).sum(axis=2) / flux[:, None]
            # the window has one spare pixel: an estimate further than 1 px from
            # its centre means the aperture lost the blob (no real signal)
            bad = ~(flux > 0) | ~(np.abs(N - centre_px).max(axis=1) <= 1.0)
            C = np.where(bad[:, None], np.nan, N)
        flux = np.where(np.isnan(C[:, 0]), np.nan, flux)  # lost in the last iteration too
        # second moments over the aperture -> axis ratio (roundness)
        D = F - C[:, :, None]  # (M, 2, S)
        mxx, myy = ((WS * D * D).sum(axis=2) / flux[:, None]).T
        AD = A * D
        mxy = (np.matmul(AD[:, 1:2], wts) * AD[:, 0:1]).sum(axis=(1, 2)) / flux
        tr, det = mxx + myy, mxx * myy - mxy * mxy
        disc = np.sqrt(np.maximum(tr * tr / 4.0 - det, 0.0))
        roundness = np.sqrt(np.maximum(tr / 2.0 - disc, 0.0) / (tr / 2.0 + disc))
    out = np.empty((M, 6))
    out[:, 0:2] = C
    out[:, 2] = flux
    out[:, 3] = peak
    out[:, 4] = roundness
    out[:, 5] = sat
    return out


@njit
def _centroids_compiled(img, c0, aperture, half, iterations):
    """_centroids, compiled, one blob at a time: the same windows (half-size half (M,)),
    ring background, aperture iterations and moments, without numpy's per-call cost.
    Used where numba is installed; _centroids is the reference it is tested against."""
    H, W = img.shape
    M = c0.shape[0]
    out = np.empty((M, 6))
    for m in range(M):
        r = half[m]
        S = 2 * r + 3
        ix, iy = int(np.rint(c0[m, 0])), int(np.rint(c0[m, 1]))
        x0, y0 = ix - r - 1, iy - r - 1
        win = np.empty((S, S))
        valid = np.empty((S, S), dtype=np.bool_)
        sat = 0
        for a in range(S):
            for b in range(S):
                y, x = y0 + a, x0 + b
                valid[a, b] = 0 <= x < W and 0 <= y < H
                v = float(img[min(max(y, 0), H - 1), min(max(x, 0), W - 1)])
                win[a, b] = v
                if valid[a, b] and v == 255.0:
                    sat += 1
        # local background: interquartile mean of the window's valid outer-ring pixels
        ring = np.empty(4 * S - 4)
        nv = 0
        for b in range(S):
            for a in (0, S - 1):
                if valid[a, b]:
                    ring[nv] = win[a, b]
                    nv += 1
        for a in range(1, S - 1):
            for b in (0, S - 1):
                if valid[a, b]:
                    ring[nv] = win[a, b]
                    nv += 1
        ring = np.sort(ring[:nv])
        lo, hi = nv // 4, max(nv - nv // 4, nv // 4 + 1)
        bg = ring[lo:hi].sum() / (hi - lo)
        peak = -np.inf
        for a in range(S):
            for b in range(S):
                win[a, b] = win[a, b] - bg if valid[a, b] else 0.0
                peak = max(peak, win[a, b])
        Fx = np.arange(S) + x0 + 0.0
        Fy = np.arange(S) + y0 + 0.0
        cx, cy = c0[m, 0], c0[m, 1]
        R = aperture[m] + 0.5
        Ax = np.empty(S)
        Ay = np.empty(S)
        WSx = np.empty(S)
        WSy = np.empty(S)
        flux = np.nan
        lost = False
        for _ in range(max(iterations, 1)):
            for k in range(S):  # pixel coverage of the aperture per column and row
                Ax[k] = min(max(R - abs(Fx[k] - cx), 0.0), 1.0)
                Ay[k] = min(max(R - abs(Fy[k] - cy), 0.0), 1.0)
            for k in range(S):
                sx = 0.0
                sy = 0.0
                for j in range(S):
                    sx += Ay[j] * win[j, k]
                    sy += win[k, j] * Ax[j]
                WSx[k] = sx * Ax[k]
                WSy[k] = sy * Ay[k]
            flux = WSx.sum()
            nx = (WSx * Fx).sum() / flux
            ny = (WSy * Fy).sum() / flux
            # one spare pixel: an estimate further than 1 px from the window centre lost the blob
            if not (flux > 0) or not (max(abs(nx - ix), abs(ny - iy)) <= 1.0):
                lost = True
                break
            cx, cy = nx, ny
        if lost:
            out[m, 0] = out[m, 1] = out[m, 2] = out[m, 4] = np.nan
            out[m, 3], out[m, 5] = peak, sat
            continue
        mxx = myy = mxy = 0.0
        for k in range(S):
            dx, dy = Fx[k] - cx, Fy[k] - cy
            mxx += WSx[k] * dx * dx
            myy += WSy[k] * dy * dy
            for j in range(S):
                mxy += Ay[j] * (Fy[j] - cy) * win[j, k] * Ax[k] * dx
        mxx /= flux
        myy /= flux
        mxy /= flux
        tr, det = mxx + myy, mxx * myy - mxy * mxy
        disc = np.sqrt(max(tr * tr / 4.0 - det, 0.0))
        out[m, 0], out[m, 1], out[m, 2], out[m, 3] = cx, cy, flux, peak
        out[m, 4] = np.sqrt(max(tr / 2.0 - disc, 0.0) / (tr / 2.0 + disc))
        out[m, 5] = sat
    return out
