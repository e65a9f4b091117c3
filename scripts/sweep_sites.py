# SPDX-License-Identifier: BSD-3-Clause
"""Random simulated sites: does the default config generalise beyond the named scenarios?

    python scripts/sweep_sites.py [--draws 24] [--seed 0] [--duration 60]
                                  [--methods isam2,batch,ekf,wls] [--jobs 2] [--json OUT]
                                  [--only 3,7] [--config FILE]

The named scenarios are what the project has tuned against; logs it has never seen are run
on the default config. Each draw here takes one of the scenarios' sites (room, factory,
warehouse, warehouse-nlos) and redraws what differs between real deployments (`_draw`):
speed, UWB rate, LOS noise, NLOS excess (size, spread, law), outliers and dropouts, constant
anchor offsets, wheel scale and slip, IMU grade, the sensor set (IMU / wheels / UWB
subsets), the standstill at the start, a UWB outage, a tag lever arm and a rotated IMU (the
last two given to the estimator in `[extrinsics]`, as a user would), and the map frame's
turn against the route (`turned_map`: the named routes all start facing +x). Every method then runs
on the default config (or `--config FILE`'s, to compare a setting across the draws) and is
scored by 2-D ATE RMSE (m, no alignment).

Printed: one row per draw (what was drawn, each method's ATE) with a flag where the graph
(`isam2`, `isam2-smoothed`, `batch`) is worse than the best baseline run (`ekf`, `ukf`,
`wls`, `lkf`) by more than 10 %, then per graph method the number of draws it loses and
the geometric mean and median of its ratio to the best baseline (a few outage draws whose
errors are metres carry the geometric mean: judge a change by both). A flagged draw is a
lead to a defect: re-run it with `--only N` (the draws are reproducible from `--seed`).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation
from sim_scenarios import ate_by_method  # scripts/, beside this file

from uwbfuse.config import Config, load_config
from uwbfuse.errors import SimulationError
from uwbfuse.estimator import Method
from uwbfuse.sim.simulator import SimResult, simulate_with_truth
from uwbfuse.streams import PoseStream

SITES = ("room", "factory", "warehouse", "warehouse-nlos")
GRAPH_METHODS = ("isam2", "batch", "isam2-smoothed")
LOSS_MARGIN = 1.10  # a graph row is flagged above 1.1x the best baseline (ATE ratio)
STREAM_SETS = (("imu", "wheel", "uwb"), ("wheel", "uwb"), ("imu", "uwb"), ("uwb",))
STREAM_WEIGHTS = (0.5, 0.2, 0.2, 0.1)


def _log_uniform(rng: np.random.Generator, lo: float, hi: float) -> float:
    return float(math.exp(rng.uniform(math.log(lo), math.log(hi))))


def _draw(seed: int, draw: int, duration_s: float) -> tuple[str, dict[str, Any], dict[str, Any]]:
    """Draw `draw` of sweep `seed`: (site, simulator overrides, `[extrinsics]` of the config).
    Ranges are what commercial UWB radios, AGV encoders and MEMS IMUs show (physical,
    not tuned to a result)."""
    rng = np.random.default_rng(np.random.SeedSequence([seed, draw]))
    site = SITES[int(rng.integers(len(SITES)))]
    o: dict[str, Any] = {
        "speed": _log_uniform(rng, 0.15, 1.2),  # m/s: slow tugs to fast AGVs
        "uwb_rate": _log_uniform(rng, 8.0, 100.0),  # ranges/s over all anchors
        "los_sigma": _log_uniform(rng, 0.015, 0.12),  # m: DW1000-class to noisy radios
        "nlos_mean": _log_uniform(rng, 0.05, 0.6),  # m: thin racks to concrete
        "nlos_std": _log_uniform(rng, 0.05, 0.3),  # m
        "nlos_excess": str(rng.choice(["gaussian", "lognormal"])),
        "outlier_prob": float(rng.uniform(0.0, 0.03)),
        "dropout_prob": float(rng.uniform(0.0, 0.1)),
        "nlos_dropout_prob": float(rng.uniform(0.0, 0.3)),
        "anchor_offset_max": float(rng.choice([0.0, rng.uniform(0.02, 0.15)])),  # m
        "wheel_scale_sigma": _log_uniform(rng, 0.003, 0.04),
        "slip_rate": float(rng.uniform(0.0, 1.0 / 20.0)),  # episodes per second of motion
        "still_start_s": float(rng.choice([0.0, 2.0, 5.0])),
    }
    grade = _log_uniform(rng, 1.0, 10.0)  # IMU noise and bias relative to an MPU6050
    o.update(accel_noise_density=4.0e-3 * grade, gyro_noise_density=3.0e-4 * grade,
             accel_bias_sigma=0.05 * min(grade, 4.0), gyro_bias_sigma=0.005 * min(grade, 4.0))
    o["streams"] = STREAM_SETS[int(rng.choice(len(STREAM_SETS), p=STREAM_WEIGHTS))]
    if rng.uniform() < 0.25:  # a UWB outage of 5-15 s inside the log
        length = float(rng.uniform(5.0, 15.0))
        begin = float(rng.uniform(0.3, 0.7)) * (duration_s - length)
        o["outage"] = (begin, begin + length)
    extrinsics: dict[str, Any] = {}
    if rng.uniform() < 0.3:  # the tag on a mast, off the base's centre
        tag = (float(rng.uniform(-0.3, 0.3)), float(rng.uniform(-0.2, 0.2)),
               float(rng.uniform(0.2, 1.0)))
        o["tag_in_base"] = extrinsics["tag_in_base"] = tag
    if rng.uniform() < 0.2:  # the IMU mounted turned about z
        yaw = float(rng.choice([0.5, 1.0, -0.5])) * math.pi
        imu = (0.1, 0.0, 0.2, 0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2))
        o["imu_in_base"] = extrinsics["imu_in_base"] = imu
    # rad: the map frame turned about z (`turned_map`): every named route starts facing +x,
    # a real site's map has no such relation to where the vehicle starts
    o["map_yaw"] = float(rng.uniform(-math.pi, math.pi))
    return site, o, extrinsics


def _describe(site: str, o: dict[str, Any]) -> str:
    parts = [site, "+".join(o["streams"]), f"v{o['speed']:.2f}", f"{o['uwb_rate']:.0f}Hz",
             f"los{o['los_sigma'] * 100:.1f}cm",
             f"nlos{o['nlos_mean'] * 100:.0f}/{o['nlos_std'] * 100:.0f}cm{o['nlos_excess'][0]}",
             f"out{o['outlier_prob'] * 100:.1f}%"]
    if o["anchor_offset_max"]:
        parts.append(f"off{o['anchor_offset_max'] * 100:.0f}cm")
    if "outage" in o:
        parts.append(f"outage{o['outage'][1] - o['outage'][0]:.0f}s")
    if "tag_in_base" in o:
        parts.append("lever")
    if "imu_in_base" in o:
        parts.append("imu-turned")
    parts.append(f"still{o['still_start_s']:.0f}s")
    if "map_yaw" in o:
        parts.append(f"map{math.degrees(o['map_yaw']):+.0f}deg")
    return " ".join(parts)


def simulate_draw(seed: int, draw: int, duration_s: float
                  ) -> tuple[str, dict[str, Any], dict[str, Any], SimResult]:
    """Draw `draw` of sweep `seed` simulated (simulator seed `draw`): (site, overrides as
    used, `[extrinsics]`, the log with its truth). A short route cannot reach every speed:
    the drawn speed is lowered by a fifth until it can."""
    site, o, extrinsics = _draw(seed, draw, duration_s)
    sim_o = {k: v for k, v in o.items() if k != "map_yaw"}
    while True:
        try:
            sim = simulate_with_truth(site, duration_s, seed=draw, **sim_o)
            return site, o, extrinsics, turned_map(sim, o["map_yaw"])
        except SimulationError as e:
            if "cruise speed" not in str(e) or sim_o["speed"] < 0.05:
                raise
            o["speed"] = sim_o["speed"] = sim_o["speed"] * 0.8


def turned_map(sim: SimResult, yaw: float) -> SimResult:
    """`sim` with its map frame turned by `yaw` (rad) about z: the anchors, the ground
    truth, the localiser's poses (and their covariances), the electronic map and the true
    velocity and yaw in the turned frame; the body-frame streams (IMU, wheels) and the
    ranges are unchanged. `sim.scenario` keeps the route's own frame."""
    rot = Rotation.from_euler("z", yaw)
    r_mat = rot.as_matrix()
    log = sim.log

    def poses(p: PoseStream | None) -> PoseStream | None:
        if p is None:
            return None
        cov = p.covariance
        if cov is not None:
            r6 = np.zeros((6, 6))
            r6[:3, :3] = r6[3:, 3:] = r_mat
            cov = r6 @ cov @ r6.T
        return replace(p, position=rot.apply(p.position),
                       quat_xyzw=(rot * Rotation.from_quat(p.quat_xyzw)).as_quat(),
                       covariance=cov)

    def points(ring: list[Any]) -> list[tuple[float, float]]:
        return [tuple(float(c) for c in r_mat[:2, :2] @ np.asarray(q, float)) for q in ring]

    site_map = log.map
    if site_map is not None:
        site_map = site_map.model_copy(update={
            "obstacles": [points(poly) for poly in site_map.obstacles],
            "walls": [points(line) for line in site_map.walls],
            "boundary": points(site_map.boundary)})
    turned = replace(log, anchors=replace(log.anchors, positions=rot.apply(log.anchors.positions)),
                     ground_truth=poses(log.ground_truth), pose=poses(log.pose), map=site_map)
    return replace(sim, log=turned, velocity=rot.apply(sim.velocity), yaw=sim.yaw + yaw)


def _one(seed: int, draw: int, duration_s: float, methods: list[str],
         config_path: str = "") -> dict[str, Any]:
    """One draw: its description and each method's 2-D ATE RMSE (m; NaN: the method failed
    or is not defined for the drawn sensor set)."""
    site, o, extrinsics, sim = simulate_draw(seed, draw, duration_s)
    log = sim.log
    cfg = load_config(Path(config_path)) if config_path else Config()
    if extrinsics:
        cfg = cfg.model_copy(update={"extrinsics": cfg.extrinsics.model_copy(update=extrinsics)})
    ate = ate_by_method(log, methods, cfg, f"draw {draw}")
    return {"draw": draw, "site": site, "describe": _describe(site, o), "ate": ate,
            "overrides": {k: v for k, v in o.items()}}


def _best_baseline(ate: dict[str, float]) -> float:
    base = [v for m, v in ate.items() if m not in GRAPH_METHODS and math.isfinite(v)]
    return min(base) if base else float("nan")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--draws", type=int, default=24)
    p.add_argument("--seed", type=int, default=0, help="the sweep's seed (which sites)")
    p.add_argument("--duration", type=float, default=60.0, help="log length, s")
    p.add_argument("--methods", default="isam2,batch,ekf,wls")
    p.add_argument("--jobs", type=int, default=1)
    p.add_argument("--only", default="", help="comma-separated draw numbers")
    p.add_argument("--json", default="", help="write every draw's figures here")
    p.add_argument("--config", default="", help="TOML config for every method (default: none)")
    args = p.parse_args(argv)
    methods = args.methods.split(",")
    if args.config:
        load_config(Path(args.config))  # a bad config fails here, before any simulation
    for m in methods:
        Method(m)  # a misspelt method fails here, before any simulation
    draws = ([int(d) for d in args.only.split(",")] if args.only
             else list(range(args.draws)))
    with ProcessPoolExecutor(max_workers=max(1, args.jobs)) as pool:
        rows = list(pool.map(_one, [args.seed] * len(draws), draws,
                             [args.duration] * len(draws), [methods] * len(draws),
                             [args.config] * len(draws)))
    graph = [m for m in methods if m in GRAPH_METHODS]
    print(f"sweep seed {args.seed}, {len(draws)} draws x {args.duration:g} s, "
          f"{'config ' + args.config if args.config else 'default config'} "
          "(2-D ATE RMSE, m; ! = graph above 1.1x the best baseline)")
    print("| draw | site and sensors | " + " | ".join(methods) + " |")
    print("|---|---|" + "---|" * len(methods))
    ratios: dict[str, list[float]] = {m: [] for m in graph}
    for r in rows:
        best = _best_baseline(r["ate"])
        cells = []
        for m in methods:
            v = r["ate"][m]
            flag = ""
            if m in graph and math.isfinite(v) and math.isfinite(best):
                ratios[m].append(v / best)
                flag = " !" if v > LOSS_MARGIN * best else ""
            cells.append(f"{v:.3f}{flag}")
        print(f"| {r['draw']} | {r['describe']} | " + " | ".join(cells) + " |")
    for m in graph:
        x = np.array(ratios[m])
        if len(x):
            print(f"{m}: worse than 1.1x the best baseline on {int(np.sum(x > LOSS_MARGIN))} "
                  f"of {len(x)} draws; ratio geometric mean {float(np.exp(np.mean(np.log(x)))):.2f}"
                  f", median {float(np.median(x)):.2f}, worst {float(np.max(x)):.2f}")
    if args.json:
        with open(args.json, "w", encoding="utf-8") as f:
            json.dump(rows, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
