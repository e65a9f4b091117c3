# SPDX-License-Identifier: BSD-3-Clause
import tomllib
from pathlib import Path

import pytest

from uwbfuse.cli import main
from uwbfuse.config import config_from_dict
from uwbfuse.io.writer import write_contract_log
from uwbfuse.sim.simulator import simulate


def test_calibrate_nlos_writes_a_usable_nlos_table(tmp_path: Path) -> None:
    """test that calibrate-nlos recovers the simulated NLOS bias and writes valid config"""
    log_path = tmp_path / "cal.mcap"
    write_contract_log(log_path, simulate("warehouse-nlos", duration_s=90.0, seed=11))
    out = tmp_path / "nlos.toml"
    assert main(["calibrate-nlos", str(log_path), "-o", str(out)]) == 0
    data = tomllib.loads(out.read_text())
    cfg = config_from_dict(data)
    # warehouse-nlos draws NLOS excess from N(0.3, 0.15) m, LOS noise sigma 0.05 m.
    assert cfg.nlos.range_nlos_mean == pytest.approx(0.3, abs=0.08)
    assert cfg.nlos.range_los_std == pytest.approx(0.05, abs=0.03)
    assert set(cfg.nlos.anchor) == {"A1", "A2", "A3", "A4"}


def test_calibrate_nlos_without_ground_truth_is_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """test that a log without ground truth gives exit 2 and one stderr line"""
    log = simulate("room", duration_s=10.0, seed=1)
    log.ground_truth = None
    p = tmp_path / "nogt.mcap"
    write_contract_log(p, log)
    assert main(["calibrate-nlos", str(p)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "ground truth" in err[0]
