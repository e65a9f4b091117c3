# SPDX-License-Identifier: BSD-3-Clause
"""The UKF paper's comparison as issue 16 scores it (`scripts/lidar_comparison.py`, its
defaults: `warehouse-lidar`, seeds 1-3, 90 s): ranges must help every method, and the graph
must be at least 30 % below the UKF with them. Slow: 24 runs."""

from __future__ import annotations

import numpy as np
import pytest

from tests.helpers import script_module
from uwbfuse.estimator import Method

METHODS = [Method.UKF, Method.EKF, Method.ISAM2, Method.BATCH]


def _comparison() -> dict[tuple[Method, bool], list[float]]:
    return script_module("lidar_comparison").compare(3, 90.0, METHODS)


@pytest.mark.slow
def test_lidar_comparison_targets() -> None:
    """test that on the LiDAR scenario the ranges lower every method's mean ATE, and that
    batch and isam2 are each at least 30 % below the ukf with them"""
    rows = _comparison()
    mean = {key: float(np.mean(v)) for key, v in rows.items()}
    for m in METHODS:
        assert mean[(m, True)] < mean[(m, False)], (m, mean[(m, True)], mean[(m, False)])
    ukf = mean[(Method.UKF, True)]
    assert mean[(Method.BATCH, True)] <= 0.7 * ukf, (mean[(Method.BATCH, True)], ukf)
    isam2 = mean[(Method.ISAM2, True)]
    # measured 0.0548 m against 0.0836 (-34 %; docs/results.md, session 39)
    assert isam2 <= 0.7 * ukf, (isam2, ukf)
