# SPDX-License-Identifier: BSD-3-Clause
"""Ranges at a standstill share one error: `graph.rest.RestEvidence` weighs their evidence."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from uwbfuse.config import Config, InitConfig
from uwbfuse.estimator import Method
from uwbfuse.pipeline import estimate
from uwbfuse.sim.simulator import simulate_with_truth
from uwbfuse.streams import NS_PER_S

pytest.importorskip("gtsam")

from uwbfuse.graph.rest import QuietDrift, RestEvidence, effective_count
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


def _decided(imu: tuple, v: np.ndarray, cov: np.ndarray, until_s: float,
             keyframe_s: float = 0.1) -> tuple[RestEvidence, list[bool]]:
    """Feed `RestEvidence` the IMU keyframe by keyframe; the still run judged from the
    velocity `v` (m/s) with covariance `cov` when it asks (`pending`), as the graph does;
    per keyframe interval up to `until_s`, whether it is held at rest (`at_rest`)."""
    rest = RestEvidence(InitConfig(), has_wheel=False)
    t_i, g, acc = imu
    period = round(keyframe_s * NS_PER_S)
    held = []
    for t_b in range(period, round(until_s * NS_PER_S) + 1, period):
        i = (t_i > t_b - period) & (t_i <= t_b)
        rest.add_imu(t_i[i], g[i], acc[i])
        run = rest.pending(t_b)
        if run is not None:
            rest.decide(run, v, cov)
        held.append(rest.at_rest(t_b - period, t_b))
    return rest, held


def _walk_then_still(accel_from_s: float | None = None, accel: float = 0.3,
                     seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A level IMU (100 Hz) walking for 1 s, then still, and from `accel_from_s` on
    (None: never) accelerating along x at `accel` m/s^2 with a still IMU's spread: a
    start from rest that the still test cannot see."""
    t, g, acc = _imu(8.0, 0.01, seed=seed)
    walk = t < 1.0 * NS_PER_S
    acc[walk] += np.random.default_rng(seed + 1).normal(0.0, 1.0, (int(walk.sum()), 3))
    if accel_from_s is not None:
        acc[t >= accel_from_s * NS_PER_S, 0] += accel
    return t, g, acc


def test_a_still_run_entered_at_speed_is_a_glide() -> None:
    """`decide`: the velocity entering a still run against its covariance. Glides at 0.1
    and 0.5 m/s as well known as the graph knows them (2-5 cm/s) are not held at rest, a
    velocity within its noise is, and a run without a velocity from before it is not."""
    rest = RestEvidence(InitConfig(), has_wheel=False)
    assert not rest.decide(1, np.array([0.1, 0.0, 0.0]), np.eye(3) * 0.02**2)
    assert not rest.decide(2, np.array([0.0, 0.5, 0.0]), np.eye(3) * 0.05**2)
    assert rest.decide(3, np.array([0.03, -0.02, 0.0]), np.eye(3) * 0.03**2)
    assert not rest.decide(4, None, None)


def test_a_rest_is_held_until_the_imu_integrates_a_start() -> None:
    """After a walk the IMU goes still: a run entered at rest is held from its window on
    (a zero velocity at every keyframe); one entered at 0.1 m/s is not held at all; a
    start at 0.3 m/s^2 that the still test cannot see ends the rest within half a second
    (`QuietDrift`), a rest that never starts is held to the end."""
    zero, cov = np.zeros(3), np.eye(3) * 0.03**2
    _, held = _decided(_walk_then_still(), zero, cov, 7.0)
    t = np.arange(1, len(held) + 1) * 0.1
    assert not any(np.array(held)[t < 1.5])
    assert all(np.array(held)[t > 1.7])
    _, glide = _decided(_walk_then_still(), np.array([0.1, 0.0, 0.0]), np.eye(3) * 0.02**2,
                        7.0)
    assert not any(glide)
    _, start = _decided(_walk_then_still(accel_from_s=4.0), zero, cov, 7.0)
    start = np.array(start)
    assert all(start[(t > 1.7) & (t < 4.0)])
    assert not any(start[t > 4.5])


def test_quiet_drift_turns_the_specific_force_with_the_gyro() -> None:
    """At rest an IMU that tilts by 0.06 rad at 0.02 rad/s (under the still test's gyro
    limit) after its reference window sees gravity turn in its frame; turned back by the
    gyro, its integrated velocity stays zero within its noise, unturned it does not."""
    rate, w = 100.0, 0.02
    t = np.arange(0.0, 6.0, 1.0 / rate)
    theta = w * np.clip(t - 1.0, 0.0, 3.0)
    acc = np.stack([np.zeros_like(t), 9.81 * np.sin(theta), 9.81 * np.cos(theta)], axis=1)
    gyro = np.zeros((len(t), 3))
    gyro[(t >= 1.0) & (t < 4.0), 0] = w
    rng = np.random.default_rng(0)
    acc += rng.normal(0.0, 0.01, acc.shape)
    gyro += rng.normal(0.0, 0.002, gyro.shape)
    t_ns = (t * NS_PER_S).astype(np.int64)
    chi = []
    for rates in (gyro, np.zeros_like(gyro)):  # as measured; as if the gyro saw nothing
        drift = QuietDrift(0, round(0.5 * NS_PER_S))
        for lo in range(0, len(t), 8):
            drift.add(t_ns[lo:lo + 8], rates[lo:lo + 8], acc[lo:lo + 8])
        chi.append(drift.chi2(0.015))
    assert chi[0] < 11.3 < 100.0 < chi[1]  # 11.3: chi-square (3) at 99 %


def _bumped_run(scenario: str, duration_s: float, bump_s: float) -> dict:
    """isam2's report on an IMU + UWB simulation (seed 0) whose IMU is shaken for 0.3 s
    from `bump_s` (specific force spread 1 m/s^2): the still run after it is one the
    graph sees entered."""
    log = simulate_with_truth(scenario, duration_s, seed=0, streams=("imu", "uwb")).log
    imu = log.imu
    t = (imu.t_ns - imu.t_ns[0]) / NS_PER_S
    shake = (t >= bump_s) & (t < bump_s + 0.3)
    acc = imu.accel.copy()
    acc[shake] += np.random.default_rng(0).normal(0.0, 1.0, (int(shake.sum()), 3))
    log = replace(log, imu=replace(imu, accel=acc))
    return estimate(log, Method.ISAM2, Config(), covariance=False).report


@pytest.mark.parametrize(("scenario", "bump_s"), [("room", 56.6), ("warehouse", 20.0)])
def test_a_glide_entering_a_quiet_imu_gets_no_zero_velocity(scenario: str,
                                                             bump_s: float) -> None:
    """The room's base glides at 0.1 m/s, the warehouse's at 0.5 m/s, on a straight line
    after the shake: the IMU is still, the graph's velocity entering the run is not zero
    (chi-square 37-126 in the room's seeds 0-4, 131 and 361 in the warehouse's 0 and 1,
    against 11.3), so no keyframe is held at rest."""
    assert _bumped_run(scenario, 60.0, bump_s)["standstill_keyframes"] == 0


def test_a_rest_gets_zero_velocities_until_a_quiet_start() -> None:
    """The factory's base stops at 57.3-60.3 s, shaken at 57.4 s: the run after it is
    entered at rest and held (a zero velocity per keyframe from its window on); the start
    at 60.3 s accelerates at 0.3 m/s^2 with a still IMU, and the IMU's integrated
    velocity ends the rest within seconds (held to the end of the log: about 150)."""
    held = _bumped_run("factory", 75.0, 57.4)["standstill_keyframes"]
    assert 20 < held < 60
