"""Work split into steps: generators that yield each step's estimated cost (ns) and return their result.

Acquisition's matching (acquisition.match_unlabeled_steps) and identification (rigidbody.identify_steps)
are written this way so that the pipeline can spread a large acquisition (a parked fleet's first one is
about 40 ms of work) over several fusions instead of holding up the frames behind it (pipeline.py,
fusion.acquire_step_ms). The estimates are budgets to cut the work by, never measurements, so the cut and
the result are the same on every machine and in every replay.
"""

from __future__ import annotations

from collections.abc import Generator
from typing import Any, TypeVar

T = TypeVar("T")

Steps = Generator[float, None, T]


def finish(steps: Steps[T]) -> T:
    """Run a generator of steps to its end: its result."""
    while True:
        try:
            next(steps)
        except StopIteration as done:
            return done.value


def advance(steps: Steps[Any], budget_ns: float) -> tuple[bool, Any]:
    """Run steps while their estimated cost stays within budget_ns, taking the next step to cost what the last
    did (at least one step): (done, result or None)."""
    spent = 0.0
    while True:
        try:
            last = next(steps)
        except StopIteration as done:
            return True, done.value
        spent += last
        if spent + last > budget_ns:
            return False, None
