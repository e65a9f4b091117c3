# SPDX-License-Identifier: BSD-3-Clause
"""Batch refinement: the whole log as one graph, Levenberg-Marquardt with NLOS EM.

Starting from the online pass's keyframe estimates, each round (1) computes every range
residual at the current estimate (vectorised numpy, no factor calls), (2) E-step: per-anchor
forward-backward LOS/NLOS responsibilities, (3) M-step: mixture parameters, (4) rebuilds the
range factors with the expected (single-Gaussian) likelihood and runs LM from the current
values. Rounds stop early when the responsibilities settle.
"""

from __future__ import annotations

import copy
import logging
from dataclasses import dataclass

import gtsam
import numpy as np

from uwbfuse.config import Config
from uwbfuse.graph.keys import D, X
from uwbfuse.graph.noise import robust_weight
from uwbfuse.graph.uwb import MixtureParams, hmm_smooth, range_factor

log = logging.getLogger(__name__)


@dataclass
class BatchResult:
    """Optimised values, final responsibilities and kernel weights per range."""

    values: gtsam.Values
    nlos_prob: np.ndarray
    weight: np.ndarray
    residual: np.ndarray
    mixture: MixtureParams
    rounds: int
    lm_iterations: int


def keyframe_arrays(values: gtsam.Values, n_kf: int) -> tuple[np.ndarray, np.ndarray]:
    """Rotations (n,3,3) and translations (n,3) of X(0..n-1)."""
    rot = np.empty((n_kf, 3, 3))
    trans = np.empty((n_kf, 3))
    for k in range(n_kf):
        p = values.atPose3(X(k))
        rot[k] = p.rotation().matrix()
        trans[k] = p.translation()
    return rot, trans


def residuals(
    values: gtsam.Values, rec: dict[str, np.ndarray], anchors: np.ndarray, n_kf: int,
    with_bias: bool,
) -> np.ndarray:
    """measured - predicted - bias (m) for every recorded range."""
    rot, trans = keyframe_arrays(values, n_kf)
    k = rec["k"]
    p = np.einsum("nij,nj->ni", rot[k], rec["tag_in_kf"]) + trans[k]
    pred = np.linalg.norm(p - anchors[rec["anchor"]], axis=1)
    r = rec["z"] - pred
    if with_bias:
        b = np.array([values.atDouble(D(a)) for a in range(len(anchors))])
        r = r - b[rec["anchor"]]
    return r


def _responsibilities(
    r: np.ndarray, anchor: np.ndarray, mix: MixtureParams, p_switch: float
) -> np.ndarray:
    ll_l, ll_n = mix.log_likelihoods(r)
    g = np.zeros(len(r))
    for a in np.unique(anchor):
        sel = np.flatnonzero(anchor == a)  # records are time-ordered per anchor
        g[sel] = hmm_smooth(ll_l[sel], ll_n[sel], p_switch, mix.p_nlos)
    return g


def solve(
    cfg: Config,
    base_graph: gtsam.NonlinearFactorGraph,
    initial: gtsam.Values,
    rec: dict[str, np.ndarray],
    anchors: np.ndarray,
    n_kf: int,
    mixture: MixtureParams,
) -> BatchResult:
    """EM + LM over the full graph (see the module docstring)."""
    g_cfg = cfg.graph
    with_bias = g_cfg.estimate_range_bias
    prior = MixtureParams.from_config(cfg.uwb, g_cfg)
    mix = copy.copy(mixture)
    values = initial
    rounds = max(g_cfg.em_iterations, 0) + 1 if g_cfg.nlos else 1
    g_prev = None
    total_it = 0
    order = np.lexsort((rec["t_ns"], rec["anchor"]))
    inv = np.empty_like(order)
    inv[order] = np.arange(len(order))
    r = residuals(values, rec, anchors, n_kf, with_bias)
    g = np.zeros(len(r))
    done = 0
    for it in range(rounds):
        if g_cfg.nlos:
            gs = _responsibilities(r[order], rec["anchor"][order], mix, g_cfg.nlos_switch)
            g = gs[inv]
            mix.m_step(r, g, prior)
            gs = _responsibilities(r[order], rec["anchor"][order], mix, g_cfg.nlos_switch)
            g = gs[inv]
            shift, sig = mix.effective(g)
        else:
            shift, sig = np.zeros(len(r)), np.full(len(r), cfg.uwb.sigma)
        if g_prev is not None and np.max(np.abs(g - g_prev), initial=0.0) < 0.05:
            break
        g_prev = g
        graph = gtsam.NonlinearFactorGraph(base_graph)
        zc = rec["z"] - shift
        for j in range(len(zc)):
            graph.add(range_factor(int(rec["k"][j]), int(rec["anchor"][j]), float(zc[j]),
                                   float(sig[j]), gtsam.Pose3(gtsam.Rot3(), rec["tag_in_kf"][j]),
                                   cfg.uwb, with_bias))
        params = gtsam.LevenbergMarquardtParams()
        params.setMaxIterations(g_cfg.lm_max_iterations)
        params.setRelativeErrorTol(1e-4)
        params.setAbsoluteErrorTol(1e-6)
        opt = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
        values = opt.optimize()
        total_it += opt.iterations()
        done = it + 1
        log.debug("batch round %d: %d LM iterations, error %.3f, mixture %s",
                  it, opt.iterations(), opt.error(), mix)
        r = residuals(values, rec, anchors, n_kf, with_bias)
    if g_cfg.nlos:
        shift, sig = mix.effective(g)
    else:
        shift, sig = np.zeros(len(r)), np.full(len(r), cfg.uwb.sigma)
    w = robust_weight(cfg.uwb.robust_kernel, cfg.uwb.kernel_threshold, (r - shift) / sig)
    return BatchResult(values, g, w, r, mix, done, total_it)
