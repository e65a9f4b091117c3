# SPDX-License-Identifier: BSD-3-Clause
"""The wheel track's scalar fast paths against its vectorised ones, bit for bit (GTSAM-free)."""

from __future__ import annotations

import gtsam
import numpy as np

from uwbfuse.config import WheelConfig
from uwbfuse.graph.wheel import _wheel_scale_evidence_arrays, _wheel_scale_evidence_few
from uwbfuse.positioning.wheel_track import WheelTrack, arc_step, arc_steps

NS = 1_000_000_000


def _bits(x: np.ndarray) -> np.ndarray:
    return np.asarray(x, np.float64).view(np.int64)  # signed zeros count too


def test_arc_step_equals_arc_steps_bit_for_bit():
    """Test that the scalar arc (Python floats) gives exactly `arc_steps`' numbers on random
    arcs: turning, straight (|dyaw| below the series threshold, zero, negative zero),
    backwards and at any start heading."""
    rng = np.random.default_rng(11)
    n = 5000
    v = rng.normal(0.5, 1.0, n)
    dt = rng.uniform(0.0, 0.2, n)
    yaw0 = rng.uniform(-10.0, 10.0, n)
    dyaw = rng.normal(0.0, 0.3, n)
    dyaw[::5] = rng.uniform(-2e-6, 2e-6, len(dyaw[::5]))  # both sides of the 1e-6 rad switch
    dyaw[1::50], dyaw[2::50], yaw0[3::50], v[4::50] = 0.0, -0.0, 0.0, 0.0
    dx, dy = arc_steps(v, dt, yaw0, dyaw)
    one = np.array([arc_step(*a) for a in zip(v.tolist(), dt.tolist(), yaw0.tolist(),
                                               dyaw.tolist(), strict=True)])
    assert np.array_equal(_bits(one[:, 0]), _bits(dx))
    assert np.array_equal(_bits(one[:, 1]), _bits(dy))


def test_one_pair_covariance_equals_the_vectorised_one():
    """Test that `covariance` of one pair (the scalar pieces, `_pieces_one`) equals the
    vectorised pass over many pairs exactly, on random tracks with straight samples, pairs
    starting on a sample and pairs past the track's ends."""
    rng = np.random.default_rng(12)
    t = np.cumsum(rng.integers(1, 60_000_000, 400)) + NS
    t[200:] += 3 * NS  # a 3 s dropout: pieces that carry a twist beyond it
    v, w = rng.normal(0.8, 0.6, 400), rng.normal(0.0, 0.6, 400)
    w[::4] = 0.0
    track = WheelTrack()
    track.add(t, v, w)
    ta = rng.integers(int(t[0]) - NS, int(t[-1]) + NS, 300)
    ta[:30] = t[rng.integers(0, 400, 30)]
    tb = ta + rng.integers(1, 500_000_000, 300)
    cfg = WheelConfig(sigma_v=0.07, sigma_lateral=0.03, sigma_omega=0.04)
    cov = track.covariance(ta, tb, cfg)
    for j in range(len(ta)):
        assert np.array_equal(cov[j], track.covariance(int(ta[j]), int(tb[j]), cfg))
    assert np.all(cov[:, 0, 0] > 0)


def test_a_dropout_leaves_the_wheel_factor_little_to_say():
    """Test that the covariance of a stretch the track carries on one twist through a
    dropout grows with the dropout (the speed and turn rate may have changed unseen), that
    within MAX_EXTRAPOLATION_S of a sample nothing is added, and that online (the dropout
    not yet over) and offline (its end sample in) both see it."""
    from uwbfuse.constants import MAX_EXTRAPOLATION_S, WHEEL_GUESS_ACCEL

    cfg = WheelConfig(sigma_v=0.05, sigma_lateral=0.01, sigma_omega=0.05)
    t = NS + np.arange(0, 10 * NS, 20_000_000)  # 50 Hz for 10 s
    steady = WheelTrack()
    steady.add(t, np.full(len(t), 0.5), np.zeros(len(t)))
    gap = WheelTrack()
    keep = (t < 4 * NS) | (t >= 9 * NS)  # silent from 4 to 9 s after the first sample
    gap.add(t[keep], np.full(int(keep.sum()), 0.5), np.zeros(int(keep.sum())))
    q0 = cfg.sigma_v**2
    online = WheelTrack()  # the dropout still on: the track ends at 4 s
    online.add(t[t < 4 * NS], np.full(int((t < 4 * NS).sum()), 0.5),
               np.zeros(int((t < 4 * NS).sum())))
    # a stretch within MAX_EXTRAPOLATION_S of the last sample: one piece of plain noise
    a, b = 4 * NS + 10_000_000, 4 * NS + 300_000_000
    assert online.covariance(a, b, cfg)[0, 0] == q0 * ((b - a) / NS) ** 2
    a, b = 8 * NS, 8 * NS + 100_000_000  # 0.1 s, 4 s after the last sample
    c_on = online.covariance(a, b, cfg)
    reach = (b - (4 * NS - 20_000_000)) / NS - MAX_EXTRAPOLATION_S
    assert c_on[0, 0] > 0.9 * (q0 + (WHEEL_GUESS_ACCEL * reach) ** 2) * 0.1**2
    assert c_on[0, 0] > 100 * steady.covariance(a, b, cfg)[0, 0]
    c_off = gap.covariance(4 * NS, 9 * NS, cfg)  # the dropout as one piece, offline
    assert np.sqrt(c_off[0, 0]) > 3.0 and np.sqrt(c_off[2, 2]) > 5.0  # m, rad
    assert np.sqrt(steady.covariance(4 * NS, 9 * NS, cfg)[0, 0]) < 0.3


def test_few_samples_integrate_as_the_array_pass():
    """Test that a batch of up to FEW_SAMPLES samples integrated in Python floats gives the
    array pass's poses bit for bit (random starts, straight and turning samples, zero
    intervals), and that a track fed sample by sample equals one fed in large batches to
    rounding."""
    from uwbfuse.positioning import wheel_track as wt

    rng = np.random.default_rng(13)
    for m in range(1, wt.FEW_SAMPLES + 1):
        for _ in range(200):
            start = rng.normal(0.0, 5.0, 3)
            v, w = rng.normal(0.5, 1.0, m), rng.normal(0.0, 0.8, m)
            w[rng.random(m) < 0.3] = 0.0
            tau = rng.uniform(0.0, 0.1, m)
            tau[rng.random(m) < 0.1] = 0.0
            assert np.array_equal(_bits(wt._integrate_few(start, v, w, tau)),
                                  _bits(wt._integrate(start, v, w, tau)))
    t = np.cumsum(rng.integers(5_000_000, 30_000_000, 500)) + NS
    v, w = rng.normal(0.8, 0.3, 500), rng.normal(0.0, 0.4, 500)
    one, big = WheelTrack(), WheelTrack()
    for i in range(0, 500, 3):
        one.add(t[i:i + 3], v[i:i + 3], w[i:i + 3])
    big.add(t[:250], v[:250], w[:250])
    big.add(t[250:], v[250:], w[250:])
    np.testing.assert_allclose(one.pose, big.pose, rtol=0, atol=1e-9)


def test_between_few_equals_between_bit_for_bit():
    """Test that a keyframe's motions in Python floats (`between_few`) equal `between` over
    arrays exactly: times before, inside and after the track, on samples, on an empty track."""
    rng = np.random.default_rng(14)
    t = np.cumsum(rng.integers(5_000_000, 40_000_000, 300)) + NS
    v, w = rng.normal(0.8, 0.5, 300), rng.normal(0.0, 0.7, 300)
    w[::6] = 0.0
    track = WheelTrack()
    assert np.array_equal(track.between_few(int(t[0]), [int(t[1])]), np.zeros((1, 3)))
    track.add(t, v, w)
    for _ in range(300):
        t_a = int(rng.integers(int(t[0]) - NS, int(t[-1]) + NS))
        if rng.random() < 0.2:
            t_a = int(t[rng.integers(0, 300)])
        t_b = (t_a + rng.integers(-20_000_000, 300_000_000, rng.integers(1, 17))).tolist()
        ref = track.between(np.full(len(t_b), t_a, np.int64), np.array(t_b, np.int64))
        assert np.array_equal(_bits(track.between_few(t_a, t_b)), _bits(ref))


def test_few_pair_wheel_scale_evidence_equals_the_vectorised_one():
    """Test that `wheel_scale_evidence`'s Python-float path for a few keyframe pairs gives
    the vectorised path's numbers bit for bit: tilted and turning poses, residuals inside
    and beyond the Huber threshold, 1 to 7 pairs, a NaN pose and none."""
    rng = np.random.default_rng(4)
    for trial in range(300):
        n = 1 + trial % 7
        rot_a, rot_b = np.empty((n, 3, 3)), np.empty((n, 3, 3))
        for i in range(n):
            ypr = rng.normal(0.0, [3.0, 0.05, 0.05])
            ra = gtsam.Rot3.Ypr(*ypr)
            rot_a[i] = ra.matrix()
            rot_b[i] = ra.compose(gtsam.Rot3.Ypr(*rng.normal(0.0, [0.1, 0.01, 0.01]))).matrix()
        trans_a = rng.normal(0.0, 20.0, (n, 3))
        trans_b = trans_a + rng.normal(0.0, 0.1, (n, 3))
        delta = rng.normal(0.0, 0.1, (n, 3))
        root = rng.normal(0.0, 1e-2, (n, 3, 3))
        cov = root @ np.swapaxes(root, 1, 2) + np.eye(3) * 1e-6
        scale = rng.uniform(0.9, 1.1, 2)
        if trial == 5:
            trans_b[0, 0] = np.nan
        args = (rot_a, trans_a, rot_b, trans_b, delta, cov, scale, 1.345)
        few, ref = _wheel_scale_evidence_few(*args), _wheel_scale_evidence_arrays(*args)
        for a, b in zip(few, ref, strict=True):
            np.testing.assert_array_equal(a, b)
    empty = (np.zeros((0, 3, 3)), np.zeros((0, 3)), np.zeros((0, 3, 3)), np.zeros((0, 3)),
             np.zeros((0, 3)), np.zeros((0, 3, 3)), np.ones(2), 1.345)
    for a, b in zip(_wheel_scale_evidence_few(*empty), _wheel_scale_evidence_arrays(*empty),
                    strict=True):
        np.testing.assert_array_equal(a, b)
