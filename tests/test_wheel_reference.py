# SPDX-License-Identifier: BSD-3-Clause
"""The NLOS classifier's wheel-track reference (`positioning.wheel_reference`)."""

from __future__ import annotations

import dataclasses

import numpy as np

from uwbfuse.config import Config
from uwbfuse.positioning.nlos_classifier import (
    _reference_fixes,
    log_features,
    range_features,
    range_labels,
)
from uwbfuse.positioning.wheel_reference import _procrustes, wheel_reference
from uwbfuse.sim.sensors import tag_positions
from uwbfuse.sim.simulator import simulate_with_truth
from uwbfuse.sim.trajectory import evaluate as kinematics
from uwbfuse.streams import SensorLog, WheelStream


def _reference(lg: SensorLog, ranges: np.ndarray | None = None,
               wheel: WheelStream | None = None) -> tuple[np.ndarray, np.ndarray]:
    """wheel_reference of a simulated log as `range_features` calls it."""
    cfg = Config()
    rs = lg.ranges if ranges is None else dataclasses.replace(lg.ranges, range=ranges)
    ep, pos, ok, _, tag_z = _reference_fixes(rs, lg.anchors, cfg, True)
    dz = lg.anchors.positions[rs.anchor, 2] - tag_z
    d2 = np.sqrt(np.maximum(rs.range**2 - dz**2, 0.0))
    return wheel_reference(rs.t_ns, rs.anchor, d2, lg.anchors.positions[:, :2],
                           lg.wheel if wheel is None else wheel, np.zeros(2), ep, pos[:, :2],
                           ok, cfg.uwb.sigma)


def _true_tag(s) -> np.ndarray:
    t = (s.log.ranges.t_ns - s.scenario.t0_ns) / 1e9
    return tag_positions(s.scenario, kinematics(s.timeline, t))[:, :2]


def test_nearer_the_truth_than_the_fix_line_and_own_anchor_left_out() -> None:
    """test that the residual against the wheel reference is nearer the range's own error
    than the one against the constant-velocity line of fixes, and that a range's reference
    barely moves (through the warm start only) when its own anchor's ranges are all 0.5 m
    longer, while the other anchors' references do."""
    s = simulate_with_truth("warehouse", 30.0, seed=5)
    lg = s.log
    ref, ok = _reference(lg)
    assert ok.mean() > 0.9
    assert np.median(np.linalg.norm(ref[ok] - _true_tag(s)[ok], axis=1)) < 0.2
    x, names = log_features(lg, Config())
    x_line, _ = range_features(lg.ranges, lg.anchors, Config(), True, None)  # planar line
    _, err = range_labels(lg, Config())
    i = names.index("residual")
    fin = ok & np.isfinite(x_line[:, i])
    wheel_dev = np.median(np.abs(x[fin, i] - err[fin]))
    line_dev = np.median(np.abs(x_line[fin, i] - err[fin]))
    assert wheel_dev < 0.95 * line_dev, (wheel_dev, line_dev)  # here 0.057 vs 0.066 m
    ref2, ok2 = _reference(lg, lg.ranges.range + np.where(lg.ranges.anchor == 0, 0.5, 0.0))
    own = ok & ok2 & (lg.ranges.anchor == 0)
    other = ok & ok2 & (lg.ranges.anchor != 0)
    moved_own = np.median(np.linalg.norm(ref2[own] - ref[own], axis=1))
    moved_other = np.median(np.linalg.norm(ref2[other] - ref[other], axis=1))
    # the others' fits take anchor 0 in (Cauchy-weighted), its own fits leave it out
    assert moved_other > 0.02
    assert moved_own < 0.05 * moved_other, (moved_own, moved_other)


def test_causal_later_data_changes_nothing() -> None:
    """test that a range's reference is the same when the log (ranges and wheels) is cut
    after it: the fits use only what was stamped before the range."""
    s = simulate_with_truth("warehouse-nlos", 20.0, seed=4)
    lg = s.log
    ref, ok = _reference(lg)
    t_cut = int(lg.ranges.t_ns[len(lg.ranges) // 2])
    nr = int(np.searchsorted(lg.ranges.t_ns, t_cut, side="right"))
    nw = int(np.searchsorted(lg.wheel.t_ns, t_cut, side="right"))
    part = dataclasses.replace(lg, ranges=lg.ranges.slice(0, nr), wheel=lg.wheel.slice(0, nw))
    ref_p, ok_p = _reference(part)
    keep = nr - 8  # the last epoch of the shorter log may close early
    np.testing.assert_array_equal(ok[:keep], ok_p[:keep])
    assert ok[:keep].mean() > 0.8
    # multilaterate's Gauss-Newton may take one more step in the longer log (5e-8 m)
    np.testing.assert_allclose(ref[:keep][ok[:keep]], ref_p[:keep][ok_p[:keep]], atol=1e-6)


def test_start_falls_back_to_the_fix_line() -> None:
    """test that ranges before the first fit have no wheel reference and that their
    features are then those of the constant-velocity line of the planar fixes."""
    s = simulate_with_truth("warehouse", 10.0, seed=6)
    lg = s.log
    _, ok = _reference(lg)
    first = int(np.argmax(ok))
    assert 0 < first and not ok[:first].any()
    x, _ = log_features(lg, Config())
    # the planar fixes' line, as on a wheeled log without `wheel_reference`
    x_line, _ = range_features(lg.ranges, lg.anchors, Config(), True, None)
    np.testing.assert_array_equal(x[:first], x_line[:first])
    assert not np.array_equal(x[ok], x_line[ok])


def test_procrustes_still_and_moving() -> None:
    """test the start transform: a still track (spread below MIN_SPREAD_M) gives yaw 0 and
    the mean offset; a moving one recovers the rotation and translation."""
    q = np.array([[0.0, 0.0], [0.01, 0.0], [0.0, 0.02]])
    tf = _procrustes(q, q + np.array([3.0, -1.0]))
    np.testing.assert_allclose(tf, [3.0, -1.0, 0.0], atol=1e-12)
    q = np.column_stack([np.linspace(0, 3, 10), np.sin(np.linspace(0, 3, 10))])
    yaw = 0.7
    r = np.array([[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]])
    np.testing.assert_allclose(_procrustes(q, q @ r.T + np.array([1.0, 2.0])), [1.0, 2.0, yaw],
                               atol=1e-9)


def test_wheel_gap_and_empty_wheels() -> None:
    """test that a 3 s hole in the wheel stream gives no reference more than
    MAX_WHEEL_GAP_S after its last sample, that the fits after it stay on the truth (they
    take no range from before the hole), and that an empty wheel stream gives none."""
    s = simulate_with_truth("warehouse", 30.0, seed=5)
    lg = s.log
    w = lg.wheel
    t0 = int(w.t_ns[0])
    hole = (w.t_ns > t0 + 10 * 10**9) & (w.t_ns < t0 + 13 * 10**9)
    gappy = WheelStream(w.t_ns[~hole], w.v[~hole], w.omega[~hole])
    ref, ok = _reference(lg, wheel=gappy)
    t = lg.ranges.t_ns
    in_hole = (t > t0 + 11.05 * 10**9) & (t < t0 + 12.95 * 10**9)
    assert in_hole.any() and not ok[in_hole].any()
    after = ok & (t > t0 + 13 * 10**9)
    assert after.sum() > 0.5 * np.count_nonzero(t > t0 + 13 * 10**9)
    assert np.median(np.linalg.norm(ref[after] - _true_tag(s)[after], axis=1)) < 0.2
    empty = WheelStream(w.t_ns[:0], w.v[:0], w.omega[:0])
    _, ok0 = _reference(lg, wheel=empty)
    assert not ok0.any()
