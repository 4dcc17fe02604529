"""The console in a real browser: headless Chromium, driven over the DevTools protocol, against a running demo.

No test dependency beyond aiohttp (already the console's): the DevTools protocol is JSON over a
WebSocket, which aiohttp's client speaks. Skips with the reason when /usr/bin/chromium is absent
(Debian: `apt-get install chromium chromium-driver`; .ci/run installs it); with
VISIONPOS_REQUIRE_CHROMIUM=1 (.ci/run) a missing browser fails instead.
"""

from __future__ import annotations

import asyncio
import base64
import json
import os
import subprocess
import tempfile
from pathlib import Path

import numpy as np
import pytest

CHROMIUM = "/usr/bin/chromium"
FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
         "--disable-background-networking", "--disable-component-update", "--disable-sync",
         # WebGL without a GPU: Chromium's software rasteriser (SwiftShader) must be allowed explicitly
         "--enable-unsafe-swiftshader", "--window-size=1400,1000", "--remote-debugging-port=0"]

if not os.path.exists(CHROMIUM):
    if os.environ.get("VISIONPOS_REQUIRE_CHROMIUM"):
        raise RuntimeError(f"VISIONPOS_REQUIRE_CHROMIUM is set but {CHROMIUM} is missing")
    pytest.skip(f"{CHROMIUM} is absent: the console's browser tests need Debian's chromium "
                "(apt-get install chromium chromium-driver)", allow_module_level=True)

# a second body the simulator does not fly: never tracked, so the page must say why
GHOST = {"name": "ghost", "markers": [[0.0, 0.0, 0.0], [0.21, 0.0, 0.0], [0.0, 0.13, 0.0], [0.06, 0.07, 0.05]]}


class Browser:
    """Headless Chromium with a fresh profile; evaluate() and screenshot() over the DevTools protocol."""

    def __init__(self, url: str, profile: Path, flags: tuple[str, ...] = ()):
        import aiohttp

        self.url = url
        self.profile = profile
        self.proc = subprocess.Popen([CHROMIUM, *FLAGS, *flags, f"--user-data-dir={profile}", url],
                                     stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        self.http = aiohttp.ClientSession()
        self.ws = None
        self._id = 0

    async def connect(self, timeout_s: float = 30.0) -> None:
        port_file = self.profile / "DevToolsActivePort"
        loop = asyncio.get_running_loop()
        end = loop.time() + timeout_s
        while True:
            assert loop.time() < end, "Chromium did not open its DevTools port"
            if port_file.exists() and port_file.read_text().strip():
                port = int(port_file.read_text().split()[0])
                try:
                    async with self.http.get(f"http://127.0.0.1:{port}/json/list") as r:
                        targets = await r.json()
                    pages = [t for t in targets if t.get("type") == "page"]
                    if pages:
                        self.ws = await self.http.ws_connect(pages[0]["webSocketDebuggerUrl"], max_msg_size=0)
                        return
                except OSError:
                    pass
            await asyncio.sleep(0.2)

    async def call(self, method: str, **params) -> dict:
        self._id += 1
        mid = self._id
        await self.ws.send_str(json.dumps({"id": mid, "method": method, "params": params}))
        while True:
            msg = json.loads((await asyncio.wait_for(self.ws.receive(), 30)).data)
            if msg.get("id") == mid:
                assert "error" not in msg, msg
                return msg["result"]

    async def evaluate(self, expression: str):
        r = await self.call("Runtime.evaluate", expression=expression, returnByValue=True)
        return r["result"].get("value")

    async def wait_for(self, expression: str, timeout_s: float = 40.0):
        loop = asyncio.get_running_loop()
        end = loop.time() + timeout_s
        while loop.time() < end:
            v = await self.evaluate(expression)
            if v:
                return v
            await asyncio.sleep(0.25)
        raise AssertionError(f"timed out waiting for {expression}; page stats: "
                             f"{await self.evaluate('JSON.stringify(window.visionposConsole)')}")

    async def screenshot(self, path: Path) -> np.ndarray:
        import cv2

        r = await self.call("Page.captureScreenshot", format="png")
        data = base64.b64decode(r["data"])
        path.write_bytes(data)
        return cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)

    async def close(self) -> None:
        if self.ws is not None:
            await self.ws.close()
        await self.http.close()
        self.proc.terminate()
        try:
            self.proc.wait(10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait(5)


def _rect(browser_value: dict, dpr: float = 1.0) -> tuple[int, int, int, int]:
    return tuple(int(round(browser_value[k] * dpr)) for k in ("x", "y", "w", "h"))


def _drawn(img: np.ndarray, rect: tuple[int, int, int, int], background_bgr: tuple[int, int, int]) -> float:
    """Share of the pixels of rect that differ from the background colour by more than a little."""
    x, y, w, h = rect
    crop = img[y:y + h, x:x + w].astype(int)
    return float((np.abs(crop - np.array(background_bgr)).sum(axis=2) > 30).mean())


JS_RECT = "(() => {{ const r = document.querySelector('{sel}').getBoundingClientRect(); " \
          "return {{x: r.x, y: r.y, w: r.width, h: r.height}}; }})()"


@pytest.mark.slow
def test_console_in_chromium_shows_the_arena_the_cameras_and_health(tmp_path, arena_yaml):
    import yaml

    from console.settings import ConsoleSettings
    from visionpos.app.demo import demo_arena, run_demo

    data = arena_yaml("thesis")
    data["bodies"].append(GHOST)
    path = tmp_path / "arena.yaml"
    path.write_text(yaml.safe_dump(data))
    arena = demo_arena(str(path), 14.0, 3, [])
    shots = Path(os.environ.get("VISIONPOS_SCREENSHOTS") or tempfile.mkdtemp(prefix="visionpos-console-"))
    shots.mkdir(parents=True, exist_ok=True)
    views = []
    found: dict = {}

    async def during(ctx) -> None:
        console = views[0]
        browser = Browser(console.url, tmp_path / "profile")
        try:
            await browser.connect()
            await browser.wait_for("window.visionposConsole && window.visionposConsole.states > 30 && "
                                   "window.visionposConsole.health > 2 && window.visionposConsole.frames3d > 10")
            # a tracked body and the ghost's reason in the health table
            await browser.wait_for("[...document.querySelectorAll('#bodies tbody tr')].some(r => "
                                   "r.cells[0].textContent === 'quad' && r.cells[1].textContent === 'yes')")
            # /api/health says the same (polled: on a loaded host the body may drop out for a moment)
            for _ in range(40):
                found["health"] = console.health()
                if all(b["tracked"] == (b["name"] == "quad") for b in found["health"]["bodies"]):
                    break
                await asyncio.sleep(0.25)
            found["bodies"] = await browser.evaluate(
                "[...document.querySelectorAll('#bodies tbody tr')].map(r => [...r.cells].map(c => c.textContent))")
            found["cameras"] = await browser.evaluate(
                "[...document.querySelectorAll('#cameras tbody tr')].map(r => [...r.cells].map(c => c.textContent))")
            found["blobs"] = await browser.evaluate("window.visionposConsole.blobs")
            found["errors"] = await browser.evaluate("window.visionposConsole.errors")
            found["dpr"] = await browser.evaluate("window.devicePixelRatio")
            found["r3d"] = await browser.evaluate(JS_RECT.format(sel="#view3d"))
            found["rcam"] = await browser.evaluate(JS_RECT.format(sel="#camgrid canvas"))
            found["img"] = await browser.screenshot(shots / "console.png")
            # the first camera's "still image" button: the station's image shows under the blobs, read out
            await browser.evaluate("document.querySelector('#camgrid .stationtools button').click()")
            await browser.wait_for("Object.values(window.visionposConsole.stills || {}).some(s => s.loaded)")
            found["still"] = await browser.evaluate("document.querySelector('#camgrid .stationtools span').textContent")
            found["img_still"] = await browser.screenshot(shots / "console-still.png")
        finally:
            await browser.close()

    settings = ConsoleSettings(port=0)
    asyncio.run(asyncio.wait_for(run_demo(arena, 14.0, None, during=during, console=settings,
                                          on_console=views.append), 240))
    print(f"screenshots in {shots}")
    img, dpr = found["img"], found["dpr"] or 1.0
    # the 3D canvas draws: grid, frustums and the body cover a fair share of it (background #15181c)
    assert _drawn(img, _rect(found["r3d"], dpr), (0x1c, 0x18, 0x15)) > 0.02
    # every camera view shows blobs, and the first one's canvas has them drawn (background #0d0f12)
    assert set(found["blobs"]) == {"1", "2", "3", "4"} and all(n > 0 for n in found["blobs"].values())
    assert _drawn(img, _rect(found["rcam"], dpr), (0x12, 0x0f, 0x0d)) > 0.0005
    # the health table lists the cameras (name and streaming) and the tracked body
    names = {c.name for c in arena.cameras}
    assert {row[0].split(" ", 1)[1] for row in found["cameras"]} == names
    assert all(row[1] == "streaming" for row in found["cameras"])
    rows = {r[0]: r for r in found["bodies"]}
    assert rows["quad"][1] == "yes"
    # the ghost is not tracked, and the page says why (the pipeline's reason, not the placeholder)
    assert rows["ghost"][1] == "NO"
    assert rows["ghost"][6] and rows["ghost"][6] != "not seen yet", rows["ghost"]
    assert found["errors"] == []
    # the still image: read out, and drawn (the simulated image's noise and discs change the view's pixels)
    assert found["still"].startswith("background "), found["still"]
    assert not np.array_equal(found["img_still"], found["img"])
    # /api/health says the same
    h = found["health"]
    assert {b["name"]: b["tracked"] for b in h["bodies"]} == {"quad": True, "ghost": False}
    assert any(w.startswith("body ghost is not tracked:") for w in h["warnings"])


@pytest.mark.slow
def test_calibration_panel_in_chromium_fills_in_and_shows_the_solve(tmp_path):
    """`visionpos record`'s console with a simulated wand wave fed in: the panel's heat maps, pairs and ENOUGH, then
    Solve clicked and the per-camera residuals shown."""
    from console.calibration import CalibrationAssistant
    from console.settings import ConsoleSettings
    from visionpos.app.console import RecordSource, open_console
    from visionpos.calibration.coverage import Thresholds
    from visionpos.sim import load_scenario, simulate

    sc = load_scenario("thesis", ["sim.duration=8"], session="wand")
    frames = sorted(simulate(sc).frames, key=lambda f: f.recv_ns)
    shots = Path(os.environ.get("VISIONPOS_SCREENSHOTS") or tempfile.mkdtemp(prefix="visionpos-console-"))
    shots.mkdir(parents=True, exist_ok=True)
    found: dict = {}

    async def main():
        # the simulated wave stays in the middle of the volume: 8 to 12 % of each image
        source = RecordSource(sc.arena, CalibrationAssistant(sc.arena, tmp_path / "arena.yaml",
                                                             Thresholds(min_coverage=0.05)))
        console = await open_console(ConsoleSettings(port=0), source)
        browser = Browser(console.url, tmp_path / "profile")
        try:
            await browser.connect()
            await browser.wait_for("window.visionposConsole && window.visionposConsole.calib")
            found["before"] = await browser.evaluate("document.getElementById('calib-verdict').textContent")
            for f in frames:
                source.push(f)
            await browser.wait_for("window.visionposConsole.calib.enough === true")
            found["pairs"] = await browser.evaluate(
                "[...document.querySelectorAll('#calib-pairs tbody tr')].map(r => "
                "[...r.cells].map(c => c.textContent))")
            found["cells"] = await browser.evaluate("window.visionposConsole.calib.heatCells")
            await browser.evaluate("document.getElementById('calib-solve').click()")
            await browser.wait_for("document.querySelectorAll('#calib-result-table tbody tr').length === 4", 120)
            found["result"] = await browser.evaluate(
                "[...document.querySelectorAll('#calib-result-table tbody tr')].map(r => "
                "[...r.cells].map(c => c.textContent))")
            found["wand"] = await browser.evaluate("document.querySelector('.calib-wand').textContent")
            await browser.evaluate("document.getElementById('calib').scrollIntoView()")
            found["dpr"] = await browser.evaluate("window.devicePixelRatio")
            found["rheat"] = await browser.evaluate(JS_RECT.format(sel="#calib-heat canvas"))
            found["img"] = await browser.screenshot(shots / "calibration.png")
        finally:
            await browser.close()
            await console.stop()

    asyncio.run(asyncio.wait_for(main(), 240))
    print(f"screenshots in {shots}")
    assert found["before"] == "not yet"
    assert len(found["pairs"]) == 6 and all(int(r[1]) >= 100 for r in found["pairs"])
    assert found["cells"] > 0
    assert [r[0] for r in found["result"]] == [c.name for c in sc.arena.cameras]
    assert all(0.1 < float(r[1]) < 0.4 for r in found["result"]), found["result"]
    assert found["wand"].startswith("wand length A-C: error")
    # the heat map draws its lit cells (background #0d0f12, empty cells #1a1d22)
    assert _drawn(found["img"], _rect(found["rheat"], found["dpr"] or 1.0), (0x22, 0x1d, 0x1a)) > 0.01


# ------------------------------------------------------------------ the browser's own web against the console

# the attacker's page: a page of another site tries the console cross-origin, then, after its name was rebound
# to this host (DNS rebinding, played by _rebinding_site), the same requests same-origin
ATTACK_JS = """
window.attack = {};
const MASK = JSON.stringify({cmd: "mask", camera: 1, ignore: [[0, 0, 960, 640]]});
function tryWs(url) {
  return new Promise(done => {
    const ws = new WebSocket(url);
    ws.onopen = () => { ws.send(MASK); setTimeout(() => done("open"), 500); };
    ws.onerror = () => done("error");
  });
}
async function tryFetch(url, opts) {
  try { return (await fetch(url, opts)).status; } catch (e) { return "blocked"; }
}
async function attackConsole(httpBase, wsBase) {
  return {fetch: await tryFetch(httpBase + "/api/health", {mode: "no-cors"}), ws: await tryWs(wsBase + "/ws")};
}
"""


async def _rebinding_site(console_port: int, page: str):
    """attacker.example's server on a loopback port: GET /attack answers its page; every other connection is
    relayed to the console byte for byte, as a browser's connections reach it once the name is rebound."""

    async def handle(reader, writer):
        try:
            head = await reader.readuntil(b"\r\n\r\n")
        except (asyncio.IncompleteReadError, asyncio.LimitOverrunError, ConnectionError):
            writer.close()
            return
        if head.startswith(b"GET /attack "):
            body = page.encode()
            writer.write(b"HTTP/1.1 200 OK\r\nContent-Type: text/html\r\nConnection: close\r\nContent-Length: "
                         + str(len(body)).encode() + b"\r\n\r\n" + body)
            await writer.drain()
            writer.close()
            return
        up_r, up_w = await asyncio.open_connection("127.0.0.1", console_port)
        up_w.write(head)

        async def pipe(r, w):
            try:
                while data := await r.read(65536):
                    w.write(data)
                    await w.drain()
            except ConnectionError:
                pass
            finally:
                w.close()

        await asyncio.gather(pipe(reader, up_w), pipe(up_r, writer))

    return await asyncio.start_server(handle, "127.0.0.1", 0)


def test_pages_of_other_origins_and_foreign_hosts_change_nothing_in_chromium(tmp_path, arena_yaml):
    """A page of another site tries the console cross-origin and then, rebound to this host, as its own origin;
    then the browser opens the console under a foreign name. Every request is refused; no mask reaches a station
    and nothing the console shows changes."""
    from visionpos.config.arena import parse_arena

    from .test_security import _console, state

    arena = parse_arena(arena_yaml("thesis"), "thesis.yaml")
    found: dict = {}

    async def main():
        console, source = await _console(arena)
        console._task.cancel()  # no updates: only the browser's requests could read or change anything
        before = state(console, source)
        cport = console.port
        page = (f"<html><body>attacker<script>{ATTACK_JS}(async () => {{"
                f"attack.cross = await attackConsole('http://127.0.0.1:{cport}', 'ws://127.0.0.1:{cport}');"
                "attack.rebound = await attackConsole('', 'ws://' + location.host);"
                "attack.done = true; })();</script></body></html>")
        site = await _rebinding_site(cport, page)
        sport = site.sockets[0].getsockname()[1]
        browser = Browser(f"http://attacker.example:{sport}/attack", tmp_path / "profile",
                          ("--host-resolver-rules=MAP attacker.example 127.0.0.1",))
        try:
            await browser.connect()
            found["attack"] = await browser.wait_for("window.attack && window.attack.done && window.attack", 20)
            found["mid"] = state(console, source)
            # the console itself under a foreign name: refused, and a socket from that page too
            await browser.call("Page.navigate", url=f"http://attacker.example:{cport}/")
            await browser.wait_for("document.readyState === 'complete' && location.port === '%d'" % cport, 20)
            found["text"] = await browser.evaluate("document.body.innerText")
            found["ws"] = (await browser.call("Runtime.evaluate", returnByValue=True, awaitPromise=True, expression=
                "new Promise(done => { const ws = new WebSocket('ws://' + location.host + '/ws'); ws.onopen = () => "
                "{ ws.send(JSON.stringify({cmd: 'mask', camera: 1, ignore: [[0, 0, 960, 640]]})); "
                "setTimeout(() => done('open'), 500); }; ws.onerror = () => done('error'); })"))["result"]["value"]
            found["after"] = state(console, source)
            found["refused"] = console.counters.get("refused_host", 0) + console.counters["refused_origin"]
        finally:
            await browser.close()
            site.close()
            await console.stop()
        found["before"] = before

    asyncio.run(asyncio.wait_for(main(), 90))
    a = found["attack"]
    assert a["cross"]["ws"] == "error" and a["rebound"]["ws"] == "error", a
    assert a["rebound"]["fetch"] == 403, a  # same-origin after the rebinding: the status is readable
    assert found["mid"] == found["before"]
    assert "refused" in found["text"] and "not this console" in found["text"], found["text"]
    assert found["ws"] == "error"
    assert found["after"] == found["before"]  # no mask sent, no still, no health read, the scene as it was
    assert found["refused"] >= 5


def test_the_token_leaves_the_address_bar_and_the_page_runs_on_its_cookie(tmp_path, arena_yaml):
    """The URL printed at start (?token=...) opened in the browser: the console answers with its cookie and a
    redirect to "/", so the address bar (a screenshot, a shared link) holds no token, and the page connects."""
    from visionpos.config.arena import parse_arena

    from .test_security import _console

    token = "tok-" + "Zk3" * 8
    arena = parse_arena(arena_yaml("thesis"), "thesis.yaml")
    found: dict = {}

    async def main():
        console, source = await _console(arena, token=token)  # on loopback, but configured: needed everywhere
        browser = Browser(f"{console.address}?token={token}", tmp_path / "profile")
        try:
            await browser.connect()
            await browser.wait_for("window.visionposConsole && window.visionposConsole.states > 3", 20)
            found["href"] = await browser.evaluate("location.href")
            found["text"] = await browser.evaluate("document.body.innerText")
            found["refused"] = console.counters["refused_token"]
        finally:
            await browser.close()
            await console.stop()

    asyncio.run(asyncio.wait_for(main(), 60))
    assert token not in found["href"], found["href"]
    assert found["href"].endswith("/")
    assert token not in found["text"]
    assert found["refused"] == 0
