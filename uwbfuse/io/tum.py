# SPDX-License-Identifier: BSD-3-Clause
"""TUM trajectory files: `t x y z qx qy qz qw`, one pose per line.

t is in seconds; we write it from the integer nanoseconds exactly (9 decimals) and read it
back exactly (no float round trip), so a write/read cycle keeps every stamp. Poses are the
base frame in the map frame, quaternions in (x, y, z, w) order.
"""

from __future__ import annotations

import logging
import math
import re
from decimal import Decimal, InvalidOperation
from pathlib import Path

import numpy as np

from uwbfuse.errors import TrajectoryFileError
from uwbfuse.io.atomic import atomic_open
from uwbfuse.io.fields import MAX_COORD_M
from uwbfuse.streams import NS_PER_S, PoseStream

log = logging.getLogger(__name__)

_DECIMAL = re.compile(r"^(?P<sign>[+-]?)(?P<whole>[0-9]*)(?:\.(?P<frac>[0-9]*))?$")
HEADER = "# t x y z qx qy qz qw  (t: s; x y z: m, base frame in map frame)\n"
_MAX_NS = (1 << 63) - 1  # stamps are int64 nanoseconds (year 2262)
# a written quaternion is unit: one with a norm outside [MIN, MAX] is no rotation (and at
# 1e-200 or 1e200 the norm itself underflows or overflows)
MIN_QUAT_NORM, MAX_QUAT_NORM = 1e-6, 1e6


def _format_stamp(t_ns: int) -> str:
    """Seconds with exactly 9 decimals from integer nanoseconds (negative stamps too)."""
    sign = "-" if t_ns < 0 else ""
    s, ns = divmod(abs(int(t_ns)), NS_PER_S)
    return f"{sign}{s}.{ns:09d}"


def _parse_stamp_ns(tok: str) -> int:
    """Integer nanoseconds from a decimal seconds string (exact; rounds below 1 ns)."""
    m = _DECIMAL.match(tok)
    if m is not None and (m["whole"] or m["frac"]):
        frac = m["frac"] or ""
        ns = int(m["whole"] or "0") * NS_PER_S + int(frac[:9].ljust(9, "0"))
        if len(frac) > 9 and frac[9] >= "5":
            ns += 1
        return -ns if m["sign"] == "-" else ns
    try:
        d = Decimal(tok)
    except InvalidOperation:
        raise ValueError(f"bad time {tok!r}") from None
    if not d.is_finite() or abs(d) > 10 * _MAX_NS:
        raise ValueError(f"bad time {tok!r}")
    return int((d * NS_PER_S).to_integral_value())


def write_tum(path: str | Path, poses: PoseStream) -> None:
    """Write `poses` to `path` as TUM, atomically (temporary file + rename).

    Raises TrajectoryFileError when the directory is not writable or a pose is not finite;
    the target is then left untouched.
    """
    p = Path(path)
    pos = np.asarray(poses.position, dtype=np.float64)
    quat = np.asarray(poses.quat_xyzw, dtype=np.float64)
    if len(poses) and not (np.isfinite(pos).all() and np.isfinite(quat).all()):
        bad = int(np.flatnonzero(~(np.isfinite(pos).all(1) & np.isfinite(quat).all(1)))[0])
        raise TrajectoryFileError(f"{p}: pose {bad} is not finite, nothing written")
    lines = [HEADER]
    lines.extend(
        f"{_format_stamp(t)} {x:.6f} {y:.6f} {z:.6f} {qx:.9f} {qy:.9f} {qz:.9f} {qw:.9f}\n"
        for t, (x, y, z), (qx, qy, qz, qw) in zip(
            poses.t_ns.tolist(), pos.tolist(), quat.tolist(), strict=True
        )
    )
    with atomic_open(p, "w", error=TrajectoryFileError, what="trajectory") as f:
        f.writelines(lines)


def read_tum(path: str | Path) -> PoseStream:
    """Read a TUM file: '#' comments and blank lines skipped, rows sorted by time.

    Columns may be separated by spaces, tabs or commas. Quaternions are normalised; a row
    with a wrong column count, a non-number, a non-finite value or a zero quaternion raises
    TrajectoryFileError naming the file and line. Rows with a repeated stamp keep the first.
    `has_orientation` is False when every quaternion is exactly the identity (position-only
    ground truth written as TUM).
    """
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8-sig")
    except FileNotFoundError:
        raise TrajectoryFileError(f"{p}: trajectory file not found") from None
    except IsADirectoryError:
        raise TrajectoryFileError(f"{p}: is a directory, expected a TUM file") from None
    except (OSError, UnicodeDecodeError) as e:
        raise TrajectoryFileError(f"{p}: cannot read trajectory: {e}") from None

    stamps: list[int] = []
    values: list[list[float]] = []
    for lineno, raw in enumerate(text.splitlines(), start=1):
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        toks = line.replace(",", " ").split()
        if len(toks) != 8:
            raise TrajectoryFileError(
                f"{p}:{lineno}: expected 8 columns 't x y z qx qy qz qw', got {len(toks)}"
            )
        try:
            stamps.append(_parse_stamp_ns(toks[0]))
            row = [float(x) for x in toks[1:]]
        except ValueError:
            raise TrajectoryFileError(f"{p}:{lineno}: not a number in {line[:80]!r}") from None
        if not -_MAX_NS <= stamps[-1] <= _MAX_NS:
            raise TrajectoryFileError(f"{p}:{lineno}: time {toks[0]} s is out of range "
                                      "(int64 nanoseconds: +-9.2e9 s)")
        if not all(np.isfinite(row)):
            raise TrajectoryFileError(f"{p}:{lineno}: non-finite value in {line[:80]!r}")
        if max(abs(x) for x in row[:3]) > MAX_COORD_M:
            raise TrajectoryFileError(f"{p}:{lineno}: position beyond {MAX_COORD_M:g} m in "
                                      f"{line[:80]!r}")
        # math.hypot scales: no overflow warning for 1e308 components (np.linalg.norm's dot)
        if not MIN_QUAT_NORM <= math.hypot(*row[3:7]) <= MAX_QUAT_NORM:
            what = "zero" if max(abs(x) for x in row[3:7]) < 1 else "huge"
            raise TrajectoryFileError(f"{p}:{lineno}: {what} quaternion (norm outside "
                                      f"[{MIN_QUAT_NORM:g}, {MAX_QUAT_NORM:g}]: not a rotation)")
        values.append(row)
    if not stamps:
        raise TrajectoryFileError(f"{p}: no poses in trajectory file")

    t_ns = np.array(stamps, dtype=np.int64)
    data = np.array(values, dtype=np.float64)
    order = np.argsort(t_ns, kind="stable")
    t_ns, data = t_ns[order], data[order]
    keep = np.ones(len(t_ns), dtype=bool)
    keep[1:] = np.diff(t_ns) != 0
    if not keep.all():
        log.warning("%s: dropped %d poses with a repeated stamp", p, int((~keep).sum()))
        t_ns, data = t_ns[keep], data[keep]
    quat = data[:, 3:7]
    identity = bool(np.all(quat[:, :3] == 0.0) and np.all(quat[:, 3] > 0.0))
    quat = quat / np.linalg.norm(quat, axis=1, keepdims=True)
    return PoseStream(t_ns, np.ascontiguousarray(data[:, :3]), quat, not identity)
