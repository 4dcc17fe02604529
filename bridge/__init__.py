"""Outputs of the fusion server: MAVLink to each vehicle's autopilot and the UDP pose stream.

    from bridge import Bridge
    b = Bridge(arena)            # reads the arena's `vehicles:` and `pose_stream:` sections
    b.start(); b.publish(states); ...; b.close()

See docs/autopilot-setup.md and docs/pose-stream.md.
"""

from bridge.config import Endpoint, PoseStreamConfig, VehicleConfig, parse_endpoint, parse_pose_stream, parse_vehicles
from bridge.mavlink import Bridge, VehicleLink
from bridge.pose_stream import PoseStream, decode_binary

__all__ = [
    "Bridge",
    "VehicleLink",
    "PoseStream",
    "decode_binary",
    "Endpoint",
    "VehicleConfig",
    "PoseStreamConfig",
    "parse_endpoint",
    "parse_vehicles",
    "parse_pose_stream",
]
