# SPDX-License-Identifier: BSD-3-Clause
"""Trajectories as MCAP: `geometry_msgs/msg/PoseStamped` on `/uwbfuse/<method>/pose`.

ROS 2 cdr with the message definition embedded (profile `ros2`), readable by Foxglove, the
`mcap` reader with the `mcap_ros2` decoder, and evo (through `rosbags`). Chunks are not
compressed: zstd/lz4 are optional packages for the reader side, and a pose file is small
(about 100 bytes per pose). The log time of each message is its header stamp.
"""

from __future__ import annotations

from pathlib import Path

from uwbfuse.errors import TrajectoryFileError
from uwbfuse.io.atomic import atomic_open
from uwbfuse.streams import NS_PER_S, PoseStream

POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
FRAME_ID = "map"

# The full definition, dependencies included, as ROS 2 tools embed it.
_SEP = "=" * 80
POSE_STAMPED_MSGDEF = f"""\
std_msgs/Header header
geometry_msgs/Pose pose
{_SEP}
MSG: std_msgs/Header
builtin_interfaces/Time stamp
string frame_id
{_SEP}
MSG: builtin_interfaces/Time
int32 sec
uint32 nanosec
{_SEP}
MSG: geometry_msgs/Pose
Point position
Quaternion orientation
{_SEP}
MSG: geometry_msgs/Point
float64 x
float64 y
float64 z
{_SEP}
MSG: geometry_msgs/Quaternion
float64 x 0
float64 y 0
float64 z 0
float64 w 1
"""


def pose_topic(method: str) -> str:
    """Topic of a method's trajectory, e.g. `/uwbfuse/isam2/pose`."""
    return f"/uwbfuse/{method}/pose"


def write_pose_mcap(path: str | Path, poses: PoseStream, method: str) -> None:
    """Write `poses` to `path` as PoseStamped (frame_id "map"), atomically.

    Raises TrajectoryFileError when the file cannot be written; the target is then untouched.
    """
    from mcap.writer import CompressionType
    from mcap_ros2.writer import Writer

    p = Path(path)
    topic = pose_topic(method)
    with atomic_open(p, "wb", error=TrajectoryFileError, what="MCAP trajectory") as f:
        writer = Writer(f, compression=CompressionType.NONE)
        schema = writer.register_msgdef(POSE_STAMPED, POSE_STAMPED_MSGDEF)
        for seq, (t, xyz, q) in enumerate(
            zip(
                poses.t_ns.tolist(),
                poses.position.tolist(),
                poses.quat_xyzw.tolist(),
                strict=True,
            )
        ):
            sec, nsec = divmod(int(t), NS_PER_S)
            msg = {
                "header": {"stamp": {"sec": sec, "nanosec": nsec}, "frame_id": FRAME_ID},
                "pose": {
                    "position": {"x": xyz[0], "y": xyz[1], "z": xyz[2]},
                    "orientation": {"x": q[0], "y": q[1], "z": q[2], "w": q[3]},
                },
            }
            writer.write_message(
                topic, schema, msg, log_time=max(int(t), 0), publish_time=max(int(t), 0),
                sequence=seq,
            )
        writer.finish()
