# SPDX-License-Identifier: BSD-3-Clause
"""`uwbfuse montecarlo` as a library function: the same scenario over many seeds.

Each run is one task on the cluster (`uwbfuse.fleet`): simulate the scenario with seed
`seed0 + i` (in memory, no log file), run every method on it through `pipeline.estimate`,
and score it against the simulated ground truth: the position error at fixed times after
the start of the log (20, 100, 150 and 200 s, as Table 5 of Qiu et al. 2022, "RMSE
comparison between dynamic measurement and real value") and the ATE RMSE over the whole
run. The study's table gives, per time, the RMSE of those errors over the runs for each
method and each method's improvement over the baseline (`imu` when run, as in the paper).

Errors are horizontal (x, y) position errors in the map frame by default, as the AGV
papers report them and `compare` heads its table (`dims=3` for 3-D). Dead reckoning
(`imu`, `odom`) cannot know its start pose, so with `align="auto"` (the default) its
trajectory is moved onto the ground truth at its first pose (position and heading), the
paper's known-start convention; every method that uses ranges is scored as it is, in the
anchor frame.

Layout of `out_dir`: `montecarlo.csv` (RMSE by time), `montecarlo.md` (both tables),
`runs.csv` (one row per run and method), `config.toml` (effective config),
`runs/seed-NNNNN.json` (each run's rows: the done marker used to resume).
"""

from __future__ import annotations

import json
import logging
import math
import time
import traceback
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from enum import StrEnum
from pathlib import Path
from typing import Any

import numpy as np

from uwbfuse.config import dump_config, load_config
from uwbfuse.errors import FleetError, UwbfuseError
from uwbfuse.estimator import Method
from uwbfuse.fleet import (
    ClusterInfo,
    Job,
    config_digest,
    config_payload,
    one_line,
    run_jobs,
    table_csv,
    table_markdown,
    worker_config,
    write_atomic,
)
from uwbfuse.progress import ProgressFn
from uwbfuse.streams import NS_PER_S, PoseStream

log = logging.getLogger(__name__)

DEFAULT_TIMES_S: tuple[float, ...] = (20.0, 100.0, 150.0, 200.0)
"""Times after the log start at which errors are collected (Qiu 2022, Table 5), s."""



class StartAlignment(StrEnum):
    """How a trajectory is placed before scoring: `auto` gives dead reckoning (imu, odom)
    the ground-truth start pose, `first` does so for every method, `none` for none."""

    AUTO = "auto"
    NONE = "none"
    FIRST = "first"

    def applies_to(self, method: Method) -> bool:
        return self is StartAlignment.FIRST or (
            self is StartAlignment.AUTO and not method.uses_ranges
        )

DONE_FORMAT = 1


def parse_methods(methods: str | Sequence[str | Method]) -> tuple[Method, ...]:
    """'isam2,ekf,imu' or a sequence -> Methods (order kept, duplicates dropped)."""
    items = methods.split(",") if isinstance(methods, str) else list(methods)
    out: list[Method] = []
    for item in items:
        name = str(item).strip()
        if not name:
            continue
        try:
            m = Method(name)
        except ValueError:
            from uwbfuse.suggest import did_you_mean

            known = [x.value for x in Method]
            raise FleetError(f"unknown method {name!r} in --methods{did_you_mean(name, known)} "
                             f"(one of: {', '.join(known)})") from None
        if m not in out:
            out.append(m)
    if not out:
        raise FleetError("--methods names no method")
    return tuple(out)


def time_label(t_s: float) -> str:
    """Column name of the error at `t_s` seconds, e.g. 'err_20s_m'."""
    return f"err_{t_s:g}s_m"


# --------------------------------------------------------------------------------------
# Scoring one trajectory


def _yaw(quat_xyzw: np.ndarray) -> np.ndarray:
    x, y, z, w = quat_xyzw.T
    return np.arctan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


def _interp_position(poses: PoseStream, t_ns: np.ndarray) -> np.ndarray:
    """Positions linearly interpolated at `t_ns` (NaN outside the poses' time span)."""
    t = (poses.t_ns - poses.t_ns[0]).astype(np.float64)
    q = (np.asarray(t_ns, dtype=np.int64) - poses.t_ns[0]).astype(np.float64)
    out = np.column_stack([np.interp(q, t, poses.position[:, k]) for k in range(3)])
    out[(q < t[0]) | (q > t[-1])] = np.nan
    return out


def align_first_pose(est: PoseStream, gt: PoseStream) -> PoseStream:
    """`est` moved rigidly (rotation about z, translation) so its first pose has the
    ground-truth position and heading at that time: a known start pose."""
    i = int(np.clip(np.searchsorted(gt.t_ns, est.t_ns[0]), 0, len(gt) - 1))
    p_gt = _interp_position(gt, est.t_ns[:1])[0]
    if not np.isfinite(p_gt).all():
        p_gt = gt.position[i]
    dyaw = float(_yaw(gt.quat_xyzw[i : i + 1])[0] - _yaw(est.quat_xyzw[:1])[0])
    c, s = math.cos(dyaw), math.sin(dyaw)
    rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    pos = (est.position - est.position[0]) @ rot.T + p_gt
    half = 0.5 * dyaw
    qz = np.array([0.0, 0.0, math.sin(half), math.cos(half)])
    x1, y1, z1, w1 = qz
    x2, y2, z2, w2 = est.quat_xyzw.T
    quat = np.column_stack([
        w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
        w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
        w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
        w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
    ])
    return PoseStream(est.t_ns.copy(), pos, quat, est.has_orientation)


def errors_at_times(
    est: PoseStream, gt: PoseStream, t0_ns: int, times_s: Sequence[float], dims: int = 2
) -> np.ndarray:
    """Position error (m; over x, y for `dims` 2, x, y, z for 3) at `t0_ns + times_s`;
    NaN where either trajectory does not cover the time."""
    t = t0_ns + np.round(np.asarray(times_s, dtype=np.float64) * NS_PER_S).astype(np.int64)
    d = _interp_position(est, t) - _interp_position(gt, t)
    return np.linalg.norm(d[:, :dims], axis=1)


def trajectory_rmse(est: PoseStream, gt: PoseStream, dims: int = 2) -> float:
    """RMSE (m) of the position error (`dims` as in `errors_at_times`) at the estimate's
    stamps within the ground truth's time span."""
    d = est.position - _interp_position(gt, est.t_ns)
    e = np.linalg.norm(d[:, :dims], axis=1)
    e = e[np.isfinite(e)]
    return float(np.sqrt(np.mean(e**2))) if len(e) else math.nan


# --------------------------------------------------------------------------------------
# One run (worker side)


@dataclass(frozen=True)
class RunSpec:
    """Everything a worker needs for one Monte Carlo run."""

    name: str
    scenario: str
    duration_s: float
    seed: int
    methods: tuple[Method, ...]
    config: dict[str, Any]  # fleet.config_payload(): validated again on the worker
    times_s: tuple[float, ...]
    align: StartAlignment
    dims: int = 2


def run_montecarlo_job(spec: RunSpec) -> list[dict[str, Any]]:
    """Simulate one seed, run every method, score: one row per method. Never raises for
    a failing simulation or method: those rows say status "failed" and why."""
    from uwbfuse.pipeline import estimate
    from uwbfuse.sim.simulator import simulate

    def base(m: Method) -> dict[str, Any]:
        row: dict[str, Any] = {"seed": spec.seed, "method": m.value, "status": "failed"}
        row.update({time_label(t): math.nan for t in spec.times_s})
        return row

    try:
        config = worker_config(spec.config)
        sim = simulate(spec.scenario, duration_s=spec.duration_s, seed=spec.seed)
        gt = sim.ground_truth
        if gt is None or len(gt) < 2:
            raise FleetError(f"scenario {spec.scenario}: the simulation has no ground truth")
        t0_ns = sim.time_span_ns()[0]
    except Exception as e:
        text = str(e) if isinstance(e, UwbfuseError) else f"{type(e).__name__}: {e}"
        if not isinstance(e, UwbfuseError):
            log.exception("seed %d: simulation crashed", spec.seed)
        return [dict(base(m), error=one_line(text)) for m in spec.methods]

    rows = []
    for m in spec.methods:
        row = base(m)
        tic = time.perf_counter()
        try:
            res = estimate(sim, m, config)
            est = res.trajectory
            if spec.align.applies_to(m):
                est = align_first_pose(est, gt)
            errs = errors_at_times(est, gt, t0_ns, spec.times_s, spec.dims)
            row.update({time_label(t): float(e) for t, e in zip(spec.times_s, errs, strict=True)})
            ate = trajectory_rmse(est, gt, spec.dims)
            row.update(status="ok", error="", poses=len(est), ate_rmse_m=ate)
        except UwbfuseError as e:
            row["error"] = one_line(str(e))
        except Exception as e:
            log.exception("seed %d: method %s crashed", spec.seed, m.value)
            row["error"] = one_line(f"{type(e).__name__}: {e}")
            row["traceback"] = traceback.format_exc()
        row["wall_s"] = time.perf_counter() - tic
        rows.append(row)
    return rows


# --------------------------------------------------------------------------------------
# The study (client side)


@dataclass
class MonteCarloResult:
    """The study: per-run rows and, per method and time, the RMSE over the runs."""

    scenario: str
    runs: int
    duration_s: float
    methods: tuple[Method, ...]
    times_s: tuple[float, ...]
    baseline: Method | None
    rows: list[dict[str, Any]]
    rmse: dict[Method, list[float]]
    n_used: dict[Method, list[int]]
    out_dir: Path
    cluster: ClusterInfo
    wall_s: float
    dims: int = 2

    def time_table(self) -> tuple[list[str], list[dict[str, Any]]]:
        """Qiu 2022 Table 5 layout: one row per time, RMSE per method, then each method's
        improvement over the baseline in percent."""
        others = [m for m in self.methods if m is not self.baseline]
        ordered = ([self.baseline] if self.baseline is not None else []) + others
        cols = ["t_s"] + [f"{m.value}_rmse_m" for m in ordered]
        if self.baseline is not None:
            cols += [f"{m.value}_vs_{self.baseline.value}_pct" for m in others]
        rows = []
        for k, t in enumerate(self.times_s):
            row: dict[str, Any] = {"t_s": t}
            for m in ordered:
                row[f"{m.value}_rmse_m"] = self.rmse[m][k]
            if self.baseline is not None:
                b = self.rmse[self.baseline][k]
                for m in others:
                    v = self.rmse[m][k]
                    ok = math.isfinite(b) and math.isfinite(v) and b > 0
                    row[f"{m.value}_vs_{self.baseline.value}_pct"] = (
                        100.0 * (b - v) / b if ok else math.nan
                    )
            rows.append(row)
        return cols, rows

    def method_table(self) -> tuple[list[str], list[dict[str, Any]]]:
        """Per method: runs that succeeded and failed, mean ATE RMSE, mean wall time."""
        cols = ["method", "runs_ok", "runs_failed", "ate_rmse_mean_m", "wall_mean_s", "first_error"]
        rows = []
        for m in self.methods:
            mine = [r for r in self.rows if r["method"] == m.value]
            ok = [r for r in mine if r["status"] == "ok"]
            ate = [r["ate_rmse_m"] for r in ok if math.isfinite(r.get("ate_rmse_m", math.nan))]
            walls = [r["wall_s"] for r in mine if "wall_s" in r]
            failed = [r for r in mine if r["status"] != "ok"]
            rows.append({
                "method": m.value, "runs_ok": len(ok), "runs_failed": len(failed),
                "ate_rmse_mean_m": float(np.mean(ate)) if ate else math.nan,
                "wall_mean_s": float(np.mean(walls)) if walls else math.nan,
                "first_error": failed[0]["error"] if failed else "",
            })
        return cols, rows

    def table(self) -> str:
        """Both tables as Markdown, with a title line."""
        title = (
            f"Monte Carlo: scenario {self.scenario}, {self.runs} runs of {self.duration_s:g} s; "
            f"RMSE over runs of the {'horizontal' if self.dims == 2 else '3-D'} position "
            "error at each time"
        )
        if self.baseline is not None:
            b = self.baseline.value
            title += f" (*_vs_{b}_pct: error reduction over {b})"
        tc, tr = self.time_table()
        mc, mr = self.method_table()
        return f"{title}\n\n{table_markdown(tc, tr)}\n{table_markdown(mc, mr)}"


def _summarise(
    rows: list[dict[str, Any]], methods: tuple[Method, ...], times_s: tuple[float, ...]
) -> tuple[dict[Method, list[float]], dict[Method, list[int]]]:
    rmse: dict[Method, list[float]] = {}
    used: dict[Method, list[int]] = {}
    for m in methods:
        ok = [r for r in rows if r["method"] == m.value and r["status"] == "ok"]
        rmse[m], used[m] = [], []
        for t in times_s:
            e = np.array([r[time_label(t)] for r in ok], dtype=np.float64)
            e = e[np.isfinite(e)]
            used[m].append(len(e))
            rmse[m].append(float(np.sqrt(np.mean(e**2))) if len(e) else math.nan)
    return rmse, used


def _marker_key(spec: RunSpec, config_sha: str) -> dict[str, Any]:
    return {
        "format": DONE_FORMAT, "scenario": spec.scenario, "duration_s": spec.duration_s,
        "seed": spec.seed, "methods": [m.value for m in spec.methods],
        "times_s": list(spec.times_s), "align": spec.align.value, "dims": spec.dims,
        "config_sha256": config_sha,
    }


def _completed_rows(path: Path, key: dict[str, Any]) -> list[dict[str, Any]] | None:
    try:
        marker = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    if not isinstance(marker, dict) or any(marker.get(k) != v for k, v in key.items()):
        return None
    rows = marker.get("rows")
    if not isinstance(rows, list) or any(r.get("status") != "ok" for r in rows):
        return None
    for r in rows:  # JSON has no NaN by our writing: None stands for it
        for k, v in r.items():
            if v is None:
                r[k] = math.nan
    return rows


def _json_rows(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    return [
        {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in r.items()}
        for r in rows
    ]


def _checked_inputs(
    scenario: str, runs: int, duration_s: float, methods: str | Sequence[str | Method],
    times_s: Sequence[float], align: str | StartAlignment, dims: int,
) -> tuple[StartAlignment, list[Method], tuple[float, ...]]:
    """`montecarlo`'s arguments checked before any cluster starts (FleetError, one line):
    the start alignment, the methods and the scoring times within `duration_s`."""
    from uwbfuse.methods import available_methods
    from uwbfuse.sim.scenarios import get_scenario

    get_scenario(scenario)  # unknown scenario: one clear error
    if dims not in (2, 3):
        raise FleetError(f"dims must be 2 (horizontal) or 3, got {dims}")
    if runs < 1:
        raise FleetError(f"--runs must be at least 1, got {runs}")
    if not (duration_s > 0 and math.isfinite(duration_s)):
        raise FleetError(f"--duration must be a positive number of seconds, got {duration_s}")
    try:
        start_align = StartAlignment(align)
    except ValueError:
        choices = ", ".join(a.value for a in StartAlignment)
        raise FleetError(f"unknown alignment {align!r}; one of: {choices}") from None
    chosen = parse_methods(methods)
    available = set(available_methods())
    missing = [m.value for m in chosen if m not in available]
    if missing:
        raise FleetError(f"method {missing[0]} is not available in this installation")
    times = tuple(float(t) for t in times_s if 0 < float(t) <= duration_s)
    if not times:
        raise FleetError(
            f"--duration {duration_s:g} s is shorter than the first scoring time "
            f"({min(times_s):g} s)"
        )
    return start_align, list(chosen), times


def montecarlo(
    scenario: str = "warehouse",
    runs: int = 20,
    duration_s: float = 200.0,
    methods: str | Sequence[str | Method] = "isam2,ekf,imu",
    out_dir: str | Path = "montecarlo_out",
    scheduler: str | None = None,
    *,
    config_path: str | Path | None = None,
    seed0: int = 0,
    times_s: Sequence[float] = DEFAULT_TIMES_S,
    align: str | StartAlignment = StartAlignment.AUTO,
    dims: int = 2,
    workers: int | None = None,
    dashboard: bool = False,
    resume: bool = True,
    progress: ProgressFn | None = None,
    on_start: Callable[[ClusterInfo], None] | None = None,
) -> MonteCarloResult:
    """Run `runs` simulations of `scenario` (seeds `seed0`...) with every method, one Dask
    task per run; write the tables and per-run rows under `out_dir` and return them.

    Only the times of `times_s` within `duration_s` are scored. `align`: "auto" (dead
    reckoning gets its first pose from the ground truth), "first" (every method does) or
    "none". `dims`: 2 scores horizontal errors, 3 full 3-D ones. `scheduler`, `workers`,
    `dashboard`, `resume`, `progress`, `on_start` as in
    `uwbfuse.fleet.batch_run`. A failing run or method fails its own rows only.
    """
    tic = time.perf_counter()
    start_align, chosen, times = _checked_inputs(scenario, runs, duration_s, methods, times_s,
                                                 align, dims)
    config = load_config(config_path)
    sha = config_digest(config)
    out = Path(out_dir)
    write_atomic(out / "config.toml", dump_config(config))

    specs = [
        RunSpec(f"seed-{seed0 + i:05d}", scenario, float(duration_s), seed0 + i, chosen,
                config_payload(config), times, start_align, dims)
        for i in range(runs)
    ]
    results: dict[str, list[dict[str, Any]]] = {}
    pending: list[Job] = []
    for spec in specs:
        done = _completed_rows(out / "runs" / f"{spec.name}.json", _marker_key(spec, sha))
        if resume and done is not None:
            results[spec.name] = done
        else:
            pending.append(Job(spec.name, run_montecarlo_job, spec))

    def on_result(job: Job, value: Any, error: BaseException | None) -> None:
        spec: RunSpec = job.arg
        if error is not None:
            text = one_line(f"task lost: {type(error).__name__}: {error}")
            value = [
                {"seed": spec.seed, "method": m.value, "status": "failed", "error": text,
                 **{time_label(t): math.nan for t in spec.times_s}}
                for m in spec.methods
            ]
        marker = dict(_marker_key(spec, sha), rows=_json_rows(value))
        write_atomic(out / "runs" / f"{spec.name}.json", json.dumps(marker, indent=1) + "\n")
        results[spec.name] = [{k: v for k, v in r.items() if k != "traceback"} for r in value]

    info = run_jobs(
        pending, on_result, scheduler=scheduler, workers=workers, dashboard=dashboard,
        on_start=on_start, progress=progress, done_before=len(results),
    )
    rows = [r for spec in specs for r in results[spec.name]]
    rmse, used = _summarise(rows, chosen, times)
    baseline = Method.IMU if Method.IMU in chosen and len(chosen) > 1 else None
    result = MonteCarloResult(
        scenario, runs, float(duration_s), chosen, times, baseline, rows, rmse, used, out,
        info, time.perf_counter() - tic, dims,
    )
    run_cols = ["seed", "method", "status", "error", "ate_rmse_m", "poses", "wall_s"]
    run_cols += [time_label(t) for t in times]
    tc, tr = result.time_table()
    write_atomic(out / "runs.csv", table_csv(run_cols, rows))
    write_atomic(out / "montecarlo.csv", table_csv(tc, tr))
    write_atomic(out / "montecarlo.md", result.table())
    return result
