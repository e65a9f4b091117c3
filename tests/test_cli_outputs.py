# SPDX-License-Identifier: BSD-3-Clause
"""The command line as people expect it: summary, --report, progress, --version, help,
"did you mean", all-or-none outputs, SIGTERM, and evo agreeing with `uwbfuse eval`."""

from __future__ import annotations

import argparse
import contextlib
import copy
import io
import json
import os
import signal
from contextlib import contextmanager
from importlib.metadata import version
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from tests.helpers import ROOT
from uwbfuse.cli import build_parser, main
from uwbfuse.io.tum import read_tum
from uwbfuse.progress import ProgressBar

SAMPLE = ROOT / "data" / "warehouse_60s.mcap"


@pytest.fixture(scope="module")
def ekf_run(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """One `run --method ekf` on the bundled sample with every output asked for."""
    d = tmp_path_factory.mktemp("run")
    files = {k: d / f"est.{k}" for k in ("tum", "mcap", "csv", "json")}
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main(["run", str(SAMPLE), "--method", "ekf", "-o", str(files["tum"]),
                     "--mcap-out", str(files["mcap"]), "--cov-out", str(files["csv"]),
                     "--report", str(files["json"])])
    return {"code": code, "out": out.getvalue(), "err": err.getvalue(), "dir": d, **files}


def test_run_prints_a_short_summary_and_writes_the_report(ekf_run: dict[str, Any]) -> None:
    """test a few summary lines with one latency figure; the diagnostics in --report JSON."""
    assert ekf_run["code"] == 0
    lines = ekf_run["out"].splitlines()
    assert 1 <= len(lines) <= 4, lines
    assert lines[0].startswith("ekf: 600 poses")
    assert ekf_run["out"].count("latency") == 1
    assert ekf_run["err"] == ""  # not a terminal: no progress bar
    rep = json.loads(ekf_run["json"].read_text())
    assert rep["method"] == "ekf" and rep["poses"] == 600
    assert rep["update_latency_ms"]["definition"].startswith("wall time of one estimator step")
    assert rep["update_latency_ms"]["n"] >= 600 and rep["update_latency_ms"]["p99"] > 0
    assert rep["read"]["messages"]["/imu"] == 12001
    assert "update_latency_ms" not in rep["estimator"]
    assert rep["outputs"]["--cov-out"] == str(ekf_run["csv"])
    assert sorted(p.name for p in ekf_run["dir"].iterdir()) == [
        "est.csv", "est.json", "est.mcap", "est.tum"]


def test_run_cov_csv_has_a_row_per_pose(ekf_run: dict[str, Any]) -> None:
    """test --cov-out: one header line, then t and 36 finite entries per TUM pose."""
    tum = read_tum(ekf_run["tum"])
    rows = np.loadtxt(ekf_run["csv"], delimiter=",", skiprows=1)
    assert rows.shape == (len(tum), 37)
    np.testing.assert_allclose(rows[:, 0], tum.t_s, atol=1e-9)
    cov = rows[:, 1:].reshape(-1, 6, 6)
    np.testing.assert_allclose(cov, np.transpose(cov, (0, 2, 1)))
    assert np.all(np.diagonal(cov, axis1=1, axis2=2) > 0)


def test_evo_gives_uwbfuse_eval_numbers(
    ekf_run: dict[str, Any], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """test the README's evo commands: APE = ATE, RPE 10 m with --all_pairs
    --pairs_from_reference = RPE 10 m, RPE 10 frames (10 Hz) = RPE 1 s; --save-gt for evo,
    and evo reading the run's MCAP output."""
    from evo.core import metrics, sync
    from evo.main_ape import ape
    from evo.main_rpe import rpe
    from evo.tools import file_interface
    from rosbags.rosbag2 import Reader

    gt_tum, est_json = tmp_path / "gt.tum", tmp_path / "m.json"
    assert main(["eval", str(ekf_run["tum"]), "--gt", str(SAMPLE), "--save-gt", str(gt_tum),
                 "--json", str(est_json)]) == 0
    ours = json.loads(est_json.read_text())
    ref = file_interface.read_tum_trajectory_file(str(gt_tum))
    with Reader(ekf_run["mcap"]) as reader:
        est = file_interface.read_bag_trajectory(reader, "/uwbfuse/ekf/pose")
    ref, est = sync.associate_trajectories(ref, est, max_diff=0.02)
    tp = metrics.PoseRelation.translation_part
    ate = ape(copy.deepcopy(ref), copy.deepcopy(est), tp).stats["rmse"]
    rpe_m = rpe(copy.deepcopy(ref), copy.deepcopy(est), tp, delta=10,
                delta_unit=metrics.Unit.meters, all_pairs=True,
                pairs_from_reference=True).stats["rmse"]
    rpe_f = rpe(copy.deepcopy(ref), copy.deepcopy(est), tp, delta=10,
                delta_unit=metrics.Unit.frames, all_pairs=True).stats["rmse"]
    rpes = {(r["delta"], r["delta_unit"]): r["stats_m"]["rmse"] for r in ours["rpe"]}
    assert ate == pytest.approx(ours["ate_3d_m"]["rmse"], rel=1e-6)
    assert rpe_m == pytest.approx(rpes[10.0, "m"], rel=1e-6)
    assert rpe_f == pytest.approx(rpes[1.0, "s"], rel=1e-6)


def test_save_gt_alone_and_eval_without_estimate(tmp_path: Path) -> None:
    """test `eval --gt LOG --save-gt GT.tum` without EST; EST without --save-gt is needed."""
    gt = tmp_path / "gt.tum"
    assert main(["eval", "--gt", str(SAMPLE), "--save-gt", str(gt)]) == 0
    assert len(read_tum(gt)) == 12001
    assert main(["eval", "--gt", str(SAMPLE)]) == 2


def test_mcap_out_directory_fails_before_running_and_writes_nothing(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """test that --mcap-out naming a directory is one line, exit 2, and no TUM is written."""
    (tmp_path / "d").mkdir()
    code = main(["run", str(SAMPLE), "--method", "odom", "-o", str(tmp_path / "e.tum"),
                 "--mcap-out", str(tmp_path / "d")])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and "directory" in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["d"]


def test_sigterm_mid_write_removes_temporary_files(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """test that SIGTERM while an output is being written leaves no file and exits 143."""
    import uwbfuse.io.tum as tum

    real_open = tum.atomic_open

    @contextmanager
    def killed_open(*a: Any, **k: Any) -> Any:
        with real_open(*a, **k) as f:
            f.write("partial\n")
            f.flush()
            os.kill(os.getpid(), signal.SIGTERM)
            yield f

    monkeypatch.setattr(tum, "atomic_open", killed_open)
    before = signal.getsignal(signal.SIGTERM)
    code = main(["run", str(SAMPLE), "--method", "odom", "-o", str(tmp_path / "e.tum"),
                 "--mcap-out", str(tmp_path / "e.mcap")])
    assert code == 128 + signal.SIGTERM
    assert "terminated" in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []
    assert signal.getsignal(signal.SIGTERM) == before


def test_progress_bar_time_based_on_a_terminal() -> None:
    """test the bar in place on a TTY (\\r, seconds of log) and silent when disabled."""

    class Tty(io.StringIO):
        def isatty(self) -> bool:
            return True

    s = Tty()
    bar = ProgressBar("isam2", stream=s, unit="s of log")
    for k in range(62):
        bar(k, 61, "")
    assert s.getvalue().startswith("\r") and "61/61 s of log" in s.getvalue()
    assert s.getvalue().endswith("\n")
    quiet = io.StringIO()
    ProgressBar("x", stream=quiet, enabled=False)(1, 2, "")
    assert quiet.getvalue() == ""


def test_progress_flag_forces_the_bar_on_a_pipe(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """test `--progress` on a non-terminal stderr: lines of `<method> [###] n/N s of log`."""
    assert main(["run", str(SAMPLE), "--method", "odom", "-o", str(tmp_path / "e.tum"),
                 "--progress"]) == 0
    err = capsys.readouterr().err
    assert "odom [" in err and "/61 s of log" in err


def test_version_from_package_metadata(capsys: pytest.CaptureFixture[str]) -> None:
    """test `uwbfuse --version`."""
    with pytest.raises(SystemExit) as e:
        main(["--version"])
    assert e.value.code == 0
    assert capsys.readouterr().out.strip() == f"uwbfuse {version('uwbfuse')}"


def test_every_option_has_help_and_shows_its_default() -> None:
    """test help text on every argument of every subcommand, and the default where one is."""
    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    for name, sp in sub.choices.items():
        text = sp.format_help()
        for action in sp._actions:
            if isinstance(action, argparse._HelpAction):
                continue
            assert action.help, f"{name} {action.dest}: no help"
            d = action.default
            if action.option_strings and d not in (None, False) and not action.required:
                assert f"default: {d}" in " ".join(text.split()), f"{name} {action.dest}"


@pytest.mark.parametrize(("argv", "hint"), [
    (["run", "x.mcap", "--method", "iasm2"], "did you mean 'isam2'?"),
    (["compare", "x.mcap", "--methods", "ekf,ufk"], "did you mean 'ukf'?"),
])
def test_did_you_mean_for_methods(
    argv: list[str], hint: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """test a suggestion for a misspelt method (run's --method, compare's --methods)."""
    argv = [*argv, "--out", str(tmp_path / "o")] if argv[0] == "compare" else argv
    try:
        code = main(argv)
    except SystemExit as e:
        code = e.code
    assert code == 2
    assert hint in capsys.readouterr().err


@pytest.mark.parametrize(("toml", "hint"), [
    ("[anchor]\nA0 = [0, 0, 1]\n", "unknown config section 'anchor'; did you mean 'anchors'?"),
    ("[uwb]\nrange_feild = 'r'\n", "did you mean 'range_field'?"),
    ("[topics]\nimu_topic = '/imu'\n", "did you mean 'imu'?"),
])
def test_did_you_mean_for_config(
    toml: str, hint: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """test a suggestion for a misspelt config section or key."""
    cfg = tmp_path / "c.toml"
    cfg.write_text(toml)
    assert main(["run", str(SAMPLE), "--method", "odom", "--config", str(cfg),
                 "-o", str(tmp_path / "e.tum")]) == 2
    assert hint in capsys.readouterr().err


def test_compare_progress_names_each_method() -> None:
    """test that compare's progress counts each method's seconds of log, the note naming it."""
    from uwbfuse.compare import run_methods
    from uwbfuse.config import Config
    from uwbfuse.estimator import Method
    from uwbfuse.sim.simulator import simulate

    calls: list[tuple[int, int, str]] = []
    log = simulate("room", duration_s=5.0, seed=1)
    rows = run_methods(log, [Method.ODOM, Method.IMU], Config(), 0.05,
                       progress=lambda d, t, n: calls.append((d, t, n)))
    assert [r.status for r in rows] == ["ok", "ok"]
    for name in ("odom", "imu"):
        mine = [c for c in calls if c[2].split()[0] == name]
        assert mine[0][0] == 0 and mine[-1][0] == mine[-1][1] == 6  # 5 s of log + finish
        assert any(c[2] == f"{name} finishing" for c in mine)
