"""`visionpos replay LOG --view`: the session steps a recording as `visionpos replay` does; play, pause, seek, speed."""

from __future__ import annotations

import asyncio
import json

import numpy as np
import pytest

from console.replay import ReplaySession
from visionpos.analysis.replay import load_settings, run_pipeline
from visionpos.recording import RecordingReader


@pytest.fixture(scope="module")
def session_parts(thesis_log):
    r = RecordingReader(thesis_log)
    arena = load_settings(r.config)
    return arena, list(r.packets_with_source())


def test_stepping_gives_the_poses_of_a_plain_replay(session_parts):
    arena, packets = session_parts
    ref = run_pipeline(arena, packets)
    s = ReplaySession(arena, packets)
    t_mid = s.t0_ns + 1_500_000_000
    # in slices of any size, as the console's loop runs it
    while not s.advance_to(t_mid, budget_s=0.001):
        pass
    quad = ref.bodies["quad"]
    k = int(np.searchsorted(quad.tick_ns, s.last_states[0].time_ns))
    assert quad.tick_ns[k] == s.last_states[0].time_ns
    assert s.last_states[0].tracked and quad.tracked[k]
    np.testing.assert_array_equal(s.last_states[0].position, quad.position[k])


def test_controls_pause_seek_back_and_speed(session_parts):
    arena, packets = session_parts

    async def main():
        s = ReplaySession(arena, packets)
        player = asyncio.create_task(s.run())
        try:
            await asyncio.sleep(0.4)
            played = s.clock() - s.t0_ns
            r = await s.command({"cmd": "pause"})
            assert r["playing"] is False
            t_paused = s.clock()
            await asyncio.sleep(0.2)
            assert s.clock() == t_paused  # paused: the recording clock stands
            r = await s.command({"cmd": "seek", "t_s": 2.0})
            assert r["t_s"] == pytest.approx(2.0, abs=0.011)
            forward = s.last_states[0]
            r = await s.command({"cmd": "seek", "t_s": 0.5})  # back: a fresh pipeline run up to 0.5 s
            assert r["t_s"] == pytest.approx(0.5, abs=0.011) and s.ticks == pytest.approx(50, abs=1)
            await s.command({"cmd": "speed", "x": 4})
            await s.command({"cmd": "play"})
            t0 = s.clock()
            await asyncio.sleep(0.3)
            fast = (s.clock() - t0) * 1e-9
            for bad in ({"cmd": "speed", "x": 100}, {"cmd": "seek", "t_s": -1}, {"cmd": "seek", "t_s": True},
                        {"cmd": "rewind"}):
                with pytest.raises(ValueError):
                    await s.command(bad)
            return played, forward, fast, s.speed
        finally:
            player.cancel()

    played, forward, fast, speed = asyncio.run(asyncio.wait_for(main(), 60))
    assert played > 0  # it played at 1x from the start
    assert forward.tracked
    assert speed == 4.0 and fast > 0.6  # 0.3 s of wall time at 4x: about 1.2 s of recording (slow hosts: less)


def test_the_console_drives_the_replay_over_its_websocket(session_parts):
    import aiohttp

    from console.server import ConsoleServer
    from console.settings import ConsoleSettings

    arena, packets = session_parts

    async def main():
        s = ReplaySession(arena, packets)
        s.playing = False
        console = ConsoleServer(ConsoleSettings(port=0), s, clock=s.clock, controls=s.command, extra=s.position)
        await console.start()
        try:
            async with aiohttp.ClientSession() as http:
                async with http.ws_connect(f"http://127.0.0.1:{console.port}/ws") as ws:
                    await ws.send_str(json.dumps({"cmd": "seek", "t_s": 1.0}))
                    await ws.send_str(json.dumps({"cmd": "speed", "x": "fast"}))
                    replies, states = [], []
                    # a state built while the seek ran may still be queued behind its answer: wait for the target
                    while len(replies) < 2 or not states or abs(states[-1]["replay"]["t_s"] - 1.0) > 0.011:
                        m = json.loads((await ws.receive(timeout=10)).data)
                        if m["type"] in ("replay", "error"):
                            replies.append(m)
                        elif m["type"] == "state" and replies and "cameras" in m:  # every second one has them
                            states.append(m)
            return replies, states[-1]
        finally:
            await console.stop()

    replies, state = asyncio.run(asyncio.wait_for(main(), 60))
    assert replies[0]["type"] == "replay" and replies[0]["t_s"] == pytest.approx(1.0, abs=0.011)
    assert replies[1] == {"type": "error", "error": "speed: give x between 0.05 and 16"}
    assert state["replay"]["t_s"] == pytest.approx(1.0, abs=0.011) and state["replay"]["playing"] is False
    assert state["bodies"][0]["name"] == "quad" and state["bodies"][0]["tracked"]
    assert all(len(c["blobs"]) > 0 for c in state["cameras"])
    assert any(len(c["pred"]) == 4 for c in state["cameras"])


def test_a_replay_scene_names_its_file_and_says_it_is_a_replay(session_parts):
    from console.view import ConsoleView

    arena, packets = session_parts
    scene = ConsoleView(ReplaySession(arena, packets, name="flight.mcap")).scene
    assert scene["source"] == "flight.mcap" and scene["mode"] == "replay"
    # a live server's scene: the arena's file, live
    live = ConsoleView(type("Live", (), {"arena": arena})()).scene
    assert live["source"] == arena.source and live["mode"] == "live"
