"""Arena configuration: YAML in, validated dataclasses out.

One arena file holds `cameras`, `bodies` and optional sections owned by
other stages (`fusion`, `server`, `vehicles`, `pose_stream`, `sim`). This
module validates the shared parts; each stage validates its own section
with the helpers here, so every error names the file, the key and what
would be right.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from visionpos.camera.model import Camera, CameraModelError
from visionpos.errors import VisionposError

CONFIG_DIR = Path(__file__).resolve().parents[1] / "configs"
BUILTIN_SCENARIOS = {"thesis": "thesis_arena.yaml", "arena8": "arena8.yaml", "fleet": "fleet.yaml",
                     "fleet20": "fleet20.yaml", "pair": "pair.yaml"}


class ConfigError(VisionposError, ValueError):
    """A configuration problem. str() names the file, the key and the fix."""

    def __init__(self, source: str, key: str, message: str):
        self.source, self.key, self.message = source, key, message
        super().__init__(f"{source}: {key}: {message}")


def resolve_config_path(name_or_path: str | Path) -> Path:
    """A built-in scenario name ('thesis', 'arena8') or a path -> existing Path."""
    s = str(name_or_path)
    if s in BUILTIN_SCENARIOS:
        return CONFIG_DIR / BUILTIN_SCENARIOS[s]
    p = Path(s)
    if p.exists():
        return p
    if (CONFIG_DIR / s).exists():
        return CONFIG_DIR / s
    raise ConfigError(
        s, "(file)", f"no such file; give a path or a built-in scenario name {sorted(BUILTIN_SCENARIOS)}"
    )


def _refuse_duplicate_keys(node: yaml.Node | None, path: str, source: str, seen: set[int]) -> None:
    """ConfigError for the first mapping key given twice under `node` (a composed YAML node tree)."""
    if node is None or id(node) in seen:  # an alias is checked where its anchor is
        return
    seen.add(id(node))
    if isinstance(node, yaml.MappingNode):
        lines: dict[tuple[str, str], int] = {}
        for key_node, value_node in node.value:
            if key_node.tag == "tag:yaml.org,2002:merge" or not isinstance(key_node, yaml.ScalarNode):
                continue
            key = f"{path}.{key_node.value}" if path else str(key_node.value)
            line = key_node.start_mark.line + 1
            first = lines.setdefault((key_node.tag, key_node.value), line)
            if first != line:
                raise ConfigError(source, key, f"given twice (line {first} and line {line}); keep one "
                                               "(YAML would silently take the last)")
            _refuse_duplicate_keys(value_node, key, source, seen)
    elif isinstance(node, yaml.SequenceNode):
        for i, item in enumerate(node.value):
            _refuse_duplicate_keys(item, f"{path}[{i}]", source, seen)


def parse_yaml_text(text: str, source: str) -> Any:
    """YAML text -> Python data (safe types only). A key given twice in one mapping is refused with a
    ConfigError naming `source`, the key and both lines; PyYAML would keep the last without a word."""
    try:
        _refuse_duplicate_keys(yaml.compose(text, Loader=yaml.SafeLoader), "", source, set())
        return yaml.safe_load(text)
    except yaml.YAMLError as e:
        raise ConfigError(source, "(syntax)", f"not valid YAML: {e}") from None


def load_yaml(path: str | Path) -> dict[str, Any]:
    """Read a YAML mapping; raises ConfigError naming the file on any problem (a key given twice too)."""
    p = Path(path)
    try:
        text = p.read_bytes().decode("utf-8")
    except OSError as e:
        raise ConfigError(str(p), "(file)", f"cannot read: {e.strerror or e}") from None
    except UnicodeDecodeError as e:
        line = p.read_bytes()[: e.start].count(b"\n") + 1
        raise ConfigError(str(p), "(file)", f"not UTF-8 text (byte {e.start}, line {line}); "
                                            "save the file as UTF-8") from None
    data = parse_yaml_text(text, str(p))
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ConfigError(str(p), "(top level)", "expected a mapping of sections (cameras, bodies, ...)")
    return data


class Section:
    """Typed reads from one YAML mapping with errors naming file and key path.

    >>> s = Section({"rate_hz": 50}, "arena.yaml", "vehicles[0]")
    >>> s.number("rate_hz", 100, min=1)
    50.0
    """

    def __init__(self, data: Any, source: str, path: str):
        if data is None:
            data = {}
        if not isinstance(data, dict):
            raise ConfigError(source, path, f"expected a mapping, got {type(data).__name__}")
        self.data, self.source, self.path = data, source, path

    def _key(self, key: str) -> str:
        return f"{self.path}.{key}" if self.path else key

    def error(self, key: str, message: str) -> ConfigError:
        return ConfigError(self.source, self._key(key), message)

    def has(self, key: str) -> bool:
        return key in self.data

    def sub(self, key: str) -> "Section":
        return Section(self.data.get(key), self.source, self._key(key))

    def items(self, key: str) -> list["Section"]:
        v = self.data.get(key, [])
        if not isinstance(v, list):
            raise self.error(key, "expected a list")
        return [Section(x, self.source, f"{self._key(key)}[{i}]") for i, x in enumerate(v)]

    def number(
        self, key: str, default: float | None = None, *, min: float | None = None, max: float | None = None
    ) -> float:
        if key not in self.data:
            if default is None:
                raise self.error(key, "required number is missing")
            return float(default)
        v = self.data[key]
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise self.error(key, f"expected a number, got {v!r}")
        v = float(v)
        if not np.isfinite(v):
            raise self.error(key, f"must be finite, got {v}")
        if min is not None and v < min:
            raise self.error(key, f"must be >= {min}, got {v}")
        if max is not None and v > max:
            raise self.error(key, f"must be <= {max}, got {v}")
        return v

    def integer(self, key: str, default: int | None = None, *, min: int | None = None, max: int | None = None) -> int:
        if key not in self.data and default is not None:
            return int(default)
        v = self.data.get(key)
        if isinstance(v, bool) or not isinstance(v, int):
            raise self.error(key, f"expected an integer, got {v!r}")
        if min is not None and v < min:
            raise self.error(key, f"must be >= {min}, got {v}")
        if max is not None and v > max:
            raise self.error(key, f"must be <= {max}, got {v}")
        return v

    def string(self, key: str, default: str | None = None, *, choices: tuple[str, ...] | None = None) -> str:
        if key not in self.data:
            if default is None:
                raise self.error(key, "required text is missing")
            return default
        v = self.data[key]
        if not isinstance(v, str):
            raise self.error(key, f"expected text, got {v!r}")
        if choices is not None and v not in choices:
            raise self.error(key, f"'{v}' is not one of {list(choices)}")
        return v

    def boolean(self, key: str, default: bool) -> bool:
        v = self.data.get(key, default)
        if not isinstance(v, bool):
            raise self.error(key, f"expected true or false, got {v!r}")
        return v

    def array(self, key: str, shape: tuple[int | None, ...], default: Any = None) -> np.ndarray:
        """Numeric array with a shape pattern (None = any length)."""
        if key not in self.data:
            if default is None:
                raise self.error(key, f"required array of shape {shape} is missing")
            return np.asarray(default, dtype=np.float64)
        try:
            a = np.asarray(self.data[key], dtype=np.float64)
        except (TypeError, ValueError):
            raise self.error(key, f"expected numbers of shape {shape}, got {self.data[key]!r}") from None
        if a.ndim != len(shape) or any(s is not None and s != n for s, n in zip(shape, a.shape)):
            raise self.error(key, f"expected shape {shape}, got {a.shape}")
        if not np.isfinite(a).all():
            raise self.error(key, "contains non-finite values")
        return a


@dataclass(frozen=True)
class BodyConfig:
    """A rigid body: markers (M, 3) in the body frame (m; x forward, y left, z up); M = 1: a point body (position
    only, its one marker at the origin)."""

    name: str
    id: int
    markers: np.ndarray
    marker_diameter: float = 0.014
    raw: dict[str, Any] = field(default_factory=dict)

    @property
    def is_point(self) -> bool:
        """One marker: tracked for its position only (fusion/point_tracks.py)."""
        return len(self.markers) == 1


@dataclass(frozen=True)
class ArenaConfig:
    """Cameras and bodies plus the raw YAML of every section (for stage-owned sections)."""

    source: str
    cameras: tuple[Camera, ...]
    bodies: tuple[BodyConfig, ...]
    raw: dict[str, Any]
    unposed: tuple[int, ...] = ()  # ids of cameras whose entry has no pose yet (placeholder pose at the origin)

    def camera_by_id(self) -> dict[int, Camera]:
        return {c.id: c for c in self.cameras}

    def require_poses(self, what: str) -> None:
        """ConfigError naming the first camera without a pose, for a step that needs them all."""
        if self.unposed:
            i = next(k for k, c in enumerate(self.cameras) if c.id in self.unposed)
            raise ConfigError(self.source, f"cameras[{i}].pose",
                              f"{what} needs every camera's pose and camera {self.unposed[0]} has none (of "
                              f"{len(self.unposed)} without); record a wand wave (`visionpos record`) and run "
                              "`visionpos calibrate wand` to find them, or give rough ones (position and look_at)")

    def section(self, key: str) -> Section:
        """The top-level section `key` for its parser to read (an absent or null one is empty)."""
        return Section(self.raw.get(key), self.source, key)

    def items(self, key: str) -> list[Section]:
        """The items of the top-level list section `key` (`vehicles`), each for its parser to read."""
        return Section(self.raw, self.source, "").items(key)

    def given(self, key: str) -> bool:
        """Whether the file has the top-level section `key` (not null): the optional servers (pose_stream,
        vrpn, natnet, foxglove) run only then."""
        return self.raw.get(key) is not None

    def camera_stations(self) -> dict[int, int | None]:
        """Camera id -> the station id expected to send its frames (`cameras[i].station`; None: any)."""
        entries = self.raw.get("cameras") or []
        return {c.id: entries[i].get("station") if i < len(entries) else None for i, c in enumerate(self.cameras)}

    def to_dict(self) -> dict[str, Any]:
        """A deep copy of the file's mapping: what a recording stores, what a rewritten arena file starts from."""
        return copy.deepcopy(self.raw)

    def with_cameras(self, cameras: list[Camera]) -> "ArenaConfig":
        raw = dict(self.raw)
        raw["cameras"] = [c.to_dict() for c in cameras]
        return ArenaConfig(self.source, tuple(cameras), self.bodies, raw)


def parse_arena(data: dict[str, Any], source: str = "<arena>") -> ArenaConfig:
    """Validate a parsed arena mapping."""
    from visionpos.config import sections  # sections imports this module
    from visionpos.config.schema import arena_schema

    # every key and the kind of every value, in every registered section (the CLI registers them all),
    # before any stage reads one: a wrong type is a ConfigError naming the key, not a traceback later
    arena_schema().validate(Section(data, source, ""))
    top = sections.TOP.check(Section(data, source, ""))
    cams: list[Camera] = []
    unposed: list[int] = []
    for i, c in enumerate(top.items("cameras")):
        c = sections.CAMERA.check(c)
        entry = c.data
        if isinstance(c.data.get("pose"), dict):
            sections.CAMERA_POSE.check(c.sub("pose"))
        elif c.data.get("pose") is None:
            # not calibrated yet: a placeholder pose, and the camera listed in ArenaConfig.unposed
            entry = {**c.data, "pose": {"position": [0.0, 0.0, 0.0], "quaternion_xyzw": [0.0, 0.0, 0.0, 1.0]}}
        try:
            cams.append(Camera.from_dict(entry, where=f"cameras[{i}]"))
        except CameraModelError as e:
            raise ConfigError(source, f"cameras[{i}]", str(e)) from None
        if entry is not c.data:
            unposed.append(cams[-1].id)
    ids = [c.id for c in cams]
    if len(set(ids)) != len(ids):
        raise ConfigError(source, "cameras", f"camera ids must be unique, got {ids}")
    bodies: list[BodyConfig] = []
    for b in top.items("bodies"):
        b = sections.BODY.check(b)
        if b.has("occlusion"):
            sections.BODY_OCCLUSION.check(b.sub("occlusion"))
        markers = sections.BODY.read(b, "markers")
        if len(markers) == 1 and np.any(markers[0] != 0.0):
            raise b.error("markers", f"a single-marker (point) body's marker is its origin: write [[0, 0, 0]], got "
                                     f"{markers.tolist()}")
        if len(markers) == 2:
            raise b.error("markers", "a rigid body needs at least 3 markers (one marker: a position-only point "
                                     "body, [[0, 0, 0]]), got 2")
        if len(markers) < 1:
            raise b.error("markers", "a body needs 1 marker (a point body) or at least 3 (a rigid body), got 0")
        d = np.linalg.norm(markers[:, None] - markers[None], axis=-1)
        if np.min(d + np.eye(len(markers)) * 1e9) < 0.01:
            raise b.error("markers", "two markers are closer than 10 mm; cameras cannot separate them")
        bodies.append(
            BodyConfig(
                name=sections.BODY.read(b, "name"),
                id=sections.BODY.read(b, "id", default=len(bodies) + 1),
                markers=markers,
                marker_diameter=sections.BODY.read(b, "marker_diameter"),
                raw=b.data,
            )
        )
    names = [b.name for b in bodies]
    if len(set(names)) != len(names):
        raise ConfigError(source, "bodies", f"body names must be unique, got {names}")
    return ArenaConfig(source, tuple(cams), tuple(bodies), data, tuple(unposed))


def load_arena(path: str | Path) -> ArenaConfig:
    """Load and validate an arena YAML (a path or a built-in scenario name)."""
    p = resolve_config_path(path)
    return parse_arena(load_yaml(p), str(p))


def apply_overrides(data: dict[str, Any], overrides: list[str], source: str = "--set") -> dict[str, Any]:
    """Apply `dotted.key=value` overrides to an arena mapping; returns a copy (see config/overrides.py)."""
    from visionpos.config.overrides import apply_overrides as apply  # overrides imports this module

    return apply(data, overrides, source)


def dump_yaml(data: dict[str, Any], path: str | Path) -> None:
    Path(path).write_text(yaml.safe_dump(data, sort_keys=False))
