"""Config overrides, one mechanism: `--set dotted.key=value` on the whole arena file and the
settings mappings the fusion pipeline takes (nested or dotted keys).

`--set` keys are checked against the declarations (config/schema.py) before anything changes, so
a typo fails with a suggestion instead of being ignored, and a list index out of range names the
key. Values are parsed as YAML (`--set fusion.loose_points=false`, `--set cameras.0.dist=[0,0,0,0]`),
except that a number given for a key declared as text is taken as the text typed (`--set
natnet.bitstream=3.1` is "3.1", `--set x=3.10` is "3.10", not the float's repr).
"""

from __future__ import annotations

import copy
from typing import Any

import yaml

from visionpos.config.arena import ConfigError
from visionpos.config.settings import Spec, warn_old_key


def apply_overrides(data: dict[str, Any], overrides: list[str], source: str = "--set",
                    schema: Spec | None = None) -> dict[str, Any]:
    """Apply `dotted.key=value` overrides to an arena mapping; returns a copy, `data` is unchanged.

    List items are addressed by index: `bodies.0.marker_diameter=0.02`. Keys are checked against
    `schema` (default: the whole arena file); an old spelling warns and sets the new key.
    """
    if schema is None:
        from visionpos.config.schema import arena_schema  # the schema imports the stage modules

        schema = arena_schema()
    out = copy.deepcopy(data)
    for item in overrides:
        if "=" not in item:
            raise ConfigError(source, item, "expected key=value, e.g. fusion.max_residual_px=2.0")
        key, value = item.split("=", 1)
        parts = key.strip().split(".")
        if not all(parts):
            raise ConfigError(source, key, "empty part in the dotted key; write e.g. fusion.kalman.gate_chi2=30")
        set_path(out, parts, yaml.safe_load(value), schema, source, text=value.strip())
    return out


def set_path(data: dict[str, Any], parts: list[str], value: Any, schema: Spec | None, source: str,
             text: str | None = None) -> None:
    """data[parts[0]][parts[1]]... = value, creating mappings on the way; list items by index.

    schema: the Spec of `data` (None: free-form, nothing checked). text: the value as typed; where the key is
    declared as text and YAML read a number from it, the key gets this text instead."""
    node: Any = data
    spec = schema  # mode "mapping": the spec of node (None: free); "list" / "map": the spec of its items
    mode = "mapping"
    done: list[str] = []
    for j, part in enumerate(parts):
        last = j == len(parts) - 1
        where = ".".join(done + [part])
        key: Any = part
        kind = "section"
        if mode == "list":
            n = len(node)
            if not part.isdigit() or int(part) >= n:
                what = f"has {n} items; give an index 0..{n - 1}" if n else "is empty; add items in the file"
                raise ConfigError(source, where, f"`{'.'.join(done)}` {what}")
            key = int(part)
        elif mode == "mapping" and spec is not None and not spec.extra_keys:
            new = spec.new_key(part)
            if new is None:
                raise spec.unknown_key_error(source, where, part)
            if new != part:
                warn_old_key(source, where, new)
                if part in node:
                    node[new] = node.pop(part)
                key = new
            kind = spec[new].kind
            if not last and kind not in ("section", "list", "map", "any"):
                raise ConfigError(source, where, f"is a single value, not a section; write {where}=VALUE")
        if last:
            is_number = isinstance(value, (int, float)) and not isinstance(value, bool)
            node[key] = text if kind == "text" and is_number and text is not None else value
            return
        if mode in ("list", "map"):
            child_spec = spec  # the items' spec
        elif spec is not None and not spec.extra_keys:
            child_spec = spec[key].spec
        else:
            child_spec = None
        if mode != "list" and node.get(key) is None:
            node[key] = [] if kind == "list" else {}
        child = node[key]
        if isinstance(child, list):
            mode, spec = "list", child_spec if kind == "list" else None
        elif isinstance(child, dict):
            mode, spec = ("map" if kind == "map" else "mapping"), child_spec
        else:
            raise ConfigError(source, where, f"is {child!r}, not a mapping; cannot set {'.'.join(parts)}")
        node = child
        done.append(part)


def expand_dotted(d: dict[str, Any]) -> dict[str, Any]:
    """{'kalman.gate_chi2': 20} -> {'kalman': {'gate_chi2': 20}} (nested dicts pass through)."""
    out: dict[str, Any] = {}
    for k, v in d.items():
        parts = str(k).split(".")
        node = out
        for p in parts[:-1]:
            node = node.setdefault(p, {})
        if isinstance(v, dict):
            v = expand_dotted(v)
            if isinstance(node.get(parts[-1]), dict):
                node[parts[-1]] = merge(node[parts[-1]], v)
                continue
        node[parts[-1]] = v
    return out


def merge(base: dict[str, Any], over: dict[str, Any]) -> dict[str, Any]:
    """`over` on top of `base`, recursively for mappings; returns a new mapping."""
    out = dict(base)
    for k, v in over.items():
        if isinstance(v, dict) and isinstance(out.get(k), dict):
            out[k] = merge(out[k], v)
        else:
            out[k] = v
    return out


def merge_section(base: dict[str, Any], settings: dict[str, Any] | None, name: str) -> dict[str, Any]:
    """A section's mapping (`base`) overridden by `settings`: nested, dotted, or wrapped as {name: {...}}."""
    data = expand_dotted(dict(base))
    if settings:
        over = expand_dotted(dict(settings))
        if isinstance(over.get(name), dict):  # `--set fusion.x=y` style keys
            inner = over.pop(name)
            over = merge(over, inner)
        data = merge(data, over)
    return data
