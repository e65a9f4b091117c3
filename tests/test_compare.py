# SPDX-License-Identifier: BSD-3-Clause
from pathlib import Path

import numpy as np
import pytest

from uwbfuse.compare import parse_methods, run_methods
from uwbfuse.config import Config
from uwbfuse.errors import ConfigError
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


def test_compare_writes_rpe_config_anchors_and_html(room_log: SensorLog, tmp_path: Path) -> None:
    """test that compare's table has RPE columns, its saved config carries the log's
    metadata anchors, and --html writes one report with no external references"""
    import csv
    import html
    from html.parser import HTMLParser

    from uwbfuse.compare import compare_log
    from uwbfuse.config import load_config
    from uwbfuse.io.writer import write_contract_log

    write_contract_log(tmp_path / "log.mcap", room_log)  # anchors only in the metadata
    out = tmp_path / "out"
    res = compare_log(tmp_path / "log.mcap", "wls,odom", out_dir=out, html=True)
    for name in ("table.csv", "table.md", "config.toml", "report.html"):
        assert (out / name).is_file(), name
    pngs = sorted(p.name for p in res.files if p.suffix == ".png")
    assert pngs == ["error_cdf.png", "error_track.png", "error_vs_time.png",
                    "range_residuals.png", "trajectories.png", "xy_yaw_vs_time.png"]
    assert all((out / n).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" for n in pngs)
    assert not list(out.glob(".*tmp*"))
    rows = list(csv.DictReader((out / "table.csv").open()))
    assert {"rpe1m_rmse_m", "rpe10m_rmse_m"} <= set(rows[0])
    for row in rows:  # the 30 s room log travels 2.7 m: RPE over 1 m, none over 10 m
        assert 0.0 < float(row["rpe1m_rmse_m"]) < 0.5
        assert row["rpe10m_rmse_m"] == ""
    assert "evo_rpe" in (out / "table.md").read_text()

    saved = load_config(out / "config.toml")
    assert room_log.anchors is not None
    assert list(saved.anchors) == list(room_log.anchors.ids)
    np.testing.assert_allclose(np.array(list(saved.anchors.values())),
                               room_log.anchors.positions)

    class Refs(HTMLParser):
        def __init__(self) -> None:
            super().__init__()
            self.refs: list[tuple[str, str, str]] = []
            self.tags: set[str] = set()

        def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
            self.tags.add(tag)
            self.refs += [(tag, k, v or "") for k, v in attrs if k in ("src", "href")]

    text = (out / "report.html").read_text()
    parser = Refs()
    parser.feed(text)
    assert len(parser.refs) == len(pngs) == 6
    assert all(v.startswith("data:image/png;base64,") for _, _, v in parser.refs)
    assert not parser.tags & {"script", "link", "iframe", "object"}
    assert "http://" not in text and "https://" not in text and "url(" not in text
    assert "<th>rpe10m_rmse_m</th>" in text
    assert f'"{room_log.anchors.ids[0]}" = [' in html.unescape(text)  # the effective config


def test_residual_nlos_marks_follow_the_estimator(tmp_path: Path) -> None:
    """test that the residual plot's NLOS marks are the graph's own per-range classification
    (as its report counts them), not a rule on the residual's size"""
    from uwbfuse.compare import MethodRow, RangeResiduals, range_residuals
    from uwbfuse.estimator import Method, RangeClasses
    from uwbfuse.eval.evaluate import evaluate
    from uwbfuse.pipeline import estimate
    from uwbfuse.plots import nlos_classifier, nlos_note, plot_comparison

    short = simulate("room", duration_s=20.0, seed=3)
    res = estimate(short, Method.ISAM2, Config())
    classes = res.range_classes
    assert classes is not None and np.any(classes.nlos) and not np.all(classes.nlos)
    assert short.anchors is not None
    for a, aid in enumerate(short.anchors.ids):
        assert res.report["anchors"][aid]["nlos"] == int(np.sum(classes.nlos[classes.anchor == a]))
    assert short.ground_truth is not None
    resid = range_residuals(short, short.ground_truth, Config())
    marks = resid.classified_nlos(classes)
    assert int(np.sum(marks >= 0)) == len(classes.t_ns)  # every range of the graph matched
    assert int(np.sum(marks == 1)) == int(np.sum(classes.nlos))

    # the marks follow the classes whatever the residual: a huge LOS, a tiny NLOS
    fake = RangeResiduals(np.array([10, 20, 30, 40]), np.array([0, 0, 1, 1]),
                          np.array([5.0, 0.0, 0.01, 3.0]), np.zeros((4, 2)))
    cls = RangeClasses(np.array([40, 20, 10]), np.array([1, 0, 0]), np.array([0.1, 0.9, 0.2]),
                       np.array([0.5, 1.0, 1.0]))
    assert fake.classified_nlos(cls).tolist() == [0, 1, -1, 2]

    rows = [MethodRow("wls", "ok", short.ground_truth), MethodRow("ekf", "ok")]
    assert nlos_classifier(rows) == ("", None)
    assert "no method here reports a per-range NLOS classification" in nlos_note("", rows)
    rows.append(MethodRow("isam2", "ok", short.ground_truth, range_classes=classes))
    assert nlos_classifier(rows) == ("isam2", classes)
    assert "isam2's own classification" in nlos_note("isam2", rows)

    scored = MethodRow("isam2", "ok", res.trajectory, range_classes=classes,
                       metrics=evaluate(res.trajectory, short.ground_truth, max_dt=0.05))
    files = plot_comparison(short, [scored], Config(), tmp_path)
    assert len(files) == 6 and all(p.stat().st_size > 10_000 for p in files)
