# SPDX-License-Identifier: BSD-3-Clause
"""The wheel track's scalar fast paths against its vectorised ones, bit for bit (GTSAM-free)."""

from __future__ import annotations

import numpy as np

from uwbfuse.config import WheelConfig
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
