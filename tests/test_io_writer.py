# SPDX-License-Identifier: BSD-3-Clause
"""Tests of the contract-log writer and the vectorised CDR encoders."""

from __future__ import annotations

import json
from pathlib import Path
from types import SimpleNamespace as NS

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap_ros2._dynamic import serialize_dynamic
from mcap_ros2.decoder import DecoderFactory

from uwbfuse.errors import LogWriteError
from uwbfuse.io import cdr_fast, msgdefs
from uwbfuse.io.writer import write_contract_log
from uwbfuse.streams import AnchorMap, ImuStream, PoseStream, RangeStream, SensorLog, WheelStream

T0 = 1_700_000_000_123_456_789


def small_log(n: int = 400, seed: int = 0) -> SensorLog:
    """A short synthetic log: 200 Hz IMU, 50 Hz wheels, 40 Hz ranges, 100 Hz GT."""
    rng = np.random.default_rng(seed)
    t = T0 + np.arange(n, dtype=np.int64) * 5_000_000
    anchors = AnchorMap.from_dict({"A0": [0, 0, 1.5], "7475": [1, 2, 3], "B12": [4, 5, 6]})
    nr = len(t[::5])
    return SensorLog(
        imu=ImuStream(t, rng.normal(size=(n, 3)), rng.normal(size=(n, 3)) + np.array([0, 0, 9.81])),
        wheel=WheelStream(t[::4], rng.normal(size=len(t[::4])), rng.normal(size=len(t[::4]))),
        ranges=RangeStream(t[::5], rng.integers(0, 3, nr).astype(np.int32),
                           rng.uniform(0.5, 30, nr)),
        anchors=anchors,
        ground_truth=PoseStream(t[::2], rng.normal(size=(n // 2, 3)),
                                np.tile([0.0, 0.0, 0.6, 0.8], (n // 2, 1))),
    )


def _header(t: int, frame: str) -> NS:
    return NS(stamp=NS(sec=t // 10**9, nanosec=t % 10**9), frame_id=frame)


def _vec(a: np.ndarray) -> NS:
    return NS(x=float(a[0]), y=float(a[1]), z=float(a[2]))


def _quat(q: np.ndarray) -> NS:
    return NS(x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3]))


def _encoder(type_name: str):
    return serialize_dynamic(type_name, msgdefs.schema_text(type_name))[type_name]


def test_fast_encoders_match_mcap_ros2_bytes() -> None:
    """test that the vectorised encoders give exactly the bytes of mcap_ros2's encoder."""
    log = small_log(20)
    t = int(log.imu.t_ns[3])
    ref = _encoder(msgdefs.IMU)(NS(
        header=_header(t, "imu_link"), orientation=_quat([0, 0, 0, 1]),
        orientation_covariance=[-1.0] + [0.0] * 8, angular_velocity=_vec(log.imu.gyro[3]),
        angular_velocity_covariance=[0.0] * 9, linear_acceleration=_vec(log.imu.accel[3]),
        linear_acceleration_covariance=[0.0] * 9))
    assert cdr_fast.encode_imu(log.imu.t_ns, log.imu.gyro, log.imu.accel)[3] == ref

    w = log.wheel
    ref = _encoder(msgdefs.ODOMETRY)(NS(
        header=_header(int(w.t_ns[1]), "odom"), child_frame_id="base_link",
        pose=NS(pose=NS(position=_vec([0, 0, 0]), orientation=_quat([0, 0, 0, 1])),
                covariance=[0.0] * 36),
        twist=NS(twist=NS(linear=_vec([w.v[1], 0, 0]), angular=_vec([0, 0, w.omega[1]])),
                 covariance=[0.0] * 36)))
    assert cdr_fast.encode_odometry(w.t_ns, w.v, w.omega)[1] == ref

    r = log.ranges
    aid = log.anchors.ids[int(r.anchor[2])]
    ref = _encoder(msgdefs.RANGE)(NS(
        header=_header(int(r.t_ns[2]), aid), radiation_type=0, field_of_view=2 * np.pi,
        min_range=0.0, max_range=200.0, range=float(r.range[2])))
    assert cdr_fast.encode_range(r.t_ns, log.anchors.ids, r.anchor, r.range)[2] == ref
    rx, fp = -80.0 - r.range, -85.5 - r.range
    for i in (0, 2):  # anchor ids of different lengths: the floats' alignment moves
        aid = log.anchors.ids[int(r.anchor[i])]
        ref = _encoder(msgdefs.UWB_RANGE)(NS(
            header=_header(int(r.t_ns[i]), "uwb_tag"), anchor_id=aid, range=float(r.range[i]),
            rssi=float(rx[i]), first_path_power=float(fp[i])))
        assert cdr_fast.encode_uwb_range(r.t_ns, log.anchors.ids, r.anchor, r.range, rx,
                                         fp)[i] == ref

    g = log.ground_truth
    ref = _encoder(msgdefs.POSE_STAMPED)(NS(
        header=_header(int(g.t_ns[4]), "map"),
        pose=NS(position=_vec(g.position[4]), orientation=_quat(g.quat_xyzw[4]))))
    assert cdr_fast.encode_pose_stamped(g.t_ns, g.position, g.quat_xyzw)[4] == ref


@pytest.mark.parametrize("compression", ["zstd", "lz4", "none"])
def test_writer_output_decodes_with_mcap_ros2(tmp_path: Path, compression: str) -> None:
    """test that a written log decodes with mcap + mcap_ros2, log time = stamp, anchors kept."""
    log = small_log()
    out = tmp_path / "log.mcap"
    write_contract_log(out, log, compression=compression)
    counts: dict[str, int] = {}
    with out.open("rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        assert reader.get_header().profile == "ros2"
        for schema, channel, message, ros in reader.iter_decoded_messages():
            counts[channel.topic] = counts.get(channel.topic, 0) + 1
            stamp = ros.header.stamp.sec * 10**9 + ros.header.stamp.nanosec
            assert message.log_time == stamp
            if schema.name == msgdefs.IMU:
                assert ros.header.frame_id == "imu_link"
            if schema.name == msgdefs.RANGE:
                assert ros.header.frame_id in log.anchors.ids
            if schema.name == msgdefs.ODOMETRY:
                assert ros.child_frame_id == "base_link"
        meta = {m.name: m.metadata for m in reader.iter_metadata()}
    assert counts == {"/imu": 400, "/wheel_odom": 100, "/uwb/range": 80, "/ground_truth": 200}
    anchors = {k: json.loads(v) for k, v in meta["uwb_anchors"].items()}
    assert anchors == {"A0": [0.0, 0.0, 1.5], "7475": [1.0, 2.0, 3.0], "B12": [4.0, 5.0, 6.0]}


def test_writer_is_atomic(tmp_path: Path) -> None:
    """test that a failing write leaves neither the target nor a temporary file."""
    log = small_log(20)
    log.anchors = None  # ranges without ids cannot be written
    out = tmp_path / "bad.mcap"
    with pytest.raises(ValueError, match="anchor map"):
        write_contract_log(out, log)
    assert list(tmp_path.iterdir()) == []
    with pytest.raises(ValueError, match="compression"):
        write_contract_log(out, small_log(20), compression="gzip")
    assert list(tmp_path.iterdir()) == []


def test_writer_failure_mid_write_keeps_old_file(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """test that an error while writing is one LogWriteError, the old target untouched"""
    import uwbfuse.io.writer as writer_mod

    out = tmp_path / "log.mcap"
    out.write_bytes(b"old")

    def boom(*args: object, **kwargs: object) -> None:
        raise OSError("disk full")

    monkeypatch.setattr(writer_mod, "write_mcap", boom)
    with pytest.raises(LogWriteError, match="cannot write log: disk full"):
        write_contract_log(out, small_log(20))
    assert out.read_bytes() == b"old"
    assert [p.name for p in tmp_path.iterdir()] == ["log.mcap"]


def test_written_mcap_structure_checks_out(tmp_path: Path) -> None:
    """test the vectorised MCAP writer: CRCs, summary statistics, chunk and message indexes."""
    from mcap.records import DataEnd, Footer, Message, MessageIndex
    from mcap.stream_reader import StreamReader

    log = small_log(3000)
    out = tmp_path / "log.mcap"
    write_contract_log(out, log, chunk_size=8192)
    total = 3000 + 750 + 600 + 1500
    with out.open("rb") as f:  # the stream reader validates every chunk CRC
        kinds = [type(r) for r in StreamReader(f, validate_crcs=True).records]
    assert kinds.count(Message) == total
    assert kinds.count(MessageIndex) > 40
    assert kinds[-1] is Footer and DataEnd in kinds
    with out.open("rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary.statistics.message_count == total
        assert sorted(summary.statistics.channel_message_counts.values()) == [600, 750, 1500,
                                                                              3000]
        assert len(summary.chunk_indexes) > 10
        # log-time-ordered reading goes through the chunk and message indexes
        times = [m.log_time for _, _, m in reader.iter_messages(log_time_order=True)]
        assert len(times) == total and times == sorted(times)
        imu = [m for _, c, m in reader.iter_messages(topics=["/imu"])]
        assert [m.log_time for m in imu] == log.imu.t_ns.tolist()
