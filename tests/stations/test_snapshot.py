"""`visionpos-station --snapshot`: frames for intrinsics calibration, kept only with a new view of the board."""

from pathlib import Path

import cv2
import numpy as np

from stations.cli import main
from visionpos.calibration.intrinsics import BoardSpec, pixel_rays, render_board
from visionpos.camera.model import CameraModel, look_at_rotation

MODEL = CameraModel("pinhole", 480, 360, 400.0, 400.0, 239.5, 179.5, [-0.1, 0.02, 0.0, 0.0, 0.0])
BOARD = BoardSpec("chessboard", 9, 7, 0.03)  # 8 x 6 inner corners


def _board_image(offset_xy, distance, rays):
    ctr = np.array([BOARD.cols / 2 * BOARD.square, BOARD.rows / 2 * BOARD.square, 0.0])
    C = ctr + np.array([offset_xy[0], offset_xy[1], -distance])
    R = look_at_rotation(C, C + [0.0, 0.0, distance], up=np.array([0, -1.0, 0]))  # the board off the image centre
    return render_board(MODEL, BOARD, R, -R @ C, rays=rays)


def test_snapshot_keeps_new_board_views_only(tmp_path, capsys):
    rays = pixel_rays(MODEL, 2)
    frames = tmp_path / "frames"
    frames.mkdir()
    views = [(-0.1, -0.06), (0.1, 0.06), (0.0, 0.0), (0.1, -0.06)]
    seq = []
    for k, v in enumerate(views):
        img = _board_image(v, 0.45, rays)
        seq += [img, img]  # the same view twice: the second is a duplicate
        seq.append(np.full_like(img, 40))  # no board at all
    for i, img in enumerate(seq):
        cv2.imwrite(str(frames / f"f{i:03d}.png"), img)
    (tmp_path / "station.yaml").write_text(
        "station_id: 1\ncamera_id: 3\nserver: {host: 127.0.0.1, port: 9}\ninsecure: true\n"
        "source: {kind: images, path: frames, fps: 100, loop: false}\n")
    out = tmp_path / "shots"
    rc = main(["--config", str(tmp_path / "station.yaml"), "--snapshot", str(out), "--count", "10",
               "--interval-s", "0", "--chessboard", "8x6"])
    text = capsys.readouterr().out
    assert rc == 0
    saved = sorted(Path(out).glob("cam3_*.png"))
    assert len(saved) == len(views)  # one per view: duplicates and empty frames skipped
    assert "board found; image covered" in text and "end of the source" in text
    got = cv2.imread(str(saved[1]), cv2.IMREAD_GRAYSCALE)
    np.testing.assert_array_equal(got, seq[3])  # lossless, the second view's first frame


def test_snapshot_without_a_board_saves_every_frame_at_the_interval(tmp_path):
    frames = tmp_path / "frames"
    frames.mkdir()
    for i in range(5):
        cv2.imwrite(str(frames / f"f{i}.png"), np.full((60, 80), 10 * i, np.uint8))
    (tmp_path / "station.yaml").write_text(
        "station_id: 1\ncamera_id: 4\nserver: {host: 127.0.0.1, port: 9}\ninsecure: true\n"
        "source: {kind: images, path: frames, loop: false}\n")
    rc = main(["--config", str(tmp_path / "station.yaml"), "--snapshot", str(tmp_path / "s"), "--count", "3",
               "--interval-s", "0"])
    assert rc == 0 and len(list((tmp_path / "s").glob("cam4_*.png"))) == 3
    assert main(["--config", str(tmp_path / "station.yaml"), "--snapshot", str(tmp_path / "s"),
                 "--chessboard", "9"]) == 2
