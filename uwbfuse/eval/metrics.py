# SPDX-License-Identifier: BSD-3-Clause
"""Error metrics on associated (and aligned) pose pairs: ATE, RPE, yaw error, coverage.

Definitions (all in the map frame, metres and radians):
- ATE: |p_gt - p_est| per pair, 3-D and 2-D (x/y only); evo's APE `translation_part`.
- RPE: translation error of the relative motion between two instants i < j.
  With GT orientation it is evo's RPE `translation_part`:
  |R_est_i^T (p_est_j - p_est_i) - R_gt_i^T (p_gt_j - p_gt_i)|, independent of alignment.
  Without GT orientation it is the map-frame displacement error
  |(p_est_j - p_est_i) - (p_gt_j - p_gt_i)|.
  Pairs are chosen on the ground truth, for every i (evo's `all_pairs`): over a time delta,
  the j whose stamp is nearest t_i + delta (within 10 % of delta); over a distance delta,
  the j whose travelled GT path from i is nearest delta (within 10 %), as evo's
  `filter_pairs_by_path` does.
- Yaw error: wrapped difference of ZYX yaw angles, est minus GT.
- Coverage: associated poses cover the time to the next associated pose when it is at most
  `COVERAGE_MAX_GAP_S` away; coverage is the covered time over the GT time span.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from uwbfuse.streams import F64, I64, NS_PER_S

RPE_REL_TOL = 0.1
COVERAGE_MAX_GAP_S = 0.5


@dataclass(frozen=True)
class Stats:
    """Summary of an error array (units of the errors)."""

    n: int
    rmse: float
    mean: float
    median: float
    std: float
    min: float
    max: float

    def as_dict(self) -> dict[str, float | int]:
        return asdict(self)


def stats(errors: F64) -> Stats:
    """RMSE, mean, median, population std, min and max of `errors` (as evo computes them)."""
    e = np.asarray(errors, dtype=np.float64)
    if e.size == 0:
        nan = math.nan
        return Stats(0, nan, nan, nan, nan, nan, nan)
    return Stats(
        n=int(e.size),
        rmse=float(np.sqrt(np.mean(e**2))),
        mean=float(np.mean(e)),
        median=float(np.median(e)),
        std=float(np.std(e)),
        min=float(np.min(e)),
        max=float(np.max(e)),
    )


def ate_errors(est_position: F64, gt_position: F64) -> tuple[F64, F64]:
    """Per-pair position errors (N,), metres: 3-D and 2-D (x/y)."""
    d = est_position - gt_position
    return np.linalg.norm(d, axis=1), np.linalg.norm(d[:, :2], axis=1)


def yaw_of(quat_xyzw: F64) -> F64:
    """ZYX yaw (heading about z) of quaternions (N,4 xyzw), radians."""
    x, y, z, w = quat_xyzw.T
    return np.arctan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


def wrap_angle(a: F64) -> F64:
    """Angles wrapped to [-pi, pi)."""
    return (np.asarray(a) + np.pi) % (2.0 * np.pi) - np.pi


def yaw_errors(est_quat_xyzw: F64, gt_quat_xyzw: F64) -> F64:
    """Signed heading error est - gt per pair (N,), radians in [-pi, pi)."""
    return wrap_angle(yaw_of(est_quat_xyzw) - yaw_of(gt_quat_xyzw))


def pairs_by_time(t_ns: I64, delta_s: float, rel_tol: float = RPE_REL_TOL) -> tuple[I64, I64]:
    """Pairs (i, j>i) with t_j nearest t_i + delta, |t_j - t_i - delta| < rel_tol * delta."""
    t = np.asarray(t_ns, dtype=np.int64)
    n = len(t)
    if n < 2:
        empty = np.zeros(0, dtype=np.int64)
        return empty, empty
    delta = round(delta_s * NS_PER_S)
    tol = rel_tol * delta
    i = np.arange(n, dtype=np.int64)
    target = t + delta
    hi = np.searchsorted(t, target, side="left")
    lo = hi - 1
    hi_c = np.minimum(hi, n - 1)
    d_hi = np.where(hi < n, np.abs(t[hi_c] - target), np.iinfo(np.int64).max)
    d_lo = np.where(lo > i, np.abs(target - t[np.maximum(lo, 0)]), np.iinfo(np.int64).max)
    j = np.where(d_lo <= d_hi, lo, hi)
    d = np.minimum(d_lo, d_hi)
    ok = (d < tol) & (j > i)
    return i[ok], j[ok]


def path_lengths(position: F64) -> F64:
    """Travelled distance from the first position to each position (N,), metres."""
    steps = np.linalg.norm(np.diff(position, axis=0), axis=1)
    return np.concatenate(([0.0], np.cumsum(steps)))


def pairs_by_path(
    position: F64, delta_m: float, rel_tol: float = RPE_REL_TOL
) -> tuple[I64, I64]:
    """Pairs (i, j>i) whose travelled path is nearest `delta_m`, within rel_tol * delta.

    Same choice as evo's `filter_pairs_by_path(..., all_pairs=True)` (first index on ties).
    """
    n = len(position)
    if n < 2:
        empty = np.zeros(0, dtype=np.int64)
        return empty, empty
    dist = path_lengths(position)
    i = np.arange(n - 1, dtype=np.int64)
    target = dist[:-1] + delta_m
    # Candidates among j in [i+1, n): the first index with dist >= target, and the first
    # index of the run of equal values just below it.
    hi = np.maximum(np.searchsorted(dist, target, side="left"), i + 1)
    lo_raw = hi - 1
    lo_first = np.maximum(np.searchsorted(dist, dist[np.maximum(lo_raw, 0)], side="left"), i + 1)
    has_lo = lo_raw >= i + 1
    has_hi = hi < n
    # Measured as evo does, from distances_from_here = dist[j] - dist[i].
    err_hi = np.where(has_hi, np.abs((dist[np.minimum(hi, n - 1)] - dist[:-1]) - delta_m), np.inf)
    err_lo = np.where(
        has_lo, np.abs((dist[np.minimum(lo_first, n - 1)] - dist[:-1]) - delta_m), np.inf
    )
    pick_lo = err_lo <= err_hi
    j = np.where(pick_lo, lo_first, hi)
    err = np.minimum(err_lo, err_hi)
    ok = err <= rel_tol * delta_m
    return i[ok], j[ok].astype(np.int64)


def rpe_errors(
    i: I64,
    j: I64,
    est_position: F64,
    est_quat_xyzw: F64,
    gt_position: F64,
    gt_quat_xyzw: F64 | None,
) -> F64:
    """RPE translation error per pair (i, j), metres (see the module docstring).

    `gt_quat_xyzw` None selects the map-frame displacement error (GT without orientation).
    """
    d_est = est_position[j] - est_position[i]
    d_gt = gt_position[j] - gt_position[i]
    if gt_quat_xyzw is None:
        return np.linalg.norm(d_est - d_gt, axis=1)
    local_est = Rotation.from_quat(est_quat_xyzw[i]).inv().apply(d_est)
    local_gt = Rotation.from_quat(gt_quat_xyzw[i]).inv().apply(d_gt)
    return np.linalg.norm(np.atleast_2d(local_est - local_gt), axis=1)


def coverage(t_assoc_ns: I64, gt_t0_ns: int, gt_t1_ns: int) -> float:
    """Fraction (0..1) of the GT span [t0, t1] covered by associated poses (module doc)."""
    span = gt_t1_ns - gt_t0_ns
    if span <= 0 or len(t_assoc_ns) == 0:
        return 0.0
    gaps = np.diff(np.asarray(t_assoc_ns, dtype=np.int64))
    covered = gaps[gaps <= COVERAGE_MAX_GAP_S * NS_PER_S].sum()
    return float(min(covered / span, 1.0))
