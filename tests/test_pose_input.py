# SPDX-License-Identifier: BSD-3-Clause
"""External pose input (role `pose`): reading, bad input, config, every sensor subset."""

from __future__ import annotations

import dataclasses
import math
import tomllib
from functools import cache
from pathlib import Path

import numpy as np
import pytest

from uwbfuse.cli import main
from uwbfuse.config import Config, config_from_dict
from uwbfuse.estimator import Method
from uwbfuse.eval.evaluate import evaluate
from uwbfuse.io import cdr_fast, msgdefs
from uwbfuse.io.mcap_write import ChannelDef, SchemaDef, write_mcap
from uwbfuse.io.pose_input import SKIP_BAD_COVARIANCE, floor_covariance
from uwbfuse.io.reader import read_log, skip_non_finite
from uwbfuse.io.tum import read_tum
from uwbfuse.io.writer import write_contract_log
from uwbfuse.pipeline import estimate
from uwbfuse.sim.simulator import simulate, simulate_with_truth
from uwbfuse.streams import PoseStream, SensorLog, WheelStream

CONTRACT = Path("/work/shared/CONTRACT.md")
T0 = 1_700_000_000_000_000_000


def _poses(n: int = 20) -> PoseStream:
    t = T0 + np.arange(n, dtype=np.int64) * 100_000_000
    pos = np.column_stack([np.linspace(0, 2, n), np.linspace(1, 3, n), np.zeros(n)])
    yaw = np.linspace(0.1, 0.5, n)
    quat = np.column_stack([np.zeros(n), np.zeros(n), np.sin(yaw / 2), np.cos(yaw / 2)])
    cov = np.tile(np.diag([0.04**2, 0.03**2, 0.0, 0.0, 0.0, 0.02**2]), (n, 1, 1))
    return PoseStream(t, pos, quat, True, cov)


def _wheels(n: int = 100) -> WheelStream:
    t = T0 + np.arange(n, dtype=np.int64) * 20_000_000
    return WheelStream(t, np.full(n, 0.5), np.zeros(n))


def _write_pose_log(path: Path, poses: PoseStream, *, stamped: bool = False,
                    topic: str = "/localization/pose") -> None:
    """A log with wheels and poses on `topic` (PoseWithCovarianceStamped, or PoseStamped)."""
    if not stamped:
        log = SensorLog(wheel=_wheels(), pose=poses)
        from uwbfuse.config import Topics

        write_contract_log(path, log, topics=Topics(pose=topic))
        return
    w = _wheels()
    type_name = msgdefs.POSE_STAMPED
    datas = (cdr_fast.encode_odometry(w.t_ns, w.v, w.omega)
             + cdr_fast.encode_pose_stamped(poses.t_ns, poses.position, poses.quat_xyzw))
    stamps = np.concatenate([w.t_ns, poses.t_ns])
    which = np.concatenate([np.zeros(len(w), int), np.ones(len(poses), int)])
    order = np.argsort(stamps, kind="stable")
    schemas = [SchemaDef(t, "ros2msg", msgdefs.schema_text(t).encode())
               for t in (msgdefs.ODOMETRY, type_name)]
    channels = [ChannelDef("/wheel_odom", "cdr", 0), ChannelDef(topic, "cdr", 1)]
    with path.open("wb") as f:
        write_mcap(f, schemas=schemas, channels=channels, channel=which[order],
                   log_time=stamps[order], datas=[datas[i] for i in order.tolist()])


def test_reads_pose_with_covariance_and_floors_it(tmp_path: Path) -> None:
    """test that PoseWithCovarianceStamped poses read back with their covariance, floored
    by [pose] min_sigma_position / min_sigma_rotation where the localiser gave zero"""
    poses = _poses()
    path = tmp_path / "p.mcap"
    _write_pose_log(path, poses)
    got = read_log(path, Config()).pose
    assert got is not None and len(got) == len(poses)
    np.testing.assert_allclose(got.position, poses.position, atol=1e-12)
    np.testing.assert_allclose(np.abs(got.quat_xyzw), np.abs(poses.quat_xyzw), atol=1e-12)
    sd = np.sqrt(np.diagonal(got.covariance[0]))
    np.testing.assert_allclose(sd, [0.04, 0.03, 0.02, 0.01, 0.01, 0.02], atol=1e-9)
    cfg = config_from_dict({"pose": {"min_sigma_position": 0.05, "min_sigma_rotation": 0.03}})
    sd = np.sqrt(np.diagonal(read_log(path, cfg).pose.covariance[0]))
    np.testing.assert_allclose(sd, [0.05, 0.05, 0.05, 0.03, 0.03, 0.03], atol=1e-9)


def test_reads_pose_stamped_with_config_sigmas(tmp_path: Path) -> None:
    """test that PoseStamped poses get [pose] sigma_position / sigma_rotation"""
    poses = _poses()
    path = tmp_path / "p.mcap"
    _write_pose_log(path, poses, stamped=True)
    got = read_log(path, Config()).pose
    assert got is not None and len(got) == len(poses)
    np.testing.assert_allclose(got.position, poses.position)
    sd = np.sqrt(np.diagonal(got.covariance[3]))
    np.testing.assert_allclose(sd, [0.05] * 3 + [0.02] * 3, atol=1e-12)
    cfg = config_from_dict({"pose": {"sigma_position": 0.2, "sigma_rotation": 0.1}})
    sd = np.sqrt(np.diagonal(read_log(path, cfg).pose.covariance[3]))
    np.testing.assert_allclose(sd, [0.2] * 3 + [0.1] * 3, atol=1e-12)


def test_topic_name_from_config(tmp_path: Path) -> None:
    """test that [topics] pose names the pose topic (another name: no pose stream)"""
    path = tmp_path / "p.mcap"
    _write_pose_log(path, _poses(), topic="/amcl_pose")
    assert read_log(path, Config()).pose is None
    got = read_log(path, config_from_dict({"topics": {"pose": "/amcl_pose"}})).pose
    assert got is not None and len(got) == 20


def test_lidar_map_in_map_transform(tmp_path: Path) -> None:
    """test that [extrinsics] lidar_map_in_map carries poses and covariances to the map frame"""
    poses = _poses()
    path = tmp_path / "p.mcap"
    _write_pose_log(path, poses)
    a = math.pi / 2
    cfg = config_from_dict({"extrinsics": {"lidar_map_in_map": [1.0, 2.0, 0.5, 0.0, 0.0,
                                                                 math.sin(a / 2),
                                                                 math.cos(a / 2)]}})
    got = read_log(path, cfg).pose
    p = poses.position
    np.testing.assert_allclose(got.position, np.column_stack(
        [1.0 - p[:, 1], 2.0 + p[:, 0], 0.5 + p[:, 2]]), atol=1e-9)
    yaw_in = 2 * np.arctan2(poses.quat_xyzw[:, 2], poses.quat_xyzw[:, 3])
    yaw_out = 2 * np.arctan2(got.quat_xyzw[:, 2], got.quat_xyzw[:, 3])
    np.testing.assert_allclose(np.angle(np.exp(1j * (yaw_out - yaw_in - a))), 0, atol=1e-9)
    # x and y variances swap under a quarter turn
    np.testing.assert_allclose(got.covariance[0, 0, 0], 0.03**2, rtol=1e-9)
    np.testing.assert_allclose(got.covariance[0, 1, 1], 0.04**2, rtol=1e-9)


def test_bad_pose_messages_are_counted_skips(tmp_path: Path) -> None:
    """test that NaN poses, NaN and non-positive-definite covariances are counted skips"""
    poses = _poses()
    pos, cov = poses.position.copy(), poses.covariance.copy()
    pos[2, 0] = np.nan
    cov[5, 1, 1] = np.nan
    cov[7, 0, 0] = -0.01  # negative variance
    cov[9, 0, 1] = cov[9, 1, 0] = 1.0  # |correlation| > 1: an eigenvalue below zero
    bad = PoseStream(poses.t_ns, pos, poses.quat_xyzw, True, cov)
    path = tmp_path / "p.mcap"
    _write_pose_log(path, bad)
    log = read_log(path, Config())
    assert len(log.pose) == 16
    assert log.report.skipped[skip_non_finite("pose")] == 2
    assert log.report.skipped[SKIP_BAD_COVARIANCE] == 2
    assert not np.isin(poses.t_ns[[2, 5, 7, 9]], log.pose.t_ns).any()


def test_wrong_pose_type_is_a_one_line_error(tmp_path: Path,
                                            capsys: pytest.CaptureFixture[str]) -> None:
    """test that a pose topic of another type stops `run` with exit 2 naming the topic"""
    w = _wheels()
    path = tmp_path / "p.mcap"
    schemas = [SchemaDef(msgdefs.ODOMETRY, "ros2msg", msgdefs.schema_text(msgdefs.ODOMETRY)
                         .encode())]
    channels = [ChannelDef("/wheel_odom", "cdr", 0), ChannelDef("/localization/pose", "cdr", 0)]
    which = np.tile([0, 1], len(w))
    one = cdr_fast.encode_odometry(w.t_ns, w.v, w.omega)
    datas = [d for pair in zip(one, one, strict=True) for d in pair]
    with path.open("wb") as f:
        write_mcap(f, schemas=schemas, channels=channels, channel=which,
                   log_time=np.repeat(w.t_ns, 2), datas=datas)
    code = main(["run", str(path), "--method", "ekf", "-o", str(tmp_path / "e.tum")])
    assert code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "'/localization/pose'" in err[0] and "Odometry" in err[0]


def test_floor_covariance_is_at_least_the_floor() -> None:
    """test that the floored covariance dominates both the floor and the original"""
    rng = np.random.default_rng(0)
    a = rng.normal(size=(50, 6, 6)) * 0.02
    cov = a @ np.swapaxes(a, 1, 2)
    f = np.array([0.02] * 3 + [0.01] * 3)
    out = floor_covariance(cov, f)
    assert np.linalg.eigvalsh(out - cov).min() > -1e-15
    assert np.linalg.eigvalsh(out - np.diag(f**2)).min() > -1e-15


def test_contract_example_config_accepted_for_pose_keys() -> None:
    """test that the contract example's [extrinsics] and [topics] (with pose and
    lidar_map_in_map) parse"""
    text = CONTRACT.read_text() if CONTRACT.exists() else ""
    if "```toml" not in text:
        pytest.skip("contract not available")
    block = text.split("```toml", 1)[1].split("```", 1)[0]
    data = tomllib.loads(block)
    cfg = config_from_dict({k: data[k] for k in ("anchors", "extrinsics", "topics")})
    assert cfg.topics.pose == "/localization/pose"
    assert cfg.extrinsics.lidar_map_in_map == (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0)


# ------------------------------------------------------------------------------------------
# estimation


@cache
def _lidar_log(duration: float = 40.0, seed: int = 3, dropouts: bool = False,
               **kw: float) -> SensorLog:
    """The LiDAR scenario; without its pose dropouts unless asked (a short log would end
    in the first one: the heading through it is then the wheels' and IMU's alone)."""
    if not dropouts:
        kw["pose_dropouts"] = ()  # type: ignore[assignment]
    return simulate("warehouse-lidar", duration, seed, **kw)


def _ate(log: SensorLog, method: Method, cfg: Config | None = None) -> float:
    res = estimate(log, method, cfg or Config(), covariance=False)
    return evaluate(res.trajectory, log.ground_truth).ate_2d.rmse


SUBSETS = {
    "pose+wheel": {"imu": "/none", "uwb": "/none"},
    "pose+imu+wheel": {"uwb": "/none"},
    "pose+imu+uwb": {"wheel_odom": "/none"},
    "pose+wheel+uwb": {"imu": "/none"},
}


@pytest.fixture(scope="module")
def lidar_mcap(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("lidar") / "l.mcap"
    write_contract_log(path, _lidar_log(30.0))
    return path


@pytest.mark.parametrize("subset", sorted(SUBSETS))
@pytest.mark.parametrize("method", ["isam2", "isam2-smoothed", "batch", "ekf", "ukf"])
def test_each_sensor_subset_runs(tmp_path: Path, lidar_mcap: Path, subset: str,
                                 method: str) -> None:
    """test that `uwbfuse run` works on each subset with poses, within a few cm"""
    path = lidar_mcap
    cfg = tmp_path / "c.toml"
    cfg.write_text("[topics]\n" + "".join(f'{k} = "{v}"\n' for k, v in SUBSETS[subset].items()))
    out = tmp_path / "e.tum"
    assert main(["run", str(path), "--method", method, "--config", str(cfg), "-o",
                 str(out)]) == 0
    est = read_tum(out)
    res = evaluate(est, read_log(path, Config()).ground_truth)
    assert len(est) >= 10 * 28
    assert res.ate_2d.rmse < 0.15, res.ate_2d.rmse


def test_wrong_matches_do_not_move_batch() -> None:
    """test that batch with the localiser's wrong matches stays within 5 cm of batch on the
    same log without them (pose + wheels, and with IMU and UWB)"""
    r = simulate_with_truth("warehouse-lidar", 40.0, 3, pose_wrong_rate=0.2, pose_dropouts=())
    assert r.pose_wrong.sum() > 20  # the log has wrong matches
    clean = _lidar_log(40.0, 3, pose_wrong_rate=0.0)
    for drop in ({"imu": None, "ranges": None}, {}):
        a = estimate(dataclasses.replace(r.log, **drop), Method.BATCH, Config(),
                     covariance=False).trajectory
        b = estimate(dataclasses.replace(clean, **drop), Method.BATCH, Config(),
                     covariance=False).trajectory
        n = min(len(a), len(b))
        d = np.linalg.norm(a.position[:n, :2] - b.position[:n, :2], axis=1)
        assert d.max() < 0.05, (drop, d.max())


def test_pose_kernel_config_changes_the_graph() -> None:
    """test that [pose] robust_kernel / kernel_threshold act: without a kernel the wrong
    matches pull batch away"""
    log = dataclasses.replace(_lidar_log(40.0, 3, pose_wrong_rate=0.2), imu=None, ranges=None)
    robust = _ate(log, Method.BATCH)
    plain = _ate(log, Method.BATCH, config_from_dict({"pose": {"robust_kernel": "none"}}))
    loose = _ate(log, Method.BATCH, config_from_dict({"pose": {"kernel_threshold": 30.0}}))
    assert plain > 2 * robust
    assert loose > robust


def test_filters_gate_wrong_matches() -> None:
    """test that ekf/ukf reject wrong matches at the gate, and [pose] gate_probability
    sets how many"""
    log = dataclasses.replace(_lidar_log(40.0, 3, pose_wrong_rate=0.2), ranges=None)
    for method in (Method.EKF, Method.UKF):
        res = estimate(log, method, Config(), covariance=False)
        assert res.report["poses_gated"] > 10
        assert evaluate(res.trajectory, log.ground_truth).ate_2d.rmse < 0.1
        narrow = estimate(log, method, config_from_dict({"pose": {"gate_probability": 0.5}}),
                          covariance=False)
        assert narrow.report["poses_gated"] > res.report["poses_gated"] + 20


def test_uwb_helps_through_a_pose_dropout() -> None:
    """test that on the LiDAR scenario ranges help the filters where the poses drop out"""
    log = _lidar_log(60.0, 1, dropouts=True)
    no_uwb = dataclasses.replace(log, ranges=None)
    for method in (Method.EKF, Method.UKF):
        assert _ate(log, method) < _ate(no_uwb, method)


def test_fast_pose_with_covariance_decoder_matches_mcap_ros2(tmp_path: Path) -> None:
    """test that the vectorised PoseWithCovarianceStamped decode agrees with mcap_ros2"""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    poses = _poses()
    path = tmp_path / "p.mcap"
    _write_pose_log(path, poses)
    items = []
    with path.open("rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for _, _channel, message, ros in reader.iter_decoded_messages(
                topics=["/localization/pose"]):
            items.append((message.data, ros))
    ok, cols = cdr_fast.decode_fixed(msgdefs.POSE_WITH_COVARIANCE_STAMPED,
                                     [d for d, _ in items])
    assert ok.all() and len(items) == len(poses)
    for i, (_, m) in enumerate(items):
        p, q = m.pose.pose.position, m.pose.pose.orientation
        assert tuple(cols["position"][i]) == (p.x, p.y, p.z)
        assert tuple(cols["quat"][i]) == (q.x, q.y, q.z, q.w)
        assert cols["covariance"][i].reshape(36).tolist() == list(m.pose.covariance)
        assert cols["t_ns"][i] == m.header.stamp.sec * 10**9 + m.header.stamp.nanosec
