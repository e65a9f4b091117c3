# SPDX-License-Identifier: BSD-3-Clause
"""Trajectories as a ROS 2 MCAP file that Foxglove, `ros2 bag`, rosbags and evo open.

Channels (ROS 2 cdr, message definitions embedded, profile `ros2`), every pose the base
frame `base_link` in the map frame `map`:
- `/uwbfuse/<method>/pose`: `geometry_msgs/msg/PoseStamped`;
- `/uwbfuse/<method>/pose_with_covariance`: `geometry_msgs/msg/PoseWithCovarianceStamped`,
  the 6x6 covariance in ROS order (x, y, z, rot x, rot y, rot z; map axes), with
  `UNKNOWN_VARIANCE` on the diagonal where the method gave none;
- `/tf`: `tf2_msgs/msg/TFMessage`, the `map` -> `base_link` transform of each pose;
- `/uwbfuse/anchors`: one `visualization_msgs/msg/MarkerArray` (a cylinder and a label per
  anchor), and the anchors again as the `uwb_anchors` metadata record the reader takes.
Each channel carries the `offered_qos_profiles` metadata `ros2 bag record` writes (reliable,
volatile; the markers transient-local, as a latched topic), so `ros2 bag play` republishes
with the same QoS. The log time of each message is its header stamp. Chunks are not
compressed: a pose file is small (about 600 bytes per pose), and any reader opens it.
The per-pose messages are built as numpy byte matrices (fixed layouts, fixed frame ids).
"""

from __future__ import annotations

import struct
from functools import cache
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from uwbfuse.errors import TrajectoryFileError
from uwbfuse.io import cdr_fast
from uwbfuse.io.atomic import atomic_open
from uwbfuse.io.mcap_write import ChannelDef, SchemaDef, write_mcap
from uwbfuse.io.writer import ANCHORS_METADATA, anchors_record
from uwbfuse.streams import NS_PER_S, UNKNOWN_VARIANCE, AnchorMap, PoseStream

POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
POSE_WITH_COVARIANCE_STAMPED = "geometry_msgs/msg/PoseWithCovarianceStamped"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
MARKER_ARRAY = "visualization_msgs/msg/MarkerArray"
FRAME_ID = "map"
CHILD_FRAME_ID = "base_link"
TF_TOPIC = "/tf"
ANCHORS_TOPIC = "/uwbfuse/anchors"
ANCHOR_MARKER_HEIGHT_M = 0.5  # drawn cylinder height; its diameter is 0.2 m
_CDR_LE = b"\x00\x01\x00\x00"
_INFINITE = {"sec": 2147483647, "nsec": 4294967295}  # rmw's "infinite" duration


def pose_topic(method: str) -> str:
    """Topic of a method's trajectory, e.g. `/uwbfuse/isam2/pose`."""
    return f"/uwbfuse/{method}/pose"


def pose_with_covariance_topic(method: str) -> str:
    """Topic of a method's poses with covariance, e.g. `/uwbfuse/isam2/pose_with_covariance`."""
    return f"/uwbfuse/{method}/pose_with_covariance"


@cache
def _typestore() -> Any:
    """The rosbags type store of the message types written (ROS 2 Humble)."""
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_HUMBLE)


def _msgdef(type_name: str) -> bytes:
    """The `ros2msg` definition (dependencies appended) as `ros2 bag record` embeds it."""
    text, _ = _typestore().generate_msgdef(type_name, ros_version=2)
    return text.encode()


def qos_metadata(*, latched: bool = False) -> dict[str, str]:
    """Channel metadata `offered_qos_profiles` as `ros2 bag record` writes it (rosbag2 v8)."""
    from rosbags.interfaces import (
        Qos,
        QosDurability,
        QosHistory,
        QosLiveliness,
        QosReliability,
        QosTime,
    )
    from rosbags.rosbag2.metadata import dump_qos_v8

    inf = QosTime(_INFINITE["sec"], _INFINITE["nsec"])
    qos = Qos(QosHistory.UNKNOWN, 0, QosReliability.RELIABLE,
              QosDurability.TRANSIENT_LOCAL if latched else QosDurability.VOLATILE,
              inf, inf, QosLiveliness.AUTOMATIC, inf, False)
    return {"offered_qos_profiles": dump_qos_v8([qos])}


def _stamped_rows(
    t_ns: NDArray[np.int64], prefix: bytes, stamp_at: int, values: NDArray[np.float64]
) -> list[bytes]:
    """cdr messages: encapsulation, `prefix` with the stamp at payload offset `stamp_at`,
    then the float64 columns of `values` (`len(prefix)` must be a multiple of 8)."""
    n, k = values.shape
    m = np.zeros((n, 4 + len(prefix) + 8 * k), dtype=np.uint8)
    m[:, :4] = np.frombuffer(_CDR_LE, dtype=np.uint8)
    m[:, 4 : 4 + len(prefix)] = np.frombuffer(prefix, dtype=np.uint8)
    t = np.asarray(t_ns, dtype=np.int64)
    sec = np.floor_divide(t, NS_PER_S)
    m[:, 4 + stamp_at : 8 + stamp_at].view("<i4")[:, 0] = sec.astype(np.int32)
    m[:, 8 + stamp_at : 12 + stamp_at].view("<u4")[:, 0] = (t - sec * NS_PER_S).astype(np.uint32)
    m[:, 4 + len(prefix) :].view("<f8")[:] = values
    raw = m.tobytes()
    row = m.shape[1]
    return [raw[i * row : (i + 1) * row] for i in range(n)]


def _string(text: str) -> bytes:
    b = text.encode() + b"\x00"
    return struct.pack("<I", len(b)) + b


def _pad8(b: bytes) -> bytes:
    return b + b"\x00" * (-len(b) % 8)


def pose_covariances(poses: PoseStream) -> NDArray[np.float64]:
    """(N, 6, 6) covariances: the stream's, or UNKNOWN_VARIANCE on the diagonal."""
    if poses.covariance is not None:
        return np.asarray(poses.covariance, dtype=np.float64)
    return np.broadcast_to(np.eye(6) * UNKNOWN_VARIANCE, (len(poses), 6, 6)).copy()


def encode_pose_with_covariance(poses: PoseStream) -> list[bytes]:
    """geometry_msgs/msg/PoseWithCovarianceStamped (frame map) per pose."""
    prefix = _pad8(struct.pack("<iI", 0, 0) + _string(FRAME_ID))
    values = np.hstack([poses.position, poses.quat_xyzw,
                        pose_covariances(poses).reshape(len(poses), 36)])
    return _stamped_rows(poses.t_ns, prefix, 0, values)


def encode_tf(poses: PoseStream) -> list[bytes]:
    """tf2_msgs/msg/TFMessage with one map -> base_link TransformStamped per pose."""
    prefix = _pad8(struct.pack("<I", 1) + struct.pack("<iI", 0, 0) + _string(FRAME_ID)
                   + _string(CHILD_FRAME_ID))
    return _stamped_rows(poses.t_ns, prefix, 4, np.hstack([poses.position, poses.quat_xyzw]))


def encode_anchor_markers(anchors: AnchorMap, t_ns: int) -> bytes:
    """One visualization_msgs/msg/MarkerArray: a cylinder and a text label per anchor."""
    ts = _typestore()
    T = ts.types
    sec, nsec = divmod(int(t_ns), NS_PER_S)
    header = T["std_msgs/msg/Header"](
        stamp=T["builtin_interfaces/msg/Time"](sec=sec, nanosec=nsec), frame_id=FRAME_ID)
    marker_cls, pose_cls = T["visualization_msgs/msg/Marker"], T["geometry_msgs/msg/Pose"]
    point, quat = T["geometry_msgs/msg/Point"], T["geometry_msgs/msg/Quaternion"]
    v3, rgba = T["geometry_msgs/msg/Vector3"], T["std_msgs/msg/ColorRGBA"]
    empty_image = T["sensor_msgs/msg/CompressedImage"](header=header, format="",
                                                        data=np.zeros(0, np.uint8))
    mesh = T["visualization_msgs/msg/MeshFile"](filename="", data=np.zeros(0, np.uint8))
    markers = []
    for k, (aid, pos) in enumerate(zip(anchors.ids, anchors.positions.tolist(), strict=True)):
        for j, (kind, scale, color, text, dz) in enumerate((
            (3, (0.2, 0.2, ANCHOR_MARKER_HEIGHT_M), (1.0, 0.55, 0.0, 1.0), "", 0.0),
            (9, (0.0, 0.0, 0.3), (1.0, 1.0, 1.0, 1.0), str(aid), ANCHOR_MARKER_HEIGHT_M),
        )):
            markers.append(marker_cls(
                header=header, ns="uwb_anchors" if j == 0 else "uwb_anchor_ids", id=k,
                type=kind, action=0,
                pose=pose_cls(position=point(x=pos[0], y=pos[1], z=pos[2] + dz),
                              orientation=quat(x=0.0, y=0.0, z=0.0, w=1.0)),
                scale=v3(x=scale[0], y=scale[1], z=scale[2]),
                color=rgba(r=color[0], g=color[1], b=color[2], a=color[3]),
                lifetime=T["builtin_interfaces/msg/Duration"](sec=0, nanosec=0),
                frame_locked=False, points=[], colors=[], texture_resource="",
                texture=empty_image, uv_coordinates=[], text=text, mesh_resource="",
                mesh_file=mesh, mesh_use_embedded_materials=False))
    msg = T[MARKER_ARRAY](markers=markers)
    return bytes(ts.serialize_cdr(msg, MARKER_ARRAY))


def write_pose_mcap(
    path: str | Path, poses: PoseStream, method: str, anchors: AnchorMap | None = None
) -> None:
    """Write `poses` (base_link in map) to `path`: pose, pose with covariance, /tf, and
    with `anchors` the anchor markers and `uwb_anchors` record; atomically.

    Raises TrajectoryFileError when the file cannot be written; the target is then untouched.
    """
    n = len(poses)
    t = np.maximum(np.asarray(poses.t_ns, dtype=np.int64), 0)
    streams: list[tuple[str, str, dict[str, str], NDArray[np.int64], list[bytes]]] = [
        (pose_topic(method), POSE_STAMPED, qos_metadata(), t,
         cdr_fast.encode_pose_stamped(poses.t_ns, poses.position, poses.quat_xyzw, FRAME_ID)),
        (pose_with_covariance_topic(method), POSE_WITH_COVARIANCE_STAMPED, qos_metadata(), t,
         encode_pose_with_covariance(poses)),
        (TF_TOPIC, TF_MESSAGE, qos_metadata(), t, encode_tf(poses)),
    ]
    metadata: list[tuple[str, dict[str, str]]] = []
    if anchors is not None and len(anchors):
        t0 = int(t[0]) if n else 0
        streams.append((ANCHORS_TOPIC, MARKER_ARRAY, qos_metadata(latched=True),
                        np.array([t0], dtype=np.int64), [encode_anchor_markers(anchors, t0)]))
        metadata.append((ANCHORS_METADATA, anchors_record(anchors)))
    schemas = [SchemaDef(type_name, "ros2msg", _msgdef(type_name))
               for _, type_name, _, _, _ in streams]
    channels = [ChannelDef(topic, "cdr", k, meta)
                for k, (topic, _, meta, _, _) in enumerate(streams)]
    stamps = np.concatenate([s[3] for s in streams])
    which = np.concatenate([np.full(len(s[3]), k) for k, s in enumerate(streams)])
    order = np.lexsort((which, stamps))
    every = [d for s in streams for d in s[4]]
    with atomic_open(Path(path), "wb", error=TrajectoryFileError, what="MCAP trajectory") as f:
        write_mcap(f, schemas=schemas, channels=channels, channel=which[order],
                   log_time=stamps[order], datas=[every[i] for i in order.tolist()],
                   metadata=metadata, compression="none")
