# SPDX-License-Identifier: BSD-3-Clause
"""Method `wls`: UWB-only weighted least-squares multilateration per epoch (Qiu et al. 2022).

At every step t the latest range of each anchor within (t - `wls.window`, t] forms an epoch
(ranges arrive round robin). The tag position is the NLOS-weighted fix of
`uwbfuse.positioning.nlos_weighting.weighted_fix`: per-range NLOS probabilities from the per-range
view of the NLOS model (`uwbfuse.nlos`, `[nlos] range_*`, per anchor `[nlos.anchor]` from
`calibrate_nlos`) give the weights of Qiu eq.
10-11, the expected NLOS excess is removed, and a Gauss-Newton step refines the linear
solution. For wheeled logs (planar vehicles, `wls.height_projection = auto`) the fix is 2-D
at a known tag height by anchor height projection (INS-UWB paper); otherwise 3-D (2-D at an
assumed height with fewer than four anchors). `wls.nearest_three` keeps only the three
nearest anchors.

Orientation: UWB alone gives no attitude, yet TUM output needs one. The yaw written is the
track direction: the direction of motion over the last `wls.min_track` metres of fixes
(held while the tag stands still, 0 before the first motion); roll and pitch are zero. The
base position is the tag position minus the lever arm `tag_in_base` rotated by that yaw;
before the first motion, with no heading, minus its vertical part only (the centre of the
circle of possible base positions).

`calibrate_nlos(log_with_gt, config) -> NlosModel` (re-exported here) fits the per-anchor
error distributions for the `[nlos]` table.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from uwbfuse.config import Config
from uwbfuse.errors import AnchorMapError
from uwbfuse.estimator import EstimatorBase, Method, PoseEstimate
from uwbfuse.filters.models import pose_covariance
from uwbfuse.nlos import NlosModel, NlosParams
from uwbfuse.positioning.multilateration import (
    default_tag_z,
    epoch_window_ns,
    group_epochs,
    select_nearest,
)
from uwbfuse.positioning.nlos_classifier import RangePriors
from uwbfuse.positioning.nlos_weighting import WeightedFixes, calibrate_nlos, weighted_fix
from uwbfuse.streams import NS_PER_S, AnchorMap, PoseStream

__all__ = ["EpochFixer", "TagFix", "TrackHeading", "WlsEstimator", "calibrate_nlos", "make"]

_KEEP_S = 3.0  # seconds of ranges kept in the buffer
_HISTORY_S = 10.0  # seconds of fixes kept for the track direction
_WINDOW_ADAPT_N = 2000  # ranges over which the epoch length keeps adapting to the cycle
_OUTLIER_GATE = 4.0  # normalised range residual that triggers fault exclusion
_MAX_SPEED = 3.0  # fastest plausible tag speed for the jump gate, m/s
_JUMP_FLOOR = 0.5  # jump always allowed between consecutive fixes, m
_RELOCK_S = 1.0  # after this long without an accepted fix, accept any fix, s


def yaw_quat(yaw: float) -> np.ndarray:
    """Quaternion (x, y, z, w) of a rotation by yaw (rad) about z."""
    return np.array([0.0, 0.0, math.sin(0.5 * yaw), math.cos(0.5 * yaw)])


def _agree(ref: tuple[int, np.ndarray], t_ns: int, pos: np.ndarray) -> bool:
    """Fix `pos` at t_ns is within a vehicle's reach of the fix `ref` (stamp ns, position)."""
    dt = abs(t_ns - ref[0]) / NS_PER_S
    return float(np.linalg.norm(pos - ref[1])) <= _JUMP_FLOOR + _MAX_SPEED * dt


@dataclass(frozen=True)
class TagFix:
    """One epoch's fix of the tag antenna (map frame).

    position (3,) m (z = assumed tag height in 2-D); cov (dim,dim) m^2; nlos_prob (M,) per
    anchor (NaN where no range); n_used ranges; residual_rms m.
    """

    t_ns: int
    position: np.ndarray
    cov: np.ndarray
    dim: int
    nlos_prob: np.ndarray
    n_used: int
    residual_rms: float


class EpochFixer:
    """Buffers ranges and returns the weighted fix of the epoch ending at a given time."""

    def __init__(self, config: Config, anchors: AnchorMap, streams: frozenset[str]) -> None:
        self.config = config
        self.anchors = anchors
        wls = config.wls
        lever_z = float(config.extrinsics.tag_in_base[2])
        project = wls.height_projection == "on" or (
            wls.height_projection == "auto" and "wheel" in streams
        )
        if wls.tag_height != "auto":
            self.tag_z = float(wls.tag_height)
        elif project:
            self.tag_z = config.init.base_height + lever_z
        else:
            self.tag_z = default_tag_z(anchors.positions)
        self.dim = 2 if project or len(anchors) < 4 else 3
        # Unweighted: every range LOS with the [uwb] sigma (plain LS, Qiu eq. 6).
        model = NlosModel.from_config(config)
        self.model = model if wls.weighted else replace(
            model, per_range=NlosParams(config.uwb.sigma, 0.0, 1.0, 0.0), per_anchor={})
        self.base_window_ns = round(wls.window * NS_PER_S)
        self.window_ns = self.base_window_ns
        self._n_seen = 0
        self._t = np.zeros(0, dtype=np.int64)
        self._a = np.zeros(0, dtype=np.int32)
        self._r = np.zeros(0)
        self._p = np.zeros(0)  # the classifier's P(NLOS) per buffered range (with priors)
        self.priors: RangePriors | None = None
        self._pgrid: np.ndarray | None = None
        self._last_stamps: np.ndarray | None = None
        self.n_epochs = 0
        self.n_fixes = 0
        self.n_degenerate = 0
        self.nlos_prob_sum = 0.0
        self.nlos_prob_n = 0
        self.n_excluded = 0
        self.n_jumps = 0
        self._track = False  # the last two accepted fixes agreed (the jump gate is armed)
        self._cand: tuple[int, np.ndarray] | None = None  # a fix waiting for a second opinion
        self.n_inconsistent = 0
        self._prev: tuple[int, np.ndarray] | None = None
        self._loo_grid = np.zeros((1, len(anchors)))

    def add_ranges(self, t_ns: np.ndarray, anchor: np.ndarray, rng: np.ndarray) -> None:
        """Range batch: stamps (N,) ns, anchor index (N,), range (N,) m."""
        if not len(t_ns):
            return
        self._n_seen += len(t_ns)
        self._t = np.concatenate([self._t, np.asarray(t_ns, dtype=np.int64)])
        self._a = np.concatenate([self._a, np.asarray(anchor, dtype=np.int32)])
        self._r = np.concatenate([self._r, np.asarray(rng, dtype=np.float64)])
        if self.priors is not None:
            self._p = np.concatenate([self._p, self.priors.take(t_ns, anchor)])
        keep = self._t >= self._t[-1] - round(_KEEP_S * NS_PER_S)
        if not np.all(keep):
            self._t, self._a, self._r = self._t[keep], self._a[keep], self._r[keep]
            if self.priors is not None:
                self._p = self._p[keep]

    def fix(self, t_ns: int, *, only_new: bool = False) -> TagFix | None:
        """Weighted fix of the epoch (t_ns - window, t_ns]; None if too few ranges or the
        geometry is degenerate. only_new: None unless a new range arrived since last call."""
        if not len(self._t):
            return None
        sel = self._t <= t_ns
        if self._n_seen < _WINDOW_ADAPT_N and len(self._t) >= 3 * len(self.anchors):
            # Adapt the epoch length to the round-robin cycle seen so far.
            self.window_ns = epoch_window_ns(self._t, self._a, self.base_window_ns)
        grid, stamps = group_epochs(self._t[sel], self._a[sel], self._r[sel],
                                    len(self.anchors), np.array([t_ns]), self.window_ns)
        if only_new and self._last_stamps is not None and np.array_equal(
            stamps[0], self._last_stamps
        ):
            return None
        self._last_stamps = stamps[0]
        self.n_epochs += 1
        if np.count_nonzero(np.isfinite(grid[0])) < self.dim + 1:
            self.n_degenerate += 1
            return None
        nearest = 3 if self.config.wls.nearest_three else None
        if nearest is not None:
            grid[~select_nearest(grid, nearest)] = np.nan
        self._pgrid = None if self.priors is None else group_epochs(
            self._t[sel], self._a[sel], self._p[sel], len(self.anchors), np.array([t_ns]),
            self.window_ns)[0]
        wf = weighted_fix(self.anchors, grid, self.model, dim=self.dim, tag_z=self.tag_z,
                          p_nlos=self._pgrid)
        k = 0
        if wf.fixes.ok[0] and self._worst_residual(grid[0], wf, 0) > _OUTLIER_GATE:
            wf, k = self._exclude_one(grid[0], wf)
        fx = wf.fixes
        if not fx.ok[k]:
            self.n_degenerate += 1
            return None
        if self._prev is not None:
            # Jump gate: a fix farther from the last one than a vehicle can move is held
            # back, unless fixes keep disagreeing for _RELOCK_S (then the track moves).
            # The gate needs a track: two consecutive fixes that agree. Until then a fix far
            # from the last one waits for a second opinion (below).
            dt = (t_ns - self._prev[0]) / NS_PER_S
            far = not _agree(self._prev, int(t_ns), fx.position[k])
            if far and dt < _RELOCK_S and self._track:
                self.n_jumps += 1
                return None
            if far and dt < _RELOCK_S:
                # No track yet and the fix disagrees with the only one before it: one of
                # the two is off (two outliers among four ranges took a first fix 2 m
                # away). It waits; the next fix joins whichever of the two it agrees with.
                cand, self._cand = self._cand, (int(t_ns), fx.position[k].copy())
                if cand is None or not _agree(cand, int(t_ns), fx.position[k]):
                    self.n_jumps += 1
                    return None
                far = False  # agrees with the waiting fix: the earlier one was off
            self._cand = None
            self._track = not far and dt < _RELOCK_S
        self.n_fixes += 1
        self._prev = (int(t_ns), fx.position[k].copy())
        p = wf.nlos_prob[k]
        grid = grid[[0]] if k == 0 and len(grid) == 1 else self._loo_grid[[k]]
        used = np.isfinite(grid[0])
        self.nlos_prob_sum += float(np.sum(p[used]))
        self.nlos_prob_n += int(np.count_nonzero(used))
        return TagFix(int(t_ns), fx.position[k].copy(), fx.cov[k].copy(), self.dim,
                      np.where(used, p, np.nan), int(fx.n_used[k]),
                      float(fx.residual_rms[k]))

    def _worst_residual(self, row: np.ndarray, wf: WeightedFixes, k: int) -> float:
        """Largest |range residual| of fix k in units of its mixture std (NLOS-aware)."""
        los, nmean, nstd, _prior = self.model.arrays(self.anchors)
        pos = wf.fixes.position[k]
        pred = np.linalg.norm(pos[None, :] - self.anchors.positions, axis=1)
        p = wf.nlos_prob[k]
        var = (1 - p) * np.maximum(los, 0.01) ** 2 + p * nstd**2
        z = np.abs(row - pred - p * nmean) / np.sqrt(var)
        return float(np.nanmax(z)) if np.any(np.isfinite(z)) else 0.0

    def _exclude_one(self, row: np.ndarray, wf_all: WeightedFixes) -> tuple[WeightedFixes, int]:
        """Fault exclusion: refit without each range in turn (one batch) and keep the most
        consistent fit, or, when the remaining ranges fit exactly, the one nearest the
        previous fix. Returns the fixes of the batch and the chosen row."""
        used = np.flatnonzero(np.isfinite(row))
        if len(used) - 1 < self.dim:
            self._loo_grid = row[None, :]
            self.n_inconsistent += 1
            return wf_all, 0
        grid = np.repeat(row[None, :], len(used), axis=0)
        grid[np.arange(len(used)), used] = np.nan
        pg = None if self._pgrid is None else np.repeat(self._pgrid, len(used), axis=0)
        wf = weighted_fix(self.anchors, grid, self.model, dim=self.dim, tag_z=self.tag_z,
                          p_nlos=pg)
        ok = wf.fixes.ok
        if not np.any(ok):
            self._loo_grid = row[None, :]
            return wf_all, 0
        redundant = len(used) - 1 > self.dim
        if redundant:
            score = np.array([self._worst_residual(grid[i], wf, i) if ok[i] else np.inf
                              for i in range(len(used))])
            if self._prev is not None and np.any(score < _OUTLIER_GATE):
                # Several consistent subsets (mirror geometry): the one nearest the last fix.
                dist = np.linalg.norm(wf.fixes.position - self._prev[1], axis=1)
                score = np.where(score < _OUTLIER_GATE, dist, np.inf)
        elif self._prev is not None:
            score = np.where(ok, np.linalg.norm(wf.fixes.position - self._prev[1], axis=1),
                             np.inf)
        else:
            self._loo_grid = row[None, :]
            return wf_all, 0
        self.n_excluded += 1
        self._loo_grid = grid
        return wf, int(np.argmin(score))

    def report(self) -> dict[str, Any]:
        return {
            "epochs": self.n_epochs,
            "fixes": self.n_fixes,
            "degenerate_epochs": self.n_degenerate,
            "fix_dim": self.dim,
            "epoch_window_s": self.window_ns / NS_PER_S,
            "tag_height_m": self.tag_z if self.dim == 2 else None,
            "mean_nlos_probability": self.nlos_prob_sum / self.nlos_prob_n
            if self.nlos_prob_n else None,
            "excluded_ranges": self.n_excluded,
            "jump_rejected_fixes": self.n_jumps,
            "inconsistent_epochs": self.n_inconsistent,
        }


def fix_covariance(fx: TagFix) -> np.ndarray:
    """(6,6) pose covariance (ROS order, map axes) of a fix: the least-squares covariance of
    its position axes (x, y; z too for a 3-D fix); the height of a 2-D fix and the attitude
    (track direction, not estimated) get `UNKNOWN_VARIANCE`."""
    cov = np.asarray(fx.cov, dtype=np.float64)
    if not np.all(np.isfinite(cov)):
        return pose_covariance(np.zeros((0, 0)), (None,) * 6)
    axes = (0, 1, 2) if fx.dim == 3 else (0, 1, None)
    return pose_covariance(cov, (*axes, None, None, None))


class TrackHeading:
    """Yaw (rad) as the direction of motion over the last `min_track` metres of positions."""

    def __init__(self, min_track: float) -> None:
        self.min_track = min_track
        self.yaw = 0.0
        self.moving_seen = False
        self._hist: deque[tuple[float, np.ndarray]] = deque()

    def base_position(self, tag: np.ndarray, lever: np.ndarray) -> np.ndarray:
        """The base position (3,) m, map frame, of the tag position `tag` (3,) m, map frame,
        and the lever arm `lever` (3,) m, base frame, turned by the track yaw. Before the
        first motion there is no heading: the base lies on a circle of the lever's
        horizontal length around the tag, and the circle's centre (the tag, less the
        lever's height) is the guess of least error, |lever| where a lever turned by a
        guessed yaw errs by up to twice that."""
        if not self.moving_seen:
            return tag - np.array([0.0, 0.0, lever[2]])
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        return tag - np.array([c * lever[0] - s * lever[1], s * lever[0] + c * lever[1],
                               lever[2]])

    def update(self, t_s: float, xy: np.ndarray) -> float:
        """Add a position (m, map frame) at t_s; return the current track yaw."""
        self._hist.append((t_s, np.asarray(xy[:2], dtype=np.float64)))
        while self._hist and self._hist[0][0] < t_s - _HISTORY_S:
            self._hist.popleft()
        for _t, q in reversed(self._hist):
            d = xy[:2] - q
            if math.hypot(d[0], d[1]) >= self.min_track:
                self.yaw = math.atan2(d[1], d[0])
                self.moving_seen = True
                break
        return self.yaw


class WlsEstimator(EstimatorBase):
    """Streaming UWB-only WLS (see module doc); IMU and wheel batches are ignored."""

    def __init__(self, config: Config, anchors: AnchorMap, streams: frozenset[str]) -> None:
        self.config = config
        self.fixer = EpochFixer(config, anchors, streams)
        self.heading = TrackHeading(config.wls.min_track)
        self.lever = np.asarray(config.extrinsics.tag_in_base, dtype=np.float64)
        self._tag: np.ndarray | None = None
        self._cov: np.ndarray | None = None
        self._est: PoseEstimate | None = None
        self.n_held = 0

    def add_imu(self, t_ns: np.ndarray, gyro: np.ndarray, accel: np.ndarray) -> None:
        """Ignored: WLS is UWB only."""

    def add_wheel(self, t_ns: np.ndarray, v: np.ndarray, omega: np.ndarray) -> None:
        """Ignored: WLS is UWB only."""

    def add_ranges(self, t_ns: np.ndarray, anchor: np.ndarray, rng: np.ndarray) -> None:
        self.fixer.add_ranges(t_ns, anchor, rng)

    def use_range_priors(self, priors: RangePriors) -> None:
        """Take the learned classifier's P(NLOS) per range as the NLOS probabilities of the
        weights (in place of those from the residuals and the per-range [nlos] model)."""
        self.fixer.priors = priors

    def step(self, t_ns: int) -> None:
        fx = self.fixer.fix(t_ns)
        if fx is not None:
            self._tag = fx.position
            self._cov = fix_covariance(fx)
            self.heading.update(t_ns / NS_PER_S, fx.position)
        elif self._tag is not None:
            self.n_held += 1
        if self._tag is None:
            self._est = None
            return
        self._est = PoseEstimate(int(t_ns), self.heading.base_position(self._tag, self.lever),
                                 yaw_quat(self.heading.yaw), self._cov)

    def estimate(self) -> PoseEstimate | None:
        return self._est

    def finish(self) -> PoseStream | None:
        return None

    def report(self) -> dict[str, Any]:
        out = self.fixer.report()
        out["held_epochs"] = self.n_held
        return out


def make(
    method: Method, config: Config, anchors: AnchorMap | None, streams: frozenset[str]
) -> WlsEstimator:
    """Factory for `Method.WLS`."""
    if anchors is None or not len(anchors):
        raise AnchorMapError(f"method {method.value} needs an anchor map")
    return WlsEstimator(config, anchors, streams)
