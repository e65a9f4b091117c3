# SPDX-License-Identifier: BSD-3-Clause
"""The consider covariance of the Kalman baselines (`uwbfuse.filters.consider`)."""

from __future__ import annotations

import numpy as np

from uwbfuse.filters.consider import ConsiderCovariance


def test_consider_covariance_adds_an_unmodelled_constant_bias() -> None:
    """test that a filter averaging n readings of a constant, blind to a bias b shared by
    them, is reported with its own variance plus the bias's: P + var(b), in closed form"""
    p0, r, var_b, n = 100.0, 0.04, 0.01, 400
    p = np.array([[p0]])
    cc = ConsiderCovariance(p, np.array([var_b]))
    h = np.array([[1.0]])
    for _ in range(n):
        k = p @ h.T / (h @ p @ h.T + r)
        p = (np.eye(1) - k @ h) @ p
        cc.update(k, h, np.array([r]), np.array([0]))
    own = 1.0 / (1.0 / p0 + n / r)  # the filter's posterior variance
    gain_sum = n * own / r          # the weight the estimate gives the readings in all
    np.testing.assert_allclose(p[0, 0], own, rtol=1e-9)
    np.testing.assert_allclose(cc.state[0, 0], own + gain_sum**2 * var_b, rtol=1e-9)
    # the bias's variance itself is not touched by updates that do not estimate it
    np.testing.assert_allclose(cc.p[1, 1], var_b)


def test_consider_covariance_propagates_and_forgets_a_decaying_excess() -> None:
    """test that a Gauss-Markov excess (factor f, noise (1 - f^2) v) keeps its stationary
    variance and its correlation with the state decays by f per step"""
    cc = ConsiderCovariance(np.array([[1.0]]), np.array([0.5]))
    cc.p[0, 1] = cc.p[1, 0] = 0.3
    f = np.array([0.9])
    cc.propagate(np.eye(1), np.zeros((1, 1)), f, (1.0 - f * f) * 0.5)
    np.testing.assert_allclose(cc.p[1, 1], 0.5)
    np.testing.assert_allclose(cc.p[0, 1], 0.27)
    np.testing.assert_allclose(cc.state, [[1.0]])
