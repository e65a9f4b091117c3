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
        or covariance r (m,m); rows with an `anchor` (m,) index >= 0 also read that
        anchor's excess (None, or -1 for a row: no range). Joseph form expanded with the
        gain zero on the excesses, P - K H P - P H^T K^T + K S K^T, so valid for any gain."""
        n = self.n
        hh = np.zeros((h.shape[0], len(self.p)))
        hh[:, :n] = h
        if anchor is not None:
            a = np.asarray(anchor, np.int64)
            rows = np.flatnonzero(a >= 0)
            hh[rows, n + a[rows]] = 1.0
        ph = self.p @ hh.T                                  # (N,m)
        s = hh @ ph + (np.diag(r) if np.ndim(r) == 1 else r)
        kph = k @ ph.T                                      # (n,N)
        self.p[:n] -= kph
        self.p[:, :n] -= kph.T
        self.p[:n, :n] += k @ s @ k.T
        self.p = 0.5 * (self.p + self.p.T)  # the expanded form drifts from symmetric

    def update_linearised(self, c: F64, rows: np.ndarray, var: F64, anchor: np.ndarray
                          ) -> None:
        """A sigma-point filter's update by statistical linearisation: c (n+m, n+m) the
        joint covariance of (state error, predicted measurements) before the update, `rows`
        the measurements it used (indices into m) with the noise variances `var` it gave
        them, `anchor` (len(rows),) their anchors (-1: no range). Its composite gain over
        those rows is K = Pxz (Pzz + R)^-1 (sequential scalar updates at fixed variances
        condition the same joint Gaussian); the rows read the state through H = Pxz^T P^-1
        plus a white residual of covariance Pzz - H Pxz, the part the linear model misses."""
        n = self.n
        idx = n + np.asarray(rows, np.int64)
        pxz = c[:n, idx]
        pzz = c[np.ix_(idx, idx)]
        s = pzz + np.diag(var)
        k = np.linalg.solve(s, pxz.T).T
        h = np.linalg.lstsq(c[:n, :n], pxz, rcond=None)[0].T  # P symmetric: Pxz^T P^-1
        self.update(k, h, s - h @ pxz, anchor)

    def propagate(self, t: F64, q: F64, f: F64, qc: F64) -> None:
        """The filter's transition t (n,n) and noise q (n,n); each excess times f (M,) plus
        noise of variances qc (M,)."""
        self.p = propagate_with_biases(self.p, self.n, t, q, f, qc)

    def restart(self, block: slice, cov: F64) -> None:
        """The filter restarted the states `block` (within n) at covariance `cov`,
        uncorrelated with the rest (a lost-track restart)."""
        self.p[block, :] = 0.0
        self.p[:, block] = 0.0
        self.p[block, block] = cov

    def add(self, dp: F64) -> None:
        """Add dp (n,n) to the filter block (the filter's own covariance inflations)."""
        self.p[: self.n, : self.n] += dp

    @property
    def state(self) -> F64:
        """(n,n) covariance of the filter's error state under the truth model."""
        return self.p[: self.n, : self.n]
