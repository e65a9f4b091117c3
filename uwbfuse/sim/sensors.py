# SPDX-License-Identifier: BSD-3-Clause
"""Sensor models: IMU (REP-145), wheel odometry and UWB two-way ranging.

Every function takes the scenario, the trajectory timeline, sample times in seconds since
the log start and its own numpy Generator, and returns whole arrays (no per-sample loops).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from uwbfuse.sim.nlos import nlos_excess, segments_blocked, unit_ar1
from uwbfuse.sim.scenarios import Scenario
from uwbfuse.sim.trajectory import Kinematics, Timeline, evaluate

F64 = NDArray[np.float64]
B = NDArray[np.bool_]


# ---------------------------------------------------------------------------------------
# IMU


@dataclass(frozen=True)
class ImuSamples:
    """IMU output and truth at the sample times, all in the IMU frame.

    gyro (N,3) rad/s and accel (N,3) m/s^2 (specific force) as measured; the noiseless
    values; the true biases (N,3) that were added (turn-on constant + random walk).
    """

    gyro: F64
    accel: F64
    gyro_true: F64
    accel_true: F64
    gyro_bias: F64
    accel_bias: F64


def imu_truth(sc: Scenario, kin: Kinematics) -> tuple[F64, F64]:
    """Noiseless (gyro rad/s, specific force m/s^2), each (N,3) in the IMU frame.

    Planar motion: in the base frame the acceleration of the base origin is (dv/dt, v omega,
    0) and the angular velocity (0, 0, omega); the IMU at lever arm r adds the Euler term
    alpha x r and the centripetal term omega x (omega x r); gravity adds +g on base z.
    """
    n = len(kin.v)
    r = np.asarray(sc.imu_in_base[:3], dtype=np.float64)
    w, al = kin.omega, kin.alpha
    f = np.empty((n, 3))
    f[:, 0] = kin.a - al * r[1] - w * w * r[0]
    f[:, 1] = kin.v * w + al * r[0] - w * w * r[1]
    f[:, 2] = sc.gravity
    g = np.zeros((n, 3))
    g[:, 2] = w
    rot = Rotation.from_quat(np.asarray(sc.imu_in_base[3:], dtype=np.float64))
    if not np.allclose(rot.as_matrix(), np.eye(3)):
        f = rot.inv().apply(f)
        g = rot.inv().apply(g)
    return g, f


def _bias(rng: np.random.Generator, n: int, dt: float, sigma0: float, rw: float) -> F64:
    """Turn-on constant N(0, sigma0^2) plus random walk with density rw, (n,3)."""
    b0 = rng.normal(0.0, sigma0, size=3)
    steps = rng.normal(0.0, rw * np.sqrt(dt), size=(n, 3))
    steps[0] = 0.0
    return b0 + np.cumsum(steps, axis=0)


def imu_samples(
    sc: Scenario, kin: Kinematics, rng: np.random.Generator
) -> ImuSamples:
    """MPU6050-grade IMU: truth + bias (constant + random walk) + white noise."""
    n = len(kin.v)
    dt = 1.0 / sc.imu_rate
    g_true, f_true = imu_truth(sc, kin)
    bg = _bias(rng, n, dt, sc.gyro_bias_sigma, sc.gyro_bias_rw)
    ba = _bias(rng, n, dt, sc.accel_bias_sigma, sc.accel_bias_rw)
    sg = sc.gyro_noise_density * np.sqrt(sc.imu_rate)
    sa = sc.accel_noise_density * np.sqrt(sc.imu_rate)
    gyro = g_true + bg + rng.normal(0.0, sg, size=(n, 3))
    accel = f_true + ba + rng.normal(0.0, sa, size=(n, 3))
    return ImuSamples(gyro, accel, g_true, f_true, bg, ba)


# ---------------------------------------------------------------------------------------
# Wheels


@dataclass(frozen=True)
class WheelSamples:
    """Wheel odometry: v (N,) m/s and omega (N,) rad/s as reported, the true interval means,
    the slip mask (N,) and the scale factors (v, omega) that were applied."""

    v: F64
    omega: F64
    v_true: F64
    omega_true: F64
    slip: B
    scale: tuple[float, float]


def wheel_samples(
    sc: Scenario, tl: Timeline, t_s: F64, rng: np.random.Generator, duration_s: float
) -> WheelSamples:
    """Encoder odometry: mean (v, omega) over (t - 1/rate, t], scale error, noise, slip.

    The means are exact (distance and yaw differences over the interval). Encoders read
    exactly zero while the wheels stand still, so noise is added only while moving. A slip
    episode makes one wheel turn faster than the ground: v gains e/2 and omega +-e/track,
    with e = gain * |v|.
    """
    dt = 1.0 / sc.wheel_rate
    k_end = evaluate(tl, t_s, with_position=False)
    k_beg = evaluate(tl, np.maximum(t_s - dt, 0.0), with_position=False)
    span = t_s - np.maximum(t_s - dt, 0.0)
    v_true = (k_end.s - k_beg.s) / span
    w_true = (k_end.yaw - k_beg.yaw) / span
    n = len(t_s)
    scale = np.clip(1.0 + rng.normal(0.0, sc.wheel_scale_sigma, size=2), 0.9, 1.1)
    moving = (np.abs(v_true) > 1e-12) | (np.abs(w_true) > 1e-12)
    v = v_true * scale[0] + moving * rng.normal(0.0, sc.wheel_sigma_v, size=n)
    w = w_true * scale[1] + moving * rng.normal(0.0, sc.wheel_sigma_omega, size=n)
    # slip episodes: Poisson in time, effective only while moving
    n_ep = rng.poisson(sc.slip_rate * duration_s)
    starts = rng.uniform(0.0, duration_s, size=n_ep)
    lens = rng.uniform(*sc.slip_duration, size=n_ep)
    gains = rng.uniform(*sc.slip_gain, size=n_ep)
    sides = rng.choice([-1.0, 1.0], size=n_ep)
    order = np.argsort(starts)
    starts, lens, gains, sides = starts[order], lens[order], gains[order], sides[order]
    # the latest episode started at or before each sample; active while it lasts
    which = np.searchsorted(starts, t_s, side="right") - 1
    wc = np.clip(which, 0, None)
    active = (which >= 0) & (t_s < starts[wc] + lens[wc]) if n_ep else np.zeros(n, dtype=bool)
    slip = active & (np.abs(v_true) > 1e-3)
    if n_ep:
        e = gains[wc] * np.abs(v_true)
        v = v + slip * 0.5 * e
        w = w + slip * sides[wc] * e / sc.wheel_track
    return WheelSamples(v, w, v_true, w_true, slip, (float(scale[0]), float(scale[1])))


# ---------------------------------------------------------------------------------------
# UWB


@dataclass(frozen=True)
class RangeSamples:
    """Ranges after dropouts: stamps t_s (N,) s, anchor index (N,), measured range (N,) m,
    true range (N,) m, NLOS and outlier masks (N,), the NLOS excess that was added (N,) m,
    the per-anchor constant offsets (M,) m, and how many ranges were dropped."""

    t_s: F64
    anchor: NDArray[np.int32]
    range: F64
    true_range: F64
    nlos: B
    outlier: B
    nlos_excess: F64
    anchor_offset: F64
    dropped: int


def tag_positions(sc: Scenario, kin: Kinematics) -> F64:
    """Tag antenna positions (N,3) in the map frame, m."""
    c, s = np.cos(kin.yaw), np.sin(kin.yaw)
    tx, ty, tz = sc.tag_in_base
    out = np.empty((len(c), 3))
    out[:, 0] = kin.position[:, 0] + c * tx - s * ty
    out[:, 1] = kin.position[:, 1] + s * tx + c * ty
    out[:, 2] = sc.base_height + tz
    return out


def uwb_ranges(
    sc: Scenario, tl: Timeline, duration_s: float, rng: np.random.Generator
) -> RangeSamples:
    """Two-way ranges, round robin: slot k at (k + 0.5) / uwb_rate s ranges to anchor k mod M.

    Error model (m): LOS noise N(0, los_sigma^2) on every range; while the 2-D segment tag ->
    anchor crosses an obstacle (NLOS), an excess delay of mean nlos_mean and std nlos_std
    under the law `nlos_excess` (`nlos.nlos_excess`): a slow per-anchor AR(1) part (share
    nlos_corr of the variance, correlation time nlos_tau_s) plus a white part; gross
    outliers (prob. outlier_prob, +-U(outlier_range),
    negative with prob. outlier_negative); constant per-anchor offsets U(+-anchor_offset_max);
    dropouts (dropout_prob, nlos_dropout_prob while NLOS) and an optional outage window.
    """
    anchors = np.array([p for _, p in sc.anchors], dtype=np.float64)
    m = len(anchors)
    n = int(np.floor(duration_s * sc.uwb_rate - 0.5)) + 1 if duration_s > 0 else 0
    t = (np.arange(n) + 0.5) / sc.uwb_rate
    t = t[t < duration_s]
    n = len(t)
    idx = (np.arange(n) % m).astype(np.int32)
    kin = evaluate(tl, t)
    tag = tag_positions(sc, kin)
    a = anchors[idx]
    true_range = np.linalg.norm(a - tag, axis=1)
    nlos = segments_blocked(tag[:, :2], a[:, :2], sc.boxes)

    offsets = rng.uniform(-sc.anchor_offset_max, sc.anchor_offset_max, size=m)
    x_slow = np.empty(n)
    dt_anchor = m / sc.uwb_rate
    for j in range(m):  # one AR(1) per anchor (M is small)
        sel = idx == j
        x_slow[sel] = unit_ar1(rng, int(sel.sum()), dt_anchor, sc.nlos_tau_s)
    x_white = rng.standard_normal(n)
    excess = np.where(nlos, nlos_excess(x_slow, x_white, sc.nlos_mean, sc.nlos_std,
                                        sc.nlos_corr, sc.nlos_excess), 0.0)
    noise = rng.normal(0.0, sc.los_sigma, size=n)
    outlier = rng.random(n) < sc.outlier_prob
    mag = rng.uniform(*sc.outlier_range, size=n)
    sign = np.where(rng.random(n) < sc.outlier_negative, -1.0, 1.0)
    meas = true_range + offsets[idx] + noise + excess + outlier * sign * mag
    meas = np.maximum(meas, 0.01)

    keep = rng.random(n) >= np.where(nlos, sc.nlos_dropout_prob, sc.dropout_prob)
    if sc.outage is not None:
        keep &= ~((t >= sc.outage[0]) & (t < sc.outage[1]))
    return RangeSamples(
        t[keep], idx[keep], meas[keep], true_range[keep], nlos[keep], outlier[keep],
        excess[keep], offsets, int(n - keep.sum()),
    )
