"""Intrinsics from chessboard or ChArUco images, pinhole or fisheye (Kannala-Brandt).

detect -> select diverse views -> cv2.calibrateCamera / cv2.fisheye.calibrate
-> drop views far worse than the rest and solve again -> a CameraModel plus
per-view and per-corner residuals (for the coverage/residual plot).

Board sizes count *squares*: a chessboard of `cols` x `rows` squares has
(cols-1) x (rows-1) inner corners, which is what is detected.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import cv2
import numpy as np

from visionpos.calibration.wand import CalibrationError
from visionpos.camera.model import FISHEYE, PINHOLE, CameraModel

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm")


@dataclass(frozen=True)
class BoardSpec:
    """kind: 'chessboard' or 'charuco'; cols x rows squares of `square` m;
    ChArUco: `marker` m markers from the cv2.aruco dictionary `dictionary`."""

    kind: str = "chessboard"
    cols: int = 10
    rows: int = 7
    square: float = 0.025
    marker: float = 0.018
    dictionary: str = "DICT_4X4_50"

    def __post_init__(self) -> None:
        if self.kind not in ("chessboard", "charuco"):
            raise CalibrationError(f"board '{self.kind}' is unknown; use chessboard or charuco")
        if self.cols < 3 or self.rows < 3:
            raise CalibrationError(f"a board needs at least 3 x 3 squares, got {self.cols} x {self.rows}")
        if not self.square > 0:
            raise CalibrationError(f"square size must be positive, got {self.square}")
        if self.kind == "charuco":
            if not 0 < self.marker < self.square:
                raise CalibrationError(f"ChArUco marker size {self.marker} must be positive and below the square size")
            if not hasattr(cv2.aruco, self.dictionary):
                raise CalibrationError(f"unknown ArUco dictionary '{self.dictionary}' (e.g. DICT_4X4_50, DICT_5X5_100)")

    @property
    def pattern(self) -> tuple[int, int]:
        """Inner corners (per row, per column) as OpenCV's patternSize."""
        return self.cols - 1, self.rows - 1

    def corners(self) -> np.ndarray:
        """(N, 3) inner-corner positions in the board frame (m), id order (row-major, z = 0)."""
        if self.kind == "charuco":
            return np.asarray(self.charuco_board().getChessboardCorners(), np.float64).reshape(-1, 3)
        nx, ny = self.pattern
        gx, gy = np.meshgrid(np.arange(1, nx + 1), np.arange(1, ny + 1))
        return np.column_stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)]) * self.square

    def charuco_board(self):
        d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
        return cv2.aruco.CharucoBoard((self.cols, self.rows), self.square, self.marker, d)

    def flat_image(self, px_per_square: int) -> np.ndarray:
        """The board as printed: uint8 image, cols*px by rows*px, top-left square black."""
        if self.kind == "charuco":
            return self.charuco_board().generateImage((self.cols * px_per_square, self.rows * px_per_square))
        yy, xx = np.mgrid[0 : self.rows * px_per_square, 0 : self.cols * px_per_square]
        black = ((yy // px_per_square) + (xx // px_per_square)) % 2 == 0
        return np.where(black, 0, 255).astype(np.uint8)


@dataclass
class Detection:
    """Corners found in one image: ids (n,) into BoardSpec.corners(), pixels (n, 2)."""

    name: str
    ids: np.ndarray
    pixels: np.ndarray


def detect_corners(image: np.ndarray, board: BoardSpec, name: str = "") -> Detection | None:
    """Board corners in a grey or colour image; None when the board is not found."""
    img = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    if board.kind == "chessboard":
        ok, corners = cv2.findChessboardCornersSB(img, board.pattern, flags=cv2.CALIB_CB_ACCURACY)
        if not ok:
            return None
        px = corners.reshape(-1, 2).astype(np.float64)
        return Detection(name, np.arange(len(px)), px)
    det = cv2.aruco.CharucoDetector(board.charuco_board())
    corners, ids, _, _ = det.detectBoard(img)
    if ids is None or len(ids) < 6:
        return None
    ids = ids.ravel().astype(int)
    px = corners.reshape(-1, 2).astype(np.float64)
    # ChArUco corner ids follow the same row-major inner-corner order
    return Detection(name, ids, px)


def _outline(det: Detection, board: BoardSpec) -> np.ndarray | None:
    """(8,) image positions of the board's four outer inner-corners via a homography (pose descriptor)."""
    obj = board.corners()[det.ids, :2]
    if len(obj) < 4:
        return None
    H, _ = cv2.findHomography(obj, det.pixels, 0)
    if H is None:
        return None
    nx, ny = board.pattern
    q = np.array([[1, 1], [nx, 1], [nx, ny], [1, ny]], float) * board.square
    p = cv2.perspectiveTransform(q[None], H)[0]
    return p.ravel()


def select_views(
    detections: Sequence[Detection], board: BoardSpec, image_size: tuple[int, int], max_views: int = 40,
    duplicate_frac: float = 0.02,
) -> list[int]:
    """Indices of diverse detections: near-duplicates dropped, then farthest-point
    sampling on the board outline (position, size and perspective) up to max_views."""
    w, h = image_size
    diag = float(np.hypot(w, h))
    desc, idx = [], []
    for i, d in enumerate(detections):
        o = _outline(d, board)
        if o is not None and np.isfinite(o).all():
            desc.append(o / diag)
            idx.append(i)
    if not idx:
        return []
    D = np.array(desc)
    # start from the view with the most corners; then farthest point (max over the 4 corners' shifts)
    counts = np.array([len(detections[i].ids) for i in idx])
    chosen = [int(np.argmax(counts))]
    dist = _outline_dist(D, D[chosen[0]])
    while len(chosen) < min(max_views, len(idx)):
        k = int(np.argmax(dist))
        if dist[k] < duplicate_frac:
            break
        chosen.append(k)
        dist = np.minimum(dist, _outline_dist(D, D[k]))
    return sorted(idx[k] for k in chosen)


def _outline_dist(D: np.ndarray, d: np.ndarray) -> np.ndarray:
    return np.abs(D - d).reshape(len(D), 4, 2).max(axis=(1, 2))


@dataclass
class IntrinsicsResult:
    """model: the calibrated CameraModel; rms_px: overall RMS reprojection error;
    views: names of the images used; view_rms: (n,) per-image RMS; pixels and
    residuals: per view (k, 2) detected corners and (detected - reprojected) px;
    rejected: names dropped as outliers (their error was far above the rest)."""

    model: CameraModel
    rms_px: float
    views: list[str]
    view_rms: np.ndarray
    pixels: list[np.ndarray]
    residuals: list[np.ndarray]
    rejected: list[str] = field(default_factory=list)
    candidates: int = 0


def _solve(dets: list[Detection], board: BoardSpec, size: tuple[int, int], kind: str, fix_k3: bool = True):
    obj_all = board.corners()
    objs = [obj_all[d.ids].astype(np.float64) for d in dets]
    imgs = [d.pixels.astype(np.float64) for d in dets]
    w, h = size
    K0 = np.array([[max(w, h), 0, (w - 1) / 2], [0, max(w, h), (h - 1) / 2], [0, 0, 1.0]])
    crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-12)
    if kind == PINHOLE:
        rms, K, D, rvecs, tvecs = cv2.calibrateCamera(
            [o.astype(np.float32) for o in objs], [p.astype(np.float32) for p in imgs], (w, h), K0, None,
            flags=cv2.CALIB_FIX_K3 if fix_k3 else 0, criteria=crit,
        )
        dist = np.asarray(D, float).ravel()[:5]
    else:
        # OpenCV 5 moved the fisheye flags into the cv2 namespace; 4.x keeps them in cv2.fisheye
        ns = cv2.fisheye if hasattr(cv2.fisheye, "CALIB_RECOMPUTE_EXTRINSIC") else cv2
        flags = ns.CALIB_RECOMPUTE_EXTRINSIC | ns.CALIB_FIX_SKEW
        rms, K, D, rvecs, tvecs = cv2.fisheye.calibrate(
            [o.reshape(1, -1, 3) for o in objs], [p.reshape(1, -1, 2) for p in imgs], (w, h), K0, np.zeros(4),
            flags=flags, criteria=crit,
        )
        dist = np.asarray(D, float).ravel()[:4]
    model = CameraModel(kind, w, h, float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]), dist)
    res = []
    for o, p, rv, tv in zip(objs, imgs, rvecs, tvecs):
        R, _ = cv2.Rodrigues(np.asarray(rv, float).reshape(3))
        res.append(p - model.project(o, R, np.asarray(tv, float).reshape(3)))
    return model, res


def calibrate_intrinsics(
    detections: Sequence[Detection],
    board: BoardSpec,
    image_size: tuple[int, int],
    kind: str = PINHOLE,
    max_views: int = 40,
    min_views: int = 8,
    outlier_factor: float = 3.0,
    fix_k3: bool = True,
) -> IntrinsicsResult:
    """Calibrate from detections (all images of one camera in one capture mode).

    image_size: (width, height). fix_k3: keep the pinhole k3 at zero (moderate lenses;
    a free k3 trades off against the focal length). Raises CalibrationError with what
    to capture when too few views.
    """
    if kind not in (PINHOLE, FISHEYE):
        raise CalibrationError(f"camera model '{kind}' is unknown; use pinhole or fisheye")
    found = [d for d in detections if d is not None and len(d.ids) >= 6]
    sel = select_views(found, board, image_size, max_views)
    if len(sel) < min_views:
        raise CalibrationError(
            f"only {len(sel)} distinct board views (board found in {len(found)} of {len(detections)} images, "
            f"need {min_views} distinct views); capture "
            "more images with the board in different places, distances and tilts, covering the corners of the image"
        )
    dets = [found[i] for i in sel]
    model, res = _solve(dets, board, image_size, kind, fix_k3)
    view_rms = np.array([np.sqrt(np.mean(np.sum(r**2, axis=1))) for r in res])
    rejected: list[str] = []
    bad = view_rms > outlier_factor * max(np.median(view_rms), 0.05)
    if bad.any() and (~bad).sum() >= min_views:
        rejected = [d.name for d, b in zip(dets, bad) if b]
        dets = [d for d, b in zip(dets, bad) if not b]
        model, res = _solve(dets, board, image_size, kind, fix_k3)
        view_rms = np.array([np.sqrt(np.mean(np.sum(r**2, axis=1))) for r in res])
    allr = np.concatenate(res)
    rms = float(np.sqrt(np.mean(np.sum(allr**2, axis=1))))
    return IntrinsicsResult(
        model, rms, [d.name for d in dets], view_rms, [d.pixels for d in dets], res, rejected, len(found)
    )


@dataclass(frozen=True)
class CaptureMode:
    """Another capture mode of the calibrated sensor: width x height pixels after resizing the full image and
    cropping crop_px = (U, V) pixels in total, half from each side (CameraModel.rescale)."""

    width: int
    height: int
    crop_px: tuple[float, float]

    def apply(self, model: CameraModel) -> CameraModel:
        return model.rescale(self.width, self.height, self.crop_px)


def capture_mode(spec: str, native_size: tuple[int, int]) -> CaptureMode:
    """'WxH' (the crop that keeps the aspect ratio, centred, as camera drivers crop) or 'WxH+UxV' (that crop,
    which must keep the aspect ratio of the native_size (width, height) images); CalibrationError otherwise,
    with the crop that would fit."""
    size, plus, crop = spec.partition("+")
    try:
        w, h = (int(v) for v in size.lower().split("x"))
        U, V = (float(v) for v in crop.lower().split("x")) if plus else (None, None)
    except ValueError:
        raise CalibrationError(f"--rescale '{spec}': expected WxH or WxH+UxV (pixels), e.g. 640x480 or "
                               "640x360+0x120") from None
    if w <= 0 or h <= 0:
        raise CalibrationError(f"--rescale '{spec}': width and height must be positive")
    W0, H0 = native_size
    s = max(w / W0, h / H0)  # resize so the mode fits, then crop the excess
    auto = (round(W0 * s - w, 6), round(H0 * s - h, 6))
    if U is None:
        return CaptureMode(w, h, auto)
    if U < 0 or V < 0 or abs((w + U) / W0 - (h + V) / H0) > 1e-3 * (h + V) / H0:
        raise CalibrationError(
            f"--rescale '{spec}': from {W0}x{H0} images, {w}x{h} plus a {U:g}x{V:g} crop changes the aspect ratio; "
            f"the crop that keeps it is {auto[0]:g}x{auto[1]:g} (give just {w}x{h} to use it)")
    return CaptureMode(w, h, (U, V))


def load_images(directory: str | Path) -> list[tuple[str, np.ndarray]]:
    """Grey images from a folder (sorted by name); raises CalibrationError if none can be read."""
    p = Path(directory)
    if not p.is_dir():
        raise CalibrationError(f"{p}: not a folder of board images")
    files = sorted(f for f in p.iterdir() if f.suffix.lower() in IMAGE_SUFFIXES)
    out = []
    for f in files:
        img = cv2.imread(str(f), cv2.IMREAD_GRAYSCALE)
        if img is not None:
            out.append((f.name, img))
    if not out:
        raise CalibrationError(f"{p}: no readable images ({', '.join(IMAGE_SUFFIXES)})")
    sizes = {img.shape for _, img in out}
    if len(sizes) > 1:
        raise CalibrationError(
            f"{p}: images have different sizes {sorted(sizes)}; calibrate each capture mode separately "
            "(and use --rescale for the others)"
        )
    return out


def calibrate_images(
    images: Sequence[tuple[str, np.ndarray]], board: BoardSpec, kind: str = PINHOLE, max_views: int = 40,
    progress=None, fix_k3: bool = True,
) -> IntrinsicsResult:
    """Detect the board in every (name, image) and calibrate. A chessboard found in no image raises
    CalibrationError naming the inner-corner count that was looked for and, when the images show a board
    of another size, that size."""
    dets = []
    for k, (name, img) in enumerate(images):
        dets.append(detect_corners(img, board, name))
        if progress is not None:
            progress("corners", k + 1, len(images))
    if board.kind == "chessboard" and not any(d is not None for d in dets):
        nx, ny = board.pattern
        msg = (f"no chessboard with {nx}x{ny} inner corners ({board.cols}x{board.rows} squares) was found in any of "
               f"the {len(images)} images")
        other = other_chessboard_size(images, board)
        if other is not None:
            msg += (f"; the images show one with {other[0]}x{other[1]} inner corners: use --inner-corners "
                    f"{other[0]}x{other[1]} (OpenCV's pattern size counts inner corners, --squares counts squares)")
        else:
            msg += ("; check the counts (--inner-corners counts the corners where four squares meet, as OpenCV's "
                    "pattern size; --squares counts squares), and that the whole board is in the image, sharp and "
                    "evenly lit")
        raise CalibrationError(msg)
    h, w = images[0][1].shape[:2]
    return calibrate_intrinsics(dets, board, (w, h), kind, max_views, fix_k3=fix_k3)


def other_chessboard_size(images: Sequence[tuple[str, np.ndarray]], board: BoardSpec,
                          max_images: int = 4) -> tuple[int, int] | None:
    """Inner-corner counts (per row, per column), within one of the given ones or swapped, of a chessboard
    found in one of the first `max_images` images; None when there is none."""
    nx, ny = board.pattern
    tries = [(nx + dx, ny + dy) for dx in (1, -1, 0) for dy in (1, -1, 0)] + [(ny, nx), (ny + 1, nx + 1)]
    tries = [t for t in dict.fromkeys(tries) if t != (nx, ny) and min(t) >= 2]
    for _, img in images[:max_images]:
        grey = img if img.ndim == 2 else cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
        for t in tries:
            if cv2.findChessboardCornersSB(grey, t)[0]:
                return t
    return None


def model_warnings(res: IntrinsicsResult) -> list[str]:
    """Plain-language doubts about a calibration result: a high residual, a principal point far from the
    centre, unequal focal lengths, corners that left the image's edges unconstrained, a distortion that folds
    back inside the image, and a fisheye model on a narrow lens."""
    m = res.model
    out = []
    if res.rms_px > 1.0:
        out.append(f"reprojection RMS {res.rms_px:.2f} px is high (good: below 0.5 px): blurred images, a board that "
                   "is not flat, or the wrong --model")
    dx, dy = m.cx - (m.width - 1) / 2, m.cy - (m.height - 1) / 2
    if abs(dx) > 0.1 * m.width or abs(dy) > 0.1 * m.height:
        out.append(f"the principal point ({m.cx:.0f}, {m.cy:.0f}) is {abs(dx):.0f}, {abs(dy):.0f} px from the image "
                   "centre (more than 10 % of the image): the views probably did not cover the image evenly")
    if abs(m.fx / m.fy - 1) > 0.03:
        out.append(f"fx {m.fx:.1f} and fy {m.fy:.1f} differ by {100 * abs(m.fx / m.fy - 1):.1f} % (square pixels "
                   "differ by well under 1 %): add views with the board tilted both ways")
    px = np.concatenate(res.pixels) if res.pixels else np.zeros((0, 2))
    if len(px):
        hull = cv2.convexHull(px.astype(np.float32))
        covered = float(cv2.contourArea(hull)) / (m.width * m.height)
        if covered < 0.5:
            out.append(f"the board's corners cover {100 * covered:.0f} % of the image: the distortion near the edges "
                       "is extrapolated; add views with the board in the image's corners")
    # the lens mapping must grow monotonically out to the image corners, or two directions share a pixel
    corner_r = np.hypot(max(m.cx, m.width - 1 - m.cx) / m.fx, max(m.cy, m.height - 1 - m.cy) / m.fy)
    r = np.linspace(0.0, 1.05 * corner_r, 200)
    if m.kind == FISHEYE:
        theta = np.arctan(r)
        k = m.dist
        rd = theta * (1 + k[0] * theta**2 + k[1] * theta**4 + k[2] * theta**6 + k[3] * theta**8)
        fov_deg = 2 * np.degrees(np.arctan(corner_r))
        if fov_deg < 100 or np.abs(k).max() > 1.0:
            out.append(f"a fisheye model on a lens whose image diagonal spans {fov_deg:.0f} deg (coefficients "
                       f"{', '.join(f'{v:.3g}' for v in k)}): below about 100 deg a pinhole model fits as well and "
                       "extrapolates better; try --model pinhole")
    else:
        k = m.dist
        r2 = r**2
        rd = r * (1 + k[0] * r2 + k[1] * r2**2 + (k[4] if len(k) > 4 else 0.0) * r2**3)
    if np.any(np.diff(rd) <= 0):
        out.append("the fitted distortion folds back before the image corners (the coefficients are not physical "
                   "there): add views near the image edges, or keep k3 fixed (no --free-k3)")
    return out


def render_board(
    model: CameraModel, board: BoardSpec, R: np.ndarray, t: np.ndarray, supersample: int = 2,
    px_per_square: int = 80, background: int = 128, rays: np.ndarray | None = None,
) -> np.ndarray:
    """Synthetic grey image of the board seen by `model` at pose (R, t) (board -> camera).

    Every (supersampled) pixel's ray is intersected with the board plane and the
    printed board is sampled there, then the image is averaged down: exact
    geometry including distortion, with anti-aliased edges. The board's paper
    margin of one square is white. rays: pixel_rays(model, supersample), to reuse.
    """
    s = supersample
    W, H = model.width * s, model.height * s
    if rays is None:
        rays = pixel_rays(model, s)
    # board plane z_b = 0: point = R^T (lambda ray - t)
    n = R[:, 2]  # board normal in camera frame
    d = float(n @ t)
    with np.errstate(divide="ignore", invalid="ignore"):
        lam = d / (rays @ n)
        pb = (lam[:, None] * rays - t) @ R  # board-frame points
    flat = board.flat_image(px_per_square)
    margin = px_per_square
    canvas = np.full((flat.shape[0] + 2 * margin, flat.shape[1] + 2 * margin), 255, np.uint8)
    canvas[margin:-margin, margin:-margin] = flat
    scale = px_per_square / board.square
    mx = (pb[:, 0] * scale + margin - 0.5).astype(np.float32).reshape(H, W)
    my = (pb[:, 1] * scale + margin - 0.5).astype(np.float32).reshape(H, W)
    bad = ~np.isfinite(mx) | ~np.isfinite(my) | (lam.reshape(H, W) <= 0)
    mx[bad] = -1e6
    my[bad] = -1e6
    img = cv2.remap(canvas, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=background)
    return cv2.resize(img, (model.width, model.height), interpolation=cv2.INTER_AREA)


def pixel_rays(model: CameraModel, supersample: int = 2) -> np.ndarray:
    """Unit camera-frame rays (H*s*W*s, 3) of every supersampled pixel (row-major)."""
    s = supersample
    u, v = np.meshgrid((np.arange(model.width * s) + 0.5) / s - 0.5, (np.arange(model.height * s) + 0.5) / s - 0.5)
    return model.rays(np.column_stack([u.ravel(), v.ravel()]))
