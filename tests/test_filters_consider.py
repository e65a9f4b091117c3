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


def test_linearised_update_is_the_kalman_update_of_a_linear_measurement() -> None:
    """test that the sigma-point form (`update_linearised`: gain and rows from the joint
    covariance of state and predicted measurements) applies, for measurements linear in
    the state, the very update the linear filter's gain and rows give: two ranges of
    anchors 1 and 0 and one row without an anchor, the second range not used"""
    rng = np.random.default_rng(4)
    n, m = 4, 3
    a = rng.normal(size=(n, n))
    p = a @ a.T + np.eye(n)
    h = rng.normal(size=(m, n))
    c = np.block([[p, p @ h.T], [h @ p, h @ p @ h.T]])  # (x, h x): exact sigma points
    var = np.array([0.04, 0.09, 0.01])
    rows = np.array([0, 2])
    anchors = np.array([1, -1])
    excess = np.array([0.02, 0.05])
    sigma = ConsiderCovariance(p, excess)
    sigma.update_linearised(c, rows, var[rows], anchors)
    hr = h[rows]
    k = p @ hr.T @ np.linalg.inv(hr @ p @ hr.T + np.diag(var[rows]))
    linear = ConsiderCovariance(p, excess)
    linear.update(k, hr, var[rows], anchors)
    np.testing.assert_allclose(sigma.p, linear.p, rtol=1e-9, atol=1e-12)
    # the filter's own posterior where the excesses are zero, and the excess read
    np.testing.assert_allclose(linear.state, (np.eye(n) - k @ hr) @ p
                               + k[:, :1] @ k[:, :1].T * excess[1], rtol=1e-9, atol=1e-12)
