# SPDX-License-Identifier: BSD-3-Clause
"""Just enough `ros2msg` schema parsing to tell whether two definitions share a byte layout.

A schema's layout is flattened to the sequence of primitive fields it serialises (nested
messages inlined, arrays as (element layout, size) with size -1 for sequences). Field
names, comments, constants and default values do not change the bytes and are ignored, so
a schema embedded by `ros2 bag`, `rosbags` or `mcap_ros2` compares equal to ours whenever
the CDR bytes are laid out the same.
"""

from __future__ import annotations

import re

PRIMITIVES = frozenset({
    "bool", "byte", "char", "float32", "float64", "int8", "uint8", "int16", "uint16",
    "int32", "uint32", "int64", "uint64", "string", "wstring",
})
_ALIASES = {
    "Header": "std_msgs/Header",
    "time": "builtin_interfaces/Time",
    "duration": "builtin_interfaces/Duration",
}
_SEP = re.compile(r"^={3,}\s*$", re.MULTILINE)
_ARRAY = re.compile(r"^(?P<base>[^\[]+)(\[(?P<size><=)?(?P<n>\d*)\])?$")

Layout = tuple[object, ...]

MAX_DEPTH = 32  # nesting levels of message types; real ROS 2 messages nest fewer than 10
MAX_FIELDS = 100_000  # primitive fields of one flattened message (a PointCloud2 has ~20)
MAX_SCHEMA_BYTES = 1 << 20  # schema text, bytes; ros2 bag's largest embedded are ~100 kB


class SchemaError(ValueError):
    """A schema that cannot describe a message: recursive, nested too deep or too large."""


def normalize_type(name: str, package: str = "") -> str:
    """ "pkg/msg/T" and "pkg/T" -> "pkg/T"; a bare "T" -> "package/T"."""
    name = _ALIASES.get(name, name)
    parts = name.split("/")
    if len(parts) == 3:
        return f"{parts[0]}/{parts[2]}"
    if len(parts) == 1 and package:
        return f"{package}/{name}"
    return name


def parse_sections(schema_name: str, text: str) -> dict[str, list[str]]:
    """Field type strings per message type (normalized names) of a ros2msg schema text."""
    sections: dict[str, list[str]] = {}
    for i, block in enumerate(_SEP.split(text)):
        lines = block.strip().splitlines()
        if i == 0:
            name = normalize_type(schema_name)
        else:
            if not lines or not lines[0].startswith("MSG:"):
                continue
            name = normalize_type(lines[0][4:].strip())
            lines = lines[1:]
        fields = []
        for line in lines:
            line = line.split("#", 1)[0].strip()
            if not line:
                continue
            tokens = line.split()
            if len(tokens) < 2 or "=" in tokens[1] or (len(tokens) > 2 and tokens[2] == "="):
                continue  # constant (NAME=value) or garbage
            fields.append(tokens[0])
        sections[name] = fields
    return sections


def _field_type(ftype: str, package: str) -> tuple[str, int | None] | None:
    """(base type, array size: None scalar, -1 sequence, n fixed) of a field, or None."""
    m = _ARRAY.match(ftype)
    if m is None:
        return None
    base = m.group("base")
    if base.startswith("string<=") or base.startswith("wstring<="):
        base = base.split("<=")[0]
    if m.group(2) is None:
        size = None
    elif m.group("size") or not m.group("n"):
        size = -1
    else:
        size = int(m.group("n"))
    return (base if base in PRIMITIVES else normalize_type(base, package)), size


def flat_layout(type_name: str, sections: dict[str, list[str]]) -> Layout | None:
    """The flattened primitive layout of `type_name`, or None if a type is not defined.

    Raises SchemaError for a type that contains itself, nests deeper than MAX_DEPTH or
    flattens to more than MAX_FIELDS fields (checked before anything is built: a type with
    two fields of the next type, 30 levels down, would flatten to 2^30 fields).
    """
    done: dict[str, Layout | None] = {}
    sizes: dict[str, int] = {}

    def visit(key: str, stack: tuple[str, ...]) -> Layout | None:
        if key in done:
            return done[key]
        if key in stack:
            raise SchemaError(f"type {key} contains itself")
        if len(stack) >= MAX_DEPTH:
            raise SchemaError(f"types nest deeper than {MAX_DEPTH} levels")
        fields = sections.get(key)
        if fields is None:
            return None
        package = key.split("/")[0]
        out: list[object] = []
        count = 0
        result: Layout | None = None
        for ftype in fields:
            parsed = _field_type(ftype, package)
            if parsed is None:
                break
            base, size = parsed
            if base in PRIMITIVES:
                elem: object = base
                n = 1
            else:
                sub = visit(base, (*stack, key))
                if sub is None:
                    break
                elem, n = sub, sizes[base]
            count += n
            if count > MAX_FIELDS:
                raise SchemaError(f"type {key} has more than {MAX_FIELDS} fields")
            if size is None and isinstance(elem, tuple):
                out.extend(elem)
            elif size is None:
                out.append(elem)
            else:
                out.append(("array", elem, size))
        else:
            result = tuple(out)
        done[key] = result
        sizes[key] = count
        return result

    return visit(normalize_type(type_name), ())


def layout_of(schema_name: str, text: str) -> Layout | None:
    """Flattened layout of a schema record's top-level type (None if not parseable).

    Raises SchemaError for a schema over the limits (recursive, too deep, too large).
    """
    if len(text) > MAX_SCHEMA_BYTES:
        raise SchemaError(f"schema text of {len(text)} bytes, more than {MAX_SCHEMA_BYTES}")
    return flat_layout(schema_name, parse_sections(schema_name, text))
