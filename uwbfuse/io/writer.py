# SPDX-License-Identifier: BSD-3-Clause
"""Write a `SensorLog` as a contract MCAP log (ROS 2 profile, cdr, `uwb_anchors` metadata).

Topics and types (CONTRACT.md): /imu `sensor_msgs/msg/Imu` (frame imu_link), /wheel_odom
`nav_msgs/msg/Odometry` (odom -> base_link, twist.linear.x = v, twist.angular.z = omega),
/uwb/range `sensor_msgs/msg/Range` (header.frame_id = anchor id; `uwbfuse_msgs/msg/UwbRange`
with a `uwb_fields` metadata record when the ranges carry signal quality), /ground_truth
`geometry_msgs/msg/PoseStamped` (frame map), and where the log has external poses
/localization/pose `geometry_msgs/msg/PoseWithCovarianceStamped` (frame map).
Every message's log time is its header stamp.

Messages are encoded by the vectorised encoders of `cdr_fast` (byte-identical to
`mcap_ros2.writer`, checked in the tests) and written in stamp order by the vectorised
`mcap_write` (the output reads with the `mcap` and `mcap_ros2` readers, also checked). The
file is written to a temporary file in the target directory and renamed, so a failed write
leaves no partial file.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from mcap.well_known import MessageEncoding, SchemaEncoding

from uwbfuse.config import Topics
from uwbfuse.errors import LogWriteError
from uwbfuse.io import cdr_fast, msgdefs
from uwbfuse.io.atomic import atomic_open
from uwbfuse.io.mcap_write import ChannelDef, SchemaDef, write_mcap
from uwbfuse.streams import AnchorMap, SensorLog

ANCHORS_METADATA = "uwb_anchors"
MAP_METADATA = "map_obstacles"
# [uwb] field names of the log's range type ({"rssi_field": "rssi", ...}): the reader fills
# the config's empty signal-quality keys from it
UWB_FIELDS_METADATA = "uwb_fields"
# what a log with signal quality writes: `msgdefs.UWB_RANGE`'s fields
SIGNAL_FIELDS = {"rssi_field": "rssi", "first_path_power_field": "first_path_power"}
LIBRARY = "uwbfuse"

_COMPRESSION = ("zstd", "lz4", "none")


def anchors_record(anchors: AnchorMap) -> dict[str, str]:
    """The `uwb_anchors` record: anchor id -> JSON array "[x, y, z]" (metres, map frame)."""
    return {
        aid: json.dumps([float(c) for c in pos])
        for aid, pos in zip(anchors.ids, anchors.positions, strict=True)
    }


def anchors_metadata(log: SensorLog) -> dict[str, str]:
    """The `uwb_anchors` record of `log` (empty without an anchor map)."""
    return {} if log.anchors is None else anchors_record(log.anchors)


def map_metadata(log: SensorLog) -> dict[str, str]:
    """The `map_obstacles` record: obstacle id -> JSON array "[[x, y], ...]" (metres, map
    frame), from `log.map` (its obstacle polygons)."""
    if log.map is None:
        return {}
    return {f"obstacle{i}": json.dumps([[float(x), float(y)] for x, y in poly])
            for i, poly in enumerate(log.map.obstacles)}


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
        if r.rssi_dbm is not None and r.first_path_dbm is not None:
            out.append((topics.uwb, msgdefs.UWB_RANGE, r.t_ns, cdr_fast.encode_uwb_range(
                r.t_ns, log.anchors.ids, r.anchor, r.range, r.rssi_dbm, r.first_path_dbm)))
        else:
            out.append((topics.uwb, msgdefs.RANGE, r.t_ns,
                        cdr_fast.encode_range(r.t_ns, log.anchors.ids, r.anchor, r.range)))
    if log.pose is not None and len(log.pose):
        ps = log.pose
        cov = ps.covariance if ps.covariance is not None else np.zeros((len(ps), 6, 6))
        out.append((topics.pose, msgdefs.POSE_WITH_COVARIANCE_STAMPED, ps.t_ns,
                    cdr_fast.encode_pose_with_covariance_stamped(
                        ps.t_ns, ps.position, ps.quat_xyzw, cov)))
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

    compression: "zstd", "lz4" or "none" (chunked, with a summary and message indexes).
    topics: topic names (contract defaults if None). chunk_size: uncompressed bytes.
    """
    if compression not in _COMPRESSION:
        raise ValueError(f"unknown compression {compression!r} (zstd, lz4 or none)")
    topics = topics or Topics()
    path = Path(path)
    streams = _encode_streams(log, topics)
    schemas = [SchemaDef(type_name, SchemaEncoding.ROS2, msgdefs.schema_text(type_name).encode())
               for _, type_name, _, _ in streams]
    channels = [ChannelDef(topic, MessageEncoding.CDR, k)
                for k, (topic, _, _, _) in enumerate(streams)]
    stamps = (np.concatenate([s[2] for s in streams]).astype(np.int64) if streams
              else np.zeros(0, np.int64))
    which = (np.concatenate([np.full(len(s[2]), k) for k, s in enumerate(streams)])
             if streams else np.zeros(0, np.int64))
    order = np.argsort(stamps, kind="stable")
    every = [d for s in streams for d in s[3]]
    datas = [every[i] for i in order.tolist()]
    meta = anchors_metadata(log)
    obstacles = map_metadata(log)
    r = log.ranges
    fields = (SIGNAL_FIELDS if r is not None and r.rssi_dbm is not None
              and r.first_path_dbm is not None else {})
    with atomic_open(path, "wb", error=LogWriteError, what="log", fsync=True) as f:
        write_mcap(f, schemas=schemas, channels=channels, channel=which[order],
                   log_time=stamps[order], datas=datas,
                   metadata=([(ANCHORS_METADATA, meta)] if meta else [])
                   + ([(MAP_METADATA, obstacles)] if obstacles else [])
                   + ([(UWB_FIELDS_METADATA, fields)] if fields else []),
                   library=LIBRARY, compression=compression, chunk_size=chunk_size)
