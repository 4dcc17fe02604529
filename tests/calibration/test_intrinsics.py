"""Intrinsics from rendered board images with a known camera."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import yaml

from visionpos.calibration.intrinsics import (
    BoardSpec,
    calibrate_images,
    detect_corners,
    pixel_rays,
    render_board,
    select_views,
)
from visionpos.calibration.wand import CalibrationError
from visionpos.camera.model import CameraModel, look_at_rotation

PINHOLE_TRUE = CameraModel("pinhole", 480, 360, 400.0, 398.0, 243.0, 178.0, [-0.22, 0.06, 0.0004, -0.0003, 0.0])
FISHEYE_TRUE = CameraModel("fisheye", 480, 360, 230.0, 230.5, 238.0, 182.0, [0.04, -0.01, 0.002, -0.0005])


def _views(model, board, n, seed, dist=(0.28, 0.5)):
    rng = np.random.default_rng(seed)
    rays = pixel_rays(model, 2)
    ctr = np.array([board.cols / 2 * board.square, board.rows / 2 * board.square, 0.0])
    out = []
    for k in range(n):
        C = ctr + np.array([rng.uniform(-0.3, 0.3), rng.uniform(-0.25, 0.25), -rng.uniform(*dist)])
        tgt = ctr + np.array([rng.uniform(-0.08, 0.08), rng.uniform(-0.06, 0.06), 0])
        R = look_at_rotation(C, tgt, up=np.array([0, -1.0, 0]))
        out.append((f"view{k:02d}.png", render_board(model, board, R, -R @ C, rays=rays)))
    return out


def _max_mapping_error(a: CameraModel, b: CameraModel, pixels: np.ndarray) -> float:
    """Largest pixel difference between the two models where the board was seen: the ray of
    each pixel under model a, projected by model b."""
    return float(np.abs(b.project_camera(a.rays(pixels)) - pixels).max())


@pytest.fixture(scope="module")
def chess_images():
    board = BoardSpec("chessboard", 9, 7, 0.03)
    return board, _views(PINHOLE_TRUE, board, 16, seed=0)


def test_pinhole_chessboard_recovers_intrinsics(chess_images):
    board, images = chess_images
    res = calibrate_images(images, board, "pinhole")
    m = res.model
    assert res.rms_px < 0.2
    assert abs(m.fx / PINHOLE_TRUE.fx - 1) < 0.01 and abs(m.fy / PINHOLE_TRUE.fy - 1) < 0.01
    assert abs(m.cx - PINHOLE_TRUE.cx) < 3 and abs(m.cy - PINHOLE_TRUE.cy) < 3
    assert abs(m.dist[0] - PINHOLE_TRUE.dist[0]) < 0.02
    assert _max_mapping_error(PINHOLE_TRUE, m, np.concatenate(res.pixels)) < 1.0


def test_fisheye_chessboard_recovers_mapping():
    board = BoardSpec("chessboard", 9, 7, 0.03)
    images = _views(FISHEYE_TRUE, board, 14, seed=2, dist=(0.18, 0.35))
    res = calibrate_images(images, board, "fisheye")
    assert res.model.kind == "fisheye"
    assert res.rms_px < 0.2
    assert abs(res.model.fx / FISHEYE_TRUE.fx - 1) < 0.01
    assert abs(res.model.cx - FISHEYE_TRUE.cx) < 2 and abs(res.model.cy - FISHEYE_TRUE.cy) < 2
    assert _max_mapping_error(FISHEYE_TRUE, res.model, np.concatenate(res.pixels)) < 1.0


def test_charuco_pinhole():
    board = BoardSpec("charuco", 9, 7, 0.03, 0.022)
    images = _views(PINHOLE_TRUE, board, 12, seed=3)
    res = calibrate_images(images, board, "pinhole")
    assert len(res.views) >= 8
    assert res.rms_px < 0.4  # ChArUco corners in these small renders are less precise than SB chessboard corners
    assert abs(res.model.fx / PINHOLE_TRUE.fx - 1) < 0.015
    assert _max_mapping_error(PINHOLE_TRUE, res.model, np.concatenate(res.pixels)) < 1.5


def test_view_selection_drops_duplicates(chess_images):
    board, images = chess_images
    dets = [detect_corners(img, board, name) for name, img in images]
    dets = [d for d in dets if d is not None]
    doubled = dets + dets  # the same poses twice
    sel = select_views(doubled, board, (480, 360), max_views=100)
    assert len(sel) == len(dets)
    assert len(select_views(doubled, board, (480, 360), max_views=5)) == 5


def test_too_few_views_is_an_error(chess_images):
    board, images = chess_images
    with pytest.raises(CalibrationError, match="distinct board views"):
        calibrate_images(images[:4], board, "pinhole")


def test_cli_intrinsics_writes_yaml_plot_and_rescaled_mode(chess_images, tmp_path, capsys):
    from visionpos.cli import main

    board, images = chess_images
    d = tmp_path / "imgs"
    d.mkdir()
    for name, img in images:
        cv2.imwrite(str(d / name), img)
    out = tmp_path / "cam.yaml"
    plot = tmp_path / "cov.png"
    rc = main(["calibrate", "intrinsics", "--images", str(d), "--board", "chessboard", "--inner-corners", "8x6",
               "--square", "0.03", "--model", "pinhole", "--out", str(out), "--plot", str(plot),
               "--rescale", "240x180"])
    assert rc == 0
    y = yaml.safe_load(out.read_text())
    m = CameraModel.from_dict(y)
    assert abs(m.fx / PINHOLE_TRUE.fx - 1) < 0.01
    half = CameraModel.from_dict(y["modes"][0])
    assert (half.width, half.height) == (240, 180)
    assert abs(half.fx - m.fx / 2) < 1e-9
    assert plot.stat().st_size > 1000
    assert "RMS reprojection error" in capsys.readouterr().out


@pytest.fixture(scope="module")
def chess_dir(chess_images, tmp_path_factory):
    d = tmp_path_factory.mktemp("chess")
    for name, img in chess_images[1]:
        cv2.imwrite(str(d / name), img)
    return d


@pytest.mark.parametrize("size", [["--squares", "9x7"], ["--cols", "9", "--rows", "7"]])
def test_cli_board_size_as_squares_too(chess_dir, tmp_path, size):
    from visionpos.cli import main

    out = tmp_path / "cam.yaml"
    assert main(["calibrate", "intrinsics", "--images", str(chess_dir), *size, "--square", "0.03",
                 "--out", str(out), "--no-progress"]) == 0
    assert abs(CameraModel.from_dict(yaml.safe_load(out.read_text())).fx / PINHOLE_TRUE.fx - 1) < 0.01


def test_cli_squares_given_as_inner_corners_names_the_right_count(chess_dir, tmp_path, capsys):
    from visionpos.cli import main

    # the board has 9x7 squares = 8x6 inner corners; a user who counted squares types 9x7
    rc = main(["calibrate", "intrinsics", "--images", str(chess_dir), "--inner-corners", "9x7", "--square", "0.03",
               "--out", str(tmp_path / "cam.yaml"), "--no-progress"])
    err = capsys.readouterr().err
    assert rc == 2
    assert "no chessboard with 9x7 inner corners" in err and "use --inner-corners 8x6" in err
    assert not (tmp_path / "cam.yaml").exists()


def test_cli_checks_rescale_before_the_solve(chess_dir, tmp_path, capsys, monkeypatch):
    import visionpos.calibration.intrinsics as intr
    from visionpos.cli import main

    def never(*a, **k):
        raise AssertionError("the solve ran before the options were checked")

    monkeypatch.setattr(intr, "calibrate_images", never)
    rc = main(["calibrate", "intrinsics", "--images", str(chess_dir), "--inner-corners", "8x6", "--square", "0.03",
               "--out", str(tmp_path / "cam.yaml"), "--rescale", "240x120+0x0"])
    err = capsys.readouterr().err
    assert rc == 2 and "changes the aspect ratio" in err and "the crop that keeps it is 0x60" in err


def test_capture_mode_crops_to_keep_the_aspect_ratio():
    from visionpos.calibration.intrinsics import CaptureMode, capture_mode

    # the help text's example: 640x360 from 1280x960 images = resize to 640x480, crop 120 rows
    assert capture_mode("640x360", (1280, 960)) == CaptureMode(640, 360, (0.0, 120.0))
    assert capture_mode("640x360+0x120", (1280, 960)) == CaptureMode(640, 360, (0.0, 120.0))
    assert capture_mode("640x480", (1280, 960)) == CaptureMode(640, 480, (0.0, 0.0))
    m = capture_mode("640x360", (1280, 960)).apply(PINHOLE_TRUE.rescale(1280, 960))
    assert (m.width, m.height) == (640, 360)
    with pytest.raises(CalibrationError, match="expected WxH"):
        capture_mode("640by480", (1280, 960))


def test_warnings_for_a_fisheye_fit_of_a_narrow_lens(chess_images):
    from visionpos.calibration.intrinsics import model_warnings

    board, images = chess_images
    fish = calibrate_images(images, board, "fisheye")
    assert any("fisheye model" in w and "--model pinhole" in w for w in model_warnings(fish))
    pin = calibrate_images(images, board, "pinhole")
    assert not any("fisheye" in w for w in model_warnings(pin))


def test_progress_without_a_terminal_prints_whole_lines():
    import io

    from visionpos.calibration.report import progress_printer

    buf = io.StringIO()  # not a tty, like a log file
    show = progress_printer(True, buf)
    for i in range(1, 51):
        show("corners", i, 50)
    text = buf.getvalue()
    assert "\r" not in text
    lines = text.splitlines()
    assert lines[0] == "corners: 1/50 (0 %)" and lines[-1] == "corners: 50/50 (100 %)" and len(lines) == 11
