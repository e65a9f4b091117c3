# SPDX-License-Identifier: BSD-3-Clause
"""NLOS-weighted least squares and its calibration (Qiu et al. 2022), on the per-range view
of the NLOS model (`uwbfuse.nlos`: LOS e ~ N(0, los_std^2), NLOS e ~ N(nlos_mean,
nlos_std^2), prior nlos_prior per range, per anchor when calibrated).

- `weighted_fix`: Qiu eq. 10-11 per epoch: weights beta_i = 1 / E[var_i] with the NLOS
  probability of each range (`nlos.nlos_probability`), the expected NLOS excess subtracted,
  iterated (EM-like) from a robust start, then refined by Gauss-Newton with the same weights.
- `calibrate_nlos`: Qiu eq. 8-9: per anchor, the histogram of range errors (against ground
  truth) is fitted by scaled normal curves f(x) = A / (sqrt(2 pi) sigma) exp(-(x - mean)^2 /
  (2 sigma^2)) by quasi-Newton (L-BFGS-B) least squares on the bin frequencies; a LOS and an
  NLOS component per anchor give los_std, nlos_mean, nlos_std and nlos_prior = A_nlos /
  (A_los + A_nlos).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import minimize
from scipy.spatial.transform import Rotation

from uwbfuse.config import Config, RobustKernel
from uwbfuse.constants import MAX_LOS_STD, MIN_LOS_STD
from uwbfuse.errors import EstimatorError
from uwbfuse.nlos import NlosModel, NlosParams, nlos_probability, normal_pdf
from uwbfuse.positioning.multilateration import (
    Fixes,
    gauss_newton,
    linear_ls,
    multilaterate,
    project_ranges,
    select_nearest,
)
from uwbfuse.streams import AnchorMap, SensorLog

F64 = NDArray[np.float64]

@dataclass(frozen=True)
class WeightedFixes:
    """`weighted_fix` output: the fixes and each range's final NLOS probability (N,M)."""

    fixes: Fixes
    nlos_prob: F64


def weighted_fix(
    anchors: AnchorMap,
    rng: F64,
    model: NlosModel,
    *,
    dim: int = 3,
    tag_z: F64 | float | None = None,
    nearest: int | None = None,
    iterations: int = 3,
    p_nlos: F64 | None = None,
) -> WeightedFixes:
    """NLOS-weighted fixes (Qiu eq. 10-11) for N epochs of ranges rng (N,M) (m, NaN missing).

    Start: Huber Gauss-Newton with each anchor's mixture std. Then repeat: residuals ->
    NLOS probabilities p -> weights 1 / ((1-p) los^2 + p nlos^2) and ranges corrected by the
    expected excess p * nlos_mean -> weighted linear LS (eq. 10) -> weighted Gauss-Newton.
    `p_nlos` (N,M), when given (the learned classifier's P(NLOS) per range, NaN = unknown:
    the prior), replaces the residual-based probabilities in every round.
    """
    pos_a = anchors.positions
    rng = np.atleast_2d(np.asarray(rng, dtype=np.float64)).copy()
    if nearest is not None:
        rng[~select_nearest(rng, nearest)] = np.nan
    los, nmean, nstd, prior = model.arrays(anchors)
    mix_var = (1 - prior) * los**2 + prior * (nstd**2 + nmean**2) - (prior * nmean) ** 2
    sig0 = np.sqrt(np.maximum(mix_var, MIN_LOS_STD**2))
    # Start from the prior: expected excess removed, mixture std as weights.
    start = rng - prior * nmean
    fx = multilaterate(pos_a, start, dim=dim, tag_z=tag_z, sigma=sig0[None, :],
                       kernel=RobustKernel.HUBER, threshold=1.345)
    p = np.broadcast_to(prior, rng.shape).copy()
    given = None if p_nlos is None else np.where(np.isfinite(p_nlos), p_nlos, p)
    n = len(rng)
    for _ in range(iterations):
        pos = np.where(np.isfinite(fx.position), fx.position, 0.0)
        if given is not None:
            p = given
        else:
            pred = np.linalg.norm(pos[:, None, :] - pos_a[None, :, :], axis=2)
            res = rng - pred
            pos_var = np.nan_to_num(np.trace(fx.cov, axis1=1, axis2=2), nan=1.0)
            p = nlos_probability(res, los, nmean, nstd, prior,
                                 extra_var=pos_var[:, None] / dim)
            p = np.where(fx.ok[:, None], p, prior)
        var = (1 - p) * np.maximum(los, MIN_LOS_STD) ** 2 + p * nstd**2
        corrected = rng - p * nmean
        sigma = np.sqrt(var)
        w = 1.0 / var
        if dim == 2:
            assert tag_z is not None
            z = np.broadcast_to(np.asarray(tag_z, dtype=np.float64), (n,))
            xy, _ = linear_ls(pos_a[:, :2], project_ranges(corrected, pos_a[:, 2], z), w)
            x0 = np.column_stack([xy, z])
        else:
            x0 = pos
        x0 = np.where(np.isfinite(x0), x0, pos)
        fx = gauss_newton(pos_a, corrected, x0, sigma, dim=dim, kernel=RobustKernel.HUBER,
                          threshold=2.5, iterations=10)
    return WeightedFixes(fx, p)


# ---------------------------------------------------------------------- calibration
def _fit_histogram(
    errors: F64, bins: int, los_guess: NlosParams,
    los_bounds: tuple[float, float] = (0.003, 0.15),
) -> NlosParams:
    """Qiu eq. 8-9: fit A_l N(0-ish, s_l) + A_n N(m_n, s_n) to the error histogram.

    los_bounds: allowed LOS std (m); per-anchor fits are held near the global LOS std (the
    LOS noise is the radio's), so that an anchor with few LOS ranges cannot turn its LOS
    curve into a second NLOS one.
    """
    e = errors[np.isfinite(errors)]
    lo, hi = np.percentile(e, [0.5, 99.5])
    lo, hi = min(lo, -4 * los_guess.los_std), max(hi, 4 * los_guess.los_std)
    counts, edges = np.histogram(e, bins=bins, range=(lo, hi))
    width = edges[1] - edges[0]
    a_k = 0.5 * (edges[1:] + edges[:-1])  # bin midpoints, m
    b_k = counts / (len(e) * width)  # frequency density, 1/m

    def model(theta: F64) -> F64:
        w_l, mu_l, ls_l, w_n, mu_n, ls_n = theta
        return (w_l * normal_pdf(a_k, mu_l, math.exp(ls_l))
                + w_n * normal_pdf(a_k, mu_n, math.exp(ls_n)))

    def cost(theta: F64) -> float:
        return float(np.sum((model(theta) - b_k) ** 2))

    s_l = float(np.clip(np.std(e[np.abs(e) < 3 * los_guess.los_std + 0.05]), *los_bounds))
    best = None
    # Multi-start over the NLOS mean and the LOS/NLOS split: with mostly-NLOS logs a
    # start at 80 % LOS lets the LOS curve widen over the NLOS mode (a local minimum).
    starts = [(mu, w) for mu in (los_guess.nlos_mean, 3 * los_guess.nlos_mean, 0.5)
              for w in (0.2, 0.5, 0.8)]
    for mu_n0, w_n0 in starts:
        theta0 = np.array([1.0 - w_n0, 0.0, math.log(s_l), w_n0, mu_n0,
                           math.log(los_guess.nlos_std)])
        bounds = [(0.0, 1.5), (-0.1, 0.1), (math.log(los_bounds[0]), math.log(los_bounds[1])),
                  (0.0, 1.5), (0.0, 3.0), (math.log(0.01), math.log(2.0))]
        r = minimize(cost, theta0, method="L-BFGS-B", bounds=bounds)
        if best is None or r.fun < best.fun:
            best = r
    assert best is not None
    w_l, _mu_l, ls_l, w_n, mu_n, ls_n = best.x
    total = max(w_l + w_n, 1e-9)
    prior = float(w_n / total)
    los_std, nlos_std = float(math.exp(ls_l)), float(math.exp(ls_n))
    if prior < 0.01 or nlos_std < 2.0 * los_std or mu_n < los_std:
        # No distinct NLOS mode (a second curve that only widens the LOS one): keep the
        # LOS fit and the prior NLOS distribution, so rare NLOS ranges are not over-weighted.
        return NlosParams(los_std, los_guess.nlos_mean, los_guess.nlos_std,
                          float(np.clip(prior, 0.01, los_guess.nlos_prior)))
    return NlosParams(los_std, float(mu_n), nlos_std, prior)


def range_errors(log: SensorLog, config: Config) -> tuple[F64, NDArray[np.int32]]:
    """Measured minus true range (m) for every range of a log with ground truth.

    The true tag position is the ground-truth base pose interpolated at the range stamp
    (linear position, nearest orientation) with `tag_in_base` applied. Ranges outside the
    ground-truth time span are NaN. Returns (errors (R,), anchor indices (R,)).
    """
    gt, rs, anchors = log.ground_truth, log.ranges, log.anchors
    if gt is None or len(gt) < 2:
        raise EstimatorError(f"{log.source}: calibrate-nlos needs ground truth in the log")
    if rs is None or not len(rs) or anchors is None:
        raise EstimatorError(f"{log.source}: calibrate-nlos needs ranges and an anchor map")
    t = rs.t_ns
    pos = np.column_stack([np.interp(t, gt.t_ns, gt.position[:, k]) for k in range(3)])
    k = np.clip(np.searchsorted(gt.t_ns, t), 0, len(gt) - 1)
    rot = Rotation.from_quat(gt.quat_xyzw[k]).as_matrix()
    tag = pos + rot @ np.asarray(config.extrinsics.tag_in_base, dtype=np.float64)
    true = np.linalg.norm(tag - anchors.positions[rs.anchor], axis=1)
    err = rs.range - true
    outside = (t < gt.t_ns[0]) | (t > gt.t_ns[-1])
    err[outside] = np.nan
    return err, rs.anchor


def calibrate_nlos(
    log: SensorLog, config: Config, *, bins: int = 60, min_samples: int = 200
) -> NlosModel:
    """Fit the LOS/NLOS range-error distributions per anchor (Qiu eq. 8-9) from a log with
    ground truth; anchors with fewer than `min_samples` ranges keep the global fit.

    Returns the config's `NlosModel` with the fitted per-range model;
    `model.per_range_toml()` gives its `[nlos]` values.
    """
    err, anc = range_errors(log, config)
    assert log.anchors is not None
    base = NlosModel.from_config(config)
    guess = base.per_range
    ok = np.isfinite(err)
    if np.count_nonzero(ok) < min_samples:
        raise EstimatorError(
            f"{log.source}: calibrate-nlos needs at least {min_samples} ranges within the "
            f"ground-truth time span, got {int(np.count_nonzero(ok))}"
        )
    default = _fit_histogram(err[ok], bins, guess, (0.003, MAX_LOS_STD))
    per: dict[str, NlosParams] = {}
    samples: dict[str, int] = {}
    for i, aid in enumerate(log.anchors.ids):
        e = err[ok & (anc == i)]
        samples[aid] = len(e)
        if len(e) >= min_samples:
            g = default.los_std
            per[aid] = _fit_histogram(e, bins, default, (0.5 * g, 2.0 * g))
    return replace(base, per_range=default, per_anchor=per, samples=samples)


def calibrate_nlos_file(
    log_path: str | Path, *, config_path: str | Path | None = None,
    gt_path: str | Path | None = None,
) -> str:
    """`uwbfuse calibrate-nlos`: fit the per-range model on a log and return it as an
    `[nlos]` TOML snippet to paste into the config. Ground truth from the log or from a TUM
    file."""
    from uwbfuse.config import _toml_value, load_config
    from uwbfuse.io.reader import read_log
    from uwbfuse.io.tum import read_tum

    config = load_config(config_path)
    log = read_log(log_path, config)
    if gt_path is not None:
        log.ground_truth = read_tum(gt_path)
    model = calibrate_nlos(log, config)
    values = model.per_range_toml()
    per_anchor = values.pop("anchor")
    lines = [f"# per-range NLOS range-error model fitted on {log_path} (metres)", "[nlos]"]
    lines += [f"{k} = {_toml_value(v)}" for k, v in values.items()]
    lines += ["", "[nlos.anchor]  # id = [los_std, nlos_mean, nlos_std, nlos_prior]"]
    lines += [f'"{k}" = {_toml_value(v)}' for k, v in per_anchor.items()]
    return "\n".join(lines) + "\n"
