# SPDX-License-Identifier: BSD-3-Clause
"""Regression tests for what the fuzzer (scripts/fuzz.py) found: hostile logs, configs and
TUM files give a counted skip or one-line error, within bounded memory and time."""

from __future__ import annotations

import json
import struct
import time
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from mcap.writer import CompressionType
from mcap.writer import Writer as McapWriter

from tests.test_io_writer import small_log
from uwbfuse.cli import main
from uwbfuse.config import Config, config_from_dict, load_config
from uwbfuse.errors import (
    ConfigError,
    EstimatorError,
    EvaluationError,
    LogReadError,
    TrajectoryFileError,
)
from uwbfuse.estimator import MAX_EPOCHS, output_epochs
from uwbfuse.eval.evaluate import evaluate
from uwbfuse.io import cdr_fast, msgdefs, ros2msg
from uwbfuse.io.decoders import DecoderUnavailable, generic_decoder
from uwbfuse.io.fields import INVALID_STAMP, MAX_ANCHOR_ID_CHARS, time_to_ns
from uwbfuse.io.mcap_raw import MAX_CHUNK_BYTES, RawChannel, RawSchema, scan_mcap
from uwbfuse.io.reader import (
    SKIP_BAD_STAMP,
    SKIP_FAR_STAMP,
    SKIP_LONG_ANCHOR_ID,
    read_log,
    skip_malformed,
)
from uwbfuse.io.tum import read_tum, write_tum
from uwbfuse.io.writer import write_contract_log
from uwbfuse.streams import PoseStream, SensorLog, WheelStream

T0 = 1_700_000_000 * 10**9
ANCHORS = {"A0": "[0, 0, 1.5]", "A1": "[10, 0, 1.5]", "A2": "[0, 8, 1.5]"}


def _write(path: Path, channels: list[tuple[str, str, str, str, str]],
           messages: list[tuple[int, int, bytes]], anchors: dict[str, str] | None = None,
           compression: CompressionType = CompressionType.ZSTD) -> Path:
    """channels: (topic, schema, schema encoding, schema text, message encoding)."""
    with path.open("wb") as f:
        w = McapWriter(f, compression=compression, chunk_size=4096)
        w.start(profile="ros2", library="test")
        ids = [w.register_channel(topic, menc, w.register_schema(name, senc, text.encode()))
               for topic, name, senc, text, menc in channels]
        w.add_metadata("uwb_anchors", ANCHORS if anchors is None else anchors)
        for k, t, data in messages:
            w.add_message(ids[k], log_time=t, data=data, publish_time=t)
        w.finish()
    return path


def _ros(topic: str, type_name: str) -> tuple[str, str, str, str, str]:
    return topic, type_name, "ros2msg", msgdefs.schema_text(type_name), "cdr"


def _wheel_log(path: Path, v: np.ndarray, t: np.ndarray | None = None) -> Path:
    t = T0 + np.arange(len(v), dtype=np.int64) * 20_000_000 if t is None else t
    datas = cdr_fast.encode_odometry(t, v, np.zeros(len(v)))
    return _write(path, [_ros("/wheel_odom", msgdefs.ODOMETRY)],
                  [(0, int(x), d) for x, d in zip(t.tolist(), datas, strict=True)])


def _run(argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, list[str]]:
    code = main(argv)
    err = [x for x in capsys.readouterr().err.splitlines() if x.strip()]
    return code, err


# ------------------------------------------------------------------------------------------
# chunks: decompression bombs and declared sizes


def _zstd_zeros(size: int) -> bytes:
    """A zstd frame of `size` zeros from RLE blocks, content size in the header."""
    block = 1 << 17
    sizes = [block] * (size // block) + ([size % block] if size % block else [])
    head = struct.pack("<I", 0xFD2FB528) + bytes([0xC0, 0x38]) + struct.pack("<Q", size)
    return head + b"".join(struct.pack("<I", (n << 3) | 2 | (k == len(sizes) - 1))[:3]
                           + b"\x00" for k, n in enumerate(sizes))


def _chunk(compressed: bytes, declared: int, compression: bytes = b"zstd") -> bytes:
    body = (struct.pack("<QQQII", 0, 0, declared, 0, len(compression)) + compression
            + struct.pack("<Q", len(compressed)) + compressed)
    return b"\x06" + struct.pack("<Q", len(body)) + body


def _with_chunk(tmp_path: Path, chunk: bytes, cut: int = 0) -> Path:
    """A valid small log with `chunk` appended to its data section (cut short by `cut`)."""
    good = tmp_path / "good.mcap"
    write_contract_log(good, small_log())
    data = good.read_bytes()
    end = data.find(b"\x0f" + struct.pack("<Q", 4))  # DataEnd
    out = tmp_path / "bomb.mcap"
    blob = data[:end] + chunk
    out.write_bytes(blob[: len(blob) - cut] if cut else blob)
    return out


@pytest.mark.parametrize("cut", [0, 60_000])
def test_zstd_chunk_declaring_4gib_is_skipped_not_allocated(tmp_path: Path, cut: int) -> None:
    """test that a 128 KiB zstd chunk declaring (and holding) 4 GiB is a counted skip, also
    as a truncated last chunk, and the rest of the log is read"""
    p = _with_chunk(tmp_path, _chunk(_zstd_zeros(4 << 30), 4 << 30), cut)
    t = time.perf_counter()
    log = read_log(p, Config())
    assert time.perf_counter() - t < 5
    assert log.imu is not None and len(log.imu) == 400
    assert any("more than the 128 MiB limit" in w for w in log.report.warnings)


def test_zstd_frame_larger_than_declared_is_skipped(tmp_path: Path) -> None:
    """test that a zstd frame holding more than its chunk declares stops at the declared
    size (its own header says 4 GiB)"""
    p = _with_chunk(tmp_path, _chunk(_zstd_zeros(4 << 30), 1000))
    log = read_log(p, Config())
    assert any("more than its declared 1000 bytes" in w for w in log.report.warnings)


def test_lz4_frame_larger_than_declared_is_skipped(tmp_path: Path) -> None:
    """test that an lz4 chunk that decompresses past its declared size is skipped"""
    import lz4.frame

    p = _with_chunk(tmp_path, _chunk(lz4.frame.compress(bytes(1 << 20)), 4096, b"lz4"))
    log = read_log(p, Config())
    assert any("more than its declared 4096 bytes" in w for w in log.report.warnings)
    assert MAX_CHUNK_BYTES >= 32 << 20


def test_chunk_of_empty_records_is_walked_in_bounded_memory(tmp_path: Path) -> None:
    """test that a 4 MiB chunk of 9-byte records (466,000 of them) reads without a list of
    Python ints per record"""
    import tracemalloc

    p = _with_chunk(tmp_path, _chunk(_zstd_zeros(4 << 20), 4 << 20))
    tracemalloc.start()
    scan_mcap(p, lambda ch: None)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert peak < 4 * 2**20 * 2.5, peak


# ------------------------------------------------------------------------------------------
# schemas


def _loop_schema(depth: int | None) -> str:
    sep = "\n" + "=" * 80 + "\n"
    if depth is None:
        return "pkg/Loop a\nfloat64 x" + sep + "MSG: pkg/Loop\npkg/Loop a\npkg/Loop b\n"
    parts = ["pkg/N0 n"] + [f"MSG: pkg/N{d}\npkg/N{d + 1} a\npkg/N{d + 1} b"
                            for d in range(depth)] + [f"MSG: pkg/N{depth}\nfloat64 x"]
    return sep.join(parts) + "\n"


@pytest.mark.parametrize(("depth", "match"), [(None, "contains itself"), (40, "deeper"),
                                              (25, "more than")])
def test_schema_bombs_are_rejected_quickly(depth: int | None, match: str) -> None:
    """test that a recursive schema, one nested 40 deep and one that flattens to 2^25
    fields raise SchemaError at once"""
    t = time.perf_counter()
    with pytest.raises(ros2msg.SchemaError, match=match):
        ros2msg.layout_of("pkg/msg/Top", _loop_schema(depth))
    assert time.perf_counter() - t < 1.0


def test_bomb_schema_under_a_fast_type_name_reads_quickly(tmp_path: Path) -> None:
    """test that a Range channel whose schema is a 30-level two-field bomb (the old parser:
    2^30 calls) is refused in well under a second, with a one-line error"""
    t = T0 + np.arange(20, dtype=np.int64) * 10**8
    datas = cdr_fast.encode_range(t, ["A0"], np.zeros(20, int), np.full(20, 3.0))
    p = _write(tmp_path / "b.mcap", [("/uwb/range", msgdefs.RANGE, "ros2msg",
                                      _loop_schema(30), "cdr")],
               [(0, int(x), d) for x, d in zip(t.tolist(), datas, strict=True)])
    start = time.perf_counter()
    with pytest.raises(LogReadError, match="cannot parse schema") as e:
        read_log(p, Config())
    assert time.perf_counter() - start < 2.0
    assert "\n" not in str(e.value)


def test_real_schemas_keep_their_layout() -> None:
    """test that the bounded parser gives the same layouts for the ROS 2 types"""
    for name in (msgdefs.IMU, msgdefs.ODOMETRY, msgdefs.RANGE, msgdefs.JOINT_STATE):
        layout = ros2msg.layout_of(name, msgdefs.schema_text(name))
        assert layout is not None and len(layout) > 3
        assert cdr_fast.fast_type(name, "ros2msg", msgdefs.schema_text(name)) == (
            None if name == msgdefs.JOINT_STATE else name)


def test_generic_decoder_refuses_a_recursive_schema(capfd: pytest.CaptureFixture[str]) -> None:
    """test that the cdr decoder factory is never handed a recursive schema, and that a
    schema it cannot parse prints nothing of its own"""
    for text in (_loop_schema(None), "std_msgs/Header header\nfloat64[ x\n"):
        ch = RawChannel(1, "/uwb/range", "cdr", RawSchema(1, "pkg/msg/Top", "ros2msg",
                                                          text.encode()))
        with pytest.raises(DecoderUnavailable, match="cannot parse schema"):
            generic_decoder(ch)
    out = capfd.readouterr()
    assert out.out == "" and out.err == ""


@settings(max_examples=150, deadline=None)
@given(st.text(alphabet=st.sampled_from("abc/ [] <=123\n=#MSG:float64 string pkg/A"),
               max_size=300))
def test_schema_parser_is_total(text: str) -> None:
    """test that any schema text gives a layout, None or SchemaError (nothing else)"""
    try:
        ros2msg.layout_of("pkg/msg/A", text)
    except ros2msg.SchemaError:
        pass


def test_bit_flipped_schema_text_is_read_or_skipped(tmp_path: Path) -> None:
    """test that an IMU channel whose schema text has a flipped bit reads without a
    traceback (no rows decoded -> an empty stream, not a reshape error)"""
    text = bytearray(msgdefs.schema_text(msgdefs.IMU).encode())
    text[30] ^= 0x08
    t = T0 + np.arange(50, dtype=np.int64) * 5_000_000
    datas = cdr_fast.encode_imu(t, np.zeros((50, 3)), np.zeros((50, 3)))
    p = _write(tmp_path / "f.mcap", [("/imu", msgdefs.IMU, "ros2msg", text.decode(), "cdr")],
               [(0, int(x), d) for x, d in zip(t.tolist(), datas, strict=True)])
    try:
        log = read_log(p, Config())
    except LogReadError as e:
        assert "\n" not in str(e)
    else:
        assert log.imu is None or len(log.imu) in (0, 50)


# ------------------------------------------------------------------------------------------
# stamps


@pytest.mark.parametrize(("stamp", "want"), [
    (None, 0), ("NaN", INVALID_STAMP), (float("nan"), INVALID_STAMP), (True, INVALID_STAMP),
    (10**30, INVALID_STAMP), (1e300, INVALID_STAMP), ([1, 2], INVALID_STAMP),
    ({"sec": 1, "nanosec": "x"}, INVALID_STAMP), ({"sec": 2.0, "nanosec": 5}, 2 * 10**9 + 5),
    ({"sec": 10**12, "nanosec": 0}, INVALID_STAMP), (1.5, 1_500_000_000),
])
def test_time_to_ns_is_total(stamp: object, want: int) -> None:
    """test that null/"NaN"/huge/list stamps give 0 (no stamp) or INVALID_STAMP, never an
    exception"""
    assert time_to_ns(stamp) == want


@given(st.recursive(st.none() | st.booleans() | st.integers() | st.floats() | st.text(),
                    lambda c: st.lists(c, max_size=3) | st.dictionaries(
                        st.sampled_from(["sec", "nanosec", "nsec", "secs", "nsecs", "x"]), c,
                        max_size=3), max_leaves=8))
def test_time_to_ns_never_raises(stamp: object) -> None:
    """test that any JSON value as a stamp gives an int64 nanosecond value"""
    assert -(1 << 63) < time_to_ns(stamp) < 1 << 63


def _sensor_log(tmp_path: Path, edit_t: dict[str, tuple[int, int]]) -> Path:
    """small_log with stamp edits {stream: (index, new stamp)}, written as MCAP."""
    base = small_log()
    imu, wheel, ranges = base.imu, base.wheel, base.ranges
    assert imu is not None and wheel is not None and ranges is not None
    streams = {"imu": imu.t_ns.copy(), "wheel": wheel.t_ns.copy(), "uwb": ranges.t_ns.copy()}
    for name, (i, t) in edit_t.items():
        streams[name][i] = t
    a = base.anchors
    assert a is not None
    msgs: list[tuple[int, int, bytes]] = []
    for k, datas, t in (
        (0, cdr_fast.encode_imu(streams["imu"], imu.gyro, imu.accel), streams["imu"]),
        (1, cdr_fast.encode_odometry(streams["wheel"], wheel.v, wheel.omega), streams["wheel"]),
        (2, cdr_fast.encode_range(streams["uwb"], a.ids, ranges.anchor, ranges.range),
         streams["uwb"]),
    ):
        msgs += [(k, max(int(x), 0), d) for x, d in zip(t.tolist(), datas, strict=True)]
    return _write(tmp_path / "s.mcap", [_ros("/imu", msgdefs.IMU),
                                        _ros("/wheel_odom", msgdefs.ODOMETRY),
                                        _ros("/uwb/range", msgdefs.RANGE)], msgs,
                  anchors={k: json.dumps(list(map(float, p)))
                           for k, p in zip(a.ids, a.positions, strict=True)})


@pytest.mark.parametrize("edit", [
    {"uwb": (3, T0 + 10**17)},  # a range stamped three years ahead
    {"imu": (7, 1_800_000_000 * 10**9)},  # an IMU sample on another clock
    {"wheel": (5, 0)},  # zero stamp, log time 0
])
def test_far_off_stamps_are_dropped_and_counted(tmp_path: Path, edit: dict) -> None:
    """test that a stamp far from the rest of the log is a counted skip and the output grid
    keeps the log's span"""
    log = read_log(_sensor_log(tmp_path, edit), Config())
    assert log.report.skipped[SKIP_FAR_STAMP] == 1
    t0, t1 = log.time_span_ns()
    assert t1 - t0 < 10 * 10**9
    assert len(output_epochs(log, 10.0)) < 100


def test_negative_stamps_are_counted(tmp_path: Path) -> None:
    """test that a negative header stamp is dropped as a bad stamp"""
    log = read_log(_sensor_log(tmp_path, {"imu": (2, -10**9), "uwb": (1, -5)}), Config())
    assert log.report.skipped[SKIP_BAD_STAMP] == 2


def test_output_grid_is_capped() -> None:
    """test that a span needing more than MAX_EPOCHS epochs is a one-line EstimatorError,
    not a 33 GiB allocation"""
    t = np.array([0, 10**18], dtype=np.int64)
    log = SensorLog(wheel=WheelStream(t, np.zeros(2), np.zeros(2)), source="x.mcap")
    with pytest.raises(EstimatorError, match="one clock"):
        output_epochs(log, 10.0)
    assert MAX_EPOCHS >= 10**6


# ------------------------------------------------------------------------------------------
# values


@pytest.mark.parametrize("v", [-1e308, 1e300, 150.0])
def test_absurd_wheel_twist_is_a_counted_skip(tmp_path: Path, v: float,
                                              capsys: pytest.CaptureFixture[str]) -> None:
    """test that a wheel speed past MAX_WHEEL_SPEED_M_S is dropped and odom runs"""
    speeds = np.full(100, 0.5)
    speeds[40] = v
    p = _wheel_log(tmp_path / "w.mcap", speeds)
    log = read_log(p, Config())
    assert log.wheel is not None and len(log.wheel) == 99
    assert log.report.skipped["implausible wheel sample (beyond the physical bounds)"] == 1
    code, err = _run(["run", str(p), "--method", "odom", "-o", str(tmp_path / "o.tum")],
                     capsys)
    assert code == 0, err
    assert not any("Warning" in x for x in err)


def test_single_wheel_message_is_rejected(tmp_path: Path,
                                          capsys: pytest.CaptureFixture[str]) -> None:
    """test that a log of one wheel message is not run (a stream needs two samples)"""
    p = _wheel_log(tmp_path / "w.mcap", np.array([0.5]))
    out = tmp_path / "o.tum"
    code, err = _run(["run", str(p), "--method", "odom", "-o", str(out)], capsys)
    assert code == 2 and len(err) == 1 and "wheel" in err[0], err
    assert not out.exists()


def test_log_shorter_than_one_output_period_is_rejected(tmp_path: Path,
                                                       capsys: pytest.CaptureFixture[str]) -> None:
    """test that two wheel messages 20 ms apart (less than the 0.1 s output period) are a
    one-line error, not a one-pose trajectory"""
    p = _wheel_log(tmp_path / "w.mcap", np.array([0.5, 0.5]))
    out = tmp_path / "o.tum"
    code, err = _run(["run", str(p), "--method", "odom", "-o", str(out)], capsys)
    assert code == 2 and len(err) == 1 and "less than one output period" in err[0], err
    assert not out.exists()


def test_one_mib_anchor_id_is_capped(tmp_path: Path) -> None:
    """test that Range messages with 1 MiB frame ids are dropped as too long without
    building a fixed-width array of that width per range"""
    import tracemalloc

    n = 200
    t = T0 + np.arange(n, dtype=np.int64) * 25_000_000
    ids = ["A0", "A1", "A2", "X" * (1 << 20)]
    which = np.arange(n) % 4
    datas = cdr_fast.encode_range(t, ids, which, np.full(n, 3.0))
    p = _write(tmp_path / "r.mcap", [_ros("/uwb/range", msgdefs.RANGE)],
               [(0, int(x), d) for x, d in zip(t.tolist(), datas, strict=True)])
    tracemalloc.start()
    log = read_log(p, Config())
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert log.report.skipped[SKIP_LONG_ANCHOR_ID] == n // 4
    assert log.ranges is not None and len(log.ranges) == n - n // 4
    assert peak < 300 * 2**20
    assert MAX_ANCHOR_ID_CHARS == 256


@pytest.mark.parametrize("value", ["[true, 1, 2]", "[" * 100000 + "]" * 100000,
                                   "[" + "9" * 400 + ", 0, 0]", "[1e308, 0, 0]", "[1, 2",
                                   '{"x": 1}'])
def test_bad_anchor_records_are_rejected(tmp_path: Path, value: str) -> None:
    """test that a uwb_anchors value that is not three finite, sane numbers is a one-line
    error (booleans, a 100,000-deep nesting, an int past float range, 1e308)"""
    p = _write(tmp_path / "a.mcap", [_ros("/wheel_odom", msgdefs.ODOMETRY)],
               [(0, T0, cdr_fast.encode_odometry(np.array([T0]), np.ones(1), np.ones(1))[0])],
               anchors={**ANCHORS, "A1": value})
    with pytest.raises(LogReadError, match="expected a JSON array") as e:
        read_log(p, Config())
    assert "\n" not in str(e.value) and len(str(e.value)) < 400


@pytest.mark.parametrize(("stamp", "v"), [(None, 0.5), ("NaN", 0.5), ({"sec": 1}, 0.5),
                                          (None, "fast"), (None, [1, 2]), (None, 10**400)])
def test_json_wheel_messages_with_bad_fields(tmp_path: Path, stamp: object, v: object) -> None:
    """test that JSON odometry with a null/"NaN"/partial stamp or a non-number speed is read
    with those messages counted, not a TypeError"""
    msgs = []
    for k in range(60):
        t = T0 + k * 20_000_000
        st_ = stamp if k == 10 else {"sec": t // 10**9, "nanosec": t % 10**9}
        speed = v if k == 11 else 0.5
        msg = {"header": {"stamp": st_}, "twist": {"twist": {"linear": {"x": speed},
                                                              "angular": {"z": 0.0}}}}
        msgs.append((0, t, json.dumps(msg).encode()))
    p = _write(tmp_path / "j.mcap", [("/wheel_odom", "nav_msgs/msg/Odometry", "jsonschema",
                                      "", "json")], msgs)
    log = read_log(p, Config())
    assert log.wheel is not None and 58 <= len(log.wheel) <= 60
    if v != 0.5:
        assert log.report.skipped[skip_malformed("/wheel_odom")] == 1


# ------------------------------------------------------------------------------------------
# config


@pytest.mark.parametrize("text", [
    "[uwb]\nsigma = nan\n", "[uwb]\nsigma = inf\n", "[wls]\nwindow = -inf\n",
    "[uwb.range_offset]\nA0 = nan\n", "[nlos.anchor]\nA0 = [nan, 0.1, 0.1, 0.5]\n",
    "[wheel]\ntrack_width = \"0.5\"\n", "[wheel]\ntrack_width = true\n",
    "[output]\nrate = 1e-320\n", "[graph]\nlag = 1e300\n", "[anchors]\nA0 = [true, 1, 2]\n",
    "[ukf]\nbeta = inf\n", "[nlos.anchor]\nA0 = [-0.1, 0.1, 0.1, 0.2]\n",
    "[nlos.anchor]\nA0 = [0.03, 0.1, 1e-300, 0.2]\n", "[nlos.anchor]\nA0 = [0.03, 0.1, 0.1, 1.5]\n",
])
def test_config_rejects_non_finite_and_coerced_values(tmp_path: Path, text: str) -> None:
    """test that inf/NaN, booleans or text for numbers and absurd magnitudes are errors"""
    p = tmp_path / "c.toml"
    p.write_text(text)
    with pytest.raises(ConfigError, match="bad value for") as e:
        load_config(p)
    assert "\n" not in str(e.value)


def test_config_accepts_tiny_signed_coordinates(tmp_path: Path) -> None:
    """test that a quaternion or position component computed in float64 (cos(pi / 2) =
    6e-17) is a valid setting: the lower magnitude bound is for positive quantities only"""
    p = tmp_path / "c.toml"
    p.write_text("[extrinsics]\nimu_in_base = [0.1, 0, 0.2, 0, 0, 1.0, 6.123233995736766e-17]\n"
                 "tag_in_base = [1e-17, 0, 0.5]\n[anchors]\nA0 = [-3e-15, 0, 2]\n")
    cfg = load_config(p)
    assert cfg.extrinsics.imu_in_base[6] == pytest.approx(6.123233995736766e-17)
    assert cfg.anchors["A0"][0] == pytest.approx(-3e-15)


def test_config_that_is_not_utf8_or_not_a_file(tmp_path: Path) -> None:
    """test that a config with bytes that are not UTF-8, or a path through a file, is a
    ConfigError (not UnicodeDecodeError / NotADirectoryError)"""
    p = tmp_path / "c.toml"
    p.write_bytes(b"[uwb]\n# \xff\xfe\n")
    with pytest.raises(ConfigError, match="not a UTF-8"):
        load_config(p)
    with pytest.raises(ConfigError, match="cannot read config"):
        load_config(p / "inner.toml")


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.dictionaries(
    st.sampled_from(["uwb", "wheel", "wls", "graph", "output", "anchors", "imu"]),
    st.dictionaries(st.sampled_from(["sigma", "track_width", "window", "lag", "rate", "A0",
                                     "gravity", "radius", "x"]),
                    st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=4)
                    | st.lists(st.floats() | st.booleans(), max_size=4), max_size=3),
    max_size=3))
def test_config_validation_is_total(data: dict) -> None:
    """test that any TOML-shaped dict is a Config or a ConfigError, and an accepted one
    holds only finite numbers"""
    data = {k: {kk: vv for kk, vv in v.items() if vv is not None} for k, v in data.items()}
    try:
        cfg = config_from_dict(data)
    except ConfigError:
        return
    for section in ("uwb", "wheel", "wls", "output", "imu"):
        for v in getattr(cfg, section).model_dump().values():
            if isinstance(v, float):
                assert np.isfinite(v)


# ------------------------------------------------------------------------------------------
# eval / TUM


def _tum(path: Path, rows: list[str]) -> Path:
    path.write_text("\n".join(rows) + "\n")
    return path


@pytest.mark.parametrize(("row", "match"), [
    ("9300000000.5 0 0 0 0 0 0 1", "out of range"),
    ("99999999999999999999 0 0 0 0 0 0 1", "out of range|not a number"),
    ("1 0 0 0 1e-200 0 0 1e-200", "zero quaternion"),
    ("1 1e308 0 0 0 0 0 1", "position beyond"),
])
def test_tum_rows_out_of_range_are_errors(tmp_path: Path, row: str, match: str) -> None:
    """test that a stamp past 2^63 ns, a 1e-200 quaternion and a 1e308 coordinate are
    one-line TrajectoryFileErrors"""
    p = _tum(tmp_path / "e.tum", ["0 0 0 0 0 0 0 1", row])
    with pytest.raises(TrajectoryFileError, match=match) as e:
        read_tum(p)
    assert "\n" not in str(e.value)


def test_a_huge_quaternion_is_an_error_without_an_overflow_warning(tmp_path: Path) -> None:
    """test that a 1e308 quaternion component is a one-line TrajectoryFileError and raises
    no RuntimeWarning on the way (its norm's squares overflowed in np.linalg.norm's dot)"""
    import warnings

    p = _tum(tmp_path / "e.tum", ["0 0 0 0 0 0 0 1", "1 0 0 0 1e308 1e308 0 1"])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(TrajectoryFileError, match="huge quaternion"):
            read_tum(p)


@settings(max_examples=200, deadline=None)
@given(st.lists(st.lists(st.sampled_from(["0", "1", "-1", "1e308", "nan", "inf", "1e-200",
                                          "9.3e9", "x", "1.000000000001", ""]),
                         min_size=6, max_size=9), min_size=1, max_size=5))
def test_tum_reader_is_total(tmp_path_factory: pytest.TempPathFactory,
                             rows: list[list[str]]) -> None:
    """test that any rows of tokens give a PoseStream of finite unit poses or a
    TrajectoryFileError"""
    p = tmp_path_factory.mktemp("tum") / "x.tum"
    p.write_text("\n".join(" ".join(r) for r in rows) + "\n")
    try:
        s = read_tum(p)
    except TrajectoryFileError:
        return
    assert np.isfinite(s.position).all() and np.allclose(np.linalg.norm(s.quat_xyzw, axis=1), 1)


def test_eval_with_far_apart_poses_is_not_inf(tmp_path: Path) -> None:
    """test that errors that overflow are an EvaluationError, not an inf ATE with exit 0"""
    t = T0 + np.arange(20, dtype=np.int64) * 10**8
    q = np.tile([0.0, 0.0, 0.0, 1.0], (20, 1))
    gt = PoseStream(t, np.zeros((20, 3)), q)
    est = PoseStream(t, np.full((20, 3), 1e200), q)
    with pytest.raises(EvaluationError, match="not finite"):
        evaluate(est, gt, align="none")


def test_eval_cli_on_bad_tum_is_one_line(tmp_path: Path,
                                         capsys: pytest.CaptureFixture[str]) -> None:
    """test that duplicated stamps (a warning) and too few poses give exactly one stderr
    line, and a tiny quaternion with --align se3 no traceback"""
    t = T0 + np.arange(30, dtype=np.int64) * 10**8
    q = np.tile([0.0, 0.0, 0.0, 1.0], (30, 1))
    gt = tmp_path / "gt.tum"
    write_tum(gt, PoseStream(t, np.zeros((30, 3)), q))
    est = _tum(tmp_path / "e.tum", [f"{T0 / 1e9:.9f} 0 0 0 0 0 0 1"] * 30)
    code, err = _run(["eval", str(est), "--gt", str(gt)], capsys)
    assert code == 2 and len(err) == 1, err
    est = _tum(tmp_path / "e2.tum", [f"{T0 / 1e9:.9f} 0 0 0 1e-200 0 0 1e-200"])
    code, err = _run(["eval", str(est), "--gt", str(gt), "--align", "se3"], capsys)
    assert code == 2 and len(err) == 1 and "quaternion" in err[0], err
