# SPDX-License-Identifier: BSD-3-Clause
"""`uwbfuse eval` as a library function: read the two trajectories, then `evaluate`."""

from __future__ import annotations

from pathlib import Path

from uwbfuse.config import Config, load_config
from uwbfuse.errors import EvaluationError
from uwbfuse.eval.evaluate import EvalResult, evaluate
from uwbfuse.io.tum import read_tum
from uwbfuse.streams import PoseStream


def is_log_path(path: str | Path) -> bool:
    """True for a LOG argument (an .mcap or .db3 file or a rosbag2 directory), False for TUM."""
    p = Path(path)
    return p.is_dir() or p.suffix.lower() in (".mcap", ".db3")


def read_ground_truth(gt: str | Path, config: Config | None = None) -> PoseStream:
    """Ground truth from a TUM file, or from a LOG's ground-truth topic (config `[topics]`).

    Raises EvaluationError naming the topic when the log has no ground truth.
    """
    if not is_log_path(gt):
        return read_tum(gt)
    from uwbfuse.io.reader import read_log

    config = config or Config()
    log = read_log(gt, config)
    if log.ground_truth is None or len(log.ground_truth) == 0:
        raise EvaluationError(
            f"{gt}: no ground truth on topic {config.topics.ground_truth!r} "
            "(set [topics] ground_truth in --config, or pass a TUM file to --gt)"
        )
    return log.ground_truth


def evaluate_files(
    est_path: str | Path,
    gt: str | Path,
    *,
    config_path: str | Path | None = None,
    align: str = "none",
    max_dt: float = 0.02,
) -> EvalResult:
    """Score the TUM trajectory `est_path` against `gt` (a TUM file or a LOG).

    `config_path` gives the topics when `gt` is a log. Errors: TrajectoryFileError for a
    bad TUM file, LogReadError for a bad log, EvaluationError when scoring is impossible.
    """
    config = load_config(config_path)
    est = read_tum(est_path)
    truth = read_ground_truth(gt, config)
    gt_name = f"{gt} ({config.topics.ground_truth})" if is_log_path(gt) else str(gt)
    return evaluate(
        est, truth, align=align, max_dt=max_dt, est_name=str(est_path), gt_name=gt_name
    )


def export_ground_truth(
    gt: str | Path, out: str | Path, *, config_path: str | Path | None = None
) -> int:
    """Write the ground truth of `gt` (a LOG's ground-truth topic, or a TUM file) to the TUM
    file `out` (base frame in the map frame), for evo and other tools; the number of poses."""
    from uwbfuse.io.tum import write_tum

    truth = read_ground_truth(gt, load_config(config_path))
    write_tum(out, truth)
    return len(truth)
