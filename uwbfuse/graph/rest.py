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
subset search).

The IMU's still test sees spreads, not means: a glide at constant velocity and a gentle
constant acceleration pass it as a rest does, so a still run says nothing of the velocity
by itself. A run is held as a rest (`held`, `at_rest`) only on two tests at false-alarm
probability REST_FALSE_ALARM each (docs/results.md, "A standstill test that tells a glide
from a rest", session 41):
- entering (`decide`): the graph's smoothed velocity at the run's first keyframe, whose
  velocity the IMU carried in from the motion before, is zero within its marginal
  covariance (chi-square, 3 degrees of freedom). A run that began before the graph's
  start has no such estimate (the start's velocity prior is an assumption): never held.
- staying (`at_rest`): the velocity the IMU integrates from the run's first
  `standstill_window` (`QuietDrift`: specific force minus the window's mean, turned by the
  gyro's rotation since) is zero within its noise; a start the still test cannot see ends
  the rest.
While a run is held, the graph takes a zero velocity at its keyframes
(`zero_velocity_sigma`) and the run's range factors keep only their share of one range's
information (the share the classes get): without the zero velocity, ranges so weighed no
longer hold the track (session 40).

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
from scipy.spatial.transform import Rotation
from scipy.stats import chi2

from uwbfuse.config import InitConfig
from uwbfuse.constants import (
    REST_FALSE_ALARM,
    REST_HISTORY_S,
    REST_MIN_PAIRS,
    REST_RHO_REFRESH,
    REST_TREND_Z,
)
from uwbfuse.positioning.initialisation import BLOCK_S, block_still
from uwbfuse.positioning.start import wheels_still
from uwbfuse.streams import NS_PER_S

_BLOCK_NS = round(BLOCK_S * NS_PER_S)
# the chi-square (3 degrees of freedom) a velocity at rest stays under but for
# REST_FALSE_ALARM of the time
_CHI2_REST = float(chi2.ppf(1.0 - REST_FALSE_ALARM, 3))


def effective_count(n: int, rho: float) -> float:
    """Independent ranges worth n ranges whose errors are equicorrelated at rho."""
    return n / (1.0 + (n - 1) * rho) if n > 0 else 0.0


class QuietDrift:
    """The velocity (m/s, 3) the IMU integrates over a still run after its first
    `window_ns`: each specific-force sample turned into the window's body frame by the
    gyro's rotation since (rate minus the window's mean rate: at rest the gyro reads its
    bias), minus the window's mean specific force (gravity and the accelerometer bias, as
    long as the base does not move). Zero at rest; a start from rest that the still test
    cannot see (a constant acceleration has no spread) grows it at the acceleration."""

    def __init__(self, start_ns: int, window_ns: int) -> None:
        self.start = start_ns
        self.ref_end = start_ns + window_ns
        self._window_s = window_ns / NS_PER_S
        self._n = 0  # reference samples
        # sums over the reference of its specific force, its square, the rate, its square
        self._sums = np.zeros((4, 3))
        self._theta = np.zeros(3)  # rotation since the reference, rad (its body frame)
        self._t = self.ref_end  # newest sample integrated, ns
        self.dv = np.zeros(3)

    def add(self, t: np.ndarray, gyro: np.ndarray, accel: np.ndarray) -> None:
        """Time-sorted samples of the run (stamps ns, rad/s, m/s^2), each given once."""
        ref = t < self.ref_end
        if ref.any():
            self._n += int(ref.sum())
            self._sums += np.stack([accel[ref].sum(0), (accel[ref] ** 2).sum(0),
                                    gyro[ref].sum(0), (gyro[ref] ** 2).sum(0)])
        if self._n < 2 or ref.all():
            return
        t, gyro, accel = t[~ref], gyro[~ref], accel[~ref]
        f_ref, w_ref = self._sums[0] / self._n, self._sums[2] / self._n
        dt = np.diff(t, prepend=self._t) / NS_PER_S
        theta = self._theta + np.cumsum((gyro - w_ref) * dt[:, None], axis=0)
        turned = Rotation.from_rotvec(theta).apply(accel)
        self.dv += ((turned - f_ref) * dt[:, None]).sum(0)
        self._theta, self._t = theta[-1], int(t[-1])

    def chi2(self, sigma_zero: float) -> float:
        """dv against its noise at rest, summed over the axes. Over the span T since the
        reference (n samples, period dt), from the reference's spreads of specific force s_f
        (m/s^2) and rate s_w (rad/s): the specific force's white noise, s_f^2 T dt, and its
        mean's error, s_f^2 T^2 / n; the tilt that the rate's mean error (s_w^2 / n, T^4 /
        4) and white noise (s_w^2 dt, T^3 / 3) leave, turning the mean specific force f
        (|f|^2 - f_i^2 on axis i); the zero velocities at both ends, `sigma_zero` m/s each."""
        if self._n < 2:
            return 0.0
        n = self._n
        f, w = self._sums[0] / n, self._sums[2] / n
        var_f = np.maximum(self._sums[1] / n - f**2, 0.0)
        var_w = float(np.mean(np.maximum(self._sums[3] / n - w**2, 0.0)))
        span = (self._t - self.ref_end) / NS_PER_S
        dt = self._window_s / n  # the sample period, s
        tilt = (float(f @ f) - f**2) * var_w * (span**4 / (4.0 * n) + dt * span**3 / 3.0)
        var = var_f * (span * dt + span**2 / n) + tilt + 2.0 * sigma_zero**2
        return float(np.sum(self.dv**2 / var))


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
        # each recent still run's verdict (start ns: held as a rest), `decide`/`at_rest`
        self._verdict: dict[int, bool] = {}
        self._drift: QuietDrift | None = None  # the current still run's
        # m/s: the zero velocity's std, the velocity a specific force within the still
        # test's spread (standstill_accel_std_max) builds over one still block
        self.zero_velocity_sigma = cfg.standstill_accel_std_max * BLOCK_S
        self.zero_velocities = 0  # keyframes held at rest so far

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
        if self._run is not None:  # the current still run's samples: its IMU drift
            if self._drift is None or self._drift.start != self._run:
                self._drift = QuietDrift(self._run, round(self.cfg.standstill_window
                                                          * NS_PER_S))
            lo = max(self._run, int(ends[0]) - _BLOCK_NS)
            k0, k1 = np.searchsorted(t, [lo, int(ends[-1])], side="right")
            self._drift.add(t[k0:k1], g[k0:k1], a[k0:k1])
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
            if t - run >= window and (self._verdict.get(run, False)
                                      or not any(self._trend.values())):
                n = int(sums[0])
                w[i] = effective_count(n, r) - effective_count(n - 1, r)
                self.weighed += int(w[i] < 1.0)
        return w

    def pending(self, t_ns: int) -> int | None:
        """The start (ns) of the still run at t_ns (ns) when it has lasted
        `standstill_window` and awaits its verdict (`decide`), else None."""
        self._judge()
        run = self._run_at(t_ns)
        if (run is None or run in self._verdict
                or t_ns - run < round(self.cfg.standstill_window * NS_PER_S)):
            return None
        return run

    def decide(self, run: int, v: np.ndarray | None, cov: np.ndarray | None) -> bool:
        """Judge the still run that began at `run` (ns) from the graph's smoothed velocity
        `v` (m/s, map) at the run's first keyframe and its marginal covariance `cov`
        ((m/s)^2; None: the graph has no velocity from before the run): a rest (held, True)
        when v' cov^-1 v is under the chi-square quantile at 1 - REST_FALSE_ALARM."""
        held = False
        if v is not None and cov is not None:
            try:
                held = float(v @ np.linalg.solve(cov, v)) < _CHI2_REST
            except np.linalg.LinAlgError:
                held = False
        recent = set(self._runs)
        self._verdict = {r: h for r, h in self._verdict.items() if r in recent}
        self._verdict[run] = held
        return held

    def at_rest(self, t_a: int, t_b: int) -> bool:
        """Whether the graph takes a zero velocity over t_a..t_b (ns, a keyframe interval):
        both in a still run held as a rest (`decide`) whose IMU-integrated velocity
        (`QuietDrift`) is zero within its noise; when it is no longer, the run is a rest no
        more (a start the still test cannot see)."""
        self._judge()
        run = self._run_at(t_b)
        if run is None or run > t_a or not self._verdict.get(run, False):
            return False
        d = self._drift
        if d is not None and d.start == run and d.chi2(self.zero_velocity_sigma) > _CHI2_REST:
            self._verdict[run] = False
            return False
        self.zero_velocities += 1
        return True

    def held(self, t_ns: np.ndarray) -> np.ndarray:
        """Whether each stamp (ns) lies in a still run held as a rest (`decide`), (N,)."""
        self._judge()
        runs = [self._run_at(t) for t in np.asarray(t_ns).tolist()]
        return np.array([r is not None and self._verdict.get(r, False) for r in runs], bool)
