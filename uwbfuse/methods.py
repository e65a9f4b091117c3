# SPDX-License-Identifier: BSD-3-Clause
"""Registry of estimation methods: `Method` -> factory, imported lazily.

Each factory module exposes `make(method, config, anchors, streams) -> Estimator`, where
`streams` is the set of sensor streams the log has ({"imu", "wheel", "uwb"}). Lazy imports
keep `uwbfuse --help` and the I/O commands free of GTSAM start-up cost.
"""

from __future__ import annotations

import importlib
import importlib.util

from uwbfuse.config import Config
from uwbfuse.estimator import Estimator, Method
from uwbfuse.streams import AnchorMap

_FACTORY_MODULES: dict[Method, str] = {
    Method.IMU: "uwbfuse.filters.dead_reckoning",
    Method.ODOM: "uwbfuse.filters.dead_reckoning",
    Method.ISAM2: "uwbfuse.graph.estimator",
    Method.ISAM2_SMOOTHED: "uwbfuse.graph.estimator",
    Method.BATCH: "uwbfuse.graph.estimator",
    Method.EKF: "uwbfuse.filters.ekf",
    Method.UKF: "uwbfuse.filters.ukf",
    Method.WLS: "uwbfuse.filters.wls",
    Method.LKF: "uwbfuse.filters.lkf",
}

# Which sensor streams each method cannot do without.
REQUIRED_STREAMS: dict[Method, frozenset[str]] = {
    Method.IMU: frozenset({"imu"}),
    Method.ODOM: frozenset({"wheel"}),
    Method.WLS: frozenset({"uwb"}),
    Method.LKF: frozenset({"uwb"}),
    Method.EKF: frozenset({"uwb"}),
    Method.UKF: frozenset({"uwb"}),
    Method.ISAM2: frozenset({"uwb"}),
    Method.ISAM2_SMOOTHED: frozenset({"uwb"}),
    Method.BATCH: frozenset({"uwb"}),
}

# Streams with which a ranging method also runs on a log without UWB ranges (no anchor map
# needed): the Kalman filters then fuse IMU and wheels from the map origin, heading zero.
WITHOUT_RANGES: dict[Method, frozenset[str]] = {
    Method.EKF: frozenset({"imu", "wheel"}),
    Method.UKF: frozenset({"imu", "wheel"}),
}


def available_methods() -> list[Method]:
    """Methods whose implementation module is importable in this installation."""
    out = []
    for m, mod in _FACTORY_MODULES.items():
        if importlib.util.find_spec(mod) is not None:
            out.append(m)
    return out


def make_estimator(
    method: Method, config: Config, anchors: AnchorMap | None, streams: frozenset[str]
) -> Estimator:
    """Build the estimator for `method` (streams: which sensors the log has)."""
    module = importlib.import_module(_FACTORY_MODULES[method])
    return module.make(method, config, anchors, streams)
