# SPDX-License-Identifier: BSD-3-Clause
"""Pose covariances as CSV (`run --cov-out`): one row per output pose, one header line.

Columns: `t` (s, 9 decimals, the TUM stamp of the pose) then the 36 entries of its 6x6
covariance, row-major, in ROS order (x, y, z in m; rotation about the map x, y, z axes in
rad), named `cov_<row>_<col>` with the axis names x, y, z, rx, ry, rz. A component the
method does not estimate holds `UNKNOWN_VARIANCE` on the diagonal.
"""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np

from uwbfuse.errors import TrajectoryFileError
from uwbfuse.io.atomic import write_atomic
from uwbfuse.io.pose_mcap import pose_covariances
from uwbfuse.streams import NS_PER_S, PoseStream

AXES = ("x", "y", "z", "rx", "ry", "rz")
COLUMNS = ("t", *(f"cov_{a}_{b}" for a in AXES for b in AXES))


def write_cov_csv(path: str | Path, poses: PoseStream) -> None:
    """Write the covariance of every pose of `poses` to `path` (atomically)."""
    cov = pose_covariances(poses).reshape(len(poses), 36)
    if not np.isfinite(cov).all():
        bad = int(np.flatnonzero(~np.isfinite(cov).all(axis=1))[0])
        raise TrajectoryFileError(f"{path}: covariance of pose {bad} is not finite, "
                                  "nothing written")
    buf = io.StringIO()
    buf.write(",".join(COLUMNS) + "\n")
    for t, row in zip(poses.t_ns.tolist(), cov.tolist(), strict=True):
        sec, ns = divmod(abs(int(t)), NS_PER_S)
        buf.write(f"{'-' if t < 0 else ''}{sec}.{ns:09d},"
                  + ",".join(f"{v:.9g}" for v in row) + "\n")
    write_atomic(path, buf.getvalue(), error=TrajectoryFileError, what="covariance CSV")
