# SPDX-License-Identifier: BSD-3-Clause
"""UWB range factors and the NLOS model.

Range model (metres): z = |p_tag - anchor| + b + e. While the anchor is in line of sight
(LOS), b = D(a), the anchor's constant offset (antenna delay; a variable with a prior when
`estimate_range_bias`), and e ~ N(0, sigma_los). While it is in NLOS, the direct path is
blocked and the range reads long by a slowly varying excess: b = E(a, s), a per-anchor state
per time segment s (`nlos_segment` seconds) that follows a Gauss-Markov process around
D(a) + nlos_mean (std `nlos_slow_sigma`, correlation time `nlos_tau`), and e ~ N(0,
nlos_sigma). All of it is native GTSAM: `RangeFactorWithTransformBias3D` with bias key D(a)
or E(a, s), and `BetweenFactorDouble` links D -> E (mean reversion) and E(s-1) -> E(s)
(random walk).

Which component a range belongs to is hidden. Expectation-maximisation keeps the factors
native: with responsibility g = P(NLOS | data), the expected negative log-likelihood is
(1-g) r_los^2 / sigma_los^2 + g r_nlos^2 / sigma_nlos^2, i.e. a LOS factor with sigma
sigma_los / sqrt(1-g) plus an NLOS factor with sigma sigma_nlos / sqrt(g) (either dropped
when its weight is below 1 %). The robust kernel (Huber by default) wraps both and bounds
gross outliers. NLOS persists, so g comes from a two-state hidden Markov chain per anchor
(forward filtering online, forward-backward in batch); online, each transition is also
weighed by the jump of the anchor's residual since its previous range, which a slowly
varying pose error does not produce. The M-step re-estimates sigma_los,
sigma_nlos and the NLOS rate from the data.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import gtsam
import numpy as np

from uwbfuse.config import GraphConfig, UwbConfig
from uwbfuse.graph.keys import D, L, X
from uwbfuse.graph.noise import range_noise

_LOG_SQRT_2PI = 0.5 * math.log(2.0 * math.pi)
SIGMA_LOS_MIN = 0.02
SIGMA_NLOS_MIN = 0.03
MIN_WEIGHT = 0.01  # component weights below this add no factor
SEARCH_SHIFT_SIGMA = 0.5  # m: prior std of the track shift in `los_subset_search`
EXCESS_FLOOR = -0.2  # m: least NLOS excess a `los_subset_search` hypothesis may need
# `los_subset_search` solves 2^M subsets; with more anchors than this it is skipped: measured
# on warehouse-nlos with 8 anchors (3 seeds) isam2 0.19 m without the search, 0.23 m with
# it (more hypotheses, more spurious winners; anchors switch class inside the window)
SEARCH_MAX_ANCHORS = 6
JUMP_MAX_GAP_NS = 500_000_000  # residual jumps: consecutive ranges at most this far apart
JUMP_MAX_M = 1.0  # a residual change beyond this is a gross outlier, not a jump
# gross-outlier floor of each component's likelihood: 2 % spread over 20 m
LOG_OUTLIER = math.log(0.02 / 20.0)


@dataclass
class NlosModel:
    """Range-error model (see the module docstring); lengths in metres, times in seconds."""

    sigma_los: float
    sigma_nlos: float
    mu_nlos: float
    sigma_slow: float
    tau_s: float
    segment_s: float
    p_nlos: float
    p_switch: float

    @classmethod
    def from_config(cls, uwb: UwbConfig, graph: GraphConfig) -> NlosModel:
        return cls(uwb.sigma, graph.nlos_sigma, graph.nlos_mean, graph.nlos_slow_sigma,
                   graph.nlos_tau, graph.nlos_segment, graph.nlos_rate, graph.nlos_switch)

    @property
    def chain_sigma(self) -> float:
        """Std of the NLOS state's change over one segment (Gauss-Markov), m."""
        phi = math.exp(-self.segment_s / self.tau_s)
        return self.sigma_slow * math.sqrt(max(1.0 - phi * phi, 1e-6))

    @property
    def reversion_sigma(self) -> float:
        """Std of the per-segment pull of a chained NLOS state towards D + mu, m."""
        return self.sigma_slow * math.sqrt(2.0 * self.tau_s / self.segment_s)

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


def huber_log_density(r: np.ndarray, sigma: float, k: float) -> np.ndarray:
    """log of the normalised Huber density (Gaussian core, exponential tails beyond k
    sigmas) of residuals r (m): the predictive density of the robust range model."""
    u = np.abs(r) / sigma
    rho = np.where(u <= k, 0.5 * u * u, k * u - 0.5 * k * k)
    z = math.sqrt(2.0 * math.pi) * math.erf(k / math.sqrt(2.0)) + 2.0 * math.exp(-0.5 * k * k) / k
    return -rho - math.log(sigma * z)


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

    def ll(x: np.ndarray, s: float) -> np.ndarray:
        return np.logaddexp(-0.5 * (x / s) ** 2 - math.log(s) - _LOG_SQRT_2PI, LOG_OUTLIER)

    out = np.empty((len(d), 2, 2))
    out[:, 0, 0] = ll(d, s_stay_l)
    out[:, 0, 1] = ll(d - m, s_jump)
    out[:, 1, 0] = ll(d + m, s_jump)
    out[:, 1, 1] = ll(d, s_stay_n)
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
    jump (NaN). One vectorised call instead of one per anchor."""
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
    out = np.empty(len(ll_los))
    priors = np.empty(len(ll_los))
    p = p0
    d = np.clip(ll_nlos - ll_los, -50.0, 50.0)
    t_ln = p_switch * p_nlos  # P(LOS -> NLOS)
    t_nl = p_switch * (1.0 - p_nlos)  # P(NLOS -> LOS)
    jl = None if jump_ll is None else np.exp(jump_ll - jump_ll.max(axis=(1, 2), keepdims=True))
    for i in range(len(d)):
        if jl is None:
            prior = (1.0 - p_switch) * p + p_switch * p_nlos
        else:
            j = jl[i]
            to_n = (1.0 - p) * t_ln * j[0, 1] + p * (1.0 - t_nl) * j[1, 1]
            to_l = (1.0 - p) * (1.0 - t_ln) * j[0, 0] + p * t_nl * j[1, 0]
            prior = to_n / max(to_n + to_l, 1e-300)
        prior = min(max(prior, 1e-4), 1.0 - 1e-4)
        priors[i] = prior
        lo = math.log(prior / (1.0 - prior)) + d[i]
        p = 1.0 / (1.0 + math.exp(-lo))
        out[i] = p
    return out, p, priors


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
    n = len(ll_los)
    if n == 0:
        return np.zeros(0)
    a = np.array([[1.0 - p_switch * p_nlos, p_switch * p_nlos],
                  [p_switch * (1.0 - p_nlos), 1.0 - p_switch * (1.0 - p_nlos)]])
    m = np.maximum(ll_los, ll_nlos)
    e = np.stack([np.exp(ll_los - m), np.exp(ll_nlos - m)], axis=1)
    # per-step transition matrices: `a`, each entry scaled by the jump evidence if any
    if jump_ll is None:
        tr = np.broadcast_to(a, (n, 2, 2))
    else:
        tr = a * np.exp(jump_ll - jump_ll.max(axis=(1, 2), keepdims=True))
    t00, t01 = tr[:, 0, 0].tolist(), tr[:, 0, 1].tolist()
    t10, t11 = tr[:, 1, 0].tolist(), tr[:, 1, 1].tolist()
    alpha = np.empty((n, 2))
    q0 = p_nlos if p0 is None else min(max(p0, 1e-4), 1.0 - 1e-4)
    cur = np.array([1.0 - q0, q0]) * e[0]
    alpha[0] = cur / cur.sum()
    e0, e1 = e[:, 0].tolist(), e[:, 1].tolist()
    x0, x1 = float(alpha[0, 0]), float(alpha[0, 1])
    for i in range(1, n):
        y0 = (x0 * t00[i] + x1 * t10[i]) * e0[i]
        y1 = (x0 * t01[i] + x1 * t11[i]) * e1[i]
        s = max(y0 + y1, 1e-300)
        x0, x1 = y0 / s, y1 / s
        alpha[i, 0], alpha[i, 1] = x0, x1
    post = np.empty(n)
    post[-1] = alpha[-1, 1]
    b0, b1 = 1.0, 1.0
    for i in range(n - 2, -1, -1):
        c0, c1 = e0[i + 1] * b0, e1[i + 1] * b1
        j = i + 1
        nb0, nb1 = t00[j] * c0 + t01[j] * c1, t10[j] * c0 + t11[j] * c1
        s = max(nb0 + nb1, 1e-300)
        b0, b1 = nb0 / s, nb1 / s
        g0, g1 = alpha[i, 0] * b0, alpha[i, 1] * b1
        post[i] = g1 / max(g0 + g1, 1e-300)
    return post


def range_factor(
    k: int,
    anchor: int,
    measured: float,
    sigma: float,
    body_t_tag: gtsam.Pose3,
    uwb: UwbConfig,
    bias_key: int | None,
) -> gtsam.NonlinearFactor:
    """Range from X(k) through `body_t_tag` to anchor L(a), plus the bias variable if any."""
    noise = range_noise(sigma, uwb.robust_kernel, uwb.kernel_threshold)
    return range_factor_keyed(X(k), L(anchor), bias_key, float(measured), noise, body_t_tag)


def range_factor_keyed(
    pose_key: int, anchor_key: int, bias_key: int | None, measured: float,
    noise: gtsam.noiseModel.Base, body_t_tag: gtsam.Pose3,
) -> gtsam.NonlinearFactor:
    """The native range factor of `range_factor` from keys and a ready noise model."""
    if bias_key is not None:
        return gtsam.RangeFactorWithTransformBias3D(
            pose_key, anchor_key, bias_key, measured, noise, body_t_tag)
    return gtsam.RangeFactorWithTransform3D(pose_key, anchor_key, measured, noise, body_t_tag)


def los_bias_key(anchor: int, estimate_bias: bool, g: float = 0.0) -> int | None:
    """Bias key of a range's LOS part: D(a), or None when biases are not estimated.

    (`g` is accepted for symmetry; selecting only confidently-LOS ranges to calibrate D(a)
    was tried and biases D(a) negative: the selection truncates the residuals.)
    """
    return D(anchor) if estimate_bias else None


def nlos_state_factors(
    graph: gtsam.NonlinearFactorGraph,
    key: int,
    los_bias: float,
    prev_key: int | None,
    model: NlosModel,
) -> None:
    """Priors of a new NLOS state E(a, s): mean reversion to los_bias + mu, chain to E(a, s-1).

    The reversion is a prior at the anchor's current LOS-bias estimate rather than a link
    to D(a): linked, the many NLOS segments of a mostly blocked anchor would drag its LOS
    bias towards their own mean excess.
    """
    rev = model.reversion_sigma if prev_key is not None else model.sigma_slow
    noise = gtsam.noiseModel.Isotropic.Sigma(1, rev)
    graph.add(gtsam.PriorFactorDouble(key, los_bias + model.mu_nlos, noise))
    if prev_key is not None:
        graph.add(gtsam.BetweenFactorDouble(
            prev_key, key, 0.0, gtsam.noiseModel.Isotropic.Sigma(1, model.chain_sigma)))


@dataclass
class LosHypothesis:
    """Outcome of `los_subset_search` over the anchors seen in a window."""

    anchors: np.ndarray  # anchor indices considered (M,)
    los: np.ndarray  # best hypothesis: anchor in LOS (M,) bool
    current: np.ndarray  # the current classification (M,) bool
    delta: np.ndarray  # horizontal shift (2,) of the window's track, m, under `los`
    excess: np.ndarray  # NLOS excess (M,) per anchor under `los` (0 where LOS), m
    gain: float  # negative log-likelihood of `current` minus that of `los` (>= 0)
    # E[delta delta^T] (2,2), m^2, over every admissible subset weighted by its evidence:
    # how far the window's track may sit from where it is, given the LOS/NLOS ambiguity
    shift_moment: np.ndarray = field(default_factory=lambda: np.zeros((2, 2)))


def los_subset_search(
    anchor: np.ndarray, r: np.ndarray, u: np.ndarray, g: np.ndarray, model: NlosModel,
    sigma_shift: float = SEARCH_SHIFT_SIGMA, max_anchors: int = SEARCH_MAX_ANCHORS,
) -> LosHypothesis | None:
    """Which anchors are in LOS over a short window, searched over every LOS/NLOS subset.

    Fixed-lag EM refines the responsibilities continuously from the current track and can
    settle where a track pulled by NLOS ranges makes some LOS anchors read long (they then
    fit as small NLOS excesses). This tests the discrete alternatives: for each subset S of
    the anchors taken as LOS for the whole window, the window's track may shift rigidly by
    delta (horizontal, prior std `sigma_shift`); LOS anchors have residuals N(0, sigma_los),
    an NLOS anchor a constant excess m_a ~ N(mu_nlos, sigma_slow) plus N(0, sigma_nlos).
    Everything is quadratic in (delta, m), so each subset's best negative log-likelihood is
    closed-form (m eliminated by a Schur complement) and all 2^M subsets are solved at once.
    A subset whose best fit needs a clearly negative excess for one of its NLOS anchors is
    ruled out (NLOS only lengthens ranges).

    anchor (N,) anchor index, r (N,) range residual z - h - D (m) at the current track,
    u (N,2) horizontal unit vector from the anchor to the tag (d range / d tag position),
    g (N,) current P(NLOS). Ranges with |r| > 1 m are left out as gross outliers. Returns
    None when there are more than `max_anchors` anchors (2^M subsets) or too few ranges.
    """
    ok = np.abs(r) < 1.0
    anchor, r, u, g = anchor[ok], r[ok], u[ok], g[ok]
    ids, inv = np.unique(anchor, return_inverse=True)
    m = len(ids)
    if m == 0 or m > max_anchors or len(r) < 3 * m:
        return None
    n = np.bincount(inv, minlength=m).astype(float)

    def per_anchor(x: np.ndarray) -> np.ndarray:  # sums of the rows of x per anchor
        flat = x.reshape(len(x), -1)
        out = np.stack([np.bincount(inv, weights=flat[:, j], minlength=m)
                        for j in range(flat.shape[1])], axis=1)
        return out.reshape((m, *x.shape[1:]))

    suu = per_anchor(u[:, :, None] * u[:, None, :])
    su = per_anchor(u)
    sur = per_anchor(u * r[:, None])
    sr = np.bincount(inv, weights=r, minlength=m)
    srr = np.bincount(inv, weights=r * r, minlength=m)
    p = min(max(model.p_nlos, 0.02), 0.98)
    # LOS: 1/2 d'A d - b'd + c per anchor
    wl = 1.0 / model.sigma_los**2
    a_l, b_l = wl * suu, wl * sur
    c_l = 0.5 * wl * srr + n * math.log(model.sigma_los) - math.log(1.0 - p)
    # NLOS with its excess m_a eliminated; its fast noise adds to the LOS noise (else an
    # unadapted, loose sigma_los would make NLOS the tighter fit for any anchor)
    s_n = math.hypot(model.sigma_los, model.sigma_nlos)
    wn, k, mu = 1.0 / s_n**2, 1.0 / model.sigma_slow**2, model.mu_nlos
    hmm_ = wn * n + k
    gm = wn * sr + k * mu
    a_n = wn * suu - (wn * su)[:, :, None] * (wn * su)[:, None, :] / hmm_[:, None, None]
    b_n = wn * sur - (wn * su) * (gm / hmm_)[:, None]
    c_n = (0.5 * wn * srr + 0.5 * k * mu * mu - 0.5 * gm * gm / hmm_ + 0.5 * np.log(hmm_)
           + n * math.log(s_n) + math.log(model.sigma_slow) - math.log(p))
    subsets = ((np.arange(2**m)[:, None] >> np.arange(m)[None, :]) & 1).astype(bool)  # LOS
    sel = subsets[:, :, None, None]
    a_tot = np.where(sel, a_l, a_n).sum(axis=1) + np.eye(2) / sigma_shift**2
    b_tot = np.where(subsets[:, :, None], b_l, b_n).sum(axis=1)
    c_tot = np.where(subsets, c_l, c_n).sum(axis=1)
    delta = np.linalg.solve(a_tot, b_tot[:, :, None])[:, :, 0]
    cost = c_tot - 0.5 * np.einsum("si,si->s", b_tot, delta)
    # NLOS only lengthens ranges: a subset that needs a clearly negative excess (beyond
    # EXCESS_FLOOR, room for LOS biases that have absorbed some NLOS) is not a hypothesis
    ex_all = (gm[None, :] - wn * np.einsum("mi,si->sm", su, delta)) / hmm_[None, :]
    invalid = np.any(~subsets & (ex_all < EXCESS_FLOOR), axis=1)
    cur_w = np.bincount(inv, weights=g, minlength=m) / n
    current = cur_w < 0.5
    i_cur = int(np.sum(current.astype(int) << np.arange(m)))
    best = int(np.argmin(np.where(invalid, np.inf, cost)))
    los = subsets[best]
    # evidence of each subset: its best fit plus the Laplace width of the shift
    evidence = np.where(invalid, np.inf, cost + 0.5 * np.log(np.linalg.det(a_tot)))
    w = np.exp(-(evidence - evidence.min()))
    w /= w.sum()
    moment = np.einsum("s,si,sj->ij", w, delta, delta)
    return LosHypothesis(ids, los, current, delta[best], np.where(los, 0.0, ex_all[best]),
                         float(cost[i_cur] - cost[best]), moment)
