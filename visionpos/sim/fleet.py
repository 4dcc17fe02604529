"""A fleet's flight plan: timed waypoints flown rest to rest, and the plan of one drone of a fleet.

`Route` is a trajectory through timed waypoints: between two waypoints it moves along the straight
line with the septic step (zero velocity, acceleration and jerk at both ends, so the flat quadrotor's
attitude and body rate stay continuous), before the first and after the last it rests.

`fleet_route(slot, count)` is drone `slot` of `count` (the `fleet` trajectory kind). The drones fly in
pairs (slot 2k and 2k + 1 share a 1.0 m x 1.6 m cell; five cells a row, rows 1.6 m apart, centred on
the arena's origin):
  1. parked on the floor, the pair 0.5 m apart, a row of drones along x; take-off one after the other
     (slot order, every TAKEOFF_STAGGER_S) to the flight height;
  2. crossing: the pair swaps sides along x on lines 2 x CROSS_OFFSET_M apart in y (they pass at
     that distance), then swaps back one above the other (2 x CROSS_OFFSET_M apart in z: markers of
     the two merge in the images of cameras looking down at them);
  3. overtaking: both fly along +y, 2 x OVERTAKE_OFFSET_M apart in x, the first twice as far in the
     same time, so it passes the second;
  4. the whole fleet gathers in a tight grid (HUDDLE_SPACING_M) around the origin and hovers there;
  5. back above the parking spots, and landing one after the other.
With `laps` > 1 the legs 2-5 are flown that many times before the landing (a long flight of crossings).
Everything is a function of (slot, count, height, laps): the same plan for every seed.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from visionpos.sim.trajectories import Trajectory, _flat_attitude

PAIR_CELL_M = (1.0, 1.6)  # x, y size of one pair's cell
CELLS_PER_ROW = 5
PARK_HALF_GAP_M = 0.25  # a pair parks 0.5 m apart
CROSS_OFFSET_M = 0.14  # crossing lines are 0.28 m apart: the drones pass within 0.3 m
CROSS_HALF_SPAN_M = 0.4  # a crossing runs from -0.4 to +0.4 m about the cell centre
OVERTAKE_OFFSET_M = 0.125  # overtaking lanes 0.25 m apart
OVERTAKE_START_M = (-0.6, -0.3)  # y of the overtaker and the overtaken before, about the cell centre
HUDDLE_SPACING_M = 0.35  # the hover grid's spacing
TAKEOFF_STAGGER_S = 0.3  # take-offs (and landings) one after the other
FIRST_TAKEOFF_S = 1.0
CLIMB_S = 1.5
PAUSE_S = 0.3  # rest at each waypoint
HUDDLE_HOLD_S = 3.0
# the legs between take-off and landing: (duration s, where to) in the order flown
_LEGS = ("cross_start", 1.5), ("crossed", 2.0), ("over_start", 1.5), ("over_crossed", 2.0), \
        ("overtake_start", 1.5), ("overtaken", 2.5), ("huddle", 2.5), ("huddle_hold", HUDDLE_HOLD_S), \
        ("above_park", 2.5)


@dataclass(frozen=True)
class Route(Trajectory):
    """Timed waypoints: times (K,) s increasing, points (K, 3) m world; a constant heading yaw (rad)."""

    times: np.ndarray
    points: np.ndarray
    yaw: float = 0.0

    def kinematics(self, t):
        t = np.asarray(t, float)
        k = np.clip(np.searchsorted(self.times, t, side="right") - 1, 0, len(self.times) - 2)
        t0, t1 = self.times[k], self.times[k + 1]
        span = t1 - t0
        tau = np.clip((t - t0) / span, 0.0, 1.0)
        s = tau**4 * (35 - 84 * tau + 70 * tau**2 - 20 * tau**3)
        ds = 140 * tau**3 * (1 - tau) ** 3 / span
        dds = 420 * tau**2 * (1 - tau) ** 2 * (1 - 2 * tau) / span**2
        d = self.points[k + 1] - self.points[k]
        return self.points[k] + s[:, None] * d, ds[:, None] * d, dds[:, None] * d

    def attitude(self, t) -> Rotation:
        t = np.asarray(t, float)
        return _flat_attitude(self.kinematics(t)[2], np.full(len(t), self.yaw))


def _cell_centre(pair: int, n_pairs: int) -> np.ndarray:
    """(2,) x, y of a pair's cell: five cells a row, the rows centred on the origin."""
    n_rows = -(-n_pairs // CELLS_PER_ROW)
    in_row = min(CELLS_PER_ROW, n_pairs - (pair // CELLS_PER_ROW) * CELLS_PER_ROW)
    col, row = pair % CELLS_PER_ROW, pair // CELLS_PER_ROW
    return np.array([(col - (in_row - 1) / 2) * PAIR_CELL_M[0], (row - (n_rows - 1) / 2) * PAIR_CELL_M[1]])


def _huddle(slot: int, count: int) -> np.ndarray:
    """(2,) x, y of a slot in the hover grid: ten columns (a pair side by side, cells in order), rows as the
    cells', so the drones fly there without crossing."""
    cols = min(count, 2 * CELLS_PER_ROW)
    n_rows = -(-count // cols)
    pair = slot // 2
    col = (pair % CELLS_PER_ROW) * 2 + slot % 2
    row = pair // CELLS_PER_ROW
    in_row = min(cols, count - row * cols)
    return np.array([(col - (in_row - 1) / 2) * HUDDLE_SPACING_M, (row - (n_rows - 1) / 2) * HUDDLE_SPACING_M])


def _waypoints(slot: int, count: int, height: float) -> dict[str, np.ndarray]:
    """Where drone `slot` is at the end of each leg (m world)."""
    c = _cell_centre(slot // 2, -(-count // 2))
    side = -1.0 if slot % 2 == 0 else 1.0  # the pair's first drone starts on the -x side
    first = slot % 2 == 0

    def at(dx: float, dy: float, dz: float = 0.0) -> np.ndarray:
        return np.array([c[0] + dx, c[1] + dy, height + dz])

    park = at(side * PARK_HALF_GAP_M, 0.0, -height)
    over_y = OVERTAKE_START_M[0] if first else OVERTAKE_START_M[1]
    return {
        "park": park,
        "above_park": park + [0.0, 0.0, height],
        "cross_start": at(side * CROSS_HALF_SPAN_M, side * CROSS_OFFSET_M),
        "crossed": at(-side * CROSS_HALF_SPAN_M, side * CROSS_OFFSET_M),
        "over_start": at(-side * CROSS_HALF_SPAN_M, 0.0, side * CROSS_OFFSET_M),
        "over_crossed": at(side * CROSS_HALF_SPAN_M, 0.0, side * CROSS_OFFSET_M),
        "overtake_start": at(side * OVERTAKE_OFFSET_M, over_y),
        "overtaken": at(side * OVERTAKE_OFFSET_M, -over_y),  # the first flies twice as far: it overtakes
        "huddle": np.append(_huddle(slot, count), height),
        "huddle_hold": np.append(_huddle(slot, count), height),
    }


def fleet_schedule(count: int, laps: int = 1) -> dict[str, float]:
    """When the fleet's phases end (s from the start): 'takeoff' (the last drone at height), each leg of
    _LEGS by name (of the last lap), 'landed' (the last drone on the floor)."""
    t = FIRST_TAKEOFF_S + TAKEOFF_STAGGER_S * (count - 1) + CLIMB_S
    out = {"takeoff": t}
    for _ in range(laps):
        for name, dur in _LEGS:
            t += PAUSE_S + dur
            out[name] = t
    out["landed"] = t + PAUSE_S + TAKEOFF_STAGGER_S * (count - 1) + CLIMB_S
    return out


def fleet_route(slot: int, count: int, height: float = 1.0, yaw_deg: float = 0.0, laps: int = 1) -> Route:
    """The route of drone `slot` (0-based) of a fleet of `count` (module docstring), at `height` m, its legs
    flown `laps` times."""
    if not 0 <= slot < count:
        raise ValueError(f"slot {slot} is not in 0..{count - 1}")
    wp = _waypoints(slot, count, height)
    sched = fleet_schedule(count, laps)
    up_at = FIRST_TAKEOFF_S + TAKEOFF_STAGGER_S * slot
    times, points = [0.0, up_at, up_at + CLIMB_S], [wp["park"], wp["park"], wp["above_park"]]
    # hold above the parking spot until the last drone is up, then fly the legs together
    t = sched["takeoff"]
    if t > times[-1]:  # the last drone flies on at once
        times.append(t)
        points.append(wp["above_park"])
    for name, dur in _LEGS * laps:
        times += [t + PAUSE_S, t + PAUSE_S + dur]
        points += [points[-1], wp[name]]
        t += PAUSE_S + dur
    down_at = t + PAUSE_S + TAKEOFF_STAGGER_S * slot
    times += [down_at, down_at + CLIMB_S]
    points += [wp["above_park"], wp["park"]]
    return Route(np.array(times), np.array(points), float(np.radians(yaw_deg)))


def point_fleet(arena: dict, count: int, duration_s: float | None = None) -> dict:
    """A copy of an arena mapping whose bodies are `count` single-marker drones (point bodies `dot1`, `dot2`,
    ..., one marker at the origin) flying the fleet plan of `count` (session `fleet_points`), for
    `duration_s` s (default: to the last landing)."""
    out = dict(arena)
    out["bodies"] = [{"name": f"dot{i + 1}", "id": i + 1, "marker_diameter": 0.019, "markers": [[0.0, 0.0, 0.0]]}
                     for i in range(count)]
    sim = dict(out.get("sim") or {})
    sim["sessions"] = {**(sim.get("sessions") or {}), "fleet_points": {
        f"dot{i + 1}": {"trajectory": "fleet", "slot": i, "count": count} for i in range(count)}}
    sim["session"] = "fleet_points"
    sim["duration"] = float(duration_s if duration_s is not None else fleet_schedule(count)["landed"] + 0.5)
    out["sim"] = sim
    return out
