"""The scale bench's machinery (visionpos/benchmarks/scale.py) on a tiny case: its arena, a matrix cell, the
one-core server model. The figures themselves are `visionpos bench --only scale`'s."""

from __future__ import annotations

import numpy as np

from visionpos.benchmarks import GROUPS, scale
from visionpos.config.arena import parse_arena


def test_ring_arena_puts_cameras_on_a_ring_around_separate_bodies():
    arena = parse_arena(scale.ring_arena(8, 5, 1.0), "<test>")
    centres = np.array([c.center for c in arena.cameras])
    assert len(centres) == 8
    assert np.allclose(np.linalg.norm(centres[:, :2], axis=1), scale.RING_RADIUS_M)
    assert all(c.fps == scale.FPS for c in arena.cameras)
    assert len(arena.bodies) == 5 and all(np.array_equal(b.markers, arena.bodies[0].markers) for b in arena.bodies)
    spots = np.array([s["center"] for s in scale.ring_arena(8, 5, 1.0)["sim"]["sessions"]["hover"].values()])
    gaps = np.linalg.norm(spots[:, None, :2] - spots[None, :, :2], axis=-1) + np.eye(5) * 9
    assert gaps.min() >= scale.GRID_M - 1e-9


def test_matrix_cell_and_registration():
    assert GROUPS["scale"] == "scale"
    res = scale.run(quick=True, bodies=(1, 2), cameras=(4,), realtime=False)
    assert set(res.metrics) == {f"scale_{k}_c4_b{b}" for k in ("us_per_packet", "load", "output_hz") for b in (1, 2)}
    # both bodies tracked through the measured part: a pose every 100 Hz tick
    assert res.metrics["scale_output_hz_c4_b2"] > 95
    assert all(v > 0 for v in res.metrics.values())


def test_one_core_sheds_only_what_waited_too_long():
    arena = parse_arena(scale.ring_arena(4, 1, 0.6), "<test>")
    from visionpos.sim import parse_sim, simulate

    packets = scale._packets(simulate(parse_sim(arena)).frames)
    relaxed = scale.one_core(arena, packets, shed_ns=10**12)
    assert relaxed["shed_fraction"] == 0 and relaxed["packets"] == len(packets)
    # every packet arriving at once: the core can take the first ones within 1 ms, the rest wait and are shed
    burst = [(packets[0][0], data) for _, data in packets]
    crowded = scale.one_core(arena, burst, shed_ns=1_000_000)
    assert 0 < crowded["shed_fraction"] < 1
    assert crowded["wait_max_ms"] > 1.0
