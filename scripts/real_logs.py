# SPDX-License-Identifier: BSD-3-Clause
"""Every ranging method on every real log; print one Markdown table of 2-D ATE RMSE.

    python scripts/real_logs.py [--methods isam2,isam2-smoothed,batch,ekf,ukf,wls,lkf]

Logs: labyrinth (UWB + wheels, GT in the anchor frame, no alignment), ISAS-Walk1 (UWB + IMU,
handheld; GT from the Vive tracker, SE(3)-aligned as its README prescribes, and SE(2)-aligned
against the GT in the anchor frame, `gt_anchor_frame.tum`), Plaza1 and
Plaza2 from the gtsam wheel (UWB + wheels; the radios read about 7 % long, which the
default `graph.estimate_range_scale = "auto"` finds; a "no scale" row turns it off). Default
config otherwise;
nothing is taken from ground truth. Reads ../shared/data/real beside the repository.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

from uwbfuse.config import Config, load_config
from uwbfuse.errors import UwbfuseError
from uwbfuse.estimator import Method
from uwbfuse.eval.evaluate import evaluate
from uwbfuse.io.reader import read_log
from uwbfuse.io.tum import read_tum
from uwbfuse.pipeline import estimate
from uwbfuse.streams import SensorLog

REAL = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "real"


def _logs() -> list[tuple[str, SensorLog, Config, str]]:
    """(name, log with ground truth, config, alignment) for each available real log."""
    out = []
    lab = REAL / "labyrinth"
    if lab.exists():
        cfg = load_config(lab / "config.toml")
        out.append(("labyrinth", read_log(lab / "labyrinth.mcap", cfg), cfg, "none"))
    isas = REAL / "isas-walk1"
    if isas.exists():
        cfg = load_config(isas / "config.toml")
        log = read_log(isas / "ISAS-Walk1", cfg)
        log.ground_truth = read_tum(isas / "gt.tum")
        out.append(("isas-walk1 (se3)", log, cfg, "se3"))
        # the issues' figure: SE(2)-aligned to the GT in the anchor frame (our fit)
        log2 = dataclasses.replace(log, ground_truth=read_tum(isas / "gt_anchor_frame.tum"))
        out.append(("isas-walk1 (se2)", log2, cfg, "se2"))
    try:
        from uwbfuse.graph.plaza import plaza_log, plaza_path

        for name in ("Plaza1", "Plaza2"):
            log = plaza_log(plaza_path(name))
            out.append((name, log, Config(), "none"))
            # the radios read ~7 % long; for comparison, without range-scale estimation
            out.append((f"{name} (no scale)", log,
                        Config(graph={"estimate_range_scale": False}), "none"))
    except UwbfuseError as e:
        print(f"# Plaza skipped: {e}", file=sys.stderr)
    return out


GRAPH_METHODS = (Method.ISAM2, Method.ISAM2_SMOOTHED, Method.BATCH)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--methods", default="isam2,isam2-smoothed,batch,ekf,ukf,wls,lkf")
    args = p.parse_args(argv)
    methods = [Method(m) for m in args.methods.split(",")]
    print("| log | " + " | ".join(m.value for m in methods) + " |")
    print("|---|" + "---|" * len(methods))
    for name, log, cfg, align in _logs():
        cells = []
        for m in methods:
            if name.endswith("(no scale)") and m not in GRAPH_METHODS:
                cells.append("")  # the range-scale setting is the graph's alone
                continue
            tic = time.perf_counter()
            try:
                res = estimate(log, m, cfg)
                ev = evaluate(res.trajectory, log.ground_truth, align=align, max_dt=0.05)
                cells.append(f"{ev.ate_2d.rmse:.3f}")
            except UwbfuseError as e:
                cells.append(f"failed: {e}".replace("|", "/")[:60])
            print(f"# {name} {m.value}: {time.perf_counter() - tic:.1f} s", file=sys.stderr)
        print(f"| {name} | " + " | ".join(cells) + " |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
