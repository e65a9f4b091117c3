# SPDX-License-Identifier: BSD-3-Clause
"""Noise and robust-model factories built from the config.

Every GTSAM noise model of the graph comes from here, so units live in one place:
range sigmas in metres, rotation sigmas in radians, translation sigmas in metres.
"""

from __future__ import annotations

import functools
from collections.abc import Callable

import gtsam
import numpy as np

from uwbfuse.config import RobustKernel

_M = gtsam.noiseModel.mEstimator


@functools.cache
def robust_estimator(kernel: RobustKernel, threshold: float) -> gtsam.noiseModel.mEstimator.Base:
    """The m-estimator for `kernel` with `threshold` in sigmas (whitened units); one per
    (kernel, threshold), shared by the factors (an m-estimator is stateless: every range
    factor built its own)."""
    if kernel is RobustKernel.HUBER:
        return _M.Huber.Create(threshold)
    if kernel is RobustKernel.CAUCHY:
        return _M.Cauchy.Create(threshold)
    if kernel is RobustKernel.TUKEY:
        return _M.Tukey.Create(threshold)
    if kernel is RobustKernel.DCS:
        return _M.DCS.Create(threshold)
    if kernel is RobustKernel.GEMAN_MCCLURE:
        return _M.GemanMcClure.Create(threshold)
    return _M.Null.Create()


def range_noise(
    sigma: float, kernel: RobustKernel, threshold: float
) -> gtsam.noiseModel.Base:
    """1-D range noise (sigma in metres) wrapped in the robust kernel (threshold in sigmas)."""
    return range_noise_maker(kernel, threshold)(sigma)


def range_noise_maker(
    kernel: RobustKernel, threshold: float
) -> Callable[[float], gtsam.noiseModel.Base]:
    """1-D range noise at `kernel` and `threshold` (in sigmas) as a function of the sigma
    (m) alone, its m-estimator and constructors bound once (it runs for every range
    factor)."""
    sigma = gtsam.noiseModel.Isotropic.Sigma
    if kernel is RobustKernel.NONE:
        return lambda s: sigma(1, float(s))
    robust = gtsam.noiseModel.Robust.Create
    est = robust_estimator(kernel, threshold)
    return lambda s: robust(est, sigma(1, float(s)))


def robust_weight(kernel: RobustKernel, threshold: float, whitened: np.ndarray) -> np.ndarray:
    """Weights (0..1) the kernel gives to whitened residuals (vectorised, no GTSAM calls)."""
    e = np.abs(np.asarray(whitened, dtype=np.float64))
    k = threshold
    if kernel is RobustKernel.HUBER:
        return np.where(e <= k, 1.0, k / np.maximum(e, 1e-12))
    if kernel is RobustKernel.CAUCHY:
        return 1.0 / (1.0 + (e / k) ** 2)
    if kernel is RobustKernel.TUKEY:
        return np.where(e <= k, (1.0 - (e / k) ** 2) ** 2, 0.0)
    if kernel is RobustKernel.DCS:
        return np.where(e * e > k, (2.0 * k / (k + e * e)) ** 2, 1.0)
    if kernel is RobustKernel.GEMAN_MCCLURE:
        c2 = k * k
        return c2 * c2 / (c2 + e * e) ** 2
    return np.ones_like(e)


def diagonal(sigmas: np.ndarray | list[float]) -> gtsam.noiseModel.Diagonal:
    """Diagonal Gaussian from standard deviations (units of the variable's tangent space)."""
    return gtsam.noiseModel.Diagonal.Sigmas(np.asarray(sigmas, dtype=np.float64))


def pose_sigmas(rot: tuple[float, float, float], trans: tuple[float, float, float]) -> np.ndarray:
    """Pose3 tangent sigmas in GTSAM order: rotation (rad) then translation (m)."""
    return np.array([*rot, *trans], dtype=np.float64)


def gaussian_covariances(cov: np.ndarray) -> np.ndarray:
    """Covariance matrices (..., n, n) as a full Gaussian takes them: symmetrised and
    floored on the diagonal (1e-12, in the variable's squared units)."""
    c = 0.5 * (cov + np.swapaxes(cov, -1, -2))
    return c + np.eye(cov.shape[-1]) * 1e-12
