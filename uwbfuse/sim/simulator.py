# SPDX-License-Identifier: BSD-3-Clause
"""Simulate a contract log (IMU, wheels, UWB ranges, anchors, ground truth) with known truth.

`simulate` returns the `SensorLog` that `uwbfuse simulate` writes; `simulate_with_truth`
also returns what only a simulator knows (true ranges, NLOS/outlier masks, biases, slip) for
testing estimators. Both are deterministic in `seed`: each sensor draws from its own child
of `numpy.random.SeedSequence(seed)`, so changing one sensor model leaves the others' noise
unchanged.

Timing: the IMU samples at k / imu_rate (k = 0, 1, ...), wheels at k / wheel_rate (k >= 1,
the mean over the preceding interval), ranges at (k + 0.5) / uwb_rate, all in seconds after
`t0_ns` (stamps in integer nanoseconds). Ground truth is the base-frame pose at the IMU
stamps.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from uwbfuse.config import MapConfig
from uwbfuse.constants import NLOS_EXCESS_LAWS
from uwbfuse.errors import SimulationError
from uwbfuse.sim.lidar import LidarPoses, lidar_poses
from uwbfuse.sim.scenarios import SCENARIOS, Scenario, get_scenario
from uwbfuse.sim.sensors import (
    ImuSamples,
    RangeSamples,
    WheelSamples,
    imu_samples,
    uwb_ranges,
    wheel_samples,
)
from uwbfuse.sim.signal import signal_powers
from uwbfuse.sim.trajectory import MotionParams, Timeline, build_timeline, evaluate
from uwbfuse.streams import (
    NS_PER_S,
    AnchorMap,
    ImuStream,
    PoseStream,
    RangeStream,
    SensorLog,
    WheelStream,
)

__all__ = ["SCENARIOS", "SimResult", "simulate", "simulate_with_truth"]

log = logging.getLogger(__name__)

POWER_STREAM = 10  # spawn key of the signal powers' random stream

F64 = NDArray[np.float64]
B = NDArray[np.bool_]


@dataclass(frozen=True)
class SimResult:
    """A simulated log and its hidden truth. Arrays align with the log's streams.

    Ranges (one per `log.ranges` row): true_range m (tag antenna to anchor), nlos and
    outlier masks, nlos_excess m (added NLOS delay, 0 when LOS), rx_dbm / fp_dbm the total
    and first-path powers (dBm, also when the log does not carry them); anchor_offset (M,)
    m is the constant per-anchor offset. IMU (one per `log.imu` row, IMU frame): accel_bias
    m/s^2 and gyro_bias rad/s (turn-on + random walk), the noiseless imu_accel/imu_gyro.
    Truth at the IMU stamps: velocity (N,3) m/s of the base in the map frame, yaw rad
    (unwrapped), moving mask. Wheels (one per `log.wheel` row): slip mask, true interval
    means wheel_v_true m/s and wheel_omega_true rad/s, wheel_scale (v, omega).
    standstill_ns: the initial standstill [start, end) in stamp ns, or None;
    still_intervals_ns: every standstill of the log.
    """

    log: SensorLog
    scenario: Scenario
    true_range: F64
    nlos: B
    outlier: B
    nlos_excess: F64
    anchor_offset: F64
    ranges_dropped: int
    accel_bias: F64
    gyro_bias: F64
    imu_accel: F64
    imu_gyro: F64
    velocity: F64
    yaw: F64
    moving: B
    wheel_slip: B
    wheel_v_true: F64
    wheel_omega_true: F64
    wheel_scale: tuple[float, float]
    standstill_ns: tuple[int, int] | None
    still_intervals_ns: tuple[tuple[int, int], ...]
    timeline: Timeline
    rx_dbm: F64 | None = None
    fp_dbm: F64 | None = None
    pose_wrong: B | None = None  # per `log.pose` row: a wrong match (None: no poses)

    @property
    def nlos_fraction(self) -> float:
        """Share of the delivered ranges that are NLOS."""
        return float(np.mean(self.nlos)) if len(self.nlos) else 0.0


def _validate(sc: Scenario, duration_s: float) -> None:
    if not (math.isfinite(duration_s) and duration_s > 0):
        raise SimulationError(f"duration must be positive, got {duration_s}")
    for name in ("imu_rate", "wheel_rate", "uwb_rate", "speed", "accel", "spin_rate"):
        if not getattr(sc, name) > 0:
            raise SimulationError(f"{name} must be positive, got {getattr(sc, name)}")
    if sc.still_start_s < 0:
        raise SimulationError("still_start_s must be >= 0")
    if len(sc.anchors) < 1:
        raise SimulationError("a scenario needs at least one anchor")
    bad = set(sc.streams) - {"imu", "wheel", "uwb", "pose"}
    if bad or not sc.streams:
        raise SimulationError(
            f"streams must be a non-empty subset of imu, wheel, uwb, pose: {bad}")
    if sc.nlos_excess not in NLOS_EXCESS_LAWS:
        raise SimulationError(
            f"nlos_excess must be one of {', '.join(NLOS_EXCESS_LAWS)}, got {sc.nlos_excess!r}")
    if "pose" in sc.streams and not sc.pose_rate > 0:
        raise SimulationError(f"pose_rate must be positive, got {sc.pose_rate}")


def site_map(sc: Scenario) -> MapConfig:
    """The scenario's electronic map: its shelves (boxes) and mapped low obstacles."""
    return MapConfig(obstacles=[
        [(b.xmin, b.ymin), (b.xmax, b.ymin), (b.xmax, b.ymax), (b.xmin, b.ymax)]
        for b in (*sc.boxes, *sc.map_boxes)])


def _to_ns(t0_ns: int, t_s: F64) -> NDArray[np.int64]:
    return t0_ns + np.round(t_s * NS_PER_S).astype(np.int64)


def _still_intervals(tl: Timeline, duration_s: float) -> list[tuple[float, float]]:
    still = (tl.v0 == 0) & (tl.v1 == 0) & (tl.dtheta == 0)
    out = []
    for a, d in zip(tl.t0[still], tl.dur[still], strict=True):
        lo = max(a - tl.time_offset, 0.0)
        hi = min(a + d - tl.time_offset, duration_s)
        if hi > lo:
            out.append((float(lo), float(hi)))
    return out


def simulate_with_truth(
    scenario: str | Scenario = "warehouse",
    duration_s: float = 120.0,
    seed: int = 0,
    **overrides: Any,
) -> SimResult:
    """Simulate `duration_s` seconds of `scenario` (a name in SCENARIOS or a Scenario).

    `overrides` replace Scenario fields (e.g. `still_start_s=0`, `outage=(20, 30)`,
    `anchor_offset_max=0.1`, `tag_in_base=(0, 0, 0.3)`, `streams=("imu", "uwb")`); unknown
    names and unknown scenarios raise SimulationError. Truth arrays are filled for every
    sensor even when `streams` leaves it out of the log.
    """
    sc = get_scenario(scenario) if isinstance(scenario, str) else scenario
    sc = sc.with_overrides(**overrides) if overrides else sc
    _validate(sc, duration_s)
    imu_rng, wheel_rng, uwb_rng = (
        np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(3)
    )
    mp = MotionParams(sc.speed, sc.accel, sc.spin_rate)
    tl = build_timeline(list(sc.route), sc.start, mp, duration_s, sc.still_start_s)

    # IMU and ground truth
    n_imu = int(np.floor(duration_s * sc.imu_rate + 1e-9)) + 1
    t_imu = np.arange(n_imu) / sc.imu_rate
    kin = evaluate(tl, t_imu)
    imu = imu_samples(sc, kin, imu_rng)
    t_imu_ns = _to_ns(sc.t0_ns, t_imu)
    pos = np.column_stack([kin.position, np.full(n_imu, sc.base_height)])
    quat = np.zeros((n_imu, 4))
    quat[:, 2] = np.sin(0.5 * kin.yaw)
    quat[:, 3] = np.cos(0.5 * kin.yaw)
    vel = np.column_stack([kin.v * np.cos(kin.yaw), kin.v * np.sin(kin.yaw), np.zeros(n_imu)])

    # wheels
    n_wh = int(np.floor(duration_s * sc.wheel_rate + 1e-9))
    t_wh = np.arange(1, n_wh + 1) / sc.wheel_rate
    wh = wheel_samples(sc, tl, t_wh, wheel_rng, duration_s)

    # UWB
    rs = uwb_ranges(sc, tl, duration_s, uwb_rng)
    # signal powers from a stream of their own (child 10 of the seed: the sensors' children
    # 0-2 are unchanged whether or not the powers are written)
    power_rng = np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(POWER_STREAM,)))
    rx_dbm, fp_dbm = signal_powers(rs.true_range, rs.nlos, rs.nlos_excess, power_rng)

    # LiDAR localisation (own generators: the other sensors' draws do not change)
    lidar = None
    if "pose" in sc.streams:
        pose_rng, wrong_rng = (np.random.default_rng(s)
                               for s in np.random.SeedSequence(seed).spawn(5)[3:])
        lidar = lidar_poses(sc, tl, duration_s, pose_rng, wrong_rng)

    sensor_log = _sensor_log(sc, seed, t_imu_ns, imu, _to_ns(sc.t0_ns, t_wh), wh, rs,
                             (rx_dbm, fp_dbm), lidar,
                             PoseStream(t_imu_ns, pos, quat, True))
    stills_ns, standstill = _still_stamps(sc, tl, duration_s)
    log.debug(
        "simulated %s: %.1f s, %d imu, %d wheel, %d ranges (%d NLOS)",
        sc.name, duration_s, n_imu, n_wh, len(rs.t_s), int(rs.nlos.sum()),
    )
    return SimResult(
        log=sensor_log,
        scenario=sc,
        true_range=rs.true_range,
        nlos=rs.nlos,
        outlier=rs.outlier,
        nlos_excess=rs.nlos_excess,
        anchor_offset=rs.anchor_offset,
        ranges_dropped=rs.dropped,
        accel_bias=imu.accel_bias,
        gyro_bias=imu.gyro_bias,
        imu_accel=imu.accel_true,
        imu_gyro=imu.gyro_true,
        velocity=vel,
        yaw=kin.yaw,
        moving=(kin.v != 0) | (kin.omega != 0),
        wheel_slip=wh.slip,
        wheel_v_true=wh.v_true,
        wheel_omega_true=wh.omega_true,
        wheel_scale=wh.scale,
        standstill_ns=standstill,
        still_intervals_ns=stills_ns,
        timeline=tl,
        rx_dbm=rx_dbm,
        fp_dbm=fp_dbm,
        pose_wrong=None if lidar is None else lidar.wrong,
    )


def _sensor_log(sc: Scenario, seed: int, t_imu_ns: np.ndarray, imu: ImuSamples,
                t_wh_ns: np.ndarray, wh: WheelSamples, rs: RangeSamples,
                powers: tuple[np.ndarray, np.ndarray], lidar: LidarPoses | None,
                truth: PoseStream) -> SensorLog:
    """The contract's streams of one simulation (those in `sc.streams`), stamps in ns."""
    rx_dbm, fp_dbm = powers
    return SensorLog(
        imu=ImuStream(t_imu_ns, imu.gyro, imu.accel) if "imu" in sc.streams else None,
        wheel=WheelStream(t_wh_ns, wh.v, wh.omega) if "wheel" in sc.streams else None,
        ranges=RangeStream(_to_ns(sc.t0_ns, rs.t_s), rs.anchor, rs.range,
                           *((rx_dbm, fp_dbm) if sc.signal_quality else (None, None)))
        if "uwb" in sc.streams else None,
        anchors=AnchorMap.from_dict(sc.anchor_dict()),
        ground_truth=truth,
        source=f"simulated:{sc.name}:seed={seed}",
        map=site_map(sc),
        pose=None if lidar is None else PoseStream(
            _to_ns(sc.t0_ns, lidar.t_s), lidar.position, lidar.quat_xyzw, True,
            lidar.covariance),
    )


def _still_stamps(sc: Scenario, tl: Timeline, duration_s: float
                  ) -> tuple[tuple[tuple[int, int], ...], tuple[int, int] | None]:
    """The still intervals (ns) and the standstill at the start, if the scenario has one."""
    stills = _still_intervals(tl, duration_s)
    stills_ns = tuple((int(_to_ns(sc.t0_ns, np.array([a]))[0]),
                       int(_to_ns(sc.t0_ns, np.array([b]))[0])) for a, b in stills)
    standstill = stills_ns[0] if stills and stills[0][0] == 0.0 and sc.still_start_s > 0 else None
    return stills_ns, standstill


def simulate(
    scenario: str | Scenario = "warehouse",
    duration_s: float = 120.0,
    seed: int = 0,
    **overrides: Any,
) -> SensorLog:
    """Simulated `SensorLog` (imu, wheel, ranges, anchors, ground_truth); see
    `simulate_with_truth` for the arguments."""
    return simulate_with_truth(scenario, duration_s, seed, **overrides).log
