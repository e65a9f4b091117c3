# SPDX-License-Identifier: BSD-3-Clause
"""Tests of `uwbfuse montecarlo` (uwbfuse.montecarlo): scoring, the table, the cluster run."""

from __future__ import annotations

import csv
import importlib.util
import json
import math
from pathlib import Path

import numpy as np
import pytest

from uwbfuse import fleet
from uwbfuse.config import Config
from uwbfuse.errors import FleetError, SimulationError
from uwbfuse.estimator import Method
from uwbfuse.fleet import config_payload
from uwbfuse.montecarlo import (
    RunSpec,
    StartAlignment,
    align_first_pose,
    errors_at_times,
    montecarlo,
    parse_methods,
    run_montecarlo_job,
    time_label,
)
from uwbfuse.streams import NS_PER_S, PoseStream

HAVE_DASK = importlib.util.find_spec("distributed") is not None
needs_dask = pytest.mark.skipif(
    not HAVE_DASK,
    reason="dask.distributed not installed (pip install 'uwbfuse[fleet]'); CI installs it",
)
pytestmark = pytest.mark.timeout(180)
T0 = 1_700_000_000 * NS_PER_S
CFG = config_payload(Config())


def _line(n: int, yaw: float, offset: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> PoseStream:
    """A straight drive at 1 m/s along `yaw` at 10 Hz, shifted by `offset`."""
    t = T0 + np.arange(n, dtype=np.int64) * (NS_PER_S // 10)
    s = np.arange(n) * 0.1
    pos = np.column_stack([s * math.cos(yaw), s * math.sin(yaw), np.zeros(n)]) + offset
    quat = np.tile([0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2)], (n, 1))
    return PoseStream(t, pos, quat)


def test_errors_at_times_interpolate_and_flag_uncovered_times() -> None:
    """Test that errors are sampled at T s after t0 (2-D or 3-D), NaN outside coverage."""
    gt = _line(301, 0.0)
    shifted = gt.position[:201] + np.array([0.3, 0.4, 1.2])
    est = PoseStream(gt.t_ns[:201], shifted, gt.quat_xyzw[:201])
    e = errors_at_times(est, gt, T0, [5.0, 12.34, 20.0, 25.0])
    assert e[:3] == pytest.approx([0.5, 0.5, 0.5])  # horizontal by default
    assert math.isnan(e[3])
    assert errors_at_times(est, gt, T0, [12.34], dims=3) == pytest.approx([1.3])


def test_align_first_pose_puts_dead_reckoning_on_the_start_pose() -> None:
    """Test that first-pose alignment removes a start offset in position and heading."""
    gt = _line(100, 0.7, (2.0, -1.0, 0.0))
    est = _line(100, 0.0)  # same motion, started at the origin with heading zero
    aligned = align_first_pose(est, gt)
    assert np.abs(aligned.position - gt.position).max() < 1e-9
    assert np.abs(np.abs(np.sum(aligned.quat_xyzw * gt.quat_xyzw, axis=1)) - 1).max() < 1e-9


def test_parse_methods_and_labels() -> None:
    """Test that --methods is parsed in order without duplicates, and bad names fail."""
    assert parse_methods("ekf, imu,ekf") == (Method.EKF, Method.IMU)
    assert parse_methods([Method.ODOM]) == (Method.ODOM,)
    with pytest.raises(FleetError, match="unknown method 'kalman'"):
        parse_methods("ekf,kalman")
    assert time_label(20.0) == "err_20s_m" and time_label(1.5) == "err_1.5s_m"


def test_run_job_isolates_a_crashing_method(monkeypatch: pytest.MonkeyPatch) -> None:
    """Test that one run scores each method and a crashing method fails its row alone."""
    import uwbfuse.pipeline

    real = uwbfuse.pipeline.estimate

    def crash_imu(log: object, method: Method, config: Config) -> object:
        if method is Method.IMU:
            raise RuntimeError("boom")
        return real(log, method, config)

    monkeypatch.setattr(uwbfuse.pipeline, "estimate", crash_imu)
    spec = RunSpec("seed-00004", "room", 21.0, 4, (Method.IMU, Method.ODOM), CFG,
                   (20.0,), StartAlignment.AUTO)
    rows = run_montecarlo_job(spec)
    assert [r["method"] for r in rows] == ["imu", "odom"]
    imu, odom = rows
    assert imu["status"] == "failed" and imu["error"] == "RuntimeError: boom"
    assert "Traceback" in imu["traceback"] and math.isnan(imu[time_label(20.0)])
    assert odom["status"] == "ok" and odom["seed"] == 4
    assert 0 <= odom[time_label(20.0)] < 0.5 and odom["ate_rmse_m"] < 0.5
    # An unknown scenario fails every row of the run, with the simulator's message.
    bad = run_montecarlo_job(RunSpec("x", "nowhere", 5.0, 0, (Method.ODOM,), CFG,
                                     (1.0,), StartAlignment.AUTO))
    assert bad[0]["status"] == "failed" and "nowhere" in bad[0]["error"]


def test_study_checks_arguments_before_starting_a_cluster(tmp_path: Path) -> None:
    """Test that bad arguments raise one clear error and start nothing."""
    with pytest.raises(SimulationError):
        montecarlo("nowhere", runs=1, duration_s=30, methods="odom", out_dir=tmp_path)
    with pytest.raises(FleetError, match="shorter than the first scoring time"):
        montecarlo("room", runs=1, duration_s=10, methods="odom", out_dir=tmp_path)
    with pytest.raises(FleetError, match="--runs"):
        montecarlo("room", runs=0, duration_s=30, methods="odom", out_dir=tmp_path)


def _study(out: Path, **kw: object) -> object:
    return montecarlo("room", runs=3, duration_s=22.0, methods="odom,imu", out_dir=out, **kw)


@needs_dask
def test_study_on_local_cluster_matches_in_process_runs_and_resumes(tmp_path: Path) -> None:
    """Test the LocalCluster study: rows equal in-process runs, Table 5 layout, resume."""
    out = tmp_path / "mc"
    res = _study(out, workers=2)
    assert res.cluster.kind == "local" and res.times_s == (20.0,)
    assert [(r["seed"], r["method"]) for r in res.rows] == [
        (s, m) for s in range(3) for m in ("odom", "imu")
    ]
    assert all(r["status"] == "ok" for r in res.rows)

    # Same numbers as running seed 1 here (workers are separate processes).
    here = run_montecarlo_job(
        RunSpec("seed-00001", "room", 22.0, 1, (Method.ODOM, Method.IMU), CFG,
                (20.0,), StartAlignment.AUTO)
    )
    there = [r for r in res.rows if r["seed"] == 1]
    for a, b in zip(here, there, strict=True):
        assert a[time_label(20.0)] == b[time_label(20.0)]
        assert a["ate_rmse_m"] == b["ate_rmse_m"]

    # Table 5: per time, RMSE over runs per method, improvement over the IMU baseline.
    cols, rows = res.time_table()
    assert cols == ["t_s", "imu_rmse_m", "odom_rmse_m", "odom_vs_imu_pct"]
    e = np.array([r[time_label(20.0)] for r in res.rows if r["method"] == "odom"])
    assert rows[0]["odom_rmse_m"] == pytest.approx(math.sqrt(np.mean(e**2)))
    b, v = rows[0]["imu_rmse_m"], rows[0]["odom_rmse_m"]
    assert rows[0]["odom_vs_imu_pct"] == pytest.approx(100 * (b - v) / b)
    with (out / "montecarlo.csv").open() as f:
        assert [r["t_s"] for r in csv.DictReader(f)] == ["20"]
    with (out / "runs.csv").open() as f:
        assert len(list(csv.DictReader(f))) == 6
    md = (out / "montecarlo.md").read_text()
    assert "| t_s | imu_rmse_m |" in md and "| odom | 3 | 0 |" in md
    assert (out / "config.toml").exists()
    marker = json.loads((out / "runs" / "seed-00002.json").read_text())
    assert marker["seed"] == 2 and len(marker["rows"]) == 2

    # Resume: nothing runs again (no cluster), same table; a damaged marker reruns its seed.
    again = _study(out)
    assert again.cluster.kind == "none" and again.time_table() == res.time_table()
    (out / "runs" / "seed-00002.json").write_text("{")
    seen: list[tuple[int, int]] = []
    third = _study(out, workers=1, progress=lambda d, t, n: seen.append((d, t)))
    assert seen[0] == (2, 3) and seen[-1] == (3, 3)
    assert third.time_table() == res.time_table()


def test_study_inline_without_dask(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Test that without dask the study runs in this process, one run after another."""
    monkeypatch.setattr(fleet, "_import_distributed", lambda: None)
    res = montecarlo("room", runs=2, duration_s=21.0, methods="odom", out_dir=tmp_path)
    assert res.cluster.kind == "inline" and res.baseline is None
    assert [r["status"] for r in res.rows] == ["ok", "ok"]
    assert res.time_table()[0] == ["t_s", "odom_rmse_m"]
