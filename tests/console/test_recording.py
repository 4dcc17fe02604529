"""The console's record button, server side (console/recording.py): a start makes a new timestamped file in
console.record_dir and the running server records into it; a stop closes it with every packet handed to it; the
refusals change nothing."""

from __future__ import annotations

import asyncio
import re

import pytest

from console.recording import ConsoleRecorder, recording_name
from visionpos.analysis.replay import load_settings
from visionpos.recording import RecordingReader
from visionpos.server.service import FusionServer
from visionpos.server.settings import ServerSettings


def test_the_name_is_the_local_time_and_never_an_existing_file(tmp_path):
    t = (2026, 3, 9, 14, 5, 7, 0, 68, -1)
    first = recording_name(tmp_path, t)
    assert first == tmp_path / "visionpos-20260309-140507.mcap"
    first.write_bytes(b"")
    assert recording_name(tmp_path, t) == tmp_path / "visionpos-20260309-140507-2.mcap"


def test_start_records_the_running_server_and_stop_keeps_every_packet(tmp_path, thesis_log):
    reader = RecordingReader(thesis_log)
    arena = load_settings(reader.config, None, [])
    server = FusionServer(arena, ServerSettings.for_replay(arena), port=0)
    # the recorded packets as a live server takes them: registered by their HELLOs, no cookies, clocked by them
    server.ingest.verify_cookies = False
    server.ingest.set_start(-(1 << 62))
    server.ingest.clock = lambda: now_ns[0]
    now_ns = [0]
    packets = list(reader.packets_with_source())
    folder = tmp_path / "flights"
    rec = ConsoleRecorder(server, folder)
    accepted = []
    server.ingest.taps = (lambda recv_ns, data: accepted.append(data),)  # what ingest hands on (recorded too)

    async def main():
        for t, data, src in packets[:200]:  # before the start: not recorded
            now_ns[0] = t
            server.ingest.handle(data, src or ("127.0.0.1", 9000), t)
        assert rec.state() is None
        reply = await rec.command({"cmd": "record", "on": True})
        assert re.fullmatch(r"visionpos-\d{8}-\d{6}\.mcap", reply["recording"]["file"])
        accepted.clear()
        for t, data, src in packets[200:600]:
            now_ns[0] = t
            server.ingest.handle(data, src or ("127.0.0.1", 9000), t)
        during = list(accepted)
        # a second start is refused and opens no file; the recording goes on
        with pytest.raises(ValueError, match="already recording to visionpos-"):
            await rec.command({"cmd": "record", "on": True})
        assert len(list(folder.iterdir())) == 1 and server.recorder is not None
        stopped = (await rec.command({"cmd": "record", "on": False}))["stopped"]
        for t, data, src in packets[600:700]:  # after the stop: not recorded
            now_ns[0] = t
            server.ingest.handle(data, src or ("127.0.0.1", 9000), t)
        with pytest.raises(ValueError, match="not recording"):
            await rec.command({"cmd": "record", "on": False})
        return during, stopped

    during, stopped = asyncio.run(main())
    assert len(during) > 300
    path = folder / stopped["file"]
    assert stopped["bytes"] == path.stat().st_size
    assert [data for _, data in RecordingReader(path).packets()] == during
    assert server.recorder is None and server.ingest.recorder is None and rec.state() is None


def test_a_replay_or_a_bad_command_is_refused_and_makes_no_file(tmp_path):
    class Replay:  # a source without start_recording: a replay session, `record`'s RecordSource
        recorder = None

    folder = tmp_path / "flights"
    for source, msg, why in ((Replay(), {"cmd": "record", "on": True}, "cannot record"),
                             (Replay(), {"cmd": "record", "on": "yes"}, "true or false")):
        with pytest.raises(ValueError, match=why):
            asyncio.run(ConsoleRecorder(source, folder).command(msg))
    assert not folder.exists()
