# SPDX-License-Identifier: BSD-3-Clause
"""Seeded fuzzer for `uwbfuse run` and `uwbfuse eval`: hostile files in, contract checked.

Families (each case is built from the seed and its index, so a run is reproducible):

- `bytes`: byte mutations (bit flips, overwrites, inserted/deleted/duplicated spans, cuts)
  of valid logs written by `uwbfuse simulate` (short durations; zstd, lz4 and uncompressed
  chunks) and of `data/warehouse_60s.mcap` cut short.
- `hostile`: well-formed MCAP files (the `mcap` / `mcap_ros2` writers) with hostile content:
  absurd, negative, zero and far-off stamps, NaN and 1e308 values, 1 MiB anchor ids,
  recursive and depth-bomb schemas, flipped schema text, JSON messages with null/"NaN"
  stamps and fields of the wrong type, bad `uwb_anchors` records, single-message logs.
- `resource`: decompression bombs (a zstd/lz4 chunk declaring or holding GiBs, also in a
  truncated last chunk), huge record lengths, many channels, a huge range array.
- `config`: TOML configs with NaN/inf/negative/wrong-type values, unknown keys, bytes that
  are not UTF-8, paths through a file, deep tables.
- `eval`: TUM files with stamps past 2^63 ns, tiny/zero quaternions, 1e308 coordinates,
  NaN text, duplicate and reversed stamps, against TUM or LOG ground truth and every
  `--align`.

Each case runs `uwbfuse run` (wls, ekf, odom, imu; a few isam2) or `uwbfuse eval` in a child
process under a memory limit (RLIMIT_AS) and a timeout. By default the child is forked from
this process after the package is imported (fast); `--exec` starts a fresh interpreter per
case (as a user runs it). Outcomes:

  ok            exit 0
  clean         exit 2 with exactly one line on stderr
  traceback     a Python traceback (exit 1)
  memory        killed by a signal or MemoryError (the memory limit)
  hang          still running at the timeout
  multiline     exit 2 with more than one stderr line (warnings before the error, ...)
  warning       exit 0 with a Python warning (RuntimeWarning ...) on stderr
  partial       an output file left after a failure, or a temporary file left behind
  accepted      exit 0 on input that must be rejected
  other-exit    any other exit status

Everything but `ok` and `clean` breaks the contract. Usage:

  python scripts/fuzz.py --cases 2000 --seed 1          # the long run (docs/results.md)
  python scripts/fuzz.py --cases 50 --families hostile -v
"""

from __future__ import annotations

import argparse
import dataclasses
import io
import json
import os
import random
import resource
import select
import signal
import struct
import subprocess
import sys
import time
import traceback
from collections import Counter
from collections.abc import Callable
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
DEMO_LOG = REPO / "data" / "warehouse_60s.mcap"
FAMILIES = ("bytes", "hostile", "resource", "config", "eval")
OUTCOMES = ("ok", "clean", "traceback", "memory", "hang", "multiline", "warning", "partial",
            "accepted", "other-exit")
BREAKS = frozenset(OUTCOMES) - {"ok", "clean"}
FAST_METHODS = ("wls", "ekf", "odom", "imu")
GIB = 1 << 30


@dataclasses.dataclass
class Case:
    """One fuzz case: the command line, what it must not do, where its outputs go."""

    family: str
    name: str
    argv: list[str]
    must_reject: bool = False
    outputs: list[Path] = dataclasses.field(default_factory=list)
    out_dir: Path | None = None


@dataclasses.dataclass
class Outcome:
    """What a case did."""

    case: Case
    kind: str
    rc: int | None
    stderr: str
    wall_s: float
    maxrss_mb: float


# ------------------------------------------------------------------------------------------
# base logs


class Bases:
    """Valid logs (simulated, short) and their decoded streams, made once per work dir."""

    def __init__(self, work: Path, scale: float = 1.0) -> None:
        from uwbfuse.config import Config
        from uwbfuse.io.reader import read_log
        from uwbfuse.io.writer import write_contract_log
        from uwbfuse.sim.simulator import simulate

        self.work = work
        base = work / "base"
        base.mkdir(parents=True, exist_ok=True)
        specs = [("warehouse", 5.0 * scale, 1, "zstd"), ("room", 3.0 * scale, 2, "none"),
                 ("factory", 4.0 * scale, 3, "lz4"), ("warehouse", 3.0 * scale, 4, "none")]
        self.logs: list[Path] = []
        for scen, dur, seed, comp in specs:
            p = base / f"{scen}_{dur:g}s_{seed}_{comp}.mcap"
            if not p.exists():
                write_contract_log(p, simulate(scen, duration_s=dur, seed=seed),
                                   compression=comp, chunk_size=64 * 1024)
            self.logs.append(p)
        self.demo = DEMO_LOG.read_bytes() if DEMO_LOG.exists() else None
        self.sensor = read_log(self.logs[0], Config())
        gt = self.sensor.ground_truth
        assert gt is not None
        self.gt_tum = base / "gt.tum"
        self.est_tum = base / "est.tum"
        from uwbfuse.io.tum import write_tum
        from uwbfuse.streams import PoseStream

        write_tum(self.gt_tum, gt)
        rng = np.random.default_rng(0)
        write_tum(self.est_tum, PoseStream(gt.t_ns[::20], gt.position[::20]
                                           + rng.normal(0, 0.05, (len(gt.t_ns[::20]), 3)),
                                           gt.quat_xyzw[::20]))
        self.config = base / "anchors.toml"
        lines = ["[anchors]"] + [f'"{a}" = {list(map(float, p))}' for a, p in
                                 zip(self.sensor.anchors.ids, self.sensor.anchors.positions,
                                     strict=True)]
        self.config.write_text("\n".join(lines) + "\n")


# ------------------------------------------------------------------------------------------
# MCAP writing helpers (structure-aware cases)


def _cdr_streams(bases: Bases) -> dict[str, tuple[str, np.ndarray, list[bytes]]]:
    """topic -> (type, stamps, cdr messages) of the base log's sensors."""
    from uwbfuse.io import cdr_fast, msgdefs

    s = bases.sensor
    assert s.imu is not None and s.wheel is not None and s.ranges is not None
    assert s.anchors is not None
    return {
        "/imu": (msgdefs.IMU, s.imu.t_ns, cdr_fast.encode_imu(s.imu.t_ns, s.imu.gyro,
                                                               s.imu.accel)),
        "/wheel_odom": (msgdefs.ODOMETRY, s.wheel.t_ns,
                        cdr_fast.encode_odometry(s.wheel.t_ns, s.wheel.v, s.wheel.omega)),
        "/uwb/range": (msgdefs.RANGE, s.ranges.t_ns,
                       cdr_fast.encode_range(s.ranges.t_ns, s.anchors.ids, s.ranges.anchor,
                                             s.ranges.range)),
    }


def _anchor_meta(bases: Bases) -> dict[str, str]:
    a = bases.sensor.anchors
    assert a is not None
    return {k: json.dumps([float(c) for c in p]) for k, p in zip(a.ids, a.positions,
                                                                  strict=True)}


def write_mcap(path: Path, channels: list[tuple[str, str, str, str, str]],
               messages: list[tuple[int, int, bytes]], metadata: dict[str, dict[str, str]],
               compression: str = "zstd") -> None:
    """channels: (topic, schema name, schema encoding, schema text, message encoding);
    messages: (channel index, log time, bytes)."""
    from mcap.writer import CompressionType, Writer

    comp = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4,
            "none": CompressionType.NONE}[compression]
    with open(path, "wb") as f:
        w = Writer(f, compression=comp, chunk_size=64 * 1024)
        w.start(profile="ros2", library="uwbfuse-fuzz")
        ids = []
        for topic, sname, senc, stext, menc in channels:
            sid = w.register_schema(sname, senc, stext.encode("utf-8", "surrogatepass"))
            ids.append(w.register_channel(topic, menc, sid))
        for name, data in metadata.items():
            w.add_metadata(name, data)
        for k, lt, data in messages:
            w.add_message(ids[k], log_time=max(int(lt), 0) & ((1 << 64) - 1), data=data,
                          publish_time=max(int(lt), 0) & ((1 << 64) - 1))
        w.finish()


def _base_mcap(bases: Bases, path: Path, edit: Callable[[dict], None] | None = None,
               meta: dict[str, dict[str, str]] | None = None,
               extra: list[tuple[tuple[str, str, str, str, str], list[tuple[int, bytes]]]]
               | None = None, drop: tuple[str, ...] = (), compression: str = "zstd") -> None:
    """The base log's sensors re-written, after `edit` changed the stream dict in place."""
    from uwbfuse.io import msgdefs

    streams = _cdr_streams(bases)
    if edit is not None:
        edit(streams)
    channels, messages = [], []
    for topic, (tname, t, datas) in streams.items():
        if topic in drop:
            continue
        k = len(channels)
        channels.append((topic, tname, "ros2msg", msgdefs.schema_text(tname), "cdr"))
        messages.extend((k, int(x), d) for x, d in zip(np.asarray(t).tolist(), datas,
                                                         strict=True))
    for ch, msgs in extra or []:
        k = len(channels)
        channels.append(ch)
        messages.extend((k, lt, d) for lt, d in msgs)
    messages.sort(key=lambda m: m[1])
    write_mcap(path, channels, messages,
               {"uwb_anchors": _anchor_meta(bases)} if meta is None else meta, compression)


# ------------------------------------------------------------------------------------------
# case generators


def _method(rng: random.Random) -> str:
    return "isam2" if rng.random() < 0.05 else rng.choice(FAST_METHODS)


def _run_case(family: str, name: str, log: Path, case_dir: Path, rng: random.Random,
              config: Path | None = None, must_reject: bool = False,
              method: str | None = None) -> Case:
    out = case_dir / "est.tum"
    argv = ["run", str(log), "--method", method or _method(rng), "-o", str(out)]
    if config is not None:
        argv += ["--config", str(config)]
    return Case(family, name, argv, must_reject, [out], case_dir)


def _mutate(data: bytes, rng: random.Random) -> tuple[bytes, str]:
    b = bytearray(data)
    op = rng.choice(["flip", "flip", "overwrite", "insert", "delete", "dup", "cut",
                     "int-edit"])
    if op == "flip":
        k = rng.choice([1, 1, 4, 16, 64])
        for _ in range(k):
            i = rng.randrange(len(b))
            b[i] ^= 1 << rng.randrange(8)
    elif op == "overwrite":
        i = rng.randrange(len(b))
        n = rng.choice([1, 8, 64, 512])
        b[i:i + n] = bytes(rng.randrange(256) for _ in range(n))
    elif op == "insert":
        i = rng.randrange(len(b))
        b[i:i] = rng.randbytes(rng.choice([1, 9, 100, 4096]))
    elif op == "delete":
        i = rng.randrange(len(b))
        del b[i:i + rng.choice([1, 9, 100, 4096])]
    elif op == "dup":
        i = rng.randrange(len(b))
        n = rng.choice([100, 1000, 20000])
        b[i:i] = b[i:i + n]
    elif op == "cut":
        del b[rng.randrange(8, len(b)):]
    else:  # a little-endian integer somewhere set to an extreme value
        i = rng.randrange(max(1, len(b) - 8))
        v = rng.choice([0, 1, 0xFFFFFFFF, 0x7FFFFFFF, 1 << 32, (1 << 64) - 1, 1 << 62])
        b[i:i + 8] = struct.pack("<Q", v)
    return bytes(b), op


def gen_bytes(i: int, rng: random.Random, bases: Bases, case_dir: Path) -> Case:
    if bases.demo is not None and rng.random() < 0.25:
        cut = rng.randrange(20_000, 400_000)
        data, op = bases.demo[:cut], f"demo-cut{cut}"
        if rng.random() < 0.5:
            data, op2 = _mutate(data, rng)
            op += "+" + op2
    else:
        src = rng.choice(bases.logs)
        data, op = _mutate(src.read_bytes(), rng)
        op = f"{src.stem}:{op}"
    log = case_dir / "log.mcap"
    log.write_bytes(data)
    return _run_case("bytes", op, log, case_dir, rng)


def _set(streams: dict, topic: str, k: int, **fields: float) -> None:
    """Replace message k of `topic` by one with `fields` changed (re-encoded)."""
    from uwbfuse.io import cdr_fast

    tname, t, datas = streams[topic]
    _, cols = cdr_fast.decode_fixed(tname, [datas[k]])
    stamp = fields.pop("t_ns", int(t[k]))
    datas = list(datas)
    if topic == "/imu":
        g, a = cols["gyro"].copy(), cols["accel"].copy()
        g[0, 2] = fields.get("gz", g[0, 2])
        a[0, 0] = fields.get("ax", a[0, 0])
        datas[k] = cdr_fast.encode_imu(np.array([stamp]), g, a)[0]
    elif topic == "/wheel_odom":
        datas[k] = cdr_fast.encode_odometry(
            np.array([stamp]), np.array([fields.get("v", cols["v"][0])]),
            np.array([fields.get("omega", cols["omega"][0])]))[0]
    else:
        datas[k] = cdr_fast.encode_range(
            np.array([stamp]), [str(fields.get("frame_id", cols["frame_id"][0]))],
            np.array([0]), np.array([fields.get("range", cols["range"][0])]))[0]
    t = np.array(t, dtype=np.int64)
    t[k] = max(min(stamp, (1 << 63) - 1), 0)
    streams[topic] = (tname, t, datas)


_RANGES_TYPE = "uwb_msgs/msg/Ranges"
_RANGES_DEF = ("std_msgs/Header header\nuwb_msgs/Node[] nodes\n" + "=" * 80
               + "\nMSG: uwb_msgs/Node\nstring anchor_id\nfloat64 range\nbool valid\n"
               + "=" * 80 + "\nMSG: std_msgs/Header\nbuiltin_interfaces/Time stamp\n"
               "string frame_id\n" + "=" * 80 + "\nMSG: builtin_interfaces/Time\n"
               "int32 sec\nuint32 nanosec\n")


def _json_wheel(bases: Bases, stamp: object, v: object = 0.5) -> list[tuple[int, bytes]]:
    w = bases.sensor.wheel
    assert w is not None
    out = []
    for k, t in enumerate(w.t_ns.tolist()):
        st = {"sec": t // 10**9, "nanosec": t % 10**9} if k % 7 else stamp
        msg = {"header": {"stamp": st, "frame_id": "odom"},
               "twist": {"twist": {"linear": {"x": v if k == 5 else float(w.v[k])},
                                   "angular": {"z": float(w.omega[k])}}}}
        out.append((t, json.dumps(msg).encode()))
    return out


def _recursive_schema(depth: int | None) -> str:
    if depth is None:  # a type containing itself (and a pair of itself: 2^n blow-up)
        return ("std_msgs/Header header\nuwb_msgs/Loop a\nuwb_msgs/Loop b\n" + "=" * 80
                + "\nMSG: uwb_msgs/Loop\nuwb_msgs/Loop a\nuwb_msgs/Loop b\nfloat64 range\n")
    parts = ["std_msgs/Header header\nuwb_msgs/N0 n"]
    for d in range(depth):
        parts.append("=" * 80 + f"\nMSG: uwb_msgs/N{d}\nuwb_msgs/N{d + 1} a\n"
                     f"uwb_msgs/N{d + 1} b")
    parts.append("=" * 80 + f"\nMSG: uwb_msgs/N{depth}\nfloat64 range")
    parts.append("=" * 80 + "\nMSG: std_msgs/Header\nbuiltin_interfaces/Time stamp\n"
                 "string frame_id\n" + "=" * 80 + "\nMSG: builtin_interfaces/Time\n"
                 "int32 sec\nuint32 nanosec")
    return "\n".join(parts) + "\n"


HOSTILE_KINDS = (
    "future-range", "imu-1.8e9", "negative-stamp", "zero-stamp-logtime0", "twist-1e308",
    "twist-nan", "imu-1e308", "range-1e30", "frame-id-1MiB", "recursive-schema",
    "depth-bomb", "schema-flip", "json-null-stamp", "json-nan-stamp", "json-str-v",
    "json-list-stamp", "anchors-deep", "anchors-bool", "anchors-1e308", "anchors-bigint",
    "anchors-notjson", "single-wheel", "single-imu", "all-zero-stamps", "far-gt",
    "many-ids", "ranges-array", "jointstate-bad", "stamp-int-huge", "dup-channels",
    "bomb-named-range",
)


def gen_hostile(i: int, rng: random.Random, bases: Bases, case_dir: Path,
                kind: str | None = None) -> Case:
    log = case_dir / "log.mcap"
    n_w = len(bases.sensor.wheel.t_ns)  # type: ignore[union-attr]
    n_r = len(bases.sensor.ranges.t_ns)  # type: ignore[union-attr]
    t0 = int(bases.sensor.imu.t_ns[0])  # type: ignore[union-attr]
    if kind is None:
        kind = (HOSTILE_KINDS[i % len(HOSTILE_KINDS)] if rng.random() < 0.7
                else rng.choice(HOSTILE_KINDS))
    must_reject = False
    method = None
    k = rng.randrange(10, 100)
    meta = None
    extra = None
    drop: tuple[str, ...] = ()
    edit: Callable[[dict], None] | None = None
    if kind == "future-range":
        far = t0 + rng.choice([10**15, 10**17, 3 * 10**18])
        edit = lambda s: _set(s, "/uwb/range", k % n_r, t_ns=far)  # noqa: E731
    elif kind == "imu-1.8e9":
        edit = lambda s: _set(s, "/imu", k, t_ns=1_800_000_000 * 10**9)  # noqa: E731
    elif kind == "negative-stamp":
        edit = lambda s: _set(s, rng.choice(["/imu", "/wheel_odom", "/uwb/range"]),  # noqa: E731
                              k % n_w, t_ns=-rng.choice([1, 10**9, 10**18]))
    elif kind == "zero-stamp-logtime0":
        def edit(s: dict) -> None:
            for _ in range(3):
                topic = rng.choice(["/imu", "/wheel_odom", "/uwb/range"])
                _set(s, topic, rng.randrange(len(s[topic][1])), t_ns=0)
    elif kind == "twist-1e308":
        edit = lambda s: _set(s, "/wheel_odom", k % n_w, v=-1e308)  # noqa: E731
        method = rng.choice(["odom", "ekf"])
    elif kind == "twist-nan":
        edit = lambda s: _set(s, "/wheel_odom", k % n_w,  # noqa: E731
                              omega=rng.choice([np.nan, np.inf, 1e300]))
    elif kind == "imu-1e308":
        edit = lambda s: _set(s, "/imu", k, gz=rng.choice([1e308, -1e300, 1e10]),  # noqa: E731
                              ax=rng.choice([1e308, np.nan, 5.0]))
        method = rng.choice(["imu", "ekf"])
    elif kind == "range-1e30":
        edit = lambda s: _set(s, "/uwb/range", k % n_r,  # noqa: E731
                              range=rng.choice([1e30, -1.0, np.inf, 3e38]))
    elif kind == "frame-id-1MiB":
        def edit(s: dict) -> None:
            for j in range(rng.choice([1, 20, 100])):
                _set(s, "/uwb/range", (k + j) % n_r, frame_id="A" * (1 << 20))
        method = "wls"
    elif kind in ("recursive-schema", "depth-bomb"):
        text = _recursive_schema(None if kind == "recursive-schema"
                                 else rng.choice([40, 200, 2000]))
        ch = ("/uwb/range", "uwb_msgs/msg/Loop", "ros2msg", text, "cdr")
        extra = [(ch, [(t0 + j * 10**8, b"\x00\x01\x00\x00" + bytes(64)) for j in range(20)])]
        drop = ("/uwb/range",)
    elif kind == "bomb-named-range":  # a 2^n schema under the name of a fast-path type
        from uwbfuse.io import msgdefs

        ch = ("/uwb/range", msgdefs.RANGE, "ros2msg",
              _recursive_schema(rng.choice([24, 31])).replace("uwb_msgs/N0 n",
                                                             "uwb_msgs/N0 n\nfloat32 range"),
              "cdr")
        streams = _cdr_streams(bases)
        _, t, datas = streams["/uwb/range"]
        extra = [(ch, list(zip(t.tolist(), datas, strict=True)))]
        drop = ("/uwb/range",)
        method = "wls"
    elif kind == "schema-flip":
        from uwbfuse.io import msgdefs

        tname = rng.choice([msgdefs.IMU, msgdefs.ODOMETRY, msgdefs.RANGE])
        text = bytearray(msgdefs.schema_text(tname).encode())
        for _ in range(rng.choice([1, 2, 8])):
            j = rng.randrange(len(text))
            text[j] ^= 1 << rng.randrange(7)
        topic = {msgdefs.IMU: "/imu", msgdefs.ODOMETRY: "/wheel_odom"}.get(tname, "/uwb/range")
        streams = _cdr_streams(bases)
        _, t, datas = streams[topic]
        ch = (topic, tname, "ros2msg", text.decode("utf-8", "replace"), "cdr")
        extra = [(ch, list(zip(t.tolist(), datas, strict=True)))]
        drop = (topic,)
    elif kind.startswith("json-"):
        stamp = {"json-null-stamp": None, "json-nan-stamp": "NaN",
                 "json-str-v": {"sec": 1, "nanosec": 0},
                 "json-list-stamp": [1, 2]}[kind]
        v: object = {"json-str-v": rng.choice(["fast", None, [1, 2], {"a": 1}, 1e308])}.get(
            kind, 0.5)
        ch = ("/wheel_odom", "nav_msgs/msg/Odometry", "jsonschema", "", "json")
        extra = [(ch, _json_wheel(bases, stamp, v))]
        drop = ("/wheel_odom",)
        method = "odom"
    elif kind.startswith("anchors-"):
        a = _anchor_meta(bases)
        key = next(iter(a))
        a[key] = {"anchors-deep": "[" * 100000 + "]" * 100000,
                  "anchors-bool": "[true, 1, 2]",
                  "anchors-1e308": "[1e308, 1e308, 1.5]",
                  "anchors-bigint": "[" + "9" * 5000 + ", 0, 0]",
                  "anchors-notjson": "\udcff[1,2"}[kind]
        if kind == "anchors-notjson":
            a[key] = "[1, 2"
        meta = {"uwb_anchors": a}
        must_reject = True
        method = "wls"
    elif kind in ("single-wheel", "single-imu"):
        only = "/wheel_odom" if kind == "single-wheel" else "/imu"

        def edit(s: dict) -> None:
            tname, t, datas = s[only]
            s[only] = (tname, t[:1], datas[:1])
        drop = tuple(x for x in ("/imu", "/wheel_odom", "/uwb/range") if x != only)
        method = "odom" if kind == "single-wheel" else "imu"
        must_reject = True
    elif kind == "all-zero-stamps":
        def edit(s: dict) -> None:
            from uwbfuse.io import cdr_fast
            tname, t, datas = s["/wheel_odom"]
            _, cols = cdr_fast.decode_fixed(tname, datas)
            s["/wheel_odom"] = (tname, np.zeros(len(t), np.int64), cdr_fast.encode_odometry(
                np.zeros(len(t), np.int64), cols["v"], cols["omega"]))
        method = "odom"
    elif kind == "far-gt":
        from uwbfuse.io import cdr_fast, msgdefs

        gt = bases.sensor.ground_truth
        assert gt is not None
        t = gt.t_ns.copy()
        t[rng.randrange(len(t))] = 4 * 10**18
        ch = ("/ground_truth", msgdefs.POSE_STAMPED, "ros2msg",
              msgdefs.schema_text(msgdefs.POSE_STAMPED), "cdr")
        extra = [(ch, list(zip(gt.t_ns.tolist(), cdr_fast.encode_pose_stamped(
            t, gt.position, gt.quat_xyzw), strict=True)))]
    elif kind == "many-ids":
        def edit(s: dict) -> None:
            for j in range(200):
                _set(s, "/uwb/range", (k + j) % n_r, frame_id=f"X{j}" * rng.choice([1, 50]))
    elif kind == "ranges-array":
        from mcap_ros2._dynamic import serialize_dynamic

        enc = serialize_dynamic(_RANGES_TYPE, _RANGES_DEF)[_RANGES_TYPE.replace("/msg/", "/")]
        n_nodes = rng.choice([0, 3, 100000])
        msgs = []
        for j in range(30):
            t = t0 + j * 10**8
            nodes = [{"anchor_id": rng.choice(["A1", "A2", "", "Z" * 300]),
                      "range": rng.choice([3.0, float("nan"), 1e308, -2.0]), "valid": True}
                     for _ in range(n_nodes if j == 3 else 3)]
            msgs.append((t, enc({"header": {"stamp": {"sec": t // 10**9,
                                                      "nanosec": t % 10**9},
                                            "frame_id": ""}, "nodes": nodes})))
        ch = ("/uwb/range", _RANGES_TYPE, "ros2msg", _RANGES_DEF, "cdr")
        extra = [(ch, msgs)]
        drop = ("/uwb/range",)
        cfg = case_dir / "cfg.toml"
        cfg.write_text('[uwb]\narray_field = "nodes"\nanchor_field = "anchor_id"\n'
                       'range_field = "range"\nvalid_field = "valid"\n')
        _base_mcap(bases, log, None, meta, extra, drop)
        return _run_case("hostile", kind, log, case_dir, rng, config=cfg, method="wls")
    elif kind == "jointstate-bad":
        from mcap_ros2._dynamic import serialize_dynamic

        from uwbfuse.io import msgdefs
        text = msgdefs.schema_text(msgdefs.JOINT_STATE)
        enc = serialize_dynamic(msgdefs.JOINT_STATE, text)["sensor_msgs/JointState"]
        w = bases.sensor.wheel
        assert w is not None
        msgs = []
        for t in w.t_ns.tolist():
            names = rng.choice([["left_wheel_joint", "right_wheel_joint"],
                                ["left_wheel_joint"], []])
            vel = rng.choice([[1.0, 1.1], [1e308, -1e308], [float("nan")], []])
            msgs.append((t, enc({"header": {"stamp": {"sec": t // 10**9, "nanosec": t % 10**9},
                                            "frame_id": ""}, "name": names,
                                 "position": [], "velocity": vel, "effort": []})))
        ch = ("/wheel_odom", msgdefs.JOINT_STATE, "ros2msg", text, "cdr")
        extra = [(ch, msgs)]
        drop = ("/wheel_odom",)
        method = "odom"
    elif kind == "stamp-int-huge":
        ch = ("/wheel_odom", "nav_msgs/msg/Odometry", "jsonschema", "", "json")
        extra = [(ch, _json_wheel(bases, rng.choice([10**30, -(10**30), 1e300, 9.3e9])))]
        drop = ("/wheel_odom",)
        method = "odom"
    elif kind == "dup-channels":
        from uwbfuse.io import msgdefs
        streams = _cdr_streams(bases)
        _, t, datas = streams["/imu"]
        ch = ("/wheel_odom", msgdefs.IMU, "ros2msg", msgdefs.schema_text(msgdefs.IMU), "cdr")
        extra = [(ch, list(zip(t.tolist()[:50], datas[:50], strict=True)))]
    _base_mcap(bases, log, edit, meta, extra, drop, compression=rng.choice(["zstd", "none"]))
    return _run_case("hostile", kind, log, case_dir, rng, must_reject=must_reject,
                     method=method)


def zstd_zeros_frame(size: int) -> bytes:
    """A valid zstd frame of `size` zero bytes, built from RLE blocks (4 bytes per 128 KiB,
    so 4 GiB is 128 KiB) with the content size in its header: a decompression bomb."""
    block = 1 << 17
    n_full, rest = divmod(size, block)
    sizes = [block] * n_full + ([rest] if rest else [])
    head = struct.pack("<I", 0xFD2FB528) + bytes([0xC0, 0x38]) + struct.pack("<Q", size)
    blocks = [struct.pack("<I", (n << 3) | (1 << 1) | (k == len(sizes) - 1))[:3] + b"\x00"
              for k, n in enumerate(sizes)]
    return head + b"".join(blocks)


def _chunk_record(compressed: bytes, declared: int, compression: str,
                  records_len: int | None = None) -> bytes:
    comp = compression.encode()
    body = (struct.pack("<QQQI", 0, 0, declared, 0) + struct.pack("<I", len(comp)) + comp
            + struct.pack("<Q", len(compressed) if records_len is None else records_len)
            + compressed)
    return bytes([0x06]) + struct.pack("<Q", len(body)) + body


RESOURCE_KINDS = ("zstd-bomb-4g", "zstd-bomb-trunc", "zstd-declared-small", "lz4-bomb",
                  "huge-record-len", "huge-chunk-size", "many-channels", "huge-string-len",
                  "zero-records")


def gen_resource(i: int, rng: random.Random, bases: Bases, case_dir: Path,
                 kind: str | None = None) -> Case:
    log = case_dir / "log.mcap"
    magic = b"\x89MCAP0\r\n"
    header = bytes([0x01]) + struct.pack("<Q", 8) + struct.pack("<I", 4) + b"ros2" \
        + struct.pack("<I", 0)
    valid = bases.logs[0].read_bytes()
    # the valid log's data section, without its DataEnd/summary/footer: append a bomb
    body = valid[len(magic):]
    end = body.find(bytes([0x0F]) + struct.pack("<Q", 4))
    body = body[:end] if end > 0 else body
    kind = kind or RESOURCE_KINDS[i % len(RESOURCE_KINDS)]
    if kind in ("zstd-bomb-4g", "zstd-bomb-trunc", "zstd-declared-small"):
        bomb = zstd_zeros_frame(4 * GIB)
        declared = {"zstd-declared-small": 1000}.get(kind, 4 * GIB)
        rec = _chunk_record(bomb, declared, "zstd")
        data = magic + body + rec
        if kind == "zstd-bomb-trunc":
            data = data[: len(data) - len(bomb) // 2]
        else:
            data += bytes([0x0F]) + struct.pack("<Q", 4) + bytes(4) + bytes([0x02]) + \
                struct.pack("<Q", 20) + bytes(20) + magic
    elif kind == "lz4-bomb":
        import lz4.frame

        path = bases.work / "base" / "bomb.lz4"
        if not path.exists():
            path.write_bytes(lz4.frame.compress(bytes(1 << 30)))
        data = magic + body + _chunk_record(path.read_bytes(), 1 << 30, "lz4")
    elif kind == "huge-record-len":
        data = magic + body + bytes([0x05]) + struct.pack("<Q", (1 << 63)) + bytes(64)
    elif kind == "huge-chunk-size":
        data = magic + body + _chunk_record(b"abc", (1 << 64) - 1, "", records_len=1 << 62)
    elif kind == "many-channels":
        recs = []
        for c in range(20000):
            topic = b"/uwb/range" if c % 2 else f"/t{c}".encode()
            rec = struct.pack("<HH", c + 100, 0) + struct.pack("<I", len(topic)) + topic + \
                struct.pack("<I", 3) + b"cdr" + struct.pack("<I", 0)
            recs.append(bytes([0x04]) + struct.pack("<Q", len(rec)) + rec)
        data = magic + header + b"".join(recs) + body
    elif kind == "huge-string-len":
        rec = struct.pack("<H", 7) + struct.pack("<I", 0xFFFFFFF0) + b"x" * 64
        data = magic + header + bytes([0x03]) + struct.pack("<Q", len(rec)) + rec + body
    else:  # a chunk of 100 MiB of zero-length opcode-0 records
        data = magic + body + _chunk_record(zstd_zeros_frame(100 << 20), 100 << 20, "zstd")
    log.write_bytes(data)
    return _run_case("resource", kind, log, case_dir, rng, method=rng.choice(FAST_METHODS))


_CONFIG_KEYS = [
    ("uwb", "sigma"), ("uwb", "min_range"), ("uwb", "max_range"), ("uwb", "kernel_threshold"),
    ("wheel", "radius"), ("wheel", "track_width"), ("wheel", "sigma_v"), ("imu", "gravity"),
    ("imu", "accel_noise_density"), ("init", "standstill_window"), ("init", "max_window"),
    ("graph", "lag"), ("graph", "keyframe_rate"), ("ekf", "gate_probability"),
    ("wls", "window"), ("wls", "nlos_mean"), ("wls", "nlos_std"), ("wls", "los_std"),
    ("output", "rate"), ("ukf", "alpha"), ("ukf", "beta"), ("graph", "nlos_sigma"),
]
_BAD_VALUES = ["nan", "inf", "-inf", '"0.5"', "true", "[]", "{}", "1e308", "-1e308", "0",
               "-1", '"nan"', "1e-320"]
_MUST_REJECT = {"nan", "inf", "-inf", '"0.5"', "true", "[]", "{}", '"nan"'}


def gen_config(i: int, rng: random.Random, bases: Bases, case_dir: Path) -> Case:
    cfg = case_dir / "cfg.toml"
    base = bases.config.read_text()
    kind = rng.choice(["value", "value", "value", "offset", "anchor", "not-utf8", "through-file",
                       "deep", "unknown", "flip", "nlos-anchor", "binary"])
    must_reject = False
    cfg_arg: Path = cfg
    if kind == "value":
        sec, key = rng.choice(_CONFIG_KEYS)
        val = rng.choice(_BAD_VALUES)
        cfg.write_text(base + f"\n[{sec}]\n{key} = {val}\n")
        must_reject = val in _MUST_REJECT
        kind = f"{sec}.{key}={val}"
    elif kind == "offset":
        val = rng.choice(["nan", "inf", '"x"', "1e308"])
        cfg.write_text(base + f'\n[uwb.range_offset]\n"A1" = {val}\n')
        must_reject = val != "1e308"
        kind = f"range_offset={val}"
    elif kind == "anchor":
        val = rng.choice(["[nan, 0, 0]", "[1e308, 1e308, 0]", "[true, 1, 2]", '["a", 1, 2]',
                          "[1, 2]", "[inf, 0, 0]"])
        cfg.write_text(base.replace("[anchors]\n", f'[anchors]\n"A9" = {val}\n'))
        must_reject = True
        kind = f"anchor={val}"
    elif kind == "nlos-anchor":
        val = rng.choice(["[nan, 0.1, 0.1, 0.5]", "[inf, 1, 1, 1]", "[1, 2]"])
        cfg.write_text(base + f'\n[nlos.anchor]\n"A1" = {val}\n')
        must_reject = True
        kind = f"anchor_nlos={val}"
    elif kind == "not-utf8":
        cfg.write_bytes(base.encode() + b"\n# \xff\xfe\xc3\x28\n")
    elif kind == "through-file":
        cfg_arg = bases.logs[0] / "cfg.toml"
    elif kind == "deep":
        cfg.write_text(base + "\n[uwb]\nmin_range = " + "[" * 5000 + "]" * 5000 + "\n")
    elif kind == "unknown":
        cfg.write_text(base + "\n[uwbb]\nsigma = 1\n")
    elif kind == "binary":
        cfg.write_bytes(rng.randbytes(200))
    else:
        text = bytearray(base.encode())
        j = rng.randrange(len(text))
        text[j] ^= 1 << rng.randrange(7)
        cfg.write_bytes(bytes(text))
    return _run_case("config", kind, rng.choice(bases.logs[:2]), case_dir, rng,
                     config=cfg_arg, must_reject=must_reject,
                     method=rng.choice(("wls", "ekf", "odom")))


def _tum_lines(path: Path) -> list[str]:
    return [x for x in path.read_text().splitlines() if x and not x.startswith("#")]


def gen_eval(i: int, rng: random.Random, bases: Bases, case_dir: Path) -> Case:
    est = case_dir / "est.tum"
    gt_arg = str(bases.gt_tum if rng.random() < 0.6 else bases.logs[0])
    lines = _tum_lines(bases.est_tum)
    kind = rng.choice(["stamp-2^63", "quat-tiny", "coord-1e308", "nan-text", "dup-stamps",
                       "reversed", "two-poses", "huge-line", "garbage", "empty", "no-overlap",
                       "gt-mutated", "quat-zero", "stamp-neg", "coord-1e200", "inf-text"])
    must_reject = False
    j = rng.randrange(len(lines))
    tok = lines[j].split()
    if kind == "stamp-2^63":
        tok[0] = rng.choice(["9300000000.5", "1e30", "99999999999999999999"])
    elif kind == "quat-tiny":
        tok[4:8] = ["1e-200", "0", "0", "1e-200"]
    elif kind == "quat-zero":
        tok[4:8] = ["0", "0", "0", "0"]
    elif kind in ("coord-1e308", "coord-1e200"):
        tok[1] = "1e308" if kind == "coord-1e308" else "1e200"
        must_reject = True
    elif kind == "nan-text":
        tok[rng.randrange(1, 8)] = rng.choice(["nan", "NaN", "-nan"])
    elif kind == "inf-text":
        tok[rng.randrange(0, 8)] = rng.choice(["inf", "-inf", "infinity"])
    elif kind == "stamp-neg":
        tok[0] = "-" + tok[0]
    lines[j] = " ".join(tok)
    if kind == "dup-stamps":
        lines = [" ".join([lines[0].split()[0], *x.split()[1:]]) for x in lines]
    elif kind == "reversed":
        lines = lines[::-1]
    elif kind == "two-poses":
        lines = lines[:2]
    elif kind == "huge-line":
        lines.append("1 " * 1_000_000)
    elif kind == "garbage":
        lines = [rng.randbytes(50).decode("latin-1") for _ in range(5)]
    elif kind == "empty":
        lines = []
    elif kind == "no-overlap":
        lines = [" ".join([str(float(x.split()[0]) + 1e6), *x.split()[1:]]) for x in lines]
    elif kind == "gt-mutated":
        gt = case_dir / "gt.tum"
        g = _tum_lines(bases.gt_tum)
        g[rng.randrange(len(g))] = rng.choice(["1e19 0 0 0 0 0 0 1", "0 1e308 0 0 0 0 0 1",
                                               "1 2 3", "nan 0 0 0 0 0 0 1"])
        gt.write_text("\n".join(g) + "\n")
        gt_arg = str(gt)
    est.write_text("\n".join(lines) + "\n")
    argv = ["eval", str(est), "--gt", gt_arg, "--align", rng.choice(["none", "se2", "se3"]),
            "--json", str(case_dir / "m.json")]
    if gt_arg.endswith(".mcap"):
        argv += ["--config", str(bases.config)]
    return Case("eval", kind, argv, must_reject, [case_dir / "m.json"], case_dir)


GENERATORS: dict[str, Callable[[int, random.Random, Bases, Path], Case]] = {
    "bytes": gen_bytes, "hostile": gen_hostile, "resource": gen_resource,
    "config": gen_config, "eval": gen_eval,
}


def make_cases(n: int, seed: int, families: list[str], bases: Bases, work: Path,
               weights: dict[str, float] | None = None,
               part: tuple[int, int] = (0, 1)) -> list[Case]:
    """`n` cases (families drawn with `weights`), each from its own seeded generator;
    `part` (k, m) makes only the cases whose index is k modulo m (the same cases)."""
    w = weights or {"bytes": 0.35, "hostile": 0.3, "resource": 0.06, "config": 0.14,
                    "eval": 0.15}
    fam_rng = random.Random(seed)
    per_family: Counter[str] = Counter()
    cases = []
    for idx in range(n):
        fam = fam_rng.choices(families, [w.get(f, 0.1) for f in families])[0]
        k = per_family[fam]
        per_family[fam] += 1
        if idx % part[1] != part[0]:
            continue
        case_dir = work / "cases" / f"{idx:05d}_{fam}"
        case_dir.mkdir(parents=True, exist_ok=True)
        rng = random.Random(f"{seed}:{fam}:{k}")
        cases.append(GENERATORS[fam](k, rng, bases, case_dir))
    return cases


# ------------------------------------------------------------------------------------------
# running and classifying


def _limit(mem_bytes: int) -> Callable[[], None]:
    def preexec() -> None:
        resource.setrlimit(resource.RLIMIT_AS, (mem_bytes, mem_bytes))
    return preexec


def _run_exec(argv: list[str], timeout: float, mem_bytes: int) -> tuple[int | None, str, float]:
    """Fresh interpreter: (exit status or None on timeout, stderr, peak RSS MB: the largest
    of every child so far, as RUSAGE_CHILDREN keeps it)."""
    proc = subprocess.Popen([sys.executable, "-m", "uwbfuse", *argv], stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, preexec_fn=_limit(mem_bytes))
    try:
        _, err = proc.communicate(timeout=timeout)
        rc: int | None = proc.returncode
    except subprocess.TimeoutExpired:
        proc.kill()
        _, err = proc.communicate()
        rc = None
    ru = resource.getrusage(resource.RUSAGE_CHILDREN)
    return rc, err.decode("utf-8", "replace"), ru.ru_maxrss / 1024


def _run_forked(argv: list[str], timeout: float, mem_bytes: int) -> tuple[int | None, str,
                                                                            float]:
    """Forked child of this (already importing) process: same results as `_run_exec`."""
    from uwbfuse.cli import main

    r, w = os.pipe()
    sys.stdout.flush()
    sys.stderr.flush()
    pid = os.fork()
    if pid == 0:  # child
        rc = 1
        try:
            os.close(r)
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, 1)
            os.dup2(w, 2)
            sys.stdout = io.TextIOWrapper(os.fdopen(1, "wb", closefd=False))
            sys.stderr = io.TextIOWrapper(os.fdopen(2, "wb", closefd=False),
                                          line_buffering=True)
            resource.setrlimit(resource.RLIMIT_AS, (mem_bytes, mem_bytes))
            import logging
            logging.root.handlers.clear()
            rc = main(argv)
        except SystemExit as e:
            rc = e.code if isinstance(e.code, int) else 1
        except BaseException:
            traceback.print_exc()
            rc = 1
        finally:
            try:
                sys.stdout.flush()
                sys.stderr.flush()
            finally:
                os._exit(rc)
    os.close(w)
    chunks = []
    deadline = time.monotonic() + timeout
    timed_out = False
    while True:
        left = deadline - time.monotonic()
        if left <= 0:
            timed_out = True
            os.kill(pid, signal.SIGKILL)
            break
        ready, _, _ = select.select([r], [], [], left)
        if ready:
            b = os.read(r, 65536)
            if not b:
                break
            chunks.append(b)
    os.close(r)
    _, status, ru = os.wait4(pid, 0)
    if timed_out:
        rc = None
    elif os.WIFSIGNALED(status):
        rc = -os.WTERMSIG(status)
    else:
        rc = os.WEXITSTATUS(status)
    return rc, b"".join(chunks).decode("utf-8", "replace"), ru.ru_maxrss / 1024


def preimport() -> None:
    """Import what the commands import, once, so that every forked child starts warm."""
    import uwbfuse.cli
    import uwbfuse.eval.command
    import uwbfuse.pipeline  # noqa: F401


def classify(case: Case, rc: int | None, stderr: str) -> str:
    """The outcome name of one finished case (see the module docstring)."""
    lines = [x for x in stderr.splitlines() if x.strip()]
    leftovers = []
    if case.out_dir is not None:
        leftovers = [p for p in case.out_dir.iterdir() if ".tmp" in p.name]
    if rc is None:
        return "hang"
    if rc < 0 or "MemoryError" in stderr:
        return "memory"
    if "Traceback (most recent call last)" in stderr:
        return "traceback"
    if leftovers or (rc != 0 and any(p.exists() for p in case.outputs)):
        return "partial"
    if rc == 0:
        if case.must_reject:
            return "accepted"
        if any("Warning:" in x for x in lines):
            return "warning"
        return "ok"
    if rc == 2:
        return "clean" if len(lines) == 1 else "multiline"
    return "other-exit"


def run_case(case: Case, timeout: float, mem_bytes: int, use_exec: bool = False) -> Outcome:
    """Run one case in a child process and classify it."""
    for p in case.outputs:
        p.unlink(missing_ok=True)
    t0 = time.monotonic()
    runner = _run_exec if use_exec else _run_forked
    rc, err, rss = runner(case.argv, timeout, mem_bytes)
    return Outcome(case, classify(case, rc, err), rc, err, time.monotonic() - t0, rss)


def totals_table(outcomes: list[Outcome]) -> str:
    """Markdown table: one row per family, one column per outcome, with totals."""
    fams = [f for f in FAMILIES if any(o.case.family == f for o in outcomes)]
    cols = [k for k in OUTCOMES if any(o.kind == k for o in outcomes)] or ["ok"]
    count = Counter((o.case.family, o.kind) for o in outcomes)
    rows = ["| family | cases | " + " | ".join(cols) + " | breaks |",
            "|---|---:|" + "---:|" * len(cols) + "---:|"]
    for f in [*fams, "all"]:
        sel = [o for o in outcomes if f in ("all", o.case.family)]
        cells = [str(sum(1 for o in sel if o.kind == k)) if f == "all" else
                 str(count[(f, k)]) for k in cols]
        breaks = sum(1 for o in sel if o.kind in BREAKS)
        name = "**all**" if f == "all" else f
        rows.append(f"| {name} | {len(sel)} | " + " | ".join(cells) + f" | {breaks} |")
    return "\n".join(rows)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cases", type=int, default=200, help="number of cases (default 200)")
    ap.add_argument("--seed", type=int, default=1, help="master seed (default 1)")
    ap.add_argument("--families", default=",".join(FAMILIES),
                    help=f"comma-separated subset of {','.join(FAMILIES)}")
    ap.add_argument("--timeout", type=float, default=60.0, help="per case, s (default 60)")
    ap.add_argument("--mem-gb", type=float, default=3.0,
                    help="address-space limit per case, GB (default 3)")
    ap.add_argument("--work", type=Path, default=Path("fuzz_work"),
                    help="work directory for the base logs and cases (default fuzz_work)")
    ap.add_argument("--exec", action="store_true", dest="use_exec",
                    help="a fresh interpreter per case instead of a fork")
    ap.add_argument("--json", type=Path, help="write every outcome as JSON lines here")
    ap.add_argument("-v", "--verbose", action="store_true", help="print every break")
    args = ap.parse_args(argv)
    families = [f for f in args.families.split(",") if f]
    unknown = set(families) - set(FAMILIES)
    if unknown:
        ap.error(f"unknown families: {', '.join(sorted(unknown))}")
    work = args.work.resolve()
    preimport()
    bases = Bases(work)
    t0 = time.monotonic()
    cases = make_cases(args.cases, args.seed, families, bases, work)
    print(f"{len(cases)} cases generated in {time.monotonic() - t0:.1f} s", file=sys.stderr)
    outcomes = []
    mem = int(args.mem_gb * GIB)
    out = args.json.open("w") if args.json else None
    for k, case in enumerate(cases):
        o = run_case(case, args.timeout, mem, args.use_exec)
        outcomes.append(o)
        if out is not None:
            out.write(json.dumps({"family": case.family, "name": case.name,
                                  "argv": case.argv, "outcome": o.kind, "rc": o.rc,
                                  "stderr": o.stderr[-2000:], "wall_s": round(o.wall_s, 3),
                                  "maxrss_mb": round(o.maxrss_mb, 1)}) + "\n")
            out.flush()
        if args.verbose and o.kind in BREAKS:
            last = (o.stderr.strip().splitlines() or [""])[-1][:200]
            print(f"[{k}] {case.family}/{case.name}: {o.kind} rc={o.rc}: {last}",
                  file=sys.stderr)
    if out is not None:
        out.close()
    print(totals_table(outcomes))
    print(f"\n{len(outcomes)} cases in {time.monotonic() - t0:.0f} s; "
          f"max wall {max(o.wall_s for o in outcomes):.1f} s", file=sys.stderr)
    return 1 if any(o.kind in BREAKS for o in outcomes) else 0


if __name__ == "__main__":
    sys.exit(main())
