# SPDX-License-Identifier: BSD-3-Clause
"""Time the collision check on a large fleet: N AGVs x M minutes of 10 Hz trajectories.

The tracks are the warehouse-fleet routes (cycled, each AGV with its own start delay)
with 5 cm of white position noise, as an estimate would have. Rows: the plain loop in this
process, the Dask path on a local cluster of `--workers` processes (cluster start
included), and a reference row: a fixed shapely workload (100 000 rectangle-to-rectangle
distances) timed in the same run, so that times from different machines and days can be
compared as multiples of it.

    python scripts/bench_collisions.py --vehicles 10 --minutes 10 --workers 2
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np
import shapely

from uwbfuse.config import Config
from uwbfuse.safety.fleet import Track, check_fleet
from uwbfuse.safety.geometry import ObstacleMap
from uwbfuse.safety.motion import motion_from_poses
from uwbfuse.sim.fleet import WAREHOUSE_FLEET
from uwbfuse.sim.simulator import site_map
from uwbfuse.sim.trajectory import MotionParams, build_timeline, evaluate
from uwbfuse.streams import NS_PER_S, PoseStream

RATE_HZ = 10.0
NOISE_M = 0.05


def fleet_tracks(n: int, minutes: float, seed: int = 0) -> list[PoseStream]:
    """`n` noisy 10 Hz tracks on the warehouse-fleet routes, one clock."""
    rng = np.random.default_rng(seed)
    duration = 60.0 * minutes
    t = np.arange(0.0, duration, 1.0 / RATE_HZ)
    out = []
    for k in range(n):
        sc = WAREHOUSE_FLEET.vehicles[k % len(WAREHOUSE_FLEET.vehicles)][1]
        mp = MotionParams(sc.speed * (1.0 + 0.03 * ((k // 4) % 4)), sc.accel, sc.spin_rate)
        tl = build_timeline(list(sc.route), sc.start, mp, duration, 2.0 + (7.0 * k) % 120.0)
        kin = evaluate(tl, t)
        pos = np.column_stack([kin.position + rng.normal(0, NOISE_M, kin.position.shape),
                               np.zeros(len(t))])
        yaw = kin.yaw + rng.normal(0, 0.02, len(t))
        q = np.column_stack([np.zeros((len(t), 2)), np.sin(0.5 * yaw), np.cos(0.5 * yaw)])
        out.append(PoseStream((t * NS_PER_S).astype(np.int64), pos, q, True))
    return out


def reference_workload() -> float:
    """Seconds for 100 000 shapely distances between rotated rectangles (fixed seed)."""
    rng = np.random.default_rng(1)
    n = 100_000
    c = rng.uniform(0, 40, (2, n, 2))
    a = rng.uniform(0, np.pi, (2, n))
    base = np.array([[-0.5, -0.3], [0.5, -0.3], [0.5, 0.3], [-0.5, 0.3]])
    geoms = []
    for i in range(2):
        cs, sn = np.cos(a[i])[:, None], np.sin(a[i])[:, None]
        x = c[i, :, None, 0] + cs * base[:, 0] - sn * base[:, 1]
        y = c[i, :, None, 1] + sn * base[:, 0] + cs * base[:, 1]
        geoms.append(shapely.polygons(np.stack([x, y], axis=-1)))
    tic = time.perf_counter()
    shapely.distance(geoms[0], geoms[1])
    return time.perf_counter() - tic


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--vehicles", type=int, default=10)
    ap.add_argument("--minutes", type=float, default=10.0)
    ap.add_argument("--workers", type=int, default=2, help="Dask worker processes")
    ap.add_argument("--no-dask", action="store_true")
    args = ap.parse_args(argv)
    cfg = Config()
    site = ObstacleMap.from_config(site_map(WAREHOUSE_FLEET.vehicles[0][1]))
    poses = fleet_tracks(args.vehicles, args.minutes)
    n_epochs = sum(len(p) for p in poses)
    n_pairs = args.vehicles * (args.vehicles - 1) // 2

    rows = []
    tic = time.perf_counter()
    tracks = [Track(f"agv{k}", motion_from_poses(p, cfg.vehicle.velocity_window))
              for k, p in enumerate(poses)]
    prep = time.perf_counter() - tic
    paths = [("loop", False)] + ([] if args.no_dask else [("dask", True)])
    for label, dask in paths:
        tic = time.perf_counter()
        checks = check_fleet(tracks, site, cfg.vehicle, use_dask=dask, workers=args.workers)
        wall = time.perf_counter() - tic + prep
        events = sum(int(np.count_nonzero(c.kind)) for c in checks)
        rows.append((label if not dask else f"dask ({args.workers} workers)", wall, events))
    ref = reference_workload()

    print(f"{args.vehicles} AGVs x {args.minutes:g} min at {RATE_HZ:g} Hz: {n_epochs} epochs, "
          f"{n_pairs} pairs, {len(site)} obstacles; control_delay "
          f"{cfg.vehicle.control_delay} s, {cfg.vehicle.prediction_steps} slots\n")
    print("| path | wall s | epochs/s | non-clear epochs | x ref |")
    print("|---|---|---|---|---|")
    for label, wall, events in rows:
        print(f"| {label} | {wall:.2f} | {n_epochs / wall:.0f} | {events} | {wall / ref:.1f} |")
    print(f"| reference: 100k shapely rectangle distances | {ref:.3f} | | | 1.0 |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
