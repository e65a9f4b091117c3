# SPDX-License-Identifier: BSD-3-Clause
"""Pose covariances of the filters (`PoseEstimate.covariance`, ROS order, map axes)."""

from __future__ import annotations

import numpy as np
import pytest

from uwbfuse.config import Config
from uwbfuse.estimator import Method
from uwbfuse.pipeline import estimate
from uwbfuse.sim.simulator import simulate
from uwbfuse.streams import UNKNOWN_VARIANCE, PoseStream, SensorLog

CHI2_2_95 = 5.991  # chi-square 95 % quantile, 2 degrees of freedom


@pytest.fixture(scope="module")
def room() -> SensorLog:
    return simulate("room", duration_s=40.0, seed=4)


def _share_inside(traj: PoseStream, log: SensorLog, t_from: int) -> float:
    gt = log.ground_truth
    assert gt is not None and traj.covariance is not None
    sel = traj.t_ns >= t_from
    ref = np.column_stack([np.interp(traj.t_ns[sel], gt.t_ns, gt.position[:, k])
                           for k in range(2)])
    e = traj.position[sel, :2] - ref
    c = traj.covariance[sel, :2, :2]
    d2 = np.einsum("ni,ni->n", e, np.linalg.solve(c, e[:, :, None])[:, :, 0])
    return float(np.mean(d2 <= CHI2_2_95))


@pytest.mark.parametrize("method", [Method.EKF, Method.UKF])
def test_imu_filters_report_a_full_pose_covariance(room: SensorLog, method: Method) -> None:
    """test that ekf/ukf poses carry a symmetric positive definite 6x6 covariance after the
    start, and that the 2-D errors of a room log lie inside its 95 % ellipse most of the time
    (not grossly overconfident; 0.85-0.99 is not reached on every log: docs/results.md)"""
    res = estimate(room, method, Config())
    cov = res.trajectory.covariance
    assert cov is not None and cov.shape == (len(res.trajectory), 6, 6)
    t0 = res.report["initialised_at_ns"]
    after = cov[res.trajectory.t_ns >= t0]
    np.testing.assert_allclose(after, np.swapaxes(after, 1, 2), atol=1e-12)
    assert np.all(np.linalg.eigvalsh(after) > 0.0)
    assert np.all(after[:, [0, 1, 5], [0, 1, 5]] < 1.0)  # x, y, yaw known
    # measured on this 40 s log: 0.81 (ekf), 0.79 (ukf)
    assert _share_inside(res.trajectory, room, t0) > 0.7


def test_wheel_filter_leaves_height_and_tilt_unknown(room: SensorLog) -> None:
    """test that the planar (wheels, no IMU) EKF reports x, y, yaw and UNKNOWN_VARIANCE for
    z, roll and pitch, uncorrelated"""
    log = SensorLog(wheel=room.wheel, ranges=room.ranges, anchors=room.anchors,
                    ground_truth=room.ground_truth, source="sim")
    res = estimate(log, Method.EKF, Config())
    cov = res.trajectory.covariance[res.trajectory.t_ns >= res.report["initialised_at_ns"]]
    for k in (2, 3, 4):
        assert np.all(cov[:, k, k] == UNKNOWN_VARIANCE)
        assert np.all(np.delete(cov[:, k], k, axis=1) == 0.0)
    assert np.all(cov[:, 5, 5] < 0.1) and np.all(cov[:, 0, 0] < 0.1)


@pytest.mark.parametrize("method", [Method.WLS, Method.LKF])
def test_uwb_only_methods_report_their_position_covariance(room: SensorLog,
                                                           method: Method) -> None:
    """test that wls (least-squares covariance) and lkf (its P) report x, y and leave the
    attitude (track direction) unknown"""
    res = estimate(room, method, Config())
    cov = res.trajectory.covariance
    assert cov is not None
    known = cov[:, 0, 0] < UNKNOWN_VARIANCE
    assert known.mean() > 0.9
    assert np.all(cov[known, 0, 0] < 0.05) and np.all(cov[known, 5, 5] == UNKNOWN_VARIANCE)


def test_odom_covariance_grows_from_the_start(room: SensorLog) -> None:
    """test that wheel dead reckoning (no anchors) reports x, y, yaw variances that start at
    zero and grow with the distance driven, z and tilt unknown"""
    log = SensorLog(wheel=room.wheel, source="sim")
    cov = estimate(log, Method.ODOM, Config()).trajectory.covariance
    assert cov is not None
    assert cov[0, 0, 0] < 1e-6 and cov[0, 5, 5] < 1e-6
    assert np.all(np.diff(cov[:, 5, 5]) >= 0.0)
    assert cov[-1, 0, 0] + cov[-1, 1, 1] > 10 * (cov[len(cov) // 10, 0, 0] + 1e-9)
    assert np.all(cov[:, 2, 2] == UNKNOWN_VARIANCE)
