# SPDX-License-Identifier: BSD-3-Clause
"""Robust pose factors from external poses (role `pose`: a LiDAR / scan-matching localiser).

An external pose Z (base frame in the map frame, at its own stamp t in [t_a, t_b)) is
attached to keyframe X(ka) at t_a as ranges are (`builder` module docstring): with D the
base-frame motion from t_a to t (wheel track, else IMU prediction), Z = X(ka) D, so the
factor is a `PriorFactorPose3` on X(ka) with the measurement M = Z D^-1.

Its noise, in the tangent space of M (GTSAM order: rotation, translation; body axes):
- the pose covariance (ROS order x, y, z, rot x, rot y, rot z; map axes; floored by the
  reader) moved to M: map-axis perturbations (dtheta, dp) of Z move M by (dtheta,
  dp + [Z.t - M.t]x dtheta), then rotated into M's body axes by R_M^T;
- plus the motion's own uncertainty (`GraphBuilder.motion_noise`) through Ad(D);
- planar graphs (wheeled vehicles on a floor) keep only x, y and yaw: a 2-D localiser's z,
  roll and pitch say nothing about the base (the planar prior holds them), so those
  directions get no information.
The whole is wrapped in the robust kernel of `[pose] robust_kernel` / `kernel_threshold`
(on the whitened residual's norm): a localiser's wrong matches (jumps of metres, often with
a confident covariance) are down-weighted instead of pulling the track.
"""

from __future__ import annotations

import gtsam
import numpy as np

from uwbfuse.config import PoseConfig, RobustKernel
from uwbfuse.constants import NO_INFORMATION
from uwbfuse.graph.noise import robust_estimator

# GTSAM tangent (rx, ry, rz, x, y, z) indices of a planar factor's x, y, yaw
_PLANAR = np.array([2, 3, 4])
_ROS_TO_GTSAM = np.array([3, 4, 5, 0, 1, 2])  # (x, y, z, rx, ry, rz) -> (rx, ry, rz, x, y, z)


def _skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def tangent_covariance(z: gtsam.Pose3, m: gtsam.Pose3, cov_ros: np.ndarray) -> np.ndarray:
    """(6,6) covariance of M = Z D^-1 in M's tangent (rot, trans; body axes) from Z's ROS
    covariance (map axes)."""
    c = cov_ros[np.ix_(_ROS_TO_GTSAM, _ROS_TO_GTSAM)]
    j = np.eye(6)
    j[3:, :3] = _skew(np.asarray(z.translation()) - np.asarray(m.translation()))
    rt = m.rotation().matrix().T
    body = np.zeros((6, 6))
    body[:3, :3] = rt
    body[3:, 3:] = rt
    a = body @ j
    return a @ c @ a.T


def pose_noise(cov: np.ndarray, planar: bool, cfg: PoseConfig) -> gtsam.noiseModel.Base:
    """Robust Gaussian noise model of a pose factor from its tangent covariance (6,6)."""
    c = 0.5 * (cov + cov.T)
    if planar:
        info = np.eye(6) * NO_INFORMATION
        info[np.ix_(_PLANAR, _PLANAR)] = np.linalg.inv(c[np.ix_(_PLANAR, _PLANAR)])
        base = gtsam.noiseModel.Gaussian.Information(info)
    else:
        base = gtsam.noiseModel.Gaussian.Covariance(c)
    if cfg.robust_kernel is RobustKernel.NONE:
        return base
    return gtsam.noiseModel.Robust.Create(
        robust_estimator(cfg.robust_kernel, cfg.kernel_threshold), base)


def pose_factors(
    key: int, position: np.ndarray, quat_xyzw: np.ndarray, covariance: np.ndarray,
    deltas: list[gtsam.Pose3], motion_covs: list[np.ndarray], planar: bool, cfg: PoseConfig,
) -> list[gtsam.NonlinearFactor]:
    """One robust `PriorFactorPose3` on `key` per external pose (module docstring).

    position (N,3) m, quat_xyzw (N,4), covariance (N,6,6) ROS order: the poses (base in
    map); deltas: the base motion from the keyframe to each pose's stamp; motion_covs:
    its (6,6) tangent covariance (rot, trans)."""
    out: list[gtsam.NonlinearFactor] = []
    for j, d in enumerate(deltas):
        x, y, zq, w = (float(v) for v in quat_xyzw[j])
        z = gtsam.Pose3(gtsam.Rot3.Quaternion(w, x, y, zq), np.asarray(position[j], np.float64))
        m = z.compose(d.inverse())
        cov = tangent_covariance(z, m, covariance[j])
        ad = d.AdjointMap()
        cov = cov + ad @ motion_covs[j] @ ad.T
        out.append(gtsam.PriorFactorPose3(key, m, pose_noise(cov, planar, cfg)))
    return out


class PoseQueue:
    """External poses waiting for their keyframe (stamps >= the graph's first keyframe)."""

    def __init__(self, t0_ns: int) -> None:
        self.t0 = int(t0_ns)
        self._chunks: list[tuple[np.ndarray, ...]] = []
        self.dropped = 0  # poses from before the first keyframe
        self.used = 0

    def add(self, t_ns: np.ndarray, position: np.ndarray, quat_xyzw: np.ndarray,
            covariance: np.ndarray) -> None:
        t_ns = np.asarray(t_ns, np.int64)
        keep = t_ns >= self.t0
        self.dropped += int(np.count_nonzero(~keep))
        if np.any(keep):
            self._chunks.append((t_ns[keep], np.asarray(position)[keep],
                                 np.asarray(quat_xyzw)[keep], np.asarray(covariance)[keep]))

    def take(self, t_end: int) -> tuple[np.ndarray, ...]:
        """The queued poses with stamps < t_end, sorted by stamp (removed from the queue)."""
        if not self._chunks:
            return (np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 4)),
                    np.zeros((0, 6, 6)))
        cols = tuple(np.concatenate(c) for c in zip(*self._chunks, strict=True))
        order = np.argsort(cols[0], kind="stable")
        cols = tuple(c[order] for c in cols)
        n = int(np.searchsorted(cols[0], t_end, side="left"))
        self._chunks = [tuple(c[n:] for c in cols)] if n < len(cols[0]) else []
        self.used += n
        return tuple(c[:n] for c in cols)
