# SPDX-License-Identifier: BSD-3-Clause
"""The live API: `Localizer` takes sensor samples as they arrive and answers the pose.

It runs the same streaming estimator as `uwbfuse run --method isam2` (the same
`Config`, anchor map and method), fed exactly as `run` feeds it: on the output grid
(`[output] rate`, from the first sample's stamp), the samples of each epoch t_k (stamps in
(t_{k-1}, t_k]) go in stream by stream, then the estimator steps to t_k. An epoch is
processed once a sample stamped more than `reorder_window_s` after it has arrived, so
the estimate at t_k uses only data stamped at or before t_k (causal), and each epoch costs
one bounded estimator step: nothing is re-run.

Times: an integer (Python int or numpy integer) is nanoseconds, a float is seconds; both
on the sensors' stamp clock (`header.stamp`).

Poses: base frame in the map frame (the anchor frame, z up), position in metres,
quaternion (x, y, z, w), covariance 6x6 in ROS order (x, y, z, rot x, rot y, rot z; map
axes) as in `geometry_msgs/msg/PoseWithCovariance`.

Bad samples are never raised on: a sample with a non-finite or implausible value, an
unknown anchor, a range outside `[uwb] min_range, max_range`, an exact duplicate, or a
stamp at or before an epoch already processed (late beyond the reorder window) is dropped
and counted in `skipped` under the reader's reason names. A wrongly shaped argument (a
gyro that is not a 3-vector, columns of different lengths) is a `LocalizerError`.
"""

from __future__ import annotations

import bisect
import logging
from collections import Counter, deque
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from uwbfuse.config import Config
from uwbfuse.constants import FORGET_EVERY_S
from uwbfuse.errors import AnchorMapError, UwbfuseError
from uwbfuse.io.reader import (
    MAX_ACCEL_M_S2,
    MAX_GYRO_RAD_S,
    MAX_WHEEL_SPEED_M_S,
    MAX_WHEEL_YAW_RATE_RAD_S,
    SKIP_BAD_STAMP,
    SKIP_IMPLAUSIBLE,
    SKIP_NON_FINITE_RANGE,
    SKIP_NON_POSITIVE_RANGE,
    SKIP_RANGE_BOUNDS,
    SKIP_UNKNOWN_ANCHOR,
    skip_duplicate,
    skip_non_finite,
    stamp_value_order,
)
from uwbfuse.methods import Method, make_estimator
from uwbfuse.prestart import PreStart
from uwbfuse.streams import NS_PER_S, AnchorMap

log = logging.getLogger(__name__)

SKIP_LATE = "late sample (stamped at or before an epoch already processed)"
SENSORS = ("imu", "wheel", "uwb")


class LocalizerError(UwbfuseError):
    """A `Localizer` argument is malformed (shapes, method) or it is used after `finish`."""


@dataclass(frozen=True)
class Pose:
    """A pose of the base frame in the map frame at `t_ns` (int ns, stamp clock).

    `position` (3,) m, `quat_xyzw` (4,), `covariance` (6,6) in ROS order (x, y, z, rot x,
    rot y, rot z; map axes) or None where the estimator has none. `provisional`: the
    estimator has not started yet (heading needs some motion) and this is the UWB-only
    fix (or the standstill fix) that `uwbfuse run` writes for those epochs too.
    """

    t_ns: int
    position: np.ndarray
    quat_xyzw: np.ndarray
    covariance: np.ndarray | None
    provisional: bool

    @property
    def t_s(self) -> float:
        """The stamp in seconds."""
        return self.t_ns / NS_PER_S


def to_ns(t: Any) -> np.ndarray:
    """Stamps as int64 ns: integers are ns, floats are seconds (scalars or arrays)."""
    a = np.asarray(t)
    if a.dtype.kind in "iu":
        return a.astype(np.int64).reshape(-1)
    if a.dtype.kind == "f":
        with np.errstate(invalid="ignore"):
            ns = np.where(np.isfinite(a), np.round(a * NS_PER_S), -1.0)
        return ns.astype(np.int64).reshape(-1)
    raise LocalizerError(f"stamps must be integers (ns) or floats (s), not {a.dtype}")


def _column(x: Any, n: int, width: int | None, what: str) -> np.ndarray:
    """`x` as float64 (n,) or (n, width); a lone sample may come unbatched."""
    a = np.asarray(x, dtype=np.float64)
    shape = (n,) if width is None else (n, width)
    if a.shape != shape:
        if a.size == int(np.prod(shape)) and n == 1:
            return a.reshape(shape)
        raise LocalizerError(f"{what}: expected shape {shape}, got {a.shape}")
    return a


class _Pending:
    """Samples of one stream not yet given to the estimator (stamps after the last
    processed epoch), kept as a list of batches and merged when an epoch is processed."""

    def __init__(self) -> None:
        self.chunks: list[tuple[np.ndarray, ...]] = []
        self.n = 0

    def add(self, cols: tuple[np.ndarray, ...]) -> None:
        if len(cols[0]):
            self.chunks.append(cols)
            self.n += len(cols[0])

    def merged(self) -> tuple[np.ndarray, ...] | None:
        if not self.chunks:
            return None
        if len(self.chunks) > 1:
            self.chunks = [tuple(np.concatenate(c) for c in zip(*self.chunks, strict=True))]
        return self.chunks[0]

    def keep(self, cols: tuple[np.ndarray, ...]) -> None:
        self.chunks = [cols] if len(cols[0]) else []
        self.n = len(cols[0])


def _sorted_unique(cols: tuple[np.ndarray, ...], role: str,
                   skipped: Counter[str]) -> tuple[np.ndarray, ...]:
    """`cols` (stamps first) sorted by stamp, exact duplicates dropped and counted; ties
    ordered by the values as the log reader orders them (stamp, then each column)."""
    t = cols[0]
    if len(t) < 2 or bool(np.all(t[1:] > t[:-1])):
        return cols
    order, dup = stamp_value_order(t, list(cols[1:]))
    if dup.any():
        skipped[skip_duplicate(role)] += int(dup.sum())
    kept = order[~dup]
    return tuple(c[kept] for c in cols)


class Localizer:
    """Live localisation: add samples as they arrive, ask for the pose at any time.

    `config` (default: `Config()` defaults) and `anchors` (id -> [x, y, z] m in the map
    frame, or an `AnchorMap`; default: the config's `[anchors]`) are those of
    `uwbfuse run`; `method` is a causal method (`isam2` by default; `ekf`, `ukf`, `wls`,
    `lkf`, `imu`, `odom` work too; `batch` and `isam2-smoothed` are offline). `sensors`
    names the streams the vehicle has (subset of "imu", "wheel", "uwb"): the estimator is
    built for them, as `run` builds it for the streams a log has.

    Ordering: samples may arrive out of stamp order by up to `reorder_window_s` seconds
    (per stream or across streams); an epoch is processed once a sample stamped more than
    that after it has arrived, so each pose is out `reorder_window_s` plus up to one output
    period after its epoch. A sample stamped at or before an epoch already processed is
    dropped and counted (`skipped`, reason `SKIP_LATE`).

    Memory: samples wait only until their epoch is processed; poses are kept for
    `history_s` seconds for `pose(t)`; every FORGET_EVERY_S the estimator forgets what
    only offline outputs need from before twice its lag (`forget_before`), so memory
    stays flat, and `report()` counts the ranges of that recent past only.
    `covariance`: compute the poses' covariances (the graph's marginals cost time;
    `[graph] marginal_covariances` true/false overrides).
    """

    def __init__(
        self,
        config: Config | None = None,
        anchors: Mapping[str, Sequence[float]] | AnchorMap | None = None,
        *,
        method: Method | str = Method.ISAM2,
        sensors: Iterable[str] = SENSORS,
        reorder_window_s: float = 0.05,
        history_s: float = 60.0,
        covariance: bool = True,
    ) -> None:
        from uwbfuse.pipeline import with_covariance

        cfg = config if config is not None else Config()
        try:
            self.method = Method(method)
        except ValueError:
            raise LocalizerError(f"unknown method {method!r}") from None
        if self.method.spec.smoothed:
            raise LocalizerError(f"method {self.method.value} is offline (smoothed): the "
                                 "live API runs causal methods (isam2, ekf, ...)")
        streams = frozenset(sensors)
        if not streams or not streams <= set(SENSORS):
            raise LocalizerError(f"sensors must be a non-empty subset of {SENSORS}, "
                                 f"not {sorted(streams)}")
        if isinstance(anchors, AnchorMap):
            amap: AnchorMap | None = anchors
        elif anchors is not None:
            amap = AnchorMap.from_dict(dict(anchors))
        else:
            amap = AnchorMap.from_dict(dict(cfg.anchors)) if cfg.anchors else None
        if "uwb" in streams and self.method.uses_ranges and (amap is None or not len(amap)):
            raise AnchorMapError("Localizer: no anchor map: pass anchors= or give the "
                                 "config an [anchors] table")
        if reorder_window_s < 0 or history_s < 0:
            raise LocalizerError("reorder_window_s and history_s must be >= 0")
        self.config = with_covariance(cfg, covariance)
        self.anchors = amap
        self.sensors = streams
        self.reorder_window_ns = round(reorder_window_s * NS_PER_S)
        self.history_ns = round(history_s * NS_PER_S)
        self.period_ns = max(round(NS_PER_S / self.config.output.rate), 1)
        # as `pipeline.estimate`: `PreStart` answers until the method has its own start
        self._est = PreStart.around(make_estimator(self.method, self.config, amap, streams),
                                    self.method, self.config, amap, streams)
        self._index = {} if amap is None else {a: i for i, a in enumerate(amap.ids)}
        u = self.config.uwb
        self._offset = (None if amap is None or not u.range_offset else
                        np.array([u.range_offset.get(a, 0.0) for a in amap.ids]))
        self._pending = {s: _Pending() for s in SENSORS}
        self._newest: int | None = None  # newest accepted stamp
        self._origin: int | None = None  # the output grid's first epoch
        self._next_k = 0  # index of the next epoch to process
        self._done_t: int | None = None  # the last processed epoch
        self._closed = False
        self._forget_at = -(1 << 62)
        self._hist_t: deque[int] = deque()
        self._hist: deque[Pose] = deque()
        self._latest: Pose | None = None
        self.skipped: Counter[str] = Counter()
        """Dropped samples by reason (the reader's reason names, plus `SKIP_LATE`)."""
        self.epochs = 0
        """Epochs processed (estimator steps)."""

    # ------------------------------------------------------------------ input
    def add_imu(self, t: Any, gyro: Any, accel: Any) -> None:
        """IMU sample(s): stamp(s) (see module docstring), angular velocity (3,) or
        (N,3) rad/s and specific force (3,) or (N,3) m/s^2 (+9.81 on z at rest), IMU
        frame (`[extrinsics] imu_in_base`)."""
        t_ns = to_ns(t)
        g = _column(gyro, len(t_ns), 3, "imu gyro")
        a = _column(accel, len(t_ns), 3, "imu accel")
        ok = self._good("imu", t_ns, [g, a], [MAX_GYRO_RAD_S, MAX_ACCEL_M_S2])
        self._accept("imu", (t_ns[ok], g[ok], a[ok]))

    def add_wheel(self, t: Any, v: Any, omega: Any) -> None:
        """Wheel odometry sample(s) of the base frame: stamp(s), forward speed m/s and yaw
        rate rad/s, each the mean over the interval ending at its stamp."""
        t_ns = to_ns(t)
        vv = _column(v, len(t_ns), None, "wheel v")
        w = _column(omega, len(t_ns), None, "wheel omega")
        ok = self._good("wheel", t_ns, [vv, w], [MAX_WHEEL_SPEED_M_S, MAX_WHEEL_YAW_RATE_RAD_S])
        self._accept("wheel", (t_ns[ok], vv[ok], w[ok]))

    def add_range(self, t: Any, anchor_id: Any, range_m: Any) -> None:
        """UWB range(s): stamp(s), anchor id(s) (compared as strings: 7475 is "7475") and
        tag-to-anchor distance(s) in metres (the `[uwb.range_offset]` is subtracted)."""
        t_ns = to_ns(t)
        ids = np.asarray(anchor_id, dtype=object).reshape(-1)
        rng = _column(range_m, len(t_ns), None, "range")
        if len(ids) != len(t_ns):
            raise LocalizerError(f"range: {len(t_ns)} stamps but {len(ids)} anchor ids")
        anchor = np.fromiter((self._index.get(str(a), -1) for a in ids.tolist()),
                             dtype=np.int32, count=len(ids))
        u = self.config.uwb
        keep = t_ns >= 0
        self._skip(SKIP_BAD_STAMP, ~keep)
        with np.errstate(invalid="ignore"):
            for reason, bad in ((SKIP_UNKNOWN_ANCHOR, anchor < 0),
                                (SKIP_NON_FINITE_RANGE, ~np.isfinite(rng)),
                                (SKIP_NON_POSITIVE_RANGE, rng <= 0),
                                (SKIP_RANGE_BOUNDS, (rng < u.min_range) | (rng > u.max_range))):
                self._skip(reason, keep & bad)
                keep &= ~bad
        t_ns, anchor, rng = t_ns[keep], anchor[keep], rng[keep]
        if self._offset is not None:
            rng = rng - self._offset[anchor]
        self._accept("uwb", (t_ns, anchor, rng))

    def _skip(self, reason: str, bad: np.ndarray) -> None:
        n = int(np.count_nonzero(bad))
        if n:
            self.skipped[reason] += n

    def _good(self, role: str, t_ns: np.ndarray, values: list[np.ndarray],
              bounds: list[float]) -> np.ndarray:
        """Rows with a usable stamp and finite values within the reader's physical bounds."""
        good_t = t_ns >= 0
        finite = np.ones(len(t_ns), dtype=bool)
        plausible = np.ones(len(t_ns), dtype=bool)
        for a, bound in zip(values, bounds, strict=True):
            ok = np.isfinite(a)
            finite &= ok if ok.ndim == 1 else ok.all(axis=1)
            with np.errstate(invalid="ignore"):
                inside = ~ok | (np.abs(a) <= bound)
            plausible &= inside if inside.ndim == 1 else inside.all(axis=1)
        self._skip(SKIP_BAD_STAMP, ~good_t)
        self._skip(skip_non_finite(role), good_t & ~finite)
        self._skip(SKIP_IMPLAUSIBLE.format(role), good_t & finite & ~plausible)
        return good_t & finite & plausible

    def _accept(self, role: str, cols: tuple[np.ndarray, ...]) -> None:
        if self._closed:
            raise LocalizerError("Localizer: samples added after finish()")
        if role not in self.sensors:
            self.skipped[f"{role} sample (not among the Localizer's sensors)"] += len(cols[0])
            return
        t = cols[0]
        if not len(t):
            return
        if self._done_t is not None:
            late = t <= self._done_t
            if late.any():
                self.skipped[SKIP_LATE] += int(late.sum())
                cols = tuple(c[~late] for c in cols)
                t = cols[0]
                if not len(t):
                    return
        self._pending[role].add(cols)
        newest = int(t.max())
        if self._newest is None or newest > self._newest:
            self._newest = newest
        self._advance(self._newest - self.reorder_window_ns)

    # ------------------------------------------------------------------ processing
    def _epoch(self, k: int) -> int:
        assert self._origin is not None
        return self._origin + k * self.period_ns

    def _first_pending(self) -> int | None:
        firsts = [int(c[0].min()) for p in self._pending.values() for c in p.chunks]
        return min(firsts) if firsts else None

    def _advance(self, watermark: int, final: bool = False) -> None:
        """Process every epoch stamped before `watermark` (and, when `final`, the last
        stamp as a closing epoch, as `run`'s output grid ends with it)."""
        if self._origin is None:
            first = self._first_pending()
            if first is None or (first >= watermark and not final):
                return
            self._origin = first
        epochs: list[int] = []
        while self._epoch(self._next_k) < watermark:
            epochs.append(self._epoch(self._next_k))
            self._next_k += 1
        last = epochs[-1] if epochs else self._done_t
        if final and self._newest is not None and (last is None or last < self._newest):
            epochs.append(self._newest)
        if not epochs:
            return
        merged = {}
        for role in SENSORS:
            cols = self._pending[role].merged()
            if cols is not None:
                merged[role] = _sorted_unique(cols, role, self.skipped)
        starts = dict.fromkeys(merged, 0)
        adders = {"imu": self._est.add_imu, "wheel": self._est.add_wheel,
                  "uwb": self._est.add_ranges}
        for t_k in epochs:
            for role, cols in merged.items():  # imu, wheel, uwb: as `run_streaming`
                e = int(np.searchsorted(cols[0], t_k, side="right"))
                if e > starts[role]:
                    adders[role](*(c[starts[role]:e] for c in cols))
                    starts[role] = e
            self._est.step(int(t_k))
            self._done_t = int(t_k)
            self.epochs += 1
            self._record(int(t_k))
        for role, cols in merged.items():
            self._pending[role].keep(tuple(c[starts[role]:] for c in cols))
        if self._done_t is not None and self._done_t >= self._forget_at:
            # flat memory: the estimator drops what only offline outputs and the report's
            # totals need, from before twice its lag
            self._forget_at = self._done_t + round(FORGET_EVERY_S * NS_PER_S)
            self._est.forget_before(self._done_t - round(2 * self.config.graph.lag * NS_PER_S))

    def _record(self, t_k: int) -> None:
        est = self._est.estimate()
        if est is None:
            return
        if est.t_ns != t_k:
            raise RuntimeError(f"estimate stamped {est.t_ns} ns at epoch {t_k} ns")
        prov = self._est.provisional
        pose = Pose(t_k, np.asarray(est.position, np.float64),
                    np.asarray(est.quat_xyzw, np.float64),
                    None if est.covariance is None else np.asarray(est.covariance), prov)
        self._latest = pose
        self._hist_t.append(t_k)
        self._hist.append(pose)
        while self._hist_t and self._hist_t[0] < t_k - self.history_ns:
            self._hist_t.popleft()
            self._hist.popleft()

    def finish(self) -> Pose | None:
        """End of the input: process the epochs still waiting (the last at the newest
        stamp, as `run` ends its grid), close the localizer and return `latest()`."""
        if not self._closed and self._newest is not None:
            self._advance(self._newest + 1, final=True)
        self._closed = True
        return self._latest

    # ------------------------------------------------------------------ output
    def latest(self) -> Pose | None:
        """The newest pose (at the newest processed epoch), or None before the first one:
        no epoch processed yet, or no fix yet (too few anchors heard)."""
        return self._latest

    def pose(self, t: Any) -> Pose | None:
        """The causal pose at time `t`: the estimate made at the newest processed epoch at
        or before `t` (its `t_ns` says which), from data stamped up to that epoch.

        None when `t` is after the newest processed epoch by more than one output period
        (not known yet: see `latest()`), before the oldest pose kept (`history_s`), or
        before the estimator has any pose (before its first fix)."""
        t_ns = int(to_ns(t)[0])
        if not self._hist_t or t_ns > self._hist_t[-1] + self.period_ns:
            return None
        i = bisect.bisect_right(self._hist_t, t_ns) - 1
        if i < 0:
            return None
        return self._hist[i]

    def report(self) -> dict[str, Any]:
        """The estimator's report (as in `uwbfuse run --report`) plus `skipped` samples
        and `epochs` processed."""
        out = dict(self._est.report())
        out["skipped_samples"] = dict(self.skipped)
        out["epochs"] = self.epochs
        return out
