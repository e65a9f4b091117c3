# SPDX-License-Identifier: BSD-3-Clause
"""Score collision prediction against ground truth on the simulated warehouse fleet.

For every seed: simulate `warehouse-fleet` (four AGVs, one log each on one clock), estimate
each AGV's trajectory with every method, run the collision check on the estimates (and on
the ground truth itself, decimated to 10 Hz, as the predictor's own reference) with the
nominal margin and with the margin widened by k sigma (the estimator's covariance where it
gives one, else `--assumed-sigma`; `cov share`: the epochs with a known xy std), and score
it against the true footprints (`uwbfuse.safety.evaluate`): true conflicts, detection rate,
false alarms per epoch near a target, lead time. Prints a Markdown table.

    python scripts/eval_collisions.py --seeds 0,1,2 --duration 300 --jobs 2
"""

from __future__ import annotations

import argparse
import functools
import sys
import time
from concurrent.futures import ProcessPoolExecutor

import numpy as np

from uwbfuse.config import Config
from uwbfuse.estimator import Method
from uwbfuse.pipeline import estimate
from uwbfuse.safety.evaluate import FleetScore, score_fleet, truth_clearances
from uwbfuse.safety.fleet import Track, check_fleet
from uwbfuse.safety.geometry import ObstacleMap
from uwbfuse.safety.motion import motion_from_poses, position_sigma
from uwbfuse.sim.fleet import simulate_fleet
from uwbfuse.streams import PoseStream

TRUTH = "truth"
TRUTH_DECIMATE = 20  # 200 Hz ground truth -> the estimators' 10 Hz output


@functools.lru_cache(maxsize=2)
def _fleet(seed: int, duration: float) -> list:
    return simulate_fleet("warehouse-fleet", duration, seed)


def _estimate(job: tuple[int, float, int, str]) -> tuple[tuple[int, int, str], PoseStream,
                                                          float]:
    seed, duration, k, method = job
    res = _fleet(seed, duration)[k][1]
    tic = time.perf_counter()
    if method == TRUTH:
        g = res.log.ground_truth
        sl = slice(None, None, TRUTH_DECIMATE)
        traj = PoseStream(g.t_ns[sl], g.position[sl], g.quat_xyzw[sl], True)
    else:
        traj = estimate(res.log, Method(method), Config()).trajectory
    return (seed, k, method), traj, time.perf_counter() - tic


def _rmse(traj: PoseStream, gt: PoseStream) -> float:
    t = (traj.t_ns - gt.t_ns[0]).astype(float)
    own = (gt.t_ns - gt.t_ns[0]).astype(float)
    dx = traj.position[:, 0] - np.interp(t, own, gt.position[:, 0])
    dy = traj.position[:, 1] - np.interp(t, own, gt.position[:, 1])
    return float(np.sqrt(np.mean(dx * dx + dy * dy)))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="0,1,2")
    ap.add_argument("--duration", type=float, default=300.0, help="s per seed")
    ap.add_argument("--methods", default="odom,wls,ekf,isam2")
    ap.add_argument("--assumed-sigma", type=float, default=0.1,
                    help="position std where an estimator gives no covariance, m")
    ap.add_argument("--jobs", type=int, default=1, help="estimation processes")
    args = ap.parse_args(argv)
    seeds = [int(s) for s in args.seeds.split(",")]
    methods = [TRUTH, *args.methods.split(",")]
    base = Config().vehicle
    variants = {"nominal": base.model_copy(update={"sigma_factor": 0.0}),
                f"+{base.sigma_factor:g} sigma": base}
    tic = time.perf_counter()
    n_agv = len(_fleet(seeds[0], args.duration))
    jobs = [(s, args.duration, k, m) for s in seeds for m in methods for k in range(n_agv)]
    with ProcessPoolExecutor(args.jobs) as pool:
        trajs = {key: (traj, wall) for key, traj, wall in pool.map(_estimate, jobs)}
    print(f"estimated {len(jobs)} trajectories in {time.perf_counter() - tic:.0f} s",
          file=sys.stderr)

    scores: dict[tuple[str, str], FleetScore] = {}
    info: dict[str, list] = {m: [] for m in methods}
    for seed in seeds:
        fleet = _fleet(seed, args.duration)
        site = ObstacleMap.from_config(fleet[0][1].log.map)
        truth = {name: res.log.ground_truth for name, res in fleet}
        clear = truth_clearances(truth, site, base)
        for m in methods:
            tracks = []
            for k, (name, res) in enumerate(fleet):
                traj, _ = trajs[(seed, k, m)]
                known = np.isfinite(position_sigma(traj.covariance, len(traj)))
                info[m].append((_rmse(traj, res.log.ground_truth), float(known.mean())))
                tracks.append(Track(name, motion_from_poses(
                    traj, base.velocity_window, args.assumed_sigma, name=f"{m}:{name}")))
            for vname, vcfg in variants.items():
                sc = score_fleet(check_fleet(tracks, site, vcfg, use_dask=False), clear, vcfg)
                key = (m, vname)
                scores[key] = scores[key] + sc if key in scores else sc

    print(f"warehouse-fleet, seeds {args.seeds}, {args.duration:.0f} s each, 4 AGVs; "
          f"vehicle {base.length} x {base.width} m, control_delay {base.control_delay} s, "
          f"safety_margin {base.safety_margin} m; widened: covariance where given, else "
          f"{args.assumed_sigma} m\n")
    cols = ("method", "margin", "xy RMSE m", "cov share", "true conflicts", "detected",
            "detection rate", "false alarms", "near epochs", "false-alarm rate",
            "median lead s", "min lead s")
    print("| " + " | ".join(cols) + " |")
    print("|" + "|".join("---" for _ in cols) + "|")
    for m in methods:
        rmse = np.mean([r for r, _ in info[m]])
        cov = f"{np.mean([c for _, c in info[m]]):.2f}"
        for vname in variants:
            s = scores[(m, vname)]
            lead_min = f"{s.lead_s.min():.2f}" if len(s.lead_s) else ""
            print(f"| {m} | {vname} | {rmse:.3f} | {cov} | {s.conflicts} | {s.detected} | "
                  f"{s.detection_rate:.3f} | {s.false_alarms} | {s.near_epochs} | "
                  f"{s.false_alarm_rate:.3f} | {s.median_lead_s:.2f} | {lead_min} |")
    print(f"\n({time.perf_counter() - tic:.0f} s)", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
