# SPDX-License-Identifier: BSD-3-Clause
"""How close is the causal `isam2` to the best any causal estimator with our model can do?

    python scripts/causal_bound.py [--scenario warehouse-nlos] [--seeds 0,1,2,3]
                                   [--duration 120] [--step 5]

`batch` sees the whole log: where every anchor is in NLOS for tens of seconds (the
`warehouse-nlos` racetrack), it places the blocked stretch between the LOS stretches on
either side. A causal estimate cannot use the later side. To measure that limit, `batch`
is run on the log cut at t (every `--step` seconds) and only its pose at t, the newest, is
kept: the error of a full batch smoother that had to answer at t. The table compares, at
the same epochs, `isam2` (causal), that "causal batch" and `batch` on the whole log (2-D
position error RMS over the epochs, metres; default config, simulated ground truth).
Takes about a minute per seed on the default settings.
"""

from __future__ import annotations

import argparse
import dataclasses
from typing import Any

import numpy as np

from uwbfuse.config import Config
from uwbfuse.estimator import Method
from uwbfuse.pipeline import estimate
from uwbfuse.sim.simulator import simulate
from uwbfuse.streams import NS_PER_S, PoseStream


def _cut(stream: Any, t_end: int) -> Any:
    """The samples of a stream with stamps <= t_end (None stays None)."""
    if stream is None:
        return None
    keep = stream.t_ns <= t_end
    fields = {}
    for f in dataclasses.fields(stream):
        v = getattr(stream, f.name)
        sized = isinstance(v, np.ndarray) and v.ndim >= 1 and len(v) == len(keep)
        fields[f.name] = v[keep] if sized else v
    return type(stream)(**fields)


def _error_at(traj: PoseStream, gt: PoseStream, t: np.ndarray) -> np.ndarray:
    """2-D error (m) of `traj` at epochs t (nearest trajectory pose at or before t)."""
    i = np.clip(np.searchsorted(traj.t_ns, t, side="right") - 1, 0, len(traj.t_ns) - 1)
    g = np.column_stack([np.interp(t, gt.t_ns, gt.position[:, k]) for k in range(2)])
    return np.linalg.norm(traj.position[i, :2] - g, axis=1)


def one_seed(scenario: str, seed: int, duration: float, step: float) -> tuple[float, ...]:
    """RMS error at the cut epochs: isam2, causal batch, whole-log batch."""
    log = simulate(scenario, duration_s=duration, seed=seed)
    t0 = int(log.ranges.t_ns[0])
    cuts = np.arange(15.0, duration + 1e-9, step)
    t_cut = t0 + np.round(cuts * NS_PER_S).astype(np.int64)
    cfg = Config()
    isam2 = estimate(log, Method.ISAM2, cfg).trajectory
    full = estimate(log, Method.BATCH, cfg).trajectory
    causal = []
    for tc in t_cut.tolist():
        part = dataclasses.replace(
            log, imu=_cut(log.imu, tc), wheel=_cut(log.wheel, tc), ranges=_cut(log.ranges, tc),
            ground_truth=_cut(log.ground_truth, tc))
        part_traj = estimate(part, Method.BATCH, cfg).trajectory
        causal.append(_error_at(part_traj, log.ground_truth, np.array([tc]))[0])
    gt = log.ground_truth

    def rms(e: np.ndarray) -> float:
        return float(np.sqrt(np.mean(np.square(e))))

    return (rms(_error_at(isam2, gt, t_cut)), rms(np.asarray(causal)),
            rms(_error_at(full, gt, t_cut)))


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--scenario", default="warehouse-nlos")
    p.add_argument("--seeds", default="0,1,2,3")
    p.add_argument("--duration", type=float, default=120.0, help="log length, s")
    p.add_argument("--step", type=float, default=5.0, help="s between cut epochs")
    args = p.parse_args(argv)
    rows = []
    for seed in [int(s) for s in args.seeds.split(",")]:
        rows.append((seed, *one_seed(args.scenario, seed, args.duration, args.step)))
        print(f"# seed {seed} done", flush=True)
    print(f"`{args.scenario}`, {args.duration:.0f} s, error at the cut epochs (every "
          f"{args.step:.0f} s from 15 s), RMS over epochs, m:\n")
    print("| seed | isam2 (causal) | causal batch (batch on the log cut at t) | batch (whole log) "
          "| isam2 / causal batch | isam2 / batch |")
    print("|---|---|---|---|---|---|")
    for seed, a, c, b in rows:
        print(f"| {seed} | {a:.3f} | {c:.3f} | {b:.3f} | {a / c:.2f} | {a / b:.2f} |")
    arr = np.array([r[1:] for r in rows])
    m = arr.mean(axis=0)
    print(f"| mean | {m[0]:.3f} | {m[1]:.3f} | {m[2]:.3f} | {m[0] / m[1]:.2f} | "
          f"{m[0] / m[2]:.2f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
