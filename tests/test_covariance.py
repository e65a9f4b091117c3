# SPDX-License-Identifier: BSD-3-Clause
"""Pose covariances: the GTSAM -> ROS conversion, the carry along a motion, and the
consistency of the reported 2-D position ellipses on simulated logs."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from uwbfuse.config import Config
from uwbfuse.estimator import Method
from uwbfuse.graph.covariance import blend, carry, to_map
from uwbfuse.graph.offline import observed_information_share
from uwbfuse.graph.uwb import los_subset_search
from uwbfuse.nlos import NlosModel
from uwbfuse.pipeline import estimate
from uwbfuse.sim.simulator import SimResult, simulate_with_truth
from uwbfuse.streams import UNKNOWN_VARIANCE, PoseStream

CHI2_2DOF_95 = 5.991  # chi-square quantile, 2 degrees of freedom, p = 0.95

# The model told the simulator's sensors (`sim.scenarios.Scenario`: wheel noise 0.01 m/s
# and 0.01 rad/s per sample, the IMU's own densities) and anchor offsets drawn with the
# spread of the batch prior on them (U(+-0.035 m): std 0.02 m): the test checks the
# covariance the graph derives from its model, not the defaults' margins for real
# encoders and MEMS (wider than the simulator's: there the ellipses are conservative).
MATCHED = {"wheel": {"sigma_v": 0.01, "sigma_omega": 0.01, "sigma_lateral": 0.005},
           "graph": {"imu_noise_inflation": 1.0}}
OFFSETS = {"anchor_offset_max": 0.035}
# s: long enough for batch's range-model choice to settle on the mixture the simulator
# follows (at 30 s the room's seed 2 is fitted with the robust model, 7x the error)
DURATION_S = 45.0


def _mc_map_covariance(rot: np.ndarray, p: np.ndarray, cov_tangent: np.ndarray,
                       d_rot: np.ndarray, d_p: np.ndarray, n: int = 40000) -> np.ndarray:
    """Monte Carlo ROS covariance of a * delta for a = (rot, p) perturbed on the right by
    N(0, cov_tangent) in GTSAM's (rot, trans) body-frame tangent."""
    rng = np.random.default_rng(3)
    xi = rng.multivariate_normal(np.zeros(6), cov_tangent, size=n)
    r_a = Rotation.from_matrix(rot) * Rotation.from_rotvec(xi[:, :3])
    p_a = p + xi[:, 3:] @ rot.T
    r_b = r_a * Rotation.from_matrix(d_rot)
    p_b = p_a + r_a.apply(d_p)
    mean_r = Rotation.from_matrix(rot @ d_rot)
    dtheta = (r_b * mean_r.inv()).as_rotvec()  # map-axes rotation error
    dp = p_b - (p + rot @ d_p)
    return np.cov(np.hstack([dp, dtheta]).T)


def test_to_map_turns_body_axes_into_map_axes() -> None:
    """test that a body-x translation variance and a body-x rotation variance of a pose
    yawed by 90 deg become map-y variances, in ROS order (trans, rot)"""
    rot = Rotation.from_euler("z", 90, degrees=True).as_matrix()
    cov = np.diag([0.04, 0.0, 0.0, 0.09, 0.0, 0.0])  # GTSAM (rot x, y, z, trans x, y, z)
    ros = to_map(rot, cov)
    np.testing.assert_allclose(np.diag(ros), [0.0, 0.09, 0.0, 0.0, 0.04, 0.0], atol=1e-12)
    assert ros.shape == (6, 6)
    assert to_map(rot[None], cov[None]).shape == (1, 6, 6)


def test_carry_matches_monte_carlo() -> None:
    """test that the covariance carried along a motion (lever arm, rotation in map axes)
    matches a Monte Carlo of the same perturbed pose composed with the same motion"""
    rot = Rotation.from_euler("zyx", [40, 3, -2], degrees=True).as_matrix()
    p = np.array([5.0, -2.0, 0.3])
    a = np.diag([1e-4, 2e-4, 4e-4, 4e-4, 1e-4, 1e-4])
    a[2, 3] = a[3, 2] = 1e-4  # yaw correlated with body-x position
    d_rot = Rotation.from_euler("z", 30, degrees=True).as_matrix()
    d_p = np.array([1.5, 0.4, 0.0])
    expected = _mc_map_covariance(rot, p, a, d_rot, d_p)
    got = carry(to_map(rot, a), p, (p + rot @ d_p)[None])[0]
    np.testing.assert_allclose(got, expected, atol=2e-5)
    # the carried position variance grows with the lever arm under the yaw uncertainty
    assert got[0, 0] + got[1, 1] > to_map(rot, a)[0, 0] + to_map(rot, a)[1, 1]


def test_blend_is_linear_between_keyframes() -> None:
    """test that interpolated covariances blend the keyframes' linearly"""
    c0, c1 = np.eye(6) * 1e-4, np.eye(6) * 3e-4
    out = blend(np.stack([c0, c0]), np.stack([c1, c1]), np.array([0.0, 0.5]))
    np.testing.assert_allclose(out[0], c0)
    np.testing.assert_allclose(out[1], np.eye(6) * 2e-4)


def test_missing_information_spares_certain_classes() -> None:
    """test that a range whose LOS/NLOS class is certain keeps its full weight in the
    marginals and an ambiguous one (g = 0.5, the classes far apart) loses it"""
    share = observed_information_share(np.array([0.0, 0.0, 0.0, 0.1]),
                                       np.array([-0.3, -0.3, -0.3, -0.2]),
                                       np.array([0.0, 1.0, 0.5, 0.02]), 0.05, 0.07)
    np.testing.assert_allclose(share[:3], [1.0, 1.0, 0.0])
    assert 0.0 < share[3] < 1.0


def test_shift_moment_grows_with_the_los_nlos_ambiguity() -> None:
    """test that a window whose ranges fit LOS reports a small shift spread and one whose
    anchor reads 0.2 m long (NLOS or a shifted track: the data cannot tell well) a spread
    of the size of the shift"""
    cfg = Config()
    mix = NlosModel.from_config(cfg)
    rng = np.random.default_rng(0)
    ang = np.array([0.3, 1.9, 3.5, 5.0])  # four anchors around the tag
    anchor = np.repeat(np.arange(4), 40)
    u = np.stack([np.cos(ang), np.sin(ang)], 1)[anchor]
    spread = []
    for bump in (0.0, 0.2):
        r = rng.normal(0.0, mix.sigma_los, len(anchor))
        r[anchor == 0] += bump
        hyp = los_subset_search(anchor, r, u, np.zeros(len(r)), mix)
        assert hyp is not None
        spread.append(float(np.sqrt(np.trace(hyp.shift_moment))))
    assert spread[0] < 0.05
    assert spread[1] > 0.1


def _xy_mahalanobis(traj: PoseStream, sim: SimResult) -> np.ndarray:
    """Squared 2-D Mahalanobis error of every pose from the first motion on that has a
    known xy covariance."""
    gt = sim.log.ground_truth
    assert traj.covariance is not None
    t_motion = int(gt.t_ns[np.argmax(sim.moving)])
    sel = (traj.t_ns >= t_motion) & (traj.covariance[:, 0, 0] < UNKNOWN_VARIANCE)
    t = traj.t_ns[sel]
    err = np.column_stack([traj.position[sel, i] - np.interp(t, gt.t_ns, gt.position[:, i])
                           for i in range(2)])
    cov = traj.covariance[sel, :2, :2]
    return np.einsum("ni,nij,nj->n", err, np.linalg.inv(cov), err)


@pytest.mark.parametrize("method", [Method.BATCH, Method.ISAM2_SMOOTHED, Method.ISAM2],
                         ids=lambda m: m.value)
def test_graph_methods_report_a_covariance_per_pose(method: Method) -> None:
    """test that the graph methods give every output pose a symmetric positive definite
    covariance, known (not UNKNOWN_VARIANCE) in x, y once the graph runs"""
    sim = simulate_with_truth("room", duration_s=15.0, seed=1)
    res = estimate(sim.log, method, Config())
    traj = res.trajectory
    assert traj.covariance is not None and traj.covariance.shape == (len(traj), 6, 6)
    np.testing.assert_allclose(traj.covariance, traj.covariance.transpose(0, 2, 1))
    assert np.all(np.linalg.eigvalsh(traj.covariance) > 0)
    started = traj.t_ns >= res.report["first_keyframe_t_ns"]
    xy = traj.covariance[started][:, [0, 1], [0, 1]]
    assert np.all(xy < 1.0), "a running graph knows its position to better than 1 m"


def test_covariance_off_reports_none() -> None:
    """test that `graph.marginal_covariances = false` skips the marginals"""
    sim = simulate_with_truth("room", duration_s=15.0, seed=1)
    cfg = Config.model_validate({"graph": {"marginal_covariances": False}})
    res = estimate(sim.log, Method.BATCH, cfg)
    cov = res.trajectory.covariance
    # only the causal head (the UWB fallback's, if it reports one) may carry a covariance
    if cov is not None:
        final = res.trajectory.t_ns >= res.report["first_keyframe_t_ns"]
        assert np.all(cov[final][:, [0, 1], [0, 1]] == UNKNOWN_VARIANCE)


def _pooled_share(method: Method, scenarios: list[str], seeds: list[int]) -> float:
    cfg = Config.model_validate(MATCHED)
    d2 = []
    for scenario in scenarios:
        for seed in seeds:
            sim = simulate_with_truth(scenario, duration_s=DURATION_S, seed=seed, **OFFSETS)
            traj = estimate(sim.log, method, cfg).trajectory
            if traj.covariance is None:
                pytest.skip(f"{method.value} reports no pose covariance")
            d2.append(_xy_mahalanobis(traj, sim))
    return float(np.mean(np.concatenate(d2) < CHI2_2DOF_95))


@pytest.mark.slow
@pytest.mark.parametrize("method", [
    Method.BATCH,
    # the EKF reports the consider covariance (`filters.consider`): measured pooled 0.963
    # (room 1.000 / 1.000 / 0.995, factory 0.886 / 0.933 / 0.965; its own P gave 0.797)
    Method.EKF,
    pytest.param(Method.UKF, marks=pytest.mark.xfail(
        reason="ukf: its consider covariance by statistical linearisation gives pooled "
        "0.786 (its own P 0.617): on factory its errors exceed the EKF's (ATE 0.12-0.13 "
        "against 0.08-0.11 m) at a smaller reported spread")),
], ids=lambda m: m.value)
def test_95_percent_ellipse_holds_95_percent_of_the_errors(method: Method) -> None:
    """test that 85-99 % of the 2-D position errors (room and factory, 3 seeds x 45 s,
    pooled) lie inside the reported 95 % ellipse"""
    share = _pooled_share(method, ["room", "factory"], [0, 1, 2])
    assert 0.85 <= share <= 0.99, f"{method.value}: {share:.3f} inside the 95 % ellipse"


@pytest.mark.slow
@pytest.mark.xfail(reason="warehouse: NLOS ranges of small excess (the simulator's N(0.11, "
                   "0.15) m, slow AR(1)) that EM classifies LOS with confidence bias the "
                   "track by ~0.1 m for tens of seconds; the assignment spread covers "
                   "some of it (45 s: seed 0 0.12, seed 1 0.93)")
def test_batch_ellipse_under_warehouse_nlos() -> None:
    """test that batch's 95 % ellipse holds in the warehouse (two of four anchors
    blocked for most of the log)"""
    share = _pooled_share(Method.BATCH, ["warehouse"], [0, 1])
    assert 0.85 <= share <= 0.99, f"batch: {share:.3f} inside the 95 % ellipse"


def test_run_computes_the_marginals_only_for_outputs_that_carry_them(tmp_path):
    """Test that under `graph.marginal_covariances = "auto"` a run writing only the TUM
    skips the marginals (unknown covariance), and one writing --cov-out gets them."""
    from uwbfuse.io.writer import write_contract_log
    from uwbfuse.pipeline import run_log
    from uwbfuse.sim.simulator import simulate

    log = tmp_path / "room.mcap"
    write_contract_log(log, simulate("room", 20.0, 0))
    def known_share(res) -> float:  # graph epochs (after its start) with a real xy variance
        traj = res.trajectory
        graph = traj.t_ns > res.report["init_t_ns"] + 10**9
        assert np.count_nonzero(graph) > 50
        if traj.covariance is None:
            return 0.0
        return float(np.mean(traj.covariance[graph, 0, 0] < 1.0))

    plain = run_log(log, Method.ISAM2, Config(), tum_out=tmp_path / "a.tum")
    wanted = run_log(log, Method.ISAM2, Config(), tum_out=tmp_path / "b.tum",
                     cov_out=tmp_path / "b.csv")
    assert known_share(plain) == 0.0
    assert known_share(wanted) > 0.95
    np.testing.assert_allclose(plain.trajectory.position, wanted.trajectory.position)
