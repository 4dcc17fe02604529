"""Import every stage that declares a section of the arena file, so the schema is complete.

The CLI imports this before it applies `--set` overrides, and the reference generator before it
renders docs/configuration.md; the core's config layer cannot import the stages itself.
"""

import bridge.config  # noqa: F401  vehicles, pose_stream
import bridge.foxglove_live  # noqa: F401  foxglove
import bridge.natnet  # noqa: F401  natnet
import bridge.vrpn  # noqa: F401  vrpn
import console.settings  # noqa: F401  console
import visionpos.analysis.planner  # noqa: F401  plan
import visionpos.app.sitl  # noqa: F401  sitl
import visionpos.fusion.camera_monitor  # noqa: F401  camera_monitor
import visionpos.fusion.settings  # noqa: F401  fusion
import visionpos.server.settings  # noqa: F401  server
import visionpos.sim.scenario  # noqa: F401  sim
