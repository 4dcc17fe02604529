"""The camera monitor's corrected pose written to the arena file (console/arena_file.py): the file gets the pose,
a backup keeps the old one; a refused write changes nothing."""

from __future__ import annotations

import numpy as np
import pytest
import yaml

from console.arena_file import write_monitored_pose
from visionpos.config.arena import load_yaml, parse_arena
from visionpos.fusion.camera_monitor import apply_correction
from visionpos.server.service import FusionServer
from visionpos.server.settings import ServerSettings


def _server(tmp_path, arena_yaml):
    data = arena_yaml("thesis")
    path = tmp_path / "arena.yaml"
    path.write_text("# the lab's arena\n" + yaml.safe_dump(data, sort_keys=False))
    arena = parse_arena(data, str(path))
    return FusionServer(arena, ServerSettings.for_replay(arena), port=0), path


def test_the_corrected_pose_goes_into_the_arena_file_and_the_old_file_into_a_backup(tmp_path, arena_yaml):
    server, path = _server(tmp_path, arena_yaml)
    old = path.read_bytes()
    watch = server.monitor.cams[2]
    # what the monitor's _correct does to a knocked camera: 0.5 deg about its x axis, 1 cm along its z
    corrected = apply_correction(watch.camera, np.array([np.radians(0.5), 0.0, 0.0, 0.0, 0.0, 0.01]))
    watch.camera, watch.corrections = corrected, 1
    reply = write_monitored_pose(server, {"cmd": "write_pose", "camera": 2})
    assert reply["camera"] == 2 and reply["file"] == str(path.resolve())
    written = parse_arena(load_yaml(path), str(path)).camera_by_id()
    np.testing.assert_allclose(written[2].R, corrected.R, atol=1e-9)
    np.testing.assert_allclose(written[2].center, corrected.center, atol=1e-9)
    before = server.arena.camera_by_id()
    assert not np.allclose(written[2].center, before[2].center, atol=1e-3)
    for cid in (1, 3, 4):  # the others as they were
        np.testing.assert_allclose(written[cid].center, before[cid].center, atol=1e-12)
    backup = tmp_path / reply["backup"].rsplit("/", 1)[1]
    assert backup.name.startswith("arena.yaml.bak-") and backup.read_bytes() == old


def test_a_refused_write_changes_nothing(tmp_path, arena_yaml):
    server, path = _server(tmp_path, arena_yaml)
    old = path.read_bytes()
    for msg, why in (({"cmd": "write_pose", "camera": 2}, "has no corrected pose"),  # not corrected
                     ({"cmd": "write_pose", "camera": 9}, "none of the monitored cameras"),
                     ({"cmd": "write_pose", "camera": "2"}, "expected")):
        with pytest.raises(ValueError, match=why):
            write_monitored_pose(server, msg)
    server.monitor.cams[3].corrections, server.monitor.cams[3].unsolvable = 1, "too few pairs"
    with pytest.raises(ValueError, match="could not be corrected"):
        write_monitored_pose(server, {"cmd": "write_pose", "camera": 3})

    class Replay:  # no monitor: a replay session, `record`
        arena = server.arena

    with pytest.raises(ValueError, match="no camera monitor"):
        write_monitored_pose(Replay(), {"cmd": "write_pose", "camera": 2})
    assert path.read_bytes() == old and sorted(p.name for p in tmp_path.iterdir()) == ["arena.yaml"]
