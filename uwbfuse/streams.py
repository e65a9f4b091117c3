# SPDX-License-Identifier: BSD-3-Clause
"""Columnar sensor streams: one set of numpy arrays per stream, sorted by stamp.

Times are integer nanoseconds (int64) on the log's stamp clock (`header.stamp`). Every
stream is sorted by stamp with exact duplicates removed by the reader; a stream that a log
does not have is `None` in `SensorLog`.

Frames:
- IMU: angular velocity (rad/s) and specific force (m/s^2, +9.81 on z when level and
  still) in the IMU frame (REP-145); `Extrinsics.imu_in_base` maps it to the base frame.
- Wheels: forward speed v (m/s) and yaw rate omega (rad/s) of the base frame, each the mean
  over the interval that ends at its stamp.
- Ranges: tag-antenna-to-anchor distance (m), anchor given as an index into `AnchorMap`.
- Ground truth and trajectories: pose of the base frame in the map frame (anchor frame,
  z up), quaternions in (x, y, z, w) order.
- External poses (`SensorLog.pose`, a LiDAR / scan-matching localiser): a `PoseStream` of
  the base frame in the map frame (the reader has applied `[extrinsics]
  lidar_map_in_map`), with each pose's covariance (floored by `[pose]`).
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

if TYPE_CHECKING:
    from uwbfuse.config import MapConfig

NS_PER_S = 1_000_000_000

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]


def _check_len(name: str, t_ns: I64, *arrays: NDArray) -> None:
    n = len(t_ns)
    for a in arrays:
        if len(a) != n:
            raise ValueError(f"{name}: column lengths differ ({n} stamps, {len(a)} values)")


@dataclass(frozen=True)
class ImuStream:
    """IMU samples in the IMU frame: gyro (N,3) rad/s, accel = specific force (N,3) m/s^2."""

    t_ns: I64
    gyro: F64
    accel: F64

    def __post_init__(self) -> None:
        _check_len("imu", self.t_ns, self.gyro, self.accel)

    def __len__(self) -> int:
        return len(self.t_ns)

    def slice(self, start: int, stop: int) -> ImuStream:
        """Rows [start, stop) as a new stream sharing memory."""
        return ImuStream(self.t_ns[start:stop], self.gyro[start:stop], self.accel[start:stop])


@dataclass(frozen=True)
class WheelStream:
    """Wheel odometry of the base frame: v (N,) m/s forward, omega (N,) rad/s yaw rate.

    Each sample is the mean velocity over the interval that ends at its stamp.
    """

    t_ns: I64
    v: F64
    omega: F64

    def __post_init__(self) -> None:
        _check_len("wheel", self.t_ns, self.v, self.omega)

    def __len__(self) -> int:
        return len(self.t_ns)

    def slice(self, start: int, stop: int) -> WheelStream:
        return WheelStream(self.t_ns[start:stop], self.v[start:stop], self.omega[start:stop])


@dataclass(frozen=True)
class RangeStream:
    """UWB ranges: anchor (N,) int index into `AnchorMap.ids`, range (N,) metres.

    Ranges are as measured, minus any configured `[uwb.range_offset]`. Signal quality, when
    the log carries it (`[uwb] rssi_field` / `first_path_power_field`): `rssi_dbm` (N,)
    received total power and `first_path_dbm` (N,) first-path power, dBm, NaN for a range
    whose message had none; None when the log has no such field.
    """

    t_ns: I64
    anchor: NDArray[np.int32]
    range: F64
    rssi_dbm: F64 | None = None
    first_path_dbm: F64 | None = None

    def __post_init__(self) -> None:
        _check_len("uwb", self.t_ns, self.anchor, self.range,
                   *(a for a in (self.rssi_dbm, self.first_path_dbm) if a is not None))

    def __len__(self) -> int:
        return len(self.t_ns)

    def slice(self, start: int, stop: int) -> RangeStream:
        def part(a: F64 | None) -> F64 | None:
            return None if a is None else a[start:stop]

        return RangeStream(self.t_ns[start:stop], self.anchor[start:stop],
                           self.range[start:stop], part(self.rssi_dbm),
                           part(self.first_path_dbm))


UNKNOWN_VARIANCE = 1.0e6
"""Variance (m^2 or rad^2) reported for a pose component a method does not estimate
(ROS convention: a very large value marks it unknown)."""


@dataclass(frozen=True)
class PoseStream:
    """Poses of the base frame in the map frame: position (N,3) m, quat_xyzw (N,4).

    `has_orientation` is False when the source carries position only (identity quaternions).
    `covariance` (N,6,6), when known, is each pose's covariance in ROS order (x, y, z in m,
    then rotation about the map frame's x, y, z axes in rad), as in
    `geometry_msgs/msg/PoseWithCovariance`; a degree of freedom the method does not
    estimate has variance `UNKNOWN_VARIANCE`.
    """

    t_ns: I64
    position: F64
    quat_xyzw: F64
    has_orientation: bool = True
    covariance: F64 | None = None

    def __post_init__(self) -> None:
        _check_len("poses", self.t_ns, self.position, self.quat_xyzw)
        if self.covariance is not None and self.covariance.shape != (len(self.t_ns), 6, 6):
            raise ValueError(
                f"poses: covariance has shape {self.covariance.shape}, "
                f"expected ({len(self.t_ns)}, 6, 6)"
            )

    def __len__(self) -> int:
        return len(self.t_ns)

    def slice(self, start: int, stop: int) -> PoseStream:
        """Rows [start, stop) as a new stream sharing memory."""
        cov = None if self.covariance is None else self.covariance[start:stop]
        return PoseStream(self.t_ns[start:stop], self.position[start:stop],
                          self.quat_xyzw[start:stop], self.has_orientation, cov)

    @property
    def t_s(self) -> F64:
        """Stamps in seconds (float64)."""
        return self.t_ns.astype(np.float64) / NS_PER_S


@dataclass(frozen=True)
class AnchorMap:
    """Fixed UWB anchors: ids as strings, positions (M,3) in metres in the map frame."""

    ids: tuple[str, ...]
    positions: F64

    def __post_init__(self) -> None:
        if self.positions.shape != (len(self.ids), 3):
            raise ValueError("anchor positions must be (M,3) with one row per id")

    def __len__(self) -> int:
        return len(self.ids)

    def index(self, anchor_id: str) -> int:
        return self.ids.index(anchor_id)

    @classmethod
    def from_dict(cls, anchors: dict[str, tuple[float, float, float] | list[float]]) -> AnchorMap:
        ids = tuple(str(k) for k in anchors)
        pos = np.array([list(anchors[k]) for k in anchors], dtype=np.float64).reshape(-1, 3)
        return cls(ids, pos)


@dataclass
class ReadReport:
    """What a reader counted while reading: messages per topic and skips by reason."""

    messages: Counter[str] = field(default_factory=Counter)
    skipped: Counter[str] = field(default_factory=Counter)
    warnings: list[str] = field(default_factory=list)

    def skip(self, reason: str, n: int = 1) -> None:
        if n:
            self.skipped[reason] += n

    def lines(self) -> list[str]:
        """Human-readable summary, one line per skip reason and warning."""
        out = [f"skipped {n} ({reason})" for reason, n in sorted(self.skipped.items())]
        return out + list(self.warnings)


@dataclass
class SensorLog:
    """Everything an estimator may use from one log, plus ground truth for evaluation only.

    Estimators must never read `ground_truth`. `map` is the electronic map for collision
    prediction (the config's `[map]`, else the log's `map_obstacles` metadata), or None.
    """

    imu: ImuStream | None = None
    wheel: WheelStream | None = None
    ranges: RangeStream | None = None
    anchors: AnchorMap | None = None
    ground_truth: PoseStream | None = None
    source: str = ""
    report: ReadReport = field(default_factory=ReadReport)
    map: MapConfig | None = None
    pose: PoseStream | None = None  # external poses (optional role `pose`)

    def time_span_ns(self) -> tuple[int, int]:
        """First and last stamp over the sensor streams (ground truth excluded)."""
        firsts, lasts = [], []
        for s in (self.imu, self.wheel, self.ranges, self.pose):
            if s is not None and len(s):
                firsts.append(int(s.t_ns[0]))
                lasts.append(int(s.t_ns[-1]))
        if not firsts:
            raise ValueError("log has no sensor data")
        return min(firsts), max(lasts)
