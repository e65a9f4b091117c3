# SPDX-License-Identifier: BSD-3-Clause
"""Per-epoch motion state from a trajectory and its prediction over the control delay.

`motion_from_poses` gives, at every pose of a trajectory (base frame in the map frame), the
planar velocity (m/s, map axes) and yaw rate (rad/s) as the slope of a least-squares line
through the poses of the past `window` seconds (causal, as an AGV's own controller would
have them; the line fit averages out the jitter of an estimate), the heading (from the
orientation, or the direction of motion for position-only tracks) and the position std
(largest xy std of the covariance, where known). `predict` moves each state at constant
velocity and turn rate (the paper's assumption: the AGV keeps its current state for the
control delay): the velocity vector turns with the yaw rate.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from uwbfuse.errors import CollisionCheckError
from uwbfuse.streams import NS_PER_S, UNKNOWN_VARIANCE, PoseStream

F64 = NDArray[np.float64]

MIN_HEADING_SPEED = 0.05
"""m/s: below this a position-only track keeps its last heading (the direction of a
standing vehicle's jitter is noise)."""

UNKNOWN_VARIANCE_FLOOR = 0.1 * UNKNOWN_VARIANCE
"""m^2: a covariance xy variance this large marks the position uncertainty as unknown."""


@dataclass(frozen=True)
class MotionState:
    """Per epoch: t_ns (int ns, the TUM stamp), t (s, the same), x, y (m, map frame), yaw
    (rad, unwrapped), vx, vy (m/s, map axes), omega (rad/s), sigma (m: position std, NaN
    when unknown)."""

    t_ns: NDArray[np.int64]
    t: F64
    x: F64
    y: F64
    yaw: F64
    vx: F64
    vy: F64
    omega: F64
    sigma: F64

    def __len__(self) -> int:
        return len(self.t)

    @property
    def speed(self) -> F64:
        return np.hypot(self.vx, self.vy)

    def at(self, t_ns: NDArray[np.int64]) -> MotionState:
        """The state interpolated linearly at stamps `t_ns` (inside its span)."""
        t = (t_ns - self.t_ns[0]).astype(np.float64) / NS_PER_S
        own = (self.t_ns - self.t_ns[0]).astype(np.float64) / NS_PER_S
        cols = [np.interp(t, own, c) for c in
                (self.x, self.y, self.yaw, self.vx, self.vy, self.omega, self.sigma)]
        return MotionState(np.asarray(t_ns, dtype=np.int64),
                           t_ns.astype(np.float64) / NS_PER_S, *cols)

    def take(self, idx: NDArray[np.intp]) -> MotionState:
        return MotionState(self.t_ns[idx], self.t[idx], self.x[idx], self.y[idx],
                           self.yaw[idx], self.vx[idx], self.vy[idx], self.omega[idx],
                           self.sigma[idx])


def _causal_slopes(t: F64, values: F64, window: float) -> F64:
    """Slope (per s) of the least-squares line through the samples in [t_i - window, t_i],
    for every i; `values` (N,) or (N,K). Fewer than two samples: the last difference."""
    n = len(t)
    tt = t - t[0]
    v = values.reshape(n, -1)
    lo = np.searchsorted(tt, tt - window - 1e-9, side="left")
    hi = np.arange(1, n + 1)

    def csum(a: F64) -> F64:
        return np.concatenate([np.zeros((1, *a.shape[1:])), np.cumsum(a, axis=0)])

    s1, st, stt = csum(np.ones(n)), csum(tt), csum(tt * tt)
    sv, stv = csum(v), csum(tt[:, None] * v)
    cnt = s1[hi] - s1[lo]
    mt = (st[hi] - st[lo]) / cnt
    var = (stt[hi] - stt[lo]) / cnt - mt * mt
    cov = (stv[hi] - stv[lo]) / cnt[:, None] - mt[:, None] * (sv[hi] - sv[lo]) / cnt[:, None]
    good = (cnt >= 3) & (var > 1e-12)
    slope = np.zeros_like(v)
    slope[good] = cov[good] / var[good, None]
    # too few samples in the window: the difference to the previous pose
    diff = np.zeros_like(v)
    dt = np.diff(tt)
    diff[1:] = np.diff(v, axis=0) / np.where(dt > 0, dt, np.inf)[:, None]
    slope[~good] = diff[~good]
    return slope.reshape(values.shape)


def position_sigma(cov: F64 | None, n: int, assumed: float = 0.0) -> F64:
    """Largest std of the xy block of each (N,6,6) ROS-order covariance, m; `assumed` (or
    NaN when 0) where none is known."""
    fallback = assumed if assumed > 0 else np.nan
    if cov is None:
        return np.full(n, fallback)
    a, b, d = cov[:, 0, 0], cov[:, 0, 1], cov[:, 1, 1]
    lam = 0.5 * (a + d) + np.sqrt(0.25 * (a - d) ** 2 + b * b)
    unknown = ~np.isfinite(lam) | (a >= UNKNOWN_VARIANCE_FLOOR) | (d >= UNKNOWN_VARIANCE_FLOOR)
    return np.where(unknown, fallback, np.sqrt(np.clip(lam, 0.0, None)))


def motion_from_poses(poses: PoseStream, window: float, assumed_sigma: float = 0.0,
                      name: str = "trajectory") -> MotionState:
    """The motion state at every pose of `poses` (see the module docstring)."""
    if len(poses) < 2:
        raise CollisionCheckError(
            f"{name}: {len(poses)} pose(s); a collision check needs at least 2 (velocity)")
    t = (poses.t_ns - poses.t_ns[0]).astype(np.float64) / NS_PER_S
    x, y = poses.position[:, 0].copy(), poses.position[:, 1].copy()
    v = _causal_slopes(t, np.column_stack([x, y]), window)
    if poses.has_orientation:
        yaw = np.unwrap(Rotation.from_quat(poses.quat_xyzw).as_euler("ZYX")[:, 0])
    else:
        moving = np.hypot(v[:, 0], v[:, 1]) > MIN_HEADING_SPEED
        heading = np.arctan2(v[:, 1], v[:, 0])
        idx = np.maximum.accumulate(np.where(moving, np.arange(len(t)), 0))
        yaw = np.unwrap(np.where(moving[idx], heading[idx], 0.0))
    omega = _causal_slopes(t, yaw, window)
    sigma = position_sigma(poses.covariance, len(t), assumed_sigma)
    return MotionState(poses.t_ns.copy(), poses.t_s, x, y, yaw, v[:, 0].copy(),
                       v[:, 1].copy(), omega, sigma)


def predict(state: MotionState, horizon: float, steps: int) -> tuple[F64, F64, F64, F64]:
    """Poses at tau = k horizon / steps, k = 0..steps: (tau (S+1,), x, y, yaw each (N,S+1)).

    Constant velocity and turn rate: p(tau) = p0 + (1/w) [[sin wt, cos wt - 1],
    [1 - cos wt, sin wt]] v0, yaw(tau) = yaw0 + w tau (the straight line as w -> 0).
    """
    tau = np.linspace(0.0, horizon, steps + 1)
    w = state.omega[:, None]
    wt = w * tau[None, :]
    small = np.abs(wt) < 1e-6
    w_safe = np.where(small, 1.0, w)
    a = np.where(small, tau[None, :] - wt * wt * tau[None, :] / 6.0, np.sin(wt) / w_safe)
    b = np.where(small, 0.5 * wt * tau[None, :], (1.0 - np.cos(wt)) / w_safe)
    vx, vy = state.vx[:, None], state.vy[:, None]
    x = state.x[:, None] + a * vx - b * vy
    y = state.y[:, None] + b * vx + a * vy
    yaw = state.yaw[:, None] + wt
    return tau, x, y, yaw
