# SPDX-License-Identifier: BSD-3-Clause
"""Wheel odometry: a planar dead-reckoning track and the between-keyframe factor.

Each wheel sample (v m/s, omega rad/s, base frame) is the mean velocity over the interval
that ends at its stamp; the track integrates those exactly as constant-velocity arcs, so
the relative motion between any two times (keyframes, range stamps) is one SE(2) composition.
The factor between two keyframes is a native `BetweenFactorPose3` whose 6x6 covariance is
propagated from the per-sample noise (sigma_v, sigma_omega, sigma_lateral times each piece's
duration) through the arc composition; z, roll and pitch get `planar` sigmas.
The wheel twist is already in the base frame, so the base extrinsics are the identity.
"""

from __future__ import annotations

import gtsam
import numpy as np

from uwbfuse.graph.noise import gaussian_covariance
from uwbfuse.positioning.wheel_track import (  # noqa: F401 - re-exported for the graph
    WheelTrack,
    _arcs,
    se2_between,
    se2_compose,
)


def se2_to_pose3(d: np.ndarray) -> gtsam.Pose3:
    """Planar (x, y, theta) as a Pose3 (z = 0, roll = pitch = 0)."""
    return gtsam.Pose3(gtsam.Rot3.Yaw(float(d[2])), np.array([d[0], d[1], 0.0]))


def planar_covariance6(
    cov_xyt: np.ndarray, out_of_plane_sigmas: tuple[float, float, float]
) -> np.ndarray:
    """Pose3 tangent covariance (rot, trans) of a planar delta with covariance `cov_xyt` in
    (x, y, theta) and out-of-plane (roll rad, pitch rad, z m) sigmas."""
    cov6 = np.zeros((6, 6))
    sr, sp, sz = out_of_plane_sigmas
    cov6[0, 0], cov6[1, 1], cov6[5, 5] = sr**2, sp**2, sz**2
    ix = [3, 4, 2]
    cov6[np.ix_(ix, ix)] = cov_xyt
    # floor: a perfectly still vehicle still gets a tiny (1 mm, 1 mrad) uncertainty
    cov6 += np.diag([0, 0, 1e-6, 1e-6, 1e-6, 0])
    return cov6


def between_factor(
    key_a: int,
    key_b: int,
    delta: np.ndarray,
    cov_xyt: np.ndarray,
    out_of_plane_sigmas: tuple[float, float, float],
    robust_k: float | None = None,
) -> gtsam.BetweenFactorPose3:
    """BetweenFactorPose3 for a planar delta with covariance in (x, y, theta).

    `out_of_plane_sigmas` are (roll rad, pitch rad, z m) sigmas of the same interval;
    `robust_k` (whitened units) wraps the Gaussian in a Huber kernel against wheel slip.
    Tangent order of Pose3 in GTSAM: (rx, ry, rz, tx, ty, tz).
    """
    noise = gaussian_covariance(planar_covariance6(cov_xyt, out_of_plane_sigmas))
    if robust_k is not None:
        # wheel slip: a disagreeing interval (IMU, ranges) loses weight instead of
        # dragging the trajectory
        noise = gtsam.noiseModel.Robust.Create(
            gtsam.noiseModel.mEstimator.Huber.Create(robust_k), noise)
    return gtsam.BetweenFactorPose3(key_a, key_b, se2_to_pose3(delta), noise)
