# SPDX-License-Identifier: BSD-3-Clause
"""Fixed-lag iSAM2: bounded-memory incremental smoothing.

`gtsam.IncrementalFixedLagSmoother` keeps the keyframes of the last `lag` seconds and
marginalises older ones into a prior on the window (anchors and range biases are re-stamped
at every update so they never leave it). Memory and per-update time therefore stay flat over
long runs. A GTSAM failure (e.g. an indeterminant system after an outage) is reported to
the caller, who re-anchors a fresh smoother; nothing here raises GTSAM exceptions upward.
"""

from __future__ import annotations

import logging

import gtsam
import numpy as np

from uwbfuse.graph.builder import Increment
from uwbfuse.graph.keys import B, D, V, X

log = logging.getLogger(__name__)


def isam2_params() -> gtsam.ISAM2Params:
    """iSAM2 settings: relinearise beyond 0.05 (tangent units) at every update."""
    p = gtsam.ISAM2Params()
    p.setRelinearizeThreshold(0.05)
    p.relinearizeSkip = 1
    p.cacheLinearizedFactors = True
    p.findUnusedFactorSlots = True
    return p


class OnlineSmoother:
    """A fixed-lag iSAM2 over keyframe increments, with extra iterations on demand."""

    def __init__(self, lag_s: float, extra_iterations: int = 0) -> None:
        self.lag_s = lag_s
        self.extra_iterations = extra_iterations
        self.smoother = gtsam.IncrementalFixedLagSmoother(lag_s, isam2_params())

    def update(self, inc: Increment) -> list[int]:
        """Add one increment, remove its `remove` factors and re-solve.

        Returns the smoother's indices of the new factors (in `inc.graph` order). Raises
        RuntimeError from GTSAM on failure.
        """
        self.smoother.update(inc.graph, inc.values, inc.stamps, inc.remove)
        idx = list(self.smoother.getISAM2Result().getNewFactorsIndices())
        for _ in range(self.extra_iterations):
            self.smoother.update()
        return idx

    def pose(self, k: int) -> gtsam.Pose3:
        return self.smoother.calculateEstimatePose3(X(k))

    def pose_covariance(self, k: int) -> np.ndarray:
        """Marginal covariance (6,6) of X(k) in its Pose3 tangent (rot, trans; body frame)."""
        return np.asarray(self.smoother.marginalCovariance(X(k)))

    def velocity_covariance(self, k: int) -> np.ndarray:
        """Marginal covariance (3,3) of V(k), (m/s)^2, map frame."""
        return np.asarray(self.smoother.marginalCovariance(V(k)))

    def velocity(self, k: int) -> np.ndarray:
        return np.asarray(self.smoother.calculateEstimateVector(V(k)))

    def bias(self, k: int) -> gtsam.imuBias.ConstantBias:
        return self.smoother.calculateEstimateConstantBias(B(k))

    def range_bias(self, a: int) -> float:
        return float(self.smoother.calculateEstimateDouble(D(a)))

    def double(self, key: int) -> float:
        return float(self.smoother.calculateEstimateDouble(key))
