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
from uwbfuse.io.fields import (
    MAX_ANCHOR_ID_CHARS,
    MAX_COORD_M,
    MissingField,
    anchor_key,
    get_path,
    has_path,
    is_valid,
    stamp_ns,
)
from uwbfuse.io.mcap_raw import MessageRefs, RawChannel, ScanResult
from uwbfuse.io.rosbag2 import scan_log
from uwbfuse.io.writer import ANCHORS_METADATA, MAP_METADATA, UWB_FIELDS_METADATA
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

IMU, WHEEL, UWB, GT, POSE = "imu", "wheel_odom", "uwb", "ground_truth", "pose"
ROLES = (IMU, WHEEL, UWB, GT, POSE)

# skip reasons counted in ReadReport.skipped
SKIP_INVALID_FLAG = "range flagged invalid"
SKIP_NO_ANCHOR_MAP = "no anchor map"
SKIP_UNKNOWN_ANCHOR = "unknown anchor"
SKIP_NON_FINITE_RANGE = "non-finite range"
SKIP_NON_POSITIVE_RANGE = "non-positive range"  # 0 is many UWB drivers' "no range"
SKIP_RANGE_BOUNDS = "range outside [min_range, max_range]"
SKIP_NO_WHEEL_JOINTS = "joint state without the configured wheel joints"
SKIP_BAD_STAMP = "negative or unreadable stamp"
SKIP_FAR_STAMP = "stamp far from the rest of the log"
SKIP_BAD_POWER = "missing, non-finite or implausible signal power (range kept without it)"
SKIP_LONG_ANCHOR_ID = f"anchor id longer than {MAX_ANCHOR_ID_CHARS} characters"

# Physical bounds on the sensor values read (beyond them a sample is corrupt, not a
# reading): counted skips, as NaN values are.
MAX_GYRO_RAD_S = 200.0  # 11,500 deg/s: 5x the full scale of the fastest MEMS gyros
MAX_ACCEL_M_S2 = 2000.0  # 200 g: the range of high-g shock accelerometers
# dBm: UWB receivers report about -60 to -110 dBm; beyond these a power value is corrupt
# (+50 dBm is 100 W radiated, -200 dBm is far below the thermal noise of any bandwidth)
MIN_POWER_DBM, MAX_POWER_DBM = -200.0, 50.0
MAX_WHEEL_SPEED_M_S = 100.0  # 360 km/h: no wheeled indoor vehicle comes near
MAX_WHEEL_YAW_RATE_RAD_S = 100.0  # 16 turns per second
# Sensor stamps more than this from every other sensor stamp are another recording or a
# broken clock, not a gap in this log: they are dropped (else one stamp a year off would
# stretch the output grid over that year).
MAX_STAMP_GAP_NS = 3600 * 1_000_000_000


def skip_duplicate(role: str) -> str:
    """Skip reason for exact duplicates (same stamp, same values) of a role's messages."""
    return f"duplicate {role} message"


def skip_non_finite(role: str) -> str:
    """Skip reason for samples with NaN/inf values (IMU, wheels, ground truth)."""
    return f"non-finite {role} sample"


def skip_undecodable(topic: str) -> str:
    """Skip reason for messages whose bytes do not decode."""
    return f"undecodable message on {topic}"


def skip_malformed(topic: str) -> str:
    """Skip reason for decoded messages whose fields hold no usable number."""
    return f"message with an unusable field on {topic}"


# skip reasons per role: samples beyond the physical bounds (MAX_GYRO_RAD_S, ...), and a
# stream of one sample (no rate, no time span)
SKIP_IMPLAUSIBLE = "implausible {} sample (beyond the physical bounds)"
SKIP_LONE = "lone {} sample (a stream needs at least two)"


_ACCEPTED = {
    IMU: (msgdefs.IMU,),
    WHEEL: (msgdefs.ODOMETRY, msgdefs.JOINT_STATE),
    GT: (msgdefs.POSE_STAMPED, msgdefs.ODOMETRY, msgdefs.TRANSFORM_STAMPED,
         msgdefs.POSE_WITH_COVARIANCE_STAMPED),
    POSE: (msgdefs.POSE_WITH_COVARIANCE_STAMPED, msgdefs.POSE_STAMPED),
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


def _uwb_fast_ok(config: Config) -> bool:
    """Whether the [uwb] mapping reads `msgdefs.UWB_RANGE` as its vectorised decoder does
    (anchor_id, range, rssi, first_path_power; no array, no validity flag)."""
    u = config.uwb
    return (u.anchor_field == "anchor_id" and u.range_field == "range" and not u.array_field
            and not u.valid_field and u.rssi_field in ("", "rssi")
            and u.first_path_power_field in ("", "first_path_power"))


class _ChannelSink:
    """Collects one role channel's messages: vectorised decode where possible, else bytes."""

    def __init__(self, channel: RawChannel, roles: list[str], config: Config) -> None:
        self.channel = channel
        self.roles = roles
        self.type_name = _norm(channel.schema.name) if channel.schema else ""
        self.fast: str | None = None
        if channel.message_encoding == "cdr" and channel.schema is not None:
            self.fast = cdr_fast.fast_type(
                channel.schema.name, channel.schema.encoding,
                channel.schema.data.decode("utf-8", errors="replace"),
            )
        if UWB in roles and self.fast not in (None, msgdefs.RANGE) and not (
                self.fast == msgdefs.UWB_RANGE and _uwb_fast_ok(config)):
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


_BAD_VALUE = (TypeError, ValueError, OverflowError, AttributeError)


def _per_message(
    msgs: list[Any], fn: Any, topic: str, report: ReadReport
) -> tuple[np.ndarray, list[Any]]:
    """fn(message) for every message; those whose fields are not usable (a list where a
    number belongs, text, an int too large for a float) are counted and left out."""
    keep: list[int] = []
    rows: list[Any] = []
    for i, m in enumerate(msgs):
        try:
            rows.append(fn(m))
        except MissingField:
            raise
        except _BAD_VALUE:
            continue
        keep.append(i)
    report.skip(skip_malformed(topic), len(msgs) - len(keep))
    return np.asarray(keep, dtype=np.int64), rows


def _floats(rows: list[Any], width: int) -> np.ndarray:
    return np.array(rows, dtype=np.float64).reshape(len(rows), width)


def _extract_generic(
    sink: _ChannelSink, role: str, msgs: list[Any], log_time: np.ndarray, cols: _Columns,
    config: Config, report: ReadReport,
) -> None:
    """Columns of `role` from decoded messages (objects or dicts)."""
    if not msgs:
        return
    kind = _kind(role, sink.type_name, msgs[0])
    topic = sink.channel.topic
    stamps = np.array([stamp_ns(m) for m in msgs], dtype=np.int64)
    try:
        if role == POSE:
            _external_poses(msgs, stamps, log_time, cols, topic, report)
            return
        if kind == "joint_state":
            _joint_states(msgs, stamps, log_time, cols, config, report)
            return
        if kind == "mapped":
            _mapped_ranges(msgs, stamps, log_time, cols, config, report, topic)
            return
        if kind == "imu":
            k, rows = _per_message(msgs, lambda m: (*_vec(m, "angular_velocity"),
                                                    *_vec(m, "linear_acceleration")),
                                   topic, report)
            v6 = _floats(rows, 6)
            cols.add(stamps[k], log_time[k], gyro=v6[:, :3], accel=v6[:, 3:])
        elif kind == "odometry" and role == WHEEL:
            k, rows = _per_message(msgs, lambda m: (float(get_path(m, "twist.twist.linear.x")),
                                                    float(get_path(m, "twist.twist.angular.z"))),
                                   topic, report)
            v2 = _floats(rows, 2)
            cols.add(stamps[k], log_time[k], v=v2[:, 0], omega=v2[:, 1])
        elif kind in ("odometry", "pose", "transform"):
            base = {"odometry": "pose.pose", "pose": "pose", "transform": "transform"}[kind]
            pname, qname = ("translation", "rotation") if kind == "transform" else (
                "position", "orientation")
            k, rows = _per_message(msgs, lambda m: (*_vec(m, f"{base}.{pname}"),
                                                    *_vec(m, f"{base}.{qname}", "xyzw")),
                                   topic, report)
            v7 = _floats(rows, 7)
            cols.add(stamps[k], log_time[k], position=v7[:, :3], quat=v7[:, 3:])
        else:  # sensor_msgs/Range
            k, rows = _per_message(msgs, lambda m: (anchor_key(get_path(m, "header.frame_id")),
                                                    float(get_path(m, "range"))),
                                   topic, report)
            ids = np.empty(len(rows), dtype=object)
            ids[:] = [r[0] for r in rows]
            rng = np.array([r[1] for r in rows], dtype=np.float64)
            nan = np.full(len(rows), np.nan)
            cols.add(stamps[k], log_time[k], anchor=ids, range=rng,
                     valid=np.ones(len(rows), bool), rssi=nan, first_path=nan)
    except MissingField as e:
        raise _FieldError(str(e.args[0])) from None


def _external_poses(
    msgs: list[Any], stamps: np.ndarray, log_time: np.ndarray, cols: _Columns, topic: str,
    report: ReadReport,
) -> None:
    """Pose, orientation and (PoseWithCovarianceStamped) covariance of the pose role."""
    with_cov = has_path(msgs[0], "pose.covariance")
    base = "pose.pose" if with_cov else "pose"

    def row(m: Any) -> tuple[float, ...]:
        cov = ([float(c) for c in get_path(m, "pose.covariance")] if with_cov
               else [0.0] * 36)
        if len(cov) != 36:
            raise ValueError("covariance is not 36 numbers")
        return (*_vec(m, f"{base}.position"), *_vec(m, f"{base}.orientation", "xyzw"), *cov)

    k, rows = _per_message(msgs, row, topic, report)
    v = _floats(rows, 43)
    cols.add(stamps[k], log_time[k], position=v[:, :3], quat=v[:, 3:7],
             covariance=v[:, 7:].reshape(-1, 6, 6),
             has_cov=np.full(len(k), with_cov, dtype=bool))


def _joint_states(
    msgs: list[Any], stamps: np.ndarray, log_time: np.ndarray, cols: _Columns,
    config: Config, report: ReadReport,
) -> None:
    wc = config.wheel
    keep, vl, vr = [], [], []
    for i, m in enumerate(msgs):
        try:
            names = list(get_path(m, "name"))
            vel = list(get_path(m, "velocity"))
            li, ri = names.index(wc.left_joint), names.index(wc.right_joint)
            wl, wr = float(vel[li]), float(vel[ri])
        except MissingField:
            raise
        except (*_BAD_VALUE, IndexError):
            report.skip(SKIP_NO_WHEEL_JOINTS)
            continue
        keep.append(i)
        vl.append(wl)
        vr.append(wr)
    k = np.asarray(keep, dtype=np.int64)
    wl_a, wr_a = np.asarray(vl, dtype=np.float64), np.asarray(vr, dtype=np.float64)
    with np.errstate(over="ignore", invalid="ignore"):  # 1e308 rad/s: dropped as implausible
        v = wc.radius * (wl_a + wr_a) / 2.0
        omega = wc.radius * (wr_a - wl_a) / wc.track_width
    cols.add(stamps[k], log_time[k], v=v, omega=omega)


def _mapped_ranges(
    msgs: list[Any], stamps: np.ndarray, log_time: np.ndarray, cols: _Columns, config: Config,
    report: ReadReport, topic: str,
) -> None:
    """Ranges of a non-Range type through the [uwb] field mapping (arrays included), with
    the optional signal-quality fields (NaN where a message lacks them)."""
    u = config.uwb
    t_out, lt_out, ids, rng, valid, rssi, fp = [], [], [], [], [], [], []
    bad = 0
    for m, t, lt in zip(msgs, stamps.tolist(), log_time.tolist(), strict=True):
        try:
            elems = get_path(m, u.array_field) if u.array_field else (m,)
            got = [(anchor_key(get_path(e, u.anchor_field)),
                    _to_float(get_path(e, u.range_field)),
                    is_valid(get_path(e, u.valid_field)) if u.valid_field else True,
                    _optional_float(e, u.rssi_field),
                    _optional_float(e, u.first_path_power_field))
                   for e in elems]
        except MissingField:
            raise
        except _BAD_VALUE:  # an "array" that is a number, elements without fields
            bad += 1
            continue
        for a, r, ok, p_rx, p_fp in got:
            t_out.append(t)
            lt_out.append(lt)
            ids.append(a)
            rng.append(r)
            valid.append(ok)
            rssi.append(p_rx)
            fp.append(p_fp)
    report.skip(skip_malformed(topic), bad)
    anchor = np.empty(len(ids), dtype=object)
    anchor[:] = ids
    cols.add(np.array(t_out, dtype=np.int64), np.array(lt_out, dtype=np.int64),
             anchor=anchor, range=np.array(rng, dtype=np.float64),
             valid=np.array(valid, dtype=bool),
             rssi=np.array(rssi, dtype=np.float64), first_path=np.array(fp, dtype=np.float64))


def _optional_float(elem: Any, path: str) -> float | None:
    """The number at `path` (NaN when `path` is '' or not a number); None where the element
    has no such field (the range is kept without it: `_signal_power` counts both)."""
    if not path:
        return math.nan
    try:
        return _to_float(get_path(elem, path))
    except MissingField:
        return None


def _to_float(v: Any) -> float:
    try:
        return float(v)
    except (TypeError, ValueError, OverflowError):
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
        elif "anchor_id" in c:  # msgdefs.UWB_RANGE, its fields as _uwb_fast_ok checked
            cols.add(c["t_ns"], lt, anchor=c["anchor_id"], range=c["range"],
                     valid=np.ones(len(lt), dtype=bool), rssi=c["rssi"],
                     first_path=c["first_path"])
        elif role == POSE:
            cov = c.get("covariance")
            cols.add(c["t_ns"], lt, position=c["position"], quat=c["quat"],
                     covariance=np.zeros((len(lt), 6, 6)) if cov is None else cov,
                     has_cov=np.full(len(lt), cov is not None, dtype=bool))
        else:
            nan = np.full(len(lt), np.nan)
            cols.add(c["t_ns"], lt, anchor=c["frame_id"], range=c["range"],
                     valid=np.ones(len(lt), dtype=bool), rssi=nan, first_path=nan)


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


def stamp_value_order(t: np.ndarray, values: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Indices that sort rows by stamp `t` (N,), ties by the `values` columns (each (N,...)),
    and the mask, in that order, of rows that repeat the previous row exactly (stamp and
    every value): the reader's and the live API's duplicate rule."""
    flat = [v.reshape(len(t), -1) for v in values]
    keys = [c[:, j] for c in reversed(flat) for j in reversed(range(c.shape[1]))]
    order = np.lexsort([*keys, t])
    same = t[order][1:] == t[order][:-1]
    for c in flat:
        same &= np.all(c[order][1:] == c[order][:-1], axis=1)
    return order, np.concatenate([[False], same])


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
    order, dup = stamp_value_order(t, values)
    report.skip(skip_duplicate(role), int(dup.sum()))
    kept = order[~dup]
    ties = int(np.sum(t[kept][1:] == t[kept][:-1]))
    if ties and role != "uwb":  # one range message may carry ranges to several anchors
        report.warnings.append(f"{ties} {role} samples share a stamp with another sample")
    return kept


def _row_all(ok: np.ndarray) -> np.ndarray:
    """Per row, whether every value of a (n, ...) boolean array is true (n may be 0)."""
    return ok if ok.ndim == 1 else ok.all(axis=tuple(range(1, ok.ndim)))


def _good_rows(
    t: np.ndarray, values: list[np.ndarray], bounds: list[float | None], role: str,
    report: ReadReport,
) -> np.ndarray | None:
    """Mask of the rows with a usable stamp and finite, physically plausible values
    (|value| <= bound where a bound is given); None if every row is."""
    good_t = t >= 0
    finite = np.ones(len(t), dtype=bool)
    plausible = np.ones(len(t), dtype=bool)
    for a, bound in zip(values, bounds, strict=True):
        ok = np.isfinite(a)
        finite &= _row_all(ok)
        if bound is not None:
            with np.errstate(invalid="ignore"):
                plausible &= _row_all(~ok | (np.abs(a) <= bound))
    report.skip(SKIP_BAD_STAMP, int((~good_t).sum()))
    report.skip(skip_non_finite(role), int((good_t & ~finite).sum()))
    report.skip(SKIP_IMPLAUSIBLE.format(role), int((good_t & finite & ~plausible).sum()))
    ok = good_t & finite & plausible
    return None if bool(ok.all()) else ok


def _rows(sel: np.ndarray | None, *arrays: np.ndarray) -> list[np.ndarray]:
    """`arrays` restricted to `sel` (mask or index; None keeps them, without copying)."""
    return list(arrays) if sel is None else [a[sel] for a in arrays]


def _clean(
    t: np.ndarray, values: list[np.ndarray], role: str, report: ReadReport,
    bounds: list[float | None] | None = None,
) -> list[np.ndarray]:
    """[t, *values] without bad stamps, non-finite or implausible rows and exact
    duplicates, sorted by stamp. A single sample left is dropped too (no rate, no span)."""
    bounds = bounds if bounds is not None else [None] * len(values)
    cols = _rows(_good_rows(t, values, bounds, role, report), t, *values)
    cols = _rows(_sort_dedup(cols[0], cols[1:], role, report), *cols)
    if len(cols[0]) == 1:
        report.skip(SKIP_LONE.format(role))
        cols = [c[:0] for c in cols]
    return cols


def _imu_stream(r: _Role, topic: str, report: ReadReport) -> ImuStream | None:
    if not r.present:
        return None
    c = r.columns
    t = _stamps(c, IMU, topic, report)
    t, g, a = _clean(t, [c.cat("gyro", (3,)), c.cat("accel", (3,))], "imu", report,
                     [MAX_GYRO_RAD_S, MAX_ACCEL_M_S2])
    return ImuStream(t, np.ascontiguousarray(g), np.ascontiguousarray(a))


def _wheel_stream(r: _Role, topic: str, report: ReadReport) -> WheelStream | None:
    if not r.present:
        return None
    c = r.columns
    t = _stamps(c, "wheel", topic, report)
    t, v, w = _clean(t, [c.cat("v"), c.cat("omega")], "wheel", report,
                     [MAX_WHEEL_SPEED_M_S, MAX_WHEEL_YAW_RATE_RAD_S])
    return WheelStream(t, v, w)


def _gt_stream(r: _Role, topic: str, report: ReadReport) -> PoseStream | None:
    if not r.present:
        return None
    c = r.columns
    t = _stamps(c, "ground-truth", topic, report)
    t, p, q = _clean(t, [c.cat("position", (3,)), c.cat("quat", (4,))], "ground-truth",
                     report, [MAX_COORD_M, None])
    norm = np.linalg.norm(q, axis=1)
    identity = np.all(q[:, :3] == 0.0, axis=1) & ((q[:, 3] == 1.0) | (q[:, 3] == 0.0))
    has_orientation = bool(len(q)) and not bool(np.all(identity))
    q = np.where((norm > 0)[:, None], q / np.where(norm > 0, norm, 1.0)[:, None],
                 np.array([0.0, 0.0, 0.0, 1.0]))
    return PoseStream(t, np.ascontiguousarray(p), np.ascontiguousarray(q),
                      has_orientation=has_orientation)


def _pose_stream(r: _Role, topic: str, config: Config, report: ReadReport) -> PoseStream | None:
    if not r.present:
        return None
    from uwbfuse.io.pose_input import external_poses

    c = r.columns
    t = _stamps(c, "pose", topic, report)
    t, p, q, cov, has = _clean(
        t, [c.cat("position", (3,)), c.cat("quat", (4,)), c.cat("covariance", (6, 6)),
            c.cat("has_cov", dtype=bool)], "pose", report, [MAX_COORD_M, None, None, None])
    return external_poses(t, p, q, cov, has, config, report)


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
    power = [c.cat("rssi"), c.cat("first_path")]
    keep = t >= 0
    report.skip(SKIP_BAD_STAMP, int((~keep).sum()))
    report.skip(SKIP_INVALID_FLAG, int((keep & ~valid).sum()))
    keep &= valid
    anchor = np.full(len(t), -1, dtype=np.int32)
    if anchors is None:
        report.skip(SKIP_NO_ANCHOR_MAP, int(keep.sum()))
        keep[:] = False
    elif len(ids):
        # ids to codes through a dict: np.unique(ids.astype(str)) would build a fixed-width
        # array as wide as the longest id for every range
        codes: dict[str, int] = {}
        inv = np.fromiter((codes.setdefault(a, len(codes)) for a in ids.tolist()),
                          dtype=np.int64, count=len(ids))
        uniq = list(codes)
        too_long = np.array([len(a) > MAX_ANCHOR_ID_CHARS for a in uniq], dtype=bool)
        long_rows = keep & too_long[inv]
        report.skip(SKIP_LONG_ANCHOR_ID, int(long_rows.sum()))
        keep &= ~long_rows
        known = {a: i for i, a in enumerate(anchors.ids)}
        lut = np.array([known.get(a, -1) for a in uniq], dtype=np.int32)
        anchor = lut[inv]
        unknown = keep & (anchor < 0)
        if unknown.any():
            report.skip(SKIP_UNKNOWN_ANCHOR, int(unknown.sum()))
            names = sorted({a if a.isprintable() else repr(a)
                            for a, bad in zip(uniq, (lut < 0) & ~too_long, strict=True) if bad})
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
    power = [_signal_power(p[keep], report) if name else None
             for p, name in zip(power, (u.rssi_field, u.first_path_power_field), strict=True)]
    if anchors is not None and u.range_offset:
        off = np.array([u.range_offset.get(a, 0.0) for a in anchors.ids], dtype=np.float64)
        rng = rng - off[anchor]
        stray = sorted(set(u.range_offset) - set(anchors.ids))
        if stray:
            report.warnings.append(f"[uwb.range_offset] names unknown anchors: "
                                   f"{', '.join(stray)}")
    sel = _sort_dedup(t, [anchor, rng], "uwb", report)
    t, anchor, rng = _rows(sel, t, anchor, rng)
    rx, first = (None if p is None else _rows(sel, p)[0] for p in power)
    return RangeStream(t, anchor.astype(np.int32), rng, rx, first)


def _signal_power(p: np.ndarray, report: ReadReport) -> np.ndarray:
    """Signal powers (dBm) of a configured field with the missing, non-finite and
    implausible values set to NaN and counted: the range stays, without that power."""
    p = p.copy()
    bad = ~np.isfinite(p)
    with np.errstate(invalid="ignore"):
        bad |= (p < MIN_POWER_DBM) | (p > MAX_POWER_DBM)
    report.skip(SKIP_BAD_POWER, int(bad.sum()))
    p[bad] = np.nan
    return p


def _anchor_xyz(text: str) -> list[float] | None:
    """[x, y, z] from a `uwb_anchors` value (a JSON array of three numbers), else None."""
    if len(text) > 1000:  # three numbers; a longer value is not one (a nesting bomb, ...)
        return None
    try:
        xyz = json.loads(text)
        ok = (isinstance(xyz, list) and len(xyz) == 3
              and all(isinstance(c, (int, float)) and not isinstance(c, bool)
                      and math.isfinite(c) and abs(c) <= MAX_COORD_M for c in xyz))
    except (ValueError, RecursionError, OverflowError):  # bad JSON, deep, int past float
        return None
    return [float(c) for c in xyz] if ok else None


def _metadata_anchors(source: str, scans: list[ScanResult]) -> AnchorMap | None:
    for scan in scans:
        for name, data in scan.metadata:
            if name != ANCHORS_METADATA:
                continue
            out: dict[str, list[float]] = {}
            for k, v in data.items():
                xyz = _anchor_xyz(v)
                if xyz is None or len(k) > MAX_ANCHOR_ID_CHARS:
                    shown = v if len(v) <= 60 else v[:60] + "..."
                    raise LogReadError(
                        f"{source}: metadata record {ANCHORS_METADATA!r}: anchor "
                        f"{k[:60]!r} is {shown!r}, expected a JSON array [x, y, z] of finite "
                        f"numbers within {MAX_COORD_M:g} m (and an id of at most "
                        f"{MAX_ANCHOR_ID_CHARS} characters)"
                    )
                out[k] = xyz
            if out:
                return AnchorMap.from_dict(out)
    return None


# the [uwb] keys a log's `uwb_fields` metadata record may fill in (where the config leaves
# them empty): the simulator names its signal-quality fields this way, so `run` needs no
# config
_LOG_FIELDS = ("rssi_field", "first_path_power_field")


def _with_log_fields(config: Config, scans: list[ScanResult]) -> Config:
    """`config` with the empty `_LOG_FIELDS` taken from the log's `uwb_fields` record."""
    fill: dict[str, str] = {}
    for scan in scans:
        for name, data in scan.metadata:
            if name == UWB_FIELDS_METADATA:
                fill.update({k: v for k, v in data.items() if k in _LOG_FIELDS
                             and not getattr(config.uwb, k) and len(v) <= 1000})
    if not fill:
        return config
    return config.model_copy(update={"uwb": config.uwb.model_copy(update=fill)})


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


def _far_stamps(streams: list[Any], report: ReadReport) -> list[Any]:
    """The sensor streams without the samples stamped more than MAX_STAMP_GAP_NS from
    every other one: of the groups of stamps that gaps of more than that separate, the
    group with the most samples is the log (a range stamped a year ahead, an IMU
    sample on another clock, a stamp of 0 with a log time of 0 are not)."""
    present = [x for x in streams if x is not None and len(x)]
    if not present:
        return streams
    t = np.sort(np.concatenate([x.t_ns for x in present]))
    cut = np.flatnonzero(np.diff(t) > MAX_STAMP_GAP_NS)
    if not len(cut):
        return streams
    starts = np.concatenate([[0], cut + 1])
    ends = np.concatenate([cut, [len(t) - 1]])
    best = int(np.argmax(ends - starts))
    lo, hi = int(t[starts[best]]), int(t[ends[best]])
    out = []
    for x in streams:
        if x is None or not len(x):
            out.append(x)
            continue
        a = np.searchsorted(x.t_ns, lo, side="left")
        b = np.searchsorted(x.t_ns, hi, side="right")
        report.skip(SKIP_FAR_STAMP, len(x) - int(b - a))
        out.append(x.slice(int(a), int(b)))
    dropped = len(t) - int(ends[best] - starts[best] + 1)
    report.warnings.append(
        f"{dropped} sensor samples stamped more than {MAX_STAMP_GAP_NS // 10**9} s from the "
        f"rest of the log (the {int(ends[best] - starts[best] + 1)} samples from "
        f"{lo / 1e9:.3f} s to {hi / 1e9:.3f} s) were dropped"
    )
    return out


def _role_topics(config: Config) -> dict[str, list[str]]:
    topics = {IMU: config.topics.imu, WHEEL: config.topics.wheel_odom, UWB: config.topics.uwb,
              GT: config.topics.ground_truth, POSE: config.topics.pose}
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
        sink = _ChannelSink(channel, roles, config)
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
    config = _with_log_fields(config, scans)
    _collect(source, sinks, roles, config, report)
    anchors = (AnchorMap.from_dict(dict(config.anchors)) if config.anchors
               else _metadata_anchors(source, scans))
    topics = config.topics
    imu, wheel, ranges, poses = _far_stamps([
        _imu_stream(roles[IMU], topics.imu, report),
        _wheel_stream(roles[WHEEL], topics.wheel_odom, report),
        _range_stream(roles[UWB], topics.uwb, anchors, config, report),
        _pose_stream(roles[POSE], topics.pose, config, report),
    ], report)
    out = SensorLog(
        imu=imu,
        wheel=wheel,
        ranges=ranges,
        anchors=anchors,
        ground_truth=_gt_stream(roles[GT], topics.ground_truth, report),
        source=source,
        report=report,
        map=_log_map(source, scans, config),
        pose=poses,
    )
    for line in report.lines():
        log.debug("%s: %s", source, line)
    return out
