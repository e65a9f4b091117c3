# SPDX-License-Identifier: BSD-3-Clause
"""The narrow streaming API every estimator shares, and the loop that drives it.

Graph smoothers and Kalman baselines alike receive time-ordered batches of each stream
(`add_imu`, `add_wheel`, `add_ranges`), are told to process everything up to an epoch
(`step`), and report the pose available at that epoch (`estimate`). `finish` returns the
final trajectory (smoothed, for smoothers) or None when the causal outputs are final.
Batches keep per-sample Python work out of the driving loop: an estimator sees numpy
slices, never single messages.

Poses are the base frame in the map frame (anchor frame, z up); quaternions (x, y, z, w).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from uwbfuse.constants import MAX_EPOCHS
from uwbfuse.errors import EstimatorError
from uwbfuse.methods import Method  # noqa: F401  (re-exported: the public name's old home)
from uwbfuse.streams import NS_PER_S, UNKNOWN_VARIANCE, PoseStream, SensorLog


@dataclass(frozen=True)
class PoseEstimate:
    """One pose of the base frame in the map frame: position (3,) m, quat_xyzw (4,).

    `covariance` (6,6), when the estimator knows it: ROS order (x, y, z, rot x, rot y,
    rot z), map frame axes; see `PoseStream`.
    """

    t_ns: int
    position: np.ndarray
    quat_xyzw: np.ndarray
    covariance: np.ndarray | None = None


@dataclass(frozen=True)
class RangeClasses:
    """An estimator's own LOS/NLOS classification of the ranges it used: stamps (N,) int64
    ns, anchor index (N,), P(NLOS) (N,) in [0, 1]; a range counts as NLOS where
    P(NLOS) > 0.5 (as the graph's report counts them). `weight` (N,), where known, is the
    robust kernel's weight of the LOS part (1 = full; below 0.999 the report counts the
    range as down-weighted). Optional: estimators without a per-range classification have
    no `range_classes` method (or return None)."""

    t_ns: np.ndarray
    anchor: np.ndarray
    p_nlos: np.ndarray
    weight: np.ndarray | None = None

    @property
    def nlos(self) -> np.ndarray:
        return self.p_nlos > 0.5

    @property
    def downweighted(self) -> np.ndarray:
        """LOS ranges whose weight is below 0.999 (all False without weights)."""
        if self.weight is None:
            return np.zeros(len(self.p_nlos), dtype=bool)
        return ~self.nlos & (self.weight < 0.999)


class Estimator(Protocol):
    """Streaming estimator (graph or filter). Batches arrive time-sorted per stream."""

    def add_imu(self, t_ns: np.ndarray, gyro: np.ndarray, accel: np.ndarray) -> None:
        """IMU batch: stamps (N,) int64 ns, gyro (N,3) rad/s, specific force (N,3) m/s^2."""

    def add_wheel(self, t_ns: np.ndarray, v: np.ndarray, omega: np.ndarray) -> None:
        """Wheel batch: stamps (N,) ns, forward speed (N,) m/s, yaw rate (N,) rad/s."""

    def add_ranges(self, t_ns: np.ndarray, anchor: np.ndarray, rng: np.ndarray) -> None:
        """Range batch: stamps (N,) ns, anchor index (N,), range (N,) m."""

    def add_poses(self, t_ns: np.ndarray, position: np.ndarray, quat_xyzw: np.ndarray,
                  covariance: np.ndarray) -> None:
        """External-pose batch (methods whose spec `uses_pose`): stamps (N,) ns, base
        position (N,3) m and quaternion (N,4) xyzw in the map frame, covariance (N,6,6)
        ROS order (x, y, z, rot x, rot y, rot z; map axes)."""

    def step(self, t_ns: int) -> None:
        """All data with stamps <= t_ns has been added: process it."""

    def estimate(self) -> PoseEstimate | None:
        """The causal pose at the last `step` time, or None before initialisation."""

    def finish(self) -> PoseStream | None:
        """Final trajectory after the last step (smoothed), or None if causal is final."""

    def report(self) -> dict[str, Any]:
        """Estimator-specific results for the run summary (outliers, biases, events)."""

    @property
    def provisional(self) -> bool:
        """`estimate()` is a stand-in from before the method's own start (a standstill
        fix), not its started estimate (`prestart.PreStart` decides what to do with it)."""

    def pre_start(self, t_ns: np.ndarray) -> PoseStream | None:
        """After `finish()`: the final trajectory's poses at epochs `t_ns` (int64 ns, before
        its first pose) carried back along the method's own relative motion; a suffix of
        `t_ns`, or None where the method has none (`prestart.PreStart.complete`)."""

    def range_classes(self) -> RangeClasses | None:
        """The per-range LOS/NLOS classification, or None without one."""

    def forget_before(self, t_ns: int) -> None:
        """Live use: drop what only offline outputs keep of the time before `t_ns`."""


class EstimatorBase:
    """The `Estimator` protocol's optional parts for estimators that have none of them:
    no provisional answers, nothing to carry back before the start, no per-range
    classification, nothing kept beyond a bounded window (so nothing to forget)."""

    @property
    def provisional(self) -> bool:
        return False

    def pre_start(self, t_ns: np.ndarray) -> PoseStream | None:
        return None

    def range_classes(self) -> RangeClasses | None:
        return None

    def forget_before(self, t_ns: int) -> None:
        return None


@dataclass
class StreamingResult:
    """Outputs of one streaming pass."""

    causal: PoseStream
    final: PoseStream | None
    step_latency_s: np.ndarray
    wall_s: float
    report: dict[str, Any] = field(default_factory=dict)
    range_classes: RangeClasses | None = None




def output_epochs(log: SensorLog, rate_hz: float) -> np.ndarray:
    """Epoch stamps (int64 ns) on a regular grid over the log's sensor time span.

    Raises EstimatorError when the span is shorter than one period (nothing to estimate
    over: a log of one or two messages) or needs more than MAX_EPOCHS epochs.
    """
    t0, t1 = log.time_span_ns()
    period = max(round(NS_PER_S / rate_hz), 1)
    if t1 - t0 < period:
        raise EstimatorError(
            f"{log.source}: the sensor data span {(t1 - t0) / NS_PER_S:.3f} s, less than one "
            f"output period ({period / NS_PER_S:g} s at {rate_hz:g} Hz): nothing to estimate")
    n = (t1 - t0) // period + 1
    if n > MAX_EPOCHS:
        raise EstimatorError(
            f"{log.source}: the sensor stamps span {(t1 - t0) / NS_PER_S:.0f} s, "
            f"{n} output epochs at {rate_hz:g} Hz (at most {MAX_EPOCHS}): are the stamps "
            "on one clock?")
    epochs = t0 + period * np.arange(n, dtype=np.int64)
    if epochs[-1] < t1:
        epochs = np.append(epochs, np.int64(t1))
    return epochs


def _poses_to_stream(poses: list[PoseEstimate]) -> PoseStream:
    if not poses:
        empty = np.zeros((0, 3))
        return PoseStream(np.zeros(0, dtype=np.int64), empty, np.zeros((0, 4)))
    covariance = None
    if any(p.covariance is not None for p in poses):
        unknown = np.eye(6) * UNKNOWN_VARIANCE
        covariance = np.array(
            [unknown if p.covariance is None else p.covariance for p in poses],
            dtype=np.float64,
        )
    return PoseStream(
        np.array([p.t_ns for p in poses], dtype=np.int64),
        np.array([p.position for p in poses], dtype=np.float64),
        np.array([p.quat_xyzw for p in poses], dtype=np.float64),
        covariance=covariance,
    )


def run_streaming(
    estimator: Estimator, log: SensorLog, epochs: np.ndarray,
    progress: Callable[[int, int, str], None] | None = None,
) -> StreamingResult:
    """Feed `log` to `estimator` epoch by epoch; collect the causal pose at every epoch.

    For each epoch t_k the data with stamps in (t_{k-1}, t_k] is added stream by stream,
    then `step(t_k)` is called and timed (the per-update latency). `progress(done, total,
    note)` is told the whole seconds of log processed, out of the log's span plus one for
    `finish()` (it limits its own redraw rate).
    """
    streams = []
    if log.imu is not None and len(log.imu):
        ends = np.searchsorted(log.imu.t_ns, epochs, side="right")
        streams.append((estimator.add_imu, (log.imu.t_ns, log.imu.gyro, log.imu.accel), ends))
    if log.wheel is not None and len(log.wheel):
        ends = np.searchsorted(log.wheel.t_ns, epochs, side="right")
        streams.append(
            (estimator.add_wheel, (log.wheel.t_ns, log.wheel.v, log.wheel.omega), ends)
        )
    if log.ranges is not None and len(log.ranges):
        ends = np.searchsorted(log.ranges.t_ns, epochs, side="right")
        cols = (log.ranges.t_ns, log.ranges.anchor, log.ranges.range)
        streams.append((estimator.add_ranges, cols, ends))
    if log.pose is not None and len(log.pose):
        ends = np.searchsorted(log.pose.t_ns, epochs, side="right")
        cov = log.pose.covariance
        if cov is None:
            raise ValueError("external poses need their covariance (the reader sets it)")
        cols = (log.pose.t_ns, log.pose.position, log.pose.quat_xyzw, cov)
        streams.append((estimator.add_poses, cols, ends))

    starts = [0] * len(streams)
    poses: list[PoseEstimate] = []
    latency = np.empty(len(epochs))
    span_s = int((epochs[-1] - epochs[0]) // NS_PER_S) if len(epochs) else 0
    wall0 = time.perf_counter()
    for k, t in enumerate(epochs):
        for i, (add, cols, ends) in enumerate(streams):
            e = int(ends[k])
            if e > starts[i]:
                add(*(c[starts[i] : e] for c in cols))
                starts[i] = e
        tic = time.perf_counter()
        estimator.step(int(t))
        latency[k] = time.perf_counter() - tic
        if progress is not None:
            progress(int((t - epochs[0]) // NS_PER_S), span_s + 1, "")
        est = estimator.estimate()
        if est is not None:
            if est.t_ns != t:
                raise RuntimeError(
                    f"{type(estimator).__name__}.estimate() returned a pose stamped "
                    f"{est.t_ns} ns at epoch {int(t)} ns (must be the step time)"
                )
            poses.append(est)
    if progress is not None:
        progress(span_s, span_s + 1, "finishing")
    final = estimator.finish()
    wall = time.perf_counter() - wall0
    if progress is not None:
        progress(span_s + 1, span_s + 1, "")
    return StreamingResult(_poses_to_stream(poses), final, latency, wall, estimator.report(),
                           estimator.range_classes())
