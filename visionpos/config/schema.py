"""The whole arena file's declarations: the top level with every stage's section attached."""

from __future__ import annotations

from dataclasses import replace
from functools import lru_cache

from visionpos.config.settings import Spec


@lru_cache(maxsize=1)
def arena_schema() -> Spec:
    """The top-level Spec, each section's Setting holding that section's Spec."""
    from bridge.config import POSE_STREAM, VEHICLE
    from visionpos.config.sections import TOP
    from visionpos.fusion.settings import FUSION
    from visionpos.server.settings import SERVER
    from visionpos.sim.scenario import SIM

    stage = {"fusion": FUSION, "server": SERVER, "vehicles": VEHICLE, "pose_stream": POSE_STREAM, "sim": SIM}
    settings = tuple(replace(s, spec=stage[s.key]) if s.key in stage else s for s in TOP.settings)
    return replace(TOP, settings=settings)
