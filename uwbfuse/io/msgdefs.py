# SPDX-License-Identifier: BSD-3-Clause
"""ROS 2 message definitions (`ros2msg` schema text, dependencies appended) that uwbfuse writes.

The texts follow the layout `ros2 bag record -s mcap` embeds: the top-level definition, then
each dependency after a line of 80 `=` and a `MSG: pkg/Type` line (ROS 2 Humble types).
"""

from __future__ import annotations

IMU = "sensor_msgs/msg/Imu"
ODOMETRY = "nav_msgs/msg/Odometry"
RANGE = "sensor_msgs/msg/Range"
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
POSE_WITH_COVARIANCE_STAMPED = "geometry_msgs/msg/PoseWithCovarianceStamped"
TRANSFORM_STAMPED = "geometry_msgs/msg/TransformStamped"
JOINT_STATE = "sensor_msgs/msg/JointState"
# the simulator's range type with signal quality (fields read through the [uwb] mapping:
# anchor_id, range in m, rssi and first_path_power in dBm)
UWB_RANGE = "uwbfuse_msgs/msg/UwbRange"

_SEP = "=" * 80

_DEFS: dict[str, str] = {
    "builtin_interfaces/Time": "int32 sec\nuint32 nanosec",
    "std_msgs/Header": "builtin_interfaces/Time stamp\nstring frame_id",
    "geometry_msgs/Point": "float64 x\nfloat64 y\nfloat64 z",
    "geometry_msgs/Vector3": "float64 x\nfloat64 y\nfloat64 z",
    "geometry_msgs/Quaternion": "float64 x\nfloat64 y\nfloat64 z\nfloat64 w",
    "geometry_msgs/Pose": "geometry_msgs/Point position\ngeometry_msgs/Quaternion orientation",
    "geometry_msgs/Twist": "geometry_msgs/Vector3 linear\ngeometry_msgs/Vector3 angular",
    "geometry_msgs/Transform": (
        "geometry_msgs/Vector3 translation\ngeometry_msgs/Quaternion rotation"
    ),
    "geometry_msgs/PoseWithCovariance": "geometry_msgs/Pose pose\nfloat64[36] covariance",
    "geometry_msgs/TwistWithCovariance": "geometry_msgs/Twist twist\nfloat64[36] covariance",
    IMU: (
        "std_msgs/Header header\n"
        "geometry_msgs/Quaternion orientation\nfloat64[9] orientation_covariance\n"
        "geometry_msgs/Vector3 angular_velocity\nfloat64[9] angular_velocity_covariance\n"
        "geometry_msgs/Vector3 linear_acceleration\nfloat64[9] linear_acceleration_covariance"
    ),
    ODOMETRY: (
        "std_msgs/Header header\nstring child_frame_id\n"
        "geometry_msgs/PoseWithCovariance pose\ngeometry_msgs/TwistWithCovariance twist"
    ),
    RANGE: (
        "uint8 ULTRASOUND=0\nuint8 INFRARED=1\n"
        "std_msgs/Header header\nuint8 radiation_type\nfloat32 field_of_view\n"
        "float32 min_range\nfloat32 max_range\nfloat32 range"
    ),
    POSE_STAMPED: "std_msgs/Header header\ngeometry_msgs/Pose pose",
    UWB_RANGE: (
        "std_msgs/Header header\nstring anchor_id\nfloat32 range\nfloat32 rssi\n"
        "float32 first_path_power"
    ),
    POSE_WITH_COVARIANCE_STAMPED: "std_msgs/Header header\ngeometry_msgs/PoseWithCovariance pose",
    TRANSFORM_STAMPED: (
        "std_msgs/Header header\nstring child_frame_id\ngeometry_msgs/Transform transform"
    ),
    JOINT_STATE: (
        "std_msgs/Header header\nstring[] name\nfloat64[] position\nfloat64[] velocity\n"
        "float64[] effort"
    ),
}

_DEPS: dict[str, tuple[str, ...]] = {
    IMU: ("std_msgs/Header", "builtin_interfaces/Time", "geometry_msgs/Quaternion",
          "geometry_msgs/Vector3"),
    ODOMETRY: ("std_msgs/Header", "builtin_interfaces/Time", "geometry_msgs/PoseWithCovariance",
               "geometry_msgs/Pose", "geometry_msgs/Point", "geometry_msgs/Quaternion",
               "geometry_msgs/TwistWithCovariance", "geometry_msgs/Twist",
               "geometry_msgs/Vector3"),
    RANGE: ("std_msgs/Header", "builtin_interfaces/Time"),
    POSE_STAMPED: ("std_msgs/Header", "builtin_interfaces/Time", "geometry_msgs/Pose",
                   "geometry_msgs/Point", "geometry_msgs/Quaternion"),
    POSE_WITH_COVARIANCE_STAMPED: ("std_msgs/Header", "builtin_interfaces/Time",
                                   "geometry_msgs/PoseWithCovariance", "geometry_msgs/Pose",
                                   "geometry_msgs/Point", "geometry_msgs/Quaternion"),
    TRANSFORM_STAMPED: ("std_msgs/Header", "builtin_interfaces/Time", "geometry_msgs/Transform",
                        "geometry_msgs/Vector3", "geometry_msgs/Quaternion"),
    JOINT_STATE: ("std_msgs/Header", "builtin_interfaces/Time"),
    UWB_RANGE: ("std_msgs/Header", "builtin_interfaces/Time"),
}


def schema_text(type_name: str) -> str:
    """The full `ros2msg` schema text of `type_name` (e.g. "sensor_msgs/msg/Imu")."""
    parts = [_DEFS[type_name]]
    for dep in _DEPS[type_name]:
        parts.append(f"{_SEP}\nMSG: {dep}\n{_DEFS[dep]}")
    return "\n".join(parts) + "\n"
