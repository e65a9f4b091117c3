# SPDX-License-Identifier: BSD-3-Clause
"""Method `lkf`: loosely coupled constant-velocity Kalman filter on WLS fixes.

The INS-UWB AGV paper's filter: state X = [x, vx, y, vy] (plus [z, vz] for 3-D fixes),
transition Theta = blockdiag([[1, T], [0, 1]]), white-acceleration process noise
Gamma Q Gamma^T (here the exact discretisation with spectral density `lkf.accel_psd`,
m^2/s^3), measurement Z = H X + v with H picking the positions and R the fix covariance of
`uwbfuse.filters.wls.EpochFixer` (NLOS-weighted least squares per epoch). filterpy
vocabulary: `x`, `P`, `predict(dt)`, `update(z, R)`, innovation `y`, `S`, gain `K`, Joseph
form covariance update.

Fixes whose normalised innovation squared exceeds the chi-square quantile
`ekf.gate_probability` are rejected when `ekf.gating` is on; after `_RESET_S` seconds of
only rejected fixes the filter restarts at the latest fix (no lock-out). After `_COAST_S`
seconds without an accepted fix the velocity is zeroed: through a range outage (Plaza1 has
97 s without ranges) the track holds its place instead of coasting away.

The state is the tag antenna; the pose written is the base: yaw is the track direction of
the filtered positions over the last `wls.min_track` metres (held while standing), roll
and pitch zero, the lever arm `tag_in_base` removed (`TrackHeading.base_position`).
UWB only: IMU and wheel batches are ignored.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from uwbfuse.config import Config
from uwbfuse.errors import AnchorMapError
from uwbfuse.estimator import EstimatorBase, Method, PoseEstimate
from uwbfuse.filters.models import gate_threshold, pose_covariance
from uwbfuse.filters.wls import EpochFixer, TagFix, TrackHeading, yaw_quat
from uwbfuse.streams import NS_PER_S, AnchorMap, PoseStream

_RESET_S = 2.0  # seconds of rejected fixes after which the filter restarts at a fix
_V0_SIGMA = 1.0  # initial velocity std, m/s
_R_FLOOR = 0.02  # floor on the fix std in R, m
_COAST_S = 2.0  # without an accepted fix for this long the velocity is zeroed (hold), s


class ConstantVelocityKF:
    """Linear KF, state [p1, v1, p2, v2, ...] per axis (m, m/s), `dim` position axes."""

    def __init__(self, dim: int, accel_psd: float) -> None:
        self.dim = dim
        self.q = accel_psd
        self.x = np.zeros(2 * dim)
        self.P = np.eye(2 * dim)
        self.H = np.zeros((dim, 2 * dim))
        self.H[np.arange(dim), 2 * np.arange(dim)] = 1.0
        self.y = np.zeros(dim)
        self.S = np.eye(dim)
        self.K = np.zeros((2 * dim, dim))

    def reset(self, position: np.ndarray, cov: np.ndarray, v_sigma: float = _V0_SIGMA) -> None:
        """Start at `position` (dim,) with covariance `cov` (dim,dim), velocity 0 +- v_sigma."""
        self.x = np.zeros(2 * self.dim)
        self.x[0::2] = position[: self.dim]
        self.P = np.zeros((2 * self.dim, 2 * self.dim))
        idx = 2 * np.arange(self.dim)
        self.P[np.ix_(idx, idx)] = cov
        self.P[idx + 1, idx + 1] = v_sigma**2

    def predict(self, dt: float) -> None:
        """Propagate by dt seconds: x = F x, P = F P F^T + Q (white acceleration)."""
        if dt <= 0:
            return
        f1 = np.array([[1.0, dt], [0.0, 1.0]])
        q1 = self.q * np.array([[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]])
        eye = np.eye(self.dim)
        f = np.kron(eye, f1)
        self.x = f @ self.x
        self.P = f @ self.P @ f.T + np.kron(eye, q1)

    def innovation(self, z: np.ndarray, r: np.ndarray) -> float:
        """Set y and S for measurement z (dim,) with covariance r; return the NIS."""
        self.y = z[: self.dim] - self.H @ self.x
        self.S = self.H @ self.P @ self.H.T + r
        return float(self.y @ np.linalg.solve(self.S, self.y))

    def update(self, z: np.ndarray, r: np.ndarray) -> None:
        """Kalman update with position z (dim,), covariance r (dim,dim); Joseph form."""
        self.innovation(z, r)
        self.K = np.linalg.solve(self.S, self.H @ self.P).T
        self.x = self.x + self.K @ self.y
        ikh = np.eye(2 * self.dim) - self.K @ self.H
        self.P = ikh @ self.P @ ikh.T + self.K @ r @ self.K.T

    @property
    def position(self) -> np.ndarray:
        return self.x[0::2]

    @property
    def velocity(self) -> np.ndarray:
        return self.x[1::2]


class LkfEstimator(EstimatorBase):
    """Streaming loosely coupled CV Kalman filter on WLS fixes (see module doc)."""

    def __init__(self, config: Config, anchors: AnchorMap, streams: frozenset[str]) -> None:
        self.config = config
        self.fixer = EpochFixer(config, anchors, streams)
        self.kf = ConstantVelocityKF(self.fixer.dim, config.lkf.accel_psd)
        self.lever = np.asarray(config.extrinsics.tag_in_base, dtype=np.float64)
        self.gate = (
            gate_threshold(config.filter.gate_probability, self.fixer.dim)
            if config.filter.gating else math.inf
        )
        self.heading = TrackHeading(config.wls.min_track)
        self._t_ns: int | None = None
        self._last_accept_ns: int | None = None
        self._yaw = 0.0
        self._est: PoseEstimate | None = None
        self.n_updates = 0
        self.n_rejected = 0
        self.n_resets = 0

    def add_imu(self, t_ns: np.ndarray, gyro: np.ndarray, accel: np.ndarray) -> None:
        """Ignored: the LKF is UWB only."""

    def add_wheel(self, t_ns: np.ndarray, v: np.ndarray, omega: np.ndarray) -> None:
        """Ignored: the LKF is UWB only."""

    def add_ranges(self, t_ns: np.ndarray, anchor: np.ndarray, rng: np.ndarray) -> None:
        self.fixer.add_ranges(t_ns, anchor, rng)

    def _r(self, fx: TagFix) -> np.ndarray:
        cov = np.nan_to_num(fx.cov, nan=1.0)
        return cov + _R_FLOOR**2 * np.eye(self.fixer.dim)

    def step(self, t_ns: int) -> None:
        fx = self.fixer.fix(t_ns, only_new=True)
        if self._t_ns is None:
            if fx is None:
                return
            self.kf.reset(fx.position, self._r(fx))
            self._t_ns = self._last_accept_ns = int(t_ns)
        else:
            assert self._last_accept_ns is not None
            if t_ns - self._last_accept_ns > _COAST_S * NS_PER_S:
                # Ranges gone (outage, shadow): constant velocity would carry the track
                # away at the last speed for as long as the gap lasts; hold the position.
                self.kf.x[1::2] = 0.0
            self.kf.predict((t_ns - self._t_ns) / NS_PER_S)
            self._t_ns = int(t_ns)
            if fx is not None:
                r = self._r(fx)
                nis = self.kf.innovation(fx.position, r)
                if nis <= self.gate:
                    self.kf.update(fx.position, r)
                    self.n_updates += 1
                    self._last_accept_ns = int(t_ns)
                else:
                    self.n_rejected += 1
                    if t_ns - self._last_accept_ns > _RESET_S * NS_PER_S:
                        self.kf.reset(fx.position, r)
                        self.n_resets += 1
                        self._last_accept_ns = int(t_ns)
        self._yaw = self.heading.update(t_ns / NS_PER_S, self.kf.position)
        tag = np.zeros(3)
        tag[: self.fixer.dim] = self.kf.position
        if self.fixer.dim == 2:
            tag[2] = self.fixer.tag_z
        pos_idx = (0, 2, 4) if self.fixer.dim == 3 else (0, 2, None)
        cov = pose_covariance(self.kf.P, (*pos_idx, None, None, None))
        self._est = PoseEstimate(int(t_ns), self.heading.base_position(tag, self.lever),
                                 yaw_quat(self._yaw), cov)

    def estimate(self) -> PoseEstimate | None:
        return self._est

    def finish(self) -> PoseStream | None:
        return None

    def report(self) -> dict[str, Any]:
        out = self.fixer.report()
        out.update(updates=self.n_updates, rejected_fixes=self.n_rejected, resets=self.n_resets)
        return out


def make(
    method: Method, config: Config, anchors: AnchorMap | None, streams: frozenset[str]
) -> LkfEstimator:
    """Factory for `Method.LKF`."""
    if anchors is None or not len(anchors):
        raise AnchorMapError(f"method {method.value} needs an anchor map")
    return LkfEstimator(config, anchors, streams)
