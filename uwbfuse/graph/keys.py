# SPDX-License-Identifier: BSD-3-Clause
"""Variable keys of the UWB fusion graph (`gtsam.symbol_shorthand`).

- X(k): Pose3 of the base frame in the map frame at keyframe k.
- V(k): velocity (3,) of the base frame in the map frame at keyframe k, m/s (IMU logs).
- B(k): IMU bias (accelerometer m/s^2, gyroscope rad/s) at keyframe k (IMU logs).
- L(a): Point3 of anchor a in the map frame, metres (held by a tight prior).
- D(a): constant range bias of anchor a, metres (measured range minus true range).
"""

from __future__ import annotations

from gtsam.symbol_shorthand import B, D, L, V, X

__all__ = ["B", "D", "L", "V", "X"]
