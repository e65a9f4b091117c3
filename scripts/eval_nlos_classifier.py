# SPDX-License-Identifier: BSD-3-Clause
"""Evaluate the learned NLOS classifier (issue 16 part 4); print Markdown tables.

    python scripts/eval_nlos_classifier.py [--duration 60] [--train-seeds 100,101,102]
        [--test-seeds 200,201] [--trees 100] [--no-ate]

1. Held-out simulated seeds (warehouse and warehouse-nlos with signal quality): ROC AUC
   and accuracy (P > 0.5) of a forest trained on other seeds, with all features and with
   the residual features alone; labels |measured - true range| > 0.15 m (as `train-nlos`
   labels), and for reference against the simulator's own NLOS mask.
2. Real logs with ground truth and anchors (labyrinth, ISAS-Walk1 in the anchor frame):
   the residual-only forest trained on simulation, and a two-fold split in time of the
   log itself (first half trains, second half tests, and the other way round).
3. ATE (2-D RMSE, m) of wls, isam2 and batch on held-out seeds without and with `[nlos]
   classifier` (the forest with signal quality).

Reads ../shared/data/real beside the repository (skipped when absent).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from sklearn.metrics import accuracy_score, roc_auc_score

from uwbfuse.config import Config, load_config
from uwbfuse.estimator import Method
from uwbfuse.eval.evaluate import evaluate
from uwbfuse.io.reader import read_log
from uwbfuse.io.tum import read_tum
from uwbfuse.pipeline import estimate
from uwbfuse.positioning.nlos_classifier import (
    RESIDUAL_FEATURES,
    NlosClassifier,
    log_features,
    range_labels,
    train_classifier,
)
from uwbfuse.sim.simulator import SimResult, simulate_with_truth
from uwbfuse.streams import SensorLog

REAL = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "real"
SCENARIOS = ("warehouse", "warehouse-nlos")


def _sim(scenario: str, seed: int, duration: float) -> SimResult:
    return simulate_with_truth(scenario, duration, seed, signal_quality=True)


def _xy(log: SensorLog, cfg: Config) -> tuple[np.ndarray, np.ndarray, tuple[str, ...]]:
    x, names = log_features(log, cfg)
    y, _ = range_labels(log, cfg)
    return x, y, names


def _cols(x: np.ndarray, names: tuple[str, ...], want: tuple[str, ...]) -> np.ndarray:
    return x[:, [names.index(f) for f in want]]


def _scores(model: NlosClassifier, x: np.ndarray, y: np.ndarray) -> tuple[float, float]:
    p = model.predict(x)
    ok = y >= 0
    return (float(roc_auc_score(y[ok], p[ok])), float(accuracy_score(y[ok], p[ok] > 0.5)))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--duration", type=float, default=60.0)
    ap.add_argument("--train-seeds", default="100,101,102")
    ap.add_argument("--test-seeds", default="200,201")
    ap.add_argument("--trees", type=int, default=100)
    ap.add_argument("--no-ate", action="store_true")
    args = ap.parse_args(argv)
    train_seeds = [int(s) for s in args.train_seeds.split(",")]
    test_seeds = [int(s) for s in args.test_seeds.split(",")]
    cfg = Config()

    # ---- training on simulated seeds
    xs, ys = [], []
    names: tuple[str, ...] = ()
    for sc in SCENARIOS:
        for seed in train_seeds:
            x, y, names = _xy(_sim(sc, seed, args.duration).log, cfg)
            xs.append(x[y >= 0])
            ys.append(y[y >= 0])
    x_tr, y_tr = np.concatenate(xs), np.concatenate(ys)
    full = train_classifier(x_tr, y_tr, names, n_trees=args.trees,
                            info={"nlos_share": float(y_tr.mean())})
    resid = train_classifier(_cols(x_tr, names, RESIDUAL_FEATURES), y_tr, RESIDUAL_FEATURES,
                             n_trees=args.trees, info={"nlos_share": float(y_tr.mean())})
    print(f"# trained on {len(y_tr)} simulated ranges ({y_tr.mean():.1%} NLOS), seeds "
          f"{train_seeds}, {args.duration:.0f} s each", file=sys.stderr)

    # ---- 1. held-out simulated seeds
    print("\n### Held-out simulated seeds\n")
    print("| scenario | seed | ranges | NLOS share (|e| > 0.15 m) | AUC all features | "
          "acc all | AUC residual only | acc residual | AUC all vs sim NLOS mask |")
    print("|---|---|---|---|---|---|---|---|---|")
    tests: list[tuple[str, int, SimResult]] = []
    for sc in SCENARIOS:
        for seed in test_seeds:
            sim = _sim(sc, seed, args.duration)
            tests.append((sc, seed, sim))
            x, y, nm = _xy(sim.log, cfg)
            a_full, acc_full = _scores(full, x, y)
            a_res, acc_res = _scores(resid, _cols(x, nm, RESIDUAL_FEATURES), y)
            a_mask = float(roc_auc_score(sim.nlos.astype(int), full.predict(x)))
            print(f"| {sc} | {seed} | {len(y)} | {np.mean(y[y >= 0]):.2f} | {a_full:.3f} | "
                  f"{acc_full:.3f} | {a_res:.3f} | {acc_res:.3f} | {a_mask:.3f} |", flush=True)

    # ---- 2. real logs
    reals = []
    if (REAL / "labyrinth").exists():
        c = load_config(REAL / "labyrinth" / "config.toml")
        reals.append(("labyrinth", read_log(REAL / "labyrinth" / "labyrinth.mcap", c), c))
    if (REAL / "isas-walk1").exists():
        c = load_config(REAL / "isas-walk1" / "config.toml")
        lg = read_log(REAL / "isas-walk1" / "ISAS-Walk1", c)
        lg.ground_truth = read_tum(REAL / "isas-walk1" / "gt_anchor_frame.tum")
        reals.append(("isas-walk1 (gt_anchor_frame)", lg, c))
    if reals:
        print("\n### Real logs (residual features; labels |e| > 0.15 m)\n")
        print("| log | ranges | NLOS share | AUC sim-trained | acc sim-trained | "
              "AUC 2-fold in time | acc 2-fold in time |")
        print("|---|---|---|---|---|---|---|")
    for name, lg, c in reals:
        x, y, nm = _xy(lg, c)
        xr = _cols(x, nm, RESIDUAL_FEATURES)
        ok = y >= 0
        a_sim, acc_sim = _scores(resid, xr, y)
        half = np.zeros(len(y), dtype=bool)
        half[: len(y) // 2] = True
        p = np.full(len(y), np.nan)
        for tr in (half, ~half):
            sel = tr & ok
            m = train_classifier(xr[sel], y[sel], RESIDUAL_FEATURES, n_trees=args.trees)
            p[~tr] = m.predict(xr[~tr])
        a_cv = float(roc_auc_score(y[ok], p[ok]))
        acc_cv = float(accuracy_score(y[ok], p[ok] > 0.5))
        print(f"| {name} | {int(ok.sum())} | {np.mean(y[ok]):.2f} | {a_sim:.3f} | "
              f"{acc_sim:.3f} | {a_cv:.3f} | {acc_cv:.3f} |", flush=True)

    # ---- 3. ATE with and without the classifier
    if args.no_ate:
        return 0
    with tempfile.TemporaryDirectory() as tmp:
        model_path = Path(tmp) / "nlos.skops"
        full.save(model_path)
        with_clf = Config(nlos={"classifier": str(model_path)})
        methods = (Method.WLS, Method.ISAM2, Method.BATCH)
        print("\n### ATE 2-D RMSE (m) without / with `[nlos] classifier`\n")
        print("| scenario | seed | " + " | ".join(f"{m.value} without | {m.value} with"
                                                   for m in methods) + " |")
        print("|---|---|" + "---|---|" * len(methods))
        for sc, seed, sim in tests:
            cells = []
            for m in methods:
                for c in (cfg, with_clf):
                    tic = time.perf_counter()
                    res = estimate(sim.log, m, c, covariance=False)
                    ev = evaluate(res.trajectory, sim.log.ground_truth, max_dt=0.05)
                    cells.append(f"{ev.ate_2d.rmse:.3f}")
                    print(f"# {sc} {seed} {m.value} {'with' if c is with_clf else 'without'}"
                          f": {time.perf_counter() - tic:.1f} s", file=sys.stderr)
            print(f"| {sc} | {seed} | " + " | ".join(cells) + " |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
