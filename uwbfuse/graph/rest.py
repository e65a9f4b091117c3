# SPDX-License-Identifier: BSD-3-Clause
"""Ranges at a standstill: how much new evidence each one carries.

While the tag stands still, an anchor's successive ranges see one geometry and one
multipath: their errors share a part (the rest point's offset) and differ only by the
radio's noise. The LOS/NLOS model takes each range's error as independent N(0, sigma_los);
counted so, N ranges at rest give the online LOS/NLOS classes N times the evidence of one,
and on ISAS-Walk1's final rest the classes locked onto whichever LOS subset the rest point
first favoured (docs/results.md, "ISAS-Walk1's final standstill", session 40). With the
errors of one anchor's ranges in one rest equicorrelated at

    rho = 1 - s_w^2 / sigma_los^2

(s_w: the radio's noise from range to range at rest, estimated from the log's rests;
sigma_los: the model's LOS std, the whole error of one range), N such ranges carry the
evidence of n_eff(N) = N / (1 + (N - 1) rho) independent ones, so the n-th range of a rest
carries n_eff(n) - n_eff(n - 1) of one range's (`RestEvidence.weights`): its LOS/NLOS
log-likelihoods are scaled by that in the online classes (insertion filter, review, LOS
subset search). The range factors keep their whole information: taken away with a zero
velocity in its place, the rest was better on ISAS-Walk1 but a glide that the still test
passes for its first second then stopped the track (docs/results.md, session 40).

A standstill is a run of IMU blocks (`BLOCK_S`) that pass the start's still test
(`initialisation.block_still`: gyro and specific-force spreads under `[init]
standstill_gyro_max` and `standstill_accel_std_max`), with every wheel sample still
(`start.wheels_still`) where there are wheels, lasting `[init] standstill_window` or more,
whose ranges do not drift (a glide at constant velocity passes the IMU's test). Without an
IMU nothing here says the tag is still: every weight is 1.
"""

from __future__ import annotations

import bisect
import math
from collections import deque

import numpy as np

from uwbfuse.config import InitConfig
from uwbfuse.constants import (
    REST_HISTORY_S,
    REST_MIN_PAIRS,
    REST_RHO_REFRESH,
    REST_TREND_Z,
)
from uwbfuse.positioning.initialisation import BLOCK_S, block_still
from uwbfuse.positioning.start import wheels_still
from uwbfuse.streams import NS_PER_S

_BLOCK_NS = round(BLOCK_S * NS_PER_S)


def effective_count(n: int, rho: float) -> float:
    """Independent ranges worth n ranges whose errors are equicorrelated at rho."""
    return n / (1.0 + (n - 1) * rho) if n > 0 else 0.0


class RestEvidence:
    """Per range, the share of one independent range's evidence it carries (module
    docstring). Fed every IMU and wheel sample and, in time order, the ranges the graph
    uses (`weights`)."""

    def __init__(self, cfg: InitConfig, has_wheel: bool) -> None:
        self.cfg = cfg
        self.has_wheel = has_wheel
        self._imu: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []  # not yet in a block
        self._wheel_moving: list[int] = []  # stamps (ns) of moving wheel samples, recent
        self._block0: int | None = None  # start of the first block, ns
        self._imu_last = 0  # newest IMU stamp, ns
        self._done = 0  # blocks judged
        self._run: int | None = None  # start (ns) of the still run the newest block ends
        # (block end ns, start ns of its still run or None), the newest REST_HISTORY_S
        self._ends: deque[int] = deque()
        self._runs: deque[int | None] = deque()
        # the current rest (start ns, as the ranges last saw it), each anchor's last range
        # (m) and sums of its ranges in it, the |differences| of successive ranges in it
        # (m) and the radio noise s_w (m) last taken from them, at _rho_at pairs
        self._run_seen: int | None = None
        self._anchor: dict[int, tuple[float, list[float]]] = {}  # last z, `_trending` sums
        self._trend: dict[int, bool] = {}  # each anchor's ranges drift (`_trending`)
        self._dz: list[float] = []
        self._s_w = 0.0
        self._rho_at = 0
        self.weighed = 0  # ranges given a weight under 1 so far

    def add_imu(self, t_ns: np.ndarray, gyro: np.ndarray, accel: np.ndarray) -> None:
        """A time-sorted IMU batch: stamps ns, gyro rad/s, specific force m/s^2."""
        if len(t_ns) == 0:
            return
        self._imu.append((np.asarray(t_ns, np.int64), np.asarray(gyro, np.float64),
                          np.asarray(accel, np.float64)))
        if self._block0 is None:
            self._block0 = int(t_ns[0])
        self._imu_last = int(t_ns[-1])

    def add_wheel(self, t_ns: np.ndarray, v: np.ndarray, omega: np.ndarray) -> None:
        """A time-sorted wheel batch: stamps ns, speed m/s, yaw rate rad/s."""
        if len(t_ns) == 0:
            return
        moving = ~wheels_still(np.asarray(v), np.asarray(omega))
        self._wheel_moving.extend(np.asarray(t_ns, np.int64)[moving].tolist())

    def _judge(self) -> None:
        """Judge every block the IMU samples so far complete (when the ranges ask: the
        wheel samples of those blocks are in by then)."""
        if self._block0 is None:
            return
        n = (self._imu_last - self._block0) // _BLOCK_NS
        if n <= self._done:
            return
        ends = self._block0 + _BLOCK_NS * np.arange(self._done + 1, n + 1, dtype=np.int64)
        wheels = np.array([self._wheels_still(end) for end in ends.tolist()])
        if wheels.any():  # the IMU's tests only where the wheels leave a block still
            t = np.concatenate([c[0] for c in self._imu])
            g = np.concatenate([c[1] for c in self._imu])
            a = np.concatenate([c[2] for c in self._imu])
            self._imu = [(t, g, a)]
            # a block without IMU samples (a dropout) says nothing: not still
            filled = np.diff(np.searchsorted(
                t, np.concatenate([[ends[0] - _BLOCK_NS], ends]), side="right")) >= 2
            still = (wheels & filled
                     & block_still(t, g, ends, None, self.cfg.standstill_gyro_max)
                     & block_still(t, a, ends, None, self.cfg.standstill_accel_std_max))
        else:
            still = wheels
        for end, ok in zip(ends.tolist(), still.tolist(), strict=True):
            if not ok:
                self._run = None
            elif self._run is None:
                self._run = end - _BLOCK_NS
            self._ends.append(end)
            self._runs.append(self._run)
        self._done = n
        while self._ends and self._ends[0] < self._ends[-1] - REST_HISTORY_S * NS_PER_S:
            self._ends.popleft()
            self._runs.popleft()
        # the samples of blocks to come, without joining the chunks (one a batch)
        end = int(ends[-1])
        self._imu = [(c[0][k:], c[1][k:], c[2][k:]) for c in self._imu
                     if (k := int(np.searchsorted(c[0], end, side="right"))) < len(c[0])]

    def _wheels_still(self, end: int) -> bool:
        """No wheel sample in the block ending at `end` (ns) moving; True without wheels."""
        if not self.has_wheel:
            return True
        mv = self._wheel_moving
        i = bisect.bisect_right(mv, end - _BLOCK_NS)
        del mv[:max(i - 1, 0)]
        return not any(end - _BLOCK_NS < s <= end for s in mv)

    def _run_at(self, t: int) -> int | None:
        """Start (ns) of the still run that the last block judged before `t` belongs to;
        None where that block is not the one just before t's (an IMU dropout: no verdict).
        The blocks must have been judged (`_judge`)."""
        i = bisect.bisect_right(self._ends, t) - 1
        if i < 0 or t - self._ends[i] > _BLOCK_NS:
            return None
        return self._runs[i]

    def rho(self, sigma_los: float) -> float:
        """Correlation of one anchor's range errors within the current rest (module
        docstring), from its successive ranges: the radio's noise s_w = 1.4826 median |z_i -
        z_i-1| / sqrt(2), robust to the radio's quantisation and outliers; 0 until
        REST_MIN_PAIRS pairs have shown it."""
        n = len(self._dz)
        if n < REST_MIN_PAIRS:
            return 0.0
        if n >= self._rho_at * REST_RHO_REFRESH:  # the median, again as the run's pairs grow
            s_w = 1.4826 * float(np.median(self._dz)) / math.sqrt(2.0)
            self._s_w, self._rho_at = s_w, n
        return min(max(1.0 - self._s_w**2 / sigma_los**2, 0.0), 1.0)

    def _trending(self, sums: list[float], span_s: float, sigma_los: float) -> bool:
        """Whether one anchor's ranges in the rest drift (their sums: count, t, t^2, z, t z;
        t s from the rest's start, `span_s` s of it so far): the least-squares slope beyond
        REST_TREND_Z standard errors (white noise s_w about a line) and, over the rest, a
        change of more than `sigma_los` (m), one range's whole LOS error: then the ranges
        no longer share one geometry's error. A tag that glides at constant velocity
        passes the IMU's still test; its ranges change at up to its speed (a real rest's
        ranges wander by centimetres, which the test alone would call drift)."""
        n, st, stt, sz, stz = sums
        sxx = stt - st * st / n
        if n < 3 or sxx <= 0.0:
            return False
        slope = abs(stz - st * sz / n) / sxx
        return slope * math.sqrt(sxx) > REST_TREND_Z * self._s_w and slope * span_s > sigma_los

    def weights(self, t_ns: np.ndarray, anchor: np.ndarray, z: np.ndarray,
                sigma_los: float) -> np.ndarray:
        """Each range's share (N,) of one independent range's evidence, for the graph's
        ranges in time order (stamps ns, anchor index, m; each range given once):
        n_eff(n) - n_eff(n - 1) for the n-th range of its anchor in a standstill that
        has lasted `[init] standstill_window` and whose ranges do not drift, else 1.
        `sigma_los`: the model's LOS std (m) the evidence is weighed with."""
        w = np.ones(len(t_ns))
        window = round(self.cfg.standstill_window * NS_PER_S)
        self._judge()  # the IMU and wheel samples so far: the same for every range given
        rows = zip(np.asarray(t_ns).tolist(), np.asarray(anchor).tolist(),
                   np.asarray(z, np.float64).tolist(), strict=True)
        for i, (t, a, zi) in enumerate(rows):
            run = self._run_at(t)
            if run != self._run_seen:  # a new rest (or motion): its own pairs
                self._run_seen = run
                self._dz, self._rho_at = [], 0
                self._anchor.clear()
                self._trend.clear()
            if run is None:
                continue
            prev = self._anchor.get(a)
            if prev is None:
                sums = [0.0] * 5
            else:
                sums = prev[1]
                self._dz.append(abs(zi - prev[0]))
            ts = (t - run) / NS_PER_S
            for j, x in enumerate((1.0, ts, ts * ts, zi, ts * zi)):
                sums[j] += x
            self._anchor[a] = (zi, sums)
            r = self.rho(sigma_los)
            if r > 0.0:
                self._trend[a] = self._trending(sums, ts, sigma_los)
            if t - run >= window and not any(self._trend.values()):
                n = int(sums[0])
                w[i] = effective_count(n, r) - effective_count(n - 1, r)
                self.weighed += int(w[i] < 1.0)
        return w
