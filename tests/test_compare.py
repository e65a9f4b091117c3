# SPDX-License-Identifier: BSD-3-Clause
from pathlib import Path

import numpy as np
import pytest

from uwbfuse.compare import parse_methods, run_methods
from uwbfuse.config import Config
from uwbfuse.errors import ConfigError
from uwbfuse.plots import plot_comparison
from uwbfuse.sim.simulator import simulate
from uwbfuse.streams import SensorLog


@pytest.fixture(scope="module")
def room_log() -> SensorLog:
    return simulate("room", duration_s=30.0, seed=3)


def test_parse_methods_rejects_unknown() -> None:
    """test that an unknown method name is a config error naming it"""
    assert [m.value for m in parse_methods("odom, imu")] == ["odom", "imu"]
    with pytest.raises(ConfigError, match="'kalman'"):
        parse_methods("odom,kalman")


def test_failed_method_gets_its_own_row(room_log: SensorLog) -> None:
    """test that a method that cannot run fails its row and the others still run"""
    no_anchors = SensorLog(
        imu=room_log.imu, wheel=room_log.wheel, ranges=room_log.ranges, anchors=None,
        ground_truth=room_log.ground_truth, source="room-without-anchors",
    )
    rows = run_methods(no_anchors, parse_methods("wls,odom"), Config(), max_dt=0.05)
    assert [r.status for r in rows] == ["failed", "ok"]
    assert "anchor" in rows[0].error
    assert rows[1].metrics is not None and rows[1].metrics.coverage > 0.9


def test_plots_are_written(room_log: SensorLog, tmp_path: Path) -> None:
    """test that the four comparison plots are written as PNG files"""
    rows = run_methods(room_log, parse_methods("odom,imu"), Config(), max_dt=0.05)
    files = plot_comparison(room_log, rows, Config(), tmp_path)
    names = sorted(p.name for p in files)
    assert names == ["error_cdf.png", "error_vs_time.png", "range_residuals.png",
                     "trajectories.png"]
    for p in files:
        assert p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert not list(tmp_path.glob(".*tmp*"))


def test_compare_with_ground_truth_in_another_frame(room_log: SensorLog, tmp_path: Path) -> None:
    """test that --gt with se3 alignment scores a log whose GT lives in another frame"""
    from dataclasses import replace

    from scipy.spatial.transform import Rotation

    from uwbfuse.compare import compare_log
    from uwbfuse.io.tum import write_tum
    from uwbfuse.io.writer import write_contract_log
    from uwbfuse.streams import PoseStream

    gt = room_log.ground_truth
    assert gt is not None
    rot = Rotation.from_euler("z", 70, degrees=True)
    moved = PoseStream(gt.t_ns, rot.apply(gt.position) + np.array([5.0, -3.0, 1.0]),
                       (rot * Rotation.from_quat(gt.quat_xyzw)).as_quat())
    write_tum(tmp_path / "gt.tum", moved)
    write_contract_log(tmp_path / "log.mcap", replace(room_log, ground_truth=None))
    res = compare_log(tmp_path / "log.mcap", "wls", out_dir=tmp_path / "out",
                      gt_path=tmp_path / "gt.tum", align="se3")
    aligned = res.rows[0].metrics
    assert aligned is not None and aligned.ate_2d.rmse < 0.15
    res = compare_log(tmp_path / "log.mcap", "wls", out_dir=tmp_path / "out2",
                      gt_path=tmp_path / "gt.tum")
    assert res.rows[0].metrics is not None and res.rows[0].metrics.ate_2d.rmse > 1.0
