# SPDX-License-Identifier: BSD-3-Clause
"""Real-time factors of the Kalman baselines (EKF, UKF) on simulated logs.

Usage:
    python scripts/bench_filters.py [--scenario warehouse] [--durations 600,3600] [--seed 0]
                                    [--methods ekf,ukf]

Simulates each log once (not timed), then runs every method through the same streaming
loop as `uwbfuse run` (`pipeline.estimate`: initialiser included, 10 Hz outputs) and
prints one row per (log, method): log duration, wall time, CPU time of the process,
real-time factor (log duration / wall time) and the target (EKF >= 200x, UKF >= 50x).
On a shared machine the CPU-time factor is the steadier figure.
"""

from __future__ import annotations

import argparse
import time

from uwbfuse.config import Config
from uwbfuse.estimator import Method
from uwbfuse.pipeline import estimate
from uwbfuse.sim.simulator import simulate

TARGETS = {Method.EKF: 200.0, Method.UKF: 50.0}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", default="warehouse")
    ap.add_argument("--durations", default="600,3600", help="log lengths, seconds")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--methods", default="ekf,ukf")
    args = ap.parse_args()
    methods = [Method(m) for m in args.methods.split(",")]
    cfg = Config()
    header = (f"{'scenario':<12}{'log [s]':>9}{'method':>8}{'wall [s]':>10}{'cpu [s]':>9}"
              f"{'RTF wall':>10}{'RTF cpu':>9}{'target':>8}{'ok':>5}")
    print(header, flush=True)
    for dur in (float(d) for d in args.durations.split(",")):
        log = simulate(args.scenario, dur, args.seed)
        for m in methods:
            w0, c0 = time.perf_counter(), time.process_time()
            res = estimate(log, m, cfg)
            wall, cpu = time.perf_counter() - w0, time.process_time() - c0
            rtf, rtf_cpu = res.log_duration_s / wall, res.log_duration_s / cpu
            target = TARGETS.get(m, 0.0)
            print(
                f"{args.scenario:<12}{res.log_duration_s:>9.0f}{m.value:>8}{wall:>10.2f}"
                f"{cpu:>9.2f}{rtf:>9.0f}x{rtf_cpu:>8.0f}x{target:>7.0f}x"
                f"{'yes' if rtf >= target else 'no':>5}",
                flush=True,
            )


if __name__ == "__main__":
    main()
