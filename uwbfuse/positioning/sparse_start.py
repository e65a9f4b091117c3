# SPDX-License-Identifier: BSD-3-Clause
"""The start of every ranging estimator on logs whose ranges are too sparse for fixes.

`SparseStartInitialiser` wraps `positioning.Initialiser` (per-epoch multilateration, IMU
levelling, heading from the first motion) and adds, for wheeled logs without an IMU whose
round-robin ranges give no multilateration fixes (Plaza1: one anchor every half second):

- `try_initialise`: after FALLBACK_AFTER_S seconds of ranges without a start, the start
  solved from the wheel track and the last START_WINDOW_S of raw ranges (`start.solve_start`,
  every FALLBACK_RETRY_S of data, backing off to MAX_RETRY_S while full solves fail);
- `standstill_fix`: while the wheels have stood still since the first range, the position
  fitted to all ranges so far with a common range scale (`start.solve_static`, map frame,
  heading unknown).

The graph estimator and the Kalman filters use it alike, so that every method starts,
and answers from the first motion (contract), on the same logs.
"""

from __future__ import annotations

import logging
from typing import Any

import numpy as np

from uwbfuse.config import Config
from uwbfuse.constants import (
    FALLBACK_AFTER_S,
    FALLBACK_RETRY_S,
    MAX_RETRY_S,
    MIN_TRAVEL_M,
    START_WINDOW_S,
    STATIC_MAX_DRIFT_M,
    STATIC_MAX_TURN_RAD,
    STATIC_WHEEL_GAP_NS,
)
from uwbfuse.positioning.start import (
    planar_height,
    solve_start,
    solve_static,
    track_travel,
    wheels_still,
)
from uwbfuse.positioning.wheel_track import WheelTrack
from uwbfuse.streams import NS_PER_S, AnchorMap

log = logging.getLogger(__name__)



class SparseStartInitialiser:
    """`Initialiser` plus the sparse-range start and standstill fixes (module docstring).

    Implements the initialiser protocol (`add_*`, `try_initialise`, `provisional`).
    """

    def __init__(
        self, inner: Any, config: Config, anchors: AnchorMap, streams: frozenset[str],
        only_without_fixes: bool = False,
    ) -> None:
        self.inner = inner
        self.cfg = config
        self.anchors = anchors
        # only wheeled logs without an IMU: with an IMU the initialiser levels and turns
        # the start itself, and without wheels there is no track to fit
        self.enabled = "imu" not in streams and "wheel" in streams
        self.wheel = WheelTrack()
        self.pre_ranges: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        self.fallback_used = False
        # the wheel-track start only while the initialiser has had no provisional fix
        self.only_without_fixes = only_without_fixes
        self._had_fix = False
        self.standstill_epochs = 0
        self._fallback_t: int | None = None
        self._retry_s = FALLBACK_RETRY_S
        self._static: tuple[np.ndarray, np.ndarray] | None = None  # position, quat_xyzw
        self._static_t: int | None = None

    def add_imu(self, t_ns: np.ndarray, gyro: np.ndarray, accel: np.ndarray) -> None:
        self.inner.add_imu(t_ns, gyro, accel)

    def add_wheel(self, t_ns: np.ndarray, v: np.ndarray, omega: np.ndarray) -> None:
        self.inner.add_wheel(t_ns, v, omega)
        if self.enabled:
            self.wheel.add(t_ns, v, omega)

    def add_ranges(self, t_ns: np.ndarray, anchor: np.ndarray, rng: np.ndarray) -> None:
        self.inner.add_ranges(t_ns, anchor, rng)
        self.pre_ranges.append((np.asarray(t_ns), np.asarray(anchor), np.asarray(rng)))

    def provisional(self, t_ns: int) -> Any:
        p = self.inner.provisional(t_ns)
        self._had_fix = self._had_fix or p is not None
        return p

    def try_initialise(self, t_ns: int) -> Any:
        """The initialiser's start, else (wheeled, no IMU) the wheel-track start solve."""
        state = self.inner.try_initialise(t_ns)
        if state is not None or not self.enabled or not self.pre_ranges:
            return state
        if self.only_without_fixes and self._had_fix:
            return None
        t_first = int(self.pre_ranges[0][0][0])
        if t_ns - t_first < FALLBACK_AFTER_S * NS_PER_S:
            return None
        if self._fallback_t is not None and t_ns - self._fallback_t < self._retry_s * NS_PER_S:
            return None
        if len(self.wheel) < 2:
            return None  # no wheel track yet
        self._fallback_t = t_ns
        t, a, z = self.pre_range_arrays()
        # ranges from before the first wheel sample have no track to fit (it would be
        # carried back at constant velocity)
        keep = t >= max(t_ns - round(START_WINDOW_S * NS_PER_S), int(self.wheel.t[0]))
        t, a, z = t[keep], a[keep], z[keep]
        z_floor = planar_height(self.anchors, 0.0)
        state = solve_start(self.wheel, self.anchors, t, a, z,
                            np.asarray(self.cfg.extrinsics.tag_in_base, float), z_floor, t_ns)
        if state is not None:
            log.info("initialiser gave no start: fallback start from wheel track and raw "
                     "ranges at t=%.3f s", t_ns * 1e-9)
            self.fallback_used = True
        elif track_travel(self.wheel, t_ns) >= MIN_TRAVEL_M:  # a full solve failed
            self._retry_s = min(2.0 * self._retry_s, MAX_RETRY_S)
        return state

    def pre_range_arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The ranges buffered before the start: stamps ns, anchor index, metres."""
        return (np.concatenate([r[0] for r in self.pre_ranges]).astype(np.int64),
                np.concatenate([r[1] for r in self.pre_ranges]).astype(np.int64),
                np.concatenate([r[2] for r in self.pre_ranges]).astype(np.float64))

    def standstill_fix(self, t_ns: int) -> tuple[np.ndarray, np.ndarray] | None:
        """Provisional base position (map frame, m; the tag's: the lever arm's direction is
        unknown) and quaternion xyzw (identity: heading unknown) of a wheeled log without an
        IMU that has not moved since its first range, re-solved every FALLBACK_RETRY_S;
        None once the wheels move or when the fit is rejected."""
        if not self.enabled or not self.pre_ranges:
            return None
        t_first = int(self.pre_ranges[0][0][0])
        if not self._standing_still(t_first, t_ns):
            return None
        if self._static_t is not None and t_ns - self._static_t < FALLBACK_RETRY_S * NS_PER_S:
            if self._static is not None:  # else the last attempt failed: wait for the next
                self.standstill_epochs += 1
            return self._static
        self._static_t = t_ns
        _, a, z = self.pre_range_arrays()
        base_z = planar_height(self.anchors, 0.0)
        tag = np.asarray(self.cfg.extrinsics.tag_in_base, float)
        fix = solve_static(self.anchors, a, z, base_z + float(tag[2]))
        self._static = None if fix is None else (
            np.array([fix[0][0], fix[0][1], base_z]), np.array([0.0, 0.0, 0.0, 1.0]))
        if self._static is not None:
            self.standstill_epochs += 1
        return self._static

    def _standing_still(self, t_from: int, t_to: int) -> bool:
        """The wheels cover [t_from, t_to] and stood still through it (`start` STATIC_* limits)."""
        w = self.wheel
        gap = STATIC_WHEEL_GAP_NS
        if len(w) < 2 or w.t[0] > t_from + gap or w.t[-1] < t_to - gap:
            return False
        i0, i1 = np.searchsorted(w.t, [t_from, t_to])
        seg = slice(max(i0 - 1, 0), min(i1 + 1, len(w)))
        if not np.all(wheels_still(w.v[seg], w.w[seg])):
            return False
        p = w.pose[seg]
        drift = float(np.max(np.hypot(p[:, 0] - p[0, 0], p[:, 1] - p[0, 1])))
        turn = float(np.max(np.abs(p[:, 2] - p[0, 2])))
        return drift <= STATIC_MAX_DRIFT_M and turn <= STATIC_MAX_TURN_RAD
