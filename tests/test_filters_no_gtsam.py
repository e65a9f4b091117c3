# SPDX-License-Identifier: BSD-3-Clause
"""`uwbfuse.filters` without GTSAM: the import is blocked in a subprocess and `ekf` and
`ukf` run on simulated logs (the filters' start path is numpy/scipy only)."""

from __future__ import annotations

import subprocess
import sys
import textwrap

SCRIPT = textwrap.dedent(
    """
    import importlib.abc
    import sys

    class BlockGtsam(importlib.abc.MetaPathFinder):
        def find_spec(self, name, path=None, target=None):
            if name == "gtsam" or name.startswith("gtsam."):
                raise ImportError(f"blocked for the test: {name}")
            return None

    sys.meta_path.insert(0, BlockGtsam())
    from uwbfuse.config import Config
    from uwbfuse.estimator import Method
    from uwbfuse.eval.evaluate import evaluate
    from uwbfuse.pipeline import estimate
    from uwbfuse.sim.simulator import simulate
    from uwbfuse.streams import SensorLog

    log = simulate("room", duration_s=20.0, seed=3)
    wheel_only = SensorLog(wheel=log.wheel, ranges=log.ranges, anchors=log.anchors,
                           ground_truth=log.ground_truth, source="sim")
    for m, lg in ((Method.EKF, log), (Method.UKF, log), (Method.EKF, wheel_only)):
        res = estimate(lg, m, Config())
        ate = evaluate(res.trajectory, lg.ground_truth, max_dt=0.01).ate_2d.rmse
        print(m.value, len(res.trajectory), f"{ate:.3f}")
    assert "gtsam" not in sys.modules
    """
)


def test_filters_run_without_gtsam() -> None:
    """test that ekf and ukf (IMU-driven and wheel-driven) run with the gtsam import blocked"""
    out = subprocess.run([sys.executable, "-c", SCRIPT], capture_output=True, text=True,
                         timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    rows = [line.split() for line in out.stdout.splitlines()]
    assert [r[0] for r in rows] == ["ekf", "ukf", "ekf"]
    for _name, n, ate in rows:
        assert int(n) > 100
        assert float(ate) < 0.3
