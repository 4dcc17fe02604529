"""Start and stop a recording from the console: {"cmd": "record", "on": true | false} (docs/console.md).

A start opens a RecordingWriter on a new file in `console.record_dir`, named by the local time it
started (visionpos-YYYYMMDD-HHMMSS.mcap; -2, -3 ... when that name is taken), and hands it to the
fusion server (FusionServer.start_recording): from then on every accepted packet, event, health
snapshot and output goes into it, as with `serve --record`. A stop detaches it from the server
first (FusionServer.detach_recording), then closes it in a worker thread (summary, footer, fsync):
everything handed to it before is in the file. Refused with the reason, changing nothing: in a
replay or `visionpos record` (their source cannot start one), a start while one records (the
console's or `--record`'s), a stop while none does, a folder that cannot be made or a file that
cannot be created.
"""

from __future__ import annotations

import asyncio
import time
from pathlib import Path
from typing import Any

NAME_FORMAT = "visionpos-%Y%m%d-%H%M%S"


def recording_name(folder: Path, local_time: time.struct_time) -> Path:
    """The first free path folder/visionpos-YYYYMMDD-HHMMSS[-N].mcap for local_time."""
    stem = time.strftime(NAME_FORMAT, local_time)
    path, n = folder / f"{stem}.mcap", 1
    while path.exists():
        n += 1
        path = folder / f"{stem}-{n}.mcap"
    return path


class ConsoleRecorder:
    """The record button's server side for `source` (a FusionServer; anything without start_recording, such as
    a replay session or `record`'s RecordSource, refuses). folder: console.record_dir."""

    def __init__(self, source: Any, folder: str | Path, clock: Any = time.monotonic_ns):
        self.source = source
        self.folder = Path(folder)
        self.clock = clock
        self.last: dict[str, Any] | None = None  # the last recording stopped here: file, bytes, messages
        self._busy = False  # a stop is closing a file

    @property
    def available(self) -> bool:
        return hasattr(self.source, "start_recording")

    def state(self) -> dict[str, Any] | None:
        """The recording now: {"file", "path", "bytes" (on disk), "duration_s"}, or None."""
        rec = getattr(self.source, "recorder", None)
        if rec is None:
            return None
        return {"file": rec.path.name, "path": str(rec.path), "bytes": rec.bytes_written,
                "duration_s": round((self.clock() - rec.opened_monotonic_ns) / 1e9, 1)}

    async def command(self, msg: dict[str, Any]) -> dict[str, Any]:
        """Start (on: true) or stop (on: false); the reply {"recording": state, "stopped": ...}. ValueError: why
        refused (nothing changed)."""
        on = msg.get("on")
        if not isinstance(on, bool):
            raise ValueError('record: expected {"cmd": "record", "on": true or false}')
        if not self.available:
            raise ValueError("record: this console cannot record (a replay reads a recording; `visionpos record` "
                             "records from its start to its end)")
        if self._busy:
            raise ValueError("record: the last recording is still being closed; try again in a moment")
        if on:
            self._start()
            return {"recording": self.state(), "stopped": None}
        return {"recording": None, "stopped": await self._stop()}

    def _start(self) -> None:
        from visionpos.recording import RecordingWriter
        from visionpos.recording.codec import RecordingError

        current = self.source.recorder
        if current is not None:
            raise ValueError(f"record: already recording to {current.path.name}; stop it first")
        try:
            self.folder.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise ValueError(f"record: cannot make the folder {self.folder} (console.record_dir): "
                             f"{e.strerror or e}") from None
        path = recording_name(self.folder, time.localtime())
        arena = self.source.arena
        try:
            writer = RecordingWriter(path, arena.to_dict(), {"command": "console", "config_path": arena.source})
        except RecordingError as e:
            raise ValueError(f"record: {e} (console.record_dir)") from None
        self.source.start_recording(writer)

    async def _stop(self) -> dict[str, Any]:
        try:
            rec = self.source.detach_recording()
        except ValueError:
            raise ValueError("record: not recording") from None
        self._busy = True
        try:  # the footer and fsync off the loop: fusion goes on meanwhile
            await asyncio.get_running_loop().run_in_executor(None, rec.close)
        finally:
            self._busy = False
        s = rec.stats()
        self.last = {"file": rec.path.name, "path": str(rec.path), "bytes": rec.path.stat().st_size,
                     "messages": s["messages"], "dropped": s["dropped"], "error": s["error"]}
        return self.last
