"""The whole arena file's declarations: the top level with each stage's section attached.

Each stage declares its own section beside the code that reads it (fusion/settings.py,
server/settings.py, sim/scenario.py, bridge/config.py) and registers it here when imported.
The config layer thus never imports the stages above it. A section nobody has registered is
still checked by its owner's parser when the arena is loaded; the CLI and the reference-doc
generator import every stage (visionpos/app/sections.py), so `--set` checks every key there.
"""

from __future__ import annotations

from dataclasses import replace

from visionpos.config.settings import Spec

_SECTIONS: dict[str, Spec] = {}  # top-level key -> that section's Spec (for a list section: one item's)


def register_section(key: str, spec: Spec) -> None:
    """Attach a stage's Spec to the top-level key `key` of the arena file (at that module's import)."""
    _SECTIONS[key] = spec


def arena_schema() -> Spec:
    """The top-level Spec, each registered section's Setting holding that section's Spec."""
    from visionpos.config.sections import TOP

    settings = tuple(replace(s, spec=_SECTIONS[s.key]) if s.key in _SECTIONS else s for s in TOP.settings)
    return replace(TOP, settings=settings)
