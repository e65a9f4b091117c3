# SPDX-License-Identifier: BSD-3-Clause
from pathlib import Path

import pytest

from tests.helpers import ROOT
from uwbfuse.cli import main
from uwbfuse.io.tum import read_tum

SAMPLE = ROOT / "data" / "warehouse_60s.mcap"


def test_truncated_log_runs_and_reports_the_loss(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """test that a cut-off log still runs and says on stderr what was lost"""
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(SAMPLE.read_bytes()[:400_000])
    out = tmp_path / "est.tum"
    assert main(["run", str(cut), "--method", "odom", "-o", str(out)]) == 0
    err = capsys.readouterr().err
    assert "read: truncated" in err
    assert len(read_tum(out)) > 50


def test_run_writes_tum_and_mcap(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """test that run on the bundled sample writes both outputs and no temporary files"""
    tum, mc = tmp_path / "est.tum", tmp_path / "est.mcap"
    code = main(["run", str(SAMPLE), "--method", "ekf", "-o", str(tum), "--mcap-out", str(mc)])
    assert code == 0
    poses = read_tum(tum)
    assert len(poses) >= 10 * 59
    assert mc.stat().st_size > 1000
    assert sorted(p.name for p in tmp_path.iterdir()) == ["est.mcap", "est.tum"]
    assert "ekf:" in capsys.readouterr().out
