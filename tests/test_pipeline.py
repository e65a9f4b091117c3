# SPDX-License-Identifier: BSD-3-Clause
"""The contract's output density: >= 10 poses per second from the first motion on."""

import dataclasses

import numpy as np
import pytest

from uwbfuse.config import Config
from uwbfuse.errors import EstimatorError
from uwbfuse.estimator import Method
from uwbfuse.eval.evaluate import evaluate
from uwbfuse.pipeline import estimate
from uwbfuse.sim.simulator import SimResult, simulate_with_truth
from uwbfuse.streams import NS_PER_S

METHODS = [m for m in Method]
# 2-D ATE with the IMU from 8 s on, warehouse seed 2, 30 s, measured 2026-12-01: ekf 0.137,
# isam2 0.173, batch 0.190 m (IMU from the start: 0.131, 0.151, 0.138); tolerances ~1.5x
TOL_LATE_IMU = {Method.EKF: 0.20, Method.ISAM2: 0.26, Method.BATCH: 0.28}
# 2-D ATE with the wheels from 10 s on, warehouse seed 2, 40 s, measured 2026-12-01 (with
# IMU / without): ekf 0.213 / 0.194, isam2 0.222 / 0.211, batch 0.135 / 0.134 m; wheels
# from the start: ekf 0.196 / 0.182, isam2 0.216 / 0.202, batch 0.090 / 0.090 m
TOL_LATE_WHEELS = {Method.EKF: 0.32, Method.ISAM2: 0.33, Method.BATCH: 0.20}


@pytest.fixture(scope="module", params=["factory", "room"])
def sim(request: pytest.FixtureRequest) -> SimResult:
    # factory: 0.5 m/s; room: 0.1 m/s, where the heading takes longest to fix.
    return simulate_with_truth(request.param, duration_s=30.0, seed=5)


@pytest.mark.parametrize("method", METHODS, ids=[m.value for m in METHODS])
def test_poses_from_first_motion_to_the_end(sim: SimResult, method: Method) -> None:
    """test that every method writes >= 10 poses/s, without gaps, from the first motion"""
    gt = sim.log.ground_truth
    t_motion = int(gt.t_ns[np.argmax(sim.moving)])
    t_end = int(sim.log.time_span_ns()[1])
    traj = estimate(sim.log, method, Config()).trajectory
    inside = traj.t_ns[(traj.t_ns >= t_motion) & (traj.t_ns <= t_end)]
    span_s = (t_end - t_motion) / NS_PER_S
    assert len(inside) >= 10 * span_s - 1, f"{len(inside)} poses over {span_s:.1f} s"
    assert inside[0] - t_motion <= 0.1 * NS_PER_S
    assert np.max(np.diff(inside)) <= 0.1 * NS_PER_S + 1
    assert np.all(np.diff(traj.t_ns) > 0)
    assert np.all(np.isfinite(traj.position)) and np.all(np.isfinite(traj.quat_xyzw))


@pytest.mark.parametrize("method", [Method.BATCH, Method.ISAM2_SMOOTHED, Method.ISAM2])
def test_smoothers_cover_the_start_without_wheels(method: Method) -> None:
    """test that smoothers on an IMU + UWB log (no wheels) still cover the first motion"""
    sim = simulate_with_truth("factory", duration_s=30.0, seed=6, streams=("imu", "uwb"))
    gt = sim.log.ground_truth
    t_motion = int(gt.t_ns[np.argmax(sim.moving)])
    traj = estimate(sim.log, method, Config()).trajectory
    assert traj.t_ns[0] <= t_motion + 0.1 * NS_PER_S
    after = traj.t_ns[traj.t_ns >= t_motion]
    assert np.max(np.diff(after)) <= 0.1 * NS_PER_S + 1


class _Scripted:
    """Fake estimator: answers from a script {step index: position or None}."""

    def __init__(self, script: dict[int, tuple[float, float] | None], provisional_until: int = -1):
        self.script = script
        self.k = -1
        self.t = 0
        self.provisional_until = provisional_until

    @property
    def provisional(self) -> bool:
        return self.k <= self.provisional_until

    def add_imu(self, *a: object) -> None: ...
    def add_wheel(self, *a: object) -> None: ...
    def add_ranges(self, *a: object) -> None: ...

    def step(self, t_ns: int) -> None:
        self.k += 1
        self.t = t_ns

    def estimate(self) -> object:
        from uwbfuse.estimator import PoseEstimate

        xy = self.script.get(self.k)
        if xy is None:
            return None
        return PoseEstimate(self.t, np.array([*xy, 0.0]), np.array([0.0, 0.0, 0.0, 1.0]))

    def finish(self) -> None:
        return None

    def report(self) -> dict:
        return {}


@pytest.mark.parametrize(("fallback_xy", "first_fallback_epoch"), [
    ((0.3, 0.0), 10),    # agrees with the standstill fix: answers as soon as the primary stops
    ((9.0, 0.0), 60),    # 9 m off: discredited, the last provisional pose is held 5 s
])
def test_fallback_after_provisional_answers(
    fallback_xy: tuple[float, float], first_fallback_epoch: int
) -> None:
    """test PreStart: provisional answers keep the fallback; in place of a fallback
    that disagreed with them the last provisional pose is held for PROVISIONAL_GRACE_S;
    every epoch has a pose"""
    from uwbfuse.prestart import PreStart

    primary = _Scripted({k: (0.0, 0.0) for k in range(10)}, provisional_until=9)
    fallback = _Scripted({k: fallback_xy for k in range(200)})
    wf = PreStart(primary, fallback)
    answered = []
    for k in range(200):
        wf.step(k * 100_000_000)  # 10 Hz
        est = wf.estimate()
        assert est is not None and est.t_ns == k * 100_000_000
        answered.append(bool(est.position[0] != 0.0))
    assert wf.fallback is not None  # provisional answers never dropped it
    assert answered.index(True) == first_fallback_epoch
    assert all(answered[first_fallback_epoch:])


def test_fallback_fixes_are_averaged_while_the_wheels_stand_still() -> None:
    """test PreStart: while the wheels read still, the fallback answers with the mean of
    its fixes since the standstill began (closer to the point than the fixes are), and
    with its own fix again from the first moving wheel sample on"""
    from uwbfuse.prestart import PreStart

    rng = np.random.default_rng(0)
    fixes = {k: (1.0 + 0.05 * rng.standard_normal(), 2.0) for k in range(100)}
    wf = PreStart(_Scripted({}), _Scripted(fixes))
    got = []
    for k in range(100):
        t = k * 100_000_000
        moving = k >= 60
        wf.add_wheel(np.array([t - 50_000_000, t]), np.full(2, 0.3 if moving else 0.0),
                     np.zeros(2))
        wf.step(t)
        est = wf.estimate()
        assert est is not None
        got.append(float(est.position[0]))
    raw = np.array([fixes[k][0] for k in range(100)])
    assert got[:60] == pytest.approx(np.cumsum(raw[:60]) / np.arange(1, 61))
    assert got[60:] == pytest.approx(raw[60:].tolist())
    assert np.sqrt(np.mean((np.array(got[20:60]) - 1.0) ** 2)) < 0.5 * np.sqrt(
        np.mean((raw[20:60] - 1.0) ** 2))


def test_provisional_pose_is_held_while_the_fallback_has_no_fix() -> None:
    """test PreStart: a fallback without fixes (Plaza1) leaves the last provisional
    pose held until the primary starts, so no epoch after the first motion lacks a pose"""
    from uwbfuse.prestart import PreStart

    script: dict[int, tuple[float, float] | None] = {k: (1.0, 2.0) for k in range(10)}
    script.update({k: (5.0, 5.0) for k in range(150, 200)})  # the primary starts at 150
    primary = _Scripted(script, provisional_until=9)
    wf = PreStart(primary, _Scripted({}))
    got = []
    for k in range(200):
        wf.step(k * 100_000_000)
        est = wf.estimate()
        assert est is not None
        got.append(tuple(est.position[:2]))
    assert got[10:150] == [(1.0, 2.0)] * 140
    assert got[150:] == [(5.0, 5.0)] * 50
    assert wf.report()["held_provisional_epochs"] == 140


@pytest.mark.parametrize(
    ("anchors", "reason"),
    [
        ((("A1", (0.0, 0.0, 1.5)), ("A4", (40.0, 20.0, 1.5))), "ranges from 2 anchor(s) only"),
        ((("N1", (0.0, 0.0, 2.5)), ("N2", (5.0, 0.0, 2.5)), ("N3", (10.0, 0.0, 2.5))),
         "lie on one line in x, y"),
    ],
    ids=["two-anchors", "collinear-anchors"],
)
@pytest.mark.parametrize("method", [Method.ISAM2, Method.BATCH, Method.EKF])
def test_no_fix_from_the_anchors_says_why(anchors: tuple, reason: str, method: Method) -> None:
    """test that a log whose anchors cannot fix a 2-D position fails in one line that says so"""
    log = simulate_with_truth("factory", duration_s=15.0, seed=3, anchors=anchors).log
    with pytest.raises(EstimatorError) as exc:
        estimate(log, method, Config())
    msg = str(exc.value)
    assert "never initialised" in msg and reason in msg and "\n" not in msg
    assert "3 anchors not on one line" in msg


@pytest.mark.parametrize("method", [Method.EKF, Method.ISAM2, Method.BATCH])
def test_imu_that_starts_after_the_wheel_standstill(method: Method) -> None:
    """test that an IMU whose first sample comes after the wheels' standstill (moving by
    then) is levelled from its own first samples instead of from none: finite poses near
    the accuracy with the IMU from the start (they used to be NaN for the EKF, and batch
    and isam2-smoothed had no trajectory)"""
    sim = simulate_with_truth("warehouse", duration_s=30.0, seed=2)
    imu = sim.log.imu
    keep = imu.t_ns >= imu.t_ns[0] + 8 * NS_PER_S  # the wheels stand still for 2 s
    sim.log.imu = dataclasses.replace(
        imu, t_ns=imu.t_ns[keep], gyro=imu.gyro[keep], accel=imu.accel[keep])
    traj = estimate(sim.log, method, Config()).trajectory
    assert np.all(np.isfinite(traj.position)) and np.all(np.isfinite(traj.quat_xyzw))
    ate = evaluate(traj, sim.log.ground_truth).ate_2d.rmse
    assert ate < TOL_LATE_IMU[method], f"{method.value}: {ate:.3f} m"


@pytest.mark.parametrize("streams", [("imu", "wheel", "uwb"), ("wheel", "uwb")],
                         ids=["imu-wheel-uwb", "wheel-uwb"])
@pytest.mark.parametrize("method", [Method.EKF, Method.ISAM2, Method.BATCH])
def test_wheels_that_start_late(streams: tuple[str, ...], method: Method) -> None:
    """test that wheels whose first sample comes 10 s into a moving log do not take the
    start off: the heading and start solves fit only ranges the wheel track covers (with
    the track carried back at constant velocity the start was 2 m and a 7 % range scale off:
    isam2 1.77 m, batch 1.47 m)"""
    sim = simulate_with_truth("warehouse", duration_s=40.0, seed=2, streams=streams)
    w = sim.log.wheel
    keep = w.t_ns >= w.t_ns[0] + 10 * NS_PER_S
    sim.log.wheel = dataclasses.replace(w, t_ns=w.t_ns[keep], v=w.v[keep], omega=w.omega[keep])
    ate = evaluate(estimate(sim.log, method, Config()).trajectory,
                   sim.log.ground_truth).ate_2d.rmse
    assert ate < TOL_LATE_WHEELS[method], f"{method.value}: {ate:.3f} m"


@pytest.mark.parametrize("method", [Method.BATCH, Method.ISAM2_SMOOTHED])
def test_smoothers_on_a_log_too_short_to_start_write_the_provisional_poses(
    method: Method,
) -> None:
    """test that a 3 s log (the graph cannot start: no heading yet) gets the same provisional
    UWB-fix poses from the smoothers as from isam2, with the report saying so, instead of an
    error"""
    log = simulate_with_truth("warehouse", duration_s=3.0, seed=2).log
    causal = estimate(log, Method.ISAM2, Config())
    res = estimate(log, method, Config())
    assert res.report["initialised"] is False
    assert "never started" in res.report["final_trajectory"]
    np.testing.assert_array_equal(res.trajectory.t_ns, causal.trajectory.t_ns)
    np.testing.assert_allclose(res.trajectory.position, causal.trajectory.position)
    assert len(res.trajectory) >= 25
