# SPDX-License-Identifier: BSD-3-Clause
"""Benchmark `uwbfuse batch`: 16 ten-minute logs on 1 and 2 Dask workers vs plain runs.

    python scripts/bench_batch.py [--method ekf] [--logs 16] [--duration 600]
                                  [--workers 1,2] [--work DIR] [--scheduler ADDRESS]

Simulated warehouse logs (seeds 0..N-1) are written once into the work directory and
reused. The baseline is a plain `run`: `pipeline.run_log` on each log, one after another,
in this process (no process start-up, no cluster). Each batch then runs on a fresh local
cluster of W single-threaded worker processes (or on `--scheduler`). Reported per row:
wall time, cluster start-up, speed-up over the plain runs and parallel efficiency; the
per-job overhead of the cluster in wall time, (W x batch wall - plain wall) / jobs, and in
CPU time, (batch CPU - plain CPU) / jobs, where batch CPU counts this process and its
worker processes (scheduler, nannies, workers, start-up, transfer, writing results), and
`task_cpu_s` is the CPU time of the jobs themselves (their thread, in the workers). CPU
time stays meaningful on a busy machine, where wall times do not; `load1` is the load
average after each row. Every batch trajectory is checked byte for byte against the
plain run's.
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import time
from pathlib import Path


def make_logs(work: Path, n: int, duration_s: float, scenario: str) -> list[Path]:
    """Simulated contract logs (cached by name in `work/logs`)."""
    from uwbfuse.io.writer import write_contract_log
    from uwbfuse.sim.simulator import simulate

    d = work / "logs"
    d.mkdir(parents=True, exist_ok=True)
    paths = []
    for seed in range(n):
        p = d / f"{scenario}-{duration_s:g}s-seed{seed:02d}.mcap"
        if not p.exists():
            write_contract_log(p, simulate(scenario, duration_s=duration_s, seed=seed))
        paths.append(p)
    return paths


def plain_runs(logs: list[Path], method: str, out: Path) -> tuple[float, float]:
    """Wall time of `run_log` over every log here, one by one; and the summed log time."""
    from uwbfuse.config import Config
    from uwbfuse.estimator import Method
    from uwbfuse.pipeline import run_log

    out.mkdir(parents=True, exist_ok=True)
    tic = time.perf_counter()
    log_s = 0.0
    for lg in logs:
        res = run_log(lg, Method(method), Config(), tum_out=out / f"{lg.stem}.{method}.tum")
        log_s += res.log_duration_s
    return time.perf_counter() - tic, log_s


def cpu_seconds(children: bool) -> float:
    """CPU time (user + system) of this process, plus its reaped children if asked."""
    t = os.times()
    return t.user + t.system + ((t.children_user + t.children_system) if children else 0.0)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--method", default="ekf")
    ap.add_argument("--logs", type=int, default=16)
    ap.add_argument("--duration", type=float, default=600.0, help="seconds per log")
    ap.add_argument("--scenario", default="warehouse")
    ap.add_argument("--workers", default="1,2", help="comma-separated worker counts")
    ap.add_argument("--work", default="/tmp/uwbfuse-bench", help="logs and outputs go here")
    ap.add_argument("--scheduler", help="use this cluster instead of local ones")
    ap.add_argument("--keep", action="store_true", help="keep the batch outputs")
    args = ap.parse_args(argv)

    import logging

    import distributed  # noqa: F401 (installs its loggers; quieten them below)

    logging.getLogger("distributed").setLevel(logging.ERROR)
    from uwbfuse.fleet import batch_run, table_markdown

    work = Path(args.work)
    tic = time.perf_counter()
    logs = make_logs(work, args.logs, args.duration, args.scenario)
    print(f"{len(logs)} logs of {args.duration:g} s ({args.scenario}) in {work / 'logs'} "
          f"({time.perf_counter() - tic:.1f} s); cores: {os.cpu_count()}", file=sys.stderr)

    plain_dir = work / "plain"
    cpu0 = cpu_seconds(children=False)
    plain_s, log_s = plain_runs(logs, args.method, plain_dir)
    plain_cpu = cpu_seconds(children=False) - cpu0
    n = len(logs)
    rows = [{
        "run": "plain run_log, sequential", "workers": 1, "wall_s": plain_s,
        "startup_s": 0.0, "speedup": 1.0, "efficiency_pct": 100.0,
        "wall_overhead_per_job_s": 0.0, "cpu_s": plain_cpu, "cpu_overhead_per_job_s": 0.0,
        "task_cpu_s": plain_cpu,
        "x_realtime": log_s / plain_s, "load1": os.getloadavg()[0],
    }]
    print(f"plain: {plain_s:.1f} s", file=sys.stderr)
    counts = [int(w) for w in args.workers.split(",")] if not args.scheduler else [0]
    for w in counts:
        out = work / f"batch-w{w}"
        shutil.rmtree(out, ignore_errors=True)
        started: list[float] = []
        cpu0 = cpu_seconds(children=True)
        t0 = time.perf_counter()
        res = batch_run(
            logs, args.method, out_dir=out, scheduler=args.scheduler,
            workers=w or None, resume=False,
            on_start=lambda info, mark=started: mark.append(time.perf_counter()),
        )
        wall = time.perf_counter() - t0
        # Local workers are child processes, reaped when the cluster closes: their CPU
        # time is in ours. A remote cluster's is not measurable from here.
        cpu = cpu_seconds(children=True) - cpu0 if not args.scheduler else float("nan")
        if res.n_failed:
            print(f"failed: {[r['error'] for r in res.rows if r['status'] != 'ok']}",
                  file=sys.stderr)
            return 1
        same = all(
            (out / f"{lg.stem}.{args.method}.tum").read_bytes()
            == (plain_dir / f"{lg.stem}.{args.method}.tum").read_bytes()
            for lg in logs
        )
        if not same:
            print("batch trajectories differ from the plain runs", file=sys.stderr)
            return 1
        nw = res.cluster.n_workers
        rows.append({
            "run": f"batch, {res.cluster.kind} cluster", "workers": nw, "wall_s": wall,
            "startup_s": started[0] - t0 if started else 0.0,
            "speedup": plain_s / wall, "efficiency_pct": 100.0 * plain_s / (wall * nw),
            "wall_overhead_per_job_s": (nw * wall - plain_s) / n,
            "cpu_s": cpu, "cpu_overhead_per_job_s": (cpu - plain_cpu) / n,
            "task_cpu_s": sum(r["cpu_s"] for r in res.rows),
            "x_realtime": log_s / wall, "load1": os.getloadavg()[0],
        })
        print(f"{nw} worker(s): {wall:.1f} s", file=sys.stderr)
        if not args.keep:
            shutil.rmtree(out, ignore_errors=True)
    cols = ["run", "workers", "wall_s", "startup_s", "speedup", "efficiency_pct",
            "wall_overhead_per_job_s", "cpu_s", "task_cpu_s", "cpu_overhead_per_job_s",
            "x_realtime",
            "load1"]
    shown = [{k: round(v, 3) if isinstance(v, float) else v for k, v in r.items()} for r in rows]
    print(f"method {args.method}, {n} logs x {args.duration:g} s, {os.cpu_count()} cores, "
          "batch trajectories byte-identical to the plain runs")
    print(table_markdown(cols, shown), end="")
    return 0


if __name__ == "__main__":
    sys.exit(main())
