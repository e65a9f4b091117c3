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


def time_to_ns(stamp: Any) -> int:
    """A time value ({sec, nanosec} object/dict or seconds as a number) in integer ns."""
    if isinstance(stamp, bool) or stamp is None:
        return 0
    if isinstance(stamp, int):
        return stamp * NS_PER_S
    if isinstance(stamp, float):
        return round(stamp * NS_PER_S) if math.isfinite(stamp) else 0
    for sec_key, ns_key in (("sec", "nanosec"), ("sec", "nsec"), ("secs", "nsecs")):
        if has_path(stamp, sec_key) and has_path(stamp, ns_key):
            return int(get_path(stamp, sec_key)) * NS_PER_S + int(get_path(stamp, ns_key))
    return 0


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
