"""The Foxglove message types visionpos writes, as protobuf: an encoder and the schemas, with no dependency.

Foxglove and Lichtblick recognise a channel by its schema name ("foxglove.SceneUpdate") and decode
protobuf messages with the FileDescriptorSet stored as the MCAP schema. Both are built here from
SCHEMAS, a transcription of the published foxglove/*.proto definitions for the types we use (field
names, numbers and types; every field of each type, so a decoder fills the ones we leave out with
their defaults). tests/foxglove/ checks each declaration against the official generated classes
(foxglove-schemas-protobuf) and parses every message we write with them, so the core install needs
neither protobuf nor the schema package.

Messages are plain dicts keyed by field name; `encode(type_name, msg)` writes proto3 wire format:
fields in number order, scalars equal to their default left out, repeated scalars packed, a
sub-message present whenever its key is (even empty). A sub-message may also be given as the
bytes `encode` made of it (constants encoded once). `time_msg` makes timestamps and durations.
"""

from __future__ import annotations

import struct
from functools import lru_cache
from typing import Any

# "type name  field:type=number ..." in declaration order; *field: repeated, ?field: proto3 `optional`;
# an enum is declared as "enum Name VALUE=n ...".
# Transcribed from the published schemas (docs.foxglove.dev message-schemas, foxglove/*.proto).
SCHEMAS = """
google.protobuf.Timestamp  seconds:int64=1 nanos:int32=2
google.protobuf.Duration  seconds:int64=1 nanos:int32=2
foxglove.Vector3  x:double=1 y:double=2 z:double=3
foxglove.Point2  x:double=1 y:double=2
foxglove.Point3  x:double=1 y:double=2 z:double=3
foxglove.Quaternion  x:double=1 y:double=2 z:double=3 w:double=4
foxglove.Color  r:double=1 g:double=2 b:double=3 a:double=4
foxglove.KeyValuePair  key:string=1 value:string=2
foxglove.Pose  position:foxglove.Vector3=1 orientation:foxglove.Quaternion=2
foxglove.FrameTransform  timestamp:google.protobuf.Timestamp=1 parent_frame_id:string=2 child_frame_id:string=3
    translation:foxglove.Vector3=4 rotation:foxglove.Quaternion=5
foxglove.FrameTransforms  *transforms:foxglove.FrameTransform=1
foxglove.ArrowPrimitive  pose:foxglove.Pose=1 shaft_length:double=2 shaft_diameter:double=3 head_length:double=4
    head_diameter:double=5 color:foxglove.Color=6
foxglove.CubePrimitive  pose:foxglove.Pose=1 size:foxglove.Vector3=2 color:foxglove.Color=3
foxglove.SpherePrimitive  pose:foxglove.Pose=1 size:foxglove.Vector3=2 color:foxglove.Color=3
foxglove.CylinderPrimitive  pose:foxglove.Pose=1 size:foxglove.Vector3=2 bottom_scale:double=3 top_scale:double=4
    color:foxglove.Color=5
enum foxglove.LinePrimitive.Type  LINE_STRIP=0 LINE_LOOP=1 LINE_LIST=2
foxglove.LinePrimitive  type:foxglove.LinePrimitive.Type=1 pose:foxglove.Pose=2 thickness:double=3
    scale_invariant:bool=4 *points:foxglove.Point3=5 color:foxglove.Color=6 *colors:foxglove.Color=7
    *indices:fixed32=8
foxglove.TriangleListPrimitive  pose:foxglove.Pose=1 *points:foxglove.Point3=2 color:foxglove.Color=3
    *colors:foxglove.Color=4 *indices:fixed32=5
foxglove.TextPrimitive  pose:foxglove.Pose=1 billboard:bool=2 font_size:double=3 scale_invariant:bool=4
    color:foxglove.Color=5 text:string=6
foxglove.ModelPrimitive  pose:foxglove.Pose=1 scale:foxglove.Vector3=2 color:foxglove.Color=3 override_color:bool=4
    url:string=5 media_type:string=6 data:bytes=7
foxglove.SceneEntity  timestamp:google.protobuf.Timestamp=1 frame_id:string=2 id:string=3
    lifetime:google.protobuf.Duration=4 frame_locked:bool=5 *metadata:foxglove.KeyValuePair=6
    *arrows:foxglove.ArrowPrimitive=7 *cubes:foxglove.CubePrimitive=8 *spheres:foxglove.SpherePrimitive=9
    *cylinders:foxglove.CylinderPrimitive=10 *lines:foxglove.LinePrimitive=11
    *triangles:foxglove.TriangleListPrimitive=12 *texts:foxglove.TextPrimitive=13 *models:foxglove.ModelPrimitive=14
enum foxglove.SceneEntityDeletion.Type  MATCHING_ID=0 ALL=1
foxglove.SceneEntityDeletion  timestamp:google.protobuf.Timestamp=1 type:foxglove.SceneEntityDeletion.Type=2
    id:string=3
foxglove.SceneUpdate  *deletions:foxglove.SceneEntityDeletion=1 *entities:foxglove.SceneEntity=2
foxglove.CircleAnnotation  timestamp:google.protobuf.Timestamp=1 position:foxglove.Point2=2 diameter:double=3
    thickness:double=4 fill_color:foxglove.Color=5 outline_color:foxglove.Color=6 *metadata:foxglove.KeyValuePair=7
enum foxglove.PointsAnnotation.Type  UNKNOWN=0 POINTS=1 LINE_LOOP=2 LINE_STRIP=3 LINE_LIST=4
foxglove.PointsAnnotation  timestamp:google.protobuf.Timestamp=1 type:foxglove.PointsAnnotation.Type=2
    *points:foxglove.Point2=3 outline_color:foxglove.Color=4 *outline_colors:foxglove.Color=5
    fill_color:foxglove.Color=6 thickness:double=7 *metadata:foxglove.KeyValuePair=8
foxglove.TextAnnotation  timestamp:google.protobuf.Timestamp=1 position:foxglove.Point2=2 text:string=3
    font_size:double=4 text_color:foxglove.Color=5 background_color:foxglove.Color=6 *metadata:foxglove.KeyValuePair=7
foxglove.ImageAnnotations  ?timestamp:google.protobuf.Timestamp=5 *circles:foxglove.CircleAnnotation=1
    *points:foxglove.PointsAnnotation=2 *texts:foxglove.TextAnnotation=3 *metadata:foxglove.KeyValuePair=4
foxglove.CameraCalibration  timestamp:google.protobuf.Timestamp=1 frame_id:string=9 width:fixed32=2 height:fixed32=3
    distortion_model:string=4 *D:double=5 *K:double=6 *R:double=7 *P:double=8
enum foxglove.Log.Level  UNKNOWN=0 DEBUG=1 INFO=2 WARNING=3 ERROR=4 FATAL=5
foxglove.Log  timestamp:google.protobuf.Timestamp=1 level:foxglove.Log.Level=2 message:string=3 name:string=4
    file:string=5 line:fixed32=6
"""

# descriptor.proto's FieldDescriptorProto.Type numbers, and the wire type each is written with
_SCALARS = {"double": 1, "float": 2, "int64": 3, "uint64": 4, "int32": 5, "fixed64": 6, "fixed32": 7, "bool": 8,
            "string": 9, "bytes": 12, "uint32": 13}
_TYPE_MESSAGE, _TYPE_ENUM = 11, 14
_LABEL_OPTIONAL, _LABEL_REPEATED = 1, 3
_WIRE_VARINT, _WIRE_I64, _WIRE_LEN, _WIRE_I32 = 0, 1, 2, 5


def _parse(text: str) -> tuple[dict[str, list[tuple[str, int, str, str]]], dict[str, list[tuple[str, int]]]]:
    """SCHEMAS -> ({message: [(field, number, type, label "" "*" or "?")]}, {enum: [(value, number)]})."""
    messages: dict[str, list[tuple[str, int, str, str]]] = {}
    enums: dict[str, list[tuple[str, int]]] = {}
    lines: list[str] = []
    for raw in text.strip().splitlines():  # an indented line continues the one before
        if raw.startswith(" ") and lines:
            lines[-1] += " " + raw.strip()
        elif raw.strip():
            lines.append(raw.strip())
    for line in lines:
        words = line.split()
        if words[0] == "enum":
            enums[words[1]] = [(v, int(n)) for v, n in (w.split("=") for w in words[2:])]
            continue
        fields = []
        for w in words[1:]:
            spec, number = w.split("=")
            name, kind = spec.split(":")
            label = name[0] if name[0] in "*?" else ""
            fields.append((name.lstrip("*?"), int(number), kind, label))
        messages[words[0]] = fields
    return messages, enums


MESSAGES, ENUMS = _parse(SCHEMAS)


# ---------------------------------------------------------------- wire format


def varint(n: int) -> bytes:
    """A protobuf varint (negative ints as ten bytes of two's complement)."""
    if n < 0:
        n += 1 << 64  # int32/int64/enum: two's complement, ten bytes
    out = bytearray()
    while n > 0x7F:
        out.append((n & 0x7F) | 0x80)
        n >>= 7
    out.append(n)
    return bytes(out)


def _key(number: int, wire: int) -> bytes:
    return varint(number << 3 | wire)


_PACK = {"double": struct.Struct("<d"), "float": struct.Struct("<f"), "fixed32": struct.Struct("<I"),
         "fixed64": struct.Struct("<Q")}
_WIRE = {"double": _WIRE_I64, "fixed64": _WIRE_I64, "float": _WIRE_I32, "fixed32": _WIRE_I32}


def _scalar(kind: str, value: Any) -> bytes:
    """One scalar's payload (no key)."""
    if kind in _PACK:
        return _PACK[kind].pack(value)
    if kind == "string":
        b = value.encode()
        return varint(len(b)) + b
    if kind == "bytes":
        return varint(len(value)) + bytes(value)
    return varint(int(value))  # ints, bool, enum


class _Field:
    __slots__ = ("name", "key", "kind", "repeated", "message", "packed_key", "wire", "pack")

    def __init__(self, name: str, number: int, kind: str, label: str) -> None:
        self.name = name
        self.kind = kind
        self.repeated = label == "*"
        self.message = kind in MESSAGES
        if kind not in MESSAGES and kind not in ENUMS and kind not in _SCALARS:
            raise ValueError(f"protobuf schema: field {name} has unknown type {kind}")
        self.wire = _WIRE_LEN if self.message or kind in ("string", "bytes") else _WIRE.get(kind, _WIRE_VARINT)
        self.key = _key(number, self.wire)
        self.packed_key = _key(number, _WIRE_LEN)
        self.pack = _PACK.get(kind)


@lru_cache(maxsize=None)
def _fields(type_name: str) -> tuple[tuple[_Field, ...], frozenset[str]]:
    fields = tuple(_Field(*f) for f in sorted(MESSAGES[type_name], key=lambda f: f[1]))  # written in number order
    return fields, frozenset(f.name for f in fields)


def encode(type_name: str, msg: dict[str, Any]) -> bytes:
    """A message (dict of field name -> value, sub-messages as dicts, repeated fields as lists) -> bytes.

    Keys that are not fields of type_name raise KeyError (a typo must not vanish silently).
    """
    fields, names = _fields(type_name)
    if not names.issuperset(msg):
        raise KeyError(f"{type_name} has no field {sorted(msg.keys() - names)}")
    out = bytearray()
    for f in fields:
        v = msg.get(f.name)
        if v is None:
            continue
        if f.message:
            for item in (v if f.repeated else (v,)):
                body = item if type(item) is bytes else encode(f.kind, item)
                out += f.key
                out += varint(len(body))
                out += body
        elif f.repeated:
            if len(v) == 0:
                continue
            if f.pack is not None:  # packed fixed-width: one struct call
                body = struct.pack(f"<{len(v)}{f.pack.format[-1]}", *v)
            elif f.wire == _WIRE_VARINT:
                body = b"".join(varint(int(x)) for x in v)
            else:  # strings and bytes are never packed
                for x in v:
                    out += f.key + _scalar(f.kind, x)
                continue
            out += f.packed_key
            out += varint(len(body))
            out += body
        elif v:  # proto3: a default value is not written
            out += f.key
            out += _scalar(f.kind, v)
    return bytes(out)


def time_msg(ns: int) -> dict[str, int]:
    """int ns -> google.protobuf.Timestamp / Duration fields (nanos in [0, 1e9), as protobuf has them)."""
    s, n = divmod(int(ns), 1_000_000_000)
    return {"seconds": s, "nanos": n}


# ---------------------------------------------------------------- schemas (FileDescriptorSet)


def _file_of(type_name: str) -> str:
    """The .proto file a type lives in, named as the published schemas name theirs."""
    if type_name.startswith("google.protobuf."):
        return f"google/protobuf/{type_name.rsplit('.', 1)[1].lower()}.proto"
    return f"foxglove/{type_name.split('.')[1]}.proto"


def _enum_descriptor(full_name: str) -> bytes:
    values = b"".join(len_field(2, len_field(1, v.encode()) + _key(2, _WIRE_VARINT) + varint(n))
                      for v, n in ENUMS[full_name])
    return len_field(1, full_name.rsplit(".", 1)[1].encode()) + values


def len_field(number: int, payload: bytes) -> bytes:
    """A length-delimited field (message, string, bytes, packed) with its key."""
    return _key(number, _WIRE_LEN) + varint(len(payload)) + payload


def _message_descriptor(type_name: str) -> tuple[bytes, set[str]]:
    """DescriptorProto of one message (with its nested enums) and the files it depends on."""
    out = len_field(1, type_name.rsplit(".", 1)[1].encode())
    deps: set[str] = set()
    oneofs = b""
    n_oneofs = 0
    for name, number, kind, label in MESSAGES[type_name]:
        f = len_field(1, name.encode()) + _key(3, _WIRE_VARINT) + varint(number)
        f += _key(4, _WIRE_VARINT) + varint(_LABEL_REPEATED if label == "*" else _LABEL_OPTIONAL)
        if kind in _SCALARS:
            f += _key(5, _WIRE_VARINT) + varint(_SCALARS[kind])
        else:
            f += _key(5, _WIRE_VARINT) + varint(_TYPE_MESSAGE if kind in MESSAGES else _TYPE_ENUM)
            f += len_field(6, f".{kind}".encode())
            owner = kind if kind in MESSAGES else kind.rsplit(".", 1)[0]
            if _file_of(owner) != _file_of(type_name):
                deps.add(owner)
        if type_name.startswith("google.protobuf."):  # the well-known types' descriptors carry json names
            f += len_field(10, name.encode())
        if label == "?":  # proto3 `optional`: a synthetic one-field oneof
            f += _key(9, _WIRE_VARINT) + varint(n_oneofs) + _key(17, _WIRE_VARINT) + varint(1)
            oneofs += len_field(8, len_field(1, f"_{name}".encode()))
            n_oneofs += 1
        out += len_field(2, f)
    for enum in ENUMS:
        if enum.rsplit(".", 1)[0] == type_name:
            out += len_field(4, _enum_descriptor(enum))
    return out + oneofs, deps


@lru_cache(maxsize=None)
def file_descriptor_set(type_name: str) -> bytes:
    """The MCAP schema data of a channel of type_name: a FileDescriptorSet of its file and every
    file it needs, dependencies first (one message per file, as the published schemas)."""
    order: list[str] = []

    def visit(name: str) -> None:
        if name in order:
            return
        _, deps = _message_descriptor(name)
        for d in sorted(deps):
            visit(d)
        order.append(name)

    visit(type_name)
    files = b""
    for name in order:
        body, deps = _message_descriptor(name)
        package = name.rsplit(".", 1)[0]
        fd = len_field(1, _file_of(name).encode()) + len_field(2, package.encode())
        for d in sorted(deps):
            fd += len_field(3, _file_of(d).encode())
        fd += len_field(4, body) + len_field(12, b"proto3")
        files += len_field(1, fd)
    return files
