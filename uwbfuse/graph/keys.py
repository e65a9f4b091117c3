# SPDX-License-Identifier: BSD-3-Clause
"""Variable keys of the UWB fusion graph (`gtsam.symbol_shorthand`).

- X(k): Pose3 of the base frame in the map frame at keyframe k.
- V(k): velocity (3,) of the base frame in the map frame at keyframe k, m/s (IMU logs).
- B(k): IMU bias (accelerometer m/s^2, gyroscope rad/s) at keyframe k (IMU logs).
- L(a): Point3 of anchor a in the map frame, metres (held by a tight prior).
- D(a): constant range bias of anchor a, metres (measured range minus true range).
- C: range bias common to all anchors (the tag's antenna delay), metres; D(a) = C + d_a.
- E(a, s) = `nlos_key(a, s)`: range bias of anchor a while in NLOS during NLOS segment s
  (its LOS offset plus the slowly varying NLOS excess), metres.
"""

from __future__ import annotations

import gtsam
from gtsam.symbol_shorthand import B, D, L, V, X

__all__ = ["B", "C", "D", "L", "V", "X", "nlos_key"]

C = gtsam.symbol("c", 0)

_MAX_ANCHORS = 4096


_E = gtsam.symbol("e", 0)  # GTSAM's Symbol key: the character in the top 8 bits, the index


def nlos_key(anchor: int, segment: int) -> int:
    """Key of the NLOS bias state of `anchor` in time segment `segment` (both >= 0):
    `gtsam.symbol("e", segment * 4096 + anchor)`, formed without the call (it is made
    for every NLOS factor and review)."""
    return _E | (segment * _MAX_ANCHORS + anchor)
