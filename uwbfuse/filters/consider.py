# SPDX-License-Identifier: BSD-3-Clause
"""Consider covariance: the error covariance of a Kalman filter under a truth model with
per-anchor range excesses the filter does not estimate (Schmidt's consider analysis).

The filter keeps its own gains and estimate; this class applies the same gains to the
covariance of the augmented error [filter state, consider excesses] and reports its state
block. Nothing here feeds back into the filter.
"""

from __future__ import annotations

import numpy as np

from uwbfuse.filters.models import F64, augment, propagate_with_biases


class ConsiderCovariance:
    """Covariance (n + M, n + M) of [filter error state (n,), range excess per anchor (M,)]."""

    def __init__(self, p0: F64, var0: F64) -> None:
        self.n = len(p0)
        self.p = augment(p0, var0)

    def update(self, k: F64, h: F64, r: F64, anchor: np.ndarray | None) -> None:
        """The filter's update with gain k (n,m) on rows h (m,n) of noise variances r (m,)
        or covariance r (m,m); rows with an `anchor` (m,) index also read that anchor's
        excess (None: no range rows). Joseph form expanded with the gain zero on the
        excesses, P - K H P - P H^T K^T + K S K^T, so valid for any gain."""
        n = self.n
        hh = np.zeros((h.shape[0], len(self.p)))
        hh[:, :n] = h
        if anchor is not None:
            hh[np.arange(h.shape[0]), n + np.asarray(anchor)] = 1.0
        ph = self.p @ hh.T                                  # (N,m)
        s = hh @ ph + (np.diag(r) if np.ndim(r) == 1 else r)
        kph = k @ ph.T                                      # (n,N)
        self.p[:n] -= kph
        self.p[:, :n] -= kph.T
        self.p[:n, :n] += k @ s @ k.T
        self.p = 0.5 * (self.p + self.p.T)  # the expanded form drifts from symmetric

    def propagate(self, t: F64, q: F64, f: F64, qc: F64) -> None:
        """The filter's transition t (n,n) and noise q (n,n); each excess times f (M,) plus
        noise of variances qc (M,)."""
        self.p = propagate_with_biases(self.p, self.n, t, q, f, qc)

    def add(self, dp: F64) -> None:
        """Add dp (n,n) to the filter block (the filter's own covariance inflations)."""
        self.p[: self.n, : self.n] += dp

    @property
    def state(self) -> F64:
        """(n,n) covariance of the filter's error state under the truth model."""
        return self.p[: self.n, : self.n]
