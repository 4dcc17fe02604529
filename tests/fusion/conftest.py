"""Fixtures shared by the fusion tests."""

from __future__ import annotations

import pytest


@pytest.fixture
def two_of_a_kind():
    """A builder of the thesis arena with quads of its first body's layout: (paths {name: session entry},
    duration s, names: the bodies' order, default the paths') -> the Scenario, ids 1, 2, ... in that order."""
    from visionpos.config.arena import load_yaml, parse_arena, resolve_config_path
    from visionpos.sim import parse_sim

    def build(paths: dict, duration_s: float, names: list[str] | None = None):
        data = load_yaml(resolve_config_path("thesis"))
        quad = data["bodies"][0]
        data["bodies"] = [dict(quad, name=name, id=i + 1) for i, name in enumerate(names or paths)]
        data["sim"].update(duration=duration_s, session="pair", sessions={"pair": dict(paths)})
        return parse_sim(parse_arena(data, "<two of a kind>"))

    return build
