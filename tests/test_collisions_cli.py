# SPDX-License-Identifier: BSD-3-Clause
"""`uwbfuse collisions`: the events table, the map and vehicle config, bad input."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest

from uwbfuse.cli import main
from uwbfuse.config import load_config
from uwbfuse.errors import ConfigError
from uwbfuse.io.tum import write_tum
from uwbfuse.streams import NS_PER_S, PoseStream

T0 = 1_700_000_000.0

SHELF_CONFIG = """
[map]
obstacles = [[[8.0, -1.0], [9.0, -1.0], [9.0, 1.0], [8.0, 1.0]]]
[vehicle]
length = 1.0
width = 0.6
control_delay = 0.5
safety_margin = 0.2
"""


def _tum(path: Path, t: np.ndarray, x: np.ndarray, y: np.ndarray, yaw: float) -> Path:
    n = len(t)
    q = np.zeros((n, 4))
    q[:, 2], q[:, 3] = np.sin(0.5 * yaw), np.cos(0.5 * yaw)
    t_ns = np.round((T0 + t) * NS_PER_S).astype(np.int64)
    write_tum(path, PoseStream(t_ns, np.column_stack([x, y, np.zeros(n)]), q, True))
    return path


def _head_on(tmp_path: Path) -> tuple[Path, Path]:
    """a drives +x on y = 0 at 0.5 m/s towards the shelf at x = 8; b drives -x from
    x = 12 on y = 0.2 at 0.5 m/s: their fronts meet at t = 11 s, a meets the shelf at 15 s."""
    t = np.arange(0.0, 20.0, 0.1)
    a = _tum(tmp_path / "a.tum", t, 0.5 * t, np.zeros_like(t), 0.0)
    b = _tum(tmp_path / "b.tum", t, 12.0 - 0.5 * t, np.full_like(t, 0.2), np.pi)
    return a, b


def _rows(path: Path) -> list[dict[str, str]]:
    with path.open() as f:
        return list(csv.DictReader(f))


def test_events_table_for_shelf_and_head_on(tmp_path: Path,
                                            capsys: pytest.CaptureFixture[str]) -> None:
    """test that a vehicle driving into a shelf and two vehicles meeting head-on give
    collision events with the contract's columns, clearance 0 and a time to contact that is
    at most the control delay, before the contact"""
    cfg = tmp_path / "c.toml"
    cfg.write_text(SHELF_CONFIG)
    a, b = _head_on(tmp_path)
    out = tmp_path / "out"
    assert main(["collisions", str(a), str(b), "--config", str(cfg), "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "2 vehicles" in printed
    rows = _rows(out / "events.csv")
    assert list(rows[0]) == ["t", "kind", "a", "b", "distance_m", "ttc_s"]
    assert (out / "events.md").read_text().startswith("# Collision prediction")
    assert (out / "collisions.png").stat().st_size > 10_000
    # a's front 0.5 t + 0.5 meets b's front 11.5 - 0.5 t at t = 11 s, the shelf at 15 s
    for other, t_contact in (("b", 11.0), ("map", 15.0)):
        col = [r for r in rows if r["a"] == "a" and r["b"] == other
               and r["kind"] == "collision"]
        assert col, other
        first = col[0]
        assert float(first["distance_m"]) == 0.0
        t_first = float(first["t"]) - T0
        ttc = float(first["ttc_s"])
        assert 0.0 <= ttc <= 0.5
        assert t_contact - 0.5 - 0.1 - 1e-6 <= t_first <= t_contact - 0.5 + 0.1 + 1e-6
        assert t_first + ttc <= t_contact + 1e-6
        warn = [r for r in rows if r["a"] == "a" and r["b"] == other and r["kind"] == "warning"]
        assert warn and float(warn[0]["t"]) < float(first["t"])
        assert all(r["ttc_s"] == "" for r in warn)


def test_names_option(tmp_path: Path) -> None:
    """test that --names replaces the file stems in the events"""
    cfg = tmp_path / "c.toml"
    cfg.write_text(SHELF_CONFIG)
    a, b = _head_on(tmp_path)
    out = tmp_path / "out"
    assert main(["collisions", str(a), str(b), "--config", str(cfg), "--out", str(out),
                 "--names", "forklift,tugger"]) == 0
    assert {r["a"] for r in _rows(out / "events.csv")} == {"forklift", "tugger"}


def test_dump_config_shows_map_and_vehicle(capsys: pytest.CaptureFixture[str]) -> None:
    """test that dump-config lists the [map] and [vehicle] keys with their units"""
    assert main(["dump-config"]) == 0
    text = capsys.readouterr().out
    assert "[map]" in text and "[vehicle]" in text
    assert "control_delay = 0.5  # prediction horizon" in text and ", s" in text
    assert "safety_margin = 0.2  # clearance below which a warning is raised, m" in text


@pytest.mark.parametrize(("toml", "message"), [
    ("[vehicle]\nlength = 0.0\n", "'vehicle.length'"),
    ("[vehicle]\nwidth = -0.5\n", "'vehicle.width'"),
    ("[vehicle]\ncontrol_delay = -0.1\n", "'vehicle.control_delay'"),
    ("[map]\nobstacles = [[[0, 0], [1, 1], [1, 0], [0, 1]]]\n", "self-intersecting"),
    ("[map]\nobstacles = [[[0, 0], [1, 1]]]\n", "not a closed polygon"),
    ("[map]\nobstacles = [[[0, 0], [1, 0], [2, 0]]]\n", "does not enclose an area"),
    ("[map]\nboundary = [[0, 0], [1, 1], [1, 0], [0, 1]]\n", "boundary is self-intersecting"),
])
def test_bad_map_or_vehicle_is_one_line_exit_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], toml: str, message: str
) -> None:
    """test that a bad footprint, delay or polygon is one line on stderr and exit 2, with
    nothing written"""
    cfg = tmp_path / "c.toml"
    cfg.write_text(toml)
    with pytest.raises(ConfigError, match=message):
        load_config(cfg)
    a, b = _head_on(tmp_path)
    out = tmp_path / "out"
    assert main(["collisions", str(a), str(b), "--config", str(cfg), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and message.strip("'") in err and "Traceback" not in err
    assert not out.exists()


def test_bad_trajectories_are_one_line_exit_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """test that trajectories that do not overlap in time and a single-pose TUM are one
    line on stderr and exit 2"""
    t = np.arange(0.0, 10.0, 0.1)
    a = _tum(tmp_path / "a.tum", t, t, 0 * t, 0.0)
    late = _tum(tmp_path / "late.tum", t + 100.0, t, 0 * t + 5, 0.0)
    one = _tum(tmp_path / "one.tum", np.array([1.0]), np.zeros(1), np.zeros(1), 0.0)
    cases = [([a, late], "does not overlap in time"), ([a, one], "one.tum: 1 pose"),
             ([a, a], "both named 'a'")]
    for inputs, message in cases:
        out = tmp_path / "out"
        code = main(["collisions", *map(str, inputs), "--out", str(out)])
        err = capsys.readouterr().err
        assert code == 2, message
        assert err.count("\n") == 1 and message in err, err
        assert not out.exists()
