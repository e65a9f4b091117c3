# SPDX-License-Identifier: BSD-3-Clause
"""The poses before a method's own start, decided in one place.

A method needs some motion before it can fix its heading, yet the contract wants a pose at
every epoch from the first motion on. Before the start, three sources can answer:

- the method itself, provisionally (its standstill fix: `Estimator.provisional` is true);
- a UWB-only fallback (per-epoch NLOS-weighted WLS) for methods that use ranges;
- the last provisional pose, held.

While the wheels say the vehicle stands still, the fallback's answer is the mean of its
fixes since the standstill began: each fix is of the same point, so the mean's squared
error is at most the fixes' mean squared error (the per-epoch fixes' noise averages out).

`PreStart` wraps a method and decides among them epoch by epoch (the causal output), and
`PreStart.complete` gives a smoothed method's final trajectory the epochs before its first
pose: carried back along the method's own relative motion where it has one
(`Estimator.pre_start`: the wheel track), else the causal poses of those epochs.

Poses are the base frame in the map frame; covariances ROS order, map axes.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from uwbfuse.config import Config
from uwbfuse.constants import DISAGREE_M, DROP_AFTER_EPOCHS, PROVISIONAL_GRACE_S, STILL_WHEEL_GAP_NS
from uwbfuse.estimator import Estimator, EstimatorBase, PoseEstimate, RangeClasses
from uwbfuse.methods import Method, make_estimator
from uwbfuse.positioning.start import wheels_still
from uwbfuse.streams import NS_PER_S, UNKNOWN_VARIANCE, AnchorMap, PoseStream


class PreStart(EstimatorBase):
    """`primary`, with the pose before its start decided as the module docstring says.

    The fallback is fed until the primary has answered `DROP_AFTER_EPOCHS` epochs in a row.
    Provisional answers of the primary win over the fallback but do not count towards
    dropping it, and the fallback keeps running beside them. When the primary falls silent
    after them (the vehicle moved before the primary could start), the fallback answers
    again at once if its last fix agreed with the provisional one within `DISAGREE_M`. If
    not, its fixes are biased (a radio scale the fallback does not fit, which the
    standstill fix does): the last provisional position is held instead (its error is at
    most the distance moved since) for up to `PROVISIONAL_GRACE_S`, and the fallback
    answers after that. While the fallback has no fix at all (one range every half second:
    no epoch has three) the position is held until the primary starts. `finish()` is the
    primary's; `report()` the primary's with the fallback and held epochs counted.
    """

    def __init__(self, primary: Estimator, fallback: Estimator | None) -> None:
        self.primary = primary
        self.fallback: Estimator | None = fallback
        self.fallback_epochs = 0
        self.held_epochs = 0
        self._current: PoseEstimate | None = None
        self._primary_streak = 0
        self._discredited = False
        self._silent_since: int | None = None
        self._last_provisional: PoseEstimate | None = None
        self._provisional = True
        self._still_since: int | None = None  # ns: wheels still (`wheels_still`) since
        self._wheel_last: int | None = None   # ns: last wheel sample
        self._still_sum = np.zeros(3)         # fallback fixes since _still_since ...
        self._still_n = 0                     # ... and their number
        self._still_from: int | None = None   # the _still_since they belong to

    @classmethod
    def around(cls, primary: Estimator, method: Method, config: Config,
               anchors: AnchorMap | None, streams: frozenset[str]) -> PreStart:
        """`primary` (an estimator of `method`) with the UWB-only WLS fallback where the
        method is not WLS itself and the log has ranges and anchors; else without one."""
        fallback = None
        if method is not Method.WLS and "uwb" in streams and anchors is not None:
            fallback = make_estimator(Method.WLS, config, anchors, streams - {"pose"})
        return cls(primary, fallback)

    # ------------------------------------------------------------------ streams
    def add_imu(self, t_ns: np.ndarray, gyro: np.ndarray, accel: np.ndarray) -> None:
        self.primary.add_imu(t_ns, gyro, accel)
        if self.fallback is not None:
            self.fallback.add_imu(t_ns, gyro, accel)

    def add_wheel(self, t_ns: np.ndarray, v: np.ndarray, omega: np.ndarray) -> None:
        self.primary.add_wheel(t_ns, v, omega)
        if self.fallback is not None:
            self.fallback.add_wheel(t_ns, v, omega)
            self._track_standstill(np.asarray(t_ns, np.int64), np.asarray(v, np.float64),
                                   np.asarray(omega, np.float64))

    def _track_standstill(self, t: np.ndarray, v: np.ndarray, omega: np.ndarray) -> None:
        """Keep `_still_since`: the stamp since which every wheel sample is still (a sample
        averages the interval ending at its stamp, so the last moving one ends the motion)."""
        if not len(t):
            return
        still = wheels_still(v, omega)
        moving = np.flatnonzero(~still)
        if len(moving):
            self._still_since = int(t[moving[-1]]) if moving[-1] < len(t) - 1 else None
        elif self._still_since is None:
            self._still_since = int(t[0]) if self._wheel_last is None else self._wheel_last
        self._wheel_last = int(t[-1])

    def _standstill_mean(self, fb: PoseEstimate) -> PoseEstimate:
        """`fb`, or the mean of the fallback's fixes since the standstill began while the
        wheels say the vehicle stands still (module docstring)."""
        since, last = self._still_since, self._wheel_last
        if since is None or last is None or fb.t_ns - last > STILL_WHEEL_GAP_NS or (
                fb.t_ns <= since):
            self._still_from = None
            return fb
        if self._still_from != since:
            self._still_from, self._still_sum, self._still_n = since, np.zeros(3), 0
        self._still_sum = self._still_sum + fb.position
        self._still_n += 1
        return PoseEstimate(fb.t_ns, self._still_sum / self._still_n, fb.quat_xyzw,
                            fb.covariance)

    def add_ranges(self, t_ns: np.ndarray, anchor: np.ndarray, rng: np.ndarray) -> None:
        self.primary.add_ranges(t_ns, anchor, rng)
        if self.fallback is not None:
            self.fallback.add_ranges(t_ns, anchor, rng)

    def add_poses(self, t_ns: np.ndarray, position: np.ndarray, quat_xyzw: np.ndarray,
                  covariance: np.ndarray) -> None:
        self.primary.add_poses(t_ns, position, quat_xyzw, covariance)  # WLS uses none

    # ------------------------------------------------------------------ causal
    @property
    def provisional(self) -> bool:
        """`estimate()` is not the primary's own (started) estimate: the fallback's fix,
        a held provisional pose or the primary's provisional one."""
        return self._provisional

    def step(self, t_ns: int) -> None:
        self.primary.step(t_ns)
        self._current = self.primary.estimate()
        self._provisional = True
        if self._current is not None:
            self._silent_since = None
            if self.primary.provisional:
                self._last_provisional = self._current
                if self.fallback is not None:
                    self.fallback.step(t_ns)
                    fb = self.fallback.estimate()
                    if fb is not None:
                        gap = float(np.hypot(*(fb.position[:2] - self._current.position[:2])))
                        self._discredited = gap > DISAGREE_M
                return
            self._provisional = False
            self._primary_streak += 1
            if self._primary_streak >= DROP_AFTER_EPOCHS:
                self.fallback = None  # the primary is up for good: free the buffers
            elif self.fallback is not None:
                self.fallback.step(t_ns)  # keep it current in case the primary drops out
            return
        self._primary_streak = 0
        if self._silent_since is None:
            self._silent_since = t_ns
        if self.fallback is None:
            return
        self.fallback.step(t_ns)
        fb = self.fallback.estimate()
        last = self._last_provisional
        if last is not None and (fb is None or (self._discredited and (
                t_ns - self._silent_since < PROVISIONAL_GRACE_S * NS_PER_S))):
            # the held pose keeps the provisional fix's covariance (None: unknown)
            self._current = PoseEstimate(t_ns, last.position, last.quat_xyzw, last.covariance)
            self.held_epochs += 1
            return
        self._current = None if fb is None else self._standstill_mean(fb)
        if self._current is not None:
            self.fallback_epochs += 1

    def estimate(self) -> PoseEstimate | None:
        return self._current

    # ------------------------------------------------------------------ offline
    def finish(self) -> PoseStream | None:
        return self.primary.finish()

    def complete(self, final: PoseStream, causal: PoseStream,
                 epochs: np.ndarray) -> PoseStream:
        """`final` (a smoothed trajectory, after `finish()`) with the epochs before its
        first pose: those the primary carries back along its own motion
        (`Estimator.pre_start`), and before them the causal poses (`causal`, this
        estimator's outputs). Covariances: each part's own; `UNKNOWN_VARIANCE` on the
        diagonal for a part without one where another has one."""
        if not len(final):
            return final
        head_t = np.asarray(epochs, np.int64)
        head_t = head_t[head_t < final.t_ns[0]]
        carried = self.primary.pre_start(head_t) if len(head_t) else None
        parts = [final] if carried is None or not len(carried) else [carried, final]
        before = causal.t_ns < parts[0].t_ns[0]
        if np.any(before):
            parts.insert(0, PoseStream(causal.t_ns[before], causal.position[before],
                                       causal.quat_xyzw[before], causal.has_orientation,
                                       None if causal.covariance is None
                                       else causal.covariance[before]))
        if len(parts) == 1:
            return final
        return PoseStream(np.concatenate([p.t_ns for p in parts]),
                          np.concatenate([p.position for p in parts]),
                          np.concatenate([p.quat_xyzw for p in parts]),
                          final.has_orientation, _joined_covariance(parts))

    # ------------------------------------------------------------------ report
    def range_classes(self) -> RangeClasses | None:
        return self.primary.range_classes()

    def forget_before(self, t_ns: int) -> None:
        self.primary.forget_before(t_ns)

    def report(self) -> dict[str, Any]:
        out = dict(self.primary.report())
        out["provisional_epochs"] = self.fallback_epochs
        out["held_provisional_epochs"] = self.held_epochs
        return out


def _joined_covariance(parts: list[PoseStream]) -> np.ndarray | None:
    """The parts' covariances end to end (a part without one: `UNKNOWN_VARIANCE` on the
    diagonal), or None when no part has any."""
    if all(p.covariance is None for p in parts):
        return None
    unknown = np.eye(6) * UNKNOWN_VARIANCE
    return np.concatenate([p.covariance if p.covariance is not None
                           else np.tile(unknown, (len(p.t_ns), 1, 1)) for p in parts])
