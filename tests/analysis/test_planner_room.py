"""`visionpos plan` in a room: mountable suggestions only, obstacles that hide, and a room that contradicts itself
refused in one line naming the key (issue 30.3)."""

import copy

import numpy as np
import pytest

from visionpos.analysis.planner import (
    Room,
    Volume,
    mount_positions,
    parse_plan,
    segment_blocked,
    suggest_camera,
    visibility,
)
from visionpos.camera.model import Camera
from visionpos.config.arena import ConfigError, parse_arena


def _cam(cid, position, look_at=(0, 0, 1)):
    return {"id": cid, "width": 1280, "height": 960, "fx": 800, "fy": 800, "cx": 640, "cy": 480,
            "pose": {"position": list(position), "look_at": list(look_at)}}


# the issue's room: 6 x 6 x 3 m, six cameras at 2.5 m on the walls (four corners, two mid-walls)
ROOM = {"cameras": [_cam(i + 1, (x, y, 2.5)) for i, (x, y) in enumerate(
            [(-2.9, -2.9), (2.9, -2.9), (2.9, 2.9), (-2.9, 2.9), (0.0, -2.9), (0.0, 2.9)])],
        "bodies": [], "plan": {"room": {"min_m": [-3, -3, 0], "max_m": [3, 3, 3]},
                               "volume": {"min_m": [-2, -2, 0.2], "max_m": [2, 2, 2]},
                               "candidate_step_m": 1.0}}


def test_the_issue_room_gets_suggestions_inside_its_walls_each_on_a_mount_and_aimed_at_the_volume():
    arena = parse_arena(copy.deepcopy(ROOM), "room.yaml")
    room = parse_plan(arena)
    volume = Volume(room.volume.lo, room.volume.hi, 0.5)
    got = suggest_camera(arena, volume, top=10, room=room)
    assert len(got) == 10
    centre = np.array([0.0, 0.0, 1.1])
    for s in got:
        c = s.camera.center
        assert (c >= -3).all() and (c <= 3).all(), c  # the old ring put them at (3.70, 0, 2.50)
        on_wall = np.isclose(abs(c[0]), 2.9) or np.isclose(abs(c[1]), 2.9)
        on_ceiling = np.isclose(c[2], 2.9)
        # a tripod: 1.8 m high, at least 0.5 m outside the volume
        on_tripod = np.isclose(c[2], 1.8) and (np.abs(c[:2]) > 2.5 - 1e-9).any()
        assert {"wall": on_wall, "ceiling": on_ceiling, "tripod": on_tripod}[s.mount], (s.mount, c)
        axis = s.camera.R[2]  # the optical axis in the world
        np.testing.assert_allclose(axis, (centre - c) / np.linalg.norm(centre - c), atol=1e-9)


def test_mount_positions_of_a_small_room_counted_by_hand():
    # 4 x 4 x 3 m room, 0.1 m offset, 2 m step: ticks 0.1, 2.0, 3.9 along each wall; the walls' points are
    # the 8 of the 3 x 3 grid's rim (a corner belongs to two walls, listed once), at two heights (1.5 m and
    # 2.9 m): 16; the ceiling's 3 x 3 less its rim, which is the walls' top row: 1; tripods: the 9 floor
    # points less the centre (2, 2), within 0.5 m of the volume 1.5..2.5: 8; an obstacle at x, y 3.5..4
    # takes the corner (3.9, 3.9) from the walls' two heights and from the tripods: 25 - 3 = 22
    room = Room(np.array([0.0, 0, 0]), np.array([4.0, 4, 3]), candidate_step_m=2.0)
    vol = Volume(np.array([1.5, 1.5, 0.2]), np.array([2.5, 2.5, 1.5]), 0.5)
    pos = mount_positions(room, vol, 1.5)
    kinds = [m for _, m, _ in pos]
    assert (kinds.count("wall"), kinds.count("ceiling"), kinds.count("tripod")) == (16, 1, 8)
    assert all(np.isclose(p[2], 1.8) for p, m, _ in pos if m == "tripod")
    from visionpos.analysis.planner import Obstacle
    blocked = Room(room.lo, room.hi, (Obstacle("box", np.array([3.5, 3.5, 0]), np.array([4.0, 4, 3]), "o"),),
                   candidate_step_m=2.0)
    assert len(mount_positions(blocked, vol, 1.5)) == 22


def test_an_obstacle_hides_what_is_behind_it():
    a = np.array([0.0, 0, 1])
    lo, hi = np.array([0.9, -0.1, 0.9]), np.array([1.1, 0.1, 1.1])
    pts = np.array([[2.0, 0, 1], [0.5, 0, 1], [2.0, 1.0, 1], [2.0, 0, 1.15], [1.0, 0, 1]])
    # through the box; stops short of it; passes beside it (at x 0.9..1.1 it is at y 0.45..0.55); passes
    # over it (at x = 1.1 it is at z 1.0825 < 1.1: inside) ; ends inside it
    np.testing.assert_array_equal(segment_blocked(a, pts, lo, hi), [True, False, False, True, True])
    cam = Camera.from_dict(_cam(1, (0, 0, 1), (2, 0, 1)))
    from visionpos.analysis.planner import Obstacle
    vis = visibility([cam], pts[:3], (Obstacle("pillar", lo, hi, "plan.obstacles[0]"),))
    np.testing.assert_array_equal(vis[:, 0], [False, True, True])


@pytest.mark.parametrize("edit, key, words", [
    (lambda d: d["plan"].update(obstacles=[{"name": "pillar", "min_m": [2.5, -3, 0], "max_m": [3, -2.5, 3]}]),
     "cameras[1].pose.position", "inside obstacle pillar (plan.obstacles[0]"),
    (lambda d: d["plan"]["volume"].update(max_m=[3.5, 2, 2]), "plan.volume", "reaches outside the walls"),
    (lambda d: d["plan"]["room"].update(max_m=[3, -4, 3]), "plan.room.max_m", "must be above min_m"),
    (lambda d: d["cameras"][4]["pose"].update(position=[0, -4, 2.5]), "cameras[4].pose.position", "outside the walls"),
])
def test_a_room_that_contradicts_itself_is_one_line_naming_the_key(edit, key, words):
    data = copy.deepcopy(ROOM)
    edit(data)
    with pytest.raises(ConfigError) as e:
        parse_plan(parse_arena(data, "room.yaml"))
    assert e.value.key == key and words in e.value.message and "\n" not in str(e.value), str(e.value)
