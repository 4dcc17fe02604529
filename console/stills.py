"""The console's station commands: a still image from a camera's station, and its mask saved back.

    {"cmd": "still", "camera": id}                  -> {"type": "still", "camera", "jpeg" (data URL), "width",
                                                        "height", "capture_ns", "background", "hint"} or with "error"
    {"cmd": "mask", "camera": id, "ignore": [[x0, y0, x1, y1], ...]}
                                                    -> {"type": "mask", "camera", "ok", "saved", "text", "mask"}

Both go to the station over the station protocol (visionpos/server/images.py: IMAGE_REQUEST, MASK_UPDATE) and
run as their own task, so the client's other commands and the updates go on meanwhile; the answer is sent to
the asking client only. Every field is checked before anything is sent. They change station settings, so like
everything else on the console they need its token when it is bound off loopback (console/server.py).
"""

from __future__ import annotations

import asyncio
import base64
import json
from typing import Any

from visionpos import protocol as P

BACKGROUND_GOAL_DN = 20.0  # docs/stations.md: lower the exposure until the background reads below about 20
STILL_WIDTH_PX = 640  # the JPEG's width the console asks for
STILL_QUALITY = 80


def background_hint(level: float) -> str:
    """The plain-language read-out of a station's background level (grey levels 0..255)."""
    if level < BACKGROUND_GOAL_DN:
        return f"background {level:.0f}: below {BACKGROUND_GOAL_DN:.0f}, exposure is fine"
    return f"background {level:.0f}: lower exposure until below {BACKGROUND_GOAL_DN:.0f}"


def _rects(value: Any, width: int, height: int) -> list[list[int]]:
    """The command's rectangles, checked: a list of at most MAX_MASK_RECTS [x0, y0, x1, y1] integers inside
    the camera's width x height. Raises ValueError saying what is wrong."""
    if not isinstance(value, list) or len(value) > P.MAX_MASK_RECTS:
        raise ValueError(f"mask: ignore must be a list of at most {P.MAX_MASK_RECTS} [x0, y0, x1, y1]")
    out = []
    for r in value:
        if (not isinstance(r, list) or len(r) != 4
                or not all(isinstance(v, int) and not isinstance(v, bool) for v in r)):
            raise ValueError(f"mask: {r!r} is not [x0, y0, x1, y1] in whole pixels")
        x0, y0, x1, y1 = r
        if not (0 <= x0 < x1 <= width and 0 <= y0 < y1 <= height):
            raise ValueError(f"mask: rectangle {r} is not inside the camera's {width}x{height} image")
        out.append([x0, y0, x1, y1])
    return out


class StationCommands:
    """The "still" and "mask" commands of a ConsoleServer (its view's cameras, its source's Ingest)."""

    def __init__(self, console: Any):
        self.console = console
        self.tasks: set[asyncio.Task] = set()

    def _images(self) -> Any:
        ingest = getattr(self.console.source, "ingest", None)
        images = getattr(ingest, "images", None)
        if images is None:
            raise ValueError("still images and masks need a live server with stations (not a replay)")
        return images

    def _camera(self, msg: dict[str, Any]) -> dict[str, Any]:
        cam = msg.get("camera")
        for c in self.console.view.scene["cameras"]:
            if not isinstance(cam, bool) and c["id"] == cam:
                return c
        raise ValueError(f"{msg['cmd']}: camera {cam!r} is none of {sorted(self.console.view.cameras)}")

    def start(self, client: Any, msg: dict[str, Any]) -> None:
        """Check msg and send the request; the answer goes to client when it comes. Raises ValueError."""
        cam = self._camera(msg)
        if msg["cmd"] == "still":
            fut = self._images().request_image(cam["id"], STILL_WIDTH_PX, STILL_QUALITY)
            coro = self._still(client, cam, fut)
        else:
            ignore = _rects(msg.get("ignore"), cam["width"], cam["height"])
            fut = self._images().update_mask(cam["id"], ignore=ignore)
            coro = self._mask(client, cam, ignore, fut)
        task = asyncio.get_running_loop().create_task(coro)
        self.tasks.add(task)
        task.add_done_callback(self.tasks.discard)

    async def _answer(self, client: Any, reply: dict[str, Any]) -> None:
        try:
            await client.ws.send_str(json.dumps(reply))
        except (ConnectionError, RuntimeError):
            pass

    async def _still(self, client: Any, cam: dict[str, Any], fut: asyncio.Future) -> None:
        reply: dict[str, Any] = {"type": "still", "camera": cam["id"]}
        try:
            img = await self._images().wait(fut)
        except TimeoutError as e:
            reply["error"] = str(e)
        else:
            reply.update(jpeg="data:image/jpeg;base64," + base64.b64encode(img.jpeg).decode(), width=img.width,
                         height=img.height, capture_ns=img.capture_ns, background=round(img.background, 1),
                         hint=background_hint(img.background))
        await self._answer(client, reply)

    async def _mask(self, client: Any, cam: dict[str, Any], ignore: list[list[int]], fut: asyncio.Future) -> None:
        reply: dict[str, Any] = {"type": "mask", "camera": cam["id"], "ok": False, "saved": False}
        try:
            ack = await self._images().wait(fut)
        except TimeoutError as e:
            reply["text"] = str(e)
        else:
            ok = ack.status in (P.MaskStatus.SAVED, P.MaskStatus.APPLIED)
            reply.update(ok=ok, saved=ack.status == P.MaskStatus.SAVED, text=ack.text)
            if ok:  # what the camera view draws from now on (new tabs get it with the scene)
                old = cam.get("mask") or {}
                cam["mask"] = {"rois": old.get("rois", []), "ignore": ignore, "mask_png": None}
                self.console.scene_changed()
                reply["mask"] = cam["mask"]
        await self._answer(client, reply)

    def cancel(self) -> None:
        for t in list(self.tasks):
            t.cancel()
