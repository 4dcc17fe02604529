"""The console's "still" and "mask" commands end to end in a running demo on 127.0.0.1: the simulated station's
image comes back as a JPEG with bright spots where its blobs are and the background level it measured; a saved
mask lands in the station's YAML file and the blob inside it is no longer sent. Plus the commands' checks."""

from __future__ import annotations

import asyncio
import base64
import json

import aiohttp
import cv2
import numpy as np
import pytest
import yaml

from console.server import ConsoleServer
from console.settings import ConsoleSettings
from console.stills import background_hint
from visionpos.config.arena import parse_arena

from .test_server import TOKEN, FakeSource


def _decode(data_url: str) -> np.ndarray:
    assert data_url.startswith("data:image/jpeg;base64,")
    img = cv2.imdecode(np.frombuffer(base64.b64decode(data_url.split(",", 1)[1]), np.uint8), cv2.IMREAD_GRAYSCALE)
    assert img is not None, "not a decodable JPEG"
    return img


async def _reply(ws, kind: str, timeout_s: float = 5.0) -> dict:
    async def wait():
        while True:
            msg = json.loads((await ws.receive()).data)
            if msg["type"] in (kind, "error"):
                return msg
    return await asyncio.wait_for(wait(), timeout_s)


def _p99_outside(img: np.ndarray, blobs: np.ndarray, margin_px: float) -> float:
    """The 99th percentile of img's pixels farther than sqrt(area / pi) + margin_px from every blob centre."""
    yy, xx = np.mgrid[0:img.shape[0], 0:img.shape[1]]
    keep = np.ones(img.shape, bool)
    for x, y, area, _ in blobs:
        keep &= (xx - x) ** 2 + (yy - y) ** 2 > (np.sqrt(area / np.pi) + margin_px) ** 2
    return float(np.percentile(img[keep], 99))


@pytest.mark.slow
def test_still_image_and_mask_save_in_a_running_demo(tmp_path, arena_yaml):
    from visionpos.app.demo import demo_arena, run_demo

    data = arena_yaml("thesis")
    path = tmp_path / "arena.yaml"
    path.write_text(yaml.safe_dump(data))
    arena = demo_arena(str(path), 6.0, 3, [])
    cam = arena.cameras[0]
    station_file = tmp_path / "station1.yaml"
    station_file.write_text(f"# the station of camera {cam.id}\nstation_id: 1\ncamera_id: {cam.id}\n"
                            "detector:\n  threshold: auto\n")
    views, found = [], {}

    async def during(ctx) -> None:
        console = views[0]
        station = next(s for s in ctx.stations if s.camera.id == cam.id)
        await asyncio.sleep(1.0)  # streaming
        async with aiohttp.ClientSession() as http, http.ws_connect(f"http://127.0.0.1:{console.port}/ws") as ws:
            await ws.send_json({"cmd": "still", "camera": cam.id})
            found["still"] = await _reply(ws, "still")
            found["rendered"] = station.last_still
            found["rendered_blobs"] = station.last_still_blobs.copy()
            # a second request at once: the station's rate limit answers nothing, the console says so
            await ws.send_json({"cmd": "still", "camera": cam.id})
            found["second"] = await _reply(ws, "still", 6.0)
            # the mask: a rectangle around the blob nearest the image centre
            px = ctx.server.pipeline.snapshot().cameras[cam.id].px
            found["before"] = px.copy()
            x, y = px[np.argmin(np.hypot(px[:, 0] - cam.model.width / 2, px[:, 1] - cam.model.height / 2))]
            rect = [max(0, int(x) - 40), max(0, int(y) - 40), min(cam.model.width, int(x) + 40),
                    min(cam.model.height, int(y) + 40)]
            found["rect"] = rect
            await ws.send_json({"cmd": "mask", "camera": cam.id, "ignore": [rect]})
            found["mask"] = await _reply(ws, "mask")
            # from now on: what the simulator saw inside the rectangle, and what the server got
            raw_inside, sent_inside = 0, 0
            for _ in range(40):
                await asyncio.sleep(0.025)
                r = np.asarray(station.last_raw_blobs, float)
                raw_inside += int(((r[:, 0] >= rect[0]) & (r[:, 0] < rect[2]) & (r[:, 1] >= rect[1])
                                   & (r[:, 1] < rect[3])).sum()) if len(r) else 0
                p = ctx.server.pipeline.snapshot().cameras[cam.id].px
                sent_inside += int(((p[:, 0] >= rect[0]) & (p[:, 0] < rect[2]) & (p[:, 1] >= rect[1])
                                    & (p[:, 1] < rect[3])).sum())
            found["raw_inside"], found["sent_inside"] = raw_inside, sent_inside

    settings = ConsoleSettings(port=0, stations=(str(station_file),))
    asyncio.run(asyncio.wait_for(run_demo(arena, 6.0, None, during=during, console=settings,
                                          on_console=views.append), 300))
    still = found["still"]
    assert "error" not in still, still
    img = _decode(still["jpeg"])
    assert img.shape == (still["height"], still["width"])
    s = cam.model.width / img.shape[1]
    blobs = found["rendered_blobs"]
    assert len(blobs) > 0
    # bright where the blobs are ...
    for x, y, _, _ in blobs:
        u, v = int(round(x / s)), int(round(y / s))
        assert img[max(0, v - 1):v + 2, max(0, u - 1):u + 2].max() > 150, (x, y)
    # ... and nowhere else: every bright pixel is near a blob
    ys, xs = np.nonzero(img > 120)
    d = np.min(np.hypot(xs[:, None] * s - blobs[None, :, 0], ys[:, None] * s - blobs[None, :, 1]), axis=1)
    assert d.max() < np.sqrt(blobs[:, 2].max() / np.pi) + 3 * s
    # the background level: the 99th percentile outside the blobs, computed here from the rendered image
    assert still["background"] == pytest.approx(_p99_outside(found["rendered"], blobs, 3.0), abs=0.6)
    assert still["hint"] == background_hint(still["background"])
    assert "timed out" in found["second"].get("error", "") or "did not answer" in found["second"].get("error", "")
    # the mask: saved by the station, in its file, with the rest kept; the blob inside is no longer sent
    m = found["mask"]
    assert m["ok"] and m["saved"], m
    text = station_file.read_text()
    assert yaml.safe_load(text)["detector"] == {"threshold": "auto", "ignore": [found["rect"]]}
    assert text.startswith(f"# the station of camera {cam.id}\n")
    assert found["raw_inside"] > 0  # the simulator did put a blob there ...
    assert found["sent_inside"] == 0  # ... and the station no longer sent it


@pytest.fixture
def arena(arena_yaml):
    return parse_arena(arena_yaml("thesis"), "thesis.yaml")


@pytest.mark.parametrize("cmd,why", [
    ({"cmd": "still", "camera": 99}, "none of"),
    ({"cmd": "still", "camera": True}, "none of"),
    ({"cmd": "mask", "camera": 1, "ignore": "all"}, "list"),
    ({"cmd": "mask", "camera": 1, "ignore": [[0, 0, 10]]}, "x0, y0, x1, y1"),
    ({"cmd": "mask", "camera": 1, "ignore": [[0, 0, 10.5, 10]]}, "x0, y0, x1, y1"),
    ({"cmd": "mask", "camera": 1, "ignore": [[10, 0, 5, 10]]}, "inside"),
    ({"cmd": "mask", "camera": 1, "ignore": [[0, 0, 100000, 10]]}, "inside"),
    ({"cmd": "mask", "camera": 1, "ignore": [[0, 0, 1, 1]] * 65}, "at most"),
    ({"cmd": "still", "camera": 1}, "live server"),  # a source without stations (a replay)
])
def test_station_commands_are_checked_and_answered(arena, cmd, why):
    async def run():
        settings = ConsoleSettings(port=0, update_rate_hz=50.0).with_token()
        console = ConsoleServer(settings, FakeSource(arena))
        await console.start()
        try:
            async with aiohttp.ClientSession() as http, http.ws_connect(f"http://127.0.0.1:{console.port}/ws") as ws:
                await ws.send_json(cmd)
                reply = await _reply(ws, "never")
                assert reply["type"] == "error" and why in reply["error"], reply
            assert console.counters["bad_messages"] == 1
        finally:
            await console.stop()

    asyncio.run(run())


def test_station_commands_need_the_token_off_loopback(arena):
    """Bound elsewhere the console needs its token for everything, the station commands included."""
    class Images:
        asked = 0

        def request_image(self, *a):
            Images.asked += 1
            raise ValueError("no")

    async def run():
        settings = ConsoleSettings(port=0, update_rate_hz=50.0, token=TOKEN)
        source = FakeSource(arena)
        source.ingest = type("I", (), {"images": Images()})()
        console = ConsoleServer(settings, source)
        await console.start()
        try:
            async with aiohttp.ClientSession() as http:
                with pytest.raises(aiohttp.WSServerHandshakeError):
                    await http.ws_connect(f"http://127.0.0.1:{console.port}/ws")
                assert Images.asked == 0
                async with http.ws_connect(f"http://127.0.0.1:{console.port}/ws?token={TOKEN}") as ws:
                    await ws.send_json({"cmd": "still", "camera": arena.cameras[0].id})
                    assert (await _reply(ws, "still"))["type"] == "error"
                assert Images.asked == 1
        finally:
            await console.stop()

    asyncio.run(run())


def test_background_hint_reads_against_the_documented_goal():
    assert background_hint(34.2) == "background 34: lower exposure until below 20"
    assert background_hint(12.0) == "background 12: below 20, exposure is fine"
