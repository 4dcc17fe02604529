"""Frame sources behind one interface: open() / read() -> (image, t_ns) / close().

image: (H, W) uint8 grey. t_ns: capture time on the station clock (the
`clock` callable the agent passes: time.monotonic_ns with the built-in sync,
time.time_ns when PTP/chrony disciplines the host). Sources with a sensor
timestamp (Picamera2) convert it to that clock; the others stamp at read
time minus the configured timestamp_offset_ms.

read() raises SourceError when the camera fails (unplugged, garbage frame)
and EndOfStream when a file source ends without looping. The agent owns
retries and back-off.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Callable

import cv2
import numpy as np

from stations.config import SourceConfig
from visionpos.errors import VisionposError

Clock = Callable[[], int]
ToShared = Callable[[int], "int | None"]  # station-clock ns -> the shared (server) clock; None while unsynced
IMAGE_SUFFIXES = (".png", ".pgm", ".bmp", ".jpg", ".jpeg", ".tif", ".tiff")


class SourceError(VisionposError, RuntimeError):
    """The camera or file failed; the message says what and what to check."""


class EndOfStream(Exception):
    """A non-looping file source has no more frames."""


def to_grey(frame: object, what: str) -> np.ndarray:
    """Any plausible camera frame -> (H, W) uint8; SourceError for garbage."""
    if not isinstance(frame, np.ndarray) or frame.size == 0:
        raise SourceError(f"{what} returned no image ({type(frame).__name__})")
    if frame.ndim == 3 and frame.shape[2] in (3, 4):
        frame = cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY if frame.shape[2] == 3 else cv2.COLOR_BGRA2GRAY)
    elif frame.ndim == 3 and frame.shape[2] == 1:
        frame = frame[:, :, 0]
    if frame.ndim != 2:
        raise SourceError(f"{what} returned an image of shape {frame.shape}; expected grey (H, W) or colour (H, W, 3)")
    if frame.dtype == np.uint16:  # 10/12/16-bit sensors: keep the top 8 bits of the container
        frame = (frame >> 8).astype(np.uint8)
    elif frame.dtype != np.uint8:
        raise SourceError(f"{what} returned {frame.dtype} pixels; expected 8- or 16-bit")
    return np.ascontiguousarray(frame)


class _Pacer:
    """Sleeps so that reads come at a steady rate (file and simulated sources)."""

    def __init__(self, fps: float):
        self.period = 1.0 / fps if fps > 0 else 0.0
        self.next = time.monotonic()

    def wait(self) -> None:
        if self.period <= 0:
            return
        now = time.monotonic()
        if self.next > now:
            time.sleep(self.next - now)
            self.next += self.period
        else:  # behind (slow consumer): do not burst to catch up
            self.next = now + self.period


class FrameSource:
    """Base class. Attributes valid after open(): width, height, fps, name."""

    kind = "base"

    def __init__(self, cfg: SourceConfig, clock: Clock = time.monotonic_ns):
        self.cfg = cfg
        self.clock = clock
        self.width, self.height, self.fps = cfg.width, cfg.height, cfg.fps
        self.name = cfg.kind
        self.camera_kind = "unknown"  # lens model, when the source knows it (sim)
        self._offset_ns = int(cfg.timestamp_offset_ms * 1e6)

    def open(self) -> None:
        raise NotImplementedError

    def read(self) -> tuple[np.ndarray, int]:
        raise NotImplementedError

    def close(self) -> None:
        pass

    def __enter__(self) -> "FrameSource":
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _check_size(self, img: np.ndarray, what: str) -> np.ndarray:
        if self.width and self.height and img.shape != (self.height, self.width):
            raise SourceError(
                f"{what} delivered {img.shape[1]}x{img.shape[0]} px but {self.width}x{self.height} was configured "
                "(the camera may not support that mode; set source.width/height to a supported one)"
            )
        return img


class OpenCVSource(FrameSource):
    """V4L2 device (index or /dev/videoN) or a GStreamer pipeline (a string with '!')."""

    kind = "opencv"

    def __init__(self, cfg: SourceConfig, clock: Clock = time.monotonic_ns):
        super().__init__(cfg, clock)
        self.cap: cv2.VideoCapture | None = None

    def open(self) -> None:
        dev = self.cfg.device
        if isinstance(dev, str) and "!" in dev:
            cap = cv2.VideoCapture(dev, cv2.CAP_GSTREAMER)
            self.name = "gstreamer"
        else:
            target = int(dev) if isinstance(dev, str) and dev.isdigit() else dev
            api = cv2.CAP_V4L2 if hasattr(cv2, "CAP_V4L2") and Path("/dev").exists() else cv2.CAP_ANY
            cap = cv2.VideoCapture(target, api)
            self.name = f"v4l2 {dev}"
        if not cap.isOpened():
            cap.release()
            raise SourceError(
                f"cannot open camera {dev!r}: check that it is plugged in (ls /dev/video*), that this user may "
                "read it (group 'video'), and for a pipeline that OpenCV was built with GStreamer"
            )
        if self.cfg.width and self.cfg.height:
            cap.set(cv2.CAP_PROP_FRAME_WIDTH, self.cfg.width)
            cap.set(cv2.CAP_PROP_FRAME_HEIGHT, self.cfg.height)
        if self.cfg.fps:
            cap.set(cv2.CAP_PROP_FPS, self.cfg.fps)
        if not self.cfg.auto_exposure:
            # V4L2 exposure_auto menu: 1 = manual; some OpenCV builds map 0.25 = manual
            if not cap.set(cv2.CAP_PROP_AUTO_EXPOSURE, 1):
                cap.set(cv2.CAP_PROP_AUTO_EXPOSURE, 0.25)
        if self.cfg.exposure_us is not None:
            cap.set(cv2.CAP_PROP_EXPOSURE, self.cfg.exposure_us / 100.0)  # V4L2 unit: 100 us
        if self.cfg.gain is not None:
            cap.set(cv2.CAP_PROP_GAIN, self.cfg.gain)
        self.cap = cap
        self.width = self.cfg.width or int(cap.get(cv2.CAP_PROP_FRAME_WIDTH))
        self.height = self.cfg.height or int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
        self.fps = self.cfg.fps or float(cap.get(cv2.CAP_PROP_FPS) or 0.0)

    def read(self) -> tuple[np.ndarray, int]:
        if self.cap is None:
            raise SourceError("camera is not open")
        ok, frame = self.cap.read()
        t = self.clock() - self._offset_ns
        if not ok:
            raise SourceError(f"camera {self.cfg.device!r} returned no frame (unplugged, or the driver stalled)")
        return self._check_size(to_grey(frame, f"camera {self.cfg.device!r}"), f"camera {self.cfg.device!r}"), t

    def close(self) -> None:
        if self.cap is not None:
            self.cap.release()
            self.cap = None


def mid_exposure_offset_ns(exposure_us: float | None) -> int:
    """Start of exposure -> mid-exposure: half the exposure time (µs, from the frame's metadata), in ns;
    0 when the metadata has none."""
    if exposure_us is None or not exposure_us > 0:
        return 0
    return int(round(float(exposure_us) * 500.0))


class Picamera2Source(FrameSource):
    """Raspberry Pi camera through Picamera2/libcamera, manual exposure and
    gain, stamped at mid-exposure: the sensor's start-of-exposure timestamp plus half the
    frame's exposure time (a moving blob's centroid is where the marker was then)."""

    kind = "picamera2"

    def __init__(self, cfg: SourceConfig, clock: Clock = time.monotonic_ns):
        super().__init__(cfg, clock)
        self.cam = None

    def open(self) -> None:
        try:
            from picamera2 import Picamera2  # imported only when this source is used
        except ImportError:
            raise SourceError(
                "Picamera2 is not installed: on Raspberry Pi OS run `sudo apt install python3-picamera2` and "
                "create the station's virtualenv with --system-site-packages"
            ) from None
        try:
            cam = Picamera2()
        except Exception as e:  # libcamera raises RuntimeError/IndexError when no camera is attached
            raise SourceError(
                f"no Raspberry Pi camera found ({e}); check the ribbon cable and `rpicam-hello --list-cameras`"
            ) from None
        w, h = self.cfg.width or 960, self.cfg.height or 640
        fps = self.cfg.fps or 100.0
        controls: dict[str, object] = {"FrameDurationLimits": (int(1e6 / fps), int(1e6 / fps))}
        if not self.cfg.auto_exposure:
            controls["AeEnable"] = False
            controls["AwbEnable"] = False
        if self.cfg.exposure_us is not None:
            controls["ExposureTime"] = int(self.cfg.exposure_us)
        if self.cfg.gain is not None:
            controls["AnalogueGain"] = float(self.cfg.gain)
        try:
            config = cam.create_video_configuration(main={"size": (w, h), "format": "YUV420"}, controls=controls,
                                                    buffer_count=4)
            cam.configure(config)
            cam.start()
        except Exception as e:
            cam.close()
            raise SourceError(f"cannot start the Pi camera at {w}x{h} {fps:g} fps: {e}") from None
        self.cam = cam
        self.width, self.height, self.fps = w, h, fps
        self.name = f"picamera2 {cam.camera_properties.get('Model', '')}".strip()

    def _to_clock(self, sensor_ns: int) -> int:
        """Sensor timestamps are CLOCK_MONOTONIC or CLOCK_BOOTTIME depending on
        the libcamera version: take the one that makes the frame a plausible
        age (0..1 s), then move it onto the agent's clock."""
        now = self.clock()
        best = None
        for cid in (time.CLOCK_MONOTONIC, getattr(time, "CLOCK_BOOTTIME", time.CLOCK_MONOTONIC)):
            age = time.clock_gettime_ns(cid) - sensor_ns
            if 0 <= age < 1_000_000_000 and (best is None or age < best):
                best = age
        if best is None:
            return now - self._offset_ns  # unknown clock: fall back to the read time
        return now - best

    def read(self) -> tuple[np.ndarray, int]:
        if self.cam is None:
            raise SourceError("camera is not open")
        try:
            req = self.cam.capture_request()
            try:
                yuv = req.make_array("main")
                md = req.get_metadata()
            finally:
                req.release()
        except Exception as e:
            raise SourceError(f"Pi camera capture failed: {e}") from None
        img = np.ascontiguousarray(yuv[: self.height, : self.width])  # the Y plane is the grey image
        ts = md.get("SensorTimestamp")
        t = self._to_clock(int(ts)) + mid_exposure_offset_ns(md.get("ExposureTime")) if ts \
            else self.clock() - self._offset_ns
        return self._check_size(to_grey(img, "Pi camera"), "Pi camera"), t

    def close(self) -> None:
        if self.cam is not None:
            try:
                self.cam.stop()
                self.cam.close()
            finally:
                self.cam = None


class VideoFileSource(FrameSource):
    """A video file, paced at its frame rate (or source.fps) when realtime."""

    kind = "video"

    def __init__(self, cfg: SourceConfig, clock: Clock = time.monotonic_ns):
        super().__init__(cfg, clock)
        self.cap: cv2.VideoCapture | None = None
        self.pacer: _Pacer | None = None

    def open(self) -> None:
        cap = cv2.VideoCapture(self.cfg.path)
        if not cap.isOpened():
            raise SourceError(f"cannot open video {self.cfg.path} (missing, or a codec OpenCV lacks)")
        self.cap = cap
        self.width = int(cap.get(cv2.CAP_PROP_FRAME_WIDTH))
        self.height = int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
        self.fps = self.cfg.fps or float(cap.get(cv2.CAP_PROP_FPS) or 30.0)
        self.pacer = _Pacer(self.fps if self.cfg.realtime else 0.0)
        self.name = f"video {Path(self.cfg.path).name}"

    def read(self) -> tuple[np.ndarray, int]:
        if self.cap is None or self.pacer is None:
            raise SourceError("video is not open")
        ok, frame = self.cap.read()
        if not ok:
            if not self.cfg.loop:
                raise EndOfStream(self.cfg.path)
            self.cap.set(cv2.CAP_PROP_POS_FRAMES, 0)
            ok, frame = self.cap.read()
            if not ok:
                raise SourceError(f"video {self.cfg.path} yields no frames")
        self.pacer.wait()
        return to_grey(frame, f"video {self.cfg.path}"), self.clock() - self._offset_ns

    def close(self) -> None:
        if self.cap is not None:
            self.cap.release()
            self.cap = None


class ImageFolderSource(FrameSource):
    """Images of a folder in name order (png, pgm, bmp, jpg, tif)."""

    kind = "images"

    def __init__(self, cfg: SourceConfig, clock: Clock = time.monotonic_ns):
        super().__init__(cfg, clock)
        self.files: list[Path] = []
        self.i = 0
        self.pacer: _Pacer | None = None

    def open(self) -> None:
        folder = Path(self.cfg.path)
        if not folder.is_dir():
            raise SourceError(f"image folder {folder} does not exist")
        self.files = sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
        if not self.files:
            raise SourceError(f"image folder {folder} holds no images ({', '.join(IMAGE_SUFFIXES)})")
        first = cv2.imread(str(self.files[0]), cv2.IMREAD_GRAYSCALE)
        if first is None:
            raise SourceError(f"cannot read image {self.files[0]}")
        self.height, self.width = first.shape
        self.fps = self.cfg.fps or 30.0
        self.pacer = _Pacer(self.fps if self.cfg.realtime else 0.0)
        self.i = 0
        self.name = f"images {folder.name}"

    def read(self) -> tuple[np.ndarray, int]:
        if self.pacer is None:
            raise SourceError("image folder is not open")
        if self.i >= len(self.files):
            if not self.cfg.loop:
                raise EndOfStream(self.cfg.path)
            self.i = 0
        p = self.files[self.i]
        self.i += 1
        img = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise SourceError(f"cannot read image {p} (corrupt or not an image)")
        img = self._check_size(to_grey(img, f"image {p.name}"), f"image {p.name}")
        self.pacer.wait()
        return img, self.clock() - self._offset_ns


class SimSource(FrameSource):
    """IR images rendered from a simulated arena (visionpos.sim): the camera
    with this station's camera_id sees the scenario's markers at the time the
    frame is taken (scenario time loops over its duration).

    Realtime (the default), the scenario's time is a function of the frame's
    capture time on the shared clock alone: scenario start + (shared ns mod
    duration), the shared clock's 0 being the scenario's epoch. So station
    processes started at different times, on hosts with different clocks,
    render the same instant for the same capture time, as real cameras see
    one world. to_shared maps the station clock to the shared one (the
    agent's clock-sync estimate, StationAgent.to_server); without it the
    station clock is taken as shared (one host, or PTP-disciplined clocks).
    Until the clock is synced (to_shared gives None) a frame is rendered at
    its station-clock time; the agent does not send such frames.
    With realtime: false, scenario time advances one frame period per read.

    last_truth: (N, 2) true marker centres of the last frame (NaN = unseen);
    last_scenario_ns: the scenario time it shows.
    """

    kind = "sim"

    def __init__(self, cfg: SourceConfig, clock: Clock = time.monotonic_ns, camera_id: int = 0,
                 to_shared: ToShared | None = None):
        super().__init__(cfg, clock)
        self.camera_id = camera_id
        self.to_shared = to_shared
        self.last_scenario_ns = 0
        self.scenario = None
        self.camera = None
        self.last_truth = np.zeros((0, 2))

    def open(self) -> None:
        # imported here: a station loads the simulator only when configured with a sim source
        from visionpos.sim.scenario import load_scenario

        sc = load_scenario(self.cfg.scenario)
        cams = {c.id: c for c in sc.cameras}
        if self.camera_id not in cams:
            raise SourceError(f"simulated arena '{self.cfg.scenario}' has no camera {self.camera_id} "
                              f"(cameras: {sorted(cams)}); set camera_id")
        self.scenario, self.camera = sc, cams[self.camera_id]
        self.camera_kind = self.camera.model.kind
        self.width, self.height = self.camera.model.width, self.camera.model.height
        self.fps = self.cfg.fps or float(self.camera.fps or 30.0)
        self.pacer = _Pacer(self.fps if self.cfg.realtime else 0.0)
        self.rng = np.random.default_rng(self.cfg.seed)
        self.frame = 0
        self.name = f"sim {self.cfg.scenario} camera {self.camera_id}"

    def markers_world(self, true_ns: int) -> tuple[np.ndarray, np.ndarray]:
        """All simulated markers at scenario time true_ns: (N, 3) m and diameters (N,) m."""
        from scipy.spatial.transform import Rotation

        pts, diam = [], []
        for b in self.scenario.bodies:
            p, q = self.scenario.truth_at(b.name, np.array([true_ns], np.int64))
            pts.append(Rotation.from_quat(q[0]).apply(b.markers) + p[0])
            diam.append(np.full(len(b.markers), b.marker_diameter))
        if not pts:
            return np.zeros((0, 3)), np.zeros(0)
        return np.vstack(pts), np.concatenate(diam)

    def read(self) -> tuple[np.ndarray, int]:
        from visionpos.sim.render import render_camera_frame

        if self.scenario is None:
            raise SourceError("simulated source is not open")
        self.pacer.wait()
        t = self.clock()
        if self.cfg.realtime:
            shared = self.to_shared(t) if self.to_shared is not None else t
            elapsed = t if shared is None else shared
        else:  # as fast as possible: scenario time advances one frame period per read
            elapsed = int(self.frame * 1e9 / self.fps)
        self.frame += 1
        dur = max(int(self.scenario.duration_s * 1e9), 1)
        true_ns = self.scenario.start_ns + elapsed % dur
        self.last_scenario_ns = true_ns
        pts, diam = self.markers_world(true_ns)
        img, centers = render_camera_frame(self.camera, pts, diam, self.rng, peak_at_1m=self.scenario.peak_at_1m)
        self.last_truth = centers
        return img, t


SOURCES: dict[str, type[FrameSource]] = {
    "opencv": OpenCVSource,
    "picamera2": Picamera2Source,
    "video": VideoFileSource,
    "images": ImageFolderSource,
    "sim": SimSource,
}


def make_source(cfg: SourceConfig, clock: Clock = time.monotonic_ns, camera_id: int = 0,
                to_shared: ToShared | None = None) -> FrameSource:
    """The source for cfg.kind (not opened yet). to_shared: station clock -> shared clock (SimSource)."""
    if cfg.kind == "sim":
        return SimSource(cfg, clock, camera_id, to_shared)
    return SOURCES[cfg.kind](cfg, clock)
