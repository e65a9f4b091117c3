# SPDX-License-Identifier: BSD-3-Clause
"""Typed insertion into `gtsam.Values` for the per-keyframe paths.

`Values.insert` has 46 pybind11 overloads, tried in order until one's arguments convert:
an IMU bias (the 44th) or a double (the 46th, the NLOS states) took ~25 us an insert, a
Pose3 (the 10th) ~5 us. Named by its parameter, an overload is found by the keyword's name
(the others are skipped before any conversion is tried): ~7 us and ~2 us. The same
values are inserted.
"""

from __future__ import annotations

import gtsam


def insert_pose3(values: gtsam.Values, key: int, pose: gtsam.Pose3) -> None:
    """values[key] = pose (a Pose3)."""
    values.insert(key, pose3=pose)


def insert_bias(values: gtsam.Values, key: int, bias: gtsam.imuBias.ConstantBias) -> None:
    """values[key] = bias (an IMU bias)."""
    values.insert(key, constant_bias=bias)


def insert_double(values: gtsam.Values, key: int, x: float) -> None:
    """values[key] = x (a double, e.g. a range bias in metres)."""
    values.insert(key, c=float(x))
