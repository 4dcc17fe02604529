"""Made-up inputs for the bridge: arenas with vehicles and body states, for benchmarks and tests.

They live in the application layer, beside the benchmarks that use them, not in the shipped
bridge: nothing in the product builds fake states. Free ports: visionpos.app.ports.
"""

from __future__ import annotations

import time

import numpy as np

from visionpos.config.arena import ArenaConfig, parse_arena
from visionpos.messages import BodyState

# three well separated 4-marker layouts (m, body FLU)
_LAYOUTS = [
    [[0.10, 0.0, 0.0], [0.0, 0.08, 0.0], [-0.07, -0.05, 0.02], [0.02, -0.09, 0.04]],
    [[0.12, 0.02, 0.0], [-0.03, 0.10, 0.01], [-0.09, -0.06, 0.0], [0.05, -0.11, 0.03]],
    [[0.15, 0.0, 0.01], [0.0, 0.13, 0.0], [-0.11, -0.02, 0.03], [0.03, -0.14, 0.0]],
]


def arena_with_vehicles(vehicles: list[dict], pose_stream: dict | None = None,
                        source: str = "test-arena.yaml", n_bodies: int | None = None) -> ArenaConfig:
    """An ArenaConfig with bodies 'body1'.. (ids 1..) and the given `vehicles:` / `pose_stream:` sections."""
    n = n_bodies if n_bodies is not None else max(1, len(vehicles))
    bodies = [{"name": f"body{i + 1}", "id": i + 1, "markers": _LAYOUTS[i % len(_LAYOUTS)]} for i in range(n)]
    raw: dict = {"bodies": bodies, "vehicles": vehicles}
    if pose_stream is not None:
        raw["pose_stream"] = pose_stream
    return parse_arena(raw, source)


def body_state(name: str = "body1", body_id: int = 1, *, capture_ns: int | None = None, dt_ns: int = 0,
               position=(0.0, 0.0, 0.0), quaternion=(0.0, 0.0, 0.0, 1.0), velocity=(0.0, 0.0, 0.0),
               angular_velocity=(0.0, 0.0, 0.0), covariance=None, velocity_covariance=None,
               tracked: bool = True, reset_counter: int = 0, n_markers: int = 4, n_cameras: int = 3,
               residual_mm: float = 0.4) -> BodyState:
    """A BodyState; capture_ns defaults to now on the monotonic clock, time_ns = capture_ns + dt_ns."""
    c = time.monotonic_ns() if capture_ns is None else capture_ns
    return BodyState(
        name=name, body_id=body_id, time_ns=c + dt_ns, capture_ns=c,
        position=np.asarray(position, float), quaternion=np.asarray(quaternion, float),
        velocity=np.asarray(velocity, float), angular_velocity=np.asarray(angular_velocity, float),
        covariance=(
            np.diag([1e-6, 1e-6, 1e-6, 1e-5, 1e-5, 1e-5]) if covariance is None else np.asarray(covariance, float)
        ),
        velocity_covariance=np.eye(3) * 1e-4 if velocity_covariance is None else np.asarray(velocity_covariance, float),
        tracked=tracked, n_markers=n_markers, n_cameras=n_cameras, residual_mm=residual_mm,
        reset_counter=reset_counter,
    )
