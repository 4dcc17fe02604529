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
import re
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
    from visionpos.fusion.camera_monitor import apply_correction

    data = arena_yaml("thesis")
    data["bodies"].append(GHOST)
    path = tmp_path / "arena.yaml"
    path.write_text(yaml.safe_dump(data))
    original = path.read_text()
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
            await browser.evaluate("document.getElementById('rec').click()")
            # a tracked body and the ghost's reason in the health table
            await browser.wait_for("[...document.querySelectorAll('#bodies tbody tr')].some(r => "
                                   "r.cells[0].textContent === 'quad' && r.cells[1].textContent === 'yes')")
            found["bodies"] = await browser.evaluate(  # at once: on a loaded host the body may drop out later
                "[...document.querySelectorAll('#bodies tbody tr')].map(r => [...r.cells].map(c => c.textContent))")
            # /api/health says the same (polled: on a loaded host the body may drop out for a moment)
            for _ in range(40):
                found["health"] = console.health()
                if all(b["tracked"] == (b["name"] == "quad") for b in found["health"]["bodies"]):
                    break
                await asyncio.sleep(0.25)
            found["cameras"] = await browser.evaluate(
                "[...document.querySelectorAll('#cameras tbody tr')].map(r => [...r.cells].map(c => c.textContent))")
            found["blobs"] = await browser.evaluate("window.visionposConsole.blobs")
            # triage: vehicles, then bodies, then cameras; every row has its level; the layout holds still
            await browser.wait_for("(window.visionposConsole.healthTimes || []).length >= 4")
            found["triage"] = await browser.evaluate(
                "({order: [...document.querySelectorAll('#health h2')].map(e => e.textContent), "
                "vehicles: [...document.querySelectorAll('#vehicles tbody tr')].map(r => "
                "[r.className, ...[...r.cells].map(c => c.textContent)]), "
                "levels: window.visionposConsole.levels, times: window.visionposConsole.healthTimes, "
                "rate: window.visionposConsole.updatesPerS, badge: document.getElementById('badge3d').textContent, "
                "boxes: [...document.querySelectorAll('#camgrid .cam')].map(b => b.getBoundingClientRect().width), "
                "titles: [...document.querySelectorAll('#camgrid .camtitle')].map(t => "
                "[t.getBoundingClientRect().height, getComputedStyle(t).textOverflow])})")
            # the record button (pressed at the start): a new file while it records (its name, size, duration),
            # closed on a second click
            await browser.wait_for("(window.visionposConsole.record.recording || {}).duration_s >= 1", 15)
            found["recording"] = await browser.evaluate("document.getElementById('recinfo').textContent")
            await browser.evaluate("document.getElementById('rec').click()")
            await browser.wait_for("!!window.visionposConsole.record.stopped", 15)
            found["stopped"] = await browser.evaluate(
                "({info: document.getElementById('recinfo').textContent, button: "
                "document.getElementById('rec').textContent, stopped: window.visionposConsole.record.stopped})")
            # the running server's calibration panel: "gather wave" takes what the stations send from the click
            await browser.wait_for("!!document.getElementById('calib-wave')", 10)
            await browser.evaluate("document.getElementById('calib-wave').click()")
            found["wave"] = await browser.wait_for(
                "window.visionposConsole.calib.framesKept > 0 && [document.getElementById('calib-wave').textContent, "
                "document.getElementById('calib-ground').textContent, window.visionposConsole.calib.framesKept]", 10)
            found["errors"] = await browser.evaluate("window.visionposConsole.errors")
            found["dpr"] = await browser.evaluate("window.devicePixelRatio")
            found["r3d"] = await browser.evaluate(JS_RECT.format(sel="#view3d"))
            found["rcam"] = await browser.evaluate(JS_RECT.format(sel="#camgrid canvas"))
            # a view preset, then a click on the quad: its details
            await browser.evaluate("(() => { const p = document.getElementById('preset'); p.value = 'top'; "
                                   "p.dispatchEvent(new Event('change')); })()")
            found["view3d"] = await browser.evaluate("window.visionposConsole.view3d")
            for _ in range(50):  # the quad moves (and a loaded host may lose it a moment): click where it is now
                xy = await browser.evaluate("window.visionposConsole.screenOf('quad')")
                if xy:
                    for kind in ("mousePressed", "mouseReleased"):
                        await browser.call("Input.dispatchMouseEvent", type=kind, x=xy[0], y=xy[1], button="left",
                                           clickCount=1)
                    if await browser.evaluate("!!window.visionposConsole.bodyInfo"):
                        break
                await asyncio.sleep(0.2)
            found["body_info"] = await browser.evaluate("window.visionposConsole.bodyInfo")
            found["img"] = await browser.screenshot(shots / "console.png")
            # the first camera's "still image" button: the station's image shows under the blobs, read out
            await browser.evaluate("document.querySelector('#camgrid .stationtools button').click()")
            await browser.wait_for("Object.values(window.visionposConsole.stills || {}).some(s => s.loaded)")
            found["still"] = await browser.evaluate("document.querySelector('#camgrid .stationtools span').textContent")
            found["img_still"] = await browser.screenshot(shots / "console-still.png")
            # a camera the monitor corrected (as its _correct does: test_arena_file.py) gets a row and "write to
            # arena file"; the operator says OK to the confirmation
            watch = console.source.monitor.cams[2]
            watch.camera = apply_correction(watch.camera, np.array([np.radians(0.5), 0.0, 0.0, 0.0, 0.0, 0.01]))
            watch.corrections = max(watch.corrections, 1)
            await browser.wait_for("!!document.querySelector('#monitor button')", 10)
            await browser.evaluate("window.confirm = () => true; document.querySelector('#monitor button').click()")
            await browser.wait_for("!!window.visionposConsole.monitor.written", 10)
            found["written"] = await browser.evaluate(
                "({reply: window.visionposConsole.monitor.written, "
                "note: document.getElementById('monitor-note').textContent})")
        finally:
            await browser.close()

    settings = ConsoleSettings(port=0, record_dir=str(tmp_path / "flights"))
    asyncio.run(asyncio.wait_for(run_demo(arena, 14.0, None, during=during, console=settings,
                                          on_console=views.append), 240))
    print(f"screenshots in {shots}")
    img, dpr = found["img"], found["dpr"] or 1.0
    assert found["wave"][:2] == ["stop the wave", "set ground"] and found["wave"][2] > 0, found["wave"]
    # the corrected pose in the arena file, the old file in the backup the page names
    w = found["written"]["reply"]
    assert w["camera"] == 2 and w["file"] == str(path.resolve())
    assert found["written"]["note"] == f"camera 2's pose written to {w['file']} (the old file: {w['backup']})"
    assert Path(w["backup"]).read_text() == original
    cams = {c["id"]: c for c in yaml.safe_load(path.read_text())["cameras"]}
    assert cams[2]["pose"] == w["pose"] != {c["id"]: c for c in data["cameras"]}[2]["pose"]
    assert all(cams[i]["pose"] == c["pose"] for i, c in ((c["id"], c) for c in data["cameras"]) if i != 2)
    # the recording: named while it ran, then closed with every packet it was given
    from visionpos.recording import TOPIC_PACKETS, RecordingReader

    rec = found["stopped"]
    name = rec["stopped"]["file"]
    assert re.fullmatch(r"recording visionpos-\d{8}-\d{6}\.mcap, [\d.]+ [kM]B, [1-9]\d* s", found["recording"])
    assert found["recording"].split(",")[0] == f"recording {name}"
    assert rec["button"] == "record" and rec["info"].startswith(f"saved {name}, ")
    path = tmp_path / "flights" / name
    packets = sum(1 for _ in RecordingReader(path).packets())
    assert packets > 100 and packets == rec["stopped"]["messages"][TOPIC_PACKETS], rec
    # the 3D canvas draws: grid, frustums and the body cover a fair share of it (background #15181c)
    assert _drawn(img, _rect(found["r3d"], dpr), (0x1c, 0x18, 0x15)) > 0.02
    # every camera view shows blobs, and the first one's canvas has them drawn (background #0d0f12)
    assert set(found["blobs"]) == {"1", "2", "3", "4"} and all(n > 0 for n in found["blobs"].values())
    assert _drawn(img, _rect(found["rcam"], dpr), (0x12, 0x0f, 0x0d)) > 0.0005
    # the health table lists the cameras (name and streaming) and the tracked body
    names = {c.name for c in arena.cameras}
    assert {row[0].split(" ", 1)[1] for row in found["cameras"]} == names
    assert all(row[1] == "streaming" for row in found["cameras"]), found["cameras"]
    rows = {r[0]: r for r in found["bodies"]}
    assert rows["quad"][1] == "yes"
    # the ghost is not tracked, and the page says why (the pipeline's reason, not the placeholder)
    assert rows["ghost"][1] == "NO"
    assert rows["ghost"][6] and rows["ghost"][6] != "not seen yet", rows["ghost"]
    assert found["errors"] == []
    t = found["triage"]
    print("triage:", {k: t[k] for k in ("vehicles", "levels", "rate", "badge")})
    assert t["order"] == ["Vehicles", "Bodies", "Cameras"]
    assert t["levels"]["bodies:ghost"] == "bad" and t["levels"]["vehicles:quad"] in ("ok", "warn", "bad")
    assert t["vehicles"][0][0] == f"row-{t['levels']['vehicles:quad']}"
    # health once a second (docs/console.md), the page's own update rate on the badge
    gaps = np.diff(t["times"][1:])
    assert 700 < np.median(gaps) < 2500, gaps  # twice a second would be 500 ms; a loaded host stretches them
    assert t["rate"] > 0 and t["badge"].startswith("live, ")
    # a stable layout: every camera box is the canvas' width, its title one line ending in an ellipsis
    assert t["boxes"] == [302] * 4 and all(h < 24 and o == "ellipsis" for h, o in t["titles"]), t
    # the top view looks down on the arena; a click on the quad shows its pose, rate, cameras, NIS and vehicle
    v = found["view3d"]
    assert v["preset"] == "top" and v["target"] == [0, 0, 0] and v["position"][2] > 3 and abs(v["position"][0]) < 1e-6
    info = found["body_info"]
    assert info and info[0].startswith("quad: "), info
    if info[0] == "quad: tracked":  # (a loaded host may lose it for a moment)
        assert any(x.startswith("position ") for x in info) and any(x.startswith("NIS position ") for x in info)
    assert any(x.startswith("seen by: ") for x in info) and any(x.startswith("vehicle quad: ") for x in info)
    # the still image: read out, and drawn (the simulated image's noise and discs change the view's pixels)
    assert found["still"].startswith("background "), found["still"]
    assert not np.array_equal(found["img_still"], found["img"])
    # /api/health says the same
    h = found["health"]
    assert {b["name"]: b["tracked"] for b in h["bodies"]} == {"quad": True, "ghost": False}
    assert any(w.startswith("body ghost is not tracked:") for w in h["warnings"])


@pytest.mark.slow
def test_calibration_panel_in_chromium_fills_in_and_shows_the_solve(tmp_path):
    """`visionpos record`'s console with a simulated wand wave fed in: the panel's heat maps and pairs, "not yet" with
    the coverage still missing (the simulated wave stays in the middle of each image: 8 to 15 % of it, ENOUGH wants
    50 %), Solve enabled once the solver's minimums are met, clicked, and the per-camera residuals shown."""
    from console.calibration import CalibrationAssistant
    from console.settings import ConsoleSettings
    from visionpos.app.console import RecordSource, open_console
    from visionpos.sim import load_scenario, simulate

    sc = load_scenario("thesis", ["sim.duration=8"], session="wand")
    frames = sorted(simulate(sc).frames, key=lambda f: f.recv_ns)
    shots = Path(os.environ.get("VISIONPOS_SCREENSHOTS") or tempfile.mkdtemp(prefix="visionpos-console-"))
    shots.mkdir(parents=True, exist_ok=True)
    found: dict = {}

    async def main():
        source = RecordSource(sc.arena, CalibrationAssistant(sc.arena, tmp_path / "arena.yaml"))
        console = await open_console(ConsoleSettings(port=0), source)
        browser = Browser(console.url, tmp_path / "profile")
        try:
            await browser.connect()
            await browser.wait_for("window.visionposConsole && window.visionposConsole.calib")
            found["before"] = await browser.evaluate("document.getElementById('calib-verdict').textContent")
            for f in frames:
                source.push(f)
            await browser.wait_for("window.visionposConsole.calib.messages > 1 && "
                                   "!document.getElementById('calib-solve').disabled")
            found["after"] = await browser.evaluate("document.getElementById('calib-verdict').textContent")
            found["missing"] = await browser.evaluate(
                "[...document.querySelectorAll('#calib-missing li')].map(l => l.textContent)")
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
    assert found["before"] == "not yet" and found["after"] == "not yet"
    assert found["missing"] and all(re.fullmatch(r"camera pi\d covers \d+ % of its image, want 50 %: .*", m)
                                    for m in found["missing"]), found["missing"]
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
    redirect to "/", so the address bar (a screenshot, a shared link) holds no token, and the page connects.
    Then the page comes back while console.max_clients tabs are open: its header says it was refused and why, it
    does not look live, and once a tab closes it gets in on its next try."""
    import aiohttp

    from visionpos.config.arena import parse_arena

    from .test_security import _console

    token = "tok-" + "Zk3" * 8
    arena = parse_arena(arena_yaml("thesis"), "thesis.yaml")
    found: dict = {}

    async def main():
        # on loopback, but configured: needed everywhere; two tabs at most
        console, source = await _console(arena, token=token, max_clients=2)
        browser = Browser(f"{console.address}?token={token}", tmp_path / "profile")
        try:
            await browser.connect()
            await browser.wait_for("window.visionposConsole && window.visionposConsole.states > 3", 20)
            found["href"] = await browser.evaluate("location.href")
            found["text"] = await browser.evaluate("document.body.innerText")
            found["refused"] = console.counters["refused_token"]
            await browser.call("Page.navigate", url="about:blank")
            for _ in range(100):  # the page's socket closes a moment after it leaves: then its slot is free
                if not console.clients:
                    break
                await asyncio.sleep(0.05)
            async with aiohttp.ClientSession() as http:
                tabs = [await http.ws_connect(f"{console.address}ws?token={token}") for _ in range(2)]
                for _ in range(100):
                    if len(console.clients) == 2:
                        break
                    await asyncio.sleep(0.05)
                assert len(console.clients) == 2 and console.counters["refused_full"] == 0
                await browser.call("Page.navigate", url=console.address)  # the third tab: its cookie, no token
                found["full"] = await browser.wait_for(
                    "window.visionposConsole && window.visionposConsole.full && "
                    "document.getElementById('conn').textContent.startsWith('refused') && "
                    "[document.getElementById('conn').textContent, document.getElementById('conn').className, "
                    "window.visionposConsole.stale]", 20)
                found["refused_full"] = console.counters["refused_full"]
                await tabs[0].close()
                found["back"] = await browser.wait_for("document.getElementById('conn').textContent === 'live'", 20)
                await tabs[1].close()
        finally:
            await browser.close()
            await console.stop()

    asyncio.run(asyncio.wait_for(main(), 90))
    assert token not in found["href"], found["href"]
    assert found["href"].endswith("/")
    assert token not in found["text"]
    assert found["refused"] == 0
    text, cls, stale = found["full"]
    assert "at most 2 tabs" in text and "console.max_clients" in text and "next try in 5 s" in text, text
    assert cls == "bad" and stale is True
    assert found["refused_full"] >= 1 and found["back"]

def _shots() -> Path:
    """Where the screenshots go: VISIONPOS_SCREENSHOTS (docs/images regenerates the docs' pictures) or a temp dir."""
    shots = Path(os.environ.get("VISIONPOS_SCREENSHOTS") or tempfile.mkdtemp(prefix="visionpos-console-"))
    shots.mkdir(parents=True, exist_ok=True)
    return shots


def _arena(data: dict, name: str):
    from visionpos.config.arena import parse_arena

    return parse_arena(data, name)


def _grey(img: np.ndarray, rect: tuple[int, int, int, int]) -> bool:
    """No coloured pixel in rect: every pixel's channels within a few levels of each other."""
    x, y, w, h = rect
    crop = img[y:y + h, x:x + w].astype(int)
    return int((crop.max(axis=2) - crop.min(axis=2)).max()) <= 12  # the panels' own blue-grey: 9


def _solve_result(lc) -> list:
    """A wand solve's result on a live calibration panel, as solve_and_compare gives it (console/live_calibration.py):
    the running cameras with camera 2 turned 0.2 deg, scored better than the running ones; returns those cameras."""
    from visionpos.fusion.camera_monitor import apply_correction

    cams = lc.running_cameras()
    cams[1] = apply_correction(cams[1], np.array([np.radians(0.2), 0.0, 0.0, 0.0, 0.0, 0.0]))

    def score(px):
        return {"cameras": [{"id": c.id, "name": c.name, "rms_px": px, "max_px": 3 * px} for c in cams],
                "rms_px": px, "worst_rms_px": px, "wand_ac_err_mm": 0.1, "wand_ac_std_mm": 0.5, "points": 900}

    result = {"out": "lab.calibrated.yaml", "time_steps": 300, "wand_ac_mean_err_mm": 0.1, "wand_ac_std_mm": 0.5,
              "cameras": [{"id": c.id, "name": c.name, "rms_px": 0.2, "max_px": 0.8, "views": 300, "offset_ms": 0.0}
                          for c in cams], "warnings": [], "seconds": 1.0, "current": score(1.2), "new": score(0.2),
              "refused": None, "moved": [{"id": c.id, "name": c.name, "rotation_deg": 0.2 * (c.id == 2),
                                          "shift_mm": 0.0} for c in cams]}
    lc._solved = {"scene_id": lc.scene_id(), "time": lc.clock(), "cameras": cams, "report": {"rms_px": {}}}
    lc.solve = {"running": False, "result": result, "error": None, "frames": 900}
    lc.version += 1
    return cams


@pytest.mark.slow
def test_a_stopped_stream_greys_the_page_and_another_arena_rebuilds_it(tmp_path, arena_yaml):
    """`visionpos record`'s console (no fusion: quick to start) for the thesis arena, stopped, then started again on
    the same port for arena8: the page greys with the time of its last data, then shows arena8's eight cameras. Then
    a running fusion server's console there: a solve's "apply to the running server" waits for the confirmation."""
    from console.settings import ConsoleSettings
    from visionpos.app.console import RecordSource, open_console
    from visionpos.config.arena import dump_yaml
    from visionpos.fusion.pipeline import FusionPipeline
    from visionpos.server.service import FusionServer, load_config_with_overrides

    found: dict = {}
    volume = {"min_m": [-1.0, -0.5, 0.0], "max_m": [1.0, 1.5, 2.0]}  # the planner's flight volume, drawn as a box
    thesis = _arena({**arena_yaml("thesis"), "plan": {"volume": volume}}, "thesis.yaml")
    arena8 = _arena(arena_yaml("arena8"), "arena8.yaml")

    async def main():
        console = await open_console(ConsoleSettings(port=0), RecordSource(thesis))
        port = console.port
        # two reflections on camera 2 (the static-blob watch itself: test_view.py)
        console.view.static_blobs = lambda now_ns: {2: [
            {"x": 100.0, "y": 80.0, "seconds": 6.0, "ignore": [94, 74, 107, 87]},
            {"x": 500.0, "y": 300.0, "seconds": 7.0, "ignore": [494, 294, 507, 307]}]}
        browser = Browser(console.url, tmp_path / "profile")
        try:
            await browser.connect()
            await browser.wait_for("window.visionposConsole && window.visionposConsole.states > 10 && "
                                   "window.visionposConsole.health > 0 && !window.visionposConsole.stale && "
                                   "window.visionposConsole.updatesPerS > 0")
            found["volume"] = await browser.evaluate("window.visionposConsole.volume")
            found["live_badge"] = await browser.evaluate("document.getElementById('badge3d').textContent")
            found["live_rate"] = await browser.evaluate("window.visionposConsole.updatesPerS")
            found["dpr"] = await browser.evaluate("window.devicePixelRatio")
            found["rhealth"] = await browser.evaluate(JS_RECT.format(sel="#health"))
            found["img_live"] = await browser.screenshot(tmp_path / "live.png")
            # a camera's reflections are one warning line; "mask these" draws their rectangles on its view
            await browser.wait_for("!!document.querySelector('#warnings button.maskthese')", 10)
            found["mask_these"] = await browser.evaluate(
                "(() => { const b = document.querySelector('#warnings button.maskthese'); b.click(); "
                "const c = document.getElementById('cam-' + b.dataset.camera); "
                "return {camera: Number(b.dataset.camera), ignore: JSON.parse(b.dataset.ignore), "
                "line: b.parentElement.textContent, drafts: JSON.parse(c.dataset.drafts || '[]'), "
                "lines: [...document.querySelectorAll('#warnings li')].map(l => l.textContent)}; })()")
            await console.stop()
            await browser.wait_for("window.visionposConsole.stale", 10)
            found["notes"] = await browser.evaluate(
                "[...document.querySelectorAll('.stale-note')].map(e => e.textContent)")
            found["badge"] = await browser.evaluate("document.getElementById('badge3d').textContent")
            found["conn"] = await browser.evaluate("document.getElementById('conn').textContent")
            await asyncio.sleep(0.5)  # the grey filter is drawn with the next frame
            found["img_stale"] = await browser.screenshot(_shots() / "console-stale.png")
            console = await open_console(ConsoleSettings(port=port), RecordSource(arena8))
            await browser.wait_for("window.visionposConsole.cameraViews === 8 && !window.visionposConsole.stale", 20)
            found["rebuilt"] = await browser.evaluate(
                "({frusta: window.visionposConsole.frusta, rebuilds: window.visionposConsole.rebuilds, "
                "canvases: document.querySelectorAll('#camgrid canvas').length, "
                "rays: document.querySelectorAll('#rays option').length, volume: window.visionposConsole.volume, "
                "titles: [...document.querySelectorAll('#camgrid .cam > div:first-child')].map(e => e.textContent)})")
            found["errors"] = await browser.evaluate("window.visionposConsole.errors")
            # a running fusion server's console on the same port, with a solve's result on its panel: "apply to the
            # running server" asks first; cancelled, nothing changes; confirmed, the file and the running cameras
            await console.stop()
            lab = load_config_with_overrides(str(path), ["server.insecure=true"])
            server = FusionServer(lab, port=0, pipeline=FusionPipeline(lab, warm_up=False))  # never started: no frames
            console = await open_console(ConsoleSettings(port=port), server)
            solved = _solve_result(console.calibration)
            await browser.wait_for("!!document.getElementById('calib-apply-button')", 20)
            scene_before = await browser.evaluate("window.visionposConsole.sceneId")
            click = "document.getElementById('calib-apply-button').click()"
            await browser.evaluate(f"window.confirm = () => false; {click}")
            await asyncio.sleep(0.5)
            found["cancelled"] = (console.calibration.applied, path.read_text() == original)
            await browser.evaluate(f"window.confirm = () => true; {click}")
            found["applied"] = await browser.wait_for(
                f"window.visionposConsole.calib.applied && window.visionposConsole.sceneId !== '{scene_before}' && "
                "document.getElementById('calib-apply').textContent", 10)
            found["running"] = server.pipeline.cameras[2] is solved[1]
        finally:
            await browser.close()
            await console.stop()

    path = tmp_path / "lab.yaml"
    dump_yaml(arena_yaml("thesis"), path)
    original = path.read_text()
    asyncio.run(asyncio.wait_for(main(), 120))
    assert found["cancelled"] == (None, True)
    assert found["applied"].startswith(f"applied: the wand solve, written to {path.resolve()} (the old file: ")
    assert found["running"] and [b.read_text() for b in tmp_path.glob("lab.yaml.bak-*")] == [original]
    dpr = found["dpr"] or 1.0
    # live: the badge says so with the page's own update rate, and the health panel has colour (state words)
    assert re.match(r"live, \d+ updates/s", found["live_badge"]), found["live_badge"]
    assert found["live_rate"] > 0
    assert not _grey(found["img_live"], _rect(found["rhealth"], dpr))
    # stopped: every panel, the 3D badge and the header say since when, and the health panel is grey
    since = r"no data since \d\d:\d\d:\d\d"
    assert len(found["notes"]) == 3 and all(re.fullmatch(since, n) for n in found["notes"]), found["notes"]
    assert re.fullmatch(since, found["badge"]) and re.search(since, found["conn"])
    assert _grey(found["img_stale"], _rect(found["rhealth"], dpr))
    m = found["mask_these"]
    assert m["camera"] == 2 and m["ignore"] == [[94, 74, 107, 87], [494, 294, 507, 307]]
    assert m["drafts"] == m["ignore"], m  # drawn on camera 2's view (it has no station mask of its own)
    assert m["line"].startswith(f"camera {m['camera']} (") and m["line"].endswith("mask these")
    assert sum(x.startswith(f"camera {m['camera']} (") and "stayed put" in x for x in m["lines"]) == 1
    # another arena on the same port: rebuilt for its eight cameras, nothing of the thesis arena left
    r = found["rebuilt"]
    assert r["frusta"] == 8 and r["canvases"] == 8 and r["rays"] == 9 and r["rebuilds"] == 1
    # the thesis arena's plan.volume was a 2 x 2 x 2 m box centred at (0, 0.5, 1); arena8 has none
    assert found["volume"] == {"center": [0, 0.5, 1], "size": [2, 2, 2]} and r["volume"] is None
    assert [t.split(":")[0] for t in r["titles"]] == [f"camera {c.id} ({c.name})" for c in arena8.cameras]
    assert found["errors"] == []


def _with_a_gap(src: Path, out: Path, start_s: float, end_s: float) -> Path:
    """A copy of the recording src without any packet from start_s to end_s: every station silent."""
    from visionpos.recording import RecordingReader, RecordingWriter

    r = RecordingReader(src)
    packets = list(r.packets_with_source())
    t0 = packets[0][0]
    meta = {k: v for k, v in (r.meta or {}).items() if k in ("wall_start_unix_ns", "monotonic_start_ns")}
    with RecordingWriter(out, r.config, meta, foxglove_rate_hz=None) as w:
        for t, data, source in packets:
            if not start_s * 1e9 <= t - t0 < end_s * 1e9:
                w.write_packet(t, data, source)
    return out


@pytest.mark.slow
def test_a_replay_shows_only_what_a_replay_can_do_and_its_refusals(tmp_path, thesis_log):
    """`replay LOG --view` of a flight recording: the file's name in the header, no still-image or mask buttons,
    no calibration panel (no wand in it); a speed the server refuses is shown in the page; the seek bar marks
    where the body was lost (its stations fell silent for 0.6 s), and the step buttons move one frame."""
    from console.settings import ConsoleSettings
    from visionpos.app.console import replay_view

    found: dict = {}
    thesis_log = _with_a_gap(thesis_log, tmp_path / "gap.mcap", 2.2, 2.8)  # after the picture

    async def main():
        views: list = []
        task = asyncio.create_task(replay_view(str(thesis_log), None, [], None, ConsoleSettings(port=0),
                                               on_console=views.append, duration_s=60, calibrate_out=str(
                                                   tmp_path / "out.yaml")))
        while not views:
            await asyncio.sleep(0.05)
        browser = Browser(views[0].url, tmp_path / "profile")
        try:
            await browser.connect()
            await browser.wait_for("window.visionposConsole && window.visionposConsole.states > 10 && "
                                   "window.visionposConsole.calib && window.visionposConsole.calib.hidden === true")
            found["page"] = await browser.evaluate(
                "({source: document.getElementById('source').textContent, "
                "tools: document.querySelectorAll('.stationtools').length, "
                "views: document.querySelectorAll('#camgrid canvas').length, "
                "calib: !!document.getElementById('calib'), record: !document.getElementById('recbox').hidden, "
                "replay: !document.getElementById('replay').hidden})")
            await browser.evaluate("(() => { const s = document.getElementById('speed'); const o = "
                                   "document.createElement('option'); o.value = '100'; s.append(o); s.value = '100'; "
                                   "s.dispatchEvent(new Event('change')); })()")
            await browser.wait_for("window.visionposConsole.refusal", 10)
            found["notice"] = await browser.evaluate(
                "(() => { const n = document.getElementById('notice'); "
                "return {text: n.textContent, shown: !n.hidden && n.getBoundingClientRect().width > 0}; })()")
            await browser.evaluate("(() => { const s = document.getElementById('speed'); s.lastChild.remove(); "
                                   "s.value = '1'; })()")  # the menu as it was, for the picture
            await browser.wait_for("(window.visionposConsole.lost || []).length > 0", 20)
            await browser.evaluate("document.getElementById('play').dataset.playing = '1'; "
                                   "document.getElementById('play').click()")  # pause
            await browser.wait_for("document.getElementById('stepfwd').disabled === false", 10)
            await browser.evaluate("(() => { const s = document.getElementById('seek'); s.value = '2'; "
                                   "s.dispatchEvent(new Event('change')); })()")
            await browser.wait_for("window.visionposConsole.replayReply === 2", 10)  # the seek's answer
            # from the seek's own answer: the shown position (replayPos) may still be a state sent before it
            steps = [await browser.evaluate("window.visionposConsole.replayReply")]
            for button in ("stepfwd", "stepfwd", "stepback"):  # each answered once done
                n = await browser.evaluate("window.visionposConsole.replayReplies")
                await browser.evaluate(f"document.getElementById('{button}').click()")
                await browser.wait_for(f"window.visionposConsole.replayReplies > {n}", 10)
                steps.append(await browser.evaluate("window.visionposConsole.replayReply"))
            found["steps"] = steps
            found["lost"] = await browser.evaluate(
                "({marks: window.visionposConsole.lost, drawn: [...document.querySelectorAll('#lost i')].map(i => "
                "[i.style.left, i.title])})")
            await browser.screenshot(_shots() / "replay.png")
        finally:
            await browser.close()
            task.cancel()
            try:
                await task
            except asyncio.CancelledError:
                pass

    asyncio.run(asyncio.wait_for(main(), 120))
    p = found["page"]
    assert p["source"] == f"replay of {thesis_log.name}" and p["replay"]
    assert p["views"] == 4 and p["tools"] == 0 and p["calib"] is False and p["record"] is False
    assert re.fullmatch(r"\d\d:\d\d:\d\d refused: speed: give x between 0.05 and 16", found["notice"]["text"])
    assert found["notice"]["shown"]
    # the body lost in the gap (the session's own marks: test_replay.py), drawn where it happened
    marks = found["lost"]["marks"]
    assert marks and all(m["body"] == "quad" and 2.2 <= m["t_s"] < 2.9 for m in marks), marks
    assert [t for _, t in found["lost"]["drawn"]] == [f"quad lost at {m['t_s']:.2f} s" for m in marks]
    # a frame is one output tick (10 ms at 100 Hz): forward, forward, back; paused in between
    s0, s1, s2, s3 = found["steps"]
    assert round(s1 - s0, 3) == 0.01 and round(s2 - s1, 3) == 0.01 and round(s3 - s2, 3) == -0.01, found["steps"]
