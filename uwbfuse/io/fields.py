# SPDX-License-Identifier: BSD-3-Clause
"""Field access on decoded messages: dotted paths, header stamps, anchor ids.

Decoded messages are either `mcap_ros2` objects (attributes) or JSON objects (dicts); both
are read through `get_path`. Times are integer nanoseconds.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

NS_PER_S = 1_000_000_000
# what `time_to_ns` gives for a stamp that is no time at all (text, NaN, out of int64
# range): negative, so that the reader drops the message as one with a bad stamp
INVALID_STAMP = -1
_MAX_NS = (1 << 63) - 1
# positions and anchors, metres: beyond any Earth-fixed map (UTM northings are < 1e7 m);
# a larger coordinate is corrupt, and its square is on the way to overflow
MAX_COORD_M = 1e8
# longest anchor id kept, characters: ids are names or numbers ("A0", "7475", a MAC address);
# a longer one is corrupt and would make every id comparison and table that long
MAX_ANCHOR_ID_CHARS = 256


class MissingField(KeyError):
    """A dotted path does not exist in a message."""


_MISSING = object()


def get_path(msg: Any, path: str) -> Any:
    """The value at dotted `path` ("header.frame_id", "twist.twist.linear.x") in `msg`.

    Raises MissingField when any part is absent.
    """
    obj = msg
    for part in path.split("."):
        if isinstance(obj, dict):
            obj = obj.get(part, _MISSING)
        else:
            obj = getattr(obj, part, _MISSING)
        if obj is _MISSING:
            raise MissingField(path)
    return obj


def has_path(msg: Any, path: str) -> bool:
    """Whether dotted `path` exists in `msg`."""
    try:
        get_path(msg, path)
    except MissingField:
        return False
    return True


def stamp_ns(msg: Any) -> int:
    """`header.stamp` of `msg` in integer ns; 0 when there is no header or stamp.

    Accepts ROS 2 `{sec, nanosec}`, ROS 1 / Foxglove JSON `{sec, nsec}` (also `secs`,
    `nsecs`) and a bare number of seconds.
    """
    try:
        stamp = get_path(msg, "header.stamp")
    except MissingField:
        return 0
    return time_to_ns(stamp)


def _in_range(ns: int) -> int:
    return ns if -_MAX_NS <= ns <= _MAX_NS else INVALID_STAMP


def _whole(v: Any) -> bool:
    """An integer, or a float with an integer value (JSON writers differ)."""
    if isinstance(v, bool):
        return False
    if isinstance(v, (int, np.integer)):
        return True
    return isinstance(v, float) and math.isfinite(v) and v.is_integer()


def time_to_ns(stamp: Any) -> int:
    """A time value ({sec, nanosec} object/dict or seconds as a number) in integer ns.

    0 (no stamp: the log time is used) for a missing/null stamp; INVALID_STAMP for one that
    is present but no time: text, NaN, a non-integer sec, beyond the int64 nanoseconds.
    """
    if stamp is None:
        return 0
    if isinstance(stamp, bool):
        return INVALID_STAMP
    if isinstance(stamp, int):
        return _in_range(stamp * NS_PER_S)
    if isinstance(stamp, float):
        if not (math.isfinite(stamp) and abs(stamp) <= _MAX_NS / NS_PER_S):
            return INVALID_STAMP
        return _in_range(round(stamp * NS_PER_S))
    for sec_key, ns_key in (("sec", "nanosec"), ("sec", "nsec"), ("secs", "nsecs")):
        if has_path(stamp, sec_key) and has_path(stamp, ns_key):
            sec, ns = get_path(stamp, sec_key), get_path(stamp, ns_key)
            if not (_whole(sec) and _whole(ns)):
                return INVALID_STAMP
            return _in_range(int(sec) * NS_PER_S + int(ns))
    return INVALID_STAMP


def anchor_key(value: Any) -> str:
    """An anchor id as the string `[anchors]` keys use: 7475 -> "7475", b"A0" -> "A0"."""
    if isinstance(value, str):
        return value
    if isinstance(value, bytes):
        return value.decode("utf-8", errors="replace")
    if isinstance(value, float) and value.is_integer():
        return str(int(value))
    if isinstance(value, np.generic):
        return anchor_key(value.item())
    return str(value)


def is_valid(value: Any) -> bool:
    """A validity flag's truth: False/0/"false"/"0" are invalid, anything else valid."""
    if isinstance(value, str):
        return value.strip().lower() not in ("", "0", "false", "no")
    return bool(value)
