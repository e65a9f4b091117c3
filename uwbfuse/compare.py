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
from uwbfuse.estimator import Method, RangeClasses
from uwbfuse.eval.evaluate import EvalResult, RpeResult, evaluate
from uwbfuse.io.atomic import write_atomic
from uwbfuse.methods import by_reference_rank
from uwbfuse.progress import ProgressFn
from uwbfuse.streams import PoseStream, SensorLog
from uwbfuse.suggest import did_you_mean

log = logging.getLogger(__name__)

COLUMNS = (
    "method", "status", "ate2d_rmse_m", "ate2d_median_m", "ate2d_max_m", "ate3d_rmse_m",
    "rpe1m_rmse_m", "rpe10m_rmse_m", "yaw_rmse_deg", "coverage_pct", "poses", "wall_s",
    "realtime_factor", "error",
)
RPE_PATHS_M = (1.0, 10.0)
"""Travelled ground-truth path (m) of the table's RPE columns: local error over a metre,
drift over a room's length."""
RPE_NOTE = (
    "rpe1m / rpe10m: RMSE of the translation error of the relative motion over 1 m / 10 m of "
    "ground-truth path, every pose as a start (the same numbers as `evo_rpe tum GT EST "
    "--pose_relation trans_part --delta 1 --delta_unit m --all_pairs --pairs_from_reference "
    "--t_max_diff 0.05`, delta 10 for rpe10m, t_max_diff half the output period); empty "
    "when the ground-truth path is too short."
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
    rpe_path: dict[float, RpeResult] = field(default_factory=dict)  # by GT path length, m
    range_classes: RangeClasses | None = None  # the method's own LOS/NLOS per range

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
            **{
                f"rpe{d:g}m_rmse_m": f(self.rpe_path[d].stats.rmse if d in self.rpe_path else None)
                for d in RPE_PATHS_M
            },
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

    def notes(self) -> list[str]:
        """What the table's less obvious columns mean (under the table in table.md)."""
        return [RPE_NOTE]


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
            res = estimate(log_data, method, config, _named(progress, method.value),
                           covariance=False)  # nothing here shows a covariance
        except UwbfuseError as e:
            log.warning("%s failed: %s", method.value, e)
            rows.append(MethodRow(method.value, "failed", error=str(e)))
            continue
        row = MethodRow(
            method.value, "ok", res.trajectory, wall_s=res.estimate_wall_s,
            realtime_factor=res.log_duration_s / max(res.estimate_wall_s, 1e-9),
            range_classes=res.range_classes,
        )
        if gt is not None and len(gt):
            try:
                row.metrics = evaluate(
                    res.trajectory, gt, align=align, max_dt=max_dt, est_name=method.value,
                    gt_name="ground truth",
                )
                row.rpe_path = _rpe_over_paths(res.trajectory, gt, align, max_dt, row.metrics)
            except UwbfuseError as e:
                row.status, row.error = "no-eval", str(e)
        rows.append(row)
    return rows


def _rpe_over_paths(
    est: PoseStream, gt: PoseStream, align: str, max_dt: float, metrics: EvalResult
) -> dict[float, RpeResult]:
    """RPE over each of RPE_PATHS_M metres of GT path (`evaluate` scores one distance
    delta per call: the ones `metrics` lacks are evaluated again)."""
    have = {r.delta: r for r in metrics.rpe if r.unit == "m"}
    out = {}
    for delta in RPE_PATHS_M:
        if delta not in have:
            again = evaluate(est, gt, align=align, max_dt=max_dt, rpe_dist_m=delta)
            have[delta] = next(r for r in again.rpe if r.unit == "m")
        out[delta] = have[delta]
    return out


def compare_log(
    log_path: str | Path,
    methods: str | list[str] = "isam2,batch,ekf,ukf,wls,imu,odom",
    config_path: str | Path | None = None,
    out_dir: str | Path = "compare_out",
    max_dt: float | None = None,
    gt_path: str | Path | None = None,
    align: str = "none",
    html: bool = False,
    progress: ProgressFn | None = None,
) -> CompareResult:
    """Run `methods` on the log, write table, trajectories, plots and config to `out_dir`.

    gt_path: ground truth as a TUM file when the log has none on its topic; align: none |
    se2 | se3 when that ground truth is in another frame (plots then show it moved into
    the map frame by the best method's alignment). html: also write `report.html`, the
    table, plots and config in one self-contained file.
    """
    from uwbfuse.io.reader import read_log
    from uwbfuse.io.tum import read_tum, write_tum
    from uwbfuse.pipeline import check_classifier

    config = load_config(config_path)
    method_list = parse_methods(methods)
    out = Path(out_dir)
    try:
        (out / "trajectories").mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise ConfigError(f"{out}: cannot create output folder: {e.strerror or e}") from None
    check_classifier(config)  # a bad model file fails before the log is read
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
    notes = "".join(f"\n{n}\n" for n in result.notes())
    config_text = effective_config_text(config, log_data)
    for name, text in (
        ("table.csv", buf.getvalue()),
        ("table.md", f"# {log_path}\n\n" + result.markdown() + notes),
        ("config.toml", config_text),
    ):
        write_text_atomic(out / name, text)
        result.files.append(out / name)

    from uwbfuse.plots import plot_comparison

    plots = plot_comparison(plot_log, rows, config, out)
    result.files.extend(plots)
    if html:
        from uwbfuse.html_report import write_html_report

        result.files.append(write_html_report(out / "report.html", result, plots, config_text))
    return result


def effective_config_text(config: Config, log_data: SensorLog) -> str:
    """The config the run used, as TOML: `config` with the anchors actually used (the
    log's `uwb_anchors` metadata when the config has no `[anchors]`)."""
    anchors = log_data.anchors
    if anchors is None or not len(anchors):
        return dump_config(config)
    used = {aid: (float(p[0]), float(p[1]), float(p[2]))
            for aid, p in zip(anchors.ids, anchors.positions, strict=True)}
    text = dump_config(config.model_copy(update={"anchors": used}))
    if config.anchors:
        return text
    return (f"# [anchors] below: the log's 'uwb_anchors' metadata record ({log_data.source})\n"
            + text)


def _gt_in_map_frame(log_data: SensorLog, rows: list[MethodRow]) -> SensorLog:
    """The log with its ground truth moved into the map frame by the inverse alignment of
    the best-ranked scored method (smoothers first), for plotting over the anchors."""
    from dataclasses import replace

    from scipy.spatial.transform import Rotation

    gt = log_data.ground_truth
    scored = {r.method: r for r in rows if r.metrics is not None}
    order = [m.value for m in by_reference_rank()]
    pick = next((scored[m] for m in order if m in scored), None)
    if gt is None or pick is None:
        return log_data
    tf = pick.metrics.transform
    pos = (gt.position - tf.translation) @ tf.rotation
    quat = (Rotation.from_matrix(tf.rotation.T) * Rotation.from_quat(gt.quat_xyzw)).as_quat()
    moved = PoseStream(gt.t_ns, pos, quat, gt.has_orientation)
    return replace(log_data, ground_truth=moved)


@dataclass(frozen=True)
class RangeResiduals:
    """Residuals (measured - predicted, m) of ranges against a reference trajectory: range
    stamps (N,) int64 ns, anchor index (N,), residual (N,) m, tag x, y (N,2) m, map frame."""

    t_ns: np.ndarray
    anchor: np.ndarray
    residual: np.ndarray
    tag_xy: np.ndarray

    @classmethod
    def empty(cls) -> RangeResiduals:
        z = np.zeros(0)
        return cls(z.astype(np.int64), z.astype(np.int64), z, np.zeros((0, 2)))

    def classified_nlos(self, classes: RangeClasses) -> np.ndarray:
        """Each residual's class in `classes` (a method's own classification), matched by
        stamp and anchor: 1 NLOS, 0 LOS, 2 LOS but down-weighted by the robust kernel
        (weight < 0.999, where `classes` has weights), -1 not classified (a range the method
        did not use, e.g. before its start). (N,) int8."""
        out = np.full(len(self.t_ns), -1, dtype=np.int8)
        for a in np.unique(self.anchor):
            mine = np.flatnonzero(classes.anchor == a)
            if len(mine) == 0:
                continue
            order = mine[np.argsort(classes.t_ns[mine], kind="stable")]
            t_cls = classes.t_ns[order]
            sel = np.flatnonzero(self.anchor == a)
            k = np.clip(np.searchsorted(t_cls, self.t_ns[sel]), 0, len(t_cls) - 1)
            hit = t_cls[k] == self.t_ns[sel]
            j = order[k[hit]]
            out[sel[hit]] = np.where(classes.downweighted[j], 2, classes.nlos[j])
        return out


def range_residuals(log_data: SensorLog, reference: PoseStream, config: Config) -> RangeResiduals:
    """Residuals (measured - predicted) of every range against a reference trajectory.

    The tag position at each range stamp is the reference position interpolated linearly
    plus the lever arm `tag_in_base` rotated by the nearest reference orientation. Ranges
    outside the reference span are left out.
    """
    from scipy.spatial.transform import Rotation

    r = log_data.ranges
    if r is None or log_data.anchors is None or len(reference) < 2:
        return RangeResiduals.empty()
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
    return RangeResiduals(t, anchor, r.range[inside] - pred, pos[:, :2])
