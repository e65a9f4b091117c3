# SPDX-License-Identifier: BSD-3-Clause
"""The LOS/NLOS range-error model: one model, shared by the graph (online and batch), wls and
the Kalman filters' range weighting. Numpy only (no GTSAM: `uwbfuse.filters` runs without it);
the graph builds its native GTSAM factors from it in `graph/uwb.py`.

Range error e = measured range - true distance (m). In line of sight (LOS) e ~ N(0,
sigma_los) (`[uwb] sigma`: the radio's LOS noise). In NLOS the direct path is blocked and the
range reads long by an excess: a slowly varying part per anchor (std `sigma_slow`, Gauss-Markov
with correlation time `tau_s`, held per `segment_s`) around a mean `mu_nlos`, plus a fast
per-range part (std `sigma_nlos`). A range is NLOS with prior probability `p_nlos`, and an
anchor's LOS/NLOS state persists: between two of its ranges dt apart it is redrawn (from the
stationary rate `p_nlos`) with probability 1 - exp(-dt / `switch_time`) in the graph
(`switch_probabilities`; a two-state Markov chain: `hmm_filter` online, `hmm_smooth` in batch,
each transition weighed by the jump of the residual, `jump_log_likelihoods`), and with a
probability per range that they estimate from their posteriors (prior `p_switch`) in the
filters.

Two views of the same physics, and the one named difference between them:

- the **state model** (the graph): the slow NLOS excess is a per-anchor state E(a, s) that the
  graph estimates, so its mean `mu_nlos` is the excess over the anchor's estimated LOS offset
  D(a) and each range only adds the fast noise `sigma_nlos` around it. Its values are priors
  that the log re-estimates (`NlosModel.m_step`; the configured sigmas are upper bounds).
- the **per-range model** (`per_range`, an `NlosParams`; per anchor in `per_anchor`): the
  marginal error distribution of one range on its own, absolute (no anchor offset removed)
  and with the slow and fast parts together (std about hypot(sigma_slow, sigma_nlos)). It is
  what an estimator that weighs each range alone uses: wls per epoch (Qiu 2022 eq. 10-11,
  `nlos_probability`) and the filters' innovations (the prior of their EM fit to the log,
  `fit_nlos_mixture`). Its defaults are Qiu 2022's calibrated DW1000 values (Table 2), which
  reproduce Qiu's tables; `calibrate-nlos` fits them (per anchor) against ground truth.

The two share the physics (LOS noise, a positive NLOS excess of about 0.15 m spread: 0.145
per range, hypot(0.13, 0.07) = 0.148 as state + noise) and the persistence (`tau_s`, and the
class's `switch_time` / `p_switch`: the same default at 10 ranges per anchor per second).
Their means, LOS spreads and shares differ because they are different quantities: the state
model's start values are loose priors that its EM shrinks (LOS 0.10 m upper bound, excess
0.3 m over the LOS offset, share 0.3), the per-range model is a calibration a method
without EM keeps (LOS 0.026 m absolute error, NLOS mean 0.114 m absolute, share 0.2);
`docs/results.md` (2026-12-02, session 10, "One NLOS model") says how each value is
obtained.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from uwbfuse.config import Config, NlosConfig
from uwbfuse.constants import (
    JUMP_MAX_GAP_NS,
    JUMP_MAX_M,
    LOG_OUTLIER,
    MAX_LOS_STD,
    MIN_LOS_STD,
    SIGMA_LOS_MIN,
    SIGMA_NLOS_MIN,
)
from uwbfuse.streams import NS_PER_S, AnchorMap

F64 = NDArray[np.float64]
NO_PREVIOUS_RANGE = np.iinfo(np.int64).min  # ns: an anchor's previous range stamp before its first
# ranges up to which `switch_probabilities` loops in Python (numpy's per-call cost above)
FEW_SWITCH_RANGES = 16

_LOG_SQRT_2PI = 0.5 * math.log(2.0 * math.pi)
_FEW_JUMPS = 16  # `residual_jumps_by_anchor` in Python up to this many ranges


@dataclass(frozen=True)
class NlosParams:
    """The per-range model: los_std, nlos_mean, nlos_std (m) and nlos_prior (0..1)."""

    los_std: float
    nlos_mean: float
    nlos_std: float
    nlos_prior: float

    def as_list(self) -> list[float]:
        return [self.los_std, self.nlos_mean, self.nlos_std, self.nlos_prior]


def _per_range(c: NlosConfig) -> NlosParams:
    """The per-range model of an `[nlos]` section (range_* keys)."""
    return NlosParams(c.range_los_std, c.range_nlos_mean, c.range_nlos_std, c.range_nlos_prior)


@dataclass
class NlosModel:
    """The range-error model (see the module docstring); lengths in metres, times in seconds.

    State model: sigma_los, sigma_nlos (fast part), mu_nlos (over the LOS offset), sigma_slow,
    tau_s, segment_s, p_nlos, p_switch, switch_time. Per-range model: `per_range`,
    overridden per anchor id by `per_anchor` (`samples`: ranges per anchor of a
    calibration)."""

    sigma_los: float
    sigma_nlos: float
    mu_nlos: float
    sigma_slow: float
    tau_s: float
    segment_s: float
    p_nlos: float
    p_switch: float
    switch_time: float = 2.0  # s (`[nlos] switch_time`)
    per_range: NlosParams = field(default_factory=lambda: _per_range(NlosConfig()))
    per_anchor: dict[str, NlosParams] = field(default_factory=dict)
    samples: dict[str, int] = field(default_factory=dict)

    @classmethod
    def from_config(cls, config: Config) -> NlosModel:
        """The model of `[nlos]`, with `[uwb] sigma` as the LOS std."""
        c = config.nlos
        per = {k: NlosParams(*map(float, v)) for k, v in c.anchor.items()}
        return cls(config.uwb.sigma, c.excess_sigma, c.excess_mean, c.excess_slow_sigma,
                   c.tau, c.segment, c.rate, c.switch, c.switch_time, _per_range(c), per)

    def arrays(self, anchors: AnchorMap) -> tuple[F64, F64, F64, F64]:
        """Per-range model (los_std, nlos_mean, nlos_std, nlos_prior), each (M,) in
        anchor-map order."""
        rows = [self.per_anchor.get(a, self.per_range).as_list() for a in anchors.ids]
        arr = np.array(rows, dtype=np.float64).reshape(-1, 4)
        return arr[:, 0], arr[:, 1], arr[:, 2], arr[:, 3]

    def per_range_toml(self) -> dict[str, Any]:
        """TOML-ready `[nlos]` values of the per-range model: range_los_std, range_nlos_mean,
        range_nlos_std, range_nlos_prior and `anchor` = {id: [los_std, nlos_mean, nlos_std,
        nlos_prior]}."""
        d = self.per_range
        return {
            "range_los_std": round(d.los_std, 4),
            "range_nlos_mean": round(d.nlos_mean, 4),
            "range_nlos_std": round(d.nlos_std, 4),
            "range_nlos_prior": round(d.nlos_prior, 4),
            "anchor": {k: [round(x, 4) for x in p.as_list()]
                       for k, p in self.per_anchor.items()},
        }

    @property
    def chain_sigma(self) -> float:
        """Std of the NLOS state's change over one segment (Gauss-Markov), m."""
        phi = math.exp(-self.segment_s / self.tau_s)
        return self.sigma_slow * math.sqrt(max(1.0 - phi * phi, 1e-6))

    @property
    def reversion_sigma(self) -> float:
        """Std of the per-segment pull of a chained NLOS state towards D + mu, m."""
        return self.sigma_slow * math.sqrt(2.0 * self.tau_s / self.segment_s)

    @property
    def class_change_time(self) -> float:
        """Mean time between changes of an anchor's LOS/NLOS class, s: its class is
        redrawn every `switch_time` on average, NLOS with probability p_nlos, so a redraw
        changes it with probability 2 p (1 - p) over the stationary classes (p held within
        [0.02, 0.98], as `graph.uwb.los_subset_search` holds it)."""
        p = min(max(self.p_nlos, 0.02), 0.98)
        return self.switch_time / (2.0 * p * (1.0 - p))

    def log_likelihoods(
        self, r_los: np.ndarray, r_nlos: np.ndarray, var_nlos: np.ndarray | float
    ) -> tuple[np.ndarray, np.ndarray]:
        """log p(z | LOS), log p(z | NLOS) from the two residuals (m) and the NLOS state var."""
        s_l = self.sigma_los
        ll_l = -0.5 * (r_los / s_l) ** 2 - math.log(s_l) - _LOG_SQRT_2PI
        s_n = np.sqrt(self.sigma_nlos**2 + np.asarray(var_nlos))
        ll_n = -0.5 * (r_nlos / s_n) ** 2 - np.log(s_n) - _LOG_SQRT_2PI
        return np.logaddexp(ll_l, LOG_OUTLIER), np.logaddexp(ll_n, LOG_OUTLIER)

    def m_step(
        self, r_los: np.ndarray, r_nlos: np.ndarray, g: np.ndarray, prior: NlosModel,
        n0: float = 50.0,
    ) -> None:
        """Re-estimate sigma_los, sigma_nlos and p_nlos; the prior counts as n0 ranges.

        Residuals beyond 1 m are gross outliers, left to the robust kernel.
        """
        ok = (np.abs(r_los) < 1.0) & (np.abs(r_nlos) < 1.0)
        r_los, r_nlos, g = r_los[ok], r_nlos[ok], g[ok]
        if len(g) < 20:
            return
        w_l, w_n = 1.0 - g, g
        s_l = (np.sum(w_l * r_los**2) + n0 * prior.sigma_los**2) / (np.sum(w_l) + n0)
        s_n = (np.sum(w_n * r_nlos**2) + n0 * prior.sigma_nlos**2) / (np.sum(w_n) + n0)
        # the configured sigmas are upper bounds: inflating them would only hide NLOS
        self.sigma_los = min(max(float(np.sqrt(s_l)), SIGMA_LOS_MIN), prior.sigma_los)
        self.sigma_nlos = min(max(float(np.sqrt(s_n)), SIGMA_NLOS_MIN), prior.sigma_nlos)
        p = (np.sum(w_n) + n0 * prior.p_nlos) / (len(g) + n0)
        self.p_nlos = float(np.clip(p, 0.02, 0.9))

    def excess_mean_step(
        self, r_excess: np.ndarray, g: np.ndarray, prior: NlosModel, n0: float
    ) -> None:
        """Re-estimate mu_nlos, the mean NLOS excess over the LOS offset: the
        responsibility-weighted mean of the residuals `r_excess` (m, range - prediction -
        the anchor's LOS offset), the prior's mean counting as n0 ranges.

        Kept within [0, prior]: NLOS only lengthens a range, and the configured mean is an
        upper bound as the configured sigmas are (`m_step`). Residuals beyond 1 m are gross
        outliers, as in `m_step`.
        """
        ok = np.abs(r_excess) < 1.0
        w = g[ok]
        mu = (np.sum(w * r_excess[ok]) + n0 * prior.mu_nlos) / (np.sum(w) + n0)
        self.mu_nlos = float(np.clip(mu, 0.0, prior.mu_nlos))


def normal_pdf(x: F64, mean: F64 | float, std: F64 | float) -> F64:
    return np.exp(-0.5 * ((x - mean) / std) ** 2) / (math.sqrt(2 * math.pi) * std)


def nlos_probability(
    residual: F64, los_std: F64, nlos_mean: F64, nlos_std: F64, prior: F64,
    extra_var: F64 | float = 0.0,
) -> F64:
    """Posterior NLOS probability of ranges from residuals e = measured - predicted (m).

    residual (N,M); model arrays (M,); extra_var: position-induced variance added to both
    components (m^2). NaN residuals give the prior.
    """
    los = np.sqrt(np.maximum(los_std, MIN_LOS_STD) ** 2 + extra_var)
    nl = np.sqrt(nlos_std**2 + extra_var)
    pn = prior * normal_pdf(residual, nlos_mean, nl)
    pl = (1.0 - prior) * normal_pdf(residual, 0.0, los)
    with np.errstate(invalid="ignore", divide="ignore"):
        p = pn / (pn + pl)
    p = np.where(np.isfinite(p), p, np.where(residual > nlos_mean, 1.0, 0.0))
    return np.where(np.isfinite(residual), p, np.broadcast_to(prior, residual.shape))


def fit_nlos_mixture(
    residual: F64, extra_var: F64, prior: NlosParams, n0: float, iterations: int = 8,
) -> NlosParams:
    """EM fit of the LOS/NLOS model to range residuals without ground truth.

    residual (N,) m: measured minus predicted range (e.g. a filter's innovations), each with
    the variance extra_var (N,) m^2 of its prediction added to both components. E-step:
    `nlos_probability`; M-step: NLOS share and mean, and each component's spread with the
    prediction variance taken out. `prior` counts as n0 ranges in every estimate (it holds
    the model where the data say little). The NLOS mean is kept >= 0 (NLOS only lengthens
    a range) and the LOS std within [MIN_LOS_STD, MAX_LOS_STD].
    """
    r = np.asarray(residual, dtype=np.float64)
    s = np.asarray(extra_var, dtype=np.float64)
    los, mu, nstd, pi = prior.los_std, prior.nlos_mean, prior.nlos_std, prior.nlos_prior
    if len(r) == 0:
        return prior
    for _ in range(iterations):
        g = nlos_probability(r, np.float64(los), np.float64(mu), np.float64(nstd),
                             np.float64(pi), extra_var=s)
        sg, sl = float(g.sum()), float(len(r) - g.sum())
        pi = float(np.clip((sg + n0 * prior.nlos_prior) / (len(r) + n0), 0.01, 0.95))
        mu = max((float(g @ r) + n0 * prior.nlos_mean) / (sg + n0), 0.0)
        v_l = (float((1.0 - g) @ (r * r - s)) + n0 * prior.los_std**2) / (sl + n0)
        d = r - mu
        v_n = (float(g @ (d * d - s)) + n0 * prior.nlos_std**2) / (sg + n0)
        los = float(np.clip(math.sqrt(max(v_l, 0.0)), MIN_LOS_STD, MAX_LOS_STD))
        nstd = max(math.sqrt(max(v_n, 0.0)), los)

    return NlosParams(los, mu, nstd, pi)


def jump_log_likelihoods(
    delta: np.ndarray, excess: np.ndarray, model: NlosModel
) -> np.ndarray:
    """log p(delta | s_prev, s) (N,2,2) of the change of an anchor's range residual between
    two consecutive ranges (m), for s_prev, s in (LOS, NLOS); NaN delta (no usable previous
    range) gives zeros.

    Between two ranges a tenth of a second apart the odometry moves the tag accurately, so
    the change of residual cancels a slowly varying pose error that the residual's level
    cannot tell from NLOS: staying in a state changes it by noise only, entering NLOS
    raises it by the anchor's NLOS excess (`excess`, m) and leaving NLOS lowers it by as
    much. Gross outliers are floored as in `log_likelihoods`.
    """
    s_l, s_n = model.sigma_los, model.sigma_nlos
    s_stay_l = math.sqrt(2.0) * s_l
    s_stay_n = math.sqrt(2.0) * s_n
    s_jump = math.sqrt(model.sigma_slow**2 + s_n**2 + s_l**2)
    d = np.where(np.isnan(delta), 0.0, delta)  # finite otherwise (`residual_jumps`)
    m = np.maximum(excess, 0.1)

    # the four transitions' Gaussians floored as outliers, in one pass: (N,4) -> (N,2,2)
    sig = np.array([s_stay_l, s_jump, s_jump, s_stay_n])
    log_sig = np.array([math.log(x) for x in sig.tolist()])
    x = np.stack([d, d - m, d + m, d], axis=1)
    out = np.logaddexp(-0.5 * (x / sig) ** 2 - log_sig - _LOG_SQRT_2PI,
                       LOG_OUTLIER).reshape(-1, 2, 2)
    out[np.isnan(delta)] = 0.0
    return out


def residual_jumps(t_ns: np.ndarray, r: np.ndarray) -> np.ndarray:
    """Change of residual (m) from each range to the next of the same anchor (time-ordered,
    one anchor); NaN where the previous range is over JUMP_MAX_GAP_NS old or the change is
    beyond JUMP_MAX_M (a gross outlier)."""
    d = np.concatenate([[np.nan], np.diff(r)])
    gap = np.concatenate([[np.iinfo(np.int64).max], np.diff(t_ns)])
    d[(gap > JUMP_MAX_GAP_NS) | ~(np.abs(d) < JUMP_MAX_M)] = np.nan
    return d


def residual_jumps_by_anchor(
    t_ns: np.ndarray, anchor: np.ndarray, r: np.ndarray,
    lead_t: np.ndarray | None = None, lead_r: np.ndarray | None = None,
) -> np.ndarray:
    """`residual_jumps` of the ranges of several anchors at once, each anchor's ranges in
    time order. `lead_t`, `lead_r` (indexed by anchor): each anchor's previous range (stamp
    ns, residual m), which leads its chain; without them an anchor's first range has no
    jump (NaN). One vectorised call instead of one per anchor (a few ranges: in Python,
    the same operations)."""
    if len(t_ns) <= _FEW_JUMPS:
        return _residual_jumps_few(t_ns, anchor, r, lead_t, lead_r)
    order = np.lexsort((t_ns, anchor))
    a_s = anchor[order]
    t_s = np.asarray(t_ns, np.int64)[order]
    r_s = np.asarray(r, np.float64)[order]
    first = np.concatenate([[True], a_s[1:] != a_s[:-1]]) if len(a_s) else np.zeros(0, bool)
    # each range's predecessor: the previous range of its anchor, or the anchor's lead
    t_prev, r_prev = np.empty_like(t_s), np.empty_like(r_s)
    t_prev[1:], r_prev[1:] = t_s[:-1], r_s[:-1]
    if lead_t is None or lead_r is None:  # a lead too old to count: the first jump is NaN
        t_prev[first] = np.iinfo(np.int64).min // 2
        r_prev[first] = 0.0
    else:
        t_prev[first], r_prev[first] = lead_t[a_s[first]], lead_r[a_s[first]]
    d = r_s - r_prev  # as `residual_jumps` over each anchor's chain with its lead
    d[((t_s - t_prev) > JUMP_MAX_GAP_NS) | ~(np.abs(d) < JUMP_MAX_M)] = np.nan
    out = np.empty(len(t_ns))
    out[order] = d
    return out


def _residual_jumps_few(
    t_ns: np.ndarray, anchor: np.ndarray, r: np.ndarray,
    lead_t: np.ndarray | None, lead_r: np.ndarray | None,
) -> np.ndarray:
    """`residual_jumps_by_anchor` of a few ranges in Python numbers (one keyframe's)."""
    t, a = np.asarray(t_ns, np.int64).tolist(), np.asarray(anchor).tolist()
    rr = np.asarray(r, np.float64).tolist()
    out = [0.0] * len(t)
    prev: dict[int, tuple[int, float]] = {}  # each anchor's previous range
    for i in sorted(range(len(t)), key=lambda i: (a[i], t[i])):  # stable, as lexsort
        if a[i] in prev:
            t_prev, r_prev = prev[a[i]]
        elif lead_t is None or lead_r is None:  # NaN below (the gap)
            t_prev, r_prev = int(np.iinfo(np.int64).min // 2), 0.0
        else:
            t_prev, r_prev = int(lead_t[a[i]]), float(lead_r[a[i]])
        d = rr[i] - r_prev
        out[i] = math.nan if (t[i] - t_prev) > JUMP_MAX_GAP_NS or not abs(d) < JUMP_MAX_M else d
        prev[a[i]] = (t[i], rr[i])
    return np.array(out, dtype=np.float64)


def switch_probabilities(t_ns: np.ndarray, anchor: np.ndarray, switch_time: float,
                         last_t: np.ndarray | None = None) -> F64:
    """Per range, the probability (N,) that its anchor's LOS/NLOS state was redrawn since the
    anchor's previous range: 1 - exp(-dt / switch_time), dt (s) to the previous range of the
    same anchor in `t_ns` (ns, (N,); each anchor's ranges in time order), or for an anchor's
    first range to `last_t[anchor]` (ns, per anchor; None or NO_PREVIOUS_RANGE there: 1, no memory).

    A state persists for a time (an obstacle between the tag and the anchor for as long as
    the vehicle takes to pass it), not for a number of ranges: a per-range probability tied
    the chain's memory to the radio's rate (0.05 a range was 2 s at 10 ranges per anchor per
    second, 10 s at 2, 80 s on Plaza's 4 s round robin)."""
    if len(t_ns) <= FEW_SWITCH_RANGES:  # a keyframe's ranges: no sort, one numpy call
        last: dict[int, int] = {}
        dt_l = []  # s; NaN: no previous range
        for ti, ai in zip(np.asarray(t_ns).tolist(), np.asarray(anchor).tolist(), strict=True):
            prev = last.get(ai, NO_PREVIOUS_RANGE if last_t is None else int(last_t[ai]))
            last[ai] = ti
            dt_l.append(math.nan if prev == NO_PREVIOUS_RANGE else max(ti - prev, 0) / NS_PER_S)
        dt = np.array(dt_l, dtype=np.float64)
        return np.where(np.isnan(dt), 1.0, -np.expm1(-dt / switch_time))
    t = np.asarray(t_ns, np.int64)
    a = np.asarray(anchor, np.int64)
    order = np.lexsort((t, a))  # stable: each anchor's ranges keep their order
    ts, as_ = t[order], a[order]
    prev = np.full(len(t), NO_PREVIOUS_RANGE, np.int64)
    same = np.zeros(len(t), dtype=bool)
    same[1:] = as_[1:] == as_[:-1]
    prev[1:][same[1:]] = ts[:-1][same[1:]]
    if last_t is not None:
        prev[~same] = np.asarray(last_t, np.int64)[as_[~same]]
    p = np.ones(len(t))
    known = prev != NO_PREVIOUS_RANGE
    dt = np.maximum(ts[known] - prev[known], 0) / NS_PER_S
    p[known] = -np.expm1(-dt / switch_time)
    out = np.empty(len(t))
    out[order] = p
    return out


def hmm_filter(
    ll_los: np.ndarray, ll_nlos: np.ndarray, p_switch: float, p_nlos: float, p0: float,
    jump_ll: np.ndarray | None = None,
) -> tuple[np.ndarray, float, np.ndarray]:
    """Forward pass of one anchor's LOS/NLOS chain over its time-ordered ranges.

    Returns P(NLOS) per range, the last value and the predicted prior of each range (with
    the jump evidence, before the range's own level likelihood). Each step keeps the state
    with probability 1 - p_switch and otherwise redraws it with the stationary rate
    p_nlos; `jump_ll` (N,2,2, see `jump_log_likelihoods`) weighs each transition by the
    change of residual it implies.
    """
    d, jl = _filter_inputs(ll_los, ll_nlos, jump_ll)
    out, p, priors = _filter_chain(d, jl, p_switch, p_nlos, p0)
    return np.array(out, dtype=np.float64), p, np.array(priors, dtype=np.float64)


def hmm_filter_by_anchor(
    anchor: np.ndarray, ll_los: np.ndarray, ll_nlos: np.ndarray, p_switch: float | F64,
    p_nlos: float, p_last: np.ndarray, jump_ll: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """`hmm_filter` of the ranges of several anchors (each anchor's in time order): P(NLOS)
    and the predicted prior per range. Anchor a's chain starts from `p_last[a]` and leaves
    its last P(NLOS) there (in place). `p_switch`: one probability, or one per range (N,)
    for the step into it (`switch_probabilities`). The inputs are prepared once for all
    ranges (the same numbers as anchor by anchor: every step is elementwise)."""
    d, jl = _filter_inputs(ll_los, ll_nlos, jump_ll)
    keys = np.asarray(anchor).tolist()
    steps = (np.asarray(p_switch, np.float64).tolist() if np.ndim(p_switch)
             else [float(p_switch)] * len(d))
    # the chains interleaved in the ranges' order, each anchor's P(NLOS) carried in a
    # dict: a keyframe has about one range per anchor, where gathering each anchor's rows
    # into a chain of its own cost more than its steps
    p = {a: p_last[a] for a in set(keys)}
    g, prior = _filter_steps(keys, d, jl, steps, p_nlos, p)
    for a, x in p.items():
        p_last[a] = x
    return np.array(g, dtype=np.float64), np.array(prior, dtype=np.float64)


def _filter_inputs(ll_los: np.ndarray, ll_nlos: np.ndarray, jump_ll: np.ndarray | None
                   ) -> tuple[list[float], list | None]:
    """`hmm_filter`'s per-range inputs as Python lists: the clipped log-likelihood ratio
    and the jump evidence scaled to its largest entry (N,2,2)."""
    d = np.minimum(np.maximum(ll_nlos - ll_los, -50.0), 50.0).tolist()  # np.clip's
    jl = (None if jump_ll is None
          else np.exp(jump_ll - jump_ll.max(axis=(1, 2), keepdims=True)).tolist())
    return d, jl


def _filter_chain(d: list[float], jl: list | None, p_switch: float | list[float],
                  p_nlos: float, p0: float) -> tuple[list[float], float, list[float]]:
    """`hmm_filter`'s loop over one chain (`_filter_steps`); `p_switch` one value or one
    per range."""
    steps = p_switch if isinstance(p_switch, list) else [p_switch] * len(d)
    p = {0: p0}
    out, priors = _filter_steps([0] * len(d), d, jl, steps, p_nlos, p)
    return out, p[0], priors


def _filter_steps(keys: list[int], d: list[float], jl: list | None, steps: list[float],
                  p_nlos: float, p: dict[int, float]) -> tuple[list[float], list[float]]:
    """The forward steps of `hmm_filter` in Python floats (numpy item access was most of
    its time; the same values): range i continues chain `keys[i]` from `p[keys[i]]`, its
    P(NLOS) so far (updated in place); P(NLOS) and the predicted prior per range."""
    out, priors = [], []
    for i, (a, q) in enumerate(zip(keys, steps, strict=True)):
        pa = p[a]
        t_ln = q * p_nlos  # P(LOS -> NLOS)
        t_nl = q * (1.0 - p_nlos)  # P(NLOS -> LOS)
        if jl is None:
            prior = (1.0 - q) * pa + q * p_nlos
        else:
            (j00, j01), (j10, j11) = jl[i]
            to_n = (1.0 - pa) * t_ln * j01 + pa * (1.0 - t_nl) * j11
            to_l = (1.0 - pa) * (1.0 - t_ln) * j00 + pa * t_nl * j10
            prior = to_n / max(to_n + to_l, 1e-300)
        prior = min(max(prior, 1e-4), 1.0 - 1e-4)
        priors.append(prior)
        lo = math.log(prior / (1.0 - prior)) + d[i]
        pa = 1.0 / (1.0 + math.exp(-lo))
        out.append(pa)
        p[a] = pa
    return out, priors


def posterior(prior: np.ndarray, ll_los: np.ndarray, ll_nlos: np.ndarray) -> np.ndarray:
    """P(NLOS) from a prior probability and the two log-likelihoods (vectorised)."""
    lo = np.log(prior / (1.0 - prior)) + np.clip(ll_nlos - ll_los, -50.0, 50.0)
    return 1.0 / (1.0 + np.exp(-lo))


def hmm_smooth(
    ll_los: np.ndarray, ll_nlos: np.ndarray, p_switch: float, p_nlos: float,
    jump_ll: np.ndarray | None = None, p0: float | None = None,
) -> np.ndarray:
    """Forward-backward P(NLOS) per range of one anchor (time-ordered).

    `jump_ll` (N,2,2, see `jump_log_likelihoods`) weighs the transition into each range;
    `p0` is P(NLOS) of the first range before its own evidence (default: p_nlos).
    """
    if len(ll_los) == 0:
        return np.zeros(0)
    e0, e1, tr = _smooth_inputs(ll_los, ll_nlos, p_switch, p_nlos, jump_ll)
    return np.array(_smooth_chain(e0, e1, *tr, p_nlos, p0), dtype=np.float64)


def hmm_smooth_by_anchor(
    anchor: np.ndarray, ll_los: np.ndarray, ll_nlos: np.ndarray, p_switch: float | F64,
    p_nlos: float, jump_ll: np.ndarray | None = None, p0: np.ndarray | None = None,
) -> np.ndarray:
    """`hmm_smooth` of the ranges of several anchors (each anchor's in time order), each
    anchor's chain from `p0` (N,) of its first range (None: p_nlos, as `hmm_smooth`);
    `p_switch` one probability or one per range (N,) for the step into it. The inputs are
    prepared once for all ranges (the same numbers as anchor by anchor: every step is
    elementwise)."""
    e0, e1, tr = _smooth_input_arrays(ll_los, ll_nlos, p_switch, p_nlos, jump_ll)
    n = len(e0)
    if n == 0:
        return np.zeros(0)
    # each anchor's chain is one slice of the rows sorted by anchor (stable: each chain
    # keeps its time order), gathered by one fancy index per column instead of a list
    # comprehension per chain and column (that was most of this function's time)
    anchor = np.asarray(anchor)
    order = np.argsort(anchor, kind="stable")
    a_s = anchor[order]
    cuts = (np.flatnonzero(a_s[1:] != a_s[:-1]) + 1).tolist()
    cols = [c[order].tolist() for c in (e0, e1, *tr)]
    p0_s = [None] * n if p0 is None else np.asarray(p0, np.float64)[order].tolist()
    post: list[float] = []
    for lo, hi in zip([0, *cuts], [*cuts, n], strict=True):
        post.extend(_smooth_chain(*(c[lo:hi] for c in cols), p_nlos, p0_s[lo]))
    g = np.empty(n)
    g[order] = post
    return g


def _smooth_inputs(
    ll_los: np.ndarray, ll_nlos: np.ndarray, p_switch: float | F64, p_nlos: float,
    jump_ll: np.ndarray | None,
) -> tuple[list[float], list[float], tuple[list[float], ...]]:
    """`hmm_smooth`'s per-range inputs as Python lists (`_smooth_input_arrays`)."""
    e0, e1, tr = _smooth_input_arrays(ll_los, ll_nlos, p_switch, p_nlos, jump_ll)
    return e0.tolist(), e1.tolist(), tuple(t.tolist() for t in tr)


def _smooth_input_arrays(
    ll_los: np.ndarray, ll_nlos: np.ndarray, p_switch: float | F64, p_nlos: float,
    jump_ll: np.ndarray | None,
) -> tuple[np.ndarray, np.ndarray, tuple[np.ndarray, ...]]:
    """`hmm_smooth`'s per-range inputs (N,): the two likelihoods scaled to their larger
    one, and the transition matrix into each range (t00, t01, t10, t11), each entry
    scaled by the jump evidence if any; `p_switch` one value or (N,)."""
    n = len(ll_los)
    q = np.asarray(p_switch, np.float64)  # () or (N,)
    qn, ql = q * p_nlos, q * (1.0 - p_nlos)  # into NLOS, into LOS
    # the transition matrix entry by entry (no (N,2,2) array to build and take apart)
    a = (1.0 - qn, qn, ql, 1.0 - ql)
    m = np.maximum(ll_los, ll_nlos)
    e0, e1 = np.exp(ll_los - m), np.exp(ll_nlos - m)
    if jump_ll is None:
        return e0, e1, tuple(np.broadcast_to(x, (n,)) for x in a)
    j = np.exp(jump_ll - jump_ll.max(axis=(1, 2), keepdims=True))
    return e0, e1, (a[0] * j[:, 0, 0], a[1] * j[:, 0, 1], a[2] * j[:, 1, 0], a[3] * j[:, 1, 1])


def _smooth_chain(e0: list[float], e1: list[float], t00: list[float], t01: list[float],
                  t10: list[float], t11: list[float], p_nlos: float, p0: float | None
                  ) -> list[float]:
    """`hmm_smooth`'s forward and backward passes over one chain in Python floats (numpy
    item access was most of the loops' time; the same values)."""
    q0 = p_nlos if p0 is None else min(max(p0, 1e-4), 1.0 - 1e-4)
    c0, c1 = (1.0 - q0) * e0[0], q0 * e1[0]
    s = c0 + c1
    x0, x1 = c0 / s, c1 / s
    # forward messages; `max(s, 1e-300)` written as a test (the same value, NaN included)
    alpha0, alpha1 = [x0], [x1]
    for a00, a01, a10, a11, f0, f1 in zip(t00[1:], t01[1:], t10[1:], t11[1:], e0[1:], e1[1:],
                                          strict=True):
        y0 = (x0 * a00 + x1 * a10) * f0
        y1 = (x0 * a01 + x1 * a11) * f1
        s = y0 + y1
        if s < 1e-300:
            s = 1e-300
        x0, x1 = y0 / s, y1 / s
        alpha0.append(x0)
        alpha1.append(x1)
    # backward messages into range i from range i + 1, newest first
    post = []
    b0, b1 = 1.0, 1.0
    for f0, f1, a00, a01, a10, a11, x0, x1 in zip(
            reversed(e0[1:]), reversed(e1[1:]), reversed(t00[1:]), reversed(t01[1:]),
            reversed(t10[1:]), reversed(t11[1:]), reversed(alpha0[:-1]),
            reversed(alpha1[:-1]), strict=True):
        c0, c1 = f0 * b0, f1 * b1
        nb0, nb1 = a00 * c0 + a01 * c1, a10 * c0 + a11 * c1
        s = nb0 + nb1
        if s < 1e-300:
            s = 1e-300
        b0, b1 = nb0 / s, nb1 / s
        g0, g1 = x0 * b0, x1 * b1
        s = g0 + g1
        if s < 1e-300:
            s = 1e-300
        post.append(g1 / s)
    post.reverse()
    post.append(alpha1[-1])
    return post
