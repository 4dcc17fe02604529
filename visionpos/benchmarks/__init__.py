"""Benchmark groups for `visionpos bench`.

Each group is a module here exposing `run(quick: bool = False) -> BenchResult`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

# group name -> module under visionpos.benchmarks
GROUPS: dict[str, str] = {
    "geometry": "geometry",
    "detector": "detector",
    "fusion": "fusion",
    "bridge": "bridge",
    "calibration": "calibration",
    "replay": "replay",
}


@dataclass
class BenchResult:
    """metrics: flat name -> number (JSON keys, e.g. detector_fps_960x640).
    tables: markdown blocks (title -> markdown) for docs/benchmarks.md."""

    metrics: dict[str, float] = field(default_factory=dict)
    tables: dict[str, str] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
