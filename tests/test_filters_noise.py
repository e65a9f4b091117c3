# SPDX-License-Identifier: BSD-3-Clause
"""The filters' measurement noise from the log (`uwbfuse.filters.adaptive_noise`) and the
EM fit of the NLOS model it uses (`nlos.fit_nlos_mixture`)."""

from __future__ import annotations

import numpy as np

from uwbfuse.config import Config
from uwbfuse.filters.adaptive_noise import (
    InnovationVariance,
    RangeNoise,
    scalar_update,
    sequential_ranges,
)
from uwbfuse.filters.models import joseph_update
from uwbfuse.nlos import NlosParams, fit_nlos_mixture


def test_em_recovers_the_mixture_from_residuals() -> None:
    """test that EM on residuals with prediction variance finds LOS std, NLOS share and mean"""
    rng = np.random.default_rng(0)
    n = 6000
    nlos = rng.random(n) < 0.4
    s = np.full(n, 0.02**2)  # prediction variance of each residual, m^2
    r = rng.normal(0.0, 0.05, n) + rng.normal(0.0, 0.02, n)
    r[nlos] += rng.normal(0.35, 0.12, nlos.sum())
    prior = NlosParams(0.026, 0.114, 0.145, 0.2)
    fit = fit_nlos_mixture(r, s, prior, n0=200.0, iterations=30)
    assert abs(fit.los_std - 0.05) < 0.008
    assert abs(fit.nlos_prior - 0.4) < 0.05
    assert abs(fit.nlos_mean - 0.35) < 0.05
    assert abs(fit.nlos_std - 0.12) < 0.04


def test_range_noise_weighs_nlos_and_gates_gross_outliers() -> None:
    """test that a long range is corrected and widened, a gross one rejected both ways, and a
    large innovation accepted when the prediction is that uncertain (no lock-out)"""
    noise = RangeNoise(Config(), 3)
    a = np.array([0, 1, 2, 0])
    y = np.array([0.0, 0.3, -2.0, 2.0])
    s = np.array([1e-4, 1e-4, 1e-4, 4.0])
    yc, var, ok, nis = noise.weigh(a, y, s)
    assert ok.tolist() == [True, True, False, True]
    assert abs(yc[0]) < 0.01 and var[0] < 0.2 * var[1]
    assert yc[1] < 0.3 and var[1] > 10 * noise.model.los_std**2
    assert nis[2] > noise.gate


def test_range_noise_learns_the_los_spread_from_innovations() -> None:
    """test that the refits move the LOS std from the [wls] prior to the innovations' spread"""
    noise = RangeNoise(Config(), 4)
    rng = np.random.default_rng(1)
    for _ in range(30):
        a = rng.integers(0, 4, 100)
        y = rng.normal(0.0, 0.06, 100)
        s = np.full(100, 1e-4)
        _, _, ok, _ = noise.weigh(a, y, s)
        noise.accept(a, y, s, ok, np.full(100, 3.0) + y)
    assert noise.refits >= 10
    # all-LOS data: the LOS std moves from 0.026 to the data's 0.059 m; the prior (worth 200
    # ranges) keeps some mass in a weak NLOS component (measured 0.050 m, 18 %)
    m = noise.model
    assert 0.045 < m.los_std < 0.065
    assert m.nlos_prior < 0.25
    # the ranges fit the predictions without a scale: the common scale stays at 1
    assert abs(noise.scale - 1.0) < 0.01


def test_sequential_scalar_updates_equal_the_stacked_update() -> None:
    """test that scalar updates one after another give the stacked Joseph update's P and dx"""
    rng = np.random.default_rng(2)
    a = rng.normal(size=(6, 6))
    p = a @ a.T + np.eye(6)
    h = rng.normal(size=(4, 6))
    y = rng.normal(size=4)
    r = np.array([0.1, 0.2, 0.3, 0.4])
    dx_b, p_b, _, _ = joseph_update(p, h, r, y)
    pp, dx = p.copy(), np.zeros(6)
    for i in range(4):
        pp, dx, _ = scalar_update(pp, dx, h[i], float(y[i] - h[i] @ dx), float(r[i]))
    np.testing.assert_allclose(dx, dx_b, atol=1e-10)
    np.testing.assert_allclose(pp, p_b, atol=1e-10)
    # the robust sequence with LOS-looking innovations changes P and records every range
    noise = RangeNoise(Config(), 2)
    p2, _, used, _ = sequential_ranges(noise, p, np.zeros(6), h[:2] * 0.01,
                                     np.array([0.001, -0.002]), np.array([0, 1]),
                                     np.array([3.0, 4.0]))
    assert used.all() and np.all(np.diag(p2) <= np.diag(p) + 1e-12)
    assert noise._n == 2


def test_innovation_variance_matches_the_innovations() -> None:
    """test that covariance matching moves r from the prior to E[y^2] - s (r >> s here; each
    row counts at its positive part, biased high where s dominates)"""
    est = InnovationVariance(np.array([0.05**2, 0.02**2]))
    rng = np.random.default_rng(3)
    s = np.full((5000, 2), 0.01**2)
    y = rng.normal(0.0, 1.0, (5000, 2)) * np.sqrt(np.array([0.2**2, 0.05**2]) + s)
    for k in range(0, 5000, 5):
        est.update(y[k : k + 5], s[k : k + 5])
    # the prior (200 rows) against the data's memory (2000 rows)
    expect = (2000 * np.array([0.2**2, 0.05**2]) + 200 * est.prior) / 2200
    np.testing.assert_allclose(est.r, expect, rtol=0.15)


def test_range_scale_follows_the_innovations() -> None:
    """test that ranges reading 3 % long under the current scale move the scale to 1.03"""
    noise = RangeNoise(Config(), 4)
    rng = np.random.default_rng(4)
    for _ in range(20):
        a = rng.integers(0, 4, 100)
        d = rng.uniform(1.0, 8.0, 100)  # predicted (true) distances, m
        meas = 1.03 * d  # ranges as read, m
        z = meas / noise.scale  # as the filter applies the current scale
        y = z - d + rng.normal(0.0, 0.02, 100)
        s = np.full(100, 1e-4)
        _, _, ok, _ = noise.weigh(a, y, s)
        noise.accept(a, y, s, ok, z)
    assert abs(noise.scale - 1.03) < 0.005


def test_scalar_weighing_matches_the_array_form_bit_for_bit() -> None:
    """test that `weigh_one`/`accept_one` (the EKF's sequential path) give exactly the
    corrected innovations, variances, gate decisions and, through refits, the same fitted
    model as `weigh`/`accept` on the same ranges"""
    rng = np.random.default_rng(4)
    arr, one = RangeNoise(Config(), 4), RangeNoise(Config(), 4)
    for _ in range(900):
        a = int(rng.integers(0, 4))
        y = float(rng.normal(0.05, 0.2)) + (2.5 if rng.random() < 0.02 else 0.0)
        s = float(rng.uniform(1e-5, 1e-2))
        z = 4.0 + y
        yc, var, ok, nis = arr.weigh(np.array([a]), np.array([y]), np.array([s]))
        arr.accept(np.array([a]), np.array([y]), np.array([s]), ok, np.array([z]))
        yc1, var1, ok1, nis1, p1 = one.weigh_one(a, y, s)
        if ok1:
            one.accept_one(a, y, s, p1, z)
        assert (yc1, var1, ok1, nis1) == (yc[0], var[0], bool(ok[0]), nis[0])
    assert arr.refits >= 3 and one.report() == arr.report()
    assert np.array_equal(arr.p_last, one.p_last)


def test_bias_propagation_equals_the_full_transition() -> None:
    """test that propagating the error state with Gauss-Markov range biases block-wise
    (`models.propagate_with_biases`) equals Phi_full P Phi_full^T + Q_full with the biases'
    diagonal decay and noise in the full transition"""
    from uwbfuse.filters.models import propagate_with_biases

    rng = np.random.default_rng(5)
    a = rng.normal(size=(7, 7))
    p = a @ a.T
    phi = np.eye(4) + 0.1 * rng.normal(size=(4, 4))
    b = rng.normal(size=(4, 4))
    q = 0.01 * b @ b.T
    f, qb = np.array([0.9, 0.95, 0.99]), np.array([0.01, 0.02, 0.03])
    full_phi = np.zeros((7, 7))
    full_phi[:4, :4] = phi
    full_phi[4:, 4:] = np.diag(f)
    full_q = np.zeros((7, 7))
    full_q[:4, :4] = q
    full_q[4:, 4:] = np.diag(qb)
    np.testing.assert_allclose(propagate_with_biases(p, 4, phi, q, f, qb),
                               full_phi @ p @ full_phi.T + full_q, atol=1e-12)


def test_an_nlos_anchor_gets_a_range_bias_and_a_los_one_none() -> None:
    """test that the EKF's range-bias noise follows each anchor's NLOS probability: an
    anchor read 0.4 m long for seconds gets a bias state near its excess while the others
    stay near zero, and the bias is reported per anchor id"""
    from uwbfuse.estimator import Method
    from uwbfuse.pipeline import estimate
    from uwbfuse.sim.simulator import simulate

    log = simulate("room", duration_s=30.0, seed=1)
    r = log.ranges
    a0 = r.anchor == 0
    late = r.t_ns > r.t_ns[0] + 15_000_000_000
    r.range[a0 & late] += 0.4
    rep = estimate(log, Method.EKF, Config()).report
    bias = rep["range_bias"]
    ids = list(bias)
    assert bias[ids[0]] > 0.15
    assert all(abs(bias[i]) < 0.1 for i in ids[1:])


def test_noise_bank_raises_the_process_noise_for_a_noisier_imu() -> None:
    """test that the process-noise bank (`filters.noise_bank`) keeps the configured IMU
    inflation on a log whose IMU follows the [imu] figures and leads with a larger one when
    the log's IMU is 10x noisier than the inflated figures (UWB, IMU and wheels)"""
    from uwbfuse.estimator import Method
    from uwbfuse.pipeline import estimate
    from uwbfuse.sim.simulator import simulate

    chosen = []
    for factor in (1.0, 300.0):
        log = simulate("room", 30.0, 0, accel_noise_density=4.0e-3 * factor,
                       gyro_noise_density=3.0e-4 * factor)
        res = estimate(log, Method.EKF, Config())
        chosen.append(res.report["imu_noise_inflation"])
    assert chosen[0] == Config().filter.imu_noise_inflation
    assert chosen[1] > chosen[0]
