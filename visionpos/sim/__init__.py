"""Simulated arena: scenarios, trajectories, capture and IR image rendering.

    from visionpos.sim import load_scenario, simulate, iter_frames
    sc = load_scenario("thesis", ["sim.duration=10"])   # or arena8, or a path
    res = simulate(sc)          # res.frames: list[BlobFrame]; res.frame_truth; res.truth
    pos, quat = sc.truth_at("quad", times_ns)

Everything is deterministic from the scenario's seed.
"""

from visionpos.sim.capture import (
    SPURIOUS_MIRROR,
    SPURIOUS_RANDOM,
    SPURIOUS_STATIC,
    FrameTruth,
    SimResult,
    blob_photometry,
    iter_frames,
    marker_geometry,
    simulate,
)
from visionpos.sim.scenario import (
    CameraTiming,
    Scenario,
    SimBody,
    StationClock,
    load_scenario,
    scenario_from_arena,
)
from visionpos.sim.trajectories import Motion, Trajectory

__all__ = [
    "CameraTiming",
    "FrameTruth",
    "Motion",
    "SPURIOUS_MIRROR",
    "SPURIOUS_RANDOM",
    "SPURIOUS_STATIC",
    "Scenario",
    "SimBody",
    "SimResult",
    "StationClock",
    "Trajectory",
    "blob_photometry",
    "iter_frames",
    "load_scenario",
    "marker_geometry",
    "scenario_from_arena",
    "simulate",
]
