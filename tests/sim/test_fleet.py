"""The fleet scenarios (visionpos/configs/fleet.yaml, fleet20.yaml): what their truth must show, computed from
the sampled truth here, not from the plan's own numbers."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from visionpos.fusion.identity import parking_order
from visionpos.sim import load_scenario
from visionpos.sim.fleet import Route


def _truth(sc, rate_hz: float = 50.0):
    """Times (T,) ns, body positions (B, T, 3), rotations [B] and velocities (B, T, 3) of every body."""
    times = sc.start_ns + np.arange(0, int(sc.duration_s * 1e9), int(1e9 / rate_hz), dtype=np.int64)
    motions = [b.trajectory.sample_ns(times, sc.start_ns) for b in sc.bodies]
    return (times, np.stack([m.positions for m in motions]), [Rotation.from_quat(m.quaternions) for m in motions],
            np.stack([m.velocities for m in motions]))


@pytest.fixture(scope="module", params=["fleet", "fleet20"])
def fleet(request):
    sc = load_scenario(request.param)
    return (request.param, sc, *_truth(sc))


def test_fleet_shares_one_layout(fleet):
    name, sc, *_ = fleet
    assert len(sc.bodies) == (10 if name == "fleet" else 20)
    assert 8 <= len(sc.cameras) <= 12
    first = sc.bodies[0].markers
    assert len(first) == 4
    assert all(np.array_equal(b.markers, first) for b in sc.bodies)
    assert len({b.name for b in sc.bodies}) == len(sc.bodies)


def test_fleet_starts_on_the_floor_and_lands(fleet):
    _, sc, times, pos, rots, vel = fleet
    marker_z = np.stack([np.einsum("tij,mj->tmi", r.as_matrix(), b.markers)[..., 2] + p[:, None, 2]
                         for b, r, p in zip(sc.bodies, rots, pos)])  # (B, T, M)
    assert marker_z.min() > -1e-6  # never through the floor
    assert np.all(marker_z[:, 0].max(axis=1) < 0.06)  # parked: every marker within 6 cm of the floor
    assert np.all(np.abs(vel[:, 0]) < 1e-9)
    assert np.all(marker_z[:, -1].max(axis=1) < 0.06)  # landed again
    assert np.all(np.abs(vel[:, -1]) < 1e-9)
    assert np.all(pos[:, :, 2].max(axis=1) > 0.8)  # and every one flew
    # a row: the parking spots are distinct and not closer than 0.45 m
    park = pos[:, 0, :2]
    gaps = np.linalg.norm(park[:, None] - park[None], axis=-1) + np.eye(len(park)) * 9
    assert gaps.min() > 0.45
    # parked in name order: the order fusion names drones first seen in (fusion/identity.py)
    assert parking_order(pos[:, 0]).tolist() == list(range(len(pos)))
    # one after the other: take-off times (first above 5 cm) all differ
    up = [times[np.argmax(p[:, 2] > 0.05)] for p in pos]
    assert len(set(up)) == len(up)


def test_fleet_passes_close_but_never_collides(fleet):
    _, sc, times, pos, _, vel = fleet
    d = np.linalg.norm(pos[:, None] - pos[None], axis=-1) + np.eye(len(pos))[:, :, None] * 99  # (B, B, T)
    closest = d.min(axis=(0, 1))
    airborne = (pos[:, :, 2] > 0.5).all(axis=0)
    assert closest[airborne].min() <= 0.3
    assert closest.min() >= 0.2
    # more than one pair passes within 0.3 m (crossings and overtakings, not one moment)
    close_pairs = {(i, j) for i, j in zip(*np.nonzero(d.min(axis=2) <= 0.3)) if i < j}
    assert len(close_pairs) >= len(pos) // 2
    # hovering together: some time at which every drone is airborne, slow, and within 0.4 m of another
    speed = np.linalg.norm(vel, axis=-1).max(axis=0)
    together = airborne & (speed < 0.05) & (d.min(axis=1).max(axis=0) <= 0.4)
    assert together.sum() >= 50  # a second at 50 Hz


def test_fleet_markers_of_two_bodies_merge_in_some_image():
    sc = load_scenario("fleet")
    times, pos, rots, _ = _truth(sc, 20.0)
    markers = np.stack([np.einsum("tij,mj->tmi", r.as_matrix(), b.markers) + p[:, None]
                        for b, r, p in zip(sc.bodies, rots, pos)])  # (B, T, M, 3)
    B, T, M, _ = markers.shape
    merged_cameras = set()
    for cam in sc.cameras:
        px = cam.project(markers.reshape(-1, 3)).reshape(B, T, M, 2)
        for i in range(B):
            for j in range(i + 1, B):
                dd = np.linalg.norm(px[i][:, :, None] - px[j][:, None], axis=-1)  # (T, M, M)
                airborne = (pos[i, :, 2] > 0.5) & (pos[j, :, 2] > 0.5)
                if (dd.min(axis=(1, 2))[airborne] < 3.0).any():  # a 19 mm marker is > 3 px at 5 m
                    merged_cameras.add(cam.id)
    assert len(merged_cameras) >= 2


def test_route_velocity_and_acceleration_are_the_derivatives():
    r = Route(np.array([0.0, 1.0, 2.5]), np.array([[0.0, 0.0, 0.0], [1.0, 2.0, 0.5], [1.0, 2.0, 1.5]]))
    t = np.linspace(-0.5, 3.0, 701)
    h = 1e-5
    p, v, a = r.kinematics(t)
    assert np.allclose(v, (r.kinematics(t + h)[0] - r.kinematics(t - h)[0]) / (2 * h), atol=1e-6)
    assert np.allclose(a, (r.kinematics(t + h)[1] - r.kinematics(t - h)[1]) / (2 * h), atol=1e-4)
    assert np.allclose(p[t <= 0], [0, 0, 0]) and np.allclose(p[t >= 2.5], [1.0, 2.0, 1.5])
    assert np.allclose(r.kinematics(np.array([1.0]))[0], [[1.0, 2.0, 0.5]])


def test_laps_fly_the_crossings_again_before_the_landing():
    """`laps: 3` on the fleet's drones (the 10-minute flight of issue 28 is 29 laps): the legs from the first
    crossing to the return above the pads are flown three times, each lap the same path, a lap later; the
    landing comes after the last."""
    one = load_scenario("fleet", ["sim.duration=40"])
    three = load_scenario("fleet", [f"sim.sessions.fleet.quad{k}.laps=3" for k in range(1, 11)]
                          + ["sim.duration=90"])
    t_one, p_one, _, v_one = _truth(one)
    t_three, p_three, _, _ = _truth(three)
    moving = np.linalg.norm(v_one, axis=2).max(axis=0) > 0.05
    first, last = np.flatnonzero(moving)[[0, -1]]  # take-off of the first drone, landing of the last
    # the lap: from the first drone's first sideways move to its return above its pad, read off the truth
    sideways = np.flatnonzero(np.abs(v_one[0, :, :2]).max(axis=1) > 0.01)
    lap = slice(sideways[0], sideways[-1] + 1)
    n = lap.stop - lap.start
    assert np.allclose(p_three[:, lap], p_one[:, lap], atol=1e-9)

    def shift_of(k):  # where, after lap k - 1, the same path starts again (samples), searched
        for s in range(k * n, k * (n + 200)):
            if np.allclose(p_three[:, lap.start + s: lap.stop + s], p_one[:, lap], atol=1e-9):
                return s
        return None

    period = shift_of(1)
    assert period is not None and shift_of(2) == 2 * period
    # landed later by two laps, on the same pads
    assert np.allclose(p_three[:, -1], p_one[:, -1])
    landed_three = np.flatnonzero(np.linalg.norm(p_three[:, 1:] - p_three[:, :-1], axis=2).max(axis=0) > 0)[-1]
    assert landed_three > last + 2 * n
    assert first < lap.start
