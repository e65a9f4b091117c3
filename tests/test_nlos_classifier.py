# SPDX-License-Identifier: BSD-3-Clause
"""Signal-quality fields, simulated powers, the learned NLOS classifier and its model file."""

from __future__ import annotations

import json
import pickle
from pathlib import Path

import numpy as np
import pytest
from mcap.well_known import MessageEncoding, SchemaEncoding

from tests.test_io_reader import _anchor_meta, _header_json, _mcap
from tests.test_io_writer import small_log
from uwbfuse.cli import main
from uwbfuse.config import Config, config_from_dict, load_config
from uwbfuse.errors import ConfigError
from uwbfuse.estimator import Method
from uwbfuse.eval.evaluate import evaluate
from uwbfuse.io import msgdefs
from uwbfuse.io.reader import SKIP_BAD_POWER, read_log
from uwbfuse.io.writer import UWB_FIELDS_METADATA, write_contract_log
from uwbfuse.pipeline import estimate
from uwbfuse.positioning.nlos_classifier import (
    FORMAT_VERSION,
    POWER_FEATURES,
    RESIDUAL_FEATURES,
    RangePriors,
    load_classifier,
    log_features,
    range_labels,
    train_classifier,
)
from uwbfuse.sim.simulator import simulate, simulate_with_truth

CONTRACT_KEYS = """
[uwb]
anchor_field = "anchor_id"
range_field = "range"
array_field = ""
valid_field = ""
rssi_field = ""
first_path_power_field = ""

[uwb.range_offset]
A0 = 0.0

[nlos]
classifier = ""
"""


def test_contract_keys_accepted(tmp_path: Path) -> None:
    """test that the contract's [uwb] signal-quality keys and [nlos] classifier load."""
    p = tmp_path / "c.toml"
    p.write_text(CONTRACT_KEYS)
    cfg = load_config(p)
    assert cfg.uwb.rssi_field == "" and cfg.uwb.first_path_power_field == ""
    assert cfg.nlos.classifier == ""
    cfg = config_from_dict({"uwb": {"rssi_field": "rx", "first_path_power_field": "fp"},
                            "nlos": {"classifier": "m.skops"}})
    assert (cfg.uwb.rssi_field, cfg.uwb.first_path_power_field) == ("rx", "fp")
    with pytest.raises(ConfigError, match=r"nlos\.classifer"):
        config_from_dict({"nlos": {"classifer": "m.skops"}})


def _power_log(tmp_path: Path, array: bool) -> tuple[Path, Config, np.ndarray, np.ndarray]:
    """A json log whose custom range type carries RX and first-path power; ranges 1, 2 and 3
    have a NaN, an infinite and a missing power."""
    log = small_log(100)
    r = log.ranges
    n = len(r)
    rx = -80.0 - np.arange(n) * 0.1
    fp = rx - 3.0
    msgs = []
    for i, t in enumerate(r.t_ns.tolist()):
        e = {"id": log.anchors.ids[r.anchor[i]], "dist": float(r.range[i]),
             "q": {"rx": float(rx[i]), "fp": float(fp[i])}}
        if i == 1:
            e["q"]["rx"] = float("nan")
        if i == 2:
            e["q"]["fp"] = float("inf")
        if i == 3:
            del e["q"]["fp"]
        m = {"header": _header_json(t), "nodes": [e]} if array else {"header": _header_json(t),
                                                                      **e}
        msgs.append(("/uwb/range", t, json.dumps(m).encode()))
    js = (MessageEncoding.JSON, SchemaEncoding.JSONSchema)
    path = tmp_path / "p.mcap"
    _mcap(path, {"/uwb/range": ("acme/msg/Uwb", *js)}, msgs, metadata=_anchor_meta(log))
    cfg = config_from_dict({"uwb": {"anchor_field": "id", "range_field": "dist",
                                    "array_field": "nodes" if array else "",
                                    "rssi_field": "q.rx", "first_path_power_field": "q.fp"}})
    return path, cfg, rx, fp


@pytest.mark.parametrize("array", [False, True])
def test_reader_signal_power(tmp_path: Path, array: bool) -> None:
    """test that rssi/first-path fields are read (array and non-array types), and that
    NaN, infinite or missing powers are counted and their ranges kept without them."""
    path, cfg, rx, fp = _power_log(tmp_path, array)
    got = read_log(path, cfg)
    r = got.ranges
    assert len(r) == len(rx)  # every range kept
    want_rx, want_fp = rx.copy(), fp.copy()
    want_rx[1] = np.nan
    want_fp[[2, 3]] = np.nan
    np.testing.assert_allclose(r.rssi_dbm, want_rx)
    np.testing.assert_allclose(r.first_path_dbm, want_fp)
    assert got.report.skipped[SKIP_BAD_POWER] == 3
    # without the keys: no power columns
    plain = cfg.model_copy(update={"uwb": cfg.uwb.model_copy(
        update={"rssi_field": "", "first_path_power_field": ""})})
    got = read_log(path, plain)
    assert got.ranges.rssi_dbm is None and got.ranges.first_path_dbm is None
    assert SKIP_BAD_POWER not in got.report.skipped


def test_simulated_powers_written_and_read(tmp_path: Path) -> None:
    """test that simulate with signal quality writes UwbRange with a uwb_fields record that
    lets read_log find the powers without a config, and that without it the log is
    unchanged (sensor_msgs/Range, the same ranges and IMU samples)."""
    sim = simulate("room", 8.0, seed=3, signal_quality=True)
    base = simulate("room", 8.0, seed=3)
    np.testing.assert_array_equal(sim.ranges.range, base.ranges.range)
    np.testing.assert_array_equal(sim.imu.accel, base.imu.accel)
    assert base.ranges.rssi_dbm is None
    p = tmp_path / "s.mcap"
    write_contract_log(p, sim)
    from mcap.reader import make_reader

    with p.open("rb") as f:
        rd = make_reader(f)
        types = {s.name for s in rd.get_summary().schemas.values()}
        meta = {m.name: m.metadata for m in rd.iter_metadata()}
    assert msgdefs.UWB_RANGE in types and msgdefs.RANGE not in types
    assert meta[UWB_FIELDS_METADATA]["rssi_field"] == "rssi"
    got = read_log(p, Config())
    np.testing.assert_allclose(got.ranges.range, sim.ranges.range, rtol=1e-6)
    np.testing.assert_allclose(got.ranges.rssi_dbm, sim.ranges.rssi_dbm, atol=1e-4)
    np.testing.assert_allclose(got.ranges.first_path_dbm, sim.ranges.first_path_dbm, atol=1e-4)


def test_sim_power_model() -> None:
    """test the power model: RX - FP is above ~6 dB under NLOS and below it under LOS
    (APS006), and the LOS RX falls with distance by about 20 dB per decade."""
    s = simulate_with_truth("warehouse", 40.0, seed=1, signal_quality=True)
    gap = s.rx_dbm - s.fp_dbm
    assert np.median(gap[s.nlos]) > 6.0 > np.median(gap[~s.nlos])
    assert np.mean(gap[~s.nlos] < 6.0) > 0.95
    los = ~s.nlos
    slope = np.polyfit(np.log10(s.true_range[los]), s.rx_dbm[los], 1)[0]
    assert -23.0 < slope < -17.0


def _train_logs(seeds: tuple[int, ...], duration: float = 40.0) -> list:
    return [simulate_with_truth("warehouse-nlos", duration, seed=s, signal_quality=True)
            for s in seeds]


def _xy(log, cfg: Config) -> tuple[np.ndarray, np.ndarray, tuple[str, ...]]:
    x, names = log_features(log, cfg)
    y, _ = range_labels(log, cfg)
    return x[y >= 0], y[y >= 0], names


def test_features_causal() -> None:
    """test that a range's features do not depend on the ranges after it."""
    cfg = Config()
    log = simulate("warehouse-nlos", 20.0, seed=4, signal_quality=True)
    x_all, names = log_features(log, cfg)
    n = len(log.ranges) // 2
    part = simulate("warehouse-nlos", 20.0, seed=4, signal_quality=True)
    part.ranges = part.ranges.slice(0, n)
    x_half, _ = log_features(part, cfg)
    assert names == RESIDUAL_FEATURES + POWER_FEATURES
    # the last epoch of the shorter log may close early: compare up to one epoch before
    np.testing.assert_array_equal(x_all[: n - 8], x_half[: n - 8])


def test_classifier_separates_and_changes_estimates(tmp_path: Path) -> None:
    """test that a small forest trained on two seeds ranks the held-out seed's NLOS ranges
    (AUC), and that `[nlos] classifier` changes wls (lower ATE on heavy NLOS) and isam2."""
    from sklearn.metrics import roc_auc_score

    cfg = Config()
    parts = [_xy(s.log, cfg) for s in _train_logs((11, 12))]
    names = parts[0][2]
    x = np.concatenate([p[0] for p in parts])
    y = np.concatenate([p[1] for p in parts])
    model = train_classifier(x, y, names, n_trees=20, info={"nlos_share": float(y.mean())})
    test = simulate_with_truth("warehouse-nlos", 40.0, seed=13, signal_quality=True)
    xt, yt, _ = _xy(test.log, cfg)
    assert roc_auc_score(yt, model.predict(xt)) > 0.8
    path = tmp_path / "m.skops"
    model.save(path)
    with_clf = Config(nlos={"classifier": str(path)})
    ate = {}
    for m in (Method.WLS, Method.ISAM2):
        for name, c in (("without", cfg), ("with", with_clf)):
            res = estimate(test.log, m, c, covariance=False)
            ate[m, name] = evaluate(res.trajectory, test.log.ground_truth,
                                    max_dt=0.05).ate_2d.rmse
    assert ate[Method.WLS, "with"] < 0.85 * ate[Method.WLS, "without"]
    assert ate[Method.ISAM2, "with"] != ate[Method.ISAM2, "without"]
    # batch's EM (the mixture: its E-steps) weighs the log-odds by how well they predict
    # this log's residual classes: a forest of AUC > 0.8 on this kind of log keeps a clear
    # share of them
    mixture = Config(nlos={"classifier": str(path)}, graph={"range_model": "mixture"})
    report = estimate(test.log, Method.BATCH, mixture, covariance=False).report["batch"]
    assert 0.3 <= report["nlos_classifier_weight"] <= 1.0


def test_train_nlos_cli_end_to_end(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    """test train-nlos on short simulated logs, then run with the model and without."""
    logs = []
    for seed in (21, 22):
        p = tmp_path / f"s{seed}.mcap"
        assert main(["simulate", str(p), "--scenario", "warehouse-nlos", "--duration", "25",
                     "--seed", str(seed), "--signal-quality"]) == 0
        logs.append(str(p))
    model = tmp_path / "nlos.skops"
    assert main(["train-nlos", *logs, "--trees", "8", "-o", str(model)]) == 0
    assert "rx_minus_fp_db" in capsys.readouterr().out
    clf = load_classifier(model)
    assert clf.features == RESIDUAL_FEATURES + POWER_FEATURES
    cfg = tmp_path / "c.toml"
    cfg.write_text(f'[nlos]\nclassifier = "{model}"\n')
    a, b = tmp_path / "a.tum", tmp_path / "b.tum"
    assert main(["run", logs[1], "--method", "wls", "-o", str(a)]) == 0
    assert main(["run", logs[1], "--method", "wls", "--config", str(cfg), "-o", str(b)]) == 0
    assert a.read_text() != b.read_text()
    # --gt with the wrong count is one line, exit 2
    capsys.readouterr()
    assert main(["train-nlos", *logs, "--gt", str(a), "-o", str(model)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--gt" in err[0]


def _skops_dict(path: Path, **over: object) -> Path:
    import skops.io as sio
    from sklearn.ensemble import RandomForestClassifier

    rng = np.random.default_rng(0)
    x = rng.normal(size=(60, len(RESIDUAL_FEATURES)))
    forest = RandomForestClassifier(n_estimators=2).fit(x, (x[:, 0] > 0).astype(int))
    obj = {"format": "uwbfuse-nlos-classifier", "version": FORMAT_VERSION,
           "features": list(RESIDUAL_FEATURES), "label_threshold_m": 0.15, "info": {},
           "forest": forest}
    obj.update(over)
    sio.dump(obj, path)
    return path


@pytest.mark.parametrize("kind", ["pickle", "random", "text", "other-skops", "features",
                                  "version", "version-1", "forest-mismatch"])
def test_model_loading_safety(tmp_path: Path, kind: str,
                              capsys: pytest.CaptureFixture) -> None:
    """test that a file that is not a train-nlos model (a pickle, random bytes, another
    skops object) or one made for other features or another version is a one-line error,
    exit 2, through `run`."""
    p = tmp_path / "m.bin"
    if kind == "pickle":
        p.write_bytes(pickle.dumps({"format": "uwbfuse-nlos-classifier"}))
    elif kind == "random":
        p.write_bytes(np.random.default_rng(1).bytes(4096))
    elif kind == "text":
        p.write_text("not a model\n")
    elif kind == "other-skops":
        import skops.io as sio

        sio.dump({"hello": [1, 2, 3]}, p)
    elif kind == "features":
        _skops_dict(p, features=["residual", "colour", "smell", "a", "b", "c", "d"])
    elif kind == "version":
        _skops_dict(p, version=99)
    elif kind == "version-1":  # before the wheel-track reference: its features meant else
        _skops_dict(p, version=1)
    else:
        _skops_dict(p, features=list(RESIDUAL_FEATURES[:3]))
    with pytest.raises(ConfigError):
        load_classifier(p)
    _run_refuses_the_model(tmp_path, p, "wls", capsys)


def _run_refuses_the_model(tmp_path: Path, model: Path, method: str,
                           capsys: pytest.CaptureFixture, key: str = "") -> None:
    """`uwbfuse run` with `[nlos] classifier = model` exits 2 with one line naming the
    file (and `key`) and writes no output."""
    log = tmp_path / "s.mcap"
    write_contract_log(log, simulate("room", 6.0, seed=1))
    cfg = tmp_path / "c.toml"
    cfg.write_text(f'[nlos]\nclassifier = "{model}"\n')
    capsys.readouterr()
    assert main(["run", str(log), "--method", method, "--config", str(cfg),
                 "-o", str(tmp_path / "e.tum")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(model) in err[0] and key in err[0], err
    assert not (tmp_path / "e.tum").exists()


def test_model_needs_power_the_log_lacks(tmp_path: Path) -> None:
    """test that a model trained with signal quality refuses a log without it (one line)."""
    cfg = Config()
    x, y, names = _xy(_train_logs((31,), 20.0)[0].log, cfg)
    model = train_classifier(x, y, names, n_trees=3)
    with pytest.raises(ConfigError, match="rssi_dbm"):
        model.predict_log(simulate("warehouse-nlos", 10.0, seed=2), cfg)


def test_range_priors_lookup() -> None:
    """test that RangePriors follows consecutive batches and finds skipped ones."""
    t = np.array([10, 20, 20, 30, 40], dtype=np.int64)
    a = np.array([0, 1, 2, 0, 1], dtype=np.int32)
    p = np.array([0.1, 0.2, 0.3, 0.4, 0.5])
    rp = RangePriors(t, a, p, base_rate=0.5)
    np.testing.assert_array_equal(rp.take(t[:3], a[:3]), p[:3])
    np.testing.assert_array_equal(rp.take(t[4:], a[4:]), p[4:])  # skipped one
    np.testing.assert_array_equal(rp.take(np.array([20]), np.array([2])), [0.3])
    got = rp.take(np.array([25]), np.array([0]))
    assert np.isnan(got[0])
    np.testing.assert_allclose(rp.log_odds(np.array([0.5, np.nan])), [0.0, 0.0])


def test_uwb_range_fast_decode_matches_mcap_ros2() -> None:
    """test that the vectorised UwbRange decoder reads what mcap_ros2's decoder reads, for
    anchor ids of several lengths, and hands back messages it cannot read (a truncated
    one)."""
    from mcap.records import Schema
    from mcap_ros2.decoder import DecoderFactory

    from uwbfuse.io import cdr_fast

    ids = ("A", "B12", "7475", "anchor-long-name")
    n = 12
    t = 1_700_000_000_000_000_000 + np.arange(n, dtype=np.int64) * 25_000_000
    anchor = np.arange(n) % len(ids)
    rng, rx, fp = 1.0 + 0.5 * np.arange(n), -80.0 - np.arange(n), -90.0 - np.arange(n)
    datas = cdr_fast.encode_uwb_range(t, ids, anchor, rng, rx, fp)
    datas[5] = datas[5][:-3]  # truncated
    ok, cols = cdr_fast.decode_fixed(msgdefs.UWB_RANGE, datas)
    assert ok.tolist() == [i != 5 for i in range(n)]
    schema = Schema(id=1, name=msgdefs.UWB_RANGE, encoding="ros2msg",
                    data=msgdefs.schema_text(msgdefs.UWB_RANGE).encode())
    dec = DecoderFactory().decoder_for("cdr", schema)
    for i in np.flatnonzero(ok).tolist():
        m = dec(datas[i])
        assert cols["anchor_id"][i] == m.anchor_id == ids[anchor[i]]
        assert cols["range"][i] == np.float32(m.range)
        assert cols["rssi"][i] == np.float32(m.rssi)
        assert cols["first_path"][i] == np.float32(m.first_path_power)
        assert cols["t_ns"][i] == m.header.stamp.sec * 10**9 + m.header.stamp.nanosec


@pytest.mark.parametrize("command", ["run", "compare"])
def test_bad_model_fails_before_the_log_is_read(tmp_path: Path, command: str,
                                                capsys: pytest.CaptureFixture) -> None:
    model = tmp_path / "m.skops"
    model.write_bytes(b"not a model")
    cfg = tmp_path / "c.toml"
    cfg.write_text(f'[nlos]\nclassifier = "{model}"\n')
    missing_log = tmp_path / "absent.mcap"  # never opened: the model is refused first
    args = ([command, str(missing_log), "--config", str(cfg)]
            + (["--method", "wls", "-o", str(tmp_path / "e.tum")] if command == "run"
               else ["--methods", "wls", "--out", str(tmp_path / "out")]))
    assert main(args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "[nlos] classifier" in err[0] and "absent.mcap" not in err[0]


def test_power_change_and_first_path_excess() -> None:
    """test that rx_minus_fp_jump is the change of RX - FP since the anchor's previous range
    and that the first path above free space is lower under NLOS."""
    s = simulate_with_truth("warehouse-nlos", 20.0, seed=4, signal_quality=True)
    x, names = log_features(s.log, Config())
    gap = x[:, names.index("rx_minus_fp_db")]
    jump = x[:, names.index("rx_minus_fp_jump")]
    a = s.log.ranges.anchor
    i = np.flatnonzero(a == a[0])[:2]
    assert jump[i[1]] == pytest.approx(gap[i[1]] - gap[i[0]])
    fpx = x[:, names.index("fp_excess_db")]
    assert np.median(fpx[s.nlos]) < np.median(fpx[~s.nlos]) - 3.0



@pytest.mark.parametrize(("key", "value"), [
    ("label_threshold_m", "abc"), ("label_threshold_m", [1, 2]),
    ("label_threshold_m", float("nan")), ("label_threshold_m", -0.1),
    ("info", {"nlos_share": "abc"}), ("info", {"nlos_share": [1]}),
    ("info", {"nlos_share": float("nan")}), ("info", {"nlos_share": 2.0}),
])
def test_model_with_a_bad_threshold_or_nlos_share_is_one_line(
    tmp_path: Path, key: str, value: object, capsys: pytest.CaptureFixture
) -> None:
    """test that a model file whose label threshold is not a positive number or whose
    training NLOS share is not a number in [0, 1] is a one-line error naming the key, exit 2
    (float() raised ValueError / TypeError tracebacks at load or in the run, and a NaN share
    made NaN priors)."""
    p = _skops_dict(tmp_path / "m.skops", **{key: value})
    name = "nlos_share" if key == "info" else key
    with pytest.raises(ConfigError, match=name):
        load_classifier(p)
    _run_refuses_the_model(tmp_path, p, "ekf", capsys, name)
