"""The console's calibration assistant: a wand wave's coverage filling in live, and the wand solve on demand.

Fed every accepted frame (`push`, from `visionpos record`'s RecordSource or a `replay --view`
session): one list append, nothing else on the per-packet path, up to MAX_FRAMES frames (then the
wave is full and says so). Every REFRESH_S a worker thread labels the frames that came since the
last refresh and recounts coverage and pairs (visionpos/calibration/coverage.py, the solver's own
labeller and time alignment); the console sends the summary when it changed.

"solve" (a console command) runs the wand solve (workflow.solve_wand_to_file, as `visionpos
calibrate wand` does) on every frame gathered so far in a child process, so neither the event loop
nor the packets wait for it, writes the calibrated arena to `out_path` and shows the result:
residuals per camera (px), the wand-length error (mm), clock offsets (ms), the solver's warnings,
or why it could not solve. A solve while one runs, or before the solver's minimums are met, is
refused and changes nothing.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import logging
import multiprocessing
from pathlib import Path
from typing import Any

from visionpos.calibration.coverage import Thresholds, WandCoverage
from visionpos.calibration.wand import MIN_WAND_FRAMES, CalibrationError
from visionpos.calibration.workflow import solve_wand_to_file, wand_settings
from visionpos.config.arena import ArenaConfig
from visionpos.messages import BlobFrame

log = logging.getLogger(__name__)

REFRESH_S = 0.5  # coverage recount period (labels the newest half second: wand.label_camera's static-blob check)
MAX_FRAMES = 200_000  # frames kept for the solve (about 8 min of 4 cameras at 100 Hz; a wave takes 1 to 2)


class CalibrationAssistant:
    """A live wand wave for the console. out_path: where "solve" writes the calibrated arena YAML."""

    def __init__(self, arena: ArenaConfig, out_path: str | Path, thresholds: Thresholds = Thresholds(),
                 max_frames: int = MAX_FRAMES, pool: concurrent.futures.Executor | None = None):
        self.arena = arena
        self.out_path = Path(out_path)
        self.spec, self.max_offset_ms = wand_settings(arena)
        self.thresholds = thresholds
        self.max_frames = max_frames
        self.frames: list[BlobFrame] = []
        self.over = 0  # frames refused because the wave is full
        self.version = 0  # bumps whenever state() changes
        self.solve: dict[str, Any] = {"running": False, "result": None, "error": None}
        self._cov = WandCoverage(arena.cameras, self.spec, thresholds)
        self._done = 0  # frames labelled so far
        self._generation = 0  # a reset makes a running refresh's result stale
        self._summary = self._cov.summary()
        self._task: asyncio.Task | None = None
        self._solving: asyncio.Task | None = None
        self._pool = pool  # where the solve runs; None: a spawned child process, made at the first solve
        self._own_pool = pool is None
        self._refreshing = asyncio.Lock()

    # ---------------------------------------------------------------- feed (per packet)

    def push(self, frame: BlobFrame) -> None:
        if len(self.frames) < self.max_frames:
            self.frames.append(frame)
        else:
            self.over += 1

    def reset(self) -> None:
        """Forget the wave (a replay seeking back feeds it again)."""
        self.frames = []
        self.over = 0
        self._done = 0
        self._generation += 1
        self._cov = WandCoverage(self.arena.cameras, self.spec, self.thresholds)
        self._summary = self._cov.summary()
        self.version += 1

    # ---------------------------------------------------------------- lifecycle

    def start(self) -> None:
        """Start the refresh task on the running loop."""
        self._task = asyncio.get_running_loop().create_task(self._refresh_loop(), name="visionpos-calibration")

    async def stop(self) -> None:
        for t in (self._task, self._solving):
            if t is not None:
                t.cancel()
                try:
                    await t
                except (asyncio.CancelledError, Exception):
                    pass
        self._task = self._solving = None
        if self._pool is not None and self._own_pool:
            self._pool.shutdown(wait=False, cancel_futures=True)
            self._pool = None

    async def _refresh_loop(self) -> None:
        loop = asyncio.get_running_loop()
        while True:
            await asyncio.sleep(REFRESH_S)
            await self.refresh(loop)

    async def refresh(self, loop: asyncio.AbstractEventLoop | None = None) -> None:
        """Label the frames that came since the last refresh and recount, in a worker thread."""
        loop = loop or asyncio.get_running_loop()
        async with self._refreshing:  # one at a time: a chunk is counted once (the loop's and a solve's)
            n = len(self.frames)
            if n == self._done:
                return
            chunk, gen, cov = self.frames[self._done:n], self._generation, self._cov
            try:
                summary = await loop.run_in_executor(None, _label_and_count, cov, chunk)
            except Exception:
                log.exception("calibration assistant: counting the wand frames failed")
                return
            if gen != self._generation:  # reset meanwhile
                return
            self._done = n
            self._summary = summary
            self.version += 1

    # ---------------------------------------------------------------- the console's face

    def state(self) -> dict[str, Any]:
        """JSON-ready: the coverage summary (coverage.WandCoverage.summary), the frames kept, the solve."""
        return {**self._summary, "frames_kept": len(self.frames), "frames_over": self.over,
                "max_frames": self.max_frames, "out": str(self.out_path), "solve": dict(self.solve)}

    async def command(self, msg: dict[str, Any]) -> dict[str, Any]:
        """{"cmd": "solve"}: start the wand solve; ValueError (answered by the console, nothing changed) when one
        runs or the frames cannot meet the solver's minimums yet."""
        if msg.get("cmd") != "solve" or set(msg) != {"cmd"}:
            raise ValueError('calibration: expected {"cmd": "solve"}')
        if self.solve["running"]:
            raise ValueError("solve: a solve is running; wait for its result")
        await self.refresh()
        s = self._summary
        if not s["solvable"]:
            few = [f"{c['name']} {c['labelled']}" for c in s["cameras"] if c["labelled"] < MIN_WAND_FRAMES]
            raise ValueError(
                f"solve: not enough wand frames for the solver yet (it needs {MIN_WAND_FRAMES} per camera and "
                f"{MIN_WAND_FRAMES} time steps with the wand in two cameras; have {s['steps']} steps"
                + (f"; cameras with too few: {', '.join(few)}" if few else "") + ")")
        self.solve = {"running": True, "result": None, "error": None, "frames": len(self.frames)}
        self.version += 1
        frames = list(self.frames)
        self._solving = asyncio.get_running_loop().create_task(self._run_solve(frames), name="visionpos-wand-solve")
        return {"solve": "started", "frames": len(frames), "out": str(self.out_path)}

    async def _run_solve(self, frames: list[BlobFrame]) -> None:
        loop = asyncio.get_running_loop()
        if self._pool is None:  # a fresh interpreter: no fork of a process with a loop and threads
            self._pool = concurrent.futures.ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn"))
        try:
            result = await loop.run_in_executor(self._pool, *self._job(frames))
            self.solve = {"running": False, "result": self._accept(result), "error": None, "frames": len(frames)}
            log.info("calibration assistant: wand solve written to %s", self.out_path)
        except CalibrationError as e:
            self.solve = {"running": False, "result": None, "error": str(e), "frames": len(frames)}
        except Exception as e:  # a broken child, a full disk: said on the page, logged with its traceback
            log.exception("calibration assistant: the wand solve failed")
            self.solve = {"running": False, "result": None, "error": f"{type(e).__name__}: {e}",
                          "frames": len(frames)}
        self.version += 1


    def _job(self, frames: list[BlobFrame]) -> tuple[Any, ...]:
        """The solve's function and arguments, run in the pool (picklable)."""
        return solve_wand_to_file, frames, self.arena, self.spec, self.max_offset_ms, str(self.out_path)

    def _accept(self, result: Any) -> dict[str, Any]:
        """The JSON-ready result shown from what the job returned."""
        return result


def _label_and_count(cov: WandCoverage, chunk: list[BlobFrame]) -> dict[str, Any]:
    cov.add_frames(chunk)
    return cov.summary()


def default_out(recording: str | Path) -> Path:
    """Where "solve" writes when no path was given: beside the recording, wand.mcap -> wand.calibrated.yaml."""
    p = Path(recording)
    return p.with_name(p.stem + ".calibrated.yaml")
