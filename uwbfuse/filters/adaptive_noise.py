# SPDX-License-Identifier: BSD-3-Clause
"""Measurement noise of the Kalman baselines (EKF, UKF), estimated from their innovations.

Ranges (`RangeNoise`): each range enters the filter as one scalar update. Its innovation y
(measured minus predicted range, m) with prediction variance s = h P h^T (m^2) is weighed
with the per-range view of the project's LOS/NLOS range-error model (`uwbfuse.nlos`: LOS
N(0, los_std^2), NLOS N(nlos_mean, nlos_std^2)): the posterior NLOS probability p of the range
(`nlos_probability`, the prediction variance added to both components) gives the moment-
matched mixture posterior as the measurement, i.e. the expected NLOS excess p nlos_mean is
removed from the range and its variance is (1-p) los^2 + p nlos^2 + p (1-p) nlos_mean^2
(variance inflation: a range that looks NLOS counts for less, and a LOS one for the radio's
own noise).

NLOS persists for a while behind the same obstacle, so each anchor's prior for its next
range is its last posterior carried through a two-state Markov chain: (1 - q) p_last +
q p_nlos, with q the switching rate.

Every parameter comes from the log: the mixture is re-fitted by EM (`fit_nlos_mixture`)
over the innovations of the last `RANGE_NOISE_WINDOW` accepted ranges every `REFIT_EVERY`
ranges, with the model's per-range values (`[nlos] range_*`) as a prior worth
`PRIOR_RANGES` ranges; the switching rate is the expected number of LOS/NLOS changes
between consecutive ranges of an anchor (from the posteriors), with the model's `p_switch`
(`[nlos] switch`) as its prior, same weight.

Gating: a range whose squared innovation, after the mixture correction, exceeds the
chi-square quantile of `[filter] gate_probability` times its variance (mixture plus
prediction) is rejected (gross outliers, short or long). The prediction variance grows
through an outage with the process noise, so the gate widens with it and does not lock
out; the filters' divergence recovery (`base.StreamingFilter`) covers a state that is off
by more than its covariance says.

Wheel speeds and the planar floor constraint (`InnovationVariance`): covariance matching
(Mehra 1970): for a consistent filter E[y^2] = h P h^T + r for every measurement row, so r =
E[y^2 - h P h^T] over the recent rows of its kind, with the configured variance as a prior
worth `PRIOR_ROWS` rows. Each row counts at its positive part, max(y^2 - h P h^T, 0):
conservative (biased high where the prediction variance dominates), which leaves room for
errors the white model does not have (a wheel scale error, slip that lasts a turn). A skid-
steer vehicle that slips sideways in turns, or a floor that rolls the vehicle by 12 degrees,
loosens its own constraint; encoders better than the configured default tighten theirs.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from uwbfuse.config import Config
from uwbfuse.constants import (
    MATCHED_VARIANCE_MIN_SHARE,
    MEMORY_ROWS,
    MIN_LOS_STD,
    P_BOUNDS,
    PRIOR_RANGES,
    PRIOR_ROWS,
    RANGE_NOISE_WINDOW,
    REFIT_EVERY,
)
from uwbfuse.filters.models import F64, gate_threshold
from uwbfuse.nlos import NlosModel, NlosParams, fit_nlos_mixture, nlos_probability

_SQRT_2PI = math.sqrt(2 * math.pi)


def _nlos_probability_one(
    y: float, los_std: float, nlos_mean: float, nlos_std: float, prior: float, s: float
) -> float:
    """`nlos.nlos_probability` for one finite residual y (m) with extra variance s
    (m^2), in floats (exp through numpy, as the array version, so results are identical)."""
    los = math.sqrt(max(los_std, MIN_LOS_STD) ** 2 + s)
    nl = math.sqrt(nlos_std**2 + s)
    zn = (y - nlos_mean) / nl
    zl = (y - 0.0) / los
    pn = prior * (float(np.exp(np.float64(-0.5 * (zn * zn)))) / (_SQRT_2PI * nl))
    pl = (1.0 - prior) * (float(np.exp(np.float64(-0.5 * (zl * zl)))) / (_SQRT_2PI * los))
    total = pn + pl
    p = pn / total if total > 0.0 else math.nan
    if not math.isfinite(p):
        return 1.0 if y > nlos_mean else 0.0
    return p


def mixture_log_density(
    y: F64, los_std: float, nlos_mean: float, nlos_std: float, prior: F64, s: F64,
) -> F64:
    """Log predictive density (nats) of innovations y (m) with prediction variances s (m^2)
    under the LOS/NLOS mixture with NLOS prior `prior` (floored at 1e-300: a gross outlier
    that both components rule out counts as very unlikely, not as minus infinity)."""
    los = np.sqrt(max(los_std, MIN_LOS_STD) ** 2 + s)
    nl = np.sqrt(nlos_std**2 + s)
    dens = ((1.0 - prior) * np.exp(-0.5 * (y / los) ** 2) / (_SQRT_2PI * los)
            + prior * np.exp(-0.5 * ((y - nlos_mean) / nl) ** 2) / (_SQRT_2PI * nl))
    return np.log(np.maximum(dens, 1e-300))


def gaussian_log_density(y: F64, s: F64) -> float:
    """Log density (nats) of innovations y (m,) under N(0, s) with s (m,m)."""
    _, logdet = np.linalg.slogdet(s)
    return -0.5 * (logdet + float(y @ np.linalg.solve(s, y)) + len(y) * math.log(2 * math.pi))


class RangeNoise:
    """Per-range NLOS weighting and gating with a mixture fitted to the innovations."""

    def __init__(self, config: Config, n_anchor: int) -> None:
        shared = NlosModel.from_config(config)
        self.prior = shared.per_range
        self.model = self.prior
        self.gating = config.filter.gating
        self.gate = gate_threshold(config.filter.gate_probability, 1)
        self.p_last = np.full(n_anchor, self.prior.nlos_prior)
        self.q0 = shared.p_switch
        self.q = self.q0
        self._switch_sum = 0.0
        self._switch_n = 0
        self._seen = np.zeros(n_anchor, dtype=bool)
        self._y = np.zeros(RANGE_NOISE_WINDOW)
        self._s = np.zeros(RANGE_NOISE_WINDOW)
        # common range scale (ranges read `scale` x the distance): the start solve's
        # (`set_start_scale`), then at every refit the LOS-weighted least-squares fit of the
        # ranges as read to the predicted distances of all accepted ranges so far, with the
        # start's value as prior of std `[graph] range_scale_sigma`
        self.scale = 1.0
        self._scale0 = 1.0
        self.refine_scale = True
        self.scale_precision = 1.0 / config.graph.range_scale_sigma**2
        self._sxy = 0.0
        self._sxx = 0.0
        self._n = 0          # accepted ranges recorded so far
        self._since = 0      # accepted ranges since the last refit
        self.refits = 0
        #: log predictive density (nats) of every range weighed so far, gated ones too,
        #: under the model of its time: the range part of the filter's likelihood
        #: (`noise_bank`)
        self.log_likelihood = 0.0

    def set_start_scale(self, scale: float, refine: bool) -> None:
        """The start solve's common range scale: applied at once, and the prior of the fit.
        `refine`: fit it to the ranges from then on; only where the tag height is held (a
        planar vehicle): a tag free in 3-D trades height for scale (docs/results.md,
        "Constants in one module")."""
        self.scale = self._scale0 = float(scale)
        self.refine_scale = refine

    def widen_los_prior(self, los_std: float) -> None:
        """Take at least `los_std` (m; the start solve's residual spread, at least `[uwb]
        sigma`) as the LOS spread of the model and of the refits' prior. (With the per-range
        0.026 m as prior the UWB + IMU filter on simulated warehouse logs became
        overconfident: NEES 700 against about 3; with it, room fits 0.034 m for 0.026.)"""
        if los_std > self.model.los_std:
            self.model = replace(self.model, los_std=float(los_std))
            self.prior = replace(self.prior, los_std=float(los_std))

    def weigh(
        self, anchor: np.ndarray, y: F64, s: F64, evidence: F64 | None = None,
    ) -> tuple[F64, F64, np.ndarray, F64]:
        """Weigh ranges of anchors `anchor` (M,) with innovations y (M,) m and prediction
        variances s (M,) m^2. Returns the corrected innovations (M,) m, their variances
        (M,) m^2 (mixture posterior, prediction not included), the accepted mask (M,) and
        the normalised innovations squared (M,). Does not record anything (`accept` does).
        `evidence` (M,), nats: the learned NLOS classifier's log-odds per range, added to
        the prior's (`nlos_classifier.RangePriors.log_odds`)."""
        m = self.model
        prior = (1.0 - self.q) * self.p_last[anchor] + self.q * m.nlos_prior
        prior = np.clip(prior, *P_BOUNDS)
        if evidence is not None:
            prior = 1.0 / (1.0 + np.exp(-(np.log(prior / (1.0 - prior)) + evidence)))
        p = nlos_probability(y, np.float64(m.los_std), np.float64(m.nlos_mean),
                             np.float64(m.nlos_std), prior, extra_var=s)
        self.log_likelihood += float(mixture_log_density(
            y, m.los_std, m.nlos_mean, m.nlos_std, prior, s).sum())
        mu = m.nlos_mean
        var = (1.0 - p) * m.los_std**2 + p * m.nlos_std**2 + p * (1.0 - p) * mu * mu
        yc = y - p * mu
        nis = yc * yc / (var + s)
        ok = nis <= self.gate if self.gating else np.ones(len(y), dtype=bool)
        self._p = p
        return yc, var, ok, nis

    def accept(
        self, anchor: np.ndarray, y: F64, s: F64, ok: np.ndarray, rng: F64,
    ) -> None:
        """Record the ranges `rng` (m, as scaled) of the last `weigh` call that were used
        (mask `ok`): their posteriors become the anchors' chain state, their innovations
        feed the EM and the range-scale regression."""
        if not np.any(ok):
            return
        a, p = anchor[ok], self._p[ok]
        pred = rng[ok] - y[ok]
        w = (1.0 - p) / (self.model.los_std**2 + s[ok])
        self._sxy += float(w @ (rng[ok] * self.scale * pred))  # as read x predicted
        self._sxx += float(w @ (pred * pred))
        seen = self._seen[a]
        prev = self.p_last[a]
        sw = prev * (1.0 - p) + (1.0 - prev) * p
        self._switch_sum += float(sw[seen].sum())
        self._switch_n += int(seen.sum())
        self.p_last[a] = p  # (a repeated anchor keeps its last range's value)
        self._seen[a] = True
        yy, ss = y[ok], s[ok]
        k = len(yy)
        idx = (self._n + np.arange(k)) % RANGE_NOISE_WINDOW
        self._y[idx] = yy
        self._s[idx] = ss
        self._n += k
        self._since += k
        if self._since >= REFIT_EVERY:
            self._refit()

    def weigh_one(self, anchor: int, y: float, s: float, evidence: float | None = None,
                  ) -> tuple[float, float, bool, float, float]:
        """`weigh` for one range (anchor index, innovation y m, prediction variance s m^2),
        in Python floats with the same operations in the same order (the sequential EKF
        update calls it per range; numpy's per-call cost on 1-element arrays was a third of
        the EKF's time). Returns the corrected innovation, its variance, accepted, NIS and
        the NLOS posterior (for `accept_one`); `evidence` as in `weigh`, nats."""
        m = self.model
        prior = (1.0 - self.q) * float(self.p_last[anchor]) + self.q * m.nlos_prior
        prior = min(max(prior, P_BOUNDS[0]), P_BOUNDS[1])
        if evidence is not None:
            prior = 1.0 / (1.0 + math.exp(-(math.log(prior / (1.0 - prior)) + evidence)))
        p = _nlos_probability_one(y, m.los_std, m.nlos_mean, m.nlos_std, prior, s)
        los = math.sqrt(max(m.los_std, MIN_LOS_STD) ** 2 + s)
        nl = math.sqrt(m.nlos_std**2 + s)
        dens = ((1.0 - prior) * math.exp(-0.5 * (y / los) ** 2) / (_SQRT_2PI * los)
                + prior * math.exp(-0.5 * ((y - m.nlos_mean) / nl) ** 2) / (_SQRT_2PI * nl))
        self.log_likelihood += math.log(max(dens, 1e-300))
        mu = m.nlos_mean
        var = (1.0 - p) * m.los_std**2 + p * m.nlos_std**2 + p * (1.0 - p) * mu * mu
        yc = y - p * mu
        nis = yc * yc / (var + s)
        ok = nis <= self.gate if self.gating else True
        return yc, var, bool(ok), nis, p

    def accept_one(self, anchor: int, y: float, s: float, p: float, rng: float) -> None:
        """`accept` for one used range: its innovation y (m), prediction variance s (m^2),
        NLOS posterior p (from `weigh_one`) and range rng (m, as scaled)."""
        pred = rng - y
        w = (1.0 - p) / (self.model.los_std**2 + s)
        self._sxy += w * (rng * self.scale * pred)
        self._sxx += w * (pred * pred)
        if self._seen[anchor]:
            prev = float(self.p_last[anchor])
            self._switch_sum += prev * (1.0 - p) + (1.0 - prev) * p
            self._switch_n += 1
        self.p_last[anchor] = p
        self._seen[anchor] = True
        idx = self._n % RANGE_NOISE_WINDOW
        self._y[idx] = y
        self._s[idx] = s
        self._n += 1
        self._since += 1
        if self._since >= REFIT_EVERY:
            self._refit()

    def _refit(self) -> None:
        n = min(self._n, RANGE_NOISE_WINDOW)
        self.model = fit_nlos_mixture(self._y[:n], self._s[:n], self.prior, PRIOR_RANGES)
        self.q = float(np.clip(
            (self._switch_sum + PRIOR_RANGES * self.q0) / (self._switch_n + PRIOR_RANGES),
            1e-3, 0.5))
        if self.refine_scale:
            self.scale = ((self._sxy + self.scale_precision * self._scale0)
                          / (self._sxx + self.scale_precision))
        self._since = 0
        self.refits += 1

    def report(self) -> dict[str, float | int]:
        """The fitted model (m, share) and switching rate."""
        m: NlosParams = self.model
        return {
            "los_std": round(m.los_std, 4), "nlos_mean": round(m.nlos_mean, 4),
            "nlos_std": round(m.nlos_std, 4), "nlos_share": round(m.nlos_prior, 3),
            "nlos_switch": round(self.q, 4), "range_scale": round(self.scale, 5),
            "refits": self.refits,
        }


class InnovationVariance:
    """Running covariance-matching estimate of K measurement variances (see module doc)."""

    def __init__(self, prior: F64) -> None:
        self.prior = np.asarray(prior, dtype=np.float64).copy()
        self.r = self.prior.copy()
        self._num = np.zeros(len(self.prior))
        self._den = np.zeros(len(self.prior))

    def update(self, y: F64, s: F64) -> None:
        """Add rows: innovations y (N, K) and their prediction variances s (N, K)."""
        y = np.asarray(y).reshape(-1, len(self.r))
        s = np.asarray(s).reshape(-1, len(self.r))
        n = len(y)
        if n == 0:
            return
        decay = (1.0 - 1.0 / MEMORY_ROWS) ** n
        self._num = decay * self._num + np.sum(np.maximum(y * y - s, 0.0), axis=0)
        self._den = decay * self._den + n
        r = (self._num + PRIOR_ROWS * self.prior) / (self._den + PRIOR_ROWS)
        self.r = np.maximum(r, MATCHED_VARIANCE_MIN_SHARE * self.prior)


def scalar_update(
    p: F64, dx: F64, h: F64, y: float, r: float
) -> tuple[F64, F64, float]:
    """One scalar Kalman update on top of the correction dx accumulated so far.

    p (n,n) covariance, dx (n,) correction so far, h (n,) Jacobian row, y the innovation at
    dx (m), r its variance. Joseph-form covariance (written for one row:
    P - k ph^T - ph k^T + S k k^T). Returns the new P, dx and the gain k (n,).
    """
    ph = p @ h
    s = float(h @ ph) + r
    k = ph / s
    kp = np.outer(k, ph)
    p_new = p - kp - kp.T + s * np.outer(k, k)
    return p_new, dx + k * y, k


def sequential_ranges(
    noise: RangeNoise, p: F64, dx: F64, h: F64, y: F64, anchor: np.ndarray, rng: F64,
    evidence: F64 | None = None, gains: list[tuple[int, F64, float]] | None = None,
) -> tuple[F64, F64, np.ndarray, F64]:
    """Sequential robust scalar updates of M ranges rng (M,) m (rows h (M,n), innovations
    y (M,) at dx = 0) in their order. Each range is weighed (`RangeNoise.weigh_one`, the
    scalar form of `weigh`, with its classifier `evidence` (M,) nats where given) on the
    innovation and prediction variance left after the ranges before it. Returns P, dx, the
    accepted mask (M,) and the NIS (M,)."""
    m = len(y)
    used = np.zeros(m, dtype=bool)
    nis = np.zeros(m)
    y_l, a_l, r_l = y.tolist(), anchor.tolist(), rng.tolist()
    e_l = [None] * m if evidence is None else evidence.tolist()
    for i in range(m):
        hi = h[i]
        yi = y_l[i] - float(hi @ dx)
        si = float(hi @ p @ hi)
        yc, var, ok, nis[i], pn = noise.weigh_one(a_l[i], yi, si, e_l[i])
        if ok:
            p, dx, k = scalar_update(p, dx, hi, yc, var)
            if gains is not None:  # (row, gain, variance) of the accepted range
                gains.append((i, k, var))
            used[i] = True
            noise.accept_one(a_l[i], yi, si, pn, r_l[i])
    return 0.5 * (p + p.T), dx, used, nis
