"""The calibration assistant in `visionpos record`'s console on 127.0.0.1: a simulated wand wave fills the coverage,
"enough" comes, Solve writes the calibrated arena and shows residuals; refused commands change nothing."""

from __future__ import annotations

import asyncio
import json

import aiohttp
import numpy as np
import pytest

import console.calibration as calibration
from console.calibration import CalibrationAssistant, default_out
from console.settings import ConsoleSettings
from visionpos.app.console import RecordSource, open_console
from visionpos.calibration.coverage import Thresholds
from visionpos.config.arena import load_arena

TOKEN = "calib-token-0123456789"
# the simulated wave stays in the middle of the volume: 8 to 12 % of each image; a real one covers far more
SIM_THRESHOLDS = Thresholds(min_coverage=0.05)


@pytest.fixture(scope="module")
def wave():
    from visionpos.sim import load_scenario, simulate

    sc = load_scenario("thesis", ["sim.duration=8"], session="wand")
    res = simulate(sc)
    return sc.arena, sorted(res.frames, key=lambda f: f.recv_ns)


async def _console(arena, out, **settings):
    source = RecordSource(arena, CalibrationAssistant(arena, out, SIM_THRESHOLDS))
    console = await open_console(ConsoleSettings(port=0, update_rate_hz=30.0, **settings).with_token(), source)
    return console, source


async def _next(ws, kind, timeout_s=30.0, until=None):
    """The next message of this type (and satisfying until)."""
    async def wait():
        while True:
            msg = json.loads((await ws.receive()).data)
            if msg["type"] == kind and (until is None or until(msg)):
                return msg
    return await asyncio.wait_for(wait(), timeout_s)


def test_a_wand_wave_fills_in_and_solve_gives_the_calibration(wave, tmp_path, monkeypatch):
    monkeypatch.setattr(calibration, "REFRESH_S", 0.1)
    arena, frames = wave
    out = tmp_path / "arena.yaml"

    async def main():
        console, source = await _console(arena, out)
        try:
            async with aiohttp.ClientSession() as http, http.ws_connect(f"http://127.0.0.1:{console.port}/ws") as ws:
                first = await _next(ws, "calib")
                assert first["calib"]["steps"] == 0 and not first["calib"]["enough"]
                await ws.send_str(json.dumps({"cmd": "solve"}))  # nothing gathered yet: refused
                err = await _next(ws, "error")
                assert err["error"].startswith("solve: not enough wand frames")
                assert source.calibration.solve == {"running": False, "result": None, "error": None}
                seen = []
                for i in range(0, len(frames), 400):
                    for f in frames[i:i + 400]:
                        source.push(f)
                    pushed = min(i + 400, len(frames))  # counted once the refresh labelled them all
                    msg = await _next(ws, "calib", until=lambda m: sum(c["frames"] for c in m["calib"]["cameras"])
                                      == pushed)
                    seen.append(msg["calib"])
                cover = np.array([[c["coverage"] for c in s["cameras"]] for s in seen])
                assert np.all(np.diff(cover, axis=0) >= 0) and np.all(cover[-1] > cover[0])  # it fills in
                assert not seen[0]["enough"] and seen[0]["missing"]
                last = seen[-1]
                assert last["enough"] and last["missing"] == [], last["missing"]
                assert all(p["frames"] >= 100 for p in last["pairs"])
                await ws.send_str(json.dumps({"cmd": "solve"}))
                reply = await _next(ws, "calib_reply")
                assert reply["solve"] == "started" and reply["frames"] == len(frames)
                await ws.send_str(json.dumps({"cmd": "solve"}))  # a second while it runs: refused
                assert "a solve is running" in (await _next(ws, "error"))["error"]
                done = await _next(ws, "calib", 90.0, until=lambda m: not m["calib"]["solve"]["running"])
                solve = done["calib"]["solve"]
                assert solve["error"] is None, solve["error"]
                r = solve["result"]
                # the simulator's centroid noise is 0.2 px (x and y): the residual norm is about 0.2 * sqrt(2)
                # less the fitted degrees of freedom; `calibrate wand` on this wave reports 0.21 to 0.25 px
                assert all(0.1 < c["rms_px"] < 0.4 for c in r["cameras"]), r["cameras"]
                assert abs(r["wand_ac_mean_err_mm"]) < 0.5 and r["wand_ac_std_mm"] < 1.5
                assert r["out"] == str(out)
        finally:
            await console.stop()
        cal = load_arena(str(out))
        assert [c.name for c in cal.cameras] == [c.name for c in arena.cameras]
        assert cal.raw["calibration"]["extrinsics"]["rms_px"]["pi1"] == pytest.approx(r["cameras"][0]["rms_px"],
                                                                                      abs=1e-3)

    asyncio.run(asyncio.wait_for(main(), 150))


def test_solve_needs_the_token_and_bad_solve_commands_change_nothing(wave, tmp_path):
    arena, frames = wave
    out = tmp_path / "arena.yaml"

    async def main():
        console, source = await _console(arena, out, token=TOKEN)
        try:
            for f in frames:
                source.push(f)
            await source.calibration.refresh()
            version = source.calibration.version
            async with aiohttp.ClientSession() as http:
                for q in ("", "?token=wrong-token-0123456789"):
                    with pytest.raises(aiohttp.WSServerHandshakeError) as e:
                        await http.ws_connect(f"http://127.0.0.1:{console.port}/ws{q}")
                    assert e.value.status == 401
                async with http.ws_connect(f"http://127.0.0.1:{console.port}/ws?token={TOKEN}") as ws:
                    await _next(ws, "calib")
                    for bad in ({"cmd": "solve", "frames": 10}, {"cmd": "solve", "out": "/etc/x.yaml"}):
                        await ws.send_str(json.dumps(bad))
                        assert (await _next(ws, "error"))["error"] == 'calibration: expected {"cmd": "solve"}'
            assert source.calibration.solve == {"running": False, "result": None, "error": None}
            assert source.calibration.version == version
            assert console.counters["refused_token"] == 2
        finally:
            await console.stop()
        assert not out.exists()

    asyncio.run(asyncio.wait_for(main(), 60))


def test_solve_is_refused_where_there_is_no_assistant_and_default_out_sits_beside_the_recording(wave, tmp_path):
    arena, _ = wave

    async def main():
        console = await open_console(ConsoleSettings(port=0).with_token(), RecordSource(arena))
        try:
            async with aiohttp.ClientSession() as http, http.ws_connect(f"http://127.0.0.1:{console.port}/ws") as ws:
                await ws.send_str(json.dumps({"cmd": "solve"}))
                assert "no calibration assistant" in (await _next(ws, "error"))["error"]
        finally:
            await console.stop()

    asyncio.run(asyncio.wait_for(main(), 30))
    assert default_out(tmp_path / "wave.mcap") == tmp_path / "wave.calibrated.yaml"


def test_replay_view_feeds_the_assistant_and_a_seek_back_or_a_restart_keeps_its_frames(tmp_path):
    from console.replay import ReplaySession
    from visionpos.config.arena import parse_arena
    from visionpos.recording import RecordingReader
    from visionpos.sim.write import write_recording

    log = tmp_path / "wave.mcap"
    write_recording("thesis", log, duration_s=3.0, session="wand")
    reader = RecordingReader(log)
    arena = parse_arena(reader.config, str(log))
    assistant = CalibrationAssistant(arena, default_out(log), SIM_THRESHOLDS)
    session = ReplaySession(arena, list(reader.packets_with_source()), calibration=assistant)

    async def main():
        session.advance_to(session.end_ns)
        n = len(assistant.frames)
        assert n > 500
        await assistant.refresh()
        assert assistant.state()["steps"] > 50
        await session.seek(0.5)  # backwards: the pipeline starts again, the wand frames gathered stay
        assert len(assistant.frames) == n
        session.advance_to(session.end_ns)  # the same packets again: none counted twice
        assert len(assistant.frames) == n and session.finished
        await session.command({"cmd": "play"})  # play after the end: from the start, the frames kept
        assert session.clock() == session.t0_ns and session.playing and len(assistant.frames) == n
        await assistant.stop()

    asyncio.run(main())


def test_concurrent_refreshes_count_each_frame_once(wave, tmp_path):
    arena, frames = wave
    assistant = CalibrationAssistant(arena, tmp_path / "a.yaml", SIM_THRESHOLDS)

    async def main():
        for f in frames[:800]:
            assistant.push(f)
        await asyncio.gather(assistant.refresh(), assistant.refresh(), assistant.refresh())
        return assistant.state()

    s = asyncio.run(main())
    assert sum(c["frames"] for c in s["cameras"]) == 800


def test_calibrate_out_without_the_console_is_refused(tmp_path, capsys):
    from visionpos.cli.main import main

    rec = tmp_path / "wave.mcap"
    rc = main(["record", "--out", str(rec), "--config", "thesis", "--set", "server.insecure=true", "--no-console",
               "--calibrate-out",
               str(tmp_path / "a.yaml"), "--duration", "0.1"])
    assert rc != 0 and "--calibrate-out" in capsys.readouterr().err
    assert not rec.exists()
