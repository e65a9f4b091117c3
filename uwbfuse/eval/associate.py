# SPDX-License-Identifier: BSD-3-Clause
"""Time association of two trajectories (nearest stamp within a tolerance).

The rule is evo's `associate_trajectories` (nearest_time): every pose of the trajectory
with fewer poses is matched to the nearest stamp of the other one when the two stamps are
at most `max_dt` apart (ties go to the earlier stamp); unmatched poses are dropped. A pose
of the longer trajectory may serve twice when the shorter one is denser than 2 * max_dt.
Vectorised with `searchsorted`, on integer nanoseconds (exact).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from uwbfuse.streams import F64, I64, NS_PER_S, PoseStream


def match_stamps(
    t_short: I64, t_long: I64, max_dt_ns: int
) -> tuple[np.ndarray, np.ndarray]:
    """Indices (i_short, i_long) of the nearest `t_long` for each `t_short` within max_dt.

    Both arrays must be sorted. Returns int64 index arrays of equal length.
    """
    t_short = np.asarray(t_short, dtype=np.int64)
    t_long = np.asarray(t_long, dtype=np.int64)
    if len(t_short) == 0 or len(t_long) == 0:
        empty = np.zeros(0, dtype=np.int64)
        return empty, empty
    hi = np.minimum(np.searchsorted(t_long, t_short, side="right"), len(t_long) - 1)
    lo = np.maximum(hi - 1, 0)
    d_hi = np.abs(t_long[hi] - t_short)
    d_lo = np.where(hi > 0, np.abs(t_short - t_long[lo]), np.iinfo(np.int64).max)
    pick_hi = d_hi < d_lo
    best = np.where(pick_hi, hi, lo)
    d = np.where(pick_hi, d_hi, d_lo)
    ok = d <= max_dt_ns
    return np.flatnonzero(ok).astype(np.int64), best[ok].astype(np.int64)


@dataclass(frozen=True)
class Association:
    """Matched pose pairs, sorted by time: est and gt rows of the same instants.

    `t_ns` are the ground-truth stamps of the pairs; `i_est` / `i_gt` index the inputs.
    """

    t_ns: I64
    i_est: I64
    i_gt: I64
    est_position: F64
    est_quat_xyzw: F64
    gt_position: F64
    gt_quat_xyzw: F64

    def __len__(self) -> int:
        return len(self.t_ns)

    @property
    def t_s(self) -> F64:
        return self.t_ns.astype(np.float64) / NS_PER_S


def associate(est: PoseStream, gt: PoseStream, max_dt: float) -> Association:
    """Pair `est` and `gt` poses by nearest stamp within `max_dt` seconds (evo's rule)."""
    max_dt_ns = round(max_dt * NS_PER_S)
    if len(gt) > len(est):
        i_est, i_gt = match_stamps(est.t_ns, gt.t_ns, max_dt_ns)
    else:
        i_gt, i_est = match_stamps(gt.t_ns, est.t_ns, max_dt_ns)
    return Association(
        t_ns=gt.t_ns[i_gt],
        i_est=i_est,
        i_gt=i_gt,
        est_position=est.position[i_est],
        est_quat_xyzw=est.quat_xyzw[i_est],
        gt_position=gt.position[i_gt],
        gt_quat_xyzw=gt.quat_xyzw[i_gt],
    )
