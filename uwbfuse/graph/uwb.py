# SPDX-License-Identifier: BSD-3-Clause
"""UWB range factors: the NLOS model (`uwbfuse.nlos`) as native GTSAM factors.

Range model (metres): z = |p_tag - anchor| + b + e. While the anchor is in line of sight
(LOS), b = D(a), the anchor's constant offset (antenna delay; a variable with a prior when
`estimate_range_bias`), and e ~ N(0, sigma_los). While it is in NLOS, the direct path is
blocked and the range reads long by a slowly varying excess: b = E(a, s), a per-anchor state
per time segment s (`[nlos] segment` seconds) that follows a Gauss-Markov process around
D(a) + mu_nlos (`[nlos] excess_mean`, std `excess_slow_sigma`, correlation time `tau`), and
e ~ N(0, sigma_nlos) (`excess_sigma`). All of it is native GTSAM:
`RangeFactorWithTransformBias3D` with bias key D(a) or E(a, s), and `BetweenFactorDouble`
links D -> E (mean reversion) and E(s-1) -> E(s) (random walk).

Which component a range belongs to is hidden. Expectation-maximisation keeps the factors
native: with responsibility g = P(NLOS | data), the expected negative log-likelihood is
(1-g) r_los^2 / sigma_los^2 + g r_nlos^2 / sigma_nlos^2, i.e. a LOS factor with sigma
sigma_los / sqrt(1-g) plus an NLOS factor with sigma sigma_nlos / sqrt(g) (either dropped
when its weight is below 1 %). The robust kernel (Huber by default) wraps both and bounds
gross outliers. The responsibilities (two-state hidden Markov chain per anchor, residual
jumps) and the M-step are the model's, in `uwbfuse.nlos`.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field

import gtsam
import numpy as np

from uwbfuse.config import KERNEL_THRESHOLD_95, RobustKernel, UwbConfig
from uwbfuse.constants import EXCESS_FLOOR, SEARCH_MAX_ANCHORS, SEARCH_SHIFT_SIGMA
from uwbfuse.graph.keys import D
from uwbfuse.nlos import NlosModel


def huber_log_density(r: np.ndarray, sigma: float, k: float) -> np.ndarray:
    """log of the normalised Huber density (Gaussian core, exponential tails beyond k
    sigmas) of residuals r (m): the predictive density of the robust range model."""
    u = np.abs(r) / sigma
    rho = np.where(u <= k, 0.5 * u * u, k * u - 0.5 * k * k)
    z = math.sqrt(2.0 * math.pi) * math.erf(k / math.sqrt(2.0)) + 2.0 * math.exp(-0.5 * k * k) / k
    return -rho - math.log(sigma * z)


def robust_log_density(r: np.ndarray, sigma: float, uwb: UwbConfig) -> np.ndarray:
    """log predictive density of residuals r (m) under the robust range model at LOS
    sigma `sigma` (m): the Huber density at the configured threshold under the Huber
    kernel; under any other kernel (or none) at Huber's own 95 %-efficiency threshold, since
    a redescending kernel's loss is bounded and no density (docs/results.md, "Other range
    kernels on a real log")."""
    k = (uwb.kernel_threshold if uwb.robust_kernel is RobustKernel.HUBER
         else KERNEL_THRESHOLD_95[RobustKernel.HUBER])
    return huber_log_density(r, sigma, k)


def range_factor_keyed(
    pose_key: int, anchor_key: int, bias_key: int | None, measured: float,
    noise: gtsam.noiseModel.Base, body_t_tag: gtsam.Pose3,
) -> gtsam.NonlinearFactor:
    """Range from `pose_key` through `body_t_tag` to the anchor `anchor_key` (m), plus the
    bias variable `bias_key` if any, with a ready noise model (`noise.range_noise`)."""
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


_N_SUMS = 12  # per-anchor sums of `los_subset_search`


@functools.cache
def _subsets(m: int) -> np.ndarray:
    """Every subset of m anchors (2^m, m) bool, row i holding the bits of i (shared: not
    to be written)."""
    out = ((np.arange(2**m)[:, None] >> np.arange(m)[None, :]) & 1).astype(bool)
    out.flags.writeable = False
    return out


def unique_inverse(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """`np.unique(x, return_inverse=True)` of integers (N,), by one sort and a search: the
    same arrays at half the cost for a review window's few hundred ranges."""
    srt = np.sort(x)
    code = srt[np.concatenate([[True], srt[1:] != srt[:-1]])] if len(srt) else srt
    return code, np.searchsorted(code, x)


def los_subset_search(
    anchor: np.ndarray, r: np.ndarray, u: np.ndarray, g: np.ndarray, model: NlosModel,
    sigma_shift: float = SEARCH_SHIFT_SIGMA, max_anchors: int = SEARCH_MAX_ANCHORS,
    moment: bool = True, weights: np.ndarray | None = None,
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
    `moment` False: the hypothesis' `shift_moment` is left zero (a caller that reports no
    covariance skips its evidence weights; the hypothesis is the same). `weights` (N,):
    each range's share of one independent range's evidence (`rest.RestEvidence`; None: 1).
    """
    ok = np.abs(r) < 1.0
    anchor, r, u, g = anchor[ok], r[ok], u[ok], g[ok]
    ids, inv = unique_inverse(anchor)
    m = len(ids)
    if m == 0 or m > max_anchors or len(r) < 3 * m:
        return None
    count = np.bincount(inv, minlength=m).astype(float)
    # per anchor, the sums of u u^T (4), u (2), u r (2), r, r^2, 1 (each weighted) and g:
    # one bincount over the columns side by side (each anchor's sum of a column adds its
    # rows in order, as a bincount of that column alone does)
    wt = np.ones(len(r)) if weights is None else np.asarray(weights, np.float64)[ok]
    wr = wt * r
    cols = np.concatenate([(u[:, :, None] * u[:, None, :]).reshape(-1, 4) * wt[:, None],
                           u * wt[:, None], u * wr[:, None], wr[:, None], (wr * r)[:, None],
                           wt[:, None], g[:, None]], axis=1)
    sums = np.bincount((inv[:, None] * _N_SUMS + np.arange(_N_SUMS)).ravel(),
                       weights=cols.ravel(), minlength=m * _N_SUMS).reshape(m, _N_SUMS)
    suu, su, sur = sums[:, :4].reshape(m, 2, 2), sums[:, 4:6], sums[:, 6:8]
    sr, srr, n, sg = sums[:, 8], sums[:, 9], sums[:, 10], sums[:, 11]
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
    subsets = _subsets(m)  # LOS
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
    cur_w = sg / count
    current = cur_w < 0.5
    i_cur = int(np.sum(current.astype(int) << np.arange(m)))
    best = int(np.argmin(np.where(invalid, np.inf, cost)))
    los = subsets[best]
    hyp = LosHypothesis(ids, los, current, delta[best], np.where(los, 0.0, ex_all[best]),
                        float(cost[i_cur] - cost[best]))
    if moment:  # evidence of each subset: its best fit plus the Laplace width of the shift
        evidence = np.where(invalid, np.inf, cost + 0.5 * np.log(np.linalg.det(a_tot)))
        w = np.exp(-(evidence - evidence.min()))
        w /= w.sum()
        hyp.shift_moment = np.einsum("s,si,sj->ij", w, delta, delta)
    return hyp
