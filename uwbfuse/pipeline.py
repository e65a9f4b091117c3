# SPDX-License-Identifier: BSD-3-Clause
"""`uwbfuse run` as a library function: read, check, estimate, write.

`run_log` reads as its steps: load the log, check the method has what it needs, run the
estimator over the log, pick the trajectory the method stands for, write the outputs.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from uwbfuse.config import Config
from uwbfuse.constants import COLLINEAR_RMS_M
from uwbfuse.errors import AnchorMapError, EstimatorError, TrajectoryFileError
from uwbfuse.estimator import Method, RangeClasses, output_epochs, run_streaming
from uwbfuse.methods import REQUIRED_STREAMS, WITHOUT_RANGES, make_estimator
from uwbfuse.prestart import PreStart
from uwbfuse.progress import ProgressFn
from uwbfuse.streams import NS_PER_S, PoseStream, ReadReport, SensorLog

log = logging.getLogger(__name__)

_STREAM_ROLE = {"imu": "imu", "wheel": "wheel_odom", "uwb": "uwb"}


@dataclass
class RunResult:
    """What one `run` produced: the trajectory written and how it was obtained."""

    method: Method
    trajectory: PoseStream
    causal: PoseStream
    final: PoseStream | None
    step_latency_s: np.ndarray
    estimate_wall_s: float
    read_wall_s: float
    log_duration_s: float
    report: dict[str, Any] = field(default_factory=dict)
    read_report: ReadReport = field(default_factory=ReadReport)
    range_classes: RangeClasses | None = None  # the estimator's own LOS/NLOS per range

    @property
    def realtime_factor(self) -> float:
        """Log duration over wall time (reading included)."""
        wall = self.estimate_wall_s + self.read_wall_s
        return self.log_duration_s / wall if wall > 0 else float("inf")


def sensor_streams(log: SensorLog) -> frozenset[str]:
    """The sensor streams present (non-empty) in `log`: subset of {imu, wheel, uwb, pose}."""
    present = set()
    if log.imu is not None and len(log.imu):
        present.add("imu")
    if log.wheel is not None and len(log.wheel):
        present.add("wheel")
    if log.ranges is not None and len(log.ranges):
        present.add("uwb")
    if log.pose is not None and len(log.pose):
        present.add("pose")
    return frozenset(present)


def check_inputs(log: SensorLog, method: Method, config: Config) -> frozenset[str]:
    """Raise a one-line error if `log` lacks what `method` needs; return the streams."""
    streams = sensor_streams(log)
    if not method.spec.uses_pose:
        streams = streams - {"pose"}
    alone = WITHOUT_RANGES.get(method)
    if "uwb" not in streams and alone is not None and alone <= streams:
        return streams  # IMU + wheels without UWB: no anchor map needed
    if "uwb" not in streams and "pose" in streams and streams & {"imu", "wheel"}:
        return streams  # external poses with an IMU or wheels: no anchor map needed
    if method.uses_ranges and log.anchors is None:
        raise AnchorMapError(
            f"{log.source}: no anchor map: give an [anchors] table in the config or a "
            f"'uwb_anchors' metadata record in the log (method {method.value} uses ranges)"
        )
    missing = REQUIRED_STREAMS[method] - streams
    if missing:
        role = sorted(missing)[0]
        topic = getattr(config.topics, _STREAM_ROLE[role])
        present = ", ".join(sorted(log.report.messages)) or "none"
        raise EstimatorError(
            f"{log.source}: method {method.value} needs {role} data but topic {topic!r} "
            f"has none (topics present: {present})"
        )
    return streams




def _never_initialised(log: SensorLog, method: Method) -> str:
    """One line for a method that gave no pose at all, with the likely reason: too few
    anchors heard, or all of them on one line in x, y (a 2-D fix from ranges then has a
    mirror image; the starts need three anchors off a line)."""
    msg = f"{log.source}: method {method.value} never initialised (no pose estimated)"
    if log.ranges is None or log.anchors is None or not method.uses_ranges:
        return msg
    heard = np.unique(log.ranges.anchor[np.isfinite(log.ranges.range)])
    ids = ", ".join(log.anchors.ids[int(a)] for a in heard[:6]) + (
        ", ..." if len(heard) > 6 else "")
    if len(heard) < 3:
        return (f"{msg}: ranges from {len(heard)} anchor(s) only ({ids or 'none'}); "
                "a 2-D fix needs 3 anchors not on one line")
    xy = log.anchors.positions[heard, :2]
    sv = np.linalg.svd(xy - xy.mean(axis=0), compute_uv=False)
    off_line_rms = float(sv[-1]) / np.sqrt(len(heard))
    if off_line_rms < COLLINEAR_RMS_M:
        return (f"{msg}: the {len(heard)} anchors heard ({ids}) lie on one line in x, y "
                f"({off_line_rms:.2f} m RMS off it); a 2-D fix needs 3 anchors not on one line")
    return f"{msg}: {len(log.ranges)} ranges from {len(heard)} anchors ({ids})"


def with_covariance(config: Config, wanted: bool) -> Config:
    """`config` with `graph.marginal_covariances = "auto"` resolved: on where `wanted`."""
    if config.graph.marginal_covariances != "auto":
        return config
    return config.model_copy(update={"graph": config.graph.model_copy(
        update={"marginal_covariances": wanted})})


def check_classifier(config: Config) -> None:
    """Load the `[nlos] classifier` model once, if one is set, so that a missing or bad
    file is a one-line ConfigError before any log is read."""
    if config.nlos.classifier:
        from uwbfuse.positioning.nlos_classifier import load_classifier

        load_classifier(config.nlos.classifier)


def _classifier_priors(
    log: SensorLog, config: Config, streams: frozenset[str]
) -> Callable[[object], None]:
    """A function that hands an estimator the `[nlos] classifier`'s P(NLOS) per range
    (`nlos_classifier.RangePriors`; a no-op without a classifier or ranges)."""
    if not config.nlos.classifier or "uwb" not in streams or log.ranges is None:
        return lambda _est: None
    from uwbfuse.positioning.nlos_classifier import (
        RangePriors,
        load_classifier,
        set_range_priors,
    )

    model = load_classifier(config.nlos.classifier)
    p = model.predict_log(log, config)
    assert log.ranges is not None
    t, a = log.ranges.t_ns, log.ranges.anchor
    base = float(model.info.get("nlos_share", 0.5))

    def give(est: object) -> None:
        if not set_range_priors(est, RangePriors(t, a, p, base_rate=base)):
            logging.getLogger(__name__).info("%s: this method does not take the NLOS "
                                             "classifier's priors", type(est).__name__)

    return give


def estimate(
    log: SensorLog, method: Method, config: Config, progress: ProgressFn | None = None,
    covariance: bool = True,
) -> RunResult:
    """Run `method` on an already-read log (ground truth is never passed on); `progress`
    is told the seconds of log processed (see `run_streaming`); `covariance`: the poses'
    covariances are wanted (`graph.marginal_covariances = "auto"` computes them then).

    `batch` or `isam2-smoothed` whose whole-graph held-out choice picked a robust range
    model runs once more over the whole log (`whole_log_refit`)."""
    # the classifier's priors once for both passes (they differ only in [graph])
    streams = check_inputs(log, method, config)
    priors = _classifier_priors(log, config, streams)
    first = _estimate_once(log, method, config, progress, covariance, priors)
    refit = whole_log_refit(method, config, first.report, log, streams)
    if refit is None:
        return first
    second = _estimate_once(log, method, refit, None, covariance, priors)
    second.report["whole_log_refit"] = {
        "first_pass_range_model": _full_graph_report(first.report)["range_model"],
        "start_backdate_s": refit.graph.start_backdate,
        "first_pass_wall_s": first.estimate_wall_s,
    }
    second.estimate_wall_s += first.estimate_wall_s
    return second


def _full_graph_report(report: dict) -> dict:
    """The report of the whole-graph solve (batch's, or isam2-smoothed's final one)."""
    return report.get("batch") or report.get("final_smoothing") or {}


def whole_log_refit(method: Method, config: Config, report: dict, log: SensorLog,
                    streams: frozenset[str]) -> Config | None:
    """The config of the second pass of batch (or isam2-smoothed, whose final smoothing
    solves the same whole graph), or None when there is none to run.

    The graph starts where the start state is found (the heading needs some motion), and
    the ranges and odometry before it stay out. Carried back along the wheel track
    (`graph.start_backdate`), they help wherever their ranges are not classified against
    that still-poor early track: so where batch's held-out choice found a robust range
    model (no LOS/NLOS assignment) better, not the mixture (docs/results.md, "Backdated
    starts"). The second pass chooses its range model again, over the whole log (a long
    still stretch before the start can favour the mixture: room-static). Only where the
    user left both `graph.range_model` and `graph.start_backdate` at their defaults, on
    logs with wheels or an IMU to carry the start back (without wheels the IMU carries the
    attitude, a UWB fix gives the position), and where the first pass's graph started
    after the first data. `streams`: the log's streams as `check_inputs` gives them (the
    ones the estimators are built from).
    """
    g = config.graph
    fields = type(g).model_fields
    chosen = _full_graph_report(report).get("range_model") or ""
    first_kf = report.get("first_keyframe_t_ns")
    if (method not in (Method.BATCH, Method.ISAM2_SMOOTHED) or g.range_model != "auto"
            or g.start_backdate != fields["start_backdate"].default
            or not chosen.startswith("robust") or first_kf is None
            or not streams & {"wheel", "imu"}):
        return None
    t0, _ = log.time_span_ns()
    back_s = (int(first_kf) - t0) / NS_PER_S
    if back_s <= 0.0:
        return None
    # one keyframe period past the first data: the backdated start is clamped to it
    back_s += 1.0 / g.keyframe_rate
    update: dict[str, Any] = {"start_backdate": back_s}
    if method is Method.ISAM2_SMOOTHED and "wheel" not in streams:
        # without wheels the final smoothing's EM starts from isam2's own online classes,
        # which judge the backdated ranges against the still-poor early track: it keeps the
        # first pass's choice. With wheels EM starts NLOS-first (`offline.solve`), free of
        # those classes, and chooses again like batch (room-static: a long still stretch).
        update["range_model"] = chosen
    return config.model_copy(update={"graph": g.model_copy(update=update)})


def _estimate_once(
    log: SensorLog, method: Method, config: Config, progress: ProgressFn | None,
    covariance: bool, priors: Callable[[object], None],
) -> RunResult:
    """One run of `method` over the log (see `estimate`); `priors` hands an estimator the
    NLOS classifier's priors (`_classifier_priors`)."""
    config = with_covariance(config, covariance)
    streams = check_inputs(log, method, config)
    sensors_only = SensorLog(
        imu=log.imu, wheel=log.wheel, ranges=log.ranges, anchors=log.anchors,
        source=log.source, report=log.report,
        pose=log.pose if "pose" in streams else None,
    )
    primary = make_estimator(method, config, log.anchors, streams)
    # Poses from the first motion on (contract): `PreStart` answers until the method has
    # its own start (heading needs some motion) and fills a smoother's head afterwards.
    estimator = PreStart.around(primary, method, config, log.anchors, streams)
    priors(primary)
    if estimator.fallback is not None:
        priors(estimator.fallback)
    epochs = output_epochs(sensors_only, config.output.rate)
    res = run_streaming(estimator, sensors_only, epochs, progress)
    smoothed = method.spec.smoothed
    if smoothed and res.final is None and len(res.causal) == 0:
        raise EstimatorError(_never_initialised(log, method))
    if smoothed and res.final is None:
        # the log ended before the graph could start (a few seconds, no motion to fix the
        # heading): the provisional poses that isam2 writes too, said so in the report
        logging.getLogger(__name__).warning(
            "%s: method %s never started its graph; writing the provisional "
            "(causal, UWB-fix) poses", log.source, method.value)
        res.report["final_trajectory"] = ("none: the graph never started; the output is "
                                          "the provisional causal poses")
    traj = res.causal
    if smoothed and res.final is not None:
        traj = estimator.complete(res.final, res.causal, epochs)
    if len(traj) == 0:
        raise EstimatorError(_never_initialised(log, method))
    t0, t1 = log.time_span_ns()
    return RunResult(
        method=method,
        trajectory=traj,
        causal=res.causal,
        final=res.final,
        step_latency_s=res.step_latency_s,
        estimate_wall_s=res.wall_s,
        read_wall_s=0.0,
        log_duration_s=(t1 - t0) / NS_PER_S,
        report=res.report,
        read_report=log.report,
        range_classes=res.range_classes,
    )


def run_log(
    path: str | Path,
    method: Method,
    config: Config,
    tum_out: str | Path | None = None,
    mcap_out: str | Path | None = None,
    cov_out: str | Path | None = None,
    progress: ProgressFn | None = None,
    report_out: str | Path | None = None,
) -> RunResult:
    """Read the log at `path`, run `method`, write the TUM (and MCAP, covariance CSV, JSON
    run report) outputs.

    The output paths are checked before the log is read, and the outputs are written all
    or none: a failure (or an interrupt) at any step leaves no output file behind.
    """
    from uwbfuse.io.atomic import all_or_none, check_output_paths
    from uwbfuse.io.reader import read_log
    from uwbfuse.io.tum import write_tum

    outputs = {"-o": tum_out, "--mcap-out": mcap_out, "--cov-out": cov_out,
               "--report": report_out}
    check_output_paths(outputs, TrajectoryFileError)
    check_classifier(config)  # a bad model file fails before the log is read
    tic = time.perf_counter()
    sensor_log = read_log(path, config)
    read_wall = time.perf_counter() - tic
    # the graph's marginals cost time: computed (under `auto`) only for the outputs that
    # carry covariances
    result = estimate(sensor_log, method, config, progress,
                      covariance=mcap_out is not None or cov_out is not None)
    result.read_wall_s = read_wall
    with all_or_none():
        if tum_out is not None:
            write_tum(tum_out, result.trajectory)
        if mcap_out is not None:
            from uwbfuse.io.pose_mcap import write_pose_mcap

            write_pose_mcap(mcap_out, result.trajectory, method.value, sensor_log.anchors)
        if cov_out is not None:
            from uwbfuse.io.cov_csv import write_cov_csv

            write_cov_csv(cov_out, result.trajectory)
        if report_out is not None:
            from uwbfuse.report import run_report, write_report_json

            written = {k: str(v) for k, v in outputs.items() if v is not None}
            write_report_json(report_out, run_report(result, str(path), written))
    return result
