# SPDX-License-Identifier: BSD-3-Clause
"""`uwbfuse compare`: several methods on one log through one loop, a table and plots.

`compare_log` reads as its steps: read the log once, run every method through the same
streaming loop (`pipeline.estimate`), score each against the log's ground truth, write the
trajectories, the table (CSV + Markdown), the plots and the effective config into DIR.
A method that fails on this log gets a row with its error, never stops the others.
"""

from __future__ import annotations

import csv
import io
import logging
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from uwbfuse.config import Config, dump_config, load_config
from uwbfuse.errors import ConfigError, UwbfuseError
from uwbfuse.estimator import Method
from uwbfuse.eval.evaluate import EvalResult, evaluate
from uwbfuse.io.atomic import write_atomic
from uwbfuse.progress import ProgressFn
from uwbfuse.streams import NS_PER_S, PoseStream, SensorLog
from uwbfuse.suggest import did_you_mean

log = logging.getLogger(__name__)

COLUMNS = (
    "method", "status", "ate2d_rmse_m", "ate2d_median_m", "ate2d_max_m", "ate3d_rmse_m",
    "yaw_rmse_deg", "coverage_pct", "poses", "wall_s", "realtime_factor", "error",
)


@dataclass
class MethodRow:
    """One method's outcome on the log: metrics when it ran and the log has ground truth."""

    method: str
    status: str
    trajectory: PoseStream | None = None
    metrics: EvalResult | None = None
    wall_s: float = math.nan
    realtime_factor: float = math.nan
    error: str = ""

    def cells(self) -> dict[str, str]:
        m = self.metrics

        def f(v: float | None, scale: float = 1.0, digits: int = 3) -> str:
            return "" if v is None or not math.isfinite(v) else f"{v * scale:.{digits}f}"

        return {
            "method": self.method,
            "status": self.status,
            "ate2d_rmse_m": f(m.ate_2d.rmse if m else None),
            "ate2d_median_m": f(m.ate_2d.median if m else None),
            "ate2d_max_m": f(m.ate_2d.max if m else None),
            "ate3d_rmse_m": f(m.ate_3d.rmse if m else None),
            "yaw_rmse_deg": f(m.yaw.rmse if m and m.yaw else None, 180 / math.pi, 2),
            "coverage_pct": f(m.coverage if m else None, 100.0, 1),
            "poses": str(len(self.trajectory)) if self.trajectory is not None else "",
            "wall_s": f(self.wall_s, digits=2),
            "realtime_factor": f(self.realtime_factor, digits=1),
            "error": self.error,
        }


@dataclass
class CompareResult:
    """All rows plus the files written."""

    log_path: str
    rows: list[MethodRow]
    out_dir: Path
    files: list[Path] = field(default_factory=list)

    def markdown(self) -> str:
        """The table in Markdown (also written to DIR/table.md)."""
        head = "| " + " | ".join(COLUMNS) + " |"
        sep = "|" + "|".join("---" for _ in COLUMNS) + "|"
        body = [
            "| " + " | ".join(r.cells()[c].replace("|", "/") for c in COLUMNS) + " |"
            for r in self.rows
        ]
        return "\n".join([head, sep, *body]) + "\n"


def parse_methods(methods: str | list[str]) -> list[Method]:
    """'isam2,ekf' -> [Method.ISAM2, Method.EKF]; unknown names are a ConfigError."""
    names = methods.split(",") if isinstance(methods, str) else list(methods)
    out: list[Method] = []
    for name in (n.strip() for n in names):
        if not name:
            continue
        try:
            out.append(Method(name))
        except ValueError:
            known = [m.value for m in Method]
            raise ConfigError(f"--methods: unknown method {name!r}"
                              f"{did_you_mean(name, known)} (one of: {', '.join(known)})"
                              ) from None
    if not out:
        raise ConfigError("--methods: no method given")
    return out


def _named(progress: ProgressFn | None, name: str) -> ProgressFn | None:
    """`progress` with `name` put before each note."""
    if progress is None:
        return None
    return lambda done, total, note: progress(done, total, f"{name} {note}".strip())


def write_text_atomic(path: Path, text: str) -> None:
    """Write `text` to `path` whole or not at all (temporary file + rename)."""
    write_atomic(path, text, error=ConfigError, what="output")


def run_methods(
    log_data: SensorLog, methods: list[Method], config: Config, max_dt: float,
    align: str = "none", progress: ProgressFn | None = None,
) -> list[MethodRow]:
    """Run each method on the already-read log and score it against its ground truth
    (`align`: none | se2 | se3, for ground truth in another frame); `progress` is told
    each method's seconds of log processed, the note naming the method."""
    from uwbfuse.pipeline import estimate

    rows = []
    gt = log_data.ground_truth
    for method in methods:
        try:
            res = estimate(log_data, method, config, _named(progress, method.value))
        except UwbfuseError as e:
            log.warning("%s failed: %s", method.value, e)
            rows.append(MethodRow(method.value, "failed", error=str(e)))
            continue
        row = MethodRow(
            method.value, "ok", res.trajectory, wall_s=res.estimate_wall_s,
            realtime_factor=res.log_duration_s / max(res.estimate_wall_s, 1e-9),
        )
        if gt is not None and len(gt):
            try:
                row.metrics = evaluate(
                    res.trajectory, gt, align=align, max_dt=max_dt, est_name=method.value,
                    gt_name="ground truth",
                )
            except UwbfuseError as e:
                row.status, row.error = "no-eval", str(e)
        rows.append(row)
    return rows


def compare_log(
    log_path: str | Path,
    methods: str | list[str] = "isam2,batch,ekf,ukf,wls,imu,odom",
    config_path: str | Path | None = None,
    out_dir: str | Path = "compare_out",
    max_dt: float | None = None,
    gt_path: str | Path | None = None,
    align: str = "none",
    progress: ProgressFn | None = None,
) -> CompareResult:
    """Run `methods` on the log, write table, trajectories, plots and config to `out_dir`.

    gt_path: ground truth as a TUM file when the log has none on its topic; align: none |
    se2 | se3 when that ground truth is in another frame (plots then show it moved into
    the map frame by the best method's alignment).
    """
    from uwbfuse.io.reader import read_log
    from uwbfuse.io.tum import read_tum, write_tum

    config = load_config(config_path)
    method_list = parse_methods(methods)
    out = Path(out_dir)
    try:
        (out / "trajectories").mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise ConfigError(f"{out}: cannot create output folder: {e.strerror or e}") from None
    log_data = read_log(log_path, config)
    if gt_path is not None:
        log_data.ground_truth = read_tum(gt_path)
    # Estimates come at the output rate; associate within half an output period.
    tol = max_dt if max_dt is not None else 0.5 / config.output.rate
    rows = run_methods(log_data, method_list, config, tol, align, progress)
    plot_log = _gt_in_map_frame(log_data, rows) if align != "none" else log_data

    result = CompareResult(str(log_path), rows, out)
    for row in rows:
        if row.trajectory is not None:
            p = out / "trajectories" / f"{row.method}.tum"
            write_tum(p, row.trajectory)
            result.files.append(p)
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=COLUMNS, lineterminator="\n")
    writer.writeheader()
    for row in rows:
        writer.writerow(row.cells())
    for name, text in (
        ("table.csv", buf.getvalue()),
        ("table.md", f"# {log_path}\n\n" + result.markdown()),
        ("config.toml", dump_config(config)),
    ):
        write_text_atomic(out / name, text)
        result.files.append(out / name)

    from uwbfuse.plots import plot_comparison

    result.files.extend(plot_comparison(plot_log, rows, config, out))
    return result


def _gt_in_map_frame(log_data: SensorLog, rows: list[MethodRow]) -> SensorLog:
    """The log with its ground truth moved into the map frame by the inverse alignment of
    the best-ranked scored method (smoothers first), for plotting over the anchors."""
    from dataclasses import replace

    from scipy.spatial.transform import Rotation

    gt = log_data.ground_truth
    scored = {r.method: r for r in rows if r.metrics is not None}
    order = ["batch", "isam2-smoothed", "isam2", "ekf", "ukf", "lkf", "wls"]
    pick = next((scored[m] for m in order if m in scored), None)
    if gt is None or pick is None:
        return log_data
    tf = pick.metrics.transform
    pos = (gt.position - tf.translation) @ tf.rotation
    quat = (Rotation.from_matrix(tf.rotation.T) * Rotation.from_quat(gt.quat_xyzw)).as_quat()
    moved = PoseStream(gt.t_ns, pos, quat, gt.has_orientation)
    return replace(log_data, ground_truth=moved)


def range_residuals(
    log_data: SensorLog, reference: PoseStream, config: Config
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Residuals (measured - predicted) of every range against a reference trajectory.

    The tag position at each range stamp is the reference position interpolated linearly
    plus the lever arm `tag_in_base` rotated by the nearest reference orientation.
    Returns (t_s, anchor index, residual m, tag xy (N,2)); ranges outside the reference
    span are left out.
    """
    from scipy.spatial.transform import Rotation

    r = log_data.ranges
    if r is None or log_data.anchors is None or len(reference) < 2:
        z = np.zeros(0)
        return z, z.astype(int), z, np.zeros((0, 2))
    inside = (r.t_ns >= reference.t_ns[0]) & (r.t_ns <= reference.t_ns[-1])
    t = r.t_ns[inside]
    tref = reference.t_ns
    pos = np.column_stack([np.interp(t, tref, reference.position[:, i]) for i in range(3)])
    idx = np.clip(np.searchsorted(tref, t), 0, len(tref) - 1)
    lever = np.asarray(config.extrinsics.tag_in_base)
    if reference.has_orientation and np.any(lever):
        pos = pos + Rotation.from_quat(reference.quat_xyzw[idx]).apply(lever)
    elif np.any(lever):
        pos = pos + lever
    anchor = r.anchor[inside]
    pred = np.linalg.norm(pos - log_data.anchors.positions[anchor], axis=1)
    return t / NS_PER_S, anchor, r.range[inside] - pred, pos[:, :2]
