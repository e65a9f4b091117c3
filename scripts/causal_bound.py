# SPDX-License-Identifier: BSD-3-Clause
"""How close is the causal `isam2` to the best any causal estimator with our model can do?

    python scripts/causal_bound.py [--scenario warehouse-nlos] [--seeds 0,1,2,3]
                                   [--duration 120] [--step 5] [--nlos-excess lognormal]
    python scripts/causal_bound.py --real [labyrinth,isas-walk1,Plaza1,Plaza2] [--cuts 30]
    ... [--json OUT.json] [--bound-from EARLIER.json]

`batch` sees the whole log: where every anchor is in NLOS for tens of seconds (the
`warehouse-nlos` racetrack), it places the blocked stretch between the LOS stretches on
either side. A causal estimate cannot use the later side. To measure that limit, `batch`
is run on the log cut at t and only its pose at t, the newest, is kept: the error of a
full batch smoother that had to answer at t. The table compares, at the same epochs,
`isam2` (causal), `ekf` (causal), that "causal batch" and `batch` on the whole log (2-D
position error RMS over the epochs, metres; default config).

Simulations (`--scenario`): cut every `--step` seconds from 15 s on, simulated ground truth.
Real logs (`--real`, read as `scripts/real_logs.py` reads them, each with its config.toml):
`--cuts` epochs evenly spaced from the first `isam2` output to the end of the ranges;
epochs where the cut log gives batch no pose at t (no start yet) are left out of every
column and counted. Labyrinth and Plaza are scored in the map frame (their ground truth
is in the anchor frame); ISAS-Walk1 against `gt_anchor_frame.tum` with each column
SE(2)-aligned by its own fit over the scored epochs (the rule of `uwbfuse eval --align
se2`, restricted to those epochs: that GT frame is itself a fit).

`--json` writes every column's per-epoch errors; `--bound-from` takes the causal batch
column (and its epochs) from such a file instead of running it again (for re-measuring
isam2 after a change of the online path only).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from uwbfuse.config import Config
from uwbfuse.constants import NLOS_EXCESS_LAWS
from uwbfuse.errors import UwbfuseError
from uwbfuse.estimator import Method
from uwbfuse.eval.align import Alignment, fit_alignment
from uwbfuse.pipeline import estimate
from uwbfuse.sim.simulator import simulate
from uwbfuse.streams import NS_PER_S, PoseStream, SensorLog

COLUMNS = ("isam2", "ekf", "causal batch", "batch")
REAL_LOGS = ("labyrinth", "isas-walk1", "Plaza1", "Plaza2")


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


def _at(traj: PoseStream, t: np.ndarray) -> np.ndarray:
    """2-D positions of `traj` at epochs t (nearest pose at or before t; NaN before it)."""
    i = np.searchsorted(traj.t_ns, t, side="right") - 1
    out = traj.position[np.clip(i, 0, len(traj.t_ns) - 1), :2].copy()
    out[i < 0] = np.nan
    return out


def _gt_at(gt: PoseStream, t: np.ndarray) -> np.ndarray:
    return np.column_stack([np.interp(t, gt.t_ns, gt.position[:, k]) for k in range(2)])


def _errors(pos: np.ndarray, gt: np.ndarray, align: str) -> np.ndarray:
    """2-D errors (m) of positions against GT, after the column's own `align` fit."""
    if align != "none":
        tr = fit_alignment(Alignment.parse(align), np.column_stack([pos, np.zeros(len(pos))]),
                           np.column_stack([gt, np.zeros(len(gt))]))
        pos = pos @ tr.rotation[:2, :2].T + tr.translation[:2]
    return np.linalg.norm(pos - gt, axis=1)


def _causal_batch(log: SensorLog, cfg: Config, t_cut: np.ndarray,
                  say: Callable[[str], None]) -> np.ndarray:
    """Batch's 2-D position at each cut epoch from the log cut there (NaN: no pose at t)."""
    out = np.full((len(t_cut), 2), np.nan)
    for j, tc in enumerate(t_cut.tolist()):
        part = dataclasses.replace(
            log, imu=_cut(log.imu, tc), wheel=_cut(log.wheel, tc), ranges=_cut(log.ranges, tc),
            pose=_cut(log.pose, tc), ground_truth=None)
        try:
            traj = estimate(part, Method.BATCH, cfg, covariance=False).trajectory
        except UwbfuseError as e:
            say(f"cut at {(tc - t_cut[0]) / NS_PER_S:.1f} s: batch failed ({e})")
            continue
        if len(traj.t_ns) and traj.t_ns[-1] >= tc - round(0.2 * NS_PER_S):
            out[j] = _at(traj, np.array([tc]))[0]
    return out


def measure(log: SensorLog, cfg: Config, t_cut: np.ndarray, align: str,
            bound: dict[str, Any] | None, say: Callable[[str], None]) -> dict[str, Any]:
    """Per-epoch 2-D errors of every column at the cut epochs t_cut (ns) that the causal
    batch answers (those of `bound`, an earlier run's, when given)."""
    gt = log.ground_truth
    assert gt is not None
    if bound is not None:
        t_cut = np.asarray(bound["t_ns"], np.int64)
        causal = np.asarray(bound["causal_position"], np.float64)
    else:
        causal = _causal_batch(log, cfg, t_cut, say)
    pos = {"causal batch": causal}
    for name, method in (("isam2", Method.ISAM2), ("ekf", Method.EKF), ("batch", Method.BATCH)):
        pos[name] = _at(estimate(log, method, cfg, covariance=False).trajectory, t_cut)
    ok = np.all([np.all(np.isfinite(p), axis=1) for p in pos.values()], axis=0)
    g = _gt_at(gt, t_cut[ok])
    err = {c: _errors(pos[c][ok], g, align) for c in COLUMNS}
    return {"t_ns": t_cut[ok].tolist(), "left_out": int(np.count_nonzero(~ok)),
            "causal_position": causal[ok].tolist(),
            "errors": {c: e.tolist() for c, e in err.items()},
            "rms": {c: float(np.sqrt(np.mean(np.square(e)))) for c, e in err.items()}}


def _real_cases(names: list[str], n_cuts: int) -> list[tuple[str, SensorLog, Config, str, Any]]:
    """(name, log, config, alignment, cut epochs) of each available real log asked for."""
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from real_logs import _logs

    out = []
    for name, log, cfg, align in _logs():
        key = name.split(" ")[0]
        if key not in names or name.endswith(("(no scale)", "(se3)")):
            continue
        first = int(estimate(log, Method.ISAM2, cfg, covariance=False).trajectory.t_ns[0])
        end = int(log.ranges.t_ns[-1])
        t_cut = np.linspace(first, end, n_cuts + 1)[1:].round().astype(np.int64)
        out.append((key, log, cfg, align, t_cut))
    return out


def _sim_cases(scenario: str, seeds: list[int], duration: float, step: float,
               nlos_excess: str = "gaussian") -> list[tuple[str, SensorLog, Config, str, Any]]:
    out = []
    for seed in seeds:
        log = simulate(scenario, duration_s=duration, seed=seed, nlos_excess=nlos_excess)
        t0 = int(log.ranges.t_ns[0])
        cuts = np.arange(15.0, duration + 1e-9, step)
        out.append((f"{scenario} seed {seed}", log, Config(), "none",
                    t0 + np.round(cuts * NS_PER_S).astype(np.int64)))
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--scenario", default="warehouse-nlos")
    p.add_argument("--seeds", default="0,1,2,3")
    p.add_argument("--duration", type=float, default=120.0, help="simulated log length, s")
    p.add_argument("--step", type=float, default=5.0, help="s between cut epochs (sims)")
    p.add_argument("--nlos-excess", choices=NLOS_EXCESS_LAWS, default=NLOS_EXCESS_LAWS[0],
                   help="law of the simulated NLOS excess (`uwbfuse simulate --nlos-excess`)")
    p.add_argument("--real", nargs="?", const=",".join(REAL_LOGS), default=None,
                   help="real logs instead of a simulated scenario")
    p.add_argument("--cuts", type=int, default=30, help="cut epochs per real log")
    p.add_argument("--json", default=None, help="write the per-epoch errors here")
    p.add_argument("--bound-from", default=None, help="causal batch from an earlier --json")
    args = p.parse_args(argv)
    if args.real is not None:
        cases = _real_cases(args.real.split(","), args.cuts)
        title = f"real logs, {args.cuts} cut epochs each"
    else:
        cases = _sim_cases(args.scenario, [int(s) for s in args.seeds.split(",")],
                           args.duration, args.step, args.nlos_excess)
        title = (f"`{args.scenario}`, {args.duration:.0f} s, cut every {args.step:g} s "
                 "from 15 s")
    earlier = json.loads(Path(args.bound_from).read_text()) if args.bound_from else {}
    rows: dict[str, Any] = {}
    for name, log, cfg, align, t_cut in cases:
        rows[name] = measure(log, cfg, t_cut, align, earlier.get(name),
                             lambda s, n=name: print(f"# {n}: {s}", file=sys.stderr))
        print(f"# {name} done", file=sys.stderr, flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps(rows))
    print(f"{title}; 2-D error at the cut epochs, RMS over the epochs, m:\n")
    print("| log | epochs | isam2 | ekf | causal batch | batch (whole log) "
          "| isam2 / causal batch | ekf / causal batch |")
    print("|---|---|---|---|---|---|---|---|")
    for name, r in rows.items():
        m = r["rms"]
        print(f"| {name} | {len(r['t_ns'])} (-{r['left_out']}) | {m['isam2']:.3f} | "
              f"{m['ekf']:.3f} | {m['causal batch']:.3f} | {m['batch']:.3f} | "
              f"{m['isam2'] / m['causal batch']:.2f} | {m['ekf'] / m['causal batch']:.2f} |")
    if len(rows) > 1 and args.real is None:
        mean = {c: float(np.mean([r["rms"][c] for r in rows.values()])) for c in COLUMNS}
        print(f"| mean | | {mean['isam2']:.3f} | {mean['ekf']:.3f} | "
              f"{mean['causal batch']:.3f} | {mean['batch']:.3f} | "
              f"{mean['isam2'] / mean['causal batch']:.2f} | "
              f"{mean['ekf'] / mean['causal batch']:.2f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
