# SPDX-License-Identifier: BSD-3-Clause
"""Ranges at a standstill share one error: `graph.rest.RestEvidence` weighs their evidence."""

from __future__ import annotations

import numpy as np
import pytest

from uwbfuse.config import InitConfig
from uwbfuse.streams import NS_PER_S

pytest.importorskip("gtsam")

from uwbfuse.graph.rest import RestEvidence, effective_count
from uwbfuse.graph.uwb import los_subset_search
from uwbfuse.nlos import NlosModel

SIGMA_LOS = 0.06  # m


def _imu(dur_s: float, accel_std: float, rate: float = 100.0, gap: tuple | None = None,
         seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """IMU samples (stamps ns, gyro, specific force) of a level IMU, the specific force
    spread by `accel_std` m/s^2 (0.01: still, 1.0: a walk); `gap` (s, s): no samples."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, dur_s, 1.0 / rate)
    if gap is not None:
        t = t[(t < gap[0]) | (t >= gap[1])]
    gyro = rng.normal(0.0, 0.002, (len(t), 3))
    acc = np.array([0.0, 0.0, 9.81]) + rng.normal(0.0, accel_std, (len(t), 3))
    return (t * NS_PER_S).astype(np.int64), gyro, acc


def _ranges(dur_s: float, speed: float = 0.0, noise: float = 0.01, seed: int = 1
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Ranges of two anchors at 8 Hz each (time order): 5 m plus a shared offset per
    anchor, the tag receding at `speed` m/s, each range with `noise` m of its own."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.05, dur_s, 1.0 / 16.0)
    a = np.arange(len(t)) % 2
    z = 5.0 + np.array([0.2, -0.1])[a] + speed * t + rng.normal(0.0, noise, len(t))
    return (t * NS_PER_S).astype(np.int64), a, z


def _weights(imu: tuple, ranges: tuple, keyframe_s: float = 0.1) -> np.ndarray:
    """Feed `RestEvidence` as the graph does (the data up to each keyframe, then its
    ranges): the weights."""
    rest = RestEvidence(InitConfig(), has_wheel=False)
    t_i, g, acc = imu
    t_r, a, z = ranges
    w = []
    period = round(keyframe_s * NS_PER_S)
    for t_b in range(period, int(t_r[-1]) + period, period):
        i = (t_i > t_b - period) & (t_i <= t_b)
        rest.add_imu(t_i[i], g[i], acc[i])
        k = (t_r > t_b - period) & (t_r <= t_b)
        w.append(rest.weights(t_r[k], a[k], z[k], SIGMA_LOS))
    return np.concatenate(w)


def test_effective_count() -> None:
    """Independent ranges count as themselves, identical ones as one."""
    assert effective_count(0, 0.5) == 0.0
    assert effective_count(1, 0.9) == 1.0
    assert effective_count(50, 0.0) == 50.0
    assert effective_count(50, 1.0) == pytest.approx(1.0)
    assert effective_count(50, 0.9) < effective_count(1000, 0.9) < 1.0 / 0.9


def test_ranges_at_a_standstill_count_as_about_one() -> None:
    """A still IMU and ranges that repeat one error: once the standstill window has
    passed and the ranges have shown their noise (MIN_REST_PAIRS successive pairs), each
    anchor's further ranges add up to less than one range's evidence; before that every
    range counts whole."""
    t_r, a, z = _ranges(6.0)
    w = _weights(_imu(6.0, 0.01), (t_r, a, z))
    assert np.all(w[t_r < 0.5 * NS_PER_S] == 1.0)
    for anc in (0, 1):
        late = (t_r >= 2.0 * NS_PER_S) & (a == anc)
        assert late.sum() > 30
        assert 0.0 < w[late].sum() < 1.0
        assert w[late][-1] < w[late][0] < 1e-3  # each new range adds less


def test_a_walk_and_a_glide_count_every_range() -> None:
    """Every range counts whole where the IMU moves (a
    walk) and where the IMU is still but the ranges drift (a glide at 0.5 m/s, which the
    IMU cannot see); a glide at 0.1 m/s shows in the ranges within a second."""
    for imu, ranges in [(_imu(6.0, 1.0), _ranges(6.0)),
                        (_imu(6.0, 0.01), _ranges(6.0, speed=0.5))]:
        w = _weights(imu, ranges)
        assert np.all(w == 1.0)
    t_r, _, _ = rng = _ranges(6.0, speed=0.1)
    w = _weights(_imu(6.0, 0.01), rng)
    assert np.all(w[t_r > 1.0 * NS_PER_S] == 1.0)


def test_an_imu_dropout_is_no_standstill() -> None:
    """A still IMU that falls silent from 3 s: its silent blocks say nothing, so the
    ranges from then on count whole (before it they weigh less)."""
    t_r, a, z = _ranges(6.0)
    w = _weights(_imu(6.0, 0.01, gap=(3.0, 7.0)), (t_r, a, z))
    assert np.all(w[t_r > 3.1 * NS_PER_S] == 1.0)
    assert np.any(w[t_r < 3.0 * NS_PER_S] < 1e-3)


def test_subset_search_weighs_each_range() -> None:
    """`los_subset_search` with weights: no weights and unit weights give the same
    hypothesis to the bit, and every range given twice at half weight the same as once."""
    rng = np.random.default_rng(3)
    n = 120
    anchor = np.arange(n) % 4
    ang = anchor * np.pi / 2 + rng.normal(0.0, 0.05, n)
    u = np.stack([np.cos(ang), np.sin(ang)], axis=1)
    r = rng.normal(0.0, 0.05, n) + np.where(anchor == 2, 0.3, 0.0)
    g = np.where(anchor == 2, 0.1, 0.0)
    model = NlosModel(0.05, 0.1, 0.3, 0.13, 5.0, 1.0, 0.3, 0.05)
    base = los_subset_search(anchor, r, u, g, model)
    ones = los_subset_search(anchor, r, u, g, model, weights=np.ones(n))
    two = np.concatenate
    half = los_subset_search(two([anchor, anchor]), two([r, r]), two([u, u]), two([g, g]),
                             model, weights=np.full(2 * n, 0.5))
    assert base is not None and ones is not None and half is not None
    assert base.gain == ones.gain and np.array_equal(base.delta, ones.delta)
    assert np.array_equal(half.los, base.los)
    assert half.gain == pytest.approx(base.gain, rel=1e-9)
    assert np.allclose(half.delta, base.delta)
    assert np.allclose(half.shift_moment, base.shift_moment)
