# SPDX-License-Identifier: BSD-3-Clause
"""Run unusual and damaged variants of one simulated log through the contract CLI.

    python scripts/probe_inputs.py [--scenario warehouse] [--seed 2] [--duration 40]
                                   [--methods isam2,batch,ekf] [--work DIR] [--only NAME,...]

Each variant changes the simulated log the way real logs go wrong (invalid ranges, a
sensor that starts late, stops early or drops out, duplicate or burst stamps, a misplaced
anchor, too few or collinear anchors, a log too short to start), is written as a contract
MCAP and goes through `uwbfuse run` and `uwbfuse eval --gt LOG` in child processes, as a
user would run it. Printed per variant and method: exit status, 2-D ATE RMSE and max (m),
or the one-line error. A traceback, a non-zero exit on a log that has what the method
needs, or an ATE far above the `base` row is a defect to look at.
"""

from __future__ import annotations

import argparse
import dataclasses
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np

from uwbfuse.io.writer import write_contract_log
from uwbfuse.sim.simulator import simulate_with_truth
from uwbfuse.streams import NS_PER_S, SensorLog

IMU_F, WHEEL_F, RANGE_F = ("t_ns", "gyro", "accel"), ("t_ns", "v", "omega"), (
    "t_ns", "anchor", "range")


def _keep(log: SensorLog, name: str, keep: Callable[[np.ndarray], np.ndarray]) -> None:
    """Keep the samples of stream `name` where keep(seconds since its first sample)."""
    st = getattr(log, name)
    fields = {"imu": IMU_F, "wheel": WHEEL_F, "ranges": RANGE_F}[name]
    sel = keep((st.t_ns - st.t_ns[0]) / NS_PER_S)
    setattr(log, name, dataclasses.replace(st, **{f: getattr(st, f)[sel] for f in fields}))


def _invalid_ranges(log: SensorLog) -> None:
    r = log.ranges.range
    i = np.random.default_rng(0).choice(len(r), len(r) // 5, replace=False)
    k = len(i) // 3
    r[i[:k]], r[i[k:2 * k]], r[i[2 * k:]] = np.nan, -1.0, 0.0


def _nan_samples(name: str, field: str, n: int) -> Callable[[SensorLog], None]:
    def f(log: SensorLog) -> None:
        arr = getattr(getattr(log, name), field)
        arr[np.random.default_rng(1).choice(len(arr), n, replace=False)] = np.nan
    return f


def _anchor_offset(log: SensorLog) -> None:
    log.ranges.range[log.ranges.anchor == 1] += 1.0


def _huge_ranges(log: SensorLog) -> None:
    log.ranges.range[::50] = 1e6


def _dup_stamps(log: SensorLog) -> None:
    t = log.ranges.t_ns
    t[1::2] = t[0::2][: len(t[1::2])]


def _burst_stamps(log: SensorLog) -> None:
    t = log.ranges.t_ns
    t[:] = (t // 100_000_000) * 100_000_000


def _short(log: SensorLog) -> None:
    for name in ("imu", "wheel", "ranges"):
        _keep(log, name, lambda s: s < 3.0)


# name -> (simulate_with_truth overrides, change applied to the log)
VARIANTS: dict[str, tuple[dict, Callable[[SensorLog], None] | None]] = {
    "base": ({}, None),
    "20 % ranges NaN, -1 or 0": ({}, _invalid_ranges),
    "200 IMU samples NaN": ({}, _nan_samples("imu", "gyro", 200)),
    "50 wheel samples NaN": ({}, _nan_samples("wheel", "v", 50)),
    "every 50th range 1e6 m": ({}, _huge_ranges),
    "range stamps duplicated in pairs": ({}, _dup_stamps),
    "range stamps in 0.1 s bursts": ({}, _burst_stamps),
    "wheel speed sign flipped": ({}, lambda log: np.negative(log.wheel.v, out=log.wheel.v)),
    "IMU gap 15-25 s": ({}, lambda log: _keep(log, "imu", lambda s: (s < 15) | (s > 25))),
    "wheel gap 15-25 s": ({}, lambda log: _keep(log, "wheel", lambda s: (s < 15) | (s > 25))),
    "UWB gap 15-30 s": ({}, lambda log: _keep(log, "ranges", lambda s: (s < 15) | (s > 30))),
    "IMU from 10 s": ({}, lambda log: _keep(log, "imu", lambda s: s > 10)),
    "wheels from 10 s": ({}, lambda log: _keep(log, "wheel", lambda s: s > 10)),
    "UWB from 10 s": ({}, lambda log: _keep(log, "ranges", lambda s: s > 10)),
    "IMU ends at 20 s": ({}, lambda log: _keep(log, "imu", lambda s: s < 20)),
    "wheels end at 20 s": ({}, lambda log: _keep(log, "wheel", lambda s: s < 20)),
    "UWB ends at 20 s": ({}, lambda log: _keep(log, "ranges", lambda s: s < 20)),
    "IMU at 50 Hz": ({"imu_rate": 50.0}, None),
    "one anchor reads 1 m long": ({}, _anchor_offset),
    "two anchors": ({"anchors": (("A1", (0.0, 0.0, 1.5)), ("A4", (40.0, 20.0, 1.5)))}, None),
    "three collinear anchors": ({"anchors": (("A1", (0.0, 0.0, 1.5)), ("A2", (20.0, 0.0, 1.5)),
                                             ("A3", (40.0, 0.0, 1.5)))}, None),
    "3 s log": ({}, _short),
}


def _run(log_path: Path, method: str, out: Path) -> str:
    """`uwbfuse run` + `uwbfuse eval`: 'ATE max' or the error line."""
    run = subprocess.run([sys.executable, "-m", "uwbfuse", "run", str(log_path), "--method",
                          method, "-o", str(out)], capture_output=True, text=True, check=False)
    if "Traceback" in run.stderr:
        return "TRACEBACK: " + run.stderr.strip().splitlines()[-1][:120]
    if run.returncode != 0:
        err = [ln for ln in run.stderr.splitlines() if "error" in ln]
        why = err[0].split(f"{log_path}: ", 1)[-1] if err else ""
        return f"exit {run.returncode}: {why[:140]}"
    ev = subprocess.run([sys.executable, "-m", "uwbfuse", "eval", str(out), "--gt",
                         str(log_path)], capture_output=True, text=True, check=False)
    row = [ln.split() for ln in ev.stdout.splitlines() if ln.startswith("ATE 2-D")]
    return f"{float(row[0][4]):.3f} (max {float(row[0][-1]):.2f})" if row else "no eval"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--scenario", default="warehouse")
    ap.add_argument("--seed", type=int, default=2)
    ap.add_argument("--duration", type=float, default=40.0)
    ap.add_argument("--methods", default="isam2,batch,ekf")
    ap.add_argument("--work", default="/tmp/uwbfuse-probe")
    ap.add_argument("--only", default="", help="comma-separated variant names")
    args = ap.parse_args()
    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    methods = args.methods.split(",")
    names = [n for n in VARIANTS if not args.only or n in args.only.split(",")]
    print(f"{args.scenario} seed {args.seed}, {args.duration:g} s: 2-D ATE RMSE (max), m\n")
    print("| variant | " + " | ".join(methods) + " |")
    print("|---|" + "---|" * len(methods))
    for i, name in enumerate(names):
        overrides, change = VARIANTS[name]
        log = simulate_with_truth(args.scenario, args.duration, args.seed, **overrides).log
        if change is not None:
            change(log)
        path = work / f"v{i:02d}.mcap"
        write_contract_log(path, log)
        cells = [_run(path, m, work / f"v{i:02d}.{m}.tum") for m in methods]
        print(f"| {name} | " + " | ".join(cells) + " |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
