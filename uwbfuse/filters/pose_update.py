# SPDX-License-Identifier: BSD-3-Clause
"""Gated Kalman update with an external pose (role `pose`: a LiDAR / scan-matching localiser).

The measurement is the base position and heading in the map frame: x, y (and z for a 3-D
filter) in m and yaw in rad, with the matching block of the pose's covariance (ROS order,
floored by the reader). Roll and pitch are left to gravity. The filters call it at the
pose's own stamp (their windows end there). A pose whose squared Mahalanobis innovation
exceeds the chi-square gate (`[pose] gate_probability`, as many degrees of freedom as
rows) is rejected and counted: a localiser's wrong match (a jump of metres) must not
drag the state. The measurement is linear in the error state, so the UKF's unscented
update of it equals this one and both filters share it.

No GTSAM here (the filters run without it).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from uwbfuse.filters.models import F64, gate_threshold, joseph_update

# ROS covariance indices (x, y, z, rot x, rot y, rot z) of the measured components
PLANAR_ROWS = (0, 1, 5)  # x, y, yaw
SPATIAL_ROWS = (0, 1, 2, 5)  # x, y, z, yaw


def yaw_of(quat_xyzw: F64) -> float:
    """Heading (rad) of the base x axis in the map frame from a quaternion (x, y, z, w)."""
    x, y, z, w = (float(v) for v in quat_xyzw)
    return math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


def wrap(a: float) -> float:
    """Angle wrapped to (-pi, pi]."""
    return math.atan2(math.sin(a), math.cos(a))


@dataclass
class PoseUpdate:
    """Result of one gated pose update: accepted, the correction dx (n,), the posterior
    covariance, the innovation y and its normalised square (NIS)."""

    accepted: bool
    dx: F64
    P: F64
    y: F64
    nis: float


def pose_measurement(
    z_pos: F64, z_quat: F64, cov_ros: F64, rows: tuple[int, ...]
) -> tuple[F64, F64]:
    """Measured vector (x, y[, z], yaw) and its covariance for `rows` of the ROS pose."""
    z = np.array([*(float(z_pos[i]) for i in rows if i < 3), yaw_of(z_quat)])
    return z, cov_ros[np.ix_(rows, rows)]


def gated_update(p: F64, h: F64, y: F64, r: F64, probability: float) -> PoseUpdate:
    """Kalman update of covariance `p` with Jacobian `h` (m,n), innovation `y` (m,) and
    measurement covariance `r` (m,m), rejected when y^T S^-1 y exceeds the chi-square gate
    of `probability` with m degrees of freedom (then dx = 0 and P unchanged)."""
    s = h @ p @ h.T + r
    nis = float(y @ np.linalg.solve(s, y))
    if not nis <= gate_threshold(probability, len(y)):
        return PoseUpdate(False, np.zeros(p.shape[0]), p, y, nis)
    # decorrelate the rows (joseph_update takes independent variances): L^-1 with R = L L^T
    lr = np.linalg.cholesky(r)
    hw = np.linalg.solve(lr, h)
    yw = np.linalg.solve(lr, y)
    dx, p_new, _, _ = joseph_update(p, hw, np.ones(len(y)), yw)
    return PoseUpdate(True, dx, p_new, y, nis)
