# SPDX-License-Identifier: BSD-3-Clause
"""Fixed-lag iSAM2: bounded-memory incremental smoothing.

`gtsam.IncrementalFixedLagSmoother` keeps the keyframes of the last `lag` seconds and
marginalises older ones into a prior on the window (anchors and range biases are re-stamped
at every update so they never leave it). Memory and per-update time therefore stay flat over
long runs. A GTSAM failure (e.g. an indeterminant system after an outage) is reported to
the caller, who re-anchors a fresh smoother.

One failure is recovered here without loss: GTSAM 4.3's `ISAM2::marginalizeLeaves` can
leave a key due for marginalisation in a clique it never visits (it walks up from the key
while the parent clique's first variable is also due, then handles only children whose
separator holds a due key), and then throws "Asking to remove variables from the variable
index that are not unused" at its very end, after its factor bookkeeping is complete (the
visited cliques summarised into marginal factors, the factors they summarise removed,
the stranded key's own factors kept). That factor graph is still the window's posterior,
so the smoother is rebuilt from it (`_rebuild`): a fresh fixed-lag smoother eliminates it
from scratch (the due keys as leaves) and marginalises what is due. Every factor index
changes; `update` returns the old-to-new map for the caller's stored indices.
"""

from __future__ import annotations

import logging

import gtsam
import numpy as np

from uwbfuse.graph.builder import Increment
from uwbfuse.graph.keys import B, D, V, X

log = logging.getLogger(__name__)

# the message of the marginalisation failure `_rebuild` recovers (ISAM2::removeVariables)
MARGINALISATION_FAILURE = "not unused"


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

    def update(self, inc: Increment) -> tuple[list[int], dict[int, int] | None]:
        """Add one increment, remove its `remove` factors and re-solve.

        Returns the smoother's indices of the new factors (in `inc.graph` order) and, when
        the smoother had to be rebuilt, the map from every earlier factor index still in
        use to its new one (else None). Raises RuntimeError or ValueError from GTSAM on
        any other failure.
        """
        try:
            self.smoother.update(inc.graph, inc.values, inc.stamps, inc.remove)
        except ValueError as exc:
            if MARGINALISATION_FAILURE not in str(exc):
                raise
            new = list(self.smoother.getISAM2Result().getNewFactorsIndices())
            remap = self._rebuild()
            # a new factor on a key marginalised in the failed update was summarised
            return [remap.get(i, -1) for i in new], remap
        return list(self.smoother.getISAM2Result().getNewFactorsIndices()), None

    def _rebuild(self) -> dict[int, int]:
        """Replace the smoother by a fresh one holding the failed one's factors, values
        (its linearisation point) and stamps; returns {old factor index: new index}.
        Keys no factor uses any more (marginalised before the failure) are left out."""
        old = self.smoother
        factors = old.getFactors()
        theta = old.getLinearizationPoint()
        stamps = old.timestamps()
        graph = gtsam.NonlinearFactorGraph()
        old_index: list[int] = []
        used: set[int] = set()
        for i in range(factors.size()):
            f = factors.at(i)
            if f is None:
                continue
            graph.push_back(f)
            old_index.append(i)
            used.update(f.keys())
        values = gtsam.Values(theta)
        for key in theta.keys():
            if key not in used:
                values.erase(key)
        new_stamps = {key: stamps[key] for key in used}
        self.smoother = gtsam.IncrementalFixedLagSmoother(self.lag_s, isam2_params())
        self.smoother.update(graph, values, new_stamps, [])
        new_index = self.smoother.getISAM2Result().getNewFactorsIndices()
        return {o: int(n) for o, n in zip(old_index, new_index, strict=True)}

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
