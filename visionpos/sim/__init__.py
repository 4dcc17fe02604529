"""Simulated arena: scenarios, trajectories, capture and IR image rendering.

    from visionpos.sim import load_scenario, simulate, iter_frames
    sc = load_scenario("thesis", ["sim.duration=10"])   # or "arena8", or a path
    res = simulate(sc)      # res.frames: list[BlobFrame] (capture order); res.frame_truth
    pos, quat = sc.truth_at("quad", times_ns)           # truth at any int64 ns times
    for frame in iter_frames(sc, order="recv"): ...     # streaming, same content

What moves is chosen by the arena's `sim.session`, an entry of
`sim.sessions` (body name -> trajectory). The built-in arenas have:
  flight  the drones flying (thesis: the 0.5 m square at 0.8 m)
  hover   the drones hovering
  wand    the 3-marker calibration wand (A-B 5.4 cm, B-C 10.3 cm) waved
          through the volume for 60 s-style extrinsic calibration
  ground  the L-frame lying still at the origin (ground-plane calibration)
The wand and the L-frame are `sim.props`: simulated bodies that are not in
`bodies`, so fusion does not try to track them. Select with
`load_scenario("thesis", session="wand")` or `visionpos sim --session wand`
(equivalently `--set sim.session=wand`). scenario.py documents every key.

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
    parse_sim,
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
    "parse_sim",
    "simulate",
]
