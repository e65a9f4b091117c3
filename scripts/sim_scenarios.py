# SPDX-License-Identifier: BSD-3-Clause
"""Every simulated scenario, a few seeds, chosen methods; print a Markdown table of 2-D ATE.

    python scripts/sim_scenarios.py [--methods batch,isam2,ekf,ukf,wls] [--seeds 0,1,2]
                                    [--duration 60] [--scenarios warehouse,...] [--jobs 2]
                                    [--anchor-offset-max 0.15] [--nlos-excess lognormal]

The standard check that a change does not cost the simulations: default config, seeds
0..2 x 60 s of `warehouse`, `warehouse-nlos`, `factory`, `room` and `room-static`; each cell
is the mean over the seeds with the per-seed figures in brackets (2-D ATE RMSE, m, no
alignment). `--jobs N` runs the (scenario, seed) cells in N processes.
`--anchor-offset-max M` gives every anchor a constant range offset drawn within +-M metres
(the scenarios have none; real radios carry centimetres to decimetres). `--nlos-excess
lognormal` draws the NLOS excess never negative (`uwbfuse simulate --nlos-excess`).
"""

from __future__ import annotations

import argparse
import sys
import time
from concurrent.futures import ProcessPoolExecutor

import numpy as np

from uwbfuse.config import Config
from uwbfuse.constants import NLOS_EXCESS_LAWS
from uwbfuse.errors import UwbfuseError
from uwbfuse.estimator import Method
from uwbfuse.eval.evaluate import evaluate
from uwbfuse.pipeline import estimate
from uwbfuse.sim.simulator import simulate
from uwbfuse.streams import SensorLog

SCENARIOS = ("warehouse", "warehouse-nlos", "factory", "room", "room-static")


def _one(scenario: str, seed: int, duration: float, methods: list[str],
         anchor_offset_max: float = 0.0, nlos_excess: str = "gaussian") -> dict[str, float]:
    """2-D ATE RMSE (m) per method on one simulated log (NaN where the method failed)."""
    overrides: dict[str, object] = {"nlos_excess": nlos_excess}
    if anchor_offset_max:
        overrides["anchor_offset_max"] = anchor_offset_max
    log = simulate(scenario, duration_s=duration, seed=seed, **overrides)
    return ate_by_method(log, methods, Config(), f"{scenario} seed {seed}")


def ate_by_method(log: SensorLog, methods: list[str], config: Config,
                  label: str) -> dict[str, float]:
    """2-D ATE RMSE (m, no alignment, stamps matched within 50 ms) of each method on a
    simulated log; NaN where the method fails with a one-line error (printed to stderr
    after `label`, as is each method's result and wall time)."""
    assert log.ground_truth is not None
    out = {}
    for m in methods:
        tic = time.perf_counter()
        try:
            res = estimate(log, Method(m), config, covariance=False)
            out[m] = evaluate(res.trajectory, log.ground_truth, align="none",
                              max_dt=0.05).ate_2d.rmse
        except UwbfuseError as e:
            print(f"# {label} {m}: failed: {e}", file=sys.stderr)
            out[m] = float("nan")
        print(f"# {label} {m}: {out[m]:.4f} m, {time.perf_counter() - tic:.1f} s",
              file=sys.stderr, flush=True)
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--methods", default="batch,isam2,ekf,ukf,wls")
    p.add_argument("--scenarios", default=",".join(SCENARIOS))
    p.add_argument("--seeds", default="0,1,2")
    p.add_argument("--duration", type=float, default=60.0)
    p.add_argument("--jobs", type=int, default=1)
    p.add_argument("--anchor-offset-max", type=float, default=0.0,
                   help="constant per-anchor range offset, uniform within +-M, m")
    p.add_argument("--nlos-excess", choices=NLOS_EXCESS_LAWS, default=NLOS_EXCESS_LAWS[0],
                   help="law of the simulated NLOS excess (`uwbfuse simulate --nlos-excess`)")
    args = p.parse_args(argv)
    methods = args.methods.split(",")
    for m in methods:
        Method(m)  # a misspelt method fails here, before any simulation
    scenarios = args.scenarios.split(",")
    seeds = [int(s) for s in args.seeds.split(",")]
    cells = [(sc, sd) for sc in scenarios for sd in seeds]
    with ProcessPoolExecutor(max_workers=max(1, args.jobs)) as pool:
        futures = [pool.submit(_one, sc, sd, args.duration, methods,
                               args.anchor_offset_max, args.nlos_excess) for sc, sd in cells]
        results = dict(zip(cells, (f.result() for f in futures), strict=True))
    offsets = f", offsets +-{args.anchor_offset_max:g} m" if args.anchor_offset_max else ""
    if args.nlos_excess != NLOS_EXCESS_LAWS[0]:
        offsets += f", {args.nlos_excess} NLOS excess"
    print(f"| scenario ({len(seeds)} seeds x {args.duration:g} s{offsets}) | "
          + " | ".join(methods) + " |")
    print("|---|" + "---|" * len(methods))
    for sc in scenarios:
        row = []
        for m in methods:
            v = np.array([results[(sc, sd)][m] for sd in seeds])
            per = " ".join(f"{x:.4f}" for x in v)
            row.append(f"{np.mean(v):.4f} [{per}]")
        print(f"| {sc} | " + " | ".join(row) + " |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
