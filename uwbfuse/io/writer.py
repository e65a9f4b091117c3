# SPDX-License-Identifier: BSD-3-Clause
"""Write a `SensorLog` as a contract MCAP log (ROS 2 profile, cdr, `uwb_anchors` metadata).

Topics and types (CONTRACT.md): /imu `sensor_msgs/msg/Imu` (frame imu_link), /wheel_odom
`nav_msgs/msg/Odometry` (odom -> base_link, twist.linear.x = v, twist.angular.z = omega),
/uwb/range `sensor_msgs/msg/Range` (header.frame_id = anchor id), /ground_truth
`geometry_msgs/msg/PoseStamped` (frame map). Every message's log time is its header stamp.

Messages are encoded by the vectorised encoders of `cdr_fast` (byte-identical to
`mcap_ros2.writer`, checked in the tests) and written with the `mcap` writer in stamp order.
The file is written to a temporary file in the target directory and renamed, so a failed
write leaves no partial file.
"""

from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path

import numpy as np
from mcap.well_known import MessageEncoding, SchemaEncoding
from mcap.writer import CompressionType
from mcap.writer import Writer as McapWriter

from uwbfuse.config import Topics
from uwbfuse.io import cdr_fast, msgdefs
from uwbfuse.streams import SensorLog

ANCHORS_METADATA = "uwb_anchors"
LIBRARY = "uwbfuse"

_COMPRESSION = {
    "zstd": CompressionType.ZSTD,
    "lz4": CompressionType.LZ4,
    "none": CompressionType.NONE,
    "": CompressionType.NONE,
}


def anchors_metadata(log: SensorLog) -> dict[str, str]:
    """The `uwb_anchors` record: anchor id -> JSON array "[x, y, z]" (metres, map frame)."""
    if log.anchors is None:
        return {}
    return {
        aid: json.dumps([float(c) for c in pos])
        for aid, pos in zip(log.anchors.ids, log.anchors.positions, strict=True)
    }


def _encode_streams(
    log: SensorLog, topics: Topics
) -> list[tuple[str, str, np.ndarray, list[bytes]]]:
    """[(topic, type, stamps, encoded messages), ...] for every non-empty stream."""
    out: list[tuple[str, str, np.ndarray, list[bytes]]] = []
    if log.imu is not None and len(log.imu):
        imu = log.imu
        out.append((topics.imu, msgdefs.IMU, imu.t_ns,
                    cdr_fast.encode_imu(imu.t_ns, imu.gyro, imu.accel)))
    if log.wheel is not None and len(log.wheel):
        w = log.wheel
        out.append((topics.wheel_odom, msgdefs.ODOMETRY, w.t_ns,
                    cdr_fast.encode_odometry(w.t_ns, w.v, w.omega)))
    if log.ranges is not None and len(log.ranges):
        r = log.ranges
        if log.anchors is None:
            raise ValueError("cannot write ranges without an anchor map (ids unknown)")
        out.append((topics.uwb, msgdefs.RANGE, r.t_ns,
                    cdr_fast.encode_range(r.t_ns, log.anchors.ids, r.anchor, r.range)))
    if log.ground_truth is not None and len(log.ground_truth):
        g = log.ground_truth
        out.append((topics.ground_truth, msgdefs.POSE_STAMPED, g.t_ns,
                    cdr_fast.encode_pose_stamped(g.t_ns, g.position, g.quat_xyzw)))
    return out


def write_contract_log(
    path: str | Path,
    log: SensorLog,
    *,
    compression: str = "zstd",
    topics: Topics | None = None,
    chunk_size: int = 1024 * 1024,
) -> None:
    """Write `log` to the MCAP file `path` (atomically: temporary file, then rename).

    compression: "zstd", "lz4" or "none" (chunks are always used, with a summary and
    message indexes). topics: topic names (contract defaults if None).
    """
    if compression not in _COMPRESSION:
        raise ValueError(f"unknown compression {compression!r} (zstd, lz4 or none)")
    topics = topics or Topics()
    path = Path(path)
    streams = _encode_streams(log, topics)
    fd, tmp = tempfile.mkstemp(dir=path.parent or Path("."), prefix=f".{path.name}.",
                               suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            writer = McapWriter(f, chunk_size=chunk_size,
                                compression=_COMPRESSION[compression])
            writer.start(profile="ros2", library=LIBRARY)
            channels = []
            for topic, type_name, _, _ in streams:
                sid = writer.register_schema(type_name, SchemaEncoding.ROS2,
                                             msgdefs.schema_text(type_name).encode())
                channels.append(writer.register_channel(topic, MessageEncoding.CDR, sid))
            _write_merged(writer, channels, streams)
            meta = anchors_metadata(log)
            if meta:
                writer.add_metadata(ANCHORS_METADATA, meta)
            writer.finish()
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def _write_merged(
    writer: McapWriter,
    channels: list[int],
    streams: list[tuple[str, str, np.ndarray, list[bytes]]],
) -> None:
    """Add every message, all streams merged in stamp order (log time = stamp)."""
    if not streams:
        return
    stamps = np.concatenate([s[2] for s in streams]).astype(np.int64)
    which = np.concatenate([np.full(len(s[2]), k) for k, s in enumerate(streams)])
    index = np.concatenate([np.arange(len(s[2])) for s in streams])
    order = np.argsort(stamps, kind="stable")
    datas = [s[3] for s in streams]
    add = writer.add_message
    for t, k, i in zip(stamps[order].tolist(), which[order].tolist(), index[order].tolist(),
                       strict=True):
        add(channel_id=channels[k], log_time=t, data=datas[k][i], publish_time=t)
