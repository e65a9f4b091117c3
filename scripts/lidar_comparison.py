# SPDX-License-Identifier: BSD-3-Clause
"""The UKF paper's comparison (seeds/agv-odom-imu-lidar-uwb-ukf.txt, sec. 5): IMU + odometer
+ LiDAR against IMU + odometer + LiDAR + UWB, on the simulated `warehouse-lidar` scenario.

    python scripts/lidar_comparison.py [--seeds 3] [--duration 90] [--methods ukf,ekf,isam2,batch]
                                       [--pose-corr 0.0]

Per seed the same simulated log is run twice per method: as simulated, and with its UWB
ranges removed (the log's other streams unchanged). Prints a Markdown table of the 2-D ATE
RMSE (mean and worst over the seeds) for docs/results.md, and the graph's ATE against the
ukf's. Then batch with and without the localiser's wrong matches (the same seeds with
`pose_wrong_rate = 0`: every other draw is the same): the largest 2-D distance between the
two batch trajectories.
"""

from __future__ import annotations

import argparse
import dataclasses

import numpy as np

from uwbfuse.config import Config
from uwbfuse.estimator import Method
from uwbfuse.eval.evaluate import evaluate
from uwbfuse.pipeline import estimate
from uwbfuse.sim.simulator import simulate
from uwbfuse.streams import SensorLog


def ate(log: SensorLog, method: Method) -> tuple[float, object]:
    res = estimate(log, method, Config(), covariance=False)
    assert log.ground_truth is not None
    return evaluate(res.trajectory, log.ground_truth).ate_2d.rmse, res.trajectory


def compare(seeds: int, duration: float, methods: list[Method], verbose: bool = False,
            **overrides: float) -> dict[tuple[Method, bool], list[float]]:
    """2-D ATE RMSE (m) per (method, with UWB) over seeds 1..`seeds` of `warehouse-lidar`
    (`duration` s, scenario `overrides`): each log as simulated and with its ranges removed."""
    rows: dict[tuple[Method, bool], list[float]] = {}
    for seed in range(1, seeds + 1):
        log = simulate("warehouse-lidar", duration, seed, **overrides)
        no_uwb = dataclasses.replace(log, ranges=None)
        for m in methods:
            for with_uwb, lg in ((False, no_uwb), (True, log)):
                e, _ = ate(lg, m)
                rows.setdefault((m, with_uwb), []).append(e)
                if verbose:
                    print(f"seed {seed} {m.value:6s} {'+uwb' if with_uwb else 'lidar'}: "
                          f"{e:.4f} m", flush=True)
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--duration", type=float, default=90.0)
    ap.add_argument("--methods", default="ukf,ekf,isam2,batch")
    ap.add_argument("--pose-corr", type=float, default=None,
                    help="override the scenario's slow share of the LiDAR noise (0: white)")
    a = ap.parse_args()
    kw = {} if a.pose_corr is None else {"pose_corr": a.pose_corr}
    methods = [Method(m) for m in a.methods.split(",")]
    rows = compare(a.seeds, a.duration, methods, verbose=True, **kw)
    print()
    print("| method | IMU+odo+LiDAR ATE m (mean / worst) | +UWB ATE m (mean / worst) | "
          "change |")
    print("|---|---|---|---|")
    for m in methods:
        lo, hi = np.array(rows[(m, False)]), np.array(rows[(m, True)])
        print(f"| {m.value} | {lo.mean():.4f} / {lo.max():.4f} | {hi.mean():.4f} / "
              f"{hi.max():.4f} | {100 * (hi.mean() / lo.mean() - 1):+.0f} % |")
    if Method.UKF in methods:
        ukf = np.mean(rows[(Method.UKF, True)])
        for m in (Method.ISAM2, Method.BATCH):
            if m in methods:
                rel = 100 * (np.mean(rows[(m, True)]) / ukf - 1)
                print(f"{m.value} vs ukf (+UWB): {rel:+.0f} %")
    if Method.BATCH in methods:
        for seed in range(1, a.seeds + 1):
            _, with_wrong = ate(simulate("warehouse-lidar", a.duration, seed, **kw),
                                Method.BATCH)
            _, clean = ate(simulate("warehouse-lidar", a.duration, seed, pose_wrong_rate=0.0,
                                    **kw), Method.BATCH)
            n = min(len(with_wrong.t_ns), len(clean.t_ns))
            assert np.array_equal(with_wrong.t_ns[:n], clean.t_ns[:n])
            d = np.linalg.norm(with_wrong.position[:n, :2] - clean.position[:n, :2], axis=1)
            print(f"seed {seed}: batch moved by the wrong matches: max {d.max():.4f} m, "
                  f"RMS {np.sqrt(np.mean(d**2)):.4f} m")


if __name__ == "__main__":
    main()
