"""Each configuration setting declared once: YAML key (with its unit), type, default, bounds, doc.

A `Spec` lists the keys of one YAML mapping (a section, or one item of a list section). From it
come the reads (`Spec.read`, `Spec.parse`: bounds checked, unit converted to the dataclass
field, e.g. `window_ms` -> int `window_ns`), the unknown-key check with a did-you-mean
suggestion (`Spec.check`), the `--set` key check (config/overrides.py) and the Markdown
reference (config/reference.py renders docs/configuration.md).

A renamed key keeps its old spelling in `Setting.old_keys`: it still works, with a warning.
"""

from __future__ import annotations

import difflib
import warnings
from dataclasses import dataclass, make_dataclass
from dataclasses import field as dc_field
from typing import Any, Callable, Iterable

from visionpos.config.arena import ConfigError, Section


class _Required:
    def __repr__(self) -> str:
        return "REQUIRED"


REQUIRED: Any = _Required()  # the key must be given

# kinds of value; "section", "list" and "map" hold a nested Spec (map: free keys, each value a Spec)
KINDS = ("number", "integer", "text", "boolean", "array", "any", "section", "list", "map")


class DeprecatedKeyWarning(UserWarning):
    """A config key spelled the old way: it works, but the warning names the new spelling."""


@dataclass(frozen=True)
class Setting:
    """One YAML key.

    key: YAML name, carrying the unit (`window_ms`). field: dataclass field (default: key).
    convert: YAML value -> field value (e.g. ms -> int ns); auto: what 0 means when the value
    is derived at parse time (the caller passes it). spec: the nested mapping of a
    section / list / map kind. old_keys: deprecated spellings (accepted with a warning).
    """

    key: str
    kind: str
    default: Any = REQUIRED
    doc: str = ""
    field: str | None = None
    convert: Callable[[Any], Any] | None = None
    min: float | None = None
    max: float | None = None
    choices: tuple[str, ...] | None = None
    shape: tuple[int | None, ...] | None = None
    auto: str = ""
    default_doc: str | None = None
    spec: "Spec | None" = None
    old_keys: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ValueError(f"setting {self.key}: unknown kind {self.kind!r}")

    @property
    def field_name(self) -> str:
        return self.field or self.key

    @property
    def field_default(self) -> Any:
        """The dataclass default: the YAML default converted (0 for an auto value not yet derived)."""
        if self.auto:
            return 0
        value = self.default
        if self.kind == "number":
            value = float(value)
        return self.convert(value) if self.convert else value

    def read(self, s: Section, **bounds: Any) -> Any:
        """The YAML value (default if absent), checked; `bounds` replace default/min/max/choices."""
        default = bounds.get("default", self.default)
        if default is None and self.key not in s.data:
            return None  # optional, no default
        default = None if default is REQUIRED else default  # the Section reader reports it missing
        lo, hi = bounds.get("min", self.min), bounds.get("max", self.max)
        if self.kind == "number":
            return s.number(self.key, default, min=lo, max=hi)
        if self.kind == "integer":
            if self.key not in s.data and default is None:
                raise s.error(self.key, "required integer is missing")
            return s.integer(self.key, default, min=lo, max=hi)
        if self.kind == "text":
            return s.string(self.key, default, choices=bounds.get("choices", self.choices))
        if self.kind == "boolean":
            return s.boolean(self.key, default)
        if self.kind == "array":
            return s.array(self.key, self.shape or (None,), default)
        return s.data.get(self.key, default)

    def validate(self, s: Section, key: str) -> None:
        """ConfigError naming the key if the value at `key` (present, not null) is not of this kind."""
        if self.kind == "number":
            s.number(key)
        elif self.kind == "integer":
            s.integer(key)
        elif self.kind == "text":
            s.string(key, choices=self.choices)
        elif self.kind == "boolean":
            s.boolean(key, False)
        elif self.kind == "array":
            s.array(key, self.shape or (None,))
        elif self.kind == "section":
            sub = s.sub(key)  # raises unless a mapping
            if self.spec is not None:
                self.spec.validate(sub)
        elif self.kind == "list":
            for item in s.items(key):  # raises unless a list; each item a mapping
                if self.spec is not None:
                    self.spec.validate(item)
        elif self.kind == "map":
            sub = s.sub(key)
            for k in sub.data:
                if sub.data[k] is not None and self.spec is not None:
                    self.spec.validate(sub.sub(k))


@dataclass(frozen=True)
class Spec:
    """The keys of one YAML mapping. path: its place in the file for docs and errors ("fusion.kalman")."""

    path: str
    doc: str
    settings: tuple[Setting, ...]
    extra_keys: str = ""  # doc: keys not listed here are allowed (free-form), and what they are
    removed: tuple[tuple[str, str], ...] = ()  # (key, what to write instead): keys that no longer exist

    def __post_init__(self) -> None:
        keys = [k for s in self.settings for k in (s.key, *s.old_keys)]
        if len(set(keys)) != len(keys):
            raise ValueError(f"spec {self.path}: a key is declared twice")

    def __getitem__(self, key: str) -> Setting:
        for s in self.settings:
            if s.key == key:
                return s
        raise KeyError(key)

    @property
    def keys(self) -> list[str]:
        return [s.key for s in self.settings]

    def new_key(self, key: str) -> str | None:
        """The current spelling of `key` (itself, or the key it is an old spelling of); None if unknown."""
        for s in self.settings:
            if key == s.key or key in s.old_keys:
                return s.key
        return None

    def unknown_key_error(self, source: str, key_path: str, key: str) -> ConfigError:
        for old, message in self.removed:
            if key == old:
                return ConfigError(source, key_path, message)
        return ConfigError(source, key_path, f"unknown key{suggestion(key, self.keys)}; "
                                             f"`{self.path}` takes {', '.join(self.keys)}")

    def check(self, s: Section) -> Section:
        """Reject unknown keys (with a suggestion); old spellings warn and are renamed.

        Returns the section with every key in its current spelling."""
        if self.extra_keys:
            return s
        data = dict(s.data)
        for key in list(s.data):
            new = self.new_key(str(key))
            if new is None:
                raise self.unknown_key_error(s.source, s._key(str(key)), str(key))
            if new != key:
                if new in s.data:
                    raise s.error(str(key), f"is the old spelling of `{new}`, which is also given; keep `{new}` only")
                warn_old_key(s.source, s._key(str(key)), new)
                data[new] = data.pop(key)
        return Section(data, s.source, s.path)

    def read(self, s: Section, key: str, **bounds: Any) -> Any:
        return self[key].read(s, **bounds)

    def validate(self, s: Section) -> None:
        """Check a whole mapping at load, nested sections and list items too: every key declared (an
        unknown one fails with a did-you-mean), every value given of its declared kind (a number, an
        integer, text, true/false, an array of its shape, a mapping, a list). Bounds and required keys
        are the parsers' (a caller may narrow them); an old spelling is checked here and warned about
        by the parser that reads it. A null value is left to the parser (for most keys: an error)."""
        if self.extra_keys:
            return
        for key in s.data:
            new = self.new_key(str(key))
            if new is None:
                raise self.unknown_key_error(s.source, s._key(str(key)), str(key))
            if s.data[key] is not None:
                self[new].validate(s, key)

    def parse(self, s: Section, auto: dict[str, Any] | None = None) -> dict[str, Any]:
        """Check the keys, read every scalar setting: {field name: converted value}.

        auto: the derived value of each `auto` setting, used where the YAML value is 0."""
        s = self.check(s)
        out: dict[str, Any] = {}
        for st in self.settings:
            if st.kind in ("section", "list", "map", "any"):
                continue
            value = st.read(s)
            if st.auto and value == 0:
                value = (auto or {})[st.key]
            out[st.field_name] = st.convert(value) if st.convert else value
        return out


def warn_old_key(source: str, key_path: str, new_key: str) -> None:
    warnings.warn(f"{source}: {key_path}: old spelling, still accepted; write `{new_key}`",
                  DeprecatedKeyWarning, stacklevel=4)


def suggestion(key: str, known: Iterable[str]) -> str:
    """' (did you mean `x`?)' for the closest known key, or ''."""
    close = difflib.get_close_matches(str(key), list(known), n=1, cutoff=0.6)
    return f" (did you mean `{close[0]}`?)" if close else ""


def section(path: str, doc: str, *settings: Setting, extra_keys: str = "",
            removed: dict[str, str] | None = None) -> Spec:
    return Spec(path, doc, tuple(settings), extra_keys, tuple((removed or {}).items()))


def ms_to_ns(ms: float) -> int:
    """The ms -> int ns conversion every `*_ms` setting has always used (truncation, not rounding)."""
    return int(ms * 1e6)


_FIELD_TYPES = {"number": float, "integer": int, "text": str, "boolean": bool}


def settings_dataclass(name: str, spec: Spec, doc: str, module: str, *, nested: dict[str, type] | None = None,
                       extra: Iterable[tuple[str, type, Any]] = ()) -> type:
    """The frozen dataclass of one Spec: a field per scalar setting (name `Setting.field_name`, default
    `Setting.field_default`), in declaration order, then a field per `section` setting whose class is
    in `nested` (default: that class's defaults), then `extra` (name, type, default): fields the YAML
    does not set. `Spec.parse` fills it: a setting added to the Spec is a field here with no other edit.
    """
    fields: list[tuple[str, Any, Any]] = []
    for st in spec.settings:
        if st.kind == "section" and nested and st.key in nested:
            fields.append((st.field_name, nested[st.key], dc_field(default_factory=nested[st.key])))
        elif st.kind in _FIELD_TYPES:
            default = st.field_default
            kind = type(default) if st.convert or st.auto else _FIELD_TYPES[st.kind]
            fields.append((st.field_name, kind, dc_field(default=default)))
    for key, kind, default in extra:
        fields.append((key, kind, dc_field(default=default)))
    cls = make_dataclass(name, fields, frozen=True)
    cls.__doc__, cls.__module__ = doc, module
    return cls
