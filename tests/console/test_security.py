"""The console against the operator's own browser: a request naming another host (DNS rebinding) or coming from a
page of another origin is refused before any handler runs, and changes nothing (each test reads the state the
request would change before and after)."""

from __future__ import annotations

import asyncio
import json

import aiohttp
import pytest

from console.server import ConsoleServer
from console.settings import ConsoleSettings, parse_console
from visionpos import protocol as P
from visionpos.config.arena import ConfigError, parse_arena

from .test_server import TOKEN, FakeSource

MASK_ALL = {"cmd": "mask", "camera": 1, "ignore": [[0, 0, 960, 640]]}


class FakeImages:
    """A station link that applies every mask it is sent (records it): what a foreign request must never reach."""

    def __init__(self):
        self.masks: list[tuple[int, list]] = []
        self.stills = 0

    def update_mask(self, camera_id, ignore=None):
        self.masks.append((camera_id, ignore))
        fut = asyncio.get_running_loop().create_future()
        fut.set_result(P.MaskAck(1, camera_id, 1, 1, int(P.MaskStatus.APPLIED), "mask applied"))
        return fut

    def request_image(self, camera_id, max_width=640, quality=80):
        self.stills += 1
        fut = asyncio.get_running_loop().create_future()
        fut.set_exception(TimeoutError("the station did not answer"))
        return fut

    async def wait(self, fut):
        return await fut


@pytest.fixture
def arena(arena_yaml):
    return parse_arena(arena_yaml("thesis"), "thesis.yaml")


async def _console(arena, **kw):
    source = FakeSource(arena)
    source.ingest = type("Ingest", (), {"images": FakeImages()})()
    console = ConsoleServer(ConsoleSettings(port=0, update_rate_hz=50.0, **kw).with_token(), source,
                            clock=source.clock)
    await console.start()
    return console, source


def state(console, source) -> dict:
    """What a request could change: the masks sent to stations, the scene's masks, the station reads."""
    return {"masks": list(source.ingest.images.masks), "stills": source.ingest.images.stills,
            "scene": json.dumps([c.get("mask") for c in console.view.scene["cameras"]]),
            "health_calls": source.health_calls}


def run(coro):
    return asyncio.run(asyncio.wait_for(coro, 30))


async def _reply(ws, kind):
    while True:
        m = json.loads((await ws.receive(timeout=5)).data)
        if m["type"] in (kind, "error"):
            return m


def test_a_foreign_host_is_refused_before_any_handler_and_changes_nothing(arena):
    async def main():
        console, source = await _console(arena)
        console._task.cancel()  # no updates: only the requests could read or change anything
        base = f"http://127.0.0.1:{console.port}"
        evil = f"attacker.example:{console.port}"
        out = {}
        try:
            before = state(console, source)
            async with aiohttp.ClientSession() as http:
                for path in ("/", "/api/health", "/api/scene", "/static/app.js"):
                    async with http.get(base + path, headers={"Host": evil}) as r:
                        out[path] = (r.status, await r.text())
                # the rebinding attack: a WebSocket from the attacker's page, Host and Origin both its own
                try:
                    async with http.ws_connect(base + "/ws", headers={"Host": evil, "Origin": f"http://{evil}"}) as ws:
                        await ws.send_json(MASK_ALL)
                        await ws.send_json({"cmd": "still", "camera": 1})
                        out["ws"] = await ws.receive(timeout=2)
                except aiohttp.WSServerHandshakeError as e:
                    out["ws"] = e.status
                await asyncio.sleep(0.1)
                out["after"] = state(console, source)
                # the console's own names still work, and the same mask from them is applied (the fake can fail)
                async with http.ws_connect(base + "/ws", headers={"Host": f"localhost:{console.port}"}) as ws:
                    await ws.send_json(MASK_ALL)
                    out["own"] = await _reply(ws, "mask")
            out["before"], out["counters"] = before, dict(console.counters)
        finally:
            await console.stop()
        return out

    out = run(main())
    for path in ("/", "/api/health", "/api/scene", "/static/app.js"):
        status, text = out[path]
        assert status == 403 and "Host" in text and "not this console" in text, (path, status, text)
    assert out["ws"] == 403
    assert out["after"] == out["before"]  # no mask sent, no still asked, no health read
    assert out["counters"]["refused_host"] == 5
    assert out["own"]["type"] == "mask" and out["own"]["ok"], out["own"]


def test_a_page_of_another_origin_is_refused_on_every_request(arena):
    async def main():
        console, source = await _console(arena)
        console._task.cancel()
        base = f"http://127.0.0.1:{console.port}"
        out = {}
        try:
            before = state(console, source)
            async with aiohttp.ClientSession() as http:
                for name in ("http://attacker.example", "http://127.0.0.1:P+1", "null"):
                    origin = name.replace("P+1", str(console.port + 1))
                    async with http.get(base + "/api/health", headers={"Origin": origin}) as r:
                        out[name] = r.status
                    try:
                        async with http.ws_connect(base + "/ws", headers={"Origin": origin}) as ws:
                            await ws.send_json(MASK_ALL)
                            out["ws " + name] = await ws.receive(timeout=2)
                    except aiohttp.WSServerHandshakeError as e:
                        out["ws " + name] = e.status
                # a fetch without CORS sends no Origin; the browser's fetch metadata still says where it comes from
                fetch = {"Sec-Fetch-Site": "cross-site", "Sec-Fetch-Mode": "no-cors", "Sec-Fetch-Dest": "image"}
                async with http.get(base + "/api/health", headers=fetch) as r:
                    out["no-cors"] = r.status
                await asyncio.sleep(0.1)
                out["after"] = state(console, source)
                # the page opened through an SSH tunnel (local port P+1): its Origin is its Host, both loopback
                tunnel = f"127.0.0.1:{console.port + 1}"
                async with http.ws_connect(base + "/ws", headers={"Host": tunnel, "Origin": f"http://{tunnel}"}) as ws:
                    out["tunnel"] = json.loads((await ws.receive(timeout=5)).data)["type"]
                # a link from elsewhere (a navigation) opens the page; the console's own page opens the socket
                nav = {"Sec-Fetch-Site": "cross-site", "Sec-Fetch-Mode": "navigate", "Sec-Fetch-Dest": "document"}
                async with http.get(base + "/", headers=nav) as r:
                    out["navigate"] = r.status
                own = f"http://localhost:{console.port}"
                async with http.ws_connect(base + "/ws", headers={"Origin": own}) as ws:
                    out["own"] = json.loads((await ws.receive(timeout=5)).data)["type"]
            out["before"], out["refused"] = before, console.counters["refused_origin"]
        finally:
            await console.stop()
        return out

    out = run(main())
    for name in ("http://attacker.example", "http://127.0.0.1:P+1", "null"):
        assert out[name] == 403 and out["ws " + name] == 403, (name, out)
    assert out["no-cors"] == 403 and out["navigate"] == 200 and out["tunnel"] == "scene"
    assert out["after"] == out["before"] and out["refused"] == 7
    assert out["own"] == "scene"


def test_the_console_answers_to_its_own_addresses_only(arena):
    """Bound to 0.0.0.0: the address a connection came in on is the console's (127.0.0.2 here: another loopback
    address), another address or port is not, and a name in console.hosts is."""

    async def main():
        console, source = await _console(arena, bind="0.0.0.0", token=TOKEN, hosts=("mocap.lab",))
        console._task.cancel()
        port = console.port
        out = {}
        auth = {"Authorization": f"Bearer {TOKEN}"}
        try:
            async with aiohttp.ClientSession() as http:
                for host in ("127.0.0.2:P", "127.0.0.3:P", "127.0.0.2:P+1", "MOCAP.lab:P", "localhost:P", "[::1]:P",
                             "127.0.0.2", "localhost:P+1", "[::1]:P+1", "mocap.lab:P+1", "[::1", "attacker.example"):
                    value = host.replace(":P+1", f":{port + 1}").replace(":P", f":{port}")
                    async with http.get(f"http://127.0.0.2:{port}/api/health", headers={"Host": value, **auth}) as r:
                        out[host] = r.status
        finally:
            await console.stop()
        return out

    out = run(main())
    assert out == {"127.0.0.2:P": 200, "127.0.0.3:P": 403, "127.0.0.2:P+1": 403, "MOCAP.lab:P": 200,
                   "localhost:P": 200, "[::1]:P": 200,
                   "127.0.0.2": 403,  # no port: only port 80 may leave it out
                   "localhost:P+1": 200, "[::1]:P+1": 200,  # a loopback name on any port: an SSH tunnel's end
                   "mocap.lab:P+1": 403, "[::1": 403, "attacker.example": 403}


def test_allowed_hosts_list_the_loopback_names_the_bind_address_and_port_80_without_port():
    c = ConsoleServer.__new__(ConsoleServer)
    c.settings, c.port = ConsoleSettings(bind="192.168.1.10", token=TOKEN), 8080
    assert c.allowed_hosts() == {"127.0.0.1:8080", "localhost:8080", "[::1]:8080", "192.168.1.10:8080"}
    c.settings, c.port = ConsoleSettings(bind="::", token=TOKEN), 80
    assert c.allowed_hosts("::ffff:10.0.0.5") == {"127.0.0.1:80", "localhost:80", "[::1]:80", "10.0.0.5:80",
                                                  "127.0.0.1", "localhost", "[::1]", "10.0.0.5"}


def test_the_printed_address_carries_a_fresh_token_only():
    c = ConsoleServer.__new__(ConsoleServer)
    c.port = 8080
    c.settings = ConsoleSettings(bind="0.0.0.0").with_token()  # made at start: the terminal is the one way to it
    assert c.url == f"http://127.0.0.1:8080/?token={c.settings.token}" and c.address == "http://127.0.0.1:8080/"
    c.settings = ConsoleSettings(bind="0.0.0.0", token=TOKEN)  # configured: the operator has it
    assert c.url == c.address == "http://127.0.0.1:8080/"


def test_console_hosts_are_checked(arena_yaml):
    data = arena_yaml("thesis")
    data["console"] = {"hosts": ["http://mocap.lab:8080"]}
    with pytest.raises(ConfigError, match="console.hosts"):
        parse_console(parse_arena(data, "a.yaml"))
    data["console"] = {"hosts": ["Mocap.Lab"]}
    assert parse_console(parse_arena(data, "a.yaml")).hosts == ("mocap.lab",)


BAD = [  # (what the client sends, a word the refusal must hold)
    ("{not json", "not JSON"),
    ('{"cmd": "fly", "camera": 1}', "unknown command 'fly'"),
    ('{"cmd": "rays", "camera": 99}', "camera 99 is none of [1, 2, 3, 4]"),
    ('{"cmd": "still", "camera": 99}', "camera 99 is none of"),
    ('{"cmd": "mask", "camera": 99, "ignore": [[0, 0, 5, 5]]}', "camera 99 is none of"),
    ('{"cmd": "mask", "camera": 1, "ignore": [[0, 0, 5000, 10]]}', "not inside the camera's 960x640 image"),
    ('{"cmd": "mask", "camera": 1, "ignore": [[-5, 0, 10, 10]]}', "not inside"),
    ('{"cmd": "views", "on": "no"}', "views: expected"),
    ('{"cmd": "mask", "camera": 1, "ignore": [' + "[0, 0, 1, 1], " * 400 + "[0, 0, 1, 1]]}", "over 4096 bytes"),
]


def test_bad_messages_and_a_tab_too_many_get_a_refusal_each_and_change_nothing(arena):
    """Each bad message is answered {"type": "error", "error": why} to its sender and changes nothing (the masks
    sent to stations, the scene, what each tab asked for); the oversized one closes that socket after its answer;
    a tab beyond console.max_clients gets its refusal on the socket, then a close (1013, try again later)."""

    async def main():
        console, source = await _console(arena, max_clients=2)
        console._task.cancel()
        base = f"http://127.0.0.1:{console.port}"
        out = {"replies": []}
        try:
            async with aiohttp.ClientSession() as http:
                other = await http.ws_connect(base + "/ws")
                await other.send_json({"cmd": "rays", "camera": 2})
                await asyncio.sleep(0.1)
                before = state(console, source), sorted((c.rays, c.views) for c in console.clients)
                async with http.ws_connect(base + "/ws") as ws:
                    for text, _ in BAD:
                        await ws.send_str(text)
                        out["replies"].append(await _reply(ws, "never"))
                    out["closed"] = ((await ws.receive(timeout=5)).type, ws.close_code)
                    out["tab_settings"] = sorted((c.rays, c.views) for c in console.clients)
                await asyncio.sleep(0.1)
                async with http.ws_connect(base + "/ws") as third:  # the limit is 2: other + this one
                    async with http.ws_connect(base + "/ws") as fourth:
                        out["full"] = json.loads((await fourth.receive(timeout=5)).data)
                        out["full_close"] = ((await fourth.receive(timeout=5)).type, fourth.close_code)
                    out["third"] = json.loads((await third.receive(timeout=5)).data)["type"]
                out["after"] = state(console, source), sorted((c.rays, c.views) for c in console.clients)
                out["before"] = before
                await other.close()
            out["counters"] = dict(console.counters)
        finally:
            await console.stop()
        return out

    out = run(main())
    for (text, why), reply in zip(BAD, out["replies"]):
        assert reply["type"] == "error" and why in reply["error"], (text[:60], reply)
    assert out["closed"] == (aiohttp.WSMsgType.CLOSE, 1009)  # after the oversized message only
    assert out["full"]["type"] == "error" and "at most 2 tabs" in out["full"]["error"]
    assert out["full_close"] == (aiohttp.WSMsgType.CLOSE, 1013)
    assert out["third"] == "scene"
    for st, tabs in (out["before"], out["after"]):
        st.pop("health_calls")  # a tab that connects gets the health: a read, as for any tab
    assert out["after"] == out["before"]  # no mask, no still, the scene and the other tab's rays as they were
    assert out["counters"]["bad_messages"] == len(BAD) and out["counters"]["refused_full"] == 1


@pytest.mark.slow
def test_the_console_token_reaches_no_recording_and_no_log_and_the_recording_replays(tmp_path, capsys, caplog):
    """`demo --set console.token=... --record`: the token is nowhere: not in the recording's bytes, not in a log
    record, not on the terminal (a configured token is never printed); the recording replays."""
    import logging

    from mcap.reader import make_reader

    from visionpos.analysis.replay import replay_log
    from visionpos.cli import main

    token = "tok-" + "7Qx9" * 6
    rec = tmp_path / "x.mcap"
    with caplog.at_level(logging.DEBUG):
        rc = main(["demo", "--duration", "1.5", "--seed", "3", "--console-port", "0", "--set",
                   f"console.token={token}", "--record", str(rec)])
    out = capsys.readouterr()
    assert rc == 0, out.err
    assert "console at http://127.0.0.1:" in out.out
    assert token not in out.out and token not in out.err and token not in caplog.text  # configured: never printed
    data = rec.read_bytes()
    assert token.encode() not in data
    with rec.open("rb") as f:
        meta = {m.name: m.metadata for m in make_reader(f).iter_metadata()}
    import yaml

    from visionpos.recording.writer import REDACTED

    assert yaml.safe_load(meta["visionpos.config"]["yaml"])["console"]["token"] == REDACTED
    res = replay_log(rec)
    assert res.n_frames > 0
