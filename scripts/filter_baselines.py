# SPDX-License-Identifier: BSD-3-Clause
"""2-D ATE RMSE of the Kalman baselines against `wls` on simulated and real logs.

    python scripts/filter_baselines.py [--seeds 3] [--duration 120] [--methods ekf,ukf,wls]
                                       [--scenarios room,room-static,...] [--no-real]

Simulated: every scenario x seeds, default config, mean and worst over the seeds. Real (read
in place beside the repository, skipped when absent): Labyrinth with its config.toml;
ISAS-Walk1 with its config.toml, `--align se2` against gt_anchor_frame.tum; Plaza1 and Plaza2
from the gtsam package (default config). Also prints, per log and method, the share of
epochs whose 2-D error lies inside the method's 95 % covariance ellipse (where it reports one).
Nothing is taken from ground truth by the estimators.
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np

from uwbfuse.config import Config
from uwbfuse.errors import UwbfuseError
from uwbfuse.estimator import Method
from uwbfuse.eval.evaluate import evaluate
from uwbfuse.io.tum import read_tum
from uwbfuse.pipeline import estimate
from uwbfuse.sim.simulator import simulate
from uwbfuse.streams import PoseStream, SensorLog

SCENARIOS = ("room", "room-static", "warehouse", "warehouse-nlos", "factory")
CHI2_2_95 = 5.991  # chi-square 95 % quantile, 2 degrees of freedom


def real_logs() -> list[tuple[str, SensorLog, Config, str]]:
    """(name, log with ground truth, config, alignment) for each available real log: those of
    `real_logs.py`, ISAS-Walk1 scored SE(2)-aligned against `gt_anchor_frame.tum`."""
    from real_logs import REAL, _logs

    out = []
    for name, log, cfg, align in _logs():
        if name.endswith("(no scale)") or name == "isas-walk1 (se2)":
            continue  # (the se3 entry becomes the se2 one below)
        if name.startswith("isas-walk1"):
            log.ground_truth = read_tum(REAL / "isas-walk1" / "gt_anchor_frame.tum")
            name, align = "isas-walk1 (se2)", "se2"
        out.append((name, log, cfg, align))
    return out


def inside_share(traj: PoseStream, gt: PoseStream) -> float:
    """Share of output epochs whose 2-D error lies inside the 95 % ellipse of the pose
    covariance (NaN when the trajectory carries none). No alignment: map frame."""
    cov = getattr(traj, "covariance", None)
    if cov is None or not len(traj):
        return float("nan")
    t = traj.t_ns
    ok = (t >= gt.t_ns[0]) & (t <= gt.t_ns[-1])
    ref = np.column_stack([np.interp(t[ok], gt.t_ns, gt.position[:, k]) for k in range(2)])
    e = traj.position[ok, :2] - ref
    c = np.asarray(cov)[ok][:, :2, :2]
    d2 = np.einsum("ni,ni->n", e, np.linalg.solve(c, e[:, :, None])[:, :, 0])
    return float(np.mean(d2 <= CHI2_2_95))


def run(log: SensorLog, m: str, cfg: Config, align: str) -> tuple[float, float, float]:
    tic = time.perf_counter()
    res = estimate(log, Method(m), cfg)
    wall = time.perf_counter() - tic
    ev = evaluate(res.trajectory, log.ground_truth, align=align, max_dt=0.05)
    share = inside_share(res.trajectory, log.ground_truth) if align == "none" else float("nan")
    return float(ev.ate_2d.rmse), share, wall


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--seeds", type=int, default=3)
    p.add_argument("--duration", type=float, default=120.0)
    p.add_argument("--methods", default="ekf,ukf,wls")
    p.add_argument("--scenarios", default=",".join(SCENARIOS))
    p.add_argument("--no-real", action="store_true")
    args = p.parse_args(argv)
    methods = args.methods.split(",")
    print("| log | " + " | ".join(methods) + " | 95 % share " + " / ".join(methods) + " |")
    print("|---|" + "---|" * (len(methods) + 1))
    scen = [s for s in args.scenarios.split(",") if s]
    for s in scen:
        vals = {m: [] for m in methods}
        shares = {m: [] for m in methods}
        for seed in range(args.seeds):
            log = simulate(s, duration_s=args.duration, seed=seed)
            for m in methods:
                try:
                    a, sh, wall = run(log, m, Config(), "none")
                except UwbfuseError as e:
                    a, sh, wall = float("nan"), float("nan"), 0.0
                    print(f"# {s} {seed} {m}: {e}", file=sys.stderr)
                vals[m].append(a)
                shares[m].append(sh)
                print(f"# {s} seed {seed} {m}: {a:.3f} m, share {sh:.2f}, {wall:.1f} s",
                      file=sys.stderr)
        cells = [f"{np.mean(vals[m]):.3f} ({np.max(vals[m]):.3f})" for m in methods]
        sh = " / ".join(f"{np.nanmean(shares[m]):.2f}" if np.isfinite(shares[m]).any()
                        else "-" for m in methods)
        print(f"| {s} | " + " | ".join(cells) + f" | {sh} |", flush=True)
    if not args.no_real:
        for name, log, cfg, align in real_logs():
            cells, shs = [], []
            for m in methods:
                try:
                    a, sh, wall = run(log, m, cfg, align)
                    cells.append(f"{a:.3f}")
                    shs.append(f"{sh:.2f}" if np.isfinite(sh) else "-")
                except UwbfuseError as e:
                    cells.append(f"failed: {e}".replace("|", "/")[:50])
                    shs.append("-")
                    wall = 0.0
                print(f"# {name} {m}: {wall:.1f} s", file=sys.stderr)
            print(f"| {name} | " + " | ".join(cells) + f" | {' / '.join(shs)} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
