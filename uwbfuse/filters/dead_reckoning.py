# SPDX-License-Identifier: BSD-3-Clause
"""Dead reckoning from the wheels alone (`odom`) or the IMU alone (`imu`).

Without an anchor map (or without ranges) both start with the base frame at the map
origin, heading zero, as the contract says; score them with `uwbfuse eval --align se2` (or
se3). With anchors and ranges, the shared `Initialiser` fixes the start pose from the
sensors (position by multilateration, heading from the first motion) and the dead-reckoned
track is anchored there once (`AnchoredDeadReckoning`); after that no range is used, so
the error growth is that of the wheels or the IMU alone, as in the papers' IMU-only curves.

odom: planar unicycle (its pose covariance grows from zero at the start with the `[wheel]`
  per-sample noise; anchored runs and `imu` report none). Wheel sample k is the mean (v,
  omega) over (t_{k-1}, t_k], so the first sample only fixes the start time. Each interval
  is integrated as a constant-twist arc: yaw at the interval midpoint for the direction of
  travel (midpoint yaw), chord length v dt sinc(omega dt / 2) (exact for a constant twist,
  so a circle closes).

imu: strapdown mechanisation of the IMU point in the map frame, 3-D (or planar, see
  below). Gyro (bias removed) is averaged over each interval (trapezoid) and its rotation
  increments are multiplied with a parallel prefix product (log2(N) vectorised quaternion
  products per batch, no Python loop per sample); specific force is rotated to the map
  frame, gravity (0, 0, -g) added, and velocity and position integrated with cumsum for an
  acceleration linear between samples (exact for constant and linear acceleration).
  Start: a sample shows motion when the gyro norm reaches `init.standstill_gyro_max`, or
  when over the last `MOTION_WINDOW_S` the accel std (norm over axes) reaches
  `init.standstill_accel_std_max` or the accel mean moves away from the mean of all
  earlier samples by more than their noise allows (`MEAN_SHIFT_SIGMAS`). While no
  motion shows, the output is the origin at rest. If the still part (which ends
  `ONSET_GUARD_S` before the first moving sample) lasts `init.standstill_window` or
  more, all its samples give the gyro bias, the accelerometer bias along gravity and
  roll/pitch, and integration starts at rest at its end. Otherwise (a moving start)
  roll/pitch come from the mean accel over the first `init.level_window` seconds (results
  before that window is full are provisional and recomputed each step), the biases are
  zero and the start velocity is zero (unknowable from an IMU alone). On a wheeled vehicle
  (the log has wheel data, `graph.planar` "auto", or "on") vertical acceleration is
  dropped: the vehicle stays on its floor while roll/pitch/yaw remain 3-D.

Output: `estimate()` is the pose at the last `step` time, extrapolated from the last
sample with the last twist (odom) or the last rate and acceleration (imu) for at most
`MAX_EXTRAPOLATION_S`.
"""

from __future__ import annotations

import logging
import math
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from uwbfuse.config import Config
from uwbfuse.constants import (
    MAX_EXTRAPOLATION_S,
    MEAN_SHIFT_FLOOR,
    MEAN_SHIFT_SIGMAS,
    MOTION_WINDOW_S,
    ONSET_GUARD_S,
)
from uwbfuse.errors import EstimatorError
from uwbfuse.estimator import Estimator, EstimatorBase, Method, PoseEstimate
from uwbfuse.filters.models import pose_covariance, unicycle_transition
from uwbfuse.positioning.wheel_track import arc_steps
from uwbfuse.streams import F64, NS_PER_S, AnchorMap, PoseStream

log = logging.getLogger(__name__)






_FOLD_KEEP_NS = 3 * NS_PER_S  # a long still start keeps its last 3 s buffered (> guard + window)


def _qmul(a: F64, b: F64) -> F64:
    """Hamilton products a * b of quaternion arrays (..., 4) in (x, y, z, w) order."""
    ax, ay, az, aw = np.moveaxis(a, -1, 0)
    bx, by, bz, bw = np.moveaxis(b, -1, 0)
    return np.stack(
        [
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
            aw * bw - ax * bx - ay * by - az * bz,
        ],
        axis=-1,
    )


def cumulative_quat_product(q: F64) -> F64:
    """Inclusive prefix products q_0, q_0 q_1, q_0 q_1 q_2, ... of quaternions (N,4) xyzw.

    Hillis-Steele scan: ceil(log2 N) vectorised products instead of N sequential ones.
    """
    out = np.array(q, dtype=np.float64, copy=True)
    k = 1
    while k < len(out):
        out[k:] = _qmul(out[:-k], out[k:])
        k *= 2
    return out / np.linalg.norm(out, axis=1, keepdims=True)


def _yaw_quat(yaw: F64) -> F64:
    """Quaternions (N,4 xyzw) of rotations about z by yaw (N,) rad."""
    half = 0.5 * np.asarray(yaw, dtype=np.float64)
    z = np.zeros_like(half)
    return np.stack([z, z, np.sin(half), np.cos(half)], axis=-1)


def level_rotation(f_base: F64) -> Rotation:
    """R_map_base with yaw 0 whose z axis matches the specific force f_base (3,) m/s^2."""
    fx, fy, fz = (float(v) for v in f_base)
    roll = math.atan2(fy, fz)
    pitch = math.atan2(-fx, math.hypot(fy, fz))
    return Rotation.from_euler("ZYX", [0.0, pitch, roll])


class _Base(EstimatorBase):
    """Shared no-op inputs and output bookkeeping."""

    def __init__(self) -> None:
        self._t_step: int | None = None
        self._pose: PoseEstimate | None = None

    def add_imu(self, t_ns: np.ndarray, gyro: np.ndarray, accel: np.ndarray) -> None:
        """Ignored unless the subclass uses the IMU."""

    def add_wheel(self, t_ns: np.ndarray, v: np.ndarray, omega: np.ndarray) -> None:
        """Ignored unless the subclass uses the wheels."""

    def add_ranges(self, t_ns: np.ndarray, anchor: np.ndarray, rng: np.ndarray) -> None:
        """Dead reckoning never uses ranges."""

    def estimate(self) -> PoseEstimate | None:
        return self._pose

    def finish(self) -> PoseStream | None:
        """Causal outputs are final for dead reckoning."""
        return None


class OdomDeadReckoning(_Base):
    """Planar wheel dead reckoning of the base frame: (x, y, yaw) in the map frame."""

    def __init__(self, sigma_v: float = 0.05, sigma_omega: float = 0.05) -> None:
        super().__init__()
        self._t_last: int | None = None
        self._state = np.zeros(3)  # x, y (m), yaw (rad) at _t_last
        # covariance of _state, grown from zero at the start by the per-sample wheel noise
        # (sigma_v m/s, sigma_omega rad/s: `[wheel]`)
        self._P = np.zeros((3, 3))
        self._sigma = (sigma_v, sigma_omega)
        self._twist = np.zeros(2)  # v (m/s), omega (rad/s) of the last interval
        self._n = 0
        self._path = 0.0
        self._heading_change = 0.0

    def add_wheel(self, t_ns: np.ndarray, v: np.ndarray, omega: np.ndarray) -> None:
        """Integrate a batch: sample k is the mean twist over (t_{k-1}, t_k]."""
        if len(t_ns) == 0:
            return
        t = np.asarray(t_ns, dtype=np.int64)
        v = np.asarray(v, dtype=np.float64)
        w = np.asarray(omega, dtype=np.float64)
        self._n += len(t)
        if self._t_last is None:  # the first sample's interval is unknown: it starts the clock
            self._t_last, self._twist = int(t[0]), np.array([v[0], w[0]])
            t, v, w = t[1:], v[1:], w[1:]
            if len(t) == 0:
                return
        dt = np.diff(t, prepend=self._t_last).astype(np.float64) / NS_PER_S
        dth = w * dt
        yaw_end = self._state[2] + np.cumsum(dth)
        yaw_mid = yaw_end - 0.5 * dth
        dx, dy = arc_steps(v, dt, yaw_end - dth, dth)
        phi, q = unicycle_transition(dx, dy, v, dt, yaw_mid, *self._sigma)
        self._P = phi @ self._P @ phi.T + q
        x = self._state[0] + np.cumsum(dx)
        y = self._state[1] + np.cumsum(dy)
        self._state = np.array([x[-1], y[-1], yaw_end[-1]])
        self._twist = np.array([v[-1], w[-1]])
        self._t_last = int(t[-1])
        self._path += float(np.abs(v * dt).sum())
        self._heading_change += float(dth.sum())

    def step(self, t_ns: int) -> None:
        self._t_step = int(t_ns)
        if self._t_last is None:
            return
        dt = min(max(t_ns - self._t_last, 0) / NS_PER_S, MAX_EXTRAPOLATION_S)
        v, w = self._twist
        x, y, yaw = self._state
        dth = w * dt
        ddx, ddy = arc_steps(np.float64(v), np.float64(dt), yaw, np.float64(dth))
        x += float(ddx)
        y += float(ddy)
        self._pose = PoseEstimate(
            int(t_ns), np.array([x, y, 0.0]), _yaw_quat(np.array(yaw + dth)),
            pose_covariance(self._P, (0, 1, None, None, None, 2)),
        )

    def report(self) -> dict[str, Any]:
        return {
            "wheel samples": self._n,
            "wheel path length [m]": self._path,
            "wheel heading change [deg]": math.degrees(self._heading_change),
        }


class ImuDeadReckoning(_Base):
    """Strapdown IMU dead reckoning; state is the IMU point and attitude in the map frame.

    Start-up modes: "detect" (buffering, every sample still so far: the output is the
    origin at rest, levelled from the samples so far), "level" (moving start, waiting for
    `level_window` seconds of data: provisional, recomputed each step) and "run".
    """

    def __init__(self, config: Config, planar: bool) -> None:
        super().__init__()
        ext = config.extrinsics.imu_in_base
        self._t_bi = np.array(ext[:3], dtype=np.float64)  # IMU position in base, m
        self._r_bi = Rotation.from_quat(ext[3:])  # R_base_imu
        self._init = config.init
        self._g = config.imu.gravity
        self._planar = planar
        self._mode = "detect"
        self._start = ""
        self._bias_g = np.zeros(3)
        self._bias_a = np.zeros(3)
        # Start-up buffer (IMU frame) and the still samples folded out of it.
        self._buf_t = np.zeros(0, dtype=np.int64)
        self._buf_g = np.zeros((0, 3))
        self._buf_f = np.zeros((0, 3))
        self._t_first: int | None = None
        self._f_ref = np.zeros(3)
        self._fold_n = 0
        self._fold_g = np.zeros(3)
        self._fold_df = np.zeros(3)
        self._fold_df2 = np.zeros(3)
        self._checked_from = 0  # buffer stamps below this were judged with full windows
        # Navigation state at _t_last (IMU point, map frame).
        self._t_last = 0
        self._q = np.array([0.0, 0.0, 0.0, 1.0])  # R_map_imu, xyzw
        self._p = np.zeros(3)
        self._v = np.zeros(3)
        self._w_last = np.zeros(3)  # bias-corrected rate, IMU frame, rad/s
        self._a_last = np.zeros(3)  # acceleration, map frame, m/s^2
        self._n = 0

    # ---------------------------------------------------------------- integration
    def _accel_map(self, q: F64, f: F64) -> F64:
        a = Rotation.from_quat(q).apply(f - self._bias_a)
        a[:, 2] -= self._g
        if self._planar:
            a[:, 2] = 0.0
        return a

    def _integrate(self, t: np.ndarray, gyro: F64, accel: F64) -> None:
        """Advance the state over samples t (N,) ns > _t_last (vectorised, see module doc)."""
        if len(t) == 0:
            return
        dt = np.diff(t, prepend=self._t_last).astype(np.float64) / NS_PER_S
        w = gyro - self._bias_g
        w_prev = np.vstack([self._w_last, w[:-1]])
        dq = Rotation.from_rotvec(0.5 * (w_prev + w) * dt[:, None]).as_quat()
        q = cumulative_quat_product(np.vstack([self._q, dq]))[1:]
        a = self._accel_map(q, accel)
        a_prev = np.vstack([self._a_last, a[:-1]])
        v = self._v + np.cumsum(0.5 * (a_prev + a) * dt[:, None], axis=0)
        v_prev = np.vstack([self._v, v[:-1]])
        dp = v_prev * dt[:, None] + (2.0 * a_prev + a) * (dt**2)[:, None] / 6.0
        self._p = self._p + dp.sum(axis=0)
        self._v, self._q = v[-1], q[-1]
        self._w_last, self._a_last = w[-1], a[-1]
        self._t_last = int(t[-1])

    def _start_at(self, t0: int, f_level: F64, w0: F64, f0: F64) -> None:
        """Reset the state at t0: base at the origin, yaw 0, level from f_level, at rest."""
        r_mb = level_rotation(self._r_bi.apply(f_level))
        r_mi = r_mb * self._r_bi
        self._t_last = t0
        self._q = r_mi.as_quat()
        self._p = r_mb.apply(self._t_bi)  # IMU point when the base is at the origin
        self._v = np.zeros(3)
        self._w_last = w0 - self._bias_g
        self._a_last = self._accel_map(self._q[None, :], f0[None, :])[0]

    # ---------------------------------------------------------------- start-up
    def _first_motion(self) -> int:
        """Index of the first buffered sample that shows motion, or len(buffer).

        Moving: gyro norm >= standstill_gyro_max, or over the window (t - MOTION_WINDOW_S,
        t] the accel std (norm over axes) >= standstill_accel_std_max, or the window's mean
        accel is further from the mean of all earlier samples than MEAN_SHIFT_SIGMAS
        standard errors (clamped, see the constants). Vectorised with cumsum.
        """
        cfg = self._init
        t, g, f = self._buf_t, self._buf_g, self._buf_f
        n = len(t)
        k = np.arange(n)
        window_ns = round(MOTION_WINDOW_S * NS_PER_S)
        lo = np.searchsorted(t, t - window_ns, side="right")
        full = t - t[0] >= window_ns  # std of a truncated window (a few samples) is noise
        df = f - self._f_ref
        cs = np.vstack([np.zeros(3), np.cumsum(df, axis=0)])
        cs2 = np.vstack([np.zeros(3), np.cumsum(df**2, axis=0)])
        n_w = (k + 1 - lo)[:, None].astype(np.float64)
        mean_w = (cs[k + 1] - cs[lo]) / n_w
        var_w = (cs2[k + 1] - cs2[lo]) / n_w - mean_w**2
        std_w = np.sqrt(np.maximum(var_w, 0.0).sum(axis=1))
        n_p = (self._fold_n + lo)[:, None].astype(np.float64)
        mean_p = (self._fold_df + cs[lo]) / np.maximum(n_p, 1.0)
        var_p = (self._fold_df2 + cs2[lo]) / np.maximum(n_p, 1.0) - mean_p**2
        sigma_p = np.sqrt(np.maximum(var_p, 0.0).sum(axis=1))
        shift_max = np.clip(
            MEAN_SHIFT_SIGMAS * sigma_p / np.sqrt(n_w[:, 0]),
            MEAN_SHIFT_FLOOR,
            cfg.standstill_accel_std_max,
        )
        shift = np.linalg.norm(mean_w - mean_p, axis=1)
        moving = (
            (np.linalg.norm(g, axis=1) >= cfg.standstill_gyro_max)
            | ((std_w >= cfg.standstill_accel_std_max) & full)
            | ((shift >= shift_max) & (n_p[:, 0] >= n_w[:, 0]))
        )
        moving &= t >= self._checked_from
        return int(np.argmax(moving)) if moving.any() else n

    def _still_means(self, stop: int) -> tuple[F64, F64, int]:
        """Mean gyro and mean accel (IMU frame) over folded + buffer[:stop] samples, count."""
        n = self._fold_n + stop
        sum_g = self._fold_g + self._buf_g[:stop].sum(axis=0)
        sum_df = self._fold_df + (self._buf_f[:stop] - self._f_ref).sum(axis=0)
        return sum_g / n, self._f_ref + sum_df / n, n

    def _set_still_biases(self, stop: int) -> F64:
        """Gyro bias and accel bias along gravity from the still samples; returns mean accel."""
        self._bias_g, f, _ = self._still_means(stop)
        f_norm = float(np.linalg.norm(f))
        self._bias_a = (f_norm - self._g) * f / max(f_norm, 1e-9)
        return f

    def _fold(self) -> None:
        """Move old still samples out of the buffer into the running sums (bounded memory)."""
        t = self._buf_t
        if len(t) == 0 or t[-1] - t[0] < 2 * _FOLD_KEEP_NS:
            return
        stop = int(np.searchsorted(t, t[-1] - _FOLD_KEEP_NS, side="left"))
        self._fold_n += stop
        self._fold_g = self._fold_g + self._buf_g[:stop].sum(axis=0)
        df = self._buf_f[:stop] - self._f_ref
        self._fold_df = self._fold_df + df.sum(axis=0)
        self._fold_df2 = self._fold_df2 + (df**2).sum(axis=0)
        self._buf_t, self._buf_g, self._buf_f = t[stop:], self._buf_g[stop:], self._buf_f[stop:]
        self._checked_from = int(self._buf_t[0]) + round(MOTION_WINDOW_S * NS_PER_S)

    def _clear_buffer(self) -> None:
        self._buf_t = np.zeros(0, dtype=np.int64)
        self._buf_g = np.zeros((0, 3))
        self._buf_f = np.zeros((0, 3))

    def _detect(self) -> None:
        """Still or moving start? Sets the state (final: mode "run"; else provisional)."""
        cfg = self._init
        t, g, f = self._buf_t, self._buf_g, self._buf_f
        if self._t_first is None or len(t) == 0:
            return
        m = self._first_motion()
        if m == len(t):  # still so far: at rest at the origin, levelled from all samples
            f_mean = self._set_still_biases(len(t))
            self._start_at(int(t[-1]), f_mean, g[-1], f[-1])
            if t[-1] - self._t_first >= round(cfg.standstill_window * NS_PER_S):
                self._fold()
            return
        # Motion shows at m; it may have begun up to ONSET_GUARD_S before.
        stop = int(np.searchsorted(t, t[m] - round(ONSET_GUARD_S * NS_PER_S), side="right"))
        t_still_end = int(t[stop - 1]) if stop > 0 else None
        still_ns = (t_still_end - self._t_first) if t_still_end is not None else -1
        if self._fold_n > 0 or still_ns >= round(cfg.standstill_window * NS_PER_S):
            stop = max(stop, 1)
            f_mean = self._set_still_biases(stop)
            self._start = "still"
            log.debug("imu: still start, %.2f s still", (t[stop - 1] - self._t_first) / NS_PER_S)
            self._start_at(int(t[stop - 1]), f_mean, g[stop - 1], f[stop - 1])
            self._integrate(t[stop:], g[stop:], f[stop:])
            self._mode = "run"
            self._clear_buffer()
            return
        self._mode = "level"
        log.debug("imu: moving start (motion after %.2f s)", (t[m] - self._t_first) / NS_PER_S)
        self._level()

    def _level(self) -> None:
        """Moving start: level from the first level_window seconds, zero biases, at rest."""
        t, g, f = self._buf_t, self._buf_g, self._buf_f
        level_ns = round(self._init.level_window * NS_PER_S)
        sel = t <= t[0] + level_ns
        self._bias_g = np.zeros(3)
        self._bias_a = np.zeros(3)
        self._start = "moving"
        self._start_at(int(t[0]), f[sel].mean(axis=0), g[0], f[0])
        self._integrate(t[1:], g[1:], f[1:])
        if t[-1] - t[0] >= level_ns:
            self._mode = "run"
            self._clear_buffer()

    # ---------------------------------------------------------------- streaming API
    def add_imu(self, t_ns: np.ndarray, gyro: np.ndarray, accel: np.ndarray) -> None:
        if len(t_ns) == 0:
            return
        t = np.asarray(t_ns, dtype=np.int64)
        gyro = np.asarray(gyro, dtype=np.float64)
        accel = np.asarray(accel, dtype=np.float64)
        self._n += len(t)
        if self._mode == "run":
            self._integrate(t, gyro, accel)
            return
        if self._t_first is None:
            self._t_first, self._f_ref = int(t[0]), accel[0].copy()
        self._buf_t = np.concatenate([self._buf_t, t])
        self._buf_g = np.vstack([self._buf_g, gyro])
        self._buf_f = np.vstack([self._buf_f, accel])

    def step(self, t_ns: int) -> None:
        self._t_step = int(t_ns)
        if self._t_first is None:
            return
        if self._mode == "detect":
            self._detect()
        elif self._mode == "level":
            self._level()
        dt = min(max(t_ns - self._t_last, 0) / NS_PER_S, MAX_EXTRAPOLATION_S)
        r_mi = Rotation.from_quat(self._q) * Rotation.from_rotvec(self._w_last * dt)
        p_i = self._p + self._v * dt + 0.5 * self._a_last * dt * dt
        r_mb = r_mi * self._r_bi.inv()
        p_b = p_i - r_mb.apply(self._t_bi)
        self._pose = PoseEstimate(int(t_ns), p_b, r_mb.as_quat())

    def report(self) -> dict[str, Any]:
        return {
            "imu samples": self._n,
            "imu start": self._start or "still (no motion seen)",
            "planar": self._planar,
            "gyro bias [rad/s]": [float(x) for x in self._bias_g],
            "accel bias [m/s^2]": [float(x) for x in self._bias_a],
        }


def _matrix(position: F64, quat_xyzw: F64) -> F64:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat(quat_xyzw).as_matrix()
    T[:3, 3] = position
    return T


class AnchoredDeadReckoning(EstimatorBase):
    """Dead reckoning started at the pose the `Initialiser` finds from the sensors.

    Until the initialiser succeeds the output is None; at that epoch t_i the map pose is
    T_map_base(t) = T_init * inv(T_dr(t_i)) * T_dr(t): the dead-reckoned motion since t_i
    applied to the initial pose. Ranges reach only the initialiser.
    """

    def __init__(self, inner: OdomDeadReckoning | ImuDeadReckoning, initialiser: Any) -> None:
        self.inner = inner
        self.initialiser = initialiser
        self._offset: F64 | None = None  # T_init * inv(T_dr(t_i))
        self._init_t_ns: int | None = None

    def add_imu(self, t_ns: np.ndarray, gyro: np.ndarray, accel: np.ndarray) -> None:
        self.inner.add_imu(t_ns, gyro, accel)
        if self._offset is None:
            self.initialiser.add_imu(t_ns, gyro, accel)

    def add_wheel(self, t_ns: np.ndarray, v: np.ndarray, omega: np.ndarray) -> None:
        self.inner.add_wheel(t_ns, v, omega)
        if self._offset is None:
            self.initialiser.add_wheel(t_ns, v, omega)

    def add_ranges(self, t_ns: np.ndarray, anchor: np.ndarray, rng: np.ndarray) -> None:
        if self._offset is None:
            self.initialiser.add_ranges(t_ns, anchor, rng)

    def step(self, t_ns: int) -> None:
        self.inner.step(t_ns)
        if self._offset is not None:
            return
        state = self.initialiser.try_initialise(t_ns)
        dr = self.inner.estimate()
        if state is None or dr is None:
            return
        T_init = np.eye(4)
        T_init[:3, :3] = state.R_map_base
        T_init[:3, 3] = state.position
        self._offset = T_init @ np.linalg.inv(_matrix(dr.position, dr.quat_xyzw))
        self._init_t_ns = t_ns
        self.initialiser = None  # its buffers are no longer needed

    def estimate(self) -> PoseEstimate | None:
        dr = self.inner.estimate()
        if self._offset is None or dr is None:
            return None
        T = self._offset @ _matrix(dr.position, dr.quat_xyzw)
        return PoseEstimate(dr.t_ns, T[:3, 3].copy(), Rotation.from_matrix(T[:3, :3]).as_quat())

    def finish(self) -> PoseStream | None:
        return None

    def report(self) -> dict[str, Any]:
        out = {"start": "initialiser (UWB fix + heading from first motion)",
               "init_t_ns": self._init_t_ns}
        out.update(self.inner.report())
        return out


def make(
    method: Method, config: Config, anchors: AnchorMap | None, streams: frozenset[str]
) -> Estimator:
    """Dead-reckoning estimator for Method.ODOM or Method.IMU.

    With anchors and ranges the start pose comes from the `Initialiser`; otherwise the
    map origin with heading zero.
    """
    if method is Method.ODOM:
        inner: OdomDeadReckoning | ImuDeadReckoning = OdomDeadReckoning(
            config.wheel.sigma_v, config.wheel.sigma_omega)
    elif method is Method.IMU:
        planar_cfg = config.graph.planar
        planar = planar_cfg == "on" or (planar_cfg == "auto" and "wheel" in streams)
        inner = ImuDeadReckoning(config, planar)
    else:
        raise EstimatorError(f"dead reckoning has no method {method.value!r}")
    if anchors is None or len(anchors) == 0 or "uwb" not in streams:
        return inner
    from uwbfuse.filters.base import default_initialiser

    # dead reckoning never corrects its heading: its start waits until it is pinned down
    return AnchoredDeadReckoning(inner, default_initialiser(config, anchors, streams,
                                                            corrects_heading=False))
