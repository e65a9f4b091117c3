# SPDX-License-Identifier: BSD-3-Clause
"""Simulated LiDAR localisation: the pose a scan-matching localiser (AMCL, slam_toolbox)
publishes as `geometry_msgs/msg/PoseWithCovarianceStamped`.

Base frame in the map frame at `pose_rate` Hz (stamps k / pose_rate, k >= 1): the true
pose plus noise (`pose_sigma_xy` m per axis, `pose_sigma_yaw` rad in total) of which the
share `pose_corr` of the variance is slow, an AR(1) process with correlation time
`pose_tau_s` (a scan match errs alike at neighbouring places: map errors, the same few
features in view), the rest white. No pose inside
the `pose_dropouts` boxes (long featureless aisles where scan matching degenerates).
Wrong matches start as a Poisson process (`pose_wrong_rate` per second) and last a uniform
`pose_wrong_duration` s; during one the published pose is offset by a constant jump of
uniform length `pose_wrong_jump` m in a uniform direction (the matcher locked onto a
similar-looking shelf), with the same confident covariance as always. The covariance is
the localiser's 2-D one (x, y, yaw), with z, roll and pitch at the reader's floors.

Noise and dropouts draw from `rng`, the wrong matches from `wrong_rng`, so a log without
wrong matches (`pose_wrong_rate = 0`) has exactly the same poses otherwise.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.signal import lfilter

from uwbfuse.sim.scenarios import Scenario
from uwbfuse.sim.trajectory import Timeline, evaluate

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class LidarPoses:
    """t_s (N,) s after t0; position (N,3) m, quat_xyzw (N,4), covariance (N,6,6) ROS
    order; wrong (N,) the poses of a wrong match."""

    t_s: F64
    position: F64
    quat_xyzw: F64
    covariance: F64
    wrong: NDArray[np.bool_]


def _noise(rng: np.random.Generator, n: int, sc: Scenario) -> F64:
    """(n, 3) unit-variance noise: AR(1) share `pose_corr` (stationary from the start),
    white the rest."""
    a = float(np.exp(-1.0 / (sc.pose_rate * sc.pose_tau_s)))
    w = rng.normal(0.0, 1.0, (n, 3))
    y0 = rng.normal(0.0, 1.0, (1, 3))
    slow, _ = lfilter([np.sqrt(1.0 - a * a)], [1.0, -a], rng.normal(0.0, 1.0, (n, 3)),
                      axis=0, zi=a * y0)
    return np.sqrt(sc.pose_corr) * slow + np.sqrt(1.0 - sc.pose_corr) * w


def lidar_poses(sc: Scenario, tl: Timeline, duration_s: float, rng: np.random.Generator,
                wrong_rng: np.random.Generator) -> LidarPoses:
    """The localiser's poses over [0, duration_s] (module docstring)."""
    n = int(np.floor(duration_s * sc.pose_rate + 1e-9))
    t = np.arange(1, n + 1) / sc.pose_rate
    kin = evaluate(tl, t)
    noise = _noise(rng, n, sc)
    xy = kin.position + sc.pose_sigma_xy * noise[:, :2]
    yaw = kin.yaw + sc.pose_sigma_yaw * noise[:, 2]
    keep = np.ones(n, dtype=bool)
    for box in sc.pose_dropouts:
        keep &= ~box.contains(kin.position)
    wrong = np.zeros(n, dtype=bool)
    if sc.pose_wrong_rate > 0:
        t_w = 0.0
        while True:
            t_w += wrong_rng.exponential(1.0 / sc.pose_wrong_rate)
            if t_w >= duration_s:
                break
            dur = wrong_rng.uniform(*sc.pose_wrong_duration)
            jump = wrong_rng.uniform(*sc.pose_wrong_jump)
            ang = wrong_rng.uniform(-np.pi, np.pi)
            sel = (t >= t_w) & (t < t_w + dur)
            xy[sel] += jump * np.array([np.cos(ang), np.sin(ang)])
            wrong |= sel
            t_w += dur
    pos = np.column_stack([xy, np.full(n, sc.base_height)])
    quat = np.zeros((n, 4))
    quat[:, 2] = np.sin(0.5 * yaw)
    quat[:, 3] = np.cos(0.5 * yaw)
    cov = np.zeros((n, 6, 6))
    cov[:, 0, 0] = cov[:, 1, 1] = sc.pose_sigma_xy**2
    cov[:, 5, 5] = sc.pose_sigma_yaw**2
    # z, roll and pitch: a 2-D localiser does not estimate them; stated as loose as the
    # reader's default floors (0.02 m, 0.01 rad), so in-memory logs equal read-back ones
    cov[:, 2, 2] = 0.02**2
    cov[:, 3, 3] = cov[:, 4, 4] = 0.01**2
    return LidarPoses(t[keep], pos[keep], quat[keep], cov[keep], wrong[keep])
