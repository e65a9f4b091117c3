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
    """A fixed-lag iSAM2 over keyframe increments."""

    def __init__(self, lag_s: float) -> None:
        self.lag_s = lag_s
        self.smoother = gtsam.IncrementalFixedLagSmoother(lag_s, isam2_params())

    def update(self, inc: Increment) -> list[int]:
        """Add one increment, remove its `remove` factors and re-solve.

        Returns the smoother's indices of the new factors (in `inc.graph` order). Raises
        RuntimeError from GTSAM on failure.
        """
        self.smoother.update(inc.graph, inc.values, inc.stamps, inc.remove)
        return list(self.smoother.getISAM2Result().getNewFactorsIndices())

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
