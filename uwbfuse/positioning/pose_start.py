# SPDX-License-Identifier: BSD-3-Clause
"""The start from external poses (role `pose`: a LiDAR / scan-matching localiser).

`PoseStartInitialiser` is the `SparseStartInitialiser` of the graph and the filters plus
external poses: once START_POSES consecutive poses within START_SPAN_S agree with each
other (no step faster than POSE_START_MAX_SPEED: a localiser's wrong match jumps by metres
between two messages), the newest of them is the start (base in the map frame, its
attitude, velocity from the wheels or the poses, biases zero); before that, and on logs
without poses, the inner initialiser decides as before. `pose_arrays` hands the buffered
poses to the estimator once it starts.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial.transform import Rotation

from uwbfuse.constants import POSE_START_MAX_SPEED, START_POSES, START_SPAN_S
from uwbfuse.positioning.initialisation import InitialState
from uwbfuse.positioning.sparse_start import SparseStartInitialiser
from uwbfuse.streams import NS_PER_S


class PoseBuffer:
    """External poses buffered in arrival order: stamps ns, position (N,3) m, quaternion
    (N,4) xyzw, covariance (N,6,6) ROS order; base frame in the map frame."""

    def __init__(self) -> None:
        self.chunks: list[tuple[np.ndarray, ...]] = []

    def add(self, t_ns: np.ndarray, position: np.ndarray, quat_xyzw: np.ndarray,
            covariance: np.ndarray) -> None:
        if len(t_ns):
            self.chunks.append((np.asarray(t_ns, np.int64), np.asarray(position, np.float64),
                                np.asarray(quat_xyzw, np.float64),
                                np.asarray(covariance, np.float64)))

    def keep_after(self, t_ns: int) -> None:
        """Drop the poses stamped at or before t_ns."""
        t, p, q, c = self.arrays()
        later = t > t_ns
        self.chunks = [(t[later], p[later], q[later], c[later])] if np.any(later) else []

    def arrays(self) -> tuple[np.ndarray, ...]:
        """All buffered poses, concatenated (in arrival order)."""
        if not self.chunks:
            return (np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 4)),
                    np.zeros((0, 6, 6)))
        if len(self.chunks) > 1:
            self.chunks = [tuple(np.concatenate(c) for c in zip(*self.chunks, strict=True))]
        return self.chunks[0]


class PoseStartInitialiser(SparseStartInitialiser):
    """`SparseStartInitialiser` with the start from external poses (module docstring)."""

    def __init__(self, *args: object, **kwargs: object) -> None:
        super().__init__(*args, **kwargs)  # type: ignore[arg-type]
        self.poses = PoseBuffer()
        self._wheel_last: tuple[int, float] | None = None
        self.pose_start_used = False

    def add_poses(self, t_ns: np.ndarray, position: np.ndarray, quat_xyzw: np.ndarray,
                  covariance: np.ndarray) -> None:
        """External poses (base in map) before the start."""
        self.poses.add(t_ns, position, quat_xyzw, covariance)

    def add_wheel(self, t_ns: np.ndarray, v: np.ndarray, omega: np.ndarray) -> None:
        super().add_wheel(t_ns, v, omega)
        if len(t_ns):
            self._wheel_last = (int(t_ns[-1]), float(v[-1]))

    def pose_arrays(self) -> tuple[np.ndarray, ...]:
        """The poses buffered before the start (stamps ns, position, quat xyzw, cov)."""
        return self.poses.arrays()

    def try_initialise(self, t_ns: int) -> InitialState | None:  # type: ignore[override]
        state = self._pose_start(int(t_ns))
        if state is not None:
            return state
        return super().try_initialise(t_ns)

    def _pose_start(self, t_ns: int) -> InitialState | None:
        t, p, q, c = self.poses.arrays()
        sel = np.flatnonzero(t <= t_ns)
        if len(sel) < START_POSES:
            return None
        last = sel[-START_POSES:]
        tt = t[last]
        if (tt[-1] - tt[0]) > START_SPAN_S * NS_PER_S or t_ns - tt[-1] > START_SPAN_S * NS_PER_S:
            return None
        dt = np.maximum(np.diff(tt) / NS_PER_S, 1e-3)
        steps = np.linalg.norm(np.diff(p[last, :2], axis=0), axis=1)
        if np.any(steps / dt > POSE_START_MAX_SPEED):
            return None
        i = int(last[-1])
        rot = Rotation.from_quat(q[i]).as_matrix()
        speed = 0.0
        if self._wheel_last is not None:
            speed = self._wheel_last[1]
            vel = rot @ np.array([speed, 0.0, 0.0])
        else:
            span = max((tt[-1] - tt[0]) / NS_PER_S, 1e-3)
            vel = (p[last[-1]] - p[last[0]]) / span
        cov = c[i]
        self.pose_start_used = True
        return InitialState(
            t_ns=int(t[i]), position=p[i].copy(), R_map_base=rot, velocity=vel,
            gyro_bias=np.zeros(3), accel_bias=np.zeros(3),
            position_sigma=float(math.sqrt(max(cov[0, 0], cov[1, 1]))),
            yaw_sigma=float(math.sqrt(cov[5, 5])),
            still=bool(np.linalg.norm(vel) < 0.01),
        )
