# SPDX-License-Identifier: BSD-3-Clause
"""batch's evidence windows (`uwbfuse.graph.evidence_window`): which keyframes the noise,
time-offset and range-model fits look at on a long log, and that the fits still find
what the whole log shows."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from uwbfuse.config import Config
from uwbfuse.estimator import Method
from uwbfuse.pipeline import estimate
from uwbfuse.sim.simulator import simulate_with_truth
from uwbfuse.streams import NS_PER_S

gtsam = pytest.importorskip("gtsam")

from uwbfuse.graph import evidence_window  # noqa: E402
from uwbfuse.graph.evidence_window import EvidenceWindows, window_mask  # noqa: E402
from uwbfuse.graph.keys import X  # noqa: E402
from uwbfuse.graph.offline import run_lm  # noqa: E402


def test_a_log_within_the_budget_is_taken_whole():
    """test that a log with no more ranges than the budget keeps every keyframe"""
    stamps = np.arange(0.0, 600.0, 0.1)
    assert window_mask(stamps, 5000, budget=5000).all()
    assert window_mask(stamps[:100], 10**6, budget=10).all()  # shorter than one window


def test_windows_hold_the_budget_and_span_the_log():
    """test that a long log gets ceil(budget / ranges per window) windows of 30 s, the
    first at its start and the last at its end"""
    stamps = np.arange(0.0, 3600.0, 0.1)
    keep = window_mask(stamps, 36000, budget=1000, window_s=30.0)  # 10 ranges/s
    assert keep.sum() == pytest.approx(4 * 300, abs=4)  # 4 windows of 300 keyframes
    assert keep[0] and keep[-1]
    starts = np.flatnonzero(keep[1:] & ~keep[:-1]) + 1
    assert len(starts) == 3  # after the one at keyframe 0
    assert np.ptp(np.diff(stamps[starts])) < 0.2  # evenly spread


def _chain(n: int) -> gtsam.NonlinearFactorGraph:
    noise = gtsam.noiseModel.Isotropic.Sigma(6, 0.1)
    graph = gtsam.NonlinearFactorGraph()
    graph.add(gtsam.PriorFactorPose3(X(0), gtsam.Pose3(), noise))
    for k in range(n - 1):
        graph.add(gtsam.BetweenFactorPose3(X(k), X(k + 1), gtsam.Pose3(), noise))
    return graph


def test_the_windowed_graph_keeps_indices_and_starts_each_window_from_a_prior():
    """test that factors touching a keyframe outside the windows become null slots (every
    other factor keeps its index), each later window gets its prior, and LM over the
    windowed graph leaves the values outside unchanged"""
    graph = _chain(10)
    keep = np.array([1, 1, 1, 0, 0, 0, 1, 1, 0, 0], bool)
    noise = gtsam.noiseModel.Isotropic.Sigma(6, 1.0)
    win = EvidenceWindows.of(graph, keep, lambda k, v: _prior(k, v, noise))
    assert win.firsts == [6]
    initial = gtsam.Values()
    for k in range(10):
        initial.insert(X(k), gtsam.Pose3(gtsam.Rot3(), np.array([k, 0.0, 0.0])))
    out = win.graph(graph, initial)
    # between factors k -> k+1 at index k + 1: kept for (0,1), (1,2), (6,7)
    kept = [i for i in range(graph.size()) if out.at(i) is not None]
    assert kept == [0, 1, 2, 7]
    assert out.size() == graph.size() + 1  # the prior on X(6)
    res = gtsam.LevenbergMarquardtOptimizer(out, initial).optimize()
    assert np.allclose(res.atPose3(X(4)).translation(), [4.0, 0.0, 0.0])
    assert np.allclose(res.atPose3(X(7)).translation(), [6.0, 0.0, 0.0], atol=1e-6)
    # batch's LM carries only the windows' keys and hands the others back unchanged
    sol = run_lm(out, initial, 30)
    assert sol.values.size() == initial.size()
    for k in range(10):
        assert np.allclose(sol.values.atPose3(X(k)).matrix(), res.atPose3(X(k)).matrix(),
                           atol=1e-9)
    assert sol.error == pytest.approx(out.error(res), abs=1e-9)


def _prior(k: int, values: gtsam.Values, noise) -> gtsam.NonlinearFactorGraph:
    g = gtsam.NonlinearFactorGraph()
    g.add(gtsam.PriorFactorPose3(X(k), values.atPose3(X(k)), noise))
    return g


def test_batch_finds_the_wheel_time_offset_within_its_windows(monkeypatch):
    """Test that batch, its fits held to two 30 s windows of a 120 s log, still finds wheel
    stamps that run early (15 ms, as `test_batch_fits_the_wheel_time_offset` on 60 s)
    and keeps a good track.

    Measured (factory, seed 0, 120 s, budget 1500 ranges): offset 0.0166 s, evidence share
    0.519 (two windows of the graph's keyframes), 2-D ATE 0.0045 m; with the whole log as
    evidence 0.0199 s and 0.0045 m."""
    monkeypatch.setattr(evidence_window, "EVIDENCE_RANGES", 1500)
    sim = simulate_with_truth("factory", 120.0, 0)
    w = sim.log.wheel
    early = replace(sim.log, wheel=replace(w, t_ns=w.t_ns - round(0.015 * NS_PER_S)))
    res = estimate(early, Method.BATCH, Config())
    rep = res.report["batch"]
    assert 0.45 < rep["evidence_share"] < 0.6
    assert rep["wheel_time_offset_s"] == pytest.approx(0.015, abs=0.005)
    from uwbfuse.eval.evaluate import evaluate

    assert evaluate(res.trajectory, early.ground_truth).ate_2d.rmse < 0.01
