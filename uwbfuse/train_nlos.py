# SPDX-License-Identifier: BSD-3-Clause
"""`uwbfuse train-nlos`: train the NLOS random forest on logs with ground truth.

Each range of each log is labelled from ground truth (`--gt` TUM files, one per log, else
the log's ground-truth topic): NLOS when |measured - true range| exceeds the label
threshold (`constants.LABEL_THRESHOLD_M`). The features are
`nlos_classifier.range_features`, computed as at run time; the signal-quality features are
used when every log carries them. The model is written as a skops file that `[nlos]
classifier` loads.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from uwbfuse.config import load_config
from uwbfuse.constants import LABEL_THRESHOLD_M
from uwbfuse.errors import ConfigError, EstimatorError
from uwbfuse.positioning.nlos_classifier import (
    NlosClassifier,
    log_features,
    range_labels,
    train_classifier,
)

log = logging.getLogger(__name__)

MIN_RANGES_PER_CLASS = 20  # a forest needs examples of both classes to separate them


@dataclass(frozen=True)
class TrainSummary:
    """What `train_nlos` trained on: labelled ranges, the NLOS share, the features."""

    model: NlosClassifier
    n_ranges: int
    n_nlos: int
    n_unlabelled: int
    features: tuple[str, ...]


def train_nlos(
    logs: list[str | Path], out: str | Path, *, config_path: str | Path | None = None,
    gts: list[str | Path] | None = None, n_trees: int = 100,
    threshold: float = LABEL_THRESHOLD_M, seed: int = 0,
) -> TrainSummary:
    """Train on `logs` (with `gts`, one TUM per log, if given) and write the model to
    `out`. Raises ConfigError/EstimatorError (one line) for bad input."""
    from uwbfuse.io.reader import read_log
    from uwbfuse.io.tum import read_tum

    if gts and len(gts) != len(logs):
        raise ConfigError(f"--gt: {len(gts)} ground-truth files for {len(logs)} logs (give "
                          "one per log, in the same order)")
    if not threshold > 0:
        raise ConfigError(f"--threshold must be positive, got {threshold}")
    config = load_config(config_path)
    xs, ys, names_all = [], [], []
    unlabelled = 0
    for i, path in enumerate(logs):
        sl = read_log(path, config)
        if gts:
            sl.ground_truth = read_tum(gts[i])
        if sl.ground_truth is None or len(sl.ground_truth) < 2:
            raise EstimatorError(f"{path}: no ground truth to label the ranges (the log's "
                                 f"topic {config.topics.ground_truth!r} is absent; give --gt)")
        x, names = log_features(sl, config)
        y, _ = range_labels(sl, config, threshold)
        keep = y >= 0
        unlabelled += int((~keep).sum())
        xs.append(x[keep])
        ys.append(y[keep])
        names_all.append(names)
    common = tuple(f for f in names_all[0] if all(f in n for n in names_all))
    if any(n != common for n in names_all):
        log.warning("train-nlos: not every log carries signal quality; training on %s",
                    ", ".join(common))
    x = np.concatenate([xi[:, [n.index(f) for f in common]]
                        for xi, n in zip(xs, names_all, strict=True)])
    y = np.concatenate(ys)
    n_nlos = int(y.sum())
    if n_nlos < MIN_RANGES_PER_CLASS or len(y) - n_nlos < MIN_RANGES_PER_CLASS:
        raise EstimatorError(
            f"train-nlos: {n_nlos} NLOS and {len(y) - n_nlos} LOS ranges labelled (threshold "
            f"{threshold} m); each class needs at least {MIN_RANGES_PER_CLASS}")
    info = {"logs": [str(p) for p in logs], "ranges": len(y), "nlos_share": n_nlos / len(y)}
    model = train_classifier(x, y, common, n_trees=n_trees, seed=seed,
                             label_threshold=threshold, info=info)
    model.save(out)
    return TrainSummary(model, len(y), n_nlos, unlabelled, common)
