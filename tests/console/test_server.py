"""The console's server on 127.0.0.1: token, origin, bad messages, client limit, slow clients, /api/health."""

from __future__ import annotations

import asyncio
import json
import logging
from types import SimpleNamespace

import numpy as np
import pytest

from console.server import QUEUE_UPDATES, Client, ConsoleServer
from console.settings import ConsoleSettings, parse_console
from visionpos.config.arena import ConfigError, parse_arena
from visionpos.fusion.snapshot import CameraFrame, FusionSnapshot
from visionpos.messages import BodyState

TOKEN = "s3cret-token-0123456789"


class FakePipeline:
    """What the console reads of a pipeline: its snapshot (frames: camera id -> CameraFrame)."""

    def __init__(self, frames, untracked_why):
        self.frames, self.untracked_why = frames, untracked_why

    def snapshot(self):
        return FusionSnapshot(self.frames, (), self.untracked_why)


class FakeSource:
    """The face of a FusionServer the console reads; counts every read of health()."""

    def __init__(self, arena):
        self.arena = arena
        cam = arena.cameras[0]
        px = np.array([[100.0, 200.0], [300.0, 40.0]])
        frame = CameraFrame(5_000_000, px, cam.model.undistort(px), np.array([-1, -1]))
        self.pipeline = FakePipeline({cam.id: frame}, {0: "not seen by enough cameras: 1 of 4 see blobs"})
        self.last_states = [BodyState(name=b.name, body_id=b.id, time_ns=0, capture_ns=0, position=np.full(3, np.nan),
                                      quaternion=np.full(4, np.nan), velocity=np.full(3, np.nan),
                                      angular_velocity=np.full(3, np.nan), covariance=np.full((6, 6), np.nan),
                                      velocity_covariance=np.full((3, 3), np.nan), tracked=False, n_markers=0,
                                      n_cameras=0, reset_counter=0) for b in arena.bodies]
        self.health_calls = 0

    def clock(self) -> int:
        return 10_000_000

    def health(self):
        self.health_calls += 1
        cams = {c.id: {"camera_id": c.id, "state": "streaming", "fps": 50.0, "fps_nominal": 100.0, "frames": 10,
                       "latency_ms": 4.0, "clock_offset_ms": 0.1, "clock_uncertainty_us": 30.0,
                       "loss_recent": 0.0, "shed": 3} for c in self.arena.cameras}
        return {"cameras": cams, "bodies_tracked_ticks": {},
                "sinks": {"Bridge": {"vehicles": {"v1": {"body": "quad", "sysid": 1, "endpoint": "udpin:127.0.0.1:1",
                                                         "link_up": False, "sent": 0, "signed": True}}}}}


@pytest.fixture
def arena(arena_yaml):
    return parse_arena(arena_yaml("thesis"), "thesis.yaml")


async def _serve(arena, **kw):
    settings = ConsoleSettings(port=0, update_rate_hz=50.0, **kw).with_token()
    source = FakeSource(arena)
    console = ConsoleServer(settings, source, clock=source.clock)
    await console.start()
    return console, source


def run(coro):
    return asyncio.run(asyncio.wait_for(coro, 30))


def test_loopback_console_serves_page_health_and_live_updates(arena):
    import aiohttp

    async def main():
        console, source = await _serve(arena)
        base = f"http://127.0.0.1:{console.port}"
        try:
            async with aiohttp.ClientSession() as http:
                async with http.get(base + "/") as r:
                    assert r.status == 200 and "visionpos console" in await r.text()
                async with http.get(base + "/static/vendor/three.module.min.js") as r:
                    assert r.status == 200 and r.content_type == "text/javascript"
                async with http.get(base + "/static/../server.py") as r:
                    assert r.status == 404
                async with http.get(base + "/api/health") as r:
                    h = await r.json()
                async with http.ws_connect(base + "/ws") as ws:
                    first = json.loads((await ws.receive(timeout=5)).data)
                    types = set()
                    while "state" not in types:
                        types.add(json.loads((await ws.receive(timeout=5)).data)["type"])
            return first, types, h
        finally:
            await console.stop()

    first, types, h = run(main())
    assert first["type"] == "scene" and [c["id"] for c in first["cameras"]] == [1, 2, 3, 4]
    assert "health" in types
    assert [c["name"] for c in h["cameras"]] == [c.name for c in arena.cameras]
    cam = h["cameras"][0]
    assert cam["fps"] == 50.0 and cam["fps_configured"] == 100.0
    assert cam["dropped"] == {"shed": 3} and "queued too long" in h["drop_reasons"]["shed"]
    # plain-language warnings: the slow stations, the vehicle link, the lost body with its reason
    assert sum("delivers 50 frames/s, configured 100" in w for w in h["warnings"]) == 4
    assert any(w.startswith("vehicle v1 (udpin:127.0.0.1:1): link down") for w in h["warnings"])
    assert any("not seen by enough cameras: 1 of 4 see blobs" in w for w in h["warnings"])


def test_token_needed_off_loopback_and_checked_on_every_request(arena, caplog):
    import aiohttp

    async def main():
        console, source = await _serve(arena, bind="0.0.0.0", token=TOKEN)
        console._task.cancel()  # no updates: only the requests read the source here
        base = f"http://127.0.0.1:{console.port}"
        out = {}
        try:
            # unsafe: keep cookies of an IP address, as browsers do
            async with aiohttp.ClientSession(cookie_jar=aiohttp.CookieJar(unsafe=True)) as http:
                for path in ("/", "/api/health", "/static/app.js", "/ws"):
                    async with http.get(base + path) as r:
                        out[path] = r.status
                async with http.get(base + "/api/health?token=wrong-token-0123456789") as r:
                    out["wrong"] = r.status
                async with http.get(base + "/api/health", headers={"Authorization": f"Bearer {TOKEN}"}) as r:
                    out["bearer"] = r.status
                # the page's first request sets the cookie its scripts then carry
                async with http.get(base + f"/?token={TOKEN}") as r:
                    out["page"] = r.status
                async with http.get(base + "/static/app.js") as r:
                    out["cookie"] = r.status
                async with http.ws_connect(base + f"/ws?token={TOKEN}") as ws:
                    out["ws"] = json.loads((await ws.receive(timeout=5)).data)["type"]
            out["calls"] = source.health_calls
            out["refused"] = console.counters["refused_token"]
        finally:
            await console.stop()
        return out

    with caplog.at_level(logging.WARNING, logger="console.server"):
        out = run(main())
    assert [out[p] for p in ("/", "/api/health", "/static/app.js", "/ws", "wrong")] == [401] * 5
    assert out["bearer"] == out["page"] == out["cookie"] == 200 and out["ws"] == "scene"
    assert out["refused"] == 5
    # refused requests read nothing: only the bearer request and the WebSocket's first health ran health()
    assert out["calls"] == 2
    # logged once for the one peer, not five times
    assert sum("wrong token" in r.getMessage() for r in caplog.records) == 1


def test_a_console_off_loopback_without_a_token_gets_a_fresh_one():
    s = ConsoleSettings(bind="0.0.0.0").with_token()
    assert s.token_generated and len(s.token) >= 16
    assert ConsoleSettings().with_token().token is None  # loopback: none needed


def test_console_config_keys_are_checked(arena_yaml):
    data = arena_yaml("thesis")
    data["console"] = {"token": "short"}
    with pytest.raises(ConfigError, match="console.token"):
        parse_console(parse_arena(data, "a.yaml"))
    data["console"] = {"bind": "localhost"}
    with pytest.raises(ConfigError, match="console.bind"):
        parse_console(parse_arena(data, "a.yaml"))
    data["console"] = {"max_client": 3}
    with pytest.raises(ConfigError, match="max_clients"):
        parse_console(parse_arena(data, "a.yaml"))
    data["console"] = {"update_rate_hz": 20, "camera_view_rate_hz": 25}
    with pytest.raises(ConfigError, match="console.camera_view_rate_hz.*at most update_rate_hz"):
        parse_console(parse_arena(data, "a.yaml"))
    assert parse_console(parse_arena(arena_yaml("thesis"), "a.yaml")).camera_view_rate_hz == 10.0


def test_the_camera_views_ride_on_camera_view_rate_hz_of_the_updates(arena):
    async def main():
        console, source = await _serve(arena)  # 50 updates/s, camera views at the default 10/s
        source.pipeline.frames = _FreshFrames(source.pipeline.frames)
        client = Client(None, "test")
        console.clients.add(client)
        carried = []
        try:
            for _ in range(30):
                console.publish_once()
                carried.append("cameras" in json.loads(client.queue.get_nowait()))
        finally:
            console.clients.discard(client)
            await console.stop()
        return carried

    carried = run(main())
    # the first update carries them, then every fifth: 10 of 50 per second
    assert carried == [i % 5 == 0 for i in range(30)]


def test_bad_messages_cross_site_sockets_and_extra_clients_are_answered_or_refused(arena, caplog):
    import aiohttp

    async def main():
        console, source = await _serve(arena, max_clients=2)
        base = f"http://127.0.0.1:{console.port}"
        out = {}
        try:
            async with aiohttp.ClientSession() as http:
                try:
                    await http.ws_connect(base + "/ws", headers={"Origin": "http://evil.example"})
                except aiohttp.WSServerHandshakeError as e:
                    out["origin"] = e.status
                a = await http.ws_connect(base + "/ws")
                b = await http.ws_connect(base + "/ws", headers={"Origin": base})
                async with http.ws_connect(base + "/ws") as full:  # refused on the socket, with the reason
                    out["full"] = (json.loads((await full.receive(timeout=5)).data), (await full.receive()).type)
                errors = []
                for bad in ("{not json", "[1, 2]", '{"cmd": "seek", "t_s": 3}', '{"cmd": 5}'):
                    await a.send_str(bad)
                await a.send_bytes(b"\x00\x01")
                while len(errors) < 5:
                    m = json.loads((await a.receive(timeout=5)).data)
                    if m["type"] == "error":
                        errors.append(m["error"])
                out["errors"] = errors
                # an over-long message closes that client only
                await a.send_str("x" * 10_000)
                while not a.closed:
                    await a.receive(timeout=5)
                # the other client still gets its updates
                n = 0
                while n < 3:
                    if json.loads((await b.receive(timeout=5)).data)["type"] == "state":
                        n += 1
                out["b_states"] = n
                await b.close()
                await asyncio.sleep(0.1)
                out["clients_left"] = len(console.clients)
        finally:
            await console.stop()
        return out

    with caplog.at_level(logging.WARNING, logger="console.server"):
        out = run(main())
    assert out["origin"] == 403 and out["full"][0]["type"] == "error" and "at most 2" in out["full"][0]["error"]
    assert out["errors"][0] == "not JSON" and out["errors"][1] == 'expected {"cmd": "..."}'
    assert "replay controls" in out["errors"][2] and out["errors"][3] == 'expected {"cmd": "..."}'
    assert "binary" in out["errors"][4]
    assert out["b_states"] == 3 and out["clients_left"] == 0
    # logged once per cause
    bad = [r.getMessage() for r in caplog.records if "bad message" in r.getMessage()]
    assert len(bad) == 4  # json, shape, cmd, binary (shape twice: once)


def test_a_stalled_client_loses_updates_instead_of_queueing_them():
    async def main():
        ws = SimpleNamespace()
        c = Client(ws, "peer")
        for i in range(10):
            c.offer(str(i))
        return c

    c = asyncio.run(main())
    assert c.queue.qsize() == QUEUE_UPDATES and c.dropped == 10 - QUEUE_UPDATES
    assert [c.queue.get_nowait() for _ in range(QUEUE_UPDATES)] == ["8", "9"]  # the newest kept


def test_a_tab_closed_mid_stream_leaves_the_others_served(arena):
    import aiohttp

    async def main():
        console, source = await _serve(arena)
        base = f"http://127.0.0.1:{console.port}"
        try:
            async with aiohttp.ClientSession() as http:
                a = await http.ws_connect(base + "/ws")
                b = await http.ws_connect(base + "/ws")
                await a.receive(timeout=5)
                # abort the transport under the socket: no close handshake, as a killed tab
                a._response.connection.transport.abort()
                await asyncio.sleep(0.3)
                n = 0
                while n < 5:
                    if json.loads((await b.receive(timeout=5)).data)["type"] == "state":
                        n += 1
                left = len(console.clients)
                await b.close()
                return n, left, console.counters["update_errors"]
        finally:
            await console.stop()

    n, left, update_errors = run(main())
    assert n == 5 and left == 1 and update_errors == 0


class _FreshFrames(dict):
    """The frames of a camera that sends a new frame before every read (each read could build its view)."""

    def get(self, cid, default=None):
        o = dict.get(self, cid, default)
        if o is None:
            return default
        o = CameraFrame(o.capture_ns + 1_000_000, o.px, o.xn, o.label)
        self[cid] = o
        return o


def test_a_hidden_tab_gets_no_camera_views_and_none_are_built_for_it(arena):
    import aiohttp

    async def states(ws, n):
        out = []
        while len(out) < n:
            m = json.loads((await ws.receive(timeout=5)).data)
            if m["type"] in ("state", "error"):
                out.append(m)
        return out

    async def main():
        console, source = await _serve(arena, camera_view_rate_hz=25.0)  # every second update
        source.pipeline.frames = _FreshFrames(source.pipeline.frames)
        base = f"http://127.0.0.1:{console.port}"
        cam = arena.cameras[0].id
        out = {}
        try:
            async with aiohttp.ClientSession() as http:
                hidden = await http.ws_connect(base + "/ws")
                await hidden.send_str('{"cmd": "views", "on": "no"}')  # refused: the tab still shows the views
                out["bad"] = [m for m in await states(hidden, 6) if m["type"] == "error"]
                out["bad_views"] = sum("cameras" in m for m in await states(hidden, 6))
                await hidden.send_str('{"cmd": "views", "on": false}')
                await states(hidden, 3)  # updates already queued before the command
                builds = console.view.builds[cam]
                out["hidden"] = sum("cameras" in m for m in await states(hidden, 20))
                out["built_hidden"] = console.view.builds[cam] - builds
                shown = await http.ws_connect(base + "/ws")  # a second, visible tab
                await states(shown, 3)
                builds = console.view.builds[cam]
                out["shown"] = sum("cameras" in m for m in await states(shown, 20))
                out["built_shown"] = console.view.builds[cam] - builds
                out["hidden_beside"] = sum("cameras" in m for m in await states(hidden, 8))
                await hidden.close()
                await shown.close()
        finally:
            await console.stop()
        return out

    out = run(main())
    assert len(out["bad"]) == 1 and "views" in out["bad"][0]["error"]
    assert out["bad_views"] >= 2
    assert out["hidden"] == 0
    # 20 updates at 50/s: the views of every second one for a visible tab, only the watch's (2/s) for none
    assert out["built_hidden"] <= 3 and out["shown"] >= 9 and out["built_shown"] >= 9
    assert out["hidden_beside"] == 0


def test_the_health_tick_with_a_calibration_panel_never_pushes_out_a_state_update(arena):
    """A queue of QUEUE_UPDATES: the state update, then the health; the calibration state is offered again only to
    a tab whose queue dropped something since (a third message would drop the state: 30 of 31 updates/s)."""
    async def stop():
        pass

    calib = SimpleNamespace(version=1, state=lambda: {"counts": {}}, start=lambda: None, stop=stop)

    async def main():
        settings = ConsoleSettings(port=0, update_rate_hz=50.0).with_token()
        source = FakeSource(arena)
        console = ConsoleServer(settings, source, clock=source.clock, calibration=calib)
        await console.start()
        client = Client(None, "test")
        console.clients.add(client)
        got = []
        try:
            for slow in (False, True):
                if slow:  # a tab that fell behind: its queue dropped an update since its calibration state
                    for _ in range(QUEUE_UPDATES + 1):
                        console.publish_once()
                    while not client.queue.empty():
                        client.queue.get_nowait()
                console.publish_once()
                console.publish_health()
                got.append([json.loads(client.queue.get_nowait())["type"] for _ in range(client.queue.qsize())])
        finally:
            console.clients.discard(client)
            await console.stop()
        return got, client.dropped

    (fresh, behind), dropped = run(main())
    assert QUEUE_UPDATES == 2
    assert fresh == ["state", "health"]  # nothing dropped: the state kept
    assert dropped >= 1 and behind[-1] == "calib"  # the one that dropped gets it again
