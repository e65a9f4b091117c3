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


def range_classes_of(estimator: object) -> RangeClasses | None:
    """`estimator.range_classes()` where it has one, else None."""
    get = getattr(estimator, "range_classes", None)
    return get() if callable(get) else None


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


class WithFallback:
    """`primary`, with `fallback`'s pose at the epochs before `primary` has one.

    Causal estimators need a few seconds of motion to fix their heading; the contract
    wants poses from the first motion on. The fallback (UWB-only WLS for ranging methods)
    gives those epochs a provisional pose; it is fed until the primary has answered
    `DROP_AFTER_EPOCHS` epochs in a row.

    A primary may answer provisionally before its start (its `provisional` attribute is
    true: the graph's standstill fix). Such answers win over the fallback but do not count
    towards dropping it, and the fallback keeps running beside them. When the primary falls
    silent after them (the vehicle moved before the primary could start), the fallback
    answers again at once if its last fix agreed with the provisional one within
    `DISAGREE_M`. If not, its fixes are biased (Plaza2: WLS ~9 m off while the standstill
    fix, which fits a common range scale, is 0.2 m off): the last provisional position is
    held instead (its error is at most the distance moved since) for up to
    `PROVISIONAL_GRACE_S`, long enough for the primary to start (it needs a couple of
    metres of motion), and the fallback answers after that. While the fallback has no fix
    at all (Plaza1: one range every half second, no WLS fix) the position is held until
    the primary starts. Every epoch from the first motion on has a pose (contract).
    `finish()` and `report()` are the primary's (the report counts the fallback epochs).
    """

    DROP_AFTER_EPOCHS = 20
    """The fallback is dropped once the primary has answered this many epochs in a row."""
    DISAGREE_M = 1.0
    """Horizontal distance between the fallback's and a provisional fix that discredits
    the fallback, m."""
    PROVISIONAL_GRACE_S = 5.0
    """Longest hold of the last provisional position in place of a discredited fallback, s."""

    def __init__(self, primary: Estimator, fallback: Estimator) -> None:
        self.primary = primary
        self.fallback: Estimator | None = fallback
        self.fallback_epochs = 0
        self._current: PoseEstimate | None = None
        self._primary_streak = 0
        self._discredited = False
        self._silent_since: int | None = None
        self._last_provisional: PoseEstimate | None = None
        self.held_epochs = 0
        self._provisional = True

    def add_imu(self, t_ns: np.ndarray, gyro: np.ndarray, accel: np.ndarray) -> None:
        self.primary.add_imu(t_ns, gyro, accel)
        if self.fallback is not None:
            self.fallback.add_imu(t_ns, gyro, accel)

    def add_wheel(self, t_ns: np.ndarray, v: np.ndarray, omega: np.ndarray) -> None:
        self.primary.add_wheel(t_ns, v, omega)
        if self.fallback is not None:
            self.fallback.add_wheel(t_ns, v, omega)

    def add_ranges(self, t_ns: np.ndarray, anchor: np.ndarray, rng: np.ndarray) -> None:
        self.primary.add_ranges(t_ns, anchor, rng)
        if self.fallback is not None:
            self.fallback.add_ranges(t_ns, anchor, rng)

    @property
    def provisional(self) -> bool:
        """`estimate()` is not the primary's own (started) estimate: the fallback's fix,
        a held provisional pose or the primary's provisional one."""
        return self._provisional
    def add_poses(self, t_ns: np.ndarray, position: np.ndarray, quat_xyzw: np.ndarray,
                  covariance: np.ndarray) -> None:
        self.primary.add_poses(t_ns, position, quat_xyzw, covariance)  # WLS uses none

    def step(self, t_ns: int) -> None:
        self.primary.step(t_ns)
        self._current = self.primary.estimate()
        self._provisional = True
        if self._current is not None:
            self._silent_since = None
            if getattr(self.primary, "provisional", False):
                self._last_provisional = self._current
                if self.fallback is not None:
                    self.fallback.step(t_ns)
                    fb = self.fallback.estimate()
                    if fb is not None:
                        gap = float(np.hypot(*(fb.position[:2] - self._current.position[:2])))
                        self._discredited = gap > self.DISAGREE_M
                return
            self._provisional = False
            self._primary_streak += 1
            if self._primary_streak >= self.DROP_AFTER_EPOCHS:
                self.fallback = None  # the primary is up for good: free the buffers
            elif self.fallback is not None:
                self.fallback.step(t_ns)  # keep it current in case the primary drops out
            return
        self._primary_streak = 0
        if self._silent_since is None:
            self._silent_since = t_ns
        if self.fallback is not None:
            self.fallback.step(t_ns)
            fb = self.fallback.estimate()
            last = self._last_provisional
            if last is not None and (fb is None or (self._discredited and (
                    t_ns - self._silent_since < self.PROVISIONAL_GRACE_S * NS_PER_S))):
                # the held pose keeps the provisional fix's covariance (None: unknown)
                self._current = PoseEstimate(t_ns, last.position, last.quat_xyzw,
                                             last.covariance)
                self.held_epochs += 1
                return
            self._current = fb
            if self._current is not None:
                self.fallback_epochs += 1

    def estimate(self) -> PoseEstimate | None:
        return self._current

    def finish(self) -> PoseStream | None:
        return self.primary.finish()

    def range_classes(self) -> RangeClasses | None:
        return range_classes_of(self.primary)

    def report(self) -> dict[str, Any]:
        out = dict(self.primary.report())
        out["provisional_epochs"] = self.fallback_epochs
        out["held_provisional_epochs"] = self.held_epochs
        return out


@dataclass
class StreamingResult:
    """Outputs of one streaming pass."""

    causal: PoseStream
    final: PoseStream | None
    step_latency_s: np.ndarray
    wall_s: float
    report: dict[str, Any] = field(default_factory=dict)
    range_classes: RangeClasses | None = None


# Epochs the output grid may have: 10^7 is 11.6 days at 10 Hz (each epoch costs a step and
# a pose, about 1 kB); more means stamps on different clocks, not a long log
MAX_EPOCHS = 10_000_000


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
                           range_classes_of(estimator))
