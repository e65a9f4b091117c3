# SPDX-License-Identifier: BSD-3-Clause
"""Evaluation: association, alignment and metrics, cross-checked against evo's Python API."""

from __future__ import annotations

import copy
import json
from pathlib import Path

import numpy as np
import pytest
from evo import main_ape, main_rpe
from evo.core import metrics, sync
from evo.core.trajectory import PoseTrajectory3D
from evo.core.units import Unit
from scipy.spatial.transform import Rotation

from uwbfuse.cli import main as cli_main
from uwbfuse.errors import EvaluationError
from uwbfuse.eval import evaluate
from uwbfuse.eval.associate import match_stamps
from uwbfuse.eval.command import evaluate_files
from uwbfuse.io.tum import write_tum
from uwbfuse.streams import NS_PER_S, PoseStream

T0_NS = 1_700_000_000 * NS_PER_S


def _truth(t_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A smooth 3-D path (figure-eight with height change) and attitude at times t_s."""
    xyz = np.stack(
        [10 * np.cos(0.1 * t_s), 5 * np.sin(0.2 * t_s), 0.5 * np.sin(0.05 * t_s)], axis=1
    )
    rpy = np.stack([0.1 * np.sin(0.3 * t_s), 0.05 * np.cos(0.2 * t_s), 0.1 * t_s], axis=1)
    return xyz, Rotation.from_euler("xyz", rpy).as_quat()


def _pair(
    gt_dt: float = 0.1, est_dt: float = 0.05, seed: int = 1, duration: float = 60.0
) -> tuple[PoseStream, PoseStream]:
    """GT on a regular grid; a noisy estimate in a rotated, shifted frame, jittered stamps."""
    rng = np.random.default_rng(seed)
    tg = np.arange(0.0, duration, gt_dt)
    gt_xyz, gt_q = _truth(tg)
    te = np.arange(0.003, duration, est_dt)
    te = te + rng.uniform(-0.004, 0.004, len(te))
    te_ns = T0_NS + np.round(te * NS_PER_S).astype(np.int64)
    te = (te_ns - T0_NS) / NS_PER_S
    est_xyz, est_q = _truth(te)
    frame = Rotation.from_euler("xyz", [0.02, -0.01, 0.3])
    offset = np.array([1.0, 2.0, 0.3])
    est_xyz = frame.apply(est_xyz) + offset + rng.normal(0, 0.05, est_xyz.shape)
    noise = Rotation.from_rotvec(rng.normal(0, 0.01, (len(te), 3)))
    est_q = (frame * Rotation.from_quat(est_q) * noise).as_quat()
    gt = PoseStream(T0_NS + np.round(tg * NS_PER_S).astype(np.int64), gt_xyz, gt_q)
    return PoseStream(te_ns, est_xyz, est_q), gt


def _evo(p: PoseStream) -> PoseTrajectory3D:
    return PoseTrajectory3D(
        positions_xyz=p.position,
        orientations_quat_wxyz=p.quat_xyzw[:, [3, 0, 1, 2]],
        timestamps=p.t_ns / NS_PER_S,
    )


def _assert_stats(ours: object, evo_stats: dict, tol: float = 1e-9) -> None:
    for key in ("rmse", "mean", "median", "std", "min", "max"):
        assert getattr(ours, key) == pytest.approx(float(evo_stats[key]), abs=tol), key


@pytest.mark.parametrize("align", ["none", "se3"])
@pytest.mark.parametrize(("gt_dt", "est_dt"), [(0.1, 0.05), (0.05, 0.1)])
def test_matches_evo(align: str, gt_dt: float, est_dt: float) -> None:
    """test that ATE and RPE (1 s and 10 m) equal evo's ape/rpe on the same pairs."""
    est, gt = _pair(gt_dt=gt_dt, est_dt=est_dt)
    res = evaluate(est, gt, align=align, max_dt=0.02)
    ref, es = sync.associate_trajectories(_evo(gt), _evo(est), max_diff=0.02)
    assert res.n_pairs == ref.num_poses
    np.testing.assert_allclose(res.gt_position, ref.positions_xyz)

    ape = main_ape.ape(
        copy.deepcopy(ref), copy.deepcopy(es), metrics.PoseRelation.translation_part,
        align=align == "se3", correct_scale=False,
    )
    _assert_stats(res.ate_3d, ape.stats)
    np.testing.assert_allclose(res.ate_3d_errors, ape.np_arrays["error_array"], atol=1e-9)

    # RPE over 1 s: the GT grid is regular, so 1 s is a fixed number of frames for evo;
    # estimate stamps are jittered, so we give evo the GT grid when GT is the sparser one.
    frames = round(1.0 / max(gt_dt, est_dt))
    rpe_t = main_rpe.rpe(
        copy.deepcopy(ref), copy.deepcopy(es), metrics.PoseRelation.translation_part,
        delta=frames, delta_unit=Unit.frames, all_pairs=True,
    )
    r_time = res.rpe[0]
    assert (r_time.delta, r_time.unit, r_time.relation) == (1.0, "s", "translation_part")
    if gt_dt >= est_dt:
        _assert_stats(r_time.stats, rpe_t.stats)
    rpe_d = main_rpe.rpe(
        copy.deepcopy(ref), copy.deepcopy(es), metrics.PoseRelation.translation_part,
        delta=10.0, delta_unit=Unit.meters, all_pairs=True, pairs_from_reference=True,
    )
    r_dist = res.rpe[1]
    assert (r_dist.delta, r_dist.unit) == (10.0, "m")
    assert r_dist.stats.n == len(rpe_d.np_arrays["error_array"])
    _assert_stats(r_dist.stats, rpe_d.stats)


def test_association_matches_evo_on_random_stamps() -> None:
    """test that the vectorised matcher picks the same indices as evo's loop."""
    rng = np.random.default_rng(3)
    a = np.sort(rng.choice(10_000_000, 300, replace=False)).astype(np.int64) * 1000
    b = np.sort(rng.choice(10_000_000, 900, replace=False)).astype(np.int64) * 1000
    for max_dt_ns in (1_000_000, 20_000_000, 200_000_000):
        ia, ib = match_stamps(a, b, max_dt_ns)
        ea, eb = sync.matching_time_indices(a / 1e9, b / 1e9, max_diff=max_dt_ns / 1e9)
        np.testing.assert_array_equal(ia, ea)
        np.testing.assert_array_equal(ib, eb)


def test_se2_alignment_recovers_heading_and_offset() -> None:
    """test that se2 alignment removes a yaw + x/y offset exactly (planar trajectory)."""
    t = np.arange(0.0, 30.0, 0.1)
    xyz, _ = _truth(t)
    xyz[:, 2] = 0.0
    yaw = np.arctan2(np.gradient(xyz[:, 1]), np.gradient(xyz[:, 0]))
    q = Rotation.from_euler("z", yaw[:, None]).as_quat()
    t_ns = T0_NS + np.round(t * NS_PER_S).astype(np.int64)
    gt = PoseStream(t_ns, xyz, q)
    frame = Rotation.from_euler("z", 1.1)
    moved = frame.apply(xyz) + np.array([3.0, -4.0, 0.0])
    est = PoseStream(t_ns, moved, (frame * Rotation.from_quat(q)).as_quat())
    res = evaluate(est, gt, align="se2")
    assert res.ate_3d.max < 1e-9
    assert res.yaw is not None and res.yaw.max < 1e-9
    assert res.transform.yaw == pytest.approx(-1.1)
    unaligned = evaluate(est, gt)
    assert unaligned.ate_2d.rmse > 1.0
    assert np.degrees(unaligned.yaw.rmse) == pytest.approx(np.degrees(1.1), abs=1e-6)


def test_yaw_error_and_position_only_ground_truth() -> None:
    """test yaw error for a constant heading offset, and its skip for position-only GT."""
    est, gt = _pair(gt_dt=0.1, est_dt=0.1)
    turned = Rotation.from_quat(gt.quat_xyzw) * Rotation.from_euler("z", 0.05)
    est = PoseStream(gt.t_ns, gt.position + np.array([0.3, 0.4, 0.0]), turned.as_quat())
    res = evaluate(est, gt)
    assert res.ate_3d.rmse == pytest.approx(0.5)
    assert res.ate_2d.max == pytest.approx(0.5)
    assert res.yaw is not None
    # Small tilts make the ZYX yaw offset differ slightly from the body-z rotation.
    assert res.yaw.rmse == pytest.approx(0.05, abs=0.01)

    gt_pos = PoseStream(gt.t_ns, gt.position, np.tile([0, 0, 0, 1.0], (len(gt), 1)), False)
    res = evaluate(est, gt_pos)
    assert res.yaw is None and res.yaw_errors is None
    assert any("yaw error skipped: ground truth has no orientation" in n for n in res.notes)
    assert res.rpe[0].relation == "map_displacement"
    assert res.rpe[0].stats.max < 1e-9  # a constant offset has no map-frame relative error
    assert "yaw error skipped" in res.table()


def test_coverage_and_rate() -> None:
    """test coverage (a gap at the start is uncovered) and estimate poses per second."""
    est, gt = _pair(gt_dt=0.1, est_dt=0.1, duration=100.0)
    keep = est.t_ns >= T0_NS + 30 * NS_PER_S
    late = PoseStream(est.t_ns[keep], est.position[keep], est.quat_xyzw[keep])
    res = evaluate(late, gt)
    assert res.coverage == pytest.approx(0.7, abs=0.01)
    assert res.est_rate_hz == pytest.approx(7.0, abs=0.1)
    assert any("cover only" in n for n in res.notes)
    full = evaluate(est, gt)
    assert full.coverage > 0.99 and full.est_rate_hz == pytest.approx(10.0, abs=0.1)
    # Per-pose arrays line up for plots (error vs time, CDF).
    assert full.t_s.shape == full.ate_3d_errors.shape == full.ate_2d_errors.shape


def test_errors_no_overlap_and_too_few() -> None:
    """test one-line EvaluationErrors for disjoint time spans and too few associated poses."""
    est, gt = _pair(gt_dt=0.1, est_dt=0.1, duration=10.0)
    shifted = PoseStream(est.t_ns + 100 * NS_PER_S, est.position, est.quat_xyzw)
    with pytest.raises(EvaluationError, match="no overlap in time") as e:
        evaluate(shifted, gt)
    assert "\n" not in str(e.value)
    off = PoseStream(est.t_ns[:20:10] + 50_000_000, est.position[:20:10], est.quat_xyzw[:20:10])
    with pytest.raises(EvaluationError, match="too few associated poses"):
        evaluate(off, gt)
    with pytest.raises(EvaluationError, match="unknown alignment"):
        evaluate(est, gt, align="sim3")


def test_table_and_json(tmp_path: Path) -> None:
    """test that the table names the metrics and write_json writes them (NaN as null)."""
    est, gt = _pair(duration=5.0)  # path < 10 m: no 10 m RPE pairs
    res = evaluate(est, gt, align="se3")
    text = res.table()
    for word in ("ATE 3-D", "ATE 2-D", "RPE 1 s", "RPE 10 m", "|yaw|", "se3"):
        assert word in text
    out = tmp_path / "m.json"
    res.write_json(out)
    data = json.loads(out.read_text())
    assert data["ate_3d_m"]["rmse"] == pytest.approx(res.ate_3d.rmse)
    assert data["align"] == "se3" and data["n_pairs"] == res.n_pairs
    assert data["rpe"][1]["delta_unit"] == "m" and data["rpe"][1]["stats_m"]["rmse"] is None
    assert any("RPE 10 m: no pose pairs" in n for n in data["notes"])


def test_eval_files_and_cli(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """test evaluate_files on TUM files and `uwbfuse eval` exit codes (0, and 2 on error)."""
    est, gt = _pair()
    write_tum(tmp_path / "est.tum", est)
    write_tum(tmp_path / "gt.tum", gt)
    res = evaluate_files(tmp_path / "est.tum", tmp_path / "gt.tum", align="se3")
    assert res.ate_3d.rmse == pytest.approx(evaluate(est, gt, align="se3").ate_3d.rmse, abs=1e-5)
    code = cli_main(["eval", str(tmp_path / "est.tum"), "--gt", str(tmp_path / "gt.tum"),
                     "--align", "se3", "--json", str(tmp_path / "m.json")])
    assert code == 0
    assert "ATE 3-D" in capsys.readouterr().out
    assert json.loads((tmp_path / "m.json").read_text())["n_pairs"] == res.n_pairs
    late = PoseStream(est.t_ns + 1000 * NS_PER_S, est.position, est.quat_xyzw)
    write_tum(tmp_path / "late.tum", late)
    code = cli_main(["eval", str(tmp_path / "late.tum"), "--gt", str(tmp_path / "gt.tum")])
    err = capsys.readouterr().err
    assert code == 2 and "no overlap in time" in err and err.count("\n") == 1


def test_eval_against_log_ground_truth(tmp_path: Path) -> None:
    """test --gt LOG: GT read from /ground_truth; a log without GT names the topic."""
    pytest.importorskip("uwbfuse.io.reader", reason="log reader not available")
    from uwbfuse.io.writer import write_contract_log
    from uwbfuse.streams import SensorLog, WheelStream

    est, gt = _pair(gt_dt=0.1, est_dt=0.1, duration=20.0)
    wheel = WheelStream(gt.t_ns, np.ones(len(gt)), np.zeros(len(gt)))
    write_contract_log(tmp_path / "with_gt.mcap", SensorLog(wheel=wheel, ground_truth=gt))
    write_contract_log(tmp_path / "no_gt.mcap", SensorLog(wheel=wheel))
    write_tum(tmp_path / "est.tum", est)
    res = evaluate_files(tmp_path / "est.tum", tmp_path / "with_gt.mcap", align="se3")
    ref = evaluate(est, gt, align="se3")
    assert res.n_pairs == ref.n_pairs
    assert res.ate_3d.rmse == pytest.approx(ref.ate_3d.rmse, abs=1e-5)
    assert "/ground_truth" in res.gt_name
    with pytest.raises(EvaluationError, match="no ground truth on topic '/ground_truth'"):
        evaluate_files(tmp_path / "est.tum", tmp_path / "no_gt.mcap")
