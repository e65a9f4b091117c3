# SPDX-License-Identifier: BSD-3-Clause
"""Tests of `read_log` on logs written by our writer and by independent tools."""

from __future__ import annotations

import json
import struct
from pathlib import Path
from types import SimpleNamespace as NS
from typing import Any

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap.well_known import MessageEncoding, SchemaEncoding
from mcap.writer import CompressionType, IndexType
from mcap.writer import Writer as McapWriter
from mcap_ros2.decoder import DecoderFactory

from tests.test_io_writer import T0, small_log
from uwbfuse.config import Config, config_from_dict
from uwbfuse.io import cdr_fast, msgdefs
from uwbfuse.io.reader import (
    SKIP_INVALID_FLAG,
    SKIP_NO_ANCHOR_MAP,
    SKIP_NON_FINITE_RANGE,
    SKIP_NON_POSITIVE_RANGE,
    SKIP_RANGE_BOUNDS,
    SKIP_UNKNOWN_ANCHOR,
    read_log,
    skip_duplicate,
)
from uwbfuse.io.writer import write_contract_log
from uwbfuse.streams import SensorLog

RNG = np.random.default_rng(7)


def assert_same_log(got: SensorLog, want: SensorLog, range_tol: float = 1e-6) -> None:
    """The streams of `got` equal those of `want` (ranges are float32 on the wire)."""
    assert got.imu is not None and want.imu is not None
    np.testing.assert_array_equal(got.imu.t_ns, want.imu.t_ns)
    np.testing.assert_array_equal(got.imu.gyro, want.imu.gyro)
    np.testing.assert_array_equal(got.imu.accel, want.imu.accel)
    np.testing.assert_array_equal(got.wheel.t_ns, want.wheel.t_ns)
    np.testing.assert_array_equal(got.wheel.v, want.wheel.v)
    np.testing.assert_array_equal(got.wheel.omega, want.wheel.omega)
    assert got.anchors is not None
    assert got.anchors.ids == want.anchors.ids
    np.testing.assert_array_equal(got.anchors.positions, want.anchors.positions)
    np.testing.assert_array_equal(got.ranges.t_ns, want.ranges.t_ns)
    np.testing.assert_array_equal(got.ranges.anchor, want.ranges.anchor)
    np.testing.assert_allclose(got.ranges.range, want.ranges.range, rtol=range_tol)
    np.testing.assert_array_equal(got.ground_truth.t_ns, want.ground_truth.t_ns)
    np.testing.assert_array_equal(got.ground_truth.position, want.ground_truth.position)
    np.testing.assert_allclose(got.ground_truth.quat_xyzw, want.ground_truth.quat_xyzw)


@pytest.mark.parametrize("compression", ["zstd", "lz4", "none"])
def test_round_trip(tmp_path: Path, compression: str) -> None:
    """test that writer -> reader gives back every stream, anchors from the metadata."""
    log = small_log()
    path = tmp_path / "log.mcap"
    write_contract_log(path, log, compression=compression, chunk_size=4096)
    got = read_log(path, Config())
    assert_same_log(got, log)
    assert got.source == str(path)
    assert dict(got.report.messages) == {
        "/imu": 400, "/wheel_odom": 100, "/uwb/range": 80, "/ground_truth": 200}
    assert not got.report.skipped and not got.report.warnings


def _decode_all_generic(path: Path) -> dict[str, list[tuple[str, bytes, object]]]:
    out: dict[str, list[tuple[str, bytes, object]]] = {}
    with path.open("rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for schema, channel, message, ros in reader.iter_decoded_messages():
            out.setdefault(channel.topic, []).append((schema.name, message.data, ros))
    return out


def check_fast_matches_generic(path: Path) -> int:
    """Decode every fixed-layout message of `path` both ways; return how many were compared."""
    compared = 0
    for items in _decode_all_generic(path).values():
        type_name = items[0][0]
        if type_name not in cdr_fast.FAST_TYPES:
            continue
        ok, cols = cdr_fast.decode_fixed(type_name, [d for _, d, _ in items])
        assert ok.all()
        for i, (_, _, m) in enumerate(items):
            st = m.header.stamp
            assert cols["t_ns"][i] == st.sec * 10**9 + st.nanosec
            if type_name == msgdefs.IMU:
                av, la = m.angular_velocity, m.linear_acceleration
                assert tuple(cols["gyro"][i]) == (av.x, av.y, av.z)
                assert tuple(cols["accel"][i]) == (la.x, la.y, la.z)
            elif type_name == msgdefs.ODOMETRY:
                assert cols["v"][i] == m.twist.twist.linear.x
                assert cols["omega"][i] == m.twist.twist.angular.z
                p, q = m.pose.pose.position, m.pose.pose.orientation
                assert tuple(cols["position"][i]) == (p.x, p.y, p.z)
                assert tuple(cols["quat"][i]) == (q.x, q.y, q.z, q.w)
            elif type_name == msgdefs.RANGE:
                assert cols["frame_id"][i] == m.header.frame_id
                assert cols["range"][i] == np.float32(m.range)
            else:
                pose = m.transform if type_name == msgdefs.TRANSFORM_STAMPED else m.pose
                p = pose.translation if type_name == msgdefs.TRANSFORM_STAMPED else pose.position
                q = pose.rotation if type_name == msgdefs.TRANSFORM_STAMPED else pose.orientation
                assert tuple(cols["position"][i]) == (p.x, p.y, p.z)
                assert tuple(cols["quat"][i]) == (q.x, q.y, q.z, q.w)
            compared += 1
    return compared


def test_fast_decoder_matches_generic_on_simulated_log(tmp_path: Path) -> None:
    """test that the vectorised decoder agrees with mcap_ros2 on every simulated message."""
    path = tmp_path / "log.mcap"
    write_contract_log(path, small_log(200))
    assert check_fast_matches_generic(path) == 200 + 50 + 40 + 100


# ------------------------------------------------------------------------------------------
# hand-built MCAP files (mcap writer directly): cdr bytes from our encoders or json


def _mcap(
    path: Path,
    topics: dict[str, tuple[str, str, str]],
    messages: list[tuple[str, int, bytes]],
    *,
    metadata: dict[str, dict[str, str]] | None = None,
    chunked: bool = True,
    indexed: bool = True,
    summary: bool = True,
    compression: CompressionType = CompressionType.ZSTD,
    chunk_size: int = 2048,
) -> None:
    """topics: topic -> (type, message encoding, schema encoding); messages: (topic, log
    time, bytes)."""
    with path.open("wb") as f:
        w = McapWriter(
            f, chunk_size=chunk_size, compression=compression, use_chunking=chunked,
            index_types=IndexType.ALL if indexed else IndexType.NONE,
            repeat_channels=summary, repeat_schemas=summary, use_statistics=summary,
            use_summary_offsets=summary,
        )
        w.start(profile="ros2", library="test")
        ids = {}
        for topic, (type_name, menc, senc) in topics.items():
            data = msgdefs.schema_text(type_name).encode() if senc == SchemaEncoding.ROS2 else (
                b"{}" if senc else b"")
            sid = w.register_schema(type_name, senc, data) if senc else 0
            ids[topic] = w.register_channel(topic, menc, sid)
        for topic, t, data in messages:
            w.add_message(ids[topic], log_time=t, data=data, publish_time=t)
        for name, d in (metadata or {}).items():
            w.add_metadata(name, d)
        w.finish()


def _cdr_messages(log: SensorLog) -> tuple[dict[str, tuple[str, str, str]], list]:
    cdr = (MessageEncoding.CDR, SchemaEncoding.ROS2)
    topics = {"/imu": (msgdefs.IMU, *cdr), "/wheel_odom": (msgdefs.ODOMETRY, *cdr),
              "/uwb/range": (msgdefs.RANGE, *cdr)}
    msgs = []
    imu, w, r = log.imu, log.wheel, log.ranges
    for t, d in zip(imu.t_ns.tolist(), cdr_fast.encode_imu(imu.t_ns, imu.gyro, imu.accel),
                    strict=True):
        msgs.append(("/imu", t, d))
    for t, d in zip(w.t_ns.tolist(), cdr_fast.encode_odometry(w.t_ns, w.v, w.omega),
                    strict=True):
        msgs.append(("/wheel_odom", t, d))
    for t, d in zip(r.t_ns.tolist(),
                    cdr_fast.encode_range(r.t_ns, log.anchors.ids, r.anchor, r.range),
                    strict=True):
        msgs.append(("/uwb/range", t, d))
    msgs.sort(key=lambda m: m[1])
    return topics, msgs


def _anchor_meta(log: SensorLog) -> dict[str, dict[str, str]]:
    return {"uwb_anchors": {a: json.dumps(p.tolist()) for a, p in
                            zip(log.anchors.ids, log.anchors.positions, strict=True)}}


@pytest.mark.parametrize(
    ("chunked", "indexed", "summary", "compression"),
    [
        (False, False, False, CompressionType.NONE),  # unchunked, no summary: streamed
        (True, False, False, CompressionType.LZ4),  # chunks without message indexes
        (True, True, True, CompressionType.LZ4),
        (True, True, False, CompressionType.NONE),
    ],
)
def test_layouts_from_mcap_writer(
    tmp_path: Path, chunked: bool, indexed: bool, summary: bool, compression: CompressionType
) -> None:
    """test that unchunked, unindexed, summary-less and lz4 files all read the same."""
    log = small_log(300)
    topics, msgs = _cdr_messages(log)
    path = tmp_path / "log.mcap"
    _mcap(path, topics, msgs, metadata=_anchor_meta(log), chunked=chunked, indexed=indexed,
          summary=summary, compression=compression)
    got = read_log(path, Config())
    np.testing.assert_array_equal(got.imu.gyro, log.imu.gyro)
    np.testing.assert_array_equal(got.wheel.omega, log.wheel.omega)
    np.testing.assert_allclose(got.ranges.range, log.ranges.range, rtol=1e-6)
    np.testing.assert_array_equal(got.ranges.anchor, log.ranges.anchor)
    assert got.ground_truth is None
    assert not got.report.warnings


def _header_json(t: int, frame: str = "") -> dict:
    return {"stamp": {"sec": t // 10**9, "nanosec": t % 10**9}, "frame_id": frame}


def test_json_encoding(tmp_path: Path) -> None:
    """test that json messages (jsonschema) decode: Imu, Odometry, a custom range type."""
    log = small_log(100)
    imu, w, r = log.imu, log.wheel, log.ranges
    msgs = []
    for i, t in enumerate(imu.t_ns.tolist()):
        g, a = imu.gyro[i], imu.accel[i]
        m = {"header": _header_json(t, "imu"),
             "angular_velocity": dict(zip("xyz", g.tolist(), strict=True)),
             "linear_acceleration": dict(zip("xyz", a.tolist(), strict=True))}
        msgs.append(("/imu", t, json.dumps(m).encode()))
    for i, t in enumerate(w.t_ns.tolist()):
        m = {"header": {"stamp": {"sec": t // 10**9, "nsec": t % 10**9}},
             "twist": {"twist": {"linear": {"x": float(w.v[i])},
                                 "angular": {"z": float(w.omega[i])}}}}
        msgs.append(("/wheel_odom", t, json.dumps(m).encode()))
    for i, t in enumerate(r.t_ns.tolist()):
        m = {"header": _header_json(t), "anchor_id": log.anchors.ids[r.anchor[i]],
             "range": float(r.range[i])}
        msgs.append(("/uwb/range", t, json.dumps(m).encode()))
    js = (MessageEncoding.JSON, SchemaEncoding.JSONSchema)
    topics = {"/imu": (msgdefs.IMU, *js), "/wheel_odom": (msgdefs.ODOMETRY, *js),
              "/uwb/range": ("acme/msg/UwbRange", *js)}
    path = tmp_path / "json.mcap"
    _mcap(path, topics, msgs, metadata=_anchor_meta(log))
    got = read_log(path, Config())
    np.testing.assert_array_equal(got.imu.t_ns, imu.t_ns)
    np.testing.assert_array_equal(got.imu.accel, imu.accel)
    np.testing.assert_array_equal(got.wheel.v, w.v)
    np.testing.assert_array_equal(got.ranges.range, r.range)
    np.testing.assert_array_equal(got.ranges.anchor, r.anchor)


def test_schemaless_json_odometry_is_recognised(tmp_path: Path) -> None:
    """test that json without a schema is read by its fields (Odometry vs JointState)."""
    msgs = [("/wheel_odom", T0 + k, json.dumps(
        {"header": _header_json(T0 + k * 10**7), "name": ["left_wheel_joint", "right_wheel_joint"],
         "velocity": [1.0, 3.0]}).encode()) for k in range(5)]
    path = tmp_path / "js.mcap"
    _mcap(path, {"/wheel_odom": ("", MessageEncoding.JSON, "")}, msgs)
    got = read_log(path, Config())
    np.testing.assert_allclose(got.wheel.v, 0.1 * (1.0 + 3.0) / 2)
    np.testing.assert_allclose(got.wheel.omega, 0.1 * (3.0 - 1.0) / 0.5)


def _be_imu(t: int, gyro: np.ndarray, accel: np.ndarray, frame: str = "imu") -> bytes:
    """A big-endian CDR Imu message (encapsulation CDR_BE), built by hand."""
    f = frame.encode() + b"\x00"
    body = struct.pack(">iiI", t // 10**9, t % 10**9, len(f)) + f
    body += b"\x00" * (-len(body) % 8)
    vals = [0.0, 0.0, 0.0, 1.0] + [0.0] * 9 + list(gyro) + [0.0] * 9 + list(accel) + [0.0] * 9
    return b"\x00\x00\x00\x00" + body + struct.pack(">37d", *vals)


def test_big_endian_falls_back_to_generic(tmp_path: Path) -> None:
    """test that big-endian cdr (not for the fast path) is decoded by the generic decoder."""
    log = small_log(50)
    imu = log.imu
    le = cdr_fast.encode_imu(imu.t_ns, imu.gyro, imu.accel)
    msgs = [("/imu", t, _be_imu(t, imu.gyro[i], imu.accel[i]) if i % 2 else le[i])
            for i, t in enumerate(imu.t_ns.tolist())]
    ok, _ = cdr_fast.decode_fixed(msgdefs.IMU, [m[2] for m in msgs])
    assert ok.sum() == 25
    path = tmp_path / "be.mcap"
    _mcap(path, {"/imu": (msgdefs.IMU, MessageEncoding.CDR, SchemaEncoding.ROS2)}, msgs)
    got = read_log(path, Config())
    np.testing.assert_array_equal(got.imu.t_ns, imu.t_ns)
    np.testing.assert_array_equal(got.imu.gyro, imu.gyro)
    np.testing.assert_array_equal(got.imu.accel, imu.accel)


# ------------------------------------------------------------------------------------------
# rosbag2 directories written by the rosbags library


RTLS_MSG = """std_msgs/Header header
uint16 id
acme_rtls/Meas[] ranges
"""
MEAS_MSG = """uint16 id
float32 range
uint8 ra
"""


def _typestore() -> Any:
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    types = {}
    types.update(get_types_from_msg(RTLS_MSG, "acme_rtls/msg/Stick"))
    types.update(get_types_from_msg(MEAS_MSG, "acme_rtls/msg/Meas"))
    ts.register(types)
    return ts


def _write_rosbag(path: Path, ts: Any, rows: list[tuple[str, str, int, object]]) -> None:
    from rosbags.rosbag2 import StoragePlugin, Writer

    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        conns = {}
        for topic, type_name, t, msg in rows:
            if topic not in conns:
                conns[topic] = w.add_connection(topic, type_name, typestore=ts)
            w.write(conns[topic], t, ts.serialize_cdr(msg, type_name))


def _ros_msgs(ts: Any) -> tuple[Any, Any]:
    T = ts.types
    Time, Header = T["builtin_interfaces/msg/Time"], T["std_msgs/msg/Header"]

    def header(t: int, frame: str = "") -> object:
        return Header(stamp=Time(sec=t // 10**9, nanosec=t % 10**9), frame_id=frame)

    return T, header


def test_rosbags_rosbag2_directory(tmp_path: Path) -> None:
    """test a rosbags-written rosbag2 dir: Imu, JointState wheels, custom array ranges, TF GT."""
    ts = _typestore()
    T, header = _ros_msgs(ts)
    V3, Q = T["geometry_msgs/msg/Vector3"], T["geometry_msgs/msg/Quaternion"]
    Imu, JointState = T["sensor_msgs/msg/Imu"], T["sensor_msgs/msg/JointState"]
    Stick, Meas = T["acme_rtls/msg/Stick"], T["acme_rtls/msg/Meas"]
    TfS, Tf = T["geometry_msgs/msg/TransformStamped"], T["geometry_msgs/msg/Transform"]
    z9 = np.zeros(9)
    rows = []
    gyro = RNG.normal(size=(40, 3))
    for k in range(40):
        t = T0 + k * 10_000_000
        rows.append(("/imu", "sensor_msgs/msg/Imu", t, Imu(
            header=header(t, "imu"), orientation=Q(x=0.0, y=0.0, z=0.0, w=1.0),
            orientation_covariance=z9, angular_velocity=V3(x=gyro[k, 0], y=gyro[k, 1],
                                                           z=gyro[k, 2]),
            angular_velocity_covariance=z9, linear_acceleration=V3(x=0.0, y=0.0, z=9.81),
            linear_acceleration_covariance=z9)))
        if k % 4 == 0:
            rows.append(("/joints", "sensor_msgs/msg/JointState", t, JointState(
                header=header(t), name=["caster", "wl", "wr"],
                position=np.zeros(3), velocity=np.array([9.0, 2.0, 4.0]), effort=np.zeros(0))))
            rows.append(("/rtls", "acme_rtls/msg/Stick", t, Stick(
                header=header(t), id=1, ranges=[
                    Meas(id=7475, range=np.float32(3.5), ra=1),
                    Meas(id=9524, range=np.float32(4.5), ra=0),
                    Meas(id=1, range=np.float32(5.5), ra=1)])))
            rows.append(("/vive", "geometry_msgs/msg/TransformStamped", t, TfS(
                header=header(t, "map"), child_frame_id="tracker", transform=Tf(
                    translation=V3(x=1.0, y=2.0, z=float(k)),
                    rotation=Q(x=0.0, y=0.0, z=1.0, w=0.0)))))
    bag = tmp_path / "bag"
    _write_rosbag(bag, ts, rows)
    cfg = config_from_dict({
        "anchors": {"7475": [0, 0, 0], "9524": [1, 0, 0]},
        "topics": {"imu": "/imu", "wheel_odom": "/joints", "uwb": "/rtls",
                   "ground_truth": "/vive"},
        "uwb": {"array_field": "ranges", "anchor_field": "id", "range_field": "range",
                "valid_field": "ra", "range_offset": {"7475": 0.5}},
        "wheel": {"left_joint": "wl", "right_joint": "wr", "radius": 0.5, "track_width": 2.0},
    })
    got = read_log(bag, cfg)
    np.testing.assert_array_equal(got.imu.gyro, gyro)
    assert len(got.wheel) == 10
    np.testing.assert_allclose(got.wheel.v, 0.5 * (2.0 + 4.0) / 2)
    np.testing.assert_allclose(got.wheel.omega, 0.5 * (4.0 - 2.0) / 2.0)
    assert len(got.ranges) == 10
    assert set(got.ranges.anchor.tolist()) == {0}
    np.testing.assert_allclose(got.ranges.range, 3.0)
    assert got.report.skipped[SKIP_INVALID_FLAG] == 10
    assert got.report.skipped[SKIP_UNKNOWN_ANCHOR] == 10
    np.testing.assert_allclose(got.ground_truth.position[:, 2], np.arange(0, 40, 4))
    np.testing.assert_allclose(got.ground_truth.quat_xyzw, [[0, 0, 1, 0]] * 10)
    assert got.ground_truth.has_orientation


def test_rosbags_file_compressed_rosbag2(tmp_path: Path) -> None:
    """test a rosbag2 dir with per-file zstd compression (x.mcap.zstd) written by rosbags."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.rosbag2.enums import CompressionFormat, CompressionMode

    ts = _typestore()
    T, header = _ros_msgs(ts)
    V3, Q = T["geometry_msgs/msg/Vector3"], T["geometry_msgs/msg/Quaternion"]
    z9 = np.zeros(9)
    bag = tmp_path / "zbag"
    w = Writer(bag, version=9, storage_plugin=StoragePlugin.MCAP)
    w.set_compression(CompressionMode.FILE, CompressionFormat.ZSTD)
    with w:
        conn = w.add_connection("/imu", "sensor_msgs/msg/Imu", typestore=ts)
        for k in range(10):
            t = T0 + k * 10**7
            msg = T["sensor_msgs/msg/Imu"](
                header=header(t, "imu"), orientation=Q(x=0.0, y=0.0, z=0.0, w=1.0),
                orientation_covariance=z9, angular_velocity=V3(x=0.0, y=0.0, z=float(k)),
                angular_velocity_covariance=z9, linear_acceleration=V3(x=0.0, y=0.0, z=9.8),
                linear_acceleration_covariance=z9)
            w.write(conn, t, ts.serialize_cdr(msg, "sensor_msgs/msg/Imu"))
    assert [p.name for p in bag.glob("*.zstd")]
    got = read_log(bag, Config())
    np.testing.assert_array_equal(got.imu.gyro[:, 2], np.arange(10.0))


def test_multi_file_rosbag2_is_merged_in_order(tmp_path: Path) -> None:
    """test that a rosbag2 dir with two .mcap files listed in metadata.yaml reads both."""
    log = small_log(200)
    half = 100 * 5_000_000 + T0
    parts = []
    for k, keep in enumerate((lambda t: t < half, lambda t: t >= half)):
        part = SensorLog(
            imu=log.imu.slice(*np.flatnonzero(keep(log.imu.t_ns))[[0, -1]] + [0, 1]),
            anchors=log.anchors,
        )
        p = tmp_path / f"part_{k}.mcap"
        write_contract_log(p, part)
        parts.append(p)
    bag = tmp_path / "bag"
    bag.mkdir()
    for p in parts:
        p.rename(bag / p.name)
    (bag / "metadata.yaml").write_text(
        "rosbag2_bagfile_information:\n  storage_identifier: mcap\n  relative_file_paths:\n"
        "  - part_1.mcap\n  - part_0.mcap\n  version: 9\n"
    )
    got = read_log(bag, Config())
    np.testing.assert_array_equal(got.imu.t_ns, log.imu.t_ns)
    np.testing.assert_array_equal(got.imu.gyro, log.imu.gyro)
    assert got.report.messages["/imu"] == 200
    assert got.anchors is not None and got.anchors.ids == log.anchors.ids


# ------------------------------------------------------------------------------------------
# stamps, duplicates, filters, anchors


def test_zero_stamps_use_log_time(tmp_path: Path) -> None:
    """test that a zero header stamp is replaced by the MCAP log time (and reported)."""
    log = small_log(40)
    imu = log.imu
    t = imu.t_ns.copy()
    t[::3] = 0
    data = cdr_fast.encode_imu(t, imu.gyro, imu.accel)
    msgs = [("/imu", lt, d) for lt, d in zip(imu.t_ns.tolist(), data, strict=True)]
    path = tmp_path / "z.mcap"
    _mcap(path, {"/imu": (msgdefs.IMU, MessageEncoding.CDR, SchemaEncoding.ROS2)}, msgs)
    got = read_log(path, Config())
    np.testing.assert_array_equal(got.imu.t_ns, imu.t_ns)
    assert any("14 imu messages without a header stamp" in w for w in got.report.warnings)


def test_stamps_differ_from_log_time(tmp_path: Path) -> None:
    """test that header stamps, not log times (another clock), are the stream times."""
    log = small_log(40)
    imu = log.imu
    data = cdr_fast.encode_imu(imu.t_ns, imu.gyro, imu.accel)
    msgs = [("/imu", 5 * 10**18 + k, d) for k, d in enumerate(data)]
    path = tmp_path / "clock.mcap"
    _mcap(path, {"/imu": (msgdefs.IMU, MessageEncoding.CDR, SchemaEncoding.ROS2)}, msgs)
    np.testing.assert_array_equal(read_log(path, Config()).imu.t_ns, imu.t_ns)


def test_duplicates_dropped_and_out_of_order_sorted(tmp_path: Path) -> None:
    """test that shuffled messages come out sorted by stamp with exact duplicates counted."""
    log = small_log(200)
    topics, msgs = _cdr_messages(log)
    dups = [m for m in msgs if m[0] == "/imu"][:7] + [m for m in msgs if m[0] == "/uwb/range"][:3]
    msgs = msgs + dups
    order = RNG.permutation(len(msgs))
    path = tmp_path / "shuffled.mcap"
    _mcap(path, topics, [msgs[i] for i in order], metadata=_anchor_meta(log))
    got = read_log(path, Config())
    np.testing.assert_array_equal(got.imu.t_ns, log.imu.t_ns)
    np.testing.assert_array_equal(got.imu.gyro, log.imu.gyro)
    np.testing.assert_array_equal(got.wheel.t_ns, log.wheel.t_ns)
    np.testing.assert_array_equal(got.ranges.t_ns, log.ranges.t_ns)
    assert got.report.skipped[skip_duplicate("imu")] == 7
    assert got.report.skipped[skip_duplicate("uwb")] == 3
    assert got.report.messages["/imu"] == 207


def test_same_stamp_different_values_kept(tmp_path: Path) -> None:
    """test that two IMU samples sharing a stamp but not values are both kept (and warned)."""
    log = small_log(20)
    imu = log.imu
    t = imu.t_ns.copy()
    t[5] = t[4]
    data = cdr_fast.encode_imu(t, imu.gyro, imu.accel)
    path = tmp_path / "tie.mcap"
    _mcap(path, {"/imu": (msgdefs.IMU, MessageEncoding.CDR, SchemaEncoding.ROS2)},
          [("/imu", int(x), d) for x, d in zip(t, data, strict=True)])
    got = read_log(path, Config())
    assert len(got.imu) == 20
    assert any("share a stamp" in w for w in got.report.warnings)


def _range_log(tmp_path: Path, values: list[float], ids: list[str],
               meta: bool = True) -> Path:
    t = T0 + np.arange(len(values), dtype=np.int64) * 25_000_000
    all_ids = sorted(set(ids))
    idx = np.array([all_ids.index(i) for i in ids])
    data = cdr_fast.encode_range(t, all_ids, idx, np.array(values))
    msgs = [("/uwb/range", int(x), d) for x, d in zip(t, data, strict=True)]
    path = tmp_path / "ranges.mcap"
    md = {"uwb_anchors": {"A0": "[0, 0, 1.5]", "A1": "[10, 0, 1.5]", "7475": "[5, 5, 2]"}}
    _mcap(path, {"/uwb/range": (msgdefs.RANGE, MessageEncoding.CDR, SchemaEncoding.ROS2)},
          msgs, metadata=md if meta else None)
    return path


def test_bad_ranges_dropped_and_counted(tmp_path: Path) -> None:
    """test that NaN/inf/zero/negative/out-of-bounds ranges and unknown anchors are counted."""
    values = [1.0, float("nan"), float("inf"), -0.5, 250.0, 2.0, 3.0, 4.0, 0.2, 0.0]
    ids = ["A0", "A0", "A1", "A1", "A0", "ZZ", "7475", "A1", "A0", "A1"]
    path = _range_log(tmp_path, values, ids)
    cfg = config_from_dict({"uwb": {"range_offset": {"A1": 0.5}, "min_range": 0.1}})
    got = read_log(path, cfg)
    assert got.anchors.ids == ("A0", "A1", "7475")
    np.testing.assert_allclose(got.ranges.range, [1.0, 3.0, 3.5, 0.2])
    assert got.anchors.ids[got.ranges.anchor[1]] == "7475"
    sk = got.report.skipped
    assert sk[SKIP_NON_FINITE_RANGE] == 2
    assert sk[SKIP_NON_POSITIVE_RANGE] == 2  # -0.5 and a driver's 0 ("no range")
    assert sk[SKIP_RANGE_BOUNDS] == 1
    assert sk[SKIP_UNKNOWN_ANCHOR] == 1
    assert any("ZZ" in w for w in got.report.warnings)


def test_config_anchors_take_precedence(tmp_path: Path) -> None:
    """test that [anchors] in the config wins over the uwb_anchors metadata record."""
    path = _range_log(tmp_path, [1.0, 2.0, 3.0], ["A0", "7475", "A1"])
    got = read_log(path, config_from_dict({"anchors": {"7475": [1, 2, 3]}}))
    assert got.anchors.ids == ("7475",)
    np.testing.assert_allclose(got.ranges.range, [2.0])
    assert got.report.skipped[SKIP_UNKNOWN_ANCHOR] == 2


def test_no_anchor_map_drops_ranges(tmp_path: Path) -> None:
    """test that without any anchor map the ranges are dropped with a counted reason."""
    path = _range_log(tmp_path, [1.0, 2.0, 3.0], ["A0", "7475", "A1"], meta=False)
    got = read_log(path, Config())
    assert got.anchors is None
    assert got.ranges is not None and len(got.ranges) == 0
    assert got.report.skipped[SKIP_NO_ANCHOR_MAP] == 3


def test_identity_ground_truth_has_no_orientation(tmp_path: Path) -> None:
    """test that a GT stream with only identity quaternions is flagged position-only."""
    log = small_log(20)
    log.ground_truth = type(log.ground_truth)(
        log.ground_truth.t_ns, log.ground_truth.position,
        np.tile([0.0, 0.0, 0.0, 1.0], (len(log.ground_truth), 1)))
    path = tmp_path / "gt.mcap"
    write_contract_log(path, log)
    assert not read_log(path, Config()).ground_truth.has_orientation


def test_other_topics_are_counted_not_decoded(tmp_path: Path) -> None:
    """test that report.messages counts every topic, including ones no role uses."""
    log = small_log(30)
    topics, msgs = _cdr_messages(log)
    topics["/camera/garbage"] = ("acme/msg/Blob", MessageEncoding.CDR, "")
    msgs += [("/camera/garbage", T0, b"\xff" * 5)] * 4
    path = tmp_path / "extra.mcap"
    _mcap(path, topics, msgs, metadata=_anchor_meta(log))
    got = read_log(path, Config())
    assert got.report.messages["/camera/garbage"] == 4
    assert len(got.imu) == 30


def test_undecodable_role_messages_counted(tmp_path: Path) -> None:
    """test that corrupt bytes on a role topic are skipped and counted, not fatal."""
    log = small_log(30)
    imu = log.imu
    data = cdr_fast.encode_imu(imu.t_ns, imu.gyro, imu.accel)
    data[3] = data[3][:40]
    msgs = [("/imu", int(t), d) for t, d in zip(imu.t_ns, data, strict=True)]
    path = tmp_path / "bad.mcap"
    _mcap(path, {"/imu": (msgdefs.IMU, MessageEncoding.CDR, SchemaEncoding.ROS2)}, msgs)
    got = read_log(path, Config())
    assert len(got.imu) == 29
    assert got.report.skipped["undecodable message on /imu"] == 1


def test_generic_decoder_objects_support_paths() -> None:
    """test the dotted-path helper on attribute objects and dicts alike."""
    from uwbfuse.io.fields import anchor_key, get_path, stamp_ns

    obj = NS(header=NS(stamp=NS(sec=2, nanosec=5)), a={"b": [1]})
    assert stamp_ns(obj) == 2 * 10**9 + 5
    assert get_path(obj, "a.b") == [1]
    assert stamp_ns({"header": {"stamp": {"sec": 1, "nsec": 2}}}) == 10**9 + 2
    assert anchor_key(np.uint16(7475)) == "7475"
    assert anchor_key(7475.0) == "7475"


def test_range_with_trailing_variance_field_uses_fast_path(tmp_path: Path) -> None:
    """test a Jazzy-style Range (extra `float32 variance`): same prefix, still vectorised."""
    from mcap_ros2._dynamic import serialize_dynamic

    text = msgdefs.schema_text(msgdefs.RANGE).replace(
        "float32 range\n", "float32 range\nfloat32 variance\n", 1)
    assert cdr_fast.fast_type(msgdefs.RANGE, "ros2msg", text) == msgdefs.RANGE
    enc = serialize_dynamic(msgdefs.RANGE, text)[msgdefs.RANGE]
    msgs = []
    for k in range(6):
        t = T0 + k * 10**8
        m = NS(header=NS(stamp=NS(sec=t // 10**9, nanosec=t % 10**9), frame_id=f"A{k % 2}"),
               radiation_type=0, field_of_view=0.0, min_range=0.0, max_range=50.0,
               range=float(k + 1), variance=0.01)
        msgs.append(("/uwb/range", t, enc(m)))
    path = tmp_path / "jazzy.mcap"
    with path.open("wb") as f:
        w = McapWriter(f)
        w.start(profile="ros2", library="test")
        sid = w.register_schema(msgdefs.RANGE, SchemaEncoding.ROS2, text.encode())
        cid = w.register_channel("/uwb/range", MessageEncoding.CDR, sid)
        for _, t, d in msgs:
            w.add_message(cid, log_time=t, data=d, publish_time=t)
        w.finish()
    got = read_log(path, config_from_dict({"anchors": {"A0": [0, 0, 0], "A1": [1, 0, 0]}}))
    np.testing.assert_allclose(got.ranges.range, np.arange(1.0, 7.0))
    assert got.ranges.anchor.tolist() == [0, 1, 0, 1, 0, 1]


def test_contract_and_real_types_never_need_the_generic_decoder(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """test that the fixed-layout types are all decoded on the vectorised path."""
    import uwbfuse.io.reader as reader_mod

    def no_generic(channel: object) -> None:
        raise AssertionError("generic decoder used")

    monkeypatch.setattr(reader_mod, "generic_decoder", no_generic)
    path = tmp_path / "log.mcap"
    write_contract_log(path, small_log(100))
    assert len(read_log(path, Config()).imu) == 100
