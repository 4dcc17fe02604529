"""console.stations: each station's search area (mask image, rois, ignore) shown in its camera view."""

from __future__ import annotations

import base64

import numpy as np
import pytest
import yaml

from console.settings import parse_console
from visionpos.app.console import station_masks
from visionpos.config.arena import ConfigError, parse_arena


def _decode(data_url: str) -> np.ndarray:
    import cv2

    raw = base64.b64decode(data_url.split(",", 1)[1])
    return cv2.imdecode(np.frombuffer(raw, np.uint8), cv2.IMREAD_GRAYSCALE)


def test_station_files_give_each_camera_its_rois_ignore_and_mask(tmp_path, arena_yaml):
    import cv2

    data = arena_yaml("thesis")
    cam = data["cameras"][1]
    w, h = cam["width"], cam["height"]
    mask = np.full((h, w), 255, np.uint8)
    mask[:, : w // 2] = 0  # the left half is never searched
    cv2.imwrite(str(tmp_path / "mask2.png"), mask)
    (tmp_path / "st1.yaml").write_text(yaml.safe_dump({"camera_id": data["cameras"][0]["id"], "detector": {
        "rois": [[10, 20, 400, 300]], "ignore": [[50, 60, 70, 80]]}}))
    (tmp_path / "st2.yaml").write_text(yaml.safe_dump({"camera_id": cam["id"], "detector": {"mask": "mask2.png"}}))
    data["console"] = {"stations": ["st1.yaml", "st2.yaml"]}
    arena = parse_arena(data, str(tmp_path / "arena.yaml"))
    settings = parse_console(arena)
    masks = station_masks(arena, settings.stations)
    first, second = masks[data["cameras"][0]["id"]], masks[cam["id"]]
    assert first["rois"] == [[10, 20, 400, 300]] and first["ignore"] == [[50, 60, 70, 80]]
    m1 = _decode(first["mask_png"])
    s = m1.shape[1] / data["cameras"][0]["width"]
    assert m1[int(100 * s), int(200 * s)] == 255  # inside the ROI
    assert m1[int(70 * s), int(60 * s)] == 0 and m1[int(400 * s), int(450 * s)] == 0  # ignored; outside the ROI
    m2 = _decode(second["mask_png"])
    assert m2[:, : m2.shape[1] // 2 - 1].max() == 0 and m2[:, m2.shape[1] // 2 + 1:].min() == 255


def test_a_station_file_of_no_arena_camera_is_refused(tmp_path, arena_yaml):
    data = arena_yaml("thesis")
    (tmp_path / "st9.yaml").write_text(yaml.safe_dump({"camera_id": 99, "detector": {}}))
    data["console"] = {"stations": ["st9.yaml"]}
    arena = parse_arena(data, str(tmp_path / "arena.yaml"))
    with pytest.raises(ConfigError, match="camera_id"):
        station_masks(arena, parse_console(arena).stations)
    data["console"] = {"stations": "st9.yaml"}
    with pytest.raises(ConfigError, match="console.stations"):
        parse_console(parse_arena(data, str(tmp_path / "arena.yaml")))
