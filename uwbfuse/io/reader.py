# SPDX-License-Identifier: BSD-3-Clause
"""Read a LOG (a `.mcap` file or a rosbag2 directory) into a columnar `SensorLog`.

Steps: scan the log's storage files for raw message bytes (`rosbag2.scan_log`: MCAP by
`mcap_raw.scan_mcap`, no summary needed, truncation tolerated; sqlite3 through `rosbags`),
decode the role topics of `config.topics` (fixed-layout ROS 2 types vectorised by
`cdr_fast`, everything else by the schema-driven generic decoders), then per stream:
stamps, validity filters, sorting by stamp and removal of exact duplicates. What was
dropped, and why, is counted in
`SensorLog.report`; `report.messages` counts the messages of every topic in the log.

Time: `header.stamp` in integer ns; the MCAP log time only where a message has no header
or a zero stamp. A configured topic that the log lacks gives a `None` stream; a topic
present whose messages were all dropped gives an empty stream.
"""

from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import ValidationError

from uwbfuse.config import Config, MapConfig
from uwbfuse.errors import LogReadError
from uwbfuse.io import cdr_fast, msgdefs, ros2msg
from uwbfuse.io.decoders import DecoderUnavailable, generic_decoder
from uwbfuse.io.fields import MissingField, anchor_key, get_path, has_path, is_valid, stamp_ns
from uwbfuse.io.mcap_raw import MessageRefs, RawChannel, ScanResult
from uwbfuse.io.rosbag2 import scan_log
from uwbfuse.io.writer import ANCHORS_METADATA, MAP_METADATA
from uwbfuse.streams import (
    AnchorMap,
    ImuStream,
    PoseStream,
    RangeStream,
    ReadReport,
    SensorLog,
    WheelStream,
)

log = logging.getLogger(__name__)

IMU, WHEEL, UWB, GT = "imu", "wheel_odom", "uwb", "ground_truth"
ROLES = (IMU, WHEEL, UWB, GT)

# skip reasons counted in ReadReport.skipped
SKIP_INVALID_FLAG = "range flagged invalid"
SKIP_NO_ANCHOR_MAP = "no anchor map"
SKIP_UNKNOWN_ANCHOR = "unknown anchor"
SKIP_NON_FINITE_RANGE = "non-finite range"
SKIP_NON_POSITIVE_RANGE = "non-positive range"  # 0 is many UWB drivers' "no range"
SKIP_RANGE_BOUNDS = "range outside [min_range, max_range]"
SKIP_NO_WHEEL_JOINTS = "joint state without the configured wheel joints"


def skip_duplicate(role: str) -> str:
    """Skip reason for exact duplicates (same stamp, same values) of a role's messages."""
    return f"duplicate {role} message"


def skip_non_finite(role: str) -> str:
    """Skip reason for samples with NaN/inf values (IMU, wheels, ground truth)."""
    return f"non-finite {role} sample"


def skip_undecodable(topic: str) -> str:
    """Skip reason for messages whose bytes do not decode."""
    return f"undecodable message on {topic}"


_ACCEPTED = {
    IMU: (msgdefs.IMU,),
    WHEEL: (msgdefs.ODOMETRY, msgdefs.JOINT_STATE),
    GT: (msgdefs.POSE_STAMPED, msgdefs.ODOMETRY, msgdefs.TRANSFORM_STAMPED,
         "geometry_msgs/msg/PoseWithCovarianceStamped"),
}


def _norm(type_name: str) -> str:
    return ros2msg.normalize_type(type_name)


# ------------------------------------------------------------------------------------------
# per-channel collection


@dataclass
class _Columns:
    """Decoded columns of one role from one channel (file order, unsorted)."""

    t_ns: list[np.ndarray] = field(default_factory=list)
    log_time: list[np.ndarray] = field(default_factory=list)
    data: dict[str, list[np.ndarray]] = field(default_factory=dict)

    def add(self, t_ns: np.ndarray, log_time: np.ndarray, **cols: np.ndarray) -> None:
        self.t_ns.append(np.asarray(t_ns, dtype=np.int64))
        self.log_time.append(np.asarray(log_time, dtype=np.int64))
        for k, v in cols.items():
            self.data.setdefault(k, []).append(np.asarray(v))

    def cat(self, name: str, shape: tuple[int, ...] = (), dtype: Any = np.float64) -> np.ndarray:
        """Column `name` over all parts (the parts are released)."""
        parts = self.data.pop(name, [])
        if not parts:
            return np.zeros((0, *shape), dtype=dtype)
        return parts[0] if len(parts) == 1 else np.concatenate(parts)

    def stamps(self) -> tuple[np.ndarray, np.ndarray]:
        """Header stamps and log times over all parts (the parts are released)."""
        t, lt = self.t_ns, self.log_time
        self.t_ns, self.log_time = [], []
        if not t:
            return np.zeros(0, np.int64), np.zeros(0, np.int64)
        return np.concatenate(t), np.concatenate(lt)


class _ChannelSink:
    """Collects one role channel's messages: vectorised decode where possible, else bytes."""

    def __init__(self, channel: RawChannel, roles: list[str]) -> None:
        self.channel = channel
        self.roles = roles
        self.type_name = _norm(channel.schema.name) if channel.schema else ""
        self.fast: str | None = None
        if channel.message_encoding == "cdr" and channel.schema is not None:
            self.fast = cdr_fast.fast_type(
                channel.schema.name, channel.schema.encoding,
                channel.schema.data.decode("utf-8", errors="replace"),
            )
        if UWB in roles and self.fast not in (None, msgdefs.RANGE):
            self.fast = None  # other types on the UWB topic go through the [uwb] mapping
        self.fast_parts: list[tuple[np.ndarray, dict[str, np.ndarray]]] = []
        self.pending_time: list[np.ndarray] = []
        self.pending: list[bytes] = []

    def add(self, refs: MessageRefs) -> None:
        if self.fast is None:
            self.pending_time.append(refs.log_time)
            self.pending.extend(refs.payloads())
            return
        ok, cols = cdr_fast.decode_at(self.fast, refs.arr, refs.offset, refs.length)
        if ok.all():
            self.fast_parts.append((refs.log_time, cols))
            return
        if ok.any():
            self.fast_parts.append((refs.log_time[ok], {k: v[ok] for k, v in cols.items()}))
        self.pending_time.append(refs.log_time[~ok])
        self.pending.extend(refs.payloads(~ok))

    def pending_messages(self) -> tuple[np.ndarray, list[bytes]]:
        """Log times and bytes of the messages the vectorised path did not decode."""
        times = np.concatenate(self.pending_time) if self.pending_time else np.zeros(0, np.int64)
        return times, self.pending


# ------------------------------------------------------------------------------------------
# generic extraction (decoded objects -> columns)


class _FieldError(Exception):
    """A configured field is missing from a message (bad config for this log)."""


def _vec(msg: Any, path: str, names: str = "xyz") -> tuple[float, ...]:
    return tuple(float(get_path(msg, f"{path}.{c}")) for c in names)


def _kind(role: str, type_name: str, msg: Any) -> str:
    """What to read from a decoded message of `role` (type from schema, else by its fields)."""
    t = _norm(type_name) if type_name else ""
    if role == UWB:
        return "range" if t == _norm(msgdefs.RANGE) else "mapped"
    if role == IMU:
        return "imu"
    by_type = {_norm(msgdefs.ODOMETRY): "odometry", _norm(msgdefs.JOINT_STATE): "joint_state",
               "geometry_msgs/PoseWithCovarianceStamped": "odometry",  # pose.pose as well
               _norm(msgdefs.POSE_STAMPED): "pose", _norm(msgdefs.TRANSFORM_STAMPED):
               "transform"}
    if t in by_type:
        return by_type[t]
    # no schema name (e.g. schemaless json): guess from the fields
    if has_path(msg, "twist.twist"):
        return "odometry"
    if has_path(msg, "velocity") and has_path(msg, "name"):
        return "joint_state"
    if has_path(msg, "transform.translation"):
        return "transform"
    return "pose"


def _extract_generic(
    sink: _ChannelSink, role: str, msgs: list[Any], log_time: np.ndarray, cols: _Columns,
    config: Config, report: ReadReport,
) -> None:
    """Columns of `role` from decoded messages (objects or dicts)."""
    if not msgs:
        return
    kind = _kind(role, sink.type_name, msgs[0])
    stamps = np.array([stamp_ns(m) for m in msgs], dtype=np.int64)
    try:
        if kind == "imu":
            g = np.array([_vec(m, "angular_velocity") for m in msgs], dtype=np.float64)
            a = np.array([_vec(m, "linear_acceleration") for m in msgs], dtype=np.float64)
            cols.add(stamps, log_time, gyro=g, accel=a)
        elif kind == "odometry" and role == WHEEL:
            v = [float(get_path(m, "twist.twist.linear.x")) for m in msgs]
            w = [float(get_path(m, "twist.twist.angular.z")) for m in msgs]
            cols.add(stamps, log_time, v=np.array(v), omega=np.array(w))
        elif kind == "joint_state":
            _joint_states(msgs, stamps, log_time, cols, config, report)
        elif kind in ("odometry", "pose", "transform"):
            base = {"odometry": "pose.pose", "pose": "pose", "transform": "transform"}[kind]
            pname, qname = ("translation", "rotation") if kind == "transform" else (
                "position", "orientation")
            p = np.array([_vec(m, f"{base}.{pname}") for m in msgs], dtype=np.float64)
            q = np.array([_vec(m, f"{base}.{qname}", "xyzw") for m in msgs], dtype=np.float64)
            cols.add(stamps, log_time, position=p, quat=q)
        elif kind == "range":
            ids = np.array([anchor_key(get_path(m, "header.frame_id")) for m in msgs],
                           dtype=object)
            r = np.array([float(get_path(m, "range")) for m in msgs])
            cols.add(stamps, log_time, anchor=ids, range=r, valid=np.ones(len(msgs), bool))
        else:
            _mapped_ranges(msgs, stamps, log_time, cols, config)
    except MissingField as e:
        raise _FieldError(str(e.args[0])) from None


def _joint_states(
    msgs: list[Any], stamps: np.ndarray, log_time: np.ndarray, cols: _Columns,
    config: Config, report: ReadReport,
) -> None:
    wc = config.wheel
    keep, vl, vr = [], [], []
    for i, m in enumerate(msgs):
        names = list(get_path(m, "name"))
        vel = list(get_path(m, "velocity"))
        try:
            li, ri = names.index(wc.left_joint), names.index(wc.right_joint)
            wl, wr = float(vel[li]), float(vel[ri])
        except (ValueError, IndexError):
            report.skip(SKIP_NO_WHEEL_JOINTS)
            continue
        keep.append(i)
        vl.append(wl)
        vr.append(wr)
    k = np.asarray(keep, dtype=np.int64)
    wl_a, wr_a = np.asarray(vl, dtype=np.float64), np.asarray(vr, dtype=np.float64)
    v = wc.radius * (wl_a + wr_a) / 2.0
    omega = wc.radius * (wr_a - wl_a) / wc.track_width
    cols.add(stamps[k], log_time[k], v=v, omega=omega)


def _mapped_ranges(
    msgs: list[Any], stamps: np.ndarray, log_time: np.ndarray, cols: _Columns, config: Config
) -> None:
    """Ranges of a non-Range type through the [uwb] field mapping (arrays included)."""
    u = config.uwb
    t_out, lt_out, ids, rng, valid = [], [], [], [], []
    for m, t, lt in zip(msgs, stamps.tolist(), log_time.tolist(), strict=True):
        elems = get_path(m, u.array_field) if u.array_field else (m,)
        for e in elems:
            t_out.append(t)
            lt_out.append(lt)
            ids.append(anchor_key(get_path(e, u.anchor_field)))
            rng.append(_to_float(get_path(e, u.range_field)))
            valid.append(is_valid(get_path(e, u.valid_field)) if u.valid_field else True)
    cols.add(np.array(t_out, dtype=np.int64), np.array(lt_out, dtype=np.int64),
             anchor=np.array(ids, dtype=object), range=np.array(rng, dtype=np.float64),
             valid=np.array(valid, dtype=bool))


def _to_float(v: Any) -> float:
    try:
        return float(v)
    except (TypeError, ValueError):
        return math.nan


# ------------------------------------------------------------------------------------------
# reading


@dataclass
class _Role:
    """All columns read for one role over every file and channel."""

    columns: _Columns = field(default_factory=_Columns)
    present: bool = False


def _fast_columns(sink: _ChannelSink, role: str, cols: _Columns) -> None:
    for lt, c in sink.fast_parts:
        if role == IMU:
            cols.add(c["t_ns"], lt, gyro=c["gyro"], accel=c["accel"])
        elif role == WHEEL:
            cols.add(c["t_ns"], lt, v=c["v"], omega=c["omega"])
        elif role == GT:
            cols.add(c["t_ns"], lt, position=c["position"], quat=c["quat"])
        else:
            cols.add(c["t_ns"], lt, anchor=c["frame_id"], range=c["range"],
                     valid=np.ones(len(lt), dtype=bool))


def _type_problem(sink: _ChannelSink, role: str) -> str | None:
    """Why `sink`'s type cannot serve `role`, or None. Non-ROS (e.g. json) names pass."""
    accepted = _ACCEPTED.get(role)
    if accepted is None or "/" not in sink.type_name:
        return None
    if sink.type_name in {_norm(a) for a in accepted}:
        return None
    return f"has type {sink.type_name!r} but the {role} role accepts {', '.join(accepted)}"


class _Problems:
    """Problems with role topics: errors for sensor roles, warnings for ground truth."""

    def __init__(self, source: str, report: ReadReport) -> None:
        self.source = source
        self.report = report

    def __call__(self, role: str, topic: str, what: str) -> None:
        if role == GT:  # optional and never used by estimators: do not fail a run over it
            self.report.warnings.append(f"ground truth not read: topic {topic!r} {what}")
            return
        raise LogReadError(f"{self.source}: topic {topic!r} {what}")


def _collect(
    source: str, sinks: list[_ChannelSink], roles: dict[str, _Role], config: Config,
    report: ReadReport,
) -> None:
    """Decode what each channel sink holds into the role columns."""
    problem = _Problems(source, report)
    for sink in sinks:
        topic = sink.channel.topic
        usable = []
        for role in sink.roles:
            why = _type_problem(sink, role)
            if why is not None:
                problem(role, topic, why)
                continue
            usable.append(role)
            roles[role].present = True
            _fast_columns(sink, role, roles[role].columns)
        if not sink.pending or not usable:
            continue
        lt, datas = sink.pending_messages()
        try:
            decode = generic_decoder(sink.channel)
        except DecoderUnavailable as e:
            for role in usable:
                if role == GT:
                    roles[GT].present = False
                problem(role, topic, str(e))
            continue
        msgs: list[Any] = []
        keep: list[int] = []
        for i, d in enumerate(datas):
            try:
                msgs.append(decode(d))
            except Exception:  # corrupt bytes raise struct/index/unicode/json errors
                continue
            keep.append(i)
        report.skip(skip_undecodable(topic), len(datas) - len(keep))
        lt_kept = lt[np.asarray(keep, dtype=np.int64)]
        for role in usable:
            try:
                _extract_generic(sink, role, msgs, lt_kept, roles[role].columns, config,
                                 report)
            except _FieldError as e:
                key = {UWB: " (see [uwb] anchor_field/range_field/array_field/valid_field)"}
                problem(role, topic, f"({sink.type_name or 'no schema'}) has no field "
                        f"{e.args[0]!r}{key.get(role, '')}")


def _stamps(cols: _Columns, role: str, topic: str, report: ReadReport) -> np.ndarray:
    """Header stamps, with the log time where the stamp is zero (header missing or empty)."""
    t, lt = cols.stamps()
    zero = t == 0
    n = int(zero.sum())
    if n:
        report.warnings.append(
            f"{topic}: {n} {role} messages without a header stamp: log time used"
        )
        t = np.where(zero, lt, t)
    return t


def _sort_dedup(
    t: np.ndarray, values: list[np.ndarray], role: str, report: ReadReport
) -> np.ndarray | None:
    """Indices that sort by stamp with exact duplicates (stamp and values) removed.

    None when `t` is already strictly increasing (nothing to do).
    """
    if len(t) < 2 or bool(np.all(t[1:] > t[:-1])):
        return None
    order = np.argsort(t, kind="stable")
    ts = t[order]
    if bool(np.all(ts[1:] > ts[:-1])):
        return order
    flat = [v.reshape(len(t), -1) for v in values]
    keys = [c[:, j] for c in reversed(flat) for j in reversed(range(c.shape[1]))]
    order = np.lexsort([*keys, t])
    same = t[order][1:] == t[order][:-1]
    for c in flat:
        same &= np.all(c[order][1:] == c[order][:-1], axis=1)
    dup = np.concatenate([[False], same])
    report.skip(skip_duplicate(role), int(dup.sum()))
    kept = order[~dup]
    ties = int(np.sum(t[kept][1:] == t[kept][:-1]))
    if ties and role != "uwb":  # one range message may carry ranges to several anchors
        report.warnings.append(f"{ties} {role} samples share a stamp with another sample")
    return kept


def _finite_rows(role: str, report: ReadReport, *arrays: np.ndarray) -> np.ndarray | None:
    """Mask of the rows with finite values in every array; None if all are finite."""
    ok = np.ones(len(arrays[0]), dtype=bool)
    for a in arrays:
        ok &= np.all(np.isfinite(a.reshape(len(a), -1)), axis=1)
    bad = int((~ok).sum())
    report.skip(skip_non_finite(role), bad)
    return ok if bad else None


def _rows(sel: np.ndarray | None, *arrays: np.ndarray) -> list[np.ndarray]:
    """`arrays` restricted to `sel` (mask or index; None keeps them, without copying)."""
    return list(arrays) if sel is None else [a[sel] for a in arrays]


def _clean(
    t: np.ndarray, values: list[np.ndarray], role: str, report: ReadReport
) -> list[np.ndarray]:
    """[t, *values] without non-finite rows and exact duplicates, sorted by stamp."""
    cols = _rows(_finite_rows(role, report, *values), t, *values)
    return _rows(_sort_dedup(cols[0], cols[1:], role, report), *cols)


def _imu_stream(r: _Role, topic: str, report: ReadReport) -> ImuStream | None:
    if not r.present:
        return None
    c = r.columns
    t = _stamps(c, IMU, topic, report)
    t, g, a = _clean(t, [c.cat("gyro", (3,)), c.cat("accel", (3,))], "imu", report)
    return ImuStream(t, np.ascontiguousarray(g), np.ascontiguousarray(a))


def _wheel_stream(r: _Role, topic: str, report: ReadReport) -> WheelStream | None:
    if not r.present:
        return None
    c = r.columns
    t = _stamps(c, "wheel", topic, report)
    t, v, w = _clean(t, [c.cat("v"), c.cat("omega")], "wheel", report)
    return WheelStream(t, v, w)


def _gt_stream(r: _Role, topic: str, report: ReadReport) -> PoseStream | None:
    if not r.present:
        return None
    c = r.columns
    t = _stamps(c, "ground-truth", topic, report)
    t, p, q = _clean(t, [c.cat("position", (3,)), c.cat("quat", (4,))], "ground-truth",
                     report)
    norm = np.linalg.norm(q, axis=1)
    identity = np.all(q[:, :3] == 0.0, axis=1) & ((q[:, 3] == 1.0) | (q[:, 3] == 0.0))
    has_orientation = bool(len(q)) and not bool(np.all(identity))
    q = np.where((norm > 0)[:, None], q / np.where(norm > 0, norm, 1.0)[:, None],
                 np.array([0.0, 0.0, 0.0, 1.0]))
    return PoseStream(t, np.ascontiguousarray(p), np.ascontiguousarray(q),
                      has_orientation=has_orientation)


def _range_stream(
    r: _Role, topic: str, anchors: AnchorMap | None, config: Config, report: ReadReport
) -> RangeStream | None:
    if not r.present:
        return None
    u = config.uwb
    c = r.columns
    t = _stamps(c, "uwb", topic, report)
    ids = c.cat("anchor", dtype=object)
    rng = c.cat("range")
    valid = c.cat("valid", dtype=bool)
    keep = valid.copy()
    report.skip(SKIP_INVALID_FLAG, int((~valid).sum()))
    anchor = np.full(len(t), -1, dtype=np.int32)
    if anchors is None:
        report.skip(SKIP_NO_ANCHOR_MAP, int(keep.sum()))
        keep[:] = False
    elif len(ids):
        uniq, inv = np.unique(ids.astype(str), return_inverse=True)
        known = {a: i for i, a in enumerate(anchors.ids)}
        lut = np.array([known.get(str(a), -1) for a in uniq], dtype=np.int32)
        anchor = lut[inv.reshape(-1)]
        unknown = keep & (anchor < 0)
        if unknown.any():
            report.skip(SKIP_UNKNOWN_ANCHOR, int(unknown.sum()))
            names = sorted({str(x) for x in uniq[lut < 0]})
            report.warnings.append(
                f"{topic}: ranges to anchors not in the anchor map: {', '.join(names[:10])}"
                + (" ..." if len(names) > 10 else "")
            )
            keep &= ~unknown
    for reason, bad in (
        (SKIP_NON_FINITE_RANGE, ~np.isfinite(rng)),
        (SKIP_NON_POSITIVE_RANGE, rng <= 0),
        (SKIP_RANGE_BOUNDS, (rng < u.min_range) | (rng > u.max_range)),
    ):
        with np.errstate(invalid="ignore"):
            drop = keep & bad
        report.skip(reason, int(drop.sum()))
        keep &= ~drop
    t, anchor, rng = t[keep], anchor[keep], rng[keep]
    if anchors is not None and u.range_offset:
        off = np.array([u.range_offset.get(a, 0.0) for a in anchors.ids], dtype=np.float64)
        rng = rng - off[anchor]
        stray = sorted(set(u.range_offset) - set(anchors.ids))
        if stray:
            report.warnings.append(f"[uwb.range_offset] names unknown anchors: "
                                   f"{', '.join(stray)}")
    t, anchor, rng = _rows(_sort_dedup(t, [anchor, rng], "uwb", report), t, anchor, rng)
    return RangeStream(t, anchor.astype(np.int32), rng)


def _metadata_anchors(source: str, scans: list[ScanResult]) -> AnchorMap | None:
    for scan in scans:
        for name, data in scan.metadata:
            if name != ANCHORS_METADATA:
                continue
            out: dict[str, list[float]] = {}
            for k, v in data.items():
                try:
                    xyz = json.loads(v)
                    ok = (isinstance(xyz, list) and len(xyz) == 3
                          and all(isinstance(c, (int, float)) and math.isfinite(c) for c in xyz))
                except ValueError:
                    ok = False
                if not ok:
                    raise LogReadError(
                        f"{source}: metadata record {ANCHORS_METADATA!r}: anchor {k!r} is "
                        f"{v!r}, expected a JSON array [x, y, z] of finite numbers"
                    )
                out[k] = [float(c) for c in xyz]
            if out:
                return AnchorMap.from_dict(out)
    return None


def _metadata_map(source: str, scans: list[ScanResult]) -> MapConfig | None:
    """The `map_obstacles` record (obstacle id -> JSON "[[x, y], ...]") as a `[map]`."""
    for scan in scans:
        for name, data in scan.metadata:
            if name != MAP_METADATA:
                continue
            try:
                polys = [json.loads(v) for v in data.values()]
                return MapConfig(obstacles=polys)
            except ValidationError as e:
                why = e.errors()[0]["msg"].removeprefix("Value error, ")
            except ValueError as e:  # not JSON
                why = str(e)
            raise LogReadError(
                f"{source}: metadata record {MAP_METADATA!r}: expected obstacle id -> JSON "
                f"array of >= 3 [x, y] vertices: {why}")
    return None


def _log_map(source: str, scans: list[ScanResult], config: Config) -> MapConfig | None:
    """The config's `[map]` when it has anything, else the log's metadata record."""
    m = config.map
    if m.obstacles or m.walls or m.boundary:
        return m
    return _metadata_map(source, scans)


def _role_topics(config: Config) -> dict[str, list[str]]:
    topics = {IMU: config.topics.imu, WHEEL: config.topics.wheel_odom, UWB: config.topics.uwb,
              GT: config.topics.ground_truth}
    out: dict[str, list[str]] = {}
    for role, topic in topics.items():
        if topic:
            out.setdefault(topic, []).append(role)
    return out


def read_log(path: str | Path, config: Config) -> SensorLog:
    """Read LOG `path` (an MCAP file or a rosbag2 directory) with the topics of `config`.

    Raises LogReadError (one line naming the file) for a missing path, a file that is not
    MCAP, a directory without MCAP files, a log without messages, or one where none of the
    configured topics is present.
    """
    source = str(path)
    by_topic = _role_topics(config)
    sinks: list[_ChannelSink] = []

    def want(channel: RawChannel) -> _ChannelSink | None:
        roles = by_topic.get(channel.topic)
        if roles is None:
            return None
        sink = _ChannelSink(channel, roles)
        sinks.append(sink)
        return sink

    report = ReadReport()
    scans = scan_log(path, want)
    for scan in scans:
        prefix = f"{scan.path.name}: " if len(scans) > 1 else ""
        report.warnings.extend(prefix + w for w in scan.warnings)
        if scan.lost_messages_unknown_channel:
            report.skip("message on an undefined channel", scan.lost_messages_unknown_channel)
        for cm in scan.channels.values():
            report.messages[cm.channel.topic] += cm.count

    if sum(report.messages.values()) == 0:
        why = f" ({scans[-1].warnings[0]})" if scans and scans[-1].warnings else ""
        raise LogReadError(f"{source}: log contains no messages{why}")
    if not any(t in report.messages for t in by_topic):
        wanted = ", ".join(sorted(by_topic)) or "none"
        present = ", ".join(sorted(report.messages))
        raise LogReadError(
            f"{source}: none of the configured topics ({wanted}) is in the log "
            f"(topics present: {present}); set them under [topics]"
        )

    roles = {r: _Role() for r in ROLES}
    _collect(source, sinks, roles, config, report)
    anchors = (AnchorMap.from_dict(dict(config.anchors)) if config.anchors
               else _metadata_anchors(source, scans))
    topics = config.topics
    out = SensorLog(
        imu=_imu_stream(roles[IMU], topics.imu, report),
        wheel=_wheel_stream(roles[WHEEL], topics.wheel_odom, report),
        ranges=_range_stream(roles[UWB], topics.uwb, anchors, config, report),
        anchors=anchors,
        ground_truth=_gt_stream(roles[GT], topics.ground_truth, report),
        source=source,
        report=report,
        map=_log_map(source, scans, config),
    )
    for line in report.lines():
        log.debug("%s: %s", source, line)
    return out
