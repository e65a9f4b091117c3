# SPDX-License-Identifier: BSD-3-Clause
"""Vectorised CDR (ROS 2, little-endian XCDR1) encoding and decoding of fixed-layout types.

A ROS 2 message is a 4-byte encapsulation header (`00 01 00 00` = CDR_LE) followed by the
payload; alignment is relative to the payload start: 4 bytes for (u)int32/float32 and
string lengths, 8 bytes for float64. `std_msgs/Header` is `int32 sec, uint32 nanosec,
string frame_id` (uint32 length including the NUL, then the bytes and the NUL), so once the
frame_id length (and, for Odometry/TransformStamped, the child_frame_id length) is known,
every later field sits at a computed offset. Decoding reads the string lengths of all
messages at once, computes each message's field offsets with numpy, and gathers only the
bytes of the fields needed (a few dozen per message) straight from the chunk buffer.
Messages that do not fit (big-endian or other encapsulations, lengths that do not add up)
are reported back so the caller can use the generic decoder. Encoding builds one (n, L)
uint8 matrix per group of messages sharing their frame ids.

Supported types: sensor_msgs/msg/Imu, nav_msgs/msg/Odometry, sensor_msgs/msg/Range,
geometry_msgs/msg/PoseStamped, geometry_msgs/msg/PoseWithCovarianceStamped,
geometry_msgs/msg/TransformStamped, the simulator's uwbfuse_msgs/msg/UwbRange (anchor_id,
range, rssi, first_path_power) (ROS 2 Humble layouts,
or any schema whose flattened layout starts with them, e.g. Range with `variance`).
"""

from __future__ import annotations

from collections.abc import Sequence
from functools import cache

import numpy as np
from numpy.typing import NDArray

from uwbfuse.io import msgdefs, ros2msg
from uwbfuse.io.fields import MAX_ANCHOR_ID_CHARS

U8 = NDArray[np.uint8]
_CDR_LE = b"\x00\x01\x00\x00"
_NS = 1_000_000_000


def _a4(p: int) -> int:
    return (p + 3) & ~3


def _a8(p: int) -> int:
    return (p + 7) & ~7


# ----------------------------------------------------------------------------------------
# layouts: payload offsets (without the 4-byte encapsulation header) for given string sizes


def _header_end(l1: int) -> int:
    """Payload offset after a Header whose frame_id length field is `l1` (NUL included)."""
    return 12 + l1


def _layout(type_name: str, l1: int, l2: int) -> tuple[int, int]:
    """(payload offset of the first float field block, payload end) for the string sizes."""
    p = _header_end(l1)
    if type_name == msgdefs.IMU:
        start = _a8(p)
        return start, start + 37 * 8
    if type_name == msgdefs.ODOMETRY:
        start = _a8(_a4(p) + 4 + l2)
        return start, start + 85 * 8
    if type_name == msgdefs.RANGE:
        start = _a4(p + 1)
        return start, start + 16
    if type_name == msgdefs.POSE_STAMPED:
        start = _a8(p)
        return start, start + 7 * 8
    if type_name == msgdefs.POSE_WITH_COVARIANCE_STAMPED:
        start = _a8(p)
        return start, start + 43 * 8
    if type_name == msgdefs.TRANSFORM_STAMPED:
        start = _a8(_a4(p) + 4 + l2)
        return start, start + 7 * 8
    if type_name == msgdefs.UWB_RANGE:  # child string = anchor_id, then three float32
        start = _a4(_a4(p) + 4 + l2)
        return start, start + 3 * 4
    raise KeyError(type_name)


FAST_TYPES = frozenset(
    {msgdefs.IMU, msgdefs.ODOMETRY, msgdefs.RANGE, msgdefs.POSE_STAMPED,
     msgdefs.TRANSFORM_STAMPED, msgdefs.UWB_RANGE, msgdefs.POSE_WITH_COVARIANCE_STAMPED}
)
_HAS_CHILD = frozenset({msgdefs.ODOMETRY, msgdefs.TRANSFORM_STAMPED, msgdefs.UWB_RANGE})


# ----------------------------------------------------------------------------------------
# encoding


def _col(m: U8, off: int, dtype: str, k: int) -> np.ndarray:
    """View columns [off, off + k * itemsize) of every row as `k` values of `dtype`."""
    size = np.dtype(dtype).itemsize
    return m[:, off : off + k * size].view(dtype)


def _split_stamp(t_ns: NDArray[np.int64]) -> tuple[np.ndarray, np.ndarray]:
    t = np.asarray(t_ns, dtype=np.int64)
    sec = np.floor_divide(t, _NS)
    return sec.astype(np.int32), (t - sec * _NS).astype(np.uint32)


def _encode_group(
    type_name: str,
    t_ns: NDArray[np.int64],
    frame_id: str,
    child_frame_id: str,
    fill: dict[int, np.ndarray],
    floats32: bool = False,
) -> list[bytes]:
    """Encode n messages of one type and frame ids; `fill` maps float index -> (n,) values."""
    n = len(t_ns)
    f1 = frame_id.encode() + b"\x00"
    f2 = child_frame_id.encode() + b"\x00"
    start, end = _layout(type_name, len(f1), len(f2))
    m = np.zeros((n, 4 + end), dtype=np.uint8)
    m[:, 0:4] = np.frombuffer(_CDR_LE, dtype=np.uint8)
    sec, nsec = _split_stamp(t_ns)
    _col(m, 4, "<i4", 1)[:, 0] = sec
    _col(m, 8, "<u4", 1)[:, 0] = nsec
    _col(m, 12, "<u4", 1)[:, 0] = len(f1)
    m[:, 16 : 16 + len(f1)] = np.frombuffer(f1, dtype=np.uint8)
    if type_name in _HAS_CHILD:
        c = _a4(_header_end(len(f1)))
        _col(m, 4 + c, "<u4", 1)[:, 0] = len(f2)
        m[:, 4 + c + 4 : 4 + c + 4 + len(f2)] = np.frombuffer(f2, dtype=np.uint8)
    if floats32:
        block = _col(m, 4 + start, "<f4", (end - start) // 4)
    else:
        block = _col(m, 4 + start, "<f8", (end - start) // 8)
    for i, values in fill.items():
        block[:, i] = values
    raw = m.tobytes()
    row = m.shape[1]
    return [raw[i * row : (i + 1) * row] for i in range(n)]


def encode_imu(
    t_ns: NDArray[np.int64], gyro: np.ndarray, accel: np.ndarray, frame_id: str = "imu_link"
) -> list[bytes]:
    """sensor_msgs/msg/Imu: orientation unknown (covariance[0] = -1), rad/s and m/s^2."""
    fill = {3: np.ones(len(t_ns)), 4: np.full(len(t_ns), -1.0)}
    for k in range(3):
        fill[13 + k] = gyro[:, k]
        fill[25 + k] = accel[:, k]
    return _encode_group(msgdefs.IMU, t_ns, frame_id, "", fill)


def encode_odometry(
    t_ns: NDArray[np.int64],
    v: np.ndarray,
    omega: np.ndarray,
    frame_id: str = "odom",
    child_frame_id: str = "base_link",
    position: np.ndarray | None = None,
    quat_xyzw: np.ndarray | None = None,
) -> list[bytes]:
    """nav_msgs/msg/Odometry with twist.linear.x = v (m/s), twist.angular.z = omega (rad/s)."""
    n = len(t_ns)
    fill: dict[int, np.ndarray] = {43: np.asarray(v), 48: np.asarray(omega)}
    pos = np.zeros((n, 3)) if position is None else position
    q = np.tile([0.0, 0.0, 0.0, 1.0], (n, 1)) if quat_xyzw is None else quat_xyzw
    for k in range(3):
        fill[k] = pos[:, k]
    for k in range(4):
        fill[3 + k] = q[:, k]
    return _encode_group(msgdefs.ODOMETRY, t_ns, frame_id, child_frame_id, fill)


def encode_pose_stamped(
    t_ns: NDArray[np.int64], position: np.ndarray, quat_xyzw: np.ndarray, frame_id: str = "map"
) -> list[bytes]:
    """geometry_msgs/msg/PoseStamped: position (m) and orientation (x, y, z, w)."""
    fill = {k: position[:, k] for k in range(3)}
    fill.update({3 + k: quat_xyzw[:, k] for k in range(4)})
    return _encode_group(msgdefs.POSE_STAMPED, t_ns, frame_id, "", fill)


def encode_pose_with_covariance_stamped(
    t_ns: NDArray[np.int64], position: np.ndarray, quat_xyzw: np.ndarray,
    covariance: np.ndarray, frame_id: str = "map",
) -> list[bytes]:
    """geometry_msgs/msg/PoseWithCovarianceStamped: position (m), orientation (x, y, z, w)
    and the (N, 6, 6) covariance in ROS order (x, y, z, rot x, rot y, rot z)."""
    fill = {k: position[:, k] for k in range(3)}
    fill.update({3 + k: quat_xyzw[:, k] for k in range(4)})
    cov = np.asarray(covariance, dtype=np.float64).reshape(len(t_ns), 36)
    fill.update({7 + k: cov[:, k] for k in range(36)})
    return _encode_group(msgdefs.POSE_WITH_COVARIANCE_STAMPED, t_ns, frame_id, "", fill)


def encode_transform_stamped(
    t_ns: NDArray[np.int64],
    position: np.ndarray,
    quat_xyzw: np.ndarray,
    frame_id: str = "map",
    child_frame_id: str = "base_link",
) -> list[bytes]:
    """geometry_msgs/msg/TransformStamped: translation (m) and rotation (x, y, z, w)."""
    fill = {k: position[:, k] for k in range(3)}
    fill.update({3 + k: quat_xyzw[:, k] for k in range(4)})
    return _encode_group(msgdefs.TRANSFORM_STAMPED, t_ns, frame_id, child_frame_id, fill)


def encode_range(
    t_ns: NDArray[np.int64],
    anchor_ids: Sequence[str],
    anchor: np.ndarray,
    rng: np.ndarray,
    min_range: float = 0.0,
    max_range: float = 200.0,
) -> list[bytes]:
    """sensor_msgs/msg/Range with header.frame_id = anchor id, range in metres (float32).

    `anchor` indexes `anchor_ids`; radiation_type 0, field_of_view 2*pi.
    """
    n = len(t_ns)
    out: list[bytes] = [b""] * n
    anchor = np.asarray(anchor)
    for a in np.unique(anchor):
        idx = np.flatnonzero(anchor == a)
        k = len(idx)
        fill = {
            0: np.full(k, 2 * np.pi), 1: np.full(k, min_range), 2: np.full(k, max_range),
            3: np.asarray(rng)[idx],
        }
        msgs = _encode_group(
            msgdefs.RANGE, np.asarray(t_ns)[idx], anchor_ids[int(a)], "", fill, floats32=True
        )
        for i, b in zip(idx.tolist(), msgs, strict=True):
            out[i] = b
    return out


def encode_uwb_range(
    t_ns: NDArray[np.int64],
    anchor_ids: Sequence[str],
    anchor: np.ndarray,
    rng: np.ndarray,
    rssi_dbm: np.ndarray,
    first_path_dbm: np.ndarray,
    frame_id: str = "uwb_tag",
) -> list[bytes]:
    """`msgdefs.UWB_RANGE`: anchor_id (text), range (m), rssi and first_path_power (dBm),
    all float32; `anchor` indexes `anchor_ids`."""
    n = len(t_ns)
    out: list[bytes] = [b""] * n
    anchor = np.asarray(anchor)
    for a in np.unique(anchor):
        idx = np.flatnonzero(anchor == a)
        fill = {0: np.asarray(rng)[idx], 1: np.asarray(rssi_dbm)[idx],
                2: np.asarray(first_path_dbm)[idx]}
        msgs = _encode_group(msgdefs.UWB_RANGE, np.asarray(t_ns)[idx], frame_id,
                             anchor_ids[int(a)], fill, floats32=True)
        for i, b in zip(idx.tolist(), msgs, strict=True):
            out[i] = b
    return out


# ----------------------------------------------------------------------------------------
# decoding


@cache
def _expected_layout(type_name: str) -> ros2msg.Layout:
    layout = ros2msg.layout_of(type_name, msgdefs.schema_text(type_name))
    assert layout is not None
    return layout


def fast_type(schema_name: str, schema_encoding: str, schema_text: str) -> str | None:
    """The fast-decodable type whose layout the schema starts with, or None.

    The schema's flattened layout must begin with ours (trailing extra fields, as in later
    ROS distributions, do not move the fields read here).
    """
    if schema_encoding != "ros2msg":
        return None
    name = ros2msg.normalize_type(schema_name)
    for type_name in FAST_TYPES:
        if ros2msg.normalize_type(type_name) == name:
            break
    else:
        return None
    try:
        layout = _layout_cached(schema_name, schema_text)
    except ros2msg.SchemaError:
        return None  # the generic decoder says why
    expected = _expected_layout(type_name)
    if layout is None or layout[: len(expected)] != expected:
        return None
    return type_name


@cache
def _layout_cached(schema_name: str, schema_text: str) -> ros2msg.Layout | None:
    return ros2msg.layout_of(schema_name, schema_text)


def _take(arr: U8, offs: np.ndarray, width: int) -> U8:
    """(n, width) bytes arr[o : o + width] for every offset o."""
    return arr[offs[:, None] + np.arange(width, dtype=np.int64)]


def _f8(arr: U8, offs: np.ndarray, k: int) -> np.ndarray:
    """(n, k) float64 values starting at byte offsets `offs` (little-endian)."""
    return _take(arr, offs, 8 * k).view("<f8")


def _va4(p: np.ndarray) -> np.ndarray:
    return (p + 3) & ~3


def _va8(p: np.ndarray) -> np.ndarray:
    return (p + 7) & ~7


def _empty_columns(type_name: str, n: int) -> dict[str, np.ndarray]:
    cols: dict[str, np.ndarray] = {"t_ns": np.zeros(n, dtype=np.int64)}
    if type_name == msgdefs.IMU:
        cols["gyro"] = np.zeros((n, 3))
        cols["accel"] = np.zeros((n, 3))
    elif type_name == msgdefs.ODOMETRY:
        cols.update(v=np.zeros(n), omega=np.zeros(n), position=np.zeros((n, 3)),
                    quat=np.zeros((n, 4)))
    elif type_name == msgdefs.RANGE:
        cols["range"] = np.zeros(n)
        cols["frame_id"] = np.empty(n, dtype=object)
    elif type_name == msgdefs.UWB_RANGE:
        cols.update(range=np.zeros(n), rssi=np.zeros(n), first_path=np.zeros(n),
                    anchor_id=np.empty(n, dtype=object))
    elif type_name in (msgdefs.POSE_STAMPED, msgdefs.TRANSFORM_STAMPED):
        cols.update(position=np.zeros((n, 3)), quat=np.zeros((n, 4)))
    elif type_name == msgdefs.POSE_WITH_COVARIANCE_STAMPED:
        cols.update(position=np.zeros((n, 3)), quat=np.zeros((n, 4)),
                    covariance=np.zeros((n, 6, 6)))
    else:
        raise KeyError(type_name)
    return cols


def decode_at(
    type_name: str, arr: U8, offset: np.ndarray, length: np.ndarray
) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Decode the messages `arr[offset[i] : offset[i] + length[i]]` of a fixed-layout type.

    Only the bytes of the fields read are gathered. Returns (ok, columns): ok (n,) bool
    marks the messages decoded here (the rest need the generic decoder: other
    encapsulations, lengths that do not add up); columns hold n rows each (zeros where not
    ok): `t_ns` int64 header stamp and per type `gyro`/`accel` (Imu, (n,3)),
    `v`/`omega`/`position`/`quat` (Odometry), `range` float64 and `frame_id` str (Range),
    `position`/`quat` (PoseStamped, TransformStamped; PoseWithCovarianceStamped also
    `covariance` (n,6,6), ROS order).
    """
    n = len(offset)
    cols = _empty_columns(type_name, n)
    ok = length >= 16
    if not ok.any():
        return ok, cols
    sel = np.flatnonzero(ok)
    o, ln = offset[sel], length[sel]
    head = _take(arr, o, 16)
    good = np.all(head[:, 0:4] == np.frombuffer(_CDR_LE, dtype=np.uint8), axis=1)
    l1 = head[:, 12:16].view("<u4")[:, 0].astype(np.int64)
    p = 12 + l1  # payload offset after the header
    if type_name in _HAS_CHILD:
        c = _va4(p)
        good &= 4 + c + 4 <= ln
        l2 = np.zeros(len(o), dtype=np.int64)
        l2[good] = _take(arr, o[good] + 4 + c[good], 4).view("<u4")[:, 0]
        start = _va4(c + 4 + l2) if type_name == msgdefs.UWB_RANGE else _va8(c + 4 + l2)
    elif type_name == msgdefs.RANGE:
        start = _va4(p + 1)
    else:
        start = _va8(p)
    size = {msgdefs.IMU: 37 * 8, msgdefs.ODOMETRY: 85 * 8, msgdefs.RANGE: 16,
            msgdefs.UWB_RANGE: 12,
            msgdefs.POSE_WITH_COVARIANCE_STAMPED: 43 * 8}.get(type_name, 56)
    good &= (4 + start + size <= ln) & (l1 < ln)
    if type_name in _HAS_CHILD:
        l2, c = l2[good], c[good]
    sel, o, head, start, l1 = sel[good], o[good], head[good], start[good], l1[good]
    ok[:] = False
    ok[sel] = True
    sec = head[:, 4:8].view("<i4")[:, 0].astype(np.int64)
    nsec = head[:, 8:12].view("<u4")[:, 0].astype(np.int64)
    cols["t_ns"][sel] = sec * _NS + nsec
    b = o + 4 + start
    if type_name == msgdefs.IMU:
        cols["gyro"][sel] = _f8(arr, b + 13 * 8, 3)
        cols["accel"][sel] = _f8(arr, b + 25 * 8, 3)
    elif type_name == msgdefs.ODOMETRY:
        pose = _f8(arr, b, 7)
        cols["position"][sel] = pose[:, 0:3]
        cols["quat"][sel] = pose[:, 3:7]
        cols["v"][sel] = _f8(arr, b + 43 * 8, 1)[:, 0]
        cols["omega"][sel] = _f8(arr, b + 48 * 8, 1)[:, 0]
    elif type_name == msgdefs.RANGE:
        cols["range"][sel] = _take(arr, b + 12, 4).view("<f4")[:, 0].astype(np.float64)
        for v1 in np.unique(l1).tolist():
            k = l1 == v1
            # an over-long id is cut one past the limit (the reader drops it as too long)
            width = min(max(v1 - 1, 0), 4 * MAX_ANCHOR_ID_CHARS + 1)
            cols["frame_id"][sel[k]] = _strings(_take(arr, o[k] + 16, width))
    elif type_name == msgdefs.UWB_RANGE:
        f = _take(arr, b, 12).view("<f4").astype(np.float64)
        cols["range"][sel], cols["rssi"][sel], cols["first_path"][sel] = f.T
        for v2 in np.unique(l2).tolist():
            k = l2 == v2
            width = min(max(v2 - 1, 0), 4 * MAX_ANCHOR_ID_CHARS + 1)
            cols["anchor_id"][sel[k]] = _strings(_take(arr, o[k] + 4 + c[k] + 4, width))
    elif type_name == msgdefs.POSE_WITH_COVARIANCE_STAMPED:
        pose = _f8(arr, b, 43)
        cols["position"][sel] = pose[:, 0:3]
        cols["quat"][sel] = pose[:, 3:7]
        cols["covariance"][sel] = pose[:, 7:43].reshape(-1, 6, 6)
    else:
        pose = _f8(arr, b, 7)
        cols["position"][sel] = pose[:, 0:3]
        cols["quat"][sel] = pose[:, 3:7]
    return ok, cols


def decode_fixed(
    type_name: str, datas: Sequence[bytes]
) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """`decode_at` for a list of messages (ok and columns in input order)."""
    lengths = np.fromiter(map(len, datas), dtype=np.int64, count=len(datas))
    offsets = np.concatenate([[0], np.cumsum(lengths)[:-1]]).astype(np.int64)
    arr = np.frombuffer(b"".join(datas), dtype=np.uint8)
    if not len(arr):
        arr = np.zeros(1, dtype=np.uint8)
    return decode_at(type_name, arr, offsets, lengths)


def _strings(chars: U8) -> np.ndarray:
    """Rows of UTF-8 bytes (no NUL) -> object array of str, decoding each distinct row once."""
    n, k = chars.shape
    out = np.empty(n, dtype=object)
    if k == 0:
        out[:] = ""
        return out
    as_bytes = np.ascontiguousarray(chars).view(f"S{k}")[:, 0]
    uniq, inv = np.unique(as_bytes, return_inverse=True)
    decoded = np.array([u.decode("utf-8", errors="replace") for u in uniq], dtype=object)
    out[:] = decoded[inv.reshape(-1)]
    return out
