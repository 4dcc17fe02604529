"""The whole arena file's declarations: the top level with each stage's section attached.

Each stage declares its own section beside the code that reads it (fusion/settings.py,
server/settings.py, sim/scenario.py, bridge/config.py) and registers it here when imported, with
its parser. One convention for every section: `parse_<key>(arena, ...)` in the declaring module
returns the parsed, checked settings (parse_fusion, parse_server, parse_vrpn, parse_sim, ...);
code reads those, never the raw mapping. `parse_section(arena, key)` calls the registered one.
The config layer thus never imports the stages above it. A section nobody has registered is
still checked by its owner's parser when the arena is loaded; the CLI and the reference-doc
generator import every stage (visionpos/app/sections.py), so `--set` checks every key there.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any, Callable

from visionpos.config.settings import Spec

_SECTIONS: dict[str, Spec] = {}  # top-level key -> that section's Spec (for a list section: one item's)
_PARSERS: dict[str, Callable[..., Any]] = {}  # top-level key -> its parse_<key>(arena, ...)


def register_section(key: str, spec: Spec, parse: Callable[..., Any]) -> None:
    """Attach a stage's Spec and its parser `parse_<key>` to the top-level key `key` of the arena file
    (at that module's import)."""
    name = f"parse_{key}"
    if getattr(parse, "__name__", "") != name:
        raise ValueError(f"section {key}: its parser must be named {name}, not {parse.__name__}")
    _SECTIONS[key] = spec
    _PARSERS[key] = parse


def registered_sections() -> dict[str, tuple[Spec, Callable[..., Any]]]:
    """Top-level key -> (Spec, parser) of every section registered so far."""
    return {k: (_SECTIONS[k], _PARSERS[k]) for k in _SECTIONS}


def parse_section(arena: Any, key: str, *args: Any, **kwargs: Any) -> Any:
    """The parsed, checked settings of the arena's section `key`: its registered parse_<key>(arena, ...).
    The declaring module must have been imported (visionpos/app/sections.py imports them all)."""
    if key not in _PARSERS:
        raise KeyError(f"no parser registered for section {key!r}; import the module that declares it "
                       "(visionpos.app.sections imports every one)")
    return _PARSERS[key](arena, *args, **kwargs)


def arena_schema() -> Spec:
    """The top-level Spec, each registered section's Setting holding that section's Spec."""
    from visionpos.config.sections import TOP

    settings = tuple(replace(s, spec=_SECTIONS[s.key]) if s.key in _SECTIONS else s for s in TOP.settings)
    return replace(TOP, settings=settings)
