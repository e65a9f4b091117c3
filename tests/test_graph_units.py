# SPDX-License-Identifier: BSD-3-Clause
"""Unit tests of the graph building blocks: wheel track, noise models, NLOS chain, Plaza."""

from __future__ import annotations

import math

import numpy as np
import pytest

from uwbfuse.config import RobustKernel, WheelConfig
from uwbfuse.nlos import (
    NlosModel,
    _smooth_input_arrays,
    hmm_filter,
    hmm_filter_by_anchor,
    hmm_smooth,
    hmm_smooth_by_anchor,
    jump_log_likelihoods,
    residual_jumps,
    residual_jumps_by_anchor,
    switch_probabilities,
)

gtsam = pytest.importorskip("gtsam")

from uwbfuse.graph.noise import robust_estimator, robust_weight  # noqa: E402
from uwbfuse.graph.uwb import los_subset_search  # noqa: E402
from uwbfuse.graph.wheel import (  # noqa: E402
    WheelTrack,
    between_factor,
    planar_covariance6,
    planar_gaussian6,
)

NS = 1_000_000_000


def test_wheel_track_integrates_a_circle_exactly():
    """Test that constant (v, omega) samples give the exact arc, between any two times."""
    v, w = 0.5, 0.25
    t = np.arange(1, 401) * (NS // 50)  # 8 s at 50 Hz
    track = WheelTrack()
    track.add(t[:150], np.full(150, v), np.full(150, w))
    track.add(t[150:], np.full(250, v), np.full(250, w))
    ta, tb = int(t[10]), int(t[10]) + 3 * NS + 7_000_000  # tb between samples
    d = track.between(ta, tb)
    dt = (tb - ta) / NS
    r = v / w
    np.testing.assert_allclose(d, [r * math.sin(w * dt), r * (1 - math.cos(w * dt)), w * dt],
                               atol=1e-9)


def test_wheel_covariance_grows_and_factor_is_native():
    """Test that the propagated covariance grows with time; the factor is BetweenFactorPose3."""
    t = np.arange(1, 201) * (NS // 50)
    track = WheelTrack()
    track.add(t, np.full(200, 0.5), np.full(200, 0.1))
    cfg = WheelConfig()
    c1 = track.covariance(int(t[0]), int(t[0]) + NS, cfg)
    c2 = track.covariance(int(t[0]), int(t[0]) + 2 * NS, cfg)
    assert np.all(np.diag(c2) > np.diag(c1))
    assert np.all(np.linalg.eigvalsh(c1) > 0)
    f = between_factor(1, 2, track.between(int(t[0]), int(t[0]) + NS), c1, (0.01, 0.01, 0.01))
    assert isinstance(f, gtsam.BetweenFactorPose3)


def test_wheel_factors_built_at_once_carry_each_interval_covariance():
    """Test that `between_factors` (every wheel factor of a graph at once) gives each factor
    the Pose3 covariance laid out by hand (rx, ry, rz, tx, ty, tz: x, y, theta into tx,
    ty, rz; roll, pitch, z from the out-of-plane sigmas; the 1e-6 floor), and the Huber
    kernel when asked."""
    from uwbfuse.graph.keys import X
    from uwbfuse.graph.wheel import between_factors

    rng = np.random.default_rng(5)
    a = rng.standard_normal((4, 3, 3))
    cov = a @ a.transpose(0, 2, 1) * 1e-3
    delta = rng.standard_normal((4, 3))
    oop = (0.01, 0.02, 0.03)
    factors = between_factors([X(k) for k in range(4)], [X(k + 1) for k in range(4)],
                              delta, cov, oop, robust_k=1.345)
    assert len(factors) == 4
    for k, f in enumerate(factors):
        want = np.diag([oop[0] ** 2, oop[1] ** 2, 1e-6, 1e-6, 1e-6, oop[2] ** 2])
        ix = [3, 4, 2]
        want[np.ix_(ix, ix)] += cov[k]
        want += np.eye(6) * 1e-12  # the Gaussian's diagonal floor
        noise = f.noiseModel()
        assert isinstance(noise, gtsam.noiseModel.Robust)
        np.testing.assert_allclose(noise.noise().covariance(), want, rtol=1e-9, atol=1e-15)
        assert f.keys() == [X(k), X(k + 1)]
        m = f.measured()
        np.testing.assert_allclose([m.x(), m.y(), m.rotation().yaw()], delta[k], atol=1e-12)
    plain = between_factors([X(0)], [X(1)], delta[:1], cov[:1], oop)[0]
    assert not isinstance(plain.noiseModel(), gtsam.noiseModel.Robust)


def test_wheel_covariance_matches_monte_carlo():
    """Test the propagated (x, y, theta) covariance of a turning interval against 20,000
    noisy re-integrations of its pieces (forward, lateral, yaw noise per piece)."""
    from uwbfuse.graph.wheel import _arcs, se2_compose

    t = np.arange(1, 101) * (NS // 50)
    track = WheelTrack()
    rng = np.random.default_rng(3)
    track.add(t, 1.0 + 0.3 * rng.standard_normal(100), 0.8 + 0.4 * rng.standard_normal(100))
    cfg = WheelConfig(sigma_v=0.05, sigma_lateral=0.02, sigma_omega=0.05)
    ta, tb = int(t[5]) + 3_000_000, int(t[5]) + NS + 11_000_000  # ends between samples
    cov = track.covariance(ta, tb, cfg)
    # the pieces the propagation uses: sample edges clipped to [ta, tb]
    edges = np.unique(np.clip(np.concatenate([[ta], t, [tb]]), ta, tb))
    mid = (edges[:-1] + edges[1:]) // 2
    idx = np.clip(np.searchsorted(t, mid, side="left"), 0, len(t) - 1)
    tau = np.diff(edges) / NS
    dx, dy, dth = _arcs(track.v[idx], track.w[idx], tau)
    sig = np.array([cfg.sigma_v, cfg.sigma_lateral, cfg.sigma_omega])
    n = 20_000
    pose = np.zeros((n, 3))
    for j in range(len(tau)):
        step = np.array([dx[j], dy[j], dth[j]]) + rng.standard_normal((n, 3)) * sig * tau[j]
        pose = se2_compose(pose, step)
    mc = np.cov(pose.T)
    np.testing.assert_allclose(np.diag(cov), np.diag(mc), rtol=0.05)
    np.testing.assert_allclose(cov[0, 1], mc[0, 1], atol=0.05 * np.sqrt(mc[0, 0] * mc[1, 1]))


def test_wheel_between_and_covariance_over_arrays_equal_each_pair():
    """Test that `between` and `covariance` over arrays of pairs (batch's whole track at
    once) give exactly each pair's own: intervals of no, one and many pieces, starting on a
    sample, empty (t_b <= t_a) and past the track's ends."""
    rng = np.random.default_rng(5)
    t = np.cumsum(rng.integers(1, 40_000_000, 300)) + NS
    track = WheelTrack()
    v, w = rng.normal(1.0, 0.5, 300), rng.normal(0.0, 0.5, 300)
    w[::7] = 0.0
    track.add(t[:100], v[:100], w[:100])
    track.add(t[100:], v[100:], w[100:])
    ta = rng.integers(int(t[0]) - NS, int(t[-1]) + NS, 400)
    ta[:40] = t[rng.integers(0, 300, 40)]
    tb = ta + rng.integers(-50_000_000, 400_000_000, 400)
    tb[40:50] = ta[40:50]
    cfg = WheelConfig()
    cov = track.covariance(ta, tb, cfg)
    delta = track.between(ta, tb)
    for j in range(len(ta)):
        assert np.array_equal(cov[j], track.covariance(int(ta[j]), int(tb[j]), cfg))
        assert np.array_equal(delta[j], track.between(int(ta[j]), int(tb[j])))


@pytest.mark.parametrize("kernel", [k for k in RobustKernel if k is not RobustKernel.NONE])
def test_robust_weight_matches_gtsam(kernel):
    """Test that the vectorised kernel weights equal GTSAM's m-estimator weights."""
    est = robust_estimator(kernel, 1.345)
    e = np.array([0.1, 0.9, 1.5, 3.0, 8.0])
    ours = robust_weight(kernel, 1.345, e)
    theirs = np.array([est.weight(float(x)) for x in e])
    np.testing.assert_allclose(ours, theirs, rtol=1e-9, atol=1e-12)


def test_nlos_chain_detects_a_persistent_positive_bias():
    """Test that ranges reading 0.3 m long for a while are classified NLOS, others LOS."""
    m = NlosModel(0.05, 0.07, 0.3, 0.13, 5.0, 1.0, 0.3, 0.05)
    rng = np.random.default_rng(0)
    r = rng.normal(0.0, 0.05, 200)
    r[60:120] += 0.3
    ll_l, ll_n = m.log_likelihoods(r, r - 0.3, 0.03**2)
    g_f, _, _ = hmm_filter(ll_l, ll_n, m.p_switch, m.p_nlos, m.p_nlos)
    g_s = hmm_smooth(ll_l, ll_n, m.p_switch, m.p_nlos)
    truth = np.zeros(200, bool)
    truth[60:120] = True
    assert np.mean((g_s > 0.5) == truth) > 0.97
    assert np.mean((g_f > 0.5) == truth) > 0.9
    assert np.mean((g_s > 0.5) == truth) >= np.mean((g_f > 0.5) == truth)


def test_residual_jumps_classify_where_the_level_cannot():
    """Test that an NLOS onset and end are found from residual jumps when the pose is off.

    The predicted pose is 0.6 m off along the line of sight (every residual reads 0.6 m
    short), beyond what either hypothesis explains, so the residual level says nothing;
    the jumps of the residual between consecutive ranges (+0.3 m at the onset, -0.3 m at
    the end) do not depend on that offset.
    """
    m = NlosModel(0.05, 0.07, 0.3, 0.13, 5.0, 1.0, 0.3, 0.05)
    rng = np.random.default_rng(1)
    excess = np.zeros(150)
    excess[50:100] = 0.3
    noise = np.where(excess > 0, 0.07, 0.05)  # the model's fast NLOS and LOS noise
    r = -0.6 + excess + rng.normal(0.0, 1.0, 150) * noise
    ll_l, ll_n = m.log_likelihoods(r, r - 0.3, 0.03**2)
    truth = excess > 0
    g_level, _, _ = hmm_filter(ll_l, ll_n, m.p_switch, m.p_nlos, 0.0)
    delta = np.concatenate([[np.nan], np.diff(r)])
    jumps = jump_log_likelihoods(delta, np.full(150, 0.3), m)
    g_jump, _, _ = hmm_filter(ll_l, ll_n, m.p_switch, m.p_nlos, 0.0, jumps)
    assert np.mean((g_jump > 0.5) == truth) > 0.85  # measured 0.91 (level alone 0.67)
    assert np.mean((g_level > 0.5) == truth) < 0.7  # the level alone misses the NLOS stretch
    # without a usable previous range (NaN) the jump term is neutral
    np.testing.assert_array_equal(jump_log_likelihoods(np.array([np.nan]), np.ones(1), m), 0)


def test_los_subset_search_finds_the_los_anchors_and_the_track_offset():
    """Test the discrete LOS/NLOS search: 4 anchors, 0 and 1 in LOS, 2 and 3 reading 0.3 m
    long; the track is 0.18 m off and only anchor 0 is currently taken as LOS."""
    m = NlosModel(0.05, 0.07, 0.3, 0.13, 5.0, 1.0, 0.3, 0.05)
    rng = np.random.default_rng(0)
    anchors = np.array([[0.0, 0.0], [20.0, 0.0], [20.0, 10.0], [0.0, 10.0]])
    n = 200
    t = np.linspace(0.0, 4.5, n)
    p_true = np.column_stack([5.0 + 0.5 * t, np.full(n, 5.0)])
    a = np.arange(n) % 4
    excess = np.where(a >= 2, 0.3 + rng.normal(0, 0.07, n), rng.normal(0, 0.05, n))
    shift = np.array([0.15, -0.1])
    p_est = p_true + shift
    z = np.linalg.norm(p_true - anchors[a], axis=1) + excess
    dist = np.linalg.norm(p_est - anchors[a], axis=1)
    u = (p_est - anchors[a]) / dist[:, None]
    hyp = los_subset_search(a, z - dist, u, np.where(a == 0, 0.0, 1.0), m)
    assert hyp is not None
    np.testing.assert_array_equal(hyp.los, [True, True, False, False])
    np.testing.assert_array_equal(hyp.current, [True, False, False, False])
    np.testing.assert_allclose(hyp.delta, -shift, atol=0.03)
    np.testing.assert_allclose(hyp.excess[2:], 0.3, atol=0.03)
    assert hyp.gain > 10.0
    # with the track right and the classification right, nothing is better
    dist = np.linalg.norm(p_true - anchors[a], axis=1)
    u = (p_true - anchors[a]) / dist[:, None]
    hyp = los_subset_search(a, z - dist, u, np.where(a >= 2, 1.0, 0.0), m)
    assert hyp is not None and hyp.gain < 1.0
    # without the shift's moment: the same hypothesis, bit for bit, and a zero moment
    with_m = los_subset_search(a, z - dist, u, np.where(a == 0, 0.0, 1.0), m)
    no_m = los_subset_search(a, z - dist, u, np.where(a == 0, 0.0, 1.0), m, moment=False)
    assert with_m is not None and no_m is not None
    for f in ("anchors", "los", "current", "delta", "excess"):
        np.testing.assert_array_equal(getattr(no_m, f), getattr(with_m, f))
    assert no_m.gain == with_m.gain
    assert np.any(with_m.shift_moment != 0.0)
    np.testing.assert_array_equal(no_m.shift_moment, np.zeros((2, 2)))


def test_plaza_converter_reads_the_gtsam_data():
    """Test that a Plaza .mat file becomes a SensorLog with wheels, ranges, anchors, GT."""
    from uwbfuse.errors import LogReadError
    from uwbfuse.graph.plaza import plaza_log, plaza_path

    try:
        path = plaza_path("Plaza2")
    except LogReadError as exc:
        pytest.skip(str(exc))
    log = plaza_log(path)
    assert len(log.anchors) == 4
    assert len(log.ranges) > 1500 and len(log.wheel) > 4000
    assert np.all(np.diff(log.ranges.t_ns) >= 0)
    assert not log.ground_truth.has_orientation
    speed = np.abs(log.wheel.v)  # a golf cart: a few m/s
    assert 0.5 < np.median(speed) < 10.0


def test_residual_jumps_by_anchor_matches_one_call_per_anchor():
    """Test the all-anchor residual jumps against `residual_jumps` per anchor, with and
    without each anchor's previous range leading its chain."""
    rng = np.random.default_rng(5)
    n = 60
    t = np.sort(rng.integers(0, 3 * NS, n))
    a = rng.integers(0, 4, n)
    r = rng.normal(0.0, 0.3, n)
    lead_t = np.array([-NS, t[0] - 50_000_000, -10 * NS, t[0] - 1])
    lead_r = np.array([0.1, -0.2, 0.3, 0.0])
    got = residual_jumps_by_anchor(t, a, r)
    led = residual_jumps_by_anchor(t, a, r, lead_t, lead_r)
    for anc in range(4):
        sel = np.flatnonzero(a == anc)
        np.testing.assert_array_equal(got[sel], residual_jumps(t[sel], r[sel]))
        want = residual_jumps(np.concatenate([[lead_t[anc]], t[sel]]),
                              np.concatenate([[lead_r[anc]], r[sel]]))[1:]
        np.testing.assert_array_equal(led[sel], want)


def test_nlos_key_is_gtsam_symbol():
    """Test that `nlos_key`, formed without calling GTSAM, is its Symbol key."""
    from uwbfuse.graph.keys import nlos_key

    for anchor, segment in ((0, 0), (3, 1), (4095, 7), (17, 10**6)):
        assert nlos_key(anchor, segment) == gtsam.symbol("e", segment * 4096 + anchor)


def test_one_wheel_covariance_equals_the_array_pass():
    """Test `planar_gaussian6` (one keyframe's wheel factor covariance in Python floats)
    against `gaussian_covariances(planar_covariance6(...))`, bit for bit (signed zeros
    too)."""
    from uwbfuse.graph.noise import gaussian_covariances

    rng = np.random.default_rng(8)
    for i in range(500):
        a = rng.normal(size=(3, 3)) * 10.0 ** rng.integers(-6, 0)
        c = a @ a.T if i % 2 else a  # symmetric, and not
        if i % 5 == 0:
            c[0, 1] = c[1, 0] = -0.0
            c[2, 0] = 0.0
        oop = tuple(rng.uniform(0.001, 0.3, 3).tolist())
        np.testing.assert_array_equal(
            planar_gaussian6(c, oop).view(np.int64),
            gaussian_covariances(planar_covariance6(c, oop)).view(np.int64))


def test_residual_jumps_of_a_few_ranges_equal_the_vectorised_pass():
    """Test the few-range (Python) path of `residual_jumps_by_anchor` against its numpy
    pass, bit for bit: one keyframe's ranges, ties in time, gaps, outliers, leads."""
    rng = np.random.default_rng(11)
    for n in range(1, 17):
        t = np.sort(rng.integers(0, NS, n))
        t[n // 2:] = t[n // 2]  # ties
        a = rng.integers(0, 4, n)
        r = rng.normal(0.0, 0.6, n)  # some beyond JUMP_MAX_M
        lead_t = t[0] - rng.integers(0, 2 * NS, 4)
        lead_r = rng.normal(0.0, 0.3, 4)
        big = np.concatenate([t, t[-1] + 10 * NS + np.arange(20)])  # > the few: numpy
        for lt, lr in ((None, None), (lead_t, lead_r)):
            few = residual_jumps_by_anchor(t, a, r, lt, lr)
            ref = residual_jumps_by_anchor(big, np.concatenate([a, np.full(20, 9)]),
                                           np.concatenate([r, np.zeros(20)]), None if lt is None
                                           else np.append(lt, np.zeros(6)), None if lr is None
                                           else np.append(lr, np.zeros(6)))[:n]
            np.testing.assert_array_equal(few, ref)


def test_hmm_over_several_anchors_equals_one_call_per_anchor():
    """Test `hmm_filter_by_anchor` and `hmm_smooth_by_anchor` against `hmm_filter` and
    `hmm_smooth` anchor by anchor, bit for bit (with jump evidence), and with one switching
    probability per range, all equal, against the scalar one."""
    rng = np.random.default_rng(3)
    m = NlosModel(0.05, 0.07, 0.3, 0.13, 5.0, 1.0, 0.3, 0.05)
    n = 50
    a = rng.integers(0, 4, n)
    ll_l, ll_n = rng.normal(-1.0, 2.0, n), rng.normal(-1.0, 2.0, n)
    jl = jump_log_likelihoods(rng.normal(0.0, 0.2, n), np.full(n, 0.3), m)
    p_last = np.array([0.1, 0.5, 0.9, 0.3])
    p_each = p_last.copy()
    g, prior = hmm_filter_by_anchor(a, ll_l, ll_n, m.p_switch, m.p_nlos, p_last, jl)
    p0 = rng.uniform(0.0, 1.0, n)
    gs = hmm_smooth_by_anchor(a, ll_l, ll_n, m.p_switch, m.p_nlos, jl, p0)
    for anc in range(4):
        sel = np.flatnonzero(a == anc)
        g1, last, prior1 = hmm_filter(ll_l[sel], ll_n[sel], m.p_switch, m.p_nlos,
                                      p_each[anc], jl[sel])
        np.testing.assert_array_equal(g[sel], g1)
        np.testing.assert_array_equal(prior[sel], prior1)
        assert p_last[anc] == last
        np.testing.assert_array_equal(
            gs[sel], hmm_smooth(ll_l[sel], ll_n[sel], m.p_switch, m.p_nlos, jl[sel],
                                float(p0[sel[0]])))
    each = np.full(n, m.p_switch)
    g2, prior2 = hmm_filter_by_anchor(a, ll_l, ll_n, each, m.p_nlos, p_each.copy(), jl)
    np.testing.assert_array_equal(g2, g)
    np.testing.assert_array_equal(prior2, prior)
    np.testing.assert_array_equal(
        hmm_smooth_by_anchor(a, ll_l, ll_n, each, m.p_nlos, jl, p0), gs)


def test_smooth_inputs_entry_by_entry_equal_the_transition_matrix():
    """Test that `_smooth_input_arrays`' transition entries, built one by one, equal the
    (N,2,2) transition matrix times the scaled jump evidence bit for bit (one switching
    probability or one per range; with and without the jump evidence)."""
    rng = np.random.default_rng(12)
    m = NlosModel(0.05, 0.07, 0.3, 0.13, 5.0, 1.0, 0.3, 0.05)
    n = 300
    ll_l, ll_n = rng.normal(-1.0, 2.0, n), rng.normal(-1.0, 2.0, n)
    jl = jump_log_likelihoods(rng.normal(0.0, 0.2, n), np.full(n, 0.3), m)
    for p_sw in (rng.uniform(0.0, 0.2, n), 0.05):
        q = np.asarray(p_sw, np.float64)[..., None, None]
        a = np.concatenate(
            [np.concatenate([1.0 - q * m.p_nlos, q * m.p_nlos], axis=-1),
             np.concatenate([q * (1.0 - m.p_nlos), 1.0 - q * (1.0 - m.p_nlos)], axis=-1)],
            axis=-2)
        for jump in (jl, None):
            ref = (np.broadcast_to(a, (n, 2, 2)) if jump is None
                   else a * np.exp(jump - jump.max(axis=(1, 2), keepdims=True)))
            e0, e1, tr = _smooth_input_arrays(ll_l, ll_n, p_sw, m.p_nlos, jump)
            mx = np.maximum(ll_l, ll_n)
            np.testing.assert_array_equal(e0, np.exp(ll_l - mx))
            np.testing.assert_array_equal(e1, np.exp(ll_n - mx))
            for x, (r, c) in zip(tr, ((0, 0), (0, 1), (1, 0), (1, 1)), strict=True):
                np.testing.assert_array_equal(np.broadcast_to(x, (n,)), ref[:, r, c])


def test_hmm_smooth_by_anchor_over_a_window_equals_one_call_per_anchor():
    """Test that `hmm_smooth_by_anchor`'s chains as slices of the anchor-sorted rows give
    `hmm_smooth` anchor by anchor bit for bit over a review window's worth of ranges (with
    and without jump evidence and first priors; anchor labels unsorted and gapped), and
    nothing for no ranges."""
    rng = np.random.default_rng(11)
    m = NlosModel(0.05, 0.07, 0.3, 0.13, 5.0, 1.0, 0.3, 0.05)
    n = 400
    a = rng.choice([7, 2, 5, 0, 11], n)
    ll_l, ll_n = rng.normal(-1.0, 2.0, n), rng.normal(-1.0, 2.0, n)
    jl = jump_log_likelihoods(rng.normal(0.0, 0.2, n), np.full(n, 0.3), m)
    p_sw = rng.uniform(0.0, 0.2, n)
    p0 = rng.uniform(0.0, 1.0, n)
    for jump, first in ((jl, p0), (None, None), (jl, None)):
        gs = hmm_smooth_by_anchor(a, ll_l, ll_n, p_sw, m.p_nlos, jump, first)
        for anc in np.unique(a).tolist():
            sel = np.flatnonzero(a == anc)
            ref = hmm_smooth(ll_l[sel], ll_n[sel], p_sw[sel], m.p_nlos,
                             None if jump is None else jump[sel],
                             None if first is None else float(first[sel[0]]))
            np.testing.assert_array_equal(gs[sel], ref)
    assert hmm_smooth_by_anchor(a[:0], ll_l[:0], ll_n[:0], m.p_switch, m.p_nlos).shape == (0,)


@pytest.mark.parametrize("few", [16, 0])  # the Python loop and the numpy path
def test_switch_probabilities_follow_each_anchors_time_between_ranges(monkeypatch, few):
    """Test that the chain's redraw probability of a range is 1 - exp(-dt / switch_time)
    with dt to its own anchor's previous range (interleaved anchors), from `last_t` for an
    anchor's first range, and 1 where the anchor has none."""
    monkeypatch.setattr("uwbfuse.nlos.FEW_SWITCH_RANGES", few)
    t = np.array([0, 100, 200, 600, 1100], np.int64) * 1_000_000  # ns
    a = np.array([0, 1, 0, 1, 0])
    p = switch_probabilities(t, a, 2.0)
    np.testing.assert_allclose(p, [1.0, 1.0, -math.expm1(-0.2 / 2.0),
                                   -math.expm1(-0.5 / 2.0), -math.expm1(-0.9 / 2.0)])
    last = np.array([-1_000_000_000, np.iinfo(np.int64).min], np.int64)
    p = switch_probabilities(t, a, 2.0, last)
    np.testing.assert_allclose(p[[0, 1]], [-math.expm1(-1.0 / 2.0), 1.0])
    # both paths bit for bit (a keyframe's few ranges take the loop, a window the sort)
    rng = np.random.default_rng(1)
    a = rng.integers(0, 4, 12)
    t = np.sort(rng.integers(0, 5_000_000_000, 12)).astype(np.int64)
    p = switch_probabilities(t, a, 2.0, np.full(4, -10**9, np.int64))
    monkeypatch.setattr("uwbfuse.nlos.FEW_SWITCH_RANGES", 16 - few)
    np.testing.assert_array_equal(
        switch_probabilities(t, a, 2.0, np.full(4, -10**9, np.int64)), p)


def test_nlos_state_persists_for_a_time_whatever_the_radio_rate():
    """Test that an anchor called NLOS, then ranging without evidence either way for 1 s,
    keeps the same P(NLOS) at 10 ranges per second as at 2: the chain forgets in time
    (p_nlos + (p0 - p_nlos) exp(-T / switch_time)), not per range."""
    m = NlosModel(0.05, 0.07, 0.3, 0.13, 5.0, 1.0, 0.3, 0.05, switch_time=2.0)
    out = []
    for rate in (10, 2):
        t = np.arange(rate + 1, dtype=np.int64) * (1_000_000_000 // rate)  # 0 .. 1 s
        a = np.zeros(len(t), np.int64)
        ll_l, ll_n = np.zeros(len(t)), np.zeros(len(t))
        ll_n[0] = 20.0  # the first range is clearly NLOS
        p = switch_probabilities(t, a, m.switch_time)
        g, _ = hmm_filter_by_anchor(a, ll_l, ll_n, p, m.p_nlos, np.array([m.p_nlos]))
        out.append(g[-1])
    g0 = 1.0 / (1.0 + (1.0 - m.p_nlos) / m.p_nlos * math.exp(-20.0))
    expected = m.p_nlos + (g0 - m.p_nlos) * math.exp(-1.0 / 2.0)
    assert out[0] == pytest.approx(expected, abs=1e-9)
    assert out[1] == pytest.approx(expected, abs=1e-9)


def test_excess_mean_step_weighs_nlos_residuals_and_stays_within_zero_and_the_prior():
    """Test the online NLOS excess mean: the responsibility-weighted mean of the residuals
    with the prior's mean as n0 ranges, gross residuals (beyond 1 m) left out, and the
    result held within [0, prior]."""
    prior = NlosModel(0.05, 0.07, 0.3, 0.13, 5.0, 1.0, 0.3, 0.05)
    m = NlosModel(0.05, 0.07, 0.3, 0.13, 5.0, 1.0, 0.3, 0.05)
    r = np.array([0.1, 0.1, 0.1, 0.1, 5.0, -0.02])
    g = np.array([1.0, 1.0, 1.0, 1.0, 1.0, 0.0])  # the 5 m one is gross, the last LOS
    m.excess_mean_step(r, g, prior, n0=4.0)
    assert m.mu_nlos == pytest.approx((4 * 0.1 + 4 * 0.3) / 8)
    m.excess_mean_step(np.full(10, -0.2), np.ones(10), prior, n0=1.0)
    assert m.mu_nlos == 0.0  # NLOS only lengthens a range
    m.excess_mean_step(np.full(10, 0.8), np.ones(10), prior, n0=1.0)
    assert m.mu_nlos == prior.mu_nlos  # the configured mean is an upper bound


def test_wheel_scale_refit_recovers_the_odometry_scale_and_rebuilds_the_factors():
    """Test that `offline._WheelScale` fits (v, omega) scales of 1.03 and 0.98 from a track
    whose odometry read 1/1.03 of the distance and 1/0.98 of the turn, and that `apply`
    replaces the wheel factors at their indices with the scaled deltas."""
    from uwbfuse.graph.builder import WheelRecords
    from uwbfuse.graph.keys import X
    from uwbfuse.graph.offline import _WheelScale
    from uwbfuse.graph.wheel import se2_between, se2_compose

    rng = np.random.default_rng(0)
    n = 400
    step = np.column_stack([np.full(n - 1, 0.1), np.zeros(n - 1),
                            0.05 * np.sin(np.arange(n - 1) / 20.0)])  # (x, y, theta) per kf
    poses = [np.zeros(3)]
    for d in step:
        poses.append(se2_compose(poses[-1], d))
    poses = np.array(poses)
    values = gtsam.Values()
    graph = gtsam.NonlinearFactorGraph()
    cov = np.diag([1e-4, 1e-4, 1e-5])
    deltas = []
    for k in range(n):
        x, y, th = poses[k]
        values.insert(X(k), gtsam.Pose3(gtsam.Rot3.Yaw(th), np.array([x, y, 0.0])))
    for k in range(n - 1):
        true = se2_between(poses[k], poses[k + 1])
        raw = true / np.array([1.03, 1.03, 0.98]) + rng.normal(0, [1e-3, 1e-3, 1e-4])
        deltas.append(raw)
        graph.add(between_factor(X(k), X(k + 1), raw, cov, (0.01, 0.01, 0.01)))
    records = WheelRecords(k=list(range(n - 1)), delta=deltas, cov=[cov] * (n - 1),
                           index=list(range(n - 1)))
    ws = _WheelScale(records)
    ws.refit(values, n)
    assert ws.scale == pytest.approx([1.03, 0.98], abs=0.002)
    assert ws.apply([graph])
    f = graph.at(5)
    assert list(f.keys()) == [X(5), X(6)]
    assert f.error(values) < 0.5 * between_factor(
        X(5), X(6), deltas[5], cov, (0.01, 0.01, 0.01)).error(values)
    assert not ws.apply([graph])  # unchanged scales rebuild nothing


def test_imu_rotation_between_turns_the_bias_free_gyro_into_the_base_frame():
    """Test `ImuBuffer.rotation_between`: 0.7 rad/s about the IMU's z for 2 s, gyro bias
    0.1 rad/s, IMU mounted rolled 90 deg (its z along the base's -y): a 1.2 rad turn about
    the base's -y; and the attitude change composes over split intervals."""
    from uwbfuse.graph.imu import ImuBuffer

    buf = ImuBuffer()
    t = np.arange(0, 201, dtype=np.int64) * 10_000_000  # 100 Hz, 0..2 s
    gyro = np.tile([0.0, 0.0, 0.7], (len(t), 1))
    buf.add(t, gyro, np.tile([0.0, 0.0, 9.81], (len(t), 1)))
    r_bs = gtsam.Rot3.Rx(math.pi / 2).matrix()
    bias = np.array([0.0, 0.0, 0.1])
    rot = buf.rotation_between(0, int(2e9), bias, r_bs)
    expected = gtsam.Rot3.AxisAngle(np.array([0.0, -1.0, 0.0]), 1.2).matrix()
    np.testing.assert_allclose(rot, expected, atol=1e-9)
    half = buf.rotation_between(0, int(1e9), bias, r_bs)
    np.testing.assert_allclose(half @ buf.rotation_between(int(1e9), int(2e9), bias, r_bs),
                               rot, atol=1e-9)


def test_classifier_weight_follows_how_well_the_classifier_predicts_the_residuals() -> None:
    """Test that the NLOS classifier's weight in batch EM (`offline.classifier_weight`) is
    the slope of the residual responsibilities on its log-odds, within 0..1: a classifier
    calibrated to the residuals' classes keeps its log-odds (~1), one at chance on this log
    (a forest from another site) gets ~0, one that ranks them backwards 0."""
    from uwbfuse.graph.offline import classifier_weight

    rng = np.random.default_rng(3)
    nlos = rng.random(4000) < 0.3
    # the residuals' responsibilities: mostly sure, a few in between
    g = np.clip(np.where(nlos, 0.95, 0.05) + rng.normal(0.0, 0.03, nlos.size), 0.0, 1.0)
    # a calibrated classifier: log-odds of 0.8 / 0.2 around its base rate, some spread
    informative = np.where(nlos, 1.4, -1.4) + rng.normal(0.0, 0.5, nlos.size)
    w_informative = classifier_weight(g, informative)
    assert w_informative == 1.0  # its log-odds understate what the residuals show: capped
    # the same log-odds 4x overconfident: a quarter of the unscaled slope (about 2 here,
    # the residuals being surer than the classifier)
    assert 0.3 < classifier_weight(g, 4.0 * informative) < 0.8
    chance = rng.normal(0.0, 1.5, nlos.size)
    assert classifier_weight(g, chance) < 0.05
    assert classifier_weight(g, -informative) == 0.0


def test_median_ring_equals_np_median_of_the_ring():
    """Test that the sorted ring of the online robust sigma (`builder.MedianRing`) gives
    np.median of its finite values exactly, before and after it fills, with ties, NaN and
    infinite values and batches longer than the ring."""
    from uwbfuse.graph.builder import MedianRing

    rng = np.random.default_rng(17)
    size = 37
    ring, ref = MedianRing(size), np.full(size, np.nan)
    i = 0
    assert ring.median() is None
    for _ in range(400):
        x = np.abs(rng.normal(0.0, 0.2, rng.integers(0, 9 if rng.random() < 0.95 else 90)))
        x[rng.random(len(x)) < 0.05] = np.nan
        x[rng.random(len(x)) < 0.02] = np.inf
        x[rng.random(len(x)) < 0.1] = 0.125  # ties
        ring.add(x.tolist())
        for v in x:
            ref[i] = v
            i = (i + 1) % size
        seen = ref[np.isfinite(ref)]
        if len(seen):
            assert ring.median() == float(np.median(seen))


def test_imu_pieces_hold_a_rest_guess_through_a_dropout():
    """Test that an IMU sample is held for MAX_EXTRAPOLATION_S at most: beyond it, the
    pieces hold what the IMU reads with no turn and no acceleration at the given attitude
    and bias, and preintegrating them keeps the attitude and the velocity."""
    from uwbfuse.config import Extrinsics, ImuConfig
    from uwbfuse.constants import MAX_EXTRAPOLATION_S
    from uwbfuse.graph import imu

    buf = imu.ImuBuffer()
    t = np.arange(0, 1_000_000_001, 10_000_000, dtype=np.int64)  # 100 Hz for 1 s
    spin = np.tile([0.0, 0.0, 2.0], (len(t), 1))  # turning at 2 rad/s when the IMU stops
    buf.add(t, spin, np.tile([0.3, 0.0, 9.81], (len(t), 1)))
    params = imu.preintegration_params(ImuConfig(), Extrinsics())
    attitude = gtsam.Rot3.Ypr(0.4, 0.1, -0.05)
    bias = gtsam.imuBias.ConstantBias(np.array([0.02, -0.01, 0.03]), np.array([1e-3, 0, 0]))
    rest = imu.rest_reading(params, attitude, bias)
    gy, ac, dt = buf.pieces(1_000_000_000, 3_000_000_000, lambda: rest)
    assert math.isclose(dt.sum(), 2.0)
    held = np.cumsum(dt) <= MAX_EXTRAPOLATION_S + 1e-9
    assert np.allclose(gy[held], spin[0]) and np.allclose(gy[~held], bias.gyroscope())
    pim = imu.preintegrate(params, bias, gy[~held], ac[~held], dt[~held])
    state = pim.predict(gtsam.NavState(attitude, np.zeros(3), np.array([1.0, 0.0, 0.0])), bias)
    assert state.attitude().equals(attitude, 1e-9)
    assert np.allclose(state.velocity(), [1.0, 0.0, 0.0], atol=1e-9)


def test_a_dropout_guess_adds_the_unseen_motion_to_the_imu_factor():
    """Test that the seconds of a block the dropout's guess fills are counted, and that
    the covariance they add is the constant-velocity prior's: yaw at the turn density,
    velocity at the acceleration density, over those seconds; the level attitude and the
    bias stay the IMU's own (nothing added)."""
    from uwbfuse.config import Extrinsics, ImuConfig
    from uwbfuse.constants import MAX_EXTRAPOLATION_S
    from uwbfuse.graph import imu

    buf = imu.ImuBuffer()
    t = np.arange(0, 1_000_000_001, 10_000_000, dtype=np.int64)  # 100 Hz for 1 s
    buf.add(t, np.zeros((len(t), 3)), np.tile([0.0, 0.0, 9.81], (len(t), 1)))
    params = imu.preintegration_params(ImuConfig(), Extrinsics())
    bias = gtsam.imuBias.ConstantBias()
    rest = imu.rest_reading(params, gtsam.Rot3(), bias)

    def guess_s(t0: int, t1: int) -> float:
        return buf.pieces_with_guess(t0, t1, lambda: rest)[3]

    assert guess_s(0, 1_000_000_000) == 0.0
    assert math.isclose(guess_s(1_000_000_000, 3_000_000_000), 2.0 - MAX_EXTRAPOLATION_S)
    assert math.isclose(guess_s(2_000_000_000, 2_100_000_000), 0.1)
    t0, t1 = 2_000_000_000, 2_100_000_000  # a keyframe inside the dropout
    *pieces, g_s = buf.pieces_with_guess(t0, t1, lambda: rest)
    g = imu.guess_covariance(params, bias, tuple(pieces), g_s, 1.0, 0.5)
    # rows: rotation (3), position (3), velocity (3), biases (6)
    assert math.isclose(g[2, 2], 0.5**2 * 0.1, rel_tol=1e-6)  # yaw: turn density^2 x s
    assert abs(g[0, 0]) < 1e-12 and abs(g[1, 1]) < 1e-12  # roll, pitch: the IMU's own
    assert np.allclose(np.diag(g)[6:9], 1.0**2 * 0.1, rtol=1e-3)  # velocity
    assert np.allclose(g[9:, 9:], 0.0)


def test_unique_inverse_equals_numpys():
    """Test that `graph.uwb.unique_inverse` (a sort and a search) gives
    `np.unique(x, return_inverse=True)`'s codes and inverse for (anchor, segment) codes
    and anchor indices, one code, repeated codes and none."""
    from uwbfuse.graph.uwb import unique_inverse

    rng = np.random.default_rng(17)
    cases = [rng.integers(0, 4, n) * (1 << 40) + rng.integers(0, 9, n) for n in (1, 7, 135, 400)]
    cases += [rng.integers(0, 8, 135), np.full(5, 3 << 40), np.zeros(0, np.int64)]
    for x in cases:
        code, inv = unique_inverse(x)
        ref_code, ref_inv = np.unique(x, return_inverse=True)
        np.testing.assert_array_equal(code, ref_code)
        np.testing.assert_array_equal(inv, ref_inv.ravel())
        assert code.dtype == ref_code.dtype and inv.dtype == ref_inv.dtype
        np.testing.assert_array_equal(code[inv], x)


def test_class_change_time_is_the_mean_time_between_class_changes():
    """Test `NlosModel.class_change_time`: redraws every switch_time on average, each
    changing the class with probability 2 p (1 - p) at the stationary rate p; checked
    against a simulated two-state chain."""
    m = NlosModel(0.05, 0.07, 0.3, 0.13, 5.0, 1.0, 0.3, 0.05, switch_time=2.0)
    assert m.class_change_time == pytest.approx(2.0 / (2 * 0.3 * 0.7))
    rng = np.random.default_rng(1)
    dt, n = 0.1, 400_000
    redraw = rng.random(n) < 1.0 - math.exp(-dt / m.switch_time)
    draw = rng.random(n) < m.p_nlos
    state = np.empty(n, bool)
    s = False
    for i in range(n):
        s = draw[i] if redraw[i] else s
        state[i] = s
    changes = np.count_nonzero(state[1:] != state[:-1])
    assert n * dt / changes == pytest.approx(m.class_change_time, rel=0.05)
    # p is held within [0.02, 0.98]: no infinite span where the log has no NLOS
    m.p_nlos = 0.0
    assert m.class_change_time == pytest.approx(2.0 / (2 * 0.02 * 0.98))
