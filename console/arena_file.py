"""The camera monitor's corrected pose written to the arena file (docs/console.md, "Camera moved"):
{"cmd": "write_pose", "camera": id}, sent by the page after the operator confirmed it.

The server's camera monitor (visionpos/fusion/camera_monitor.py) corrects a knocked camera's pose in
the running pipeline only; this writes the pose it has now into the arena file the server started
with (its `cameras[i].pose`, nothing else of the file changes but its comments and layout, which the
backup keeps): first a copy of the old file beside it (ARENA.yaml.bak-YYYYMMDD-HHMMSS), then the new
file through a temporary one and a rename, so a crash leaves the old file or the new one. Refused
with the reason, changing nothing: a source without a camera monitor (a replay, `record`, a server
with camera_monitor off), a camera the monitor does not watch or has not corrected, one it could not
solve, an arena that is no file on disk or is one of the package's built-in arenas.
"""

from __future__ import annotations

import os
import shutil
import time
from pathlib import Path
from typing import Any

import visionpos
from visionpos.config.arena import ConfigError, dump_yaml, load_yaml

BUILTIN = Path(visionpos.__file__).resolve().parent


def write_camera_pose(arena_path: str | Path, camera_id: int, pose: dict[str, Any],
                      local_time: time.struct_time | None = None) -> Path:
    """Replace cameras[i].pose of the camera with id camera_id in the arena file by pose (Camera.to_dict()'s
    "pose"); returns the backup of the old file. ValueError (the file untouched) when the file has no such
    camera or cannot be read or written."""
    return write_camera_poses(arena_path, {camera_id: pose}, local_time=local_time, what="write pose")


def write_camera_poses(arena_path: str | Path, poses: dict[int, dict[str, Any]],
                       extrinsics: dict[str, Any] | None = None, local_time: time.struct_time | None = None,
                       what: str = "apply") -> Path:
    """Replace cameras[i].pose of each camera id in poses (Camera.to_dict()'s "pose") in the arena file, and
    calibration.extrinsics by `extrinsics` where given (the solve's report); returns the backup of the old file.
    ValueError (the file untouched), its text starting with `what`, when the file lacks one of the cameras or
    cannot be read or written."""
    path = Path(arena_path)
    try:
        data = load_yaml(path)
    except (OSError, ConfigError) as e:
        raise ValueError(f"{what}: cannot read the arena file {path}: {e}") from None
    cams = data.get("cameras") if isinstance(data, dict) else None
    for camera_id, pose in poses.items():
        idx = [i for i, c in enumerate(cams or []) if isinstance(c, dict) and c.get("id") == camera_id]
        if len(idx) != 1:
            raise ValueError(f"{what}: {path} has no single camera with id {camera_id}")
        cams[idx[0]]["pose"] = pose
    if extrinsics is not None:
        cal = data.get("calibration") if isinstance(data.get("calibration"), dict) else {}
        cal["extrinsics"] = extrinsics
        data["calibration"] = cal
    stamp = time.strftime("%Y%m%d-%H%M%S", local_time or time.localtime())
    backup, n = path.with_name(f"{path.name}.bak-{stamp}"), 1
    while backup.exists():
        n += 1
        backup = path.with_name(f"{path.name}.bak-{stamp}-{n}")
    tmp = path.with_name(f".{path.name}.writing")
    try:
        shutil.copy2(path, backup)
        dump_yaml(data, tmp)
        os.replace(tmp, path)
    except OSError as e:
        tmp.unlink(missing_ok=True)
        raise ValueError(f"{what}: cannot write {path}: {e.strerror or e}") from None
    return backup


def writable_arena(source: str, what: str) -> Path:
    """The arena file a server started with, resolved; ValueError (starting with `what`) when it is no file on
    disk or one of the package's built-in arenas (never rewritten: start from a copy)."""
    path = Path(source).resolve()
    if not path.is_file():
        raise ValueError(f"{what}: the arena {source} is no file on disk")
    if BUILTIN in path.parents:
        raise ValueError(f"{what}: {path.name} is a built-in arena; copy it, start from the copy, and write there")
    return path


def write_monitored_pose(source: Any, msg: dict[str, Any]) -> dict[str, Any]:
    """The console command: the monitor's corrected pose of msg["camera"] into source.arena's file; the reply
    {"camera", "file", "backup", "pose"}. ValueError: why refused (nothing written)."""
    cid = msg.get("camera")
    if isinstance(cid, bool) or not isinstance(cid, int):
        raise ValueError('write pose: expected {"cmd": "write_pose", "camera": ID}')
    monitor = getattr(source, "monitor", None)
    if monitor is None:
        raise ValueError("write pose: no camera monitor here (it runs in `serve` and `demo` with camera_monitor "
                         "enabled)")
    watch = monitor.cams.get(cid)
    if watch is None:
        raise ValueError(f"write pose: camera {cid} is none of the monitored cameras {sorted(monitor.cams)}")
    if watch.unsolvable:
        raise ValueError(f"write pose: camera {cid} could not be corrected ({watch.unsolvable}); recalibrate it")
    if watch.corrections == 0:
        raise ValueError(f"write pose: camera {cid} has no corrected pose (the monitor has not corrected it)")
    path = writable_arena(source.arena.source, "write pose")
    pose = watch.camera.to_dict()["pose"]
    backup = write_camera_pose(path, cid, pose)
    return {"camera": cid, "file": str(path), "backup": str(backup), "pose": pose}
