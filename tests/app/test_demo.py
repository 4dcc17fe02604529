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


def _held_tcp_port():
    """A listening TCP socket on 127.0.0.1 (its port is taken for anyone else)."""
    import socket

    s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    s.bind(("127.0.0.1", 0))
    s.listen(1)
    return s


@pytest.mark.slow
def test_the_demo_serves_its_vrpn_and_pose_stream_sections_to_real_clients():
    """`--set vrpn.port=...` and `--set pose_stream.destination=...` open what they say: a libmotioncapture client
    gets the body from the demo's VRPN server, a UDP socket gets the pose stream."""
    import asyncio
    import gc
    import socket
    import sys

    from tests.bridge.test_vrpn import CLIENT, HAVE_MC
    from visionpos.app.demo import demo_arena, run_demo
    from visionpos.app.ports import free_port

    vrpn_port = free_port()
    listener = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    listener.bind(("127.0.0.1", 0))
    listener.settimeout(0.0)
    sets = ["vrpn.host=127.0.0.1", f"vrpn.port={vrpn_port}", f"pose_stream.destination=127.0.0.1:"
            f"{listener.getsockname()[1]}", "pose_stream.format=json"]
    arena = demo_arena("thesis", 4.0, 3, sets)
    lines: list[bytes] = []

    frozen: list[int] = []

    async def during(ctx) -> None:
        frozen.append(gc.get_freeze_count())
        assert [o.opens() for o in ctx.outputs[-1].outputs] == [
            {"pose_stream.destinations": f"127.0.0.1:{listener.getsockname()[1]}"},
            {"vrpn.host": "127.0.0.1", "vrpn.port": vrpn_port}]
        if not HAVE_MC:
            return
        await asyncio.sleep(0.5)  # tracking
        client = await asyncio.create_subprocess_exec(sys.executable, "-c", CLIENT, f"127.0.0.1:{vrpn_port}", "2.0",
                                                      stdout=asyncio.subprocess.PIPE)
        out, _ = await client.communicate()
        lines.extend(out.splitlines())

    summary = asyncio.run(run_demo(arena, 4.0, None, during=during))
    assert summary["bodies"][0]["tracked_fraction"] > 0.8
    # the start-up heap is out of the collector's reach while the demo streams (app/serve.py), and back after
    assert frozen[0] > 10_000 and gc.get_freeze_count() == 0
    datagrams = []
    while True:
        try:
            datagrams.append(listener.recv(65536))
        except BlockingIOError:
            break
    listener.close()
    assert len(datagrams) > 100  # about one per output tick for 4 s (the socket's buffer holds a few hundred)
    assert any(b'"quad"' in d for d in datagrams[-50:])
    if HAVE_MC:
        frames = [json.loads(x) for x in lines]
        seen = [f for f in frames if "quad" in f["bodies"]]
        assert len(seen) > 50, frames[:3]  # 2 s of poses


@pytest.mark.slow
def test_a_taken_output_port_stops_the_demo_at_start_with_one_line_naming_the_key(capsys):
    from visionpos.cli import main

    held = _held_tcp_port()
    port = held.getsockname()[1]
    try:
        rc = main(["demo", "--duration", "1", "--quiet", "--no-console", "--set", "vrpn.host=127.0.0.1",
                   "--set", f"vrpn.port={port}"])
    finally:
        held.close()
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2
    assert len(err) == 1 and f"vrpn.port={port}" in err[0] and "in use" in err[0], err


def test_set_vehicles_applies_to_the_vehicles_the_demo_makes():
    """`visionpos demo --set vehicles.0.message=odometry` on an arena without a vehicles section (issue 31: it
    failed with "`vehicles` is empty")."""
    from bridge.config import parse_vehicles
    from visionpos.app.demo import demo_arena

    vehicles = parse_vehicles(demo_arena("thesis", 10.0, None, ["vehicles.0.message=odometry"]))
    assert [v.message for v in vehicles] == ["odometry"]
    assert vehicles[0].endpoint.kind == "udpin" and vehicles[0].endpoint.host == "127.0.0.1"
    assert [v.message for v in parse_vehicles(demo_arena("thesis", 10.0, None, []))] == ["vision_position_estimate"]


def test_the_demo_signs_each_vehicle_s_link_with_its_own_key():
    """A key per vehicle (docs/autopilot-setup.md, Endpoints): a pose that a crossed link carries to another
    drone fails that autopilot's signature check."""
    from bridge.config import parse_vehicles
    from visionpos.app.demo import demo_arena

    vehicles = parse_vehicles(demo_arena("pair", 10.0, None, []))
    keys = [v.signing_key for v in vehicles]
    assert len(vehicles) >= 2 and all(k is not None and len(k) == 32 for k in keys)
    assert len(set(keys)) == len(keys)
