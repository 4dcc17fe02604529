"""A station's first HELLO says its camera's real resolution: simulated stations (whose size comes with the
simulator's camera, at open) register with a real server without a packet counted malformed (issue 27, item 12)."""

from __future__ import annotations

import asyncio
import threading

import pytest

from stations.agent import StationAgent
from stations.config import parse_station
from visionpos.config.arena import parse_arena
from visionpos.server.service import FusionServer


@pytest.mark.slow
def test_simulated_stations_register_with_their_resolution_and_nothing_malformed(arena_yaml):
    data = arena_yaml("thesis")
    data.setdefault("server", {})["insecure"] = True
    arena = parse_arena(data, "thesis.yaml")
    found: dict = {}

    async def main():
        server = FusionServer(arena, host="127.0.0.1", port=0)
        await server.start()
        agents, threads = [], []
        try:
            for i, cam in enumerate(arena.cameras):
                cfg = parse_station({"station_id": 10 + i, "camera_id": cam.id, "insecure": True,
                                     "server": {"host": "127.0.0.1", "port": server.port},
                                     "source": {"kind": "sim", "scenario": "thesis", "fps": 20},
                                     "heartbeat_s": 0.2}, "station.yaml")
                agent = StationAgent(cfg)
                agents.append(agent)
                threads.append(threading.Thread(target=agent.run, daemon=True))
                threads[-1].start()
            loop = asyncio.get_running_loop()
            end = loop.time() + 20
            while loop.time() < end and not all(a.registered for a in agents):
                await asyncio.sleep(0.05)
            await asyncio.sleep(0.3)  # any late packet counted too
            found["registered"] = [a.registered for a in agents]
            found["health"] = server.health()
            found["status"] = server.ingest.status_line()
        finally:
            for a in agents:
                a.stop()
            await server.stop()
            for t in threads:
                t.join(5)

    asyncio.run(asyncio.wait_for(main(), 60))
    assert found["registered"] == [True] * 4
    h = found["health"]
    assert h["malformed"] == 0, h.get("malformed_reasons")
    assert " bad " not in found["status"], found["status"]
