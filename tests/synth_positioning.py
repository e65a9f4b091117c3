# SPDX-License-Identifier: BSD-3-Clause
"""Synthetic sensor logs with exact truth for the positioning and initialisation tests.

A trajectory is given as functions of time (position of the base origin, yaw, and for
3-D motion roll/pitch); sensors are derived numerically on a 1 kHz grid: IMU specific force
and body rates, wheel speeds as interval means, round-robin UWB ranges to the tag antenna.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from uwbfuse.streams import (
    NS_PER_S,
    AnchorMap,
    ImuStream,
    PoseStream,
    RangeStream,
    SensorLog,
    WheelStream,
)

ROOM = AnchorMap(
    ("A1", "A2", "A3", "A4"),
    np.array([[0, 0, 1.5], [0, 6, 1.5], [5, 0, 1.5], [5, 6, 1.5]], dtype=np.float64),
)
WAREHOUSE = AnchorMap(
    ("W1", "W2", "W3", "W4", "W5", "W6"),
    np.array(
        [[0, 0, 4.0], [40, 0, 4.0], [0, 20, 4.0], [40, 20, 4.0], [20, 0, 5.0], [20, 20, 5.0]],
        dtype=np.float64,
    ),
)


def smoothstep(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3 - 2 * x)


@dataclass
class Motion:
    """A trajectory: pos(t) (N,3) base origin (map, m) and rot(t) (N,3,3) R_map_base."""

    pos: Callable[[np.ndarray], np.ndarray]
    rot: Callable[[np.ndarray], np.ndarray]


def planar_drive(
    start: tuple[float, float], yaw0: float, still_s: float, speed: float = 0.6,
    turn_rate: float = 0.25, z: float = 0.0,
) -> Motion:
    """Still for still_s, smooth acceleration to `speed`, then a gentle constant-rate turn.

    Built by integrating v(t), omega(t) on a fine grid (exact to the grid's accuracy).
    """
    grid = np.arange(0.0, 200.0, 1e-3)
    ramp = smoothstep((grid - still_s) / 2.0)
    v = speed * ramp
    om = turn_rate * smoothstep((grid - still_s - 3.0) / 2.0) * np.sin(0.15 * (grid - still_s))
    yaw = yaw0 + np.concatenate([[0.0], np.cumsum(0.5 * (om[1:] + om[:-1]) * 1e-3)])
    vx, vy = v * np.cos(yaw), v * np.sin(yaw)
    x = start[0] + np.concatenate([[0.0], np.cumsum(0.5 * (vx[1:] + vx[:-1]) * 1e-3)])
    y = start[1] + np.concatenate([[0.0], np.cumsum(0.5 * (vy[1:] + vy[:-1]) * 1e-3)])

    def pos(t: np.ndarray) -> np.ndarray:
        return np.column_stack([np.interp(t, grid, x), np.interp(t, grid, y), np.full(len(t), z)])

    def rot(t: np.ndarray) -> np.ndarray:
        return Rotation.from_euler("z", np.interp(t, grid, yaw)[:, None]).as_matrix()

    return Motion(pos, rot)


def handheld_3d(start: tuple[float, float, float], yaw0: float, still_s: float) -> Motion:
    """A walking-like 3-D motion: smooth start, curving path, bobbing height, tilting."""

    def s(t: np.ndarray) -> np.ndarray:
        u = t - still_s
        return np.where(u > 0, 0.8 * (u - 2.0 * (1 - np.exp(-np.maximum(u, 0) / 2.0))), 0.0)

    def pos(t: np.ndarray) -> np.ndarray:
        d = s(t)
        heading = yaw0 + 0.08 * d
        # integrate heading along arc length numerically via fine grid
        g = np.linspace(0, max(float(np.max(d)), 1e-6), 4000)
        hx = np.concatenate([[0.0], np.cumsum(np.cos(yaw0 + 0.08 * g[1:]) * np.diff(g))])
        hy = np.concatenate([[0.0], np.cumsum(np.sin(yaw0 + 0.08 * g[1:]) * np.diff(g))])
        del heading
        z = start[2] + 0.05 * np.sin(2.0 * t) * smoothstep(t - still_s)
        return np.column_stack([start[0] + np.interp(d, g, hx), start[1] + np.interp(d, g, hy), z])

    def rot(t: np.ndarray) -> np.ndarray:
        d = s(t)
        yaw = yaw0 + 0.08 * d + 0.2 * np.sin(0.7 * t) * smoothstep(t - still_s)
        roll = 0.05 + 0.1 * np.sin(1.3 * t) * smoothstep(t - still_s)
        pitch = -0.04 + 0.08 * np.sin(0.9 * t) * smoothstep(t - still_s)
        return Rotation.from_euler("ZYX", np.column_stack([yaw, pitch, roll])).as_matrix()

    return Motion(pos, rot)


def make_log(
    motion: Motion,
    anchors: AnchorMap,
    duration: float,
    *,
    seed: int = 0,
    lever: tuple[float, float, float] = (0.1, 0.0, 0.3),
    imu: bool = True,
    wheel: bool = True,
    uwb: bool = True,
    range_sigma: float = 0.05,
    range_rate: float = 40.0,
    gyro_bias: tuple[float, float, float] = (0.003, -0.002, 0.004),
    accel_bias: tuple[float, float, float] = (0.02, -0.03, 0.04),
    gyro_noise: float = 0.002,
    accel_noise: float = 0.03,
    wheel_noise: float = 0.01,
    t0_ns: int = 1_700_000_000 * NS_PER_S,
    nlos: np.ndarray | None = None,
) -> tuple[SensorLog, np.ndarray]:
    """A SensorLog of `motion` plus the per-range NLOS mask (all False unless `nlos`).

    nlos: (M,) per-anchor positive bias in metres added to every range of that anchor with
    probability 0.5 (exponential magnitude), for the weighted-LS tests.
    """
    rng = np.random.default_rng(seed)
    dt = 1e-3
    tg = np.arange(0.0, duration + dt / 2, dt)
    p = motion.pos(tg)
    r = motion.rot(tg)
    g = 9.81
    v = np.gradient(p, dt, axis=0)
    a = np.gradient(v, dt, axis=0)
    f_base = np.einsum("nji,nj->ni", r, a + np.array([0, 0, g]))
    rel = np.einsum("nji,njk->nik", r[:-1], r[1:])
    w = Rotation.from_matrix(rel).as_rotvec() / dt
    w = np.vstack([w, w[-1:]])
    log = SensorLog(anchors=anchors if uwb else None, source="synthetic")
    if imu:
        step = 10  # 100 Hz
        ti = np.arange(step, len(tg), step)
        # Rate over (t_{k-1}, t_k] as the mean body rate of the interval.
        gyro = np.add.reduceat(w, np.arange(0, len(tg) - step, step))[: len(ti)] / step
        acc = f_base[ti]
        gyro = gyro + np.asarray(gyro_bias) + rng.normal(0, gyro_noise, gyro.shape)
        acc = acc + np.asarray(accel_bias) + rng.normal(0, accel_noise, acc.shape)
        log.imu = ImuStream((t0_ns + tg[ti] * NS_PER_S).astype(np.int64), gyro, acc)
    if wheel:
        step = 20  # 50 Hz
        tw = np.arange(step, len(tg), step)
        v_base = np.einsum("nji,nj->ni", r, v)
        seg = np.arange(0, len(tg) - step, step)
        vm = np.add.reduceat(v_base[:, 0], seg)[: len(tw)] / step
        om = np.add.reduceat(w[:, 2], seg)[: len(tw)] / step
        vm = vm + rng.normal(0, wheel_noise, vm.shape) * (np.abs(vm) > 1e-3)
        om = om + rng.normal(0, wheel_noise, om.shape) * (np.abs(vm) > 1e-3)
        log.wheel = WheelStream((t0_ns + tg[tw] * NS_PER_S).astype(np.int64), vm, om)
    mask = np.zeros(0, dtype=bool)
    if uwb:
        tr = np.arange(0.05, duration, 1.0 / range_rate)
        m = len(anchors)
        an = (np.arange(len(tr)) % m).astype(np.int32)
        idx = np.clip(np.round(tr / dt).astype(int), 0, len(tg) - 1)
        tag = p[idx] + np.einsum("nij,j->ni", r[idx], np.asarray(lever))
        true = np.linalg.norm(tag - anchors.positions[an], axis=1)
        meas = true + rng.normal(0, range_sigma, len(tr))
        mask = np.zeros(len(tr), dtype=bool)
        if nlos is not None:
            mask = (np.asarray(nlos)[an] > 0) & (rng.random(len(tr)) < 0.5)
            meas = meas + mask * rng.exponential(np.asarray(nlos)[an])
        log.ranges = RangeStream((t0_ns + tr * NS_PER_S).astype(np.int64), an, meas)
    tt = np.arange(0, len(tg), 10)
    log.ground_truth = PoseStream(
        (t0_ns + tg[tt] * NS_PER_S).astype(np.int64), p[tt], Rotation.from_matrix(r[tt]).as_quat()
    )
    return log, mask


def truth_at(log: SensorLog, t_ns: int) -> tuple[np.ndarray, float, np.ndarray]:
    """Ground-truth (position (3,), yaw rad, R (3,3)) at t_ns (nearest sample)."""
    gt = log.ground_truth
    assert gt is not None
    k = int(np.argmin(np.abs(gt.t_ns - t_ns)))
    rm = Rotation.from_quat(gt.quat_xyzw[k]).as_matrix()
    return gt.position[k], float(np.arctan2(rm[1, 0], rm[0, 0])), rm
