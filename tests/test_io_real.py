# SPDX-License-Identifier: BSD-3-Clause
"""Tests of `read_log` on the real datasets in ../shared/data/real (skipped when absent).

The figures asserted are those of each dataset's README.
"""

from __future__ import annotations

import numpy as np
import pytest

from tests.helpers import real
from tests.test_io_reader import check_fast_matches_generic
from uwbfuse.config import Config, config_from_dict, load_config
from uwbfuse.io.reader import SKIP_INVALID_FLAG, read_log

S = 1e9


def test_labyrinth() -> None:
    """test labyrinth: 233 ranges/odom/GT, 4 metadata anchors, +0.10 m range bias."""
    path = real("labyrinth/labyrinth.mcap")
    cfg = load_config(real("labyrinth/config.toml"))
    no_anchors = config_from_dict(
        {k: v for k, v in cfg.model_dump(mode="json").items() if k != "anchors"})
    got = read_log(path, no_anchors)  # anchors from the uwb_anchors metadata record
    assert got.imu is None
    assert len(got.ranges) == len(got.wheel) == len(got.ground_truth) == 233
    assert dict(got.report.messages) == {"/uwb/range": 233, "/wheel_odom": 233,
                                         "/ground_truth": 233}
    assert not got.report.skipped
    assert got.anchors.ids == ("105", "107", "108", "109")
    np.testing.assert_allclose(got.anchors.positions, [list(cfg.anchors[a]) for a in
                                                       got.anchors.ids])
    assert got.ranges.t_ns[0] / S == pytest.approx(0.128, abs=1e-3)
    assert got.ranges.t_ns[-1] / S == pytest.approx(29.902, abs=1e-3)
    np.testing.assert_array_equal(got.ranges.t_ns, got.ground_truth.t_ns)
    assert np.bincount(got.ranges.anchor).tolist() == [58, 59, 58, 58]
    true = np.linalg.norm(got.ground_truth.position[:, :2]
                          - got.anchors.positions[got.ranges.anchor, :2], axis=1)
    assert np.median(got.ranges.range - true) == pytest.approx(0.104, abs=0.005)
    assert not got.ground_truth.has_orientation
    path_len = np.sum(np.linalg.norm(np.diff(got.ground_truth.position, axis=0), axis=1))
    assert path_len == pytest.approx(9.25, abs=0.01)
    # the same with [anchors] from config.toml
    np.testing.assert_array_equal(read_log(path, cfg).ranges.range, got.ranges.range)


def test_isas_walk1() -> None:
    """test ISAS-Walk1: custom RTLSStick array ranges with the ra flag, 82 Hz IMU."""
    path = real("isas-walk1/ISAS-Walk1")
    cfg = load_config(real("isas-walk1/config.toml"))
    got = read_log(path, cfg)
    assert got.report.messages == {
        "/vive/transform/tracker_1_ref": 3168, "/waveshare_sense_hat_b": 4839,
        "/rtls_flares": 970, "/rtls_pose": 970, "/anchor_list": 970}
    assert len(got.imu) == 4839
    assert got.wheel is None and got.ground_truth is None
    assert got.report.skipped[SKIP_INVALID_FLAG] == 970 * 5 - 4266
    assert np.bincount(got.ranges.anchor).tolist() == [891, 817, 849, 861, 848]
    assert got.anchors.ids == ("7475", "9524", "10548", "15155", "20276")
    span = (got.imu.t_ns[-1] - got.imu.t_ns[0]) / S
    assert span == pytest.approx(59.1, abs=0.1)
    assert np.median(np.diff(got.imu.t_ns)) / S == pytest.approx(1 / 81.9, rel=0.05)
    rest = (got.imu.t_ns - got.imu.t_ns[0]) / S < 4.0
    assert np.linalg.norm(got.imu.accel[rest], axis=1).mean() == pytest.approx(9.98, abs=0.02)
    assert np.max(got.ranges.range) > 23.0  # the gross outlier on anchor 15155 is kept
    # range offsets are subtracted: compare against the raw reading without them
    raw_cfg = config_from_dict({**cfg.model_dump(mode="json"),
                                "uwb": {**cfg.uwb.model_dump(mode="json"), "range_offset": {}}})
    raw = read_log(path, raw_cfg)
    off = np.array([cfg.uwb.range_offset[a] for a in got.anchors.ids])
    np.testing.assert_allclose(raw.ranges.range - got.ranges.range, off[got.ranges.anchor],
                               atol=1e-9)


def test_isas_ground_truth_transform() -> None:
    """test that the Vive TransformStamped topic reads as ground truth when configured."""
    path = real("isas-walk1/ISAS-Walk1")
    cfg = config_from_dict({"topics": {"ground_truth": "/vive/transform/tracker_1_ref"}})
    got = read_log(path, cfg)
    assert len(got.ground_truth) == 3168
    assert got.ground_truth.has_orientation
    span = (got.ground_truth.t_ns[-1] - got.ground_truth.t_ns[0]) / S
    assert span == pytest.approx(63.34, abs=0.01)


def test_jackal() -> None:
    """test jackal: zstd rosbag2, IMU and wheels at 50 Hz, no anchors, README headings."""
    path = real("jackal-imu-odom/test2")
    got = read_log(path, load_config(real("jackal-imu-odom/config.toml")))
    assert len(got.imu) == 3061 and len(got.wheel) == 3060
    assert got.ranges is None and got.anchors is None and got.ground_truth is None
    assert got.imu.t_ns[0] / S == pytest.approx(47.58)
    assert got.imu.t_ns[-1] / S == pytest.approx(108.78, abs=0.01)
    assert np.median(np.diff(got.wheel.t_ns)) / S == pytest.approx(0.02)
    assert np.median(np.diff(got.imu.t_ns)) / S == pytest.approx(0.02)
    dt_w, dt_i = np.diff(got.wheel.t_ns) / S, np.diff(got.imu.t_ns) / S
    assert np.degrees(np.sum(got.wheel.omega[1:] * dt_w)) == pytest.approx(2044, abs=5)
    assert np.degrees(np.sum(got.imu.gyro[1:, 2] * dt_i)) == pytest.approx(275, abs=3)
    assert np.max(np.abs(got.wheel.v)) == pytest.approx(2.0, abs=0.1)
    assert np.mean(got.imu.accel[:, 2]) == pytest.approx(9.8, abs=0.1)


def test_jackal_default_topics_missing() -> None:
    """test that jackal with the default topics is an error listing its real topics."""
    from uwbfuse.errors import LogReadError

    with pytest.raises(LogReadError, match="/jackal_velocity_controller/odom"):
        read_log(real("jackal-imu-odom/test2"), Config())


@pytest.mark.parametrize(("rel", "n"), [
    ("labyrinth/labyrinth.mcap", 699),
    ("isas-walk1/ISAS-Walk1/ISAS-Walk1.mcap", 3168 + 4839 + 970),
    ("jackal-imu-odom/test2/test2.mcap", 6121),
])
def test_fast_decoder_matches_generic_on_real_logs(rel: str, n: int) -> None:
    """test that every fixed-layout message of the real logs decodes the same both ways."""
    assert check_fast_matches_generic(real(rel)) == n
