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


def flat_layout(type_name: str, sections: dict[str, list[str]], depth: int = 0) -> Layout | None:
    """The flattened primitive layout of `type_name`, or None if a type is not defined."""
    key = normalize_type(type_name)
    fields = sections.get(key)
    if fields is None or depth > 32:
        return None
    package = key.split("/")[0]
    out: list[object] = []
    for ftype in fields:
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
        if base in PRIMITIVES:
            elem: object = base
        else:
            sub = flat_layout(normalize_type(base, package), sections, depth + 1)
            if sub is None:
                return None
            elem = sub
        if size is None:
            if isinstance(elem, tuple):
                out.extend(elem)
            else:
                out.append(elem)
        else:
            out.append(("array", elem, size))
    return tuple(out)


def layout_of(schema_name: str, text: str) -> Layout | None:
    """Flattened layout of a schema record's top-level type (None if not parseable)."""
    return flat_layout(schema_name, parse_sections(schema_name, text))
