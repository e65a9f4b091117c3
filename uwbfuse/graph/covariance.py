# SPDX-License-Identifier: BSD-3-Clause
"""Pose covariances of the graph, in the ROS convention of `PoseStream.covariance`.

GTSAM's Pose3 marginals live in the tangent space of the pose's right perturbation,
T' = T Exp(xi), xi = (rot, trans), both in the base (body) frame. ROS wants the base pose
in the map frame with order (x, y, z, rot x, rot y, rot z), position and rotation both
perturbed in map axes: p' = p + dp, R' = Exp(dtheta) R. To first order dtheta = R rot and
dp = R trans, so `to_map` turns each 3x3 block with R and reorders to (trans, rot).

A pose b reached from a by a relative motion (b = a * delta) carries a's covariance with
`carry`: in map axes dp_b = dp_a - [p_b - p_a]x dtheta_a and dtheta_b = dtheta_a, plus the
motion's own noise (given in the Pose3 tangent at b, as GTSAM's BetweenFactor noise).
"""

from __future__ import annotations

import gtsam
import numpy as np

from uwbfuse.graph.keys import X

_ROS_ORDER = np.array([3, 4, 5, 0, 1, 2])  # GTSAM tangent index of each ROS component


def to_map(rot: np.ndarray, cov_tangent: np.ndarray) -> np.ndarray:
    """Pose3 tangent covariances (N,6,6) (rot, trans; body frame) at attitudes `rot`
    (N,3,3, base in map) -> ROS covariances (N,6,6) (x, y, z, rot x, y, z; map axes).
    Also takes a single (3,3) / (6,6) pair and then returns (6,6)."""
    single = np.ndim(cov_tangent) == 2
    r = np.atleast_3d(rot).reshape(-1, 3, 3)
    c = np.asarray(cov_tangent, np.float64).reshape(-1, 6, 6)
    big = np.zeros((len(c), 6, 6))
    big[:, :3, :3] = r
    big[:, 3:, 3:] = r
    out = big @ c @ big.transpose(0, 2, 1)
    out = out[:, _ROS_ORDER][:, :, _ROS_ORDER]
    out = 0.5 * (out + out.transpose(0, 2, 1))
    return out[0] if single else out


def _skew(v: np.ndarray) -> np.ndarray:
    """Cross-product matrices (N,3,3) of vectors (N,3)."""
    z = np.zeros(len(v))
    x, y, w = v[:, 0], v[:, 1], v[:, 2]
    return np.stack([np.stack([z, -w, y], -1), np.stack([w, z, -x], -1),
                     np.stack([-y, x, z], -1)], axis=1)


def carry(cov_a: np.ndarray, p_a: np.ndarray, p_b: np.ndarray,
          motion: np.ndarray | None = None) -> np.ndarray:
    """ROS covariances (N,6,6) of poses b = a * delta from a's (N,6,6 or 6,6) ROS
    covariance, a's and b's positions (N,3) m, and the motion's noise (N,6,6) already in
    ROS order and map axes (None: a noiseless motion)."""
    p_b = np.atleast_2d(p_b)
    lever = p_b - np.atleast_2d(p_a)
    f = np.tile(np.eye(6), (len(p_b), 1, 1))
    f[:, :3, 3:] = -_skew(lever)
    c = np.broadcast_to(cov_a, (len(p_b), 6, 6))
    out = f @ c @ f.transpose(0, 2, 1)
    if motion is not None:
        out = out + motion
    return 0.5 * (out + out.transpose(0, 2, 1))


def blend(cov_0: np.ndarray, cov_1: np.ndarray, f: np.ndarray) -> np.ndarray:
    """Covariances (N,6,6) of poses interpolated between keyframes at fraction f (N,).

    The linear blend of the two keyframes' covariances: the variance of a blend of two
    correlated estimates is at most the blend of their variances (Cauchy-Schwarz, and
    neighbouring keyframes 0.1 s apart are almost fully correlated, so the bound is tight).
    """
    w = np.asarray(f, np.float64)[:, None, None]
    return (1.0 - w) * cov_0 + w * cov_1


def keyframe_marginals(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values,
                       n_kf: int) -> np.ndarray:
    """ROS covariances (n_kf,6,6) of the keyframe poses X(0..n_kf-1) of `values`, from the
    marginals of `graph` linearised there (robust factors at their final weights).

    One sparse elimination (the same as an LM iteration); the per-key marginals then reuse
    the Bayes tree's cached shortcuts.
    """
    marginals = gtsam.Marginals(graph, values)
    cov = np.array([marginals.marginalCovariance(X(k)) for k in range(n_kf)])
    rot = np.array([values.atPose3(X(k)).rotation().matrix() for k in range(n_kf)])
    return to_map(rot, cov)
