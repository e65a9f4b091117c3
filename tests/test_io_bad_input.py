# SPDX-License-Identifier: BSD-3-Clause
"""Tests of `read_log` on bad input: one-line LogReadErrors, or partial reads with a report."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from mcap.well_known import MessageEncoding, SchemaEncoding
from mcap.writer import CompressionType

from tests.test_io_reader import _cdr_messages, _mcap
from tests.test_io_writer import small_log
from uwbfuse.config import Config, config_from_dict
from uwbfuse.errors import LogReadError, UwbfuseError
from uwbfuse.io import msgdefs
from uwbfuse.io.reader import read_log
from uwbfuse.io.writer import write_contract_log


def _one_line(err: pytest.ExceptionInfo[LogReadError], *parts: str) -> None:
    msg = str(err.value)
    assert "\n" not in msg
    for p in parts:
        assert p in msg, msg


def test_missing_path(tmp_path: Path) -> None:
    """test that a missing LOG path is a LogReadError naming it."""
    with pytest.raises(LogReadError) as e:
        read_log(tmp_path / "nope.mcap", Config())
    _one_line(e, "nope.mcap", "no such file")
    assert issubclass(LogReadError, UwbfuseError)


@pytest.mark.parametrize("content", [b"", b"hello world, not an mcap file", b"\x89MCAP"])
def test_not_an_mcap(tmp_path: Path, content: bytes) -> None:
    """test that empty and non-MCAP files are rejected by name."""
    p = tmp_path / "x.mcap"
    p.write_bytes(content)
    with pytest.raises(LogReadError) as e:
        read_log(p, Config())
    _one_line(e, str(p), "not an MCAP file")


def test_directory_without_mcap(tmp_path: Path) -> None:
    """test that a directory with neither metadata.yaml nor .mcap files is rejected."""
    (tmp_path / "notes.txt").write_text("hi")
    with pytest.raises(LogReadError) as e:
        read_log(tmp_path, Config())
    _one_line(e, str(tmp_path), "not a rosbag2 directory")


def test_rosbag2_listing_a_missing_file(tmp_path: Path) -> None:
    """test that metadata.yaml naming an absent file is an error naming that file."""
    (tmp_path / "metadata.yaml").write_text(
        "rosbag2_bagfile_information:\n  storage_identifier: mcap\n"
        "  relative_file_paths:\n  - gone_0.mcap\n"
    )
    with pytest.raises(LogReadError) as e:
        read_log(tmp_path, Config())
    _one_line(e, "gone_0.mcap", "missing")


def test_unknown_rosbag2_storage_rejected(tmp_path: Path) -> None:
    """test that a rosbag2 directory of a storage other than mcap/sqlite3 gets a clear error."""
    (tmp_path / "metadata.yaml").write_text(
        "rosbag2_bagfile_information:\n  storage_identifier: cdrfile\n"
        "  relative_file_paths:\n  - x_0.cdr\n"
    )
    with pytest.raises(LogReadError) as e:
        read_log(tmp_path, Config())
    _one_line(e, "cdrfile", "not supported")


@pytest.mark.parametrize("text", [
    "rosbag2_bagfile_information: [unclosed\n",
    "just a string\n",
    "rosbag2_bagfile_information:\n  relative_file_paths: 7\n",
    "rosbag2_bagfile_information:\n  compression_mode: message\n  compression_format: lz9\n",
    "rosbag2_bagfile_information:\n" + "  " + "[" * 5000 + "\n",
])
def test_bad_rosbag2_metadata_is_one_line(tmp_path: Path, text: str) -> None:
    """test that an unparsable or ill-typed metadata.yaml is one line naming the file."""
    (tmp_path / "metadata.yaml").write_text(text)
    with pytest.raises(LogReadError) as e:
        read_log(tmp_path, Config())
    _one_line(e, "metadata.yaml")


def test_empty_log(tmp_path: Path) -> None:
    """test that a valid MCAP without messages is an error."""
    p = tmp_path / "empty.mcap"
    _mcap(p, {"/imu": (msgdefs.IMU, MessageEncoding.CDR, SchemaEncoding.ROS2)}, [])
    with pytest.raises(LogReadError) as e:
        read_log(p, Config())
    _one_line(e, str(p), "no messages")


@pytest.mark.parametrize("compression", ["zstd", "none"])
def test_truncated_mcap_reads_what_is_complete(tmp_path: Path, compression: str) -> None:
    """test that a file cut in half yields its complete messages and a truncation warning."""
    log = small_log(4000)
    full = tmp_path / "full.mcap"
    write_contract_log(full, log, compression=compression, chunk_size=16384)
    data = full.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) // 2])
    got = read_log(cut, Config())
    assert got.imu is not None and 1000 < len(got.imu) < 4000
    n = len(got.imu)
    np.testing.assert_array_equal(got.imu.gyro, log.imu.gyro[:n])
    assert any("truncated" in w for w in got.report.warnings)
    assert got.anchors is None  # the metadata record was in the lost half


def test_truncated_unchunked_mcap(tmp_path: Path) -> None:
    """test that an unchunked file cut mid-record keeps every complete message."""
    log = small_log(500)
    topics, msgs = _cdr_messages(log)
    full = tmp_path / "full.mcap"
    _mcap(full, topics, msgs, chunked=False, indexed=False, summary=False,
          compression=CompressionType.NONE)
    data = full.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) // 2 + 7])
    got = read_log(cut, Config())
    n = len(got.imu)
    assert 150 < n < 400
    np.testing.assert_array_equal(got.imu.accel, log.imu.accel[:n])
    assert any("truncated" in w for w in got.report.warnings)


def test_truncated_to_nothing_usable(tmp_path: Path) -> None:
    """test that a file cut before its first message is an error, not an empty log."""
    full = tmp_path / "full.mcap"
    write_contract_log(full, small_log(50))
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(full.read_bytes()[:60])
    with pytest.raises(LogReadError) as e:
        read_log(cut, Config())
    _one_line(e, str(cut), "no messages")


def test_corrupt_chunk_is_skipped(tmp_path: Path) -> None:
    """test that a chunk whose compressed bytes are damaged is skipped with a warning."""
    log = small_log(4000)
    full = tmp_path / "full.mcap"
    write_contract_log(full, log, chunk_size=16384)
    data = bytearray(full.read_bytes())
    k = data.find(b"zstd") + 40  # inside the first chunk's compressed records
    data[k : k + 64] = b"\x00" * 64
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(bytes(data))
    got = read_log(bad, Config())
    assert 0 < len(got.imu) < 4000
    assert any("skipped" in w for w in got.report.warnings)


def test_configured_topic_absent_gives_none(tmp_path: Path) -> None:
    """test that a configured topic the log lacks is a None stream, not an error."""
    log = small_log(40)
    log.imu = None
    p = tmp_path / "noimu.mcap"
    write_contract_log(p, log)
    got = read_log(p, Config())
    assert got.imu is None
    assert got.wheel is not None and got.ranges is not None


def test_no_configured_topic_present_lists_topics(tmp_path: Path) -> None:
    """test that a log with none of the role topics names the topics it does have."""
    log = small_log(40)
    p = tmp_path / "log.mcap"
    write_contract_log(p, log)
    cfg = config_from_dict({"topics": {"imu": "/a", "wheel_odom": "/b", "uwb": "/c",
                                       "ground_truth": "/d"}})
    with pytest.raises(LogReadError) as e:
        read_log(p, cfg)
    _one_line(e, str(p), "/imu", "/wheel_odom", "/uwb/range", "/ground_truth", "[topics]")


def test_wrong_type_on_role_topic(tmp_path: Path) -> None:
    """test that an IMU topic carrying another type is an error naming topic and type."""
    log = small_log(40)
    p = tmp_path / "log.mcap"
    write_contract_log(p, log)
    cfg = config_from_dict({"topics": {"imu": "/wheel_odom", "wheel_odom": "/x"}})
    with pytest.raises(LogReadError) as e:
        read_log(p, cfg)
    _one_line(e, "/wheel_odom", "nav_msgs/Odometry", "imu")


def test_missing_uwb_field_names_config_key(tmp_path: Path) -> None:
    """test that a custom range type without the configured field names the [uwb] keys."""
    import json

    msgs = [("/uwb/range", 10**9 + k, json.dumps({"anchor": "A0", "dist": 1.0}).encode())
            for k in range(3)]
    p = tmp_path / "j.mcap"
    _mcap(p, {"/uwb/range": ("acme/msg/R", MessageEncoding.JSON, SchemaEncoding.JSONSchema)},
          msgs)
    with pytest.raises(LogReadError) as e:
        read_log(p, Config())
    _one_line(e, "/uwb/range", "anchor_id", "[uwb]")


def test_bad_anchor_metadata(tmp_path: Path) -> None:
    """test that a malformed uwb_anchors record is an error naming the anchor."""
    log = small_log(20)
    topics, msgs = _cdr_messages(log)
    p = tmp_path / "m.mcap"
    _mcap(p, topics, msgs, metadata={"uwb_anchors": {"A0": "[1, 2]"}})
    with pytest.raises(LogReadError) as e:
        read_log(p, Config())
    _one_line(e, "uwb_anchors", "A0", "[x, y, z]")


def test_unsupported_encoding_on_role_topic(tmp_path: Path) -> None:
    """test that a role topic in an unsupported encoding (protobuf) is a clear error."""
    p = tmp_path / "pb.mcap"
    _mcap(p, {"/imu": ("foxglove.Imu", "protobuf", "")}, [("/imu", 1, b"\x08\x01")])
    with pytest.raises(LogReadError) as e:
        read_log(p, Config())
    _one_line(e, "/imu", "protobuf")


def test_wrong_ground_truth_type_is_a_warning(tmp_path: Path) -> None:
    """test that an unusable ground-truth topic warns (GT is optional) instead of failing."""
    log = small_log(40)
    p = tmp_path / "log.mcap"
    write_contract_log(p, log)
    got = read_log(p, config_from_dict({"topics": {"ground_truth": "/imu"}}))
    assert got.ground_truth is None
    assert len(got.imu) == 40
    assert any("ground truth not read" in w and "/imu" in w for w in got.report.warnings)


def test_imu_type_on_uwb_topic_uses_field_mapping(tmp_path: Path) -> None:
    """test that a non-Range type on the UWB topic is read through [uwb] (here: no field)."""
    log = small_log(40)
    p = tmp_path / "log.mcap"
    write_contract_log(p, log)
    with pytest.raises(LogReadError) as e:
        read_log(p, config_from_dict({"topics": {"uwb": "/imu"}}))
    _one_line(e, "/imu", "anchor_id", "[uwb]")
