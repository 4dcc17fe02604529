"""Binding again after a short loss, where the lost vehicle's own EKF says it is (a fleet of one layout).

After a track is lost its binding is dropped (bridge/fleet_binding.py) and is made again from the motions: a
hovering drone barely moves, and three identical drones hovering in a row flown against ArduPilot SITL went
14 s without vision after a host stall lost their tracks (the motion did not tell them apart before their EKFs
had drifted away). But each vehicle still knows where it is: its EKF ran on this body's poses until the loss and
dead-reckons on its IMU after it (LOCAL_POSITION_NED, in the vision frame). A body reacquired where exactly one
recently lost vehicle says it is, with no other body and no other vehicle near, is that vehicle's.

Rules (rebind_by_position): a candidate vehicle lost its binding to a track loss at most REBIND_WITHIN_NS ago
(its dead reckoning has drifted little: ArduPilot drifted 185 mm in 5 s without vision); its position is at most
POSITION_STALE_NS old; exactly one free body's reference point lies within NEAR_M of it; no other body of the group
(bound or not) lies within CLEAR_M of it, and no other vehicle's position within CLEAR_M of that body. Each body
and each vehicle is used once. The motions check the binding from then on, as they check every binding.
"""

from __future__ import annotations

import numpy as np

from visionpos.geometry.frames import ned_to_world, yaw_matrix_ned

REBIND_WITHIN_NS = 3_000_000_000  # a binding lost this recently can be made again by the vehicle's position
POSITION_STALE_NS = 300_000_000  # LOCAL_POSITION_NED streams at 10 Hz: a position older than this is not used
NEAR_M = 0.15  # the body's reference point within this of where the vehicle says it is
CLEAR_M = 0.5  # ... and no other body or vehicle within this: nothing else could be taken for it


def vehicle_position_world(local_ned_m: np.ndarray, yaw_offset_rad: float) -> np.ndarray:
    """A vehicle's LOCAL_POSITION_NED (3,) m (its EKF, in the vision frame the bridge sends: world NED turned by
    yaw_offset_rad) in the world frame (3,) m."""
    return ned_to_world(yaw_matrix_ned(yaw_offset_rad).T @ np.asarray(local_ned_m, float))


def rebind_by_position(candidates: dict[str, np.ndarray], vehicles_world: dict[str, np.ndarray],
                       free_bodies: dict[str, np.ndarray], other_bodies: dict[str, np.ndarray]
                       ) -> list[tuple[str, str, float]]:
    """The bindings [(body, vehicle, distance m)] made by position (module docstring).

    candidates: {vehicle: where it says it is (3,) m world} for the vehicles that may be bound again this way;
    vehicles_world: {vehicle: (3,) m world} every live vehicle of the group with a fresh position (candidates
    included); free_bodies: {body: its reference point (3,) m world} the group's unbound tracked bodies;
    other_bodies: {body: (3,) m world} its other tracked bodies (bound ones)."""
    everyone = {**free_bodies, **other_bodies}
    made: list[tuple[str, str, float]] = []
    used: set[str] = set()
    for v, at in candidates.items():
        dist = {b: float(np.linalg.norm(p - at)) for b, p in everyone.items()}
        near = [b for b in free_bodies if dist[b] <= NEAR_M]
        if len(near) != 1 or near[0] in used:
            continue
        b = near[0]
        if any(d <= CLEAR_M for c, d in dist.items() if c != b):
            continue  # another body is near where it says it is
        if any(float(np.linalg.norm(p - free_bodies[b])) <= CLEAR_M for w, p in vehicles_world.items() if w != v):
            continue  # another vehicle says it is near that body
        used.add(b)
        made.append((b, v, dist[b]))
    return made
