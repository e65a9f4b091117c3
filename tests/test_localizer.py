# SPDX-License-Identifier: BSD-3-Clause
"""The live API: `uwbfuse.Localizer` fed sample by sample gives `uwbfuse run`'s isam2."""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

import uwbfuse
from uwbfuse.config import Config
from uwbfuse.errors import AnchorMapError
from uwbfuse.estimator import Method
from uwbfuse.io.reader import (
    SKIP_NON_FINITE_RANGE,
    SKIP_NON_POSITIVE_RANGE,
    SKIP_UNKNOWN_ANCHOR,
    read_log,
    skip_duplicate,
    skip_non_finite,
)
from uwbfuse.io.tum import read_tum
from uwbfuse.io.writer import write_contract_log
from uwbfuse.localizer import SKIP_LATE, LocalizerError
from uwbfuse.pipeline import RunResult, run_log
from uwbfuse.sim.simulator import simulate
from uwbfuse.streams import NS_PER_S, SensorLog


@dataclass
class Case:
    path: Path
    log: SensorLog
    run: RunResult
    tum: Path


@pytest.fixture(scope="module")
def case(tmp_path_factory: pytest.TempPathFactory) -> Case:
    d = tmp_path_factory.mktemp("live")
    path = d / "sim.mcap"
    write_contract_log(path, simulate("warehouse", duration_s=30.0, seed=3))
    tum = d / "isam2.tum"
    # `uwbfuse run LOG --method isam2 -o isam2.tum --cov-out cov.csv` as a library call
    res = run_log(path, Method.ISAM2, Config(), tum_out=tum, cov_out=d / "cov.csv")
    return Case(path, read_log(path, Config()), res, tum)


def _samples(log: SensorLog) -> list[tuple[int, int, int]]:
    """(stamp ns, stream 0 imu / 1 wheel / 2 uwb, row) of every sample, in stamp order."""
    assert log.imu is not None and log.wheel is not None and log.ranges is not None
    ev = [(int(t), 0, i) for i, t in enumerate(log.imu.t_ns.tolist())]
    ev += [(int(t), 1, i) for i, t in enumerate(log.wheel.t_ns.tolist())]
    ev += [(int(t), 2, i) for i, t in enumerate(log.ranges.t_ns.tolist())]
    return sorted(ev)


def _feed(loc: uwbfuse.Localizer, log: SensorLog, s: int, i: int, t: int | None = None) -> None:
    assert log.imu is not None and log.wheel is not None and log.ranges is not None
    assert log.anchors is not None
    if s == 0:
        loc.add_imu(log.imu.t_ns[i] if t is None else t, log.imu.gyro[i], log.imu.accel[i])
    elif s == 1:
        loc.add_wheel(log.wheel.t_ns[i] if t is None else t, log.wheel.v[i],
                      log.wheel.omega[i])
    else:
        loc.add_range(log.ranges.t_ns[i] if t is None else t,
                      log.anchors.ids[int(log.ranges.anchor[i])], log.ranges.range[i])


def _history(loc: uwbfuse.Localizer, run: RunResult) -> list[uwbfuse.Pose]:
    """The Localizer's pose at every epoch of `run`'s trajectory, via `pose(t)`."""
    out = []
    for t in run.trajectory.t_ns.tolist():
        p = loc.pose(int(t))
        assert p is not None and p.t_ns == t
        out.append(p)
    return out


def _assert_same(loc: uwbfuse.Localizer, run: RunResult) -> None:
    traj = run.trajectory
    poses = _history(loc, run)
    np.testing.assert_array_equal(np.array([p.position for p in poses]), traj.position)
    np.testing.assert_array_equal(np.array([p.quat_xyzw for p in poses]), traj.quat_xyzw)
    assert traj.covariance is not None
    np.testing.assert_array_equal(np.array([p.covariance for p in poses]), traj.covariance)
    last = loc.latest()
    assert last is not None and last.t_ns == traj.t_ns[-1]


def test_sample_by_sample_equals_run(case: Case) -> None:
    """test that one sample at a time, in stamp order, gives run's isam2 poses bit for bit"""
    loc = uwbfuse.Localizer(Config(), case.log.anchors, history_s=60.0)
    first_answer = None
    for t, s, i in _samples(case.log):
        _feed(loc, case.log, s, i)
        if first_answer is None and loc.latest() is not None:
            first_answer = t
    loc.finish()
    assert not loc.skipped
    _assert_same(loc, case.run)
    # causal: the pose of an epoch is out once a sample stamped after it has arrived
    # (plus the 50 ms reorder window), never later than one output period after that
    assert first_answer is not None
    assert first_answer - case.run.trajectory.t_ns[0] <= 0.05 * NS_PER_S + 0.1 * NS_PER_S
    # the CLI's TUM file (positions to 1e-6 m, quaternions to 1e-9) holds the same poses
    tum = read_tum(case.tum)
    np.testing.assert_array_equal(tum.t_ns, case.run.trajectory.t_ns)
    pos = np.array([p.position for p in _history(loc, case.run)])
    np.testing.assert_allclose(tum.position, pos, atol=1e-6, rtol=0)
    # the epochs before the graph starts carry the provisional (UWB-only) fixes
    prov = np.array([p.provisional for p in _history(loc, case.run)])
    assert prov[0] and not prov[-1]
    assert np.all(np.diff(prov.astype(int)) <= 0)  # provisional only before the start
    rep = loc.report()
    assert rep["initialised"] is True
    # flat memory: the ranges from before twice the lag have been forgotten (the report
    # counts the recent ones), and the poses are still run's
    kept = sum(a["ranges"] for a in rep["anchors"].values())
    assert case.log.ranges is not None and 0 < kept < 0.8 * len(case.log.ranges)


def test_late_and_bad_samples_are_counted_skips(case: Case) -> None:
    """test that samples out of order within the window change nothing, while bad and
    too-late samples are dropped and counted, and the poses still equal run's"""
    log = case.log
    loc = uwbfuse.Localizer(Config(), dict(zip(log.anchors.ids,  # type: ignore[union-attr]
                                               log.anchors.positions.tolist(),  # type: ignore[union-attr]
                                               strict=True)), reorder_window_s=0.05)
    rng = np.random.default_rng(0)
    # every range arrives 0-40 ms after its stamp (a UWB driver's latency), the IMU and
    # wheels at once: the arrival order is not the stamp order
    arrivals = []
    for t, s, i in _samples(log):
        delay = int(rng.integers(0, 40_000_000)) if s == 2 else 0
        arrivals.append((t + delay, t, s, i))
    arrivals.sort()
    out_of_order = sum(a[1] < b[1] for a, b in itertools.pairwise(arrivals))
    assert out_of_order > 100
    t_mid = arrivals[len(arrivals) // 2][1]
    for n, (_, t, s, i) in enumerate(arrivals):
        _feed(loc, log, s, i)
        if n == 1000:
            loc.add_imu(t, [np.nan, 0.0, 0.0], [0.0, 0.0, 9.81])
            loc.add_wheel(t, np.inf, 0.0)
            loc.add_range(t, "no-such-anchor", 5.0)
            loc.add_range(t, log.anchors.ids[0], np.nan)  # type: ignore[union-attr]
            loc.add_range(np.array([t, t]), [log.anchors.ids[1]] * 2, [0.0, -1.0])  # type: ignore[union-attr]
        if n == len(arrivals) // 2:
            _feed(loc, log, s, i)  # the same sample twice: an exact duplicate
            _feed(loc, log, 0, 0, t=t_mid - 1_000_000_000)  # a second late: beyond the window
    loc.finish()
    assert dict(loc.skipped) == {
        skip_non_finite("imu"): 1, skip_non_finite("wheel"): 1, SKIP_UNKNOWN_ANCHOR: 1,
        SKIP_NON_FINITE_RANGE: 1, SKIP_NON_POSITIVE_RANGE: 2,
        skip_duplicate(["imu", "wheel", "uwb"][arrivals[len(arrivals) // 2][2]]): 1,
        SKIP_LATE: 1}
    assert loc.report()["skipped_samples"][SKIP_LATE] == 1
    _assert_same(loc, case.run)


def test_batches_equal_samples_and_queries_before_the_start(case: Case) -> None:
    """test that array batches give the same poses, and what pose() answers before the
    first epoch, before the first fix, between epochs and after the newest"""
    log = case.log
    assert log.imu is not None and log.wheel is not None and log.ranges is not None
    assert log.anchors is not None
    # one-second batches per stream: the streams are up to 1 s out of order with each other
    loc = uwbfuse.Localizer(Config(), log.anchors, reorder_window_s=1.0)
    assert loc.latest() is None and loc.pose(0) is None
    t0 = int(log.time_span_ns()[0])
    ids = np.array(log.anchors.ids, dtype=object)[log.ranges.anchor]
    edges = t0 + NS_PER_S * np.arange(0, 40)  # one-second batches, streams interleaved
    for a, b in itertools.pairwise(edges):
        for s, st in ((0, log.imu), (1, log.wheel), (2, log.ranges)):
            sel = (st.t_ns >= a) & (st.t_ns < b)
            if s == 0:
                loc.add_imu(st.t_ns[sel], log.imu.gyro[sel], log.imu.accel[sel])
            elif s == 1:
                loc.add_wheel(st.t_ns[sel], log.wheel.v[sel], log.wheel.omega[sel])
            else:
                loc.add_range(st.t_ns[sel], ids[sel], log.ranges.range[sel])
        if a == t0:
            # one second in, standing still: the first epoch has no pose (no fix yet) or a
            # provisional one; before the first epoch there is none
            first = loc.pose(t0)
            assert first is None or first.provisional
            assert loc.pose(t0 - 1) is None
    loc.finish()
    assert not loc.skipped
    _assert_same(loc, case.run)
    traj = case.run.trajectory
    # between epochs: the newest epoch at or before t; float seconds are accepted
    mid = int(traj.t_ns[100]) + 40_000_000
    p = loc.pose(mid / NS_PER_S)
    assert p is not None and p.t_ns == traj.t_ns[100]
    assert loc.pose(int(traj.t_ns[-1]) + 2 * loc.period_ns) is None  # not known yet
    with pytest.raises(LocalizerError):
        loc.add_imu(int(traj.t_ns[-1]) + 1, [0.0, 0.0, 0.0], [0.0, 0.0, 9.81])  # finished


def test_bad_arguments_are_one_line_errors() -> None:
    """test that malformed arguments, offline methods and a missing anchor map raise
    uwbfuse errors, not tracebacks from numpy"""
    anchors = {"A0": [0.0, 0.0, 1.5], "A1": [10.0, 0.0, 1.5], "A2": [0.0, 8.0, 1.5]}
    loc = uwbfuse.Localizer(anchors=anchors)
    with pytest.raises(LocalizerError, match="shape"):
        loc.add_imu(1, [0.0, 0.0], [0.0, 0.0, 9.81])
    with pytest.raises(LocalizerError, match="anchor ids"):
        loc.add_range(np.array([1, 2]), ["A0"], [1.0, 2.0])
    with pytest.raises(LocalizerError, match="offline"):
        uwbfuse.Localizer(anchors=anchors, method="batch")
    with pytest.raises(AnchorMapError):
        uwbfuse.Localizer()
    loc.add_range(7, 7475, 3.0)  # an integer id is its decimal text: unknown here
    assert loc.skipped[SKIP_UNKNOWN_ANCHOR] == 1


def test_imu_and_uwb_without_wheels_sample_by_sample_equals_run(tmp_path: Path) -> None:
    """test that a vehicle without wheels (IMU + UWB: isam2 solves every keyframe under
    `graph.update_every = "auto"`) gets run's isam2 positions bit for bit when fed one
    sample at a time with `sensors=("imu", "uwb")`"""
    from dataclasses import replace

    path = tmp_path / "imu_uwb.mcap"
    write_contract_log(path, replace(simulate("warehouse", duration_s=20.0, seed=3), wheel=None))
    run = run_log(path, Method.ISAM2, Config(), tum_out=tmp_path / "a.tum")
    # one iSAM2 update per keyframe
    assert run.report["initialised"] is True
    assert run.report["update_latency_ms"]["n"] == run.report["keyframes"]
    log = read_log(path, Config())
    assert log.imu is not None and log.ranges is not None and log.anchors is not None
    assert log.wheel is None
    loc = uwbfuse.Localizer(Config(), log.anchors, sensors=("imu", "uwb"), history_s=60.0)
    ev = sorted([(int(t), 0, i) for i, t in enumerate(log.imu.t_ns.tolist())]
                + [(int(t), 2, i) for i, t in enumerate(log.ranges.t_ns.tolist())])
    for _, s, i in ev:
        if s == 0:
            loc.add_imu(log.imu.t_ns[i], log.imu.gyro[i], log.imu.accel[i])
        else:
            loc.add_range(log.ranges.t_ns[i], log.anchors.ids[int(log.ranges.anchor[i])],
                          log.ranges.range[i])
    loc.finish()
    assert not loc.skipped
    got = np.array([loc.pose(int(t)).position for t in run.trajectory.t_ns.tolist()])
    np.testing.assert_array_equal(got, run.trajectory.position)
    assert loc.report()["initialised"] is True
