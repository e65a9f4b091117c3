# SPDX-License-Identifier: BSD-3-Clause
"""What `uwbfuse run` tells: a few human lines on stdout, the full diagnostics as JSON.

One latency figure: the update latency, the wall time of one estimator step (the data of
one output epoch in, that epoch's pose out), as a live system would wait for it each epoch.
Estimators' own internal timings (e.g. the graph's iSAM2-update-only `update_latency_ms`)
are left out so that no second, disagreeing latency is reported.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from uwbfuse.errors import TrajectoryFileError
from uwbfuse.io.atomic import write_atomic

if TYPE_CHECKING:
    from uwbfuse.pipeline import RunResult

LATENCY_DEFINITION = ("wall time of one estimator step: the data of one output epoch in, "
                      "that epoch's pose out")
_INTERNAL_TIMINGS = ("update_latency_ms",)  # estimator-internal; superseded by the above


def _fmt(v: Any) -> str:
    if isinstance(v, float | np.floating):
        return f"{float(v):.4g}"
    if isinstance(v, dict):
        return ", ".join(f"{k}={_fmt(x)}" for k, x in v.items())
    if isinstance(v, list | tuple):
        return ", ".join(_fmt(x) for x in v)
    return str(v)


def format_report(report: dict[str, Any]) -> list[str]:
    """One line per report entry: `key: value` with nested dicts inlined."""
    return [f"{key}: {_fmt(value)}" for key, value in report.items()]


def latency_ms(step_latency_s: np.ndarray) -> dict[str, float | int | str]:
    """p50 / p99 / max of the update latency, ms, with its definition."""
    lat = np.asarray(step_latency_s, dtype=np.float64) * 1e3
    if not len(lat):
        return {"definition": LATENCY_DEFINITION, "n": 0}
    return {"definition": LATENCY_DEFINITION, "n": len(lat),
            "p50": float(np.median(lat)), "p99": float(np.percentile(lat, 99)),
            "max": float(lat.max())}


def _jsonable(v: Any) -> Any:
    if isinstance(v, dict):
        return {str(k): _jsonable(x) for k, x in v.items()}
    if isinstance(v, list | tuple):
        return [_jsonable(x) for x in v]
    if isinstance(v, np.ndarray):
        return _jsonable(v.tolist())
    if isinstance(v, np.generic):
        return _jsonable(v.item())
    if isinstance(v, float) and not math.isfinite(v):
        return None if math.isnan(v) else ("inf" if v > 0 else "-inf")
    if v is None or isinstance(v, bool | int | float | str):
        return v
    return str(v)


def run_report(res: RunResult, log: str, outputs: dict[str, str]) -> dict[str, Any]:
    """The full diagnostics of one run (what `--report FILE.json` holds)."""
    rr = res.read_report
    estimator = {k: v for k, v in res.report.items() if k not in _INTERNAL_TIMINGS}
    return _jsonable({
        "log": log,
        "method": res.method.value,
        "outputs": outputs,
        "poses": len(res.trajectory),
        "frame": "base_link in map",
        "log_duration_s": res.log_duration_s,
        "read_wall_s": res.read_wall_s,
        "estimate_wall_s": res.estimate_wall_s,
        "realtime_factor": res.realtime_factor,
        "update_latency_ms": latency_ms(res.step_latency_s),
        "read": {"messages": dict(rr.messages), "skipped": dict(rr.skipped),
                 "warnings": list(rr.warnings)},
        "estimator": estimator,
    })


def run_summary(res: RunResult, outputs: dict[str, str]) -> list[str]:
    """A few lines for a person: what was written, how fast, what was dropped."""
    lat = latency_ms(res.step_latency_s)
    where = ", ".join(outputs.values())
    lines = [f"{res.method.value}: {len(res.trajectory)} poses (base_link in map) over "
             f"{res.log_duration_s:.1f} s of log -> {where}"]
    speed = (f"read {res.read_wall_s:.2f} s, estimate {res.estimate_wall_s:.2f} s "
             f"({res.realtime_factor:.0f}x real time)")
    if lat["n"]:
        speed += f"; update latency p50 {lat['p50']:.2f} ms, p99 {lat['p99']:.2f} ms"
    lines.append(speed)
    rr = res.read_report
    skipped = sum(rr.skipped.values())
    if skipped or rr.warnings:
        lines.append(f"input: {sum(rr.messages.values())} messages, {skipped} skipped, "
                     f"{len(rr.warnings)} warnings (details on stderr)")
    return lines


def write_report_json(path: str | Path, report: dict[str, Any]) -> None:
    """Write `report` to `path` as indented JSON, atomically."""
    write_atomic(path, json.dumps(report, indent=2, allow_nan=False) + "\n",
                 error=TrajectoryFileError, what="run report")
