# SPDX-License-Identifier: BSD-3-Clause
"""UWB range factors and the NLOS mixture model.

Range model (metres): z = |p_tag - anchor| + b_a + e, with b_a the constant per-anchor
bias (antenna delay; a variable D(a) with a prior when enabled) and e drawn from a
two-component mixture: LOS N(0, sigma_los) or NLOS N(mu_nlos, sigma_nlos), mu_nlos > 0
(the direct path is blocked, so NLOS ranges read long).

The mixture is handled by expectation-maximisation with native factors only: given the
responsibility g = P(NLOS | residual), the expected negative log-likelihood of one range is
a single Gaussian with precision (1-g)/sigma_los^2 + g/sigma_nlos^2 and mean shift
g*mu_nlos/sigma_nlos^2 / precision, so each range stays one `RangeFactorWithTransform(Bias)3D`
whose measurement and sigma carry the E-step. The robust kernel (Huber by default) wraps
that Gaussian and still bounds gross outliers. NLOS in buildings persists per anchor, so
responsibilities use a two-state hidden Markov prior per anchor (forward filtering online,
forward-backward in batch). The M-step re-estimates sigma_los, mu_nlos, sigma_nlos and the
NLOS rate from the responsibilities (floored so the components stay distinct).
"""

from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np

from uwbfuse.config import GraphConfig, RobustKernel, UwbConfig
from uwbfuse.graph.keys import D, L, X
from uwbfuse.graph.noise import range_noise

_LOG_SQRT_2PI = 0.5 * np.log(2.0 * np.pi)
SIGMA_LOS_MIN = 0.02
SIGMA_NLOS_MIN = 0.05
MU_NLOS_MIN = 0.08
# gross-outlier floor of the likelihood: uniform over 20 m, probability 2 %
_LOG_OUTLIER = np.log(0.02 / 20.0)


@dataclass
class MixtureParams:
    """Range-error mixture: LOS N(0, sigma_los), NLOS N(mu_nlos, sigma_nlos), rate p_nlos."""

    sigma_los: float
    mu_nlos: float
    sigma_nlos: float
    p_nlos: float

    @classmethod
    def from_config(cls, uwb: UwbConfig, graph: GraphConfig) -> MixtureParams:
        return cls(uwb.sigma, graph.nlos_mean, graph.nlos_sigma, graph.nlos_rate)

    def log_likelihoods(self, r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """log p(r | LOS), log p(r | NLOS) for residuals r = measured - predicted (m)."""
        ll_los = -0.5 * (r / self.sigma_los) ** 2 - np.log(self.sigma_los) - _LOG_SQRT_2PI
        z = (r - self.mu_nlos) / self.sigma_nlos
        ll_nlos = -0.5 * z * z - np.log(self.sigma_nlos) - _LOG_SQRT_2PI
        return np.logaddexp(ll_los, _LOG_OUTLIER), np.logaddexp(ll_nlos, _LOG_OUTLIER)

    def effective(self, g: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Mean shift (m) and sigma (m) of the single Gaussian that stands for responsibility g."""
        w_l = (1.0 - g) / self.sigma_los**2
        w_n = g / self.sigma_nlos**2
        lam = w_l + w_n
        return w_n * self.mu_nlos / lam, 1.0 / np.sqrt(lam)

    def m_step(self, r: np.ndarray, g: np.ndarray, prior: MixtureParams, n0: float = 50.0) -> None:
        """Re-estimate the parameters from residuals and responsibilities.

        `prior` enters as n0 pseudo-observations per component, so short logs keep the
        configured values and long ones follow the data. Gross residuals (> 1.5 m) are left
        to the robust kernel and not used.
        """
        ok = np.abs(r) < 1.5
        r, g = r[ok], g[ok]
        if len(r) < 20:
            return
        w_l, w_n = 1.0 - g, g
        s_l = (np.sum(w_l * r * r) + n0 * prior.sigma_los**2) / (np.sum(w_l) + n0)
        mu = (np.sum(w_n * r) + n0 * prior.mu_nlos) / (np.sum(w_n) + n0)
        s_n = (np.sum(w_n * (r - mu) ** 2) + n0 * prior.sigma_nlos**2) / (np.sum(w_n) + n0)
        self.sigma_los = max(float(np.sqrt(s_l)), SIGMA_LOS_MIN)
        self.mu_nlos = max(float(mu), MU_NLOS_MIN)
        self.sigma_nlos = max(float(np.sqrt(s_n)), SIGMA_NLOS_MIN)
        p = (np.sum(w_n) + n0 * prior.p_nlos) / (len(r) + 2 * n0)
        self.p_nlos = float(np.clip(p, 0.02, 0.9))


def hmm_filter(
    ll_los: np.ndarray, ll_nlos: np.ndarray, p_switch: float, p_nlos: float, p0: float
) -> tuple[np.ndarray, float]:
    """Forward pass of the two-state LOS/NLOS chain of one anchor (time-ordered ranges).

    Returns the filtered P(NLOS) per range and the last one. The transition mixes
    switching (probability `p_switch` per range) towards the stationary rate `p_nlos`.
    """
    out = np.empty(len(ll_los))
    p = p0
    d = ll_nlos - ll_los
    for i in range(len(d)):
        prior = (1.0 - p_switch) * p + p_switch * p_nlos
        prior = min(max(prior, 1e-4), 1.0 - 1e-4)
        lo = np.log(prior / (1.0 - prior)) + d[i]
        p = 1.0 / (1.0 + np.exp(-np.clip(lo, -50.0, 50.0)))
        out[i] = p
    return out, p


def hmm_smooth(
    ll_los: np.ndarray, ll_nlos: np.ndarray, p_switch: float, p_nlos: float
) -> np.ndarray:
    """Forward-backward P(NLOS) per range of one anchor (time-ordered)."""
    n = len(ll_los)
    if n == 0:
        return np.zeros(0)
    a = np.array([[1.0 - p_switch * p_nlos, p_switch * p_nlos],
                  [p_switch * (1.0 - p_nlos), 1.0 - p_switch * (1.0 - p_nlos)]])
    m = np.maximum(ll_los, ll_nlos)
    e = np.stack([np.exp(ll_los - m), np.exp(ll_nlos - m)], axis=1)
    alpha = np.empty((n, 2))
    cur = np.array([1.0 - p_nlos, p_nlos]) * e[0]
    alpha[0] = cur / cur.sum()
    for i in range(1, n):
        cur = (alpha[i - 1] @ a) * e[i]
        alpha[i] = cur / max(cur.sum(), 1e-300)
    beta = np.ones(2)
    post = np.empty(n)
    post[-1] = alpha[-1, 1]
    for i in range(n - 2, -1, -1):
        beta = a @ (e[i + 1] * beta)
        beta /= max(beta.sum(), 1e-300)
        g = alpha[i] * beta
        post[i] = g[1] / max(g.sum(), 1e-300)
    return post


def range_factor(
    k: int,
    anchor: int,
    measured: float,
    sigma: float,
    body_t_tag: gtsam.Pose3,
    uwb: UwbConfig,
    with_bias: bool,
) -> gtsam.NonlinearFactor:
    """Range from keyframe pose X(k) through `body_t_tag` to anchor L(a) (+ bias D(a))."""
    noise = range_noise(sigma, uwb.robust_kernel, uwb.kernel_threshold)
    if with_bias:
        return gtsam.RangeFactorWithTransformBias3D(
            X(k), L(anchor), D(anchor), float(measured), noise, body_t_tag
        )
    return gtsam.RangeFactorWithTransform3D(X(k), L(anchor), float(measured), noise, body_t_tag)


def predicted_ranges(
    poses_rt: tuple[np.ndarray, np.ndarray], tag_in_body: np.ndarray, anchors: np.ndarray
) -> np.ndarray:
    """|R p_tag + t - anchor| (m) for rotations (N,3,3), translations (N,3), tags (N,3)."""
    rot, trans = poses_rt
    p = np.einsum("nij,nj->ni", rot, tag_in_body) + trans
    return np.linalg.norm(p - anchors, axis=1)


def kernel_is_robust(kernel: RobustKernel) -> bool:
    return kernel is not RobustKernel.NONE
