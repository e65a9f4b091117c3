# SPDX-License-Identifier: BSD-3-Clause
"""The speed reference for `batch`: a plain Huber Levenberg-Marquardt over the same graph.

What a user would write instead of our offline solve, on our own problem: the recorded
non-range factors of the batch graph (IMU `CombinedImuFactor`s or the motion prior, wheel
`BetweenFactorPose3`s, the start and anchor priors), one native
`RangeFactorWithTransform3D` per range with the configured LOS sigma under a Huber kernel
(`[uwb] sigma`, `kernel_threshold`; no NLOS model, no range bias), and one
`LevenbergMarquardtOptimizer` from the same initial values, with batch's LM settings.
`scripts/bench.py` times it beside `batch` in the same run.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import gtsam
import numpy as np

from uwbfuse.config import Config, RobustKernel
from uwbfuse.constants import LM_RELATIVE_TOL
from uwbfuse.graph.keys import L, X
from uwbfuse.graph.noise import range_noise


@dataclass(frozen=True)
class PlainLm:
    """Wall time (s) of building the range factors and of the LM, its iterations, final
    error, and the solution."""

    build_s: float
    lm_s: float
    iterations: int
    error: float
    values: gtsam.Values


def plain_huber_lm(cfg: Config, base_graph: gtsam.NonlinearFactorGraph,
                   initial: gtsam.Values, rec: dict[str, np.ndarray]) -> PlainLm:
    """One Huber LM over `base_graph` plus a range factor per record of `rec` (keyframe
    `k`, `anchor`, range `z` m, tag offset `tag_in_kf` in the base frame of the
    keyframe), from `initial` (see the module docstring)."""
    tic = time.perf_counter()
    graph = gtsam.NonlinearFactorGraph(base_graph)
    noise = range_noise(cfg.uwb.sigma, RobustKernel.HUBER, cfg.uwb.kernel_threshold)
    tags = np.asarray(rec["tag_in_kf"], np.float64)
    unique, inv = np.unique(tags, axis=0, return_inverse=True)
    t_tag = [gtsam.Pose3(gtsam.Rot3(), t) for t in unique]
    for k, a, z, i in zip(rec["k"].tolist(), rec["anchor"].tolist(), rec["z"].tolist(),
                          inv.ravel().tolist(), strict=True):
        graph.add(gtsam.RangeFactorWithTransform3D(X(k), L(a), z, noise, t_tag[i]))
    build = time.perf_counter() - tic
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(cfg.graph.lm_max_iterations)
    params.setRelativeErrorTol(LM_RELATIVE_TOL)
    params.setAbsoluteErrorTol(1e-6)
    tic = time.perf_counter()
    opt = gtsam.LevenbergMarquardtOptimizer(graph, initial, params)
    values = opt.optimize()
    lm = time.perf_counter() - tic
    return PlainLm(build, lm, int(opt.iterations()), float(opt.error()), values)
