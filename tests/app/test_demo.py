"""`visionpos demo` end to end on 127.0.0.1: stations, server, bridge, fake autopilots."""

from __future__ import annotations

import json

import pytest


@pytest.mark.slow
def test_demo_json_summary_is_sane_and_its_recording_replays(capsys, tmp_path):
    from visionpos.cli import main

    rec = tmp_path / "demo.mcap"
    rc = main(["demo", "--duration", "3", "--json", "--seed", "3", "--record", str(rec)])
    out = capsys.readouterr()
    assert rc == 0, out.err
    s = json.loads(out.out)  # stdout is only the JSON; live status went to stderr
    assert "fps" in out.err
    assert s["duration_s"] == pytest.approx(3.0, abs=0.05)
    assert [b["name"] for b in s["bodies"]] == ["quad"]
    quad = s["bodies"][0]
    for key in ("position_rmse_mm", "rotation_rmse_deg", "tracked_fraction", "rate_hz"):
        assert quad[key] is not None
    # errors are against the simulator's truth; the thesis arena tracks to about a millimetre
    assert quad["tracked_fraction"] > 0.8
    assert quad["position_rmse_mm"] < 10.0
    assert quad["rotation_rmse_deg"] < 3.0
    assert quad["rate_hz"] > 30.0
    # the autopilot really got poses, and they convert back to the true position (NED -> world)
    assert quad["mavlink_messages"] > 30
    assert quad["mavlink_position_rmse_mm"] < 10.0
    # capture -> MAVLink send cannot be shorter than the simulated exposure -> server receive (gamma, mean 4 ms)
    lat = s["latency_ms"]
    assert lat["p50"] is not None and lat["p99"] is not None
    assert 2.0 < lat["p50"] <= lat["p99"]
    # every station registered, synced and streamed ~100 fps through the real protocol
    assert len(s["stations"]) == 4
    for st in s["stations"]:
        assert st["frames_accepted"] > 0.9 * 300
        # the station's clock was offset by the scenario's raw offset; the server saw the sync result
        assert st["clock_offset_reported_ms"] == pytest.approx(st["clock_offset_true_ms"], abs=0.5)
    assert s["server"]["malformed"] == 0
    # signed with the demo's in-memory key (no key file on this machine: the tests' default key is absent)
    assert s["server"]["authenticated"] is True and s["server"]["auth_failed"] == 0

    # the live session, recorded by the server with the simulator's truth, replays offline
    from visionpos.analysis.replay import replay_log

    res = replay_log(rec)
    assert res.n_frames == s["server"]["frames_accepted"]
    m = res.metrics()[0]
    assert m.name == "quad" and m.tracked_fraction > 0.8 and m.position_rmse_mm < 10.0
