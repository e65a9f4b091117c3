# SPDX-License-Identifier: BSD-3-Clause
"""The registry of estimation methods: what each needs, what it writes, how it is scored.

`METHODS` holds one `MethodSpec` per `Method`: its implementation module (imported lazily,
so `uwbfuse --help` and the I/O commands start without GTSAM), the sensor streams it needs,
whether it uses ranges (and so an anchor map), whether its output is a smoothed final
trajectory, whether it classifies ranges LOS/NLOS, and its rank as a reference (tables,
plots and alignments take the best-ranked method present). Each implementation module
exposes `make(method, config, anchors, streams) -> Estimator`, where `streams` is the set of
sensor streams the log has ({"imu", "wheel", "uwb"}, and "pose" for methods that use
external poses).
"""

from __future__ import annotations

import importlib
import importlib.util
from dataclasses import dataclass
from enum import StrEnum
from typing import TYPE_CHECKING

from uwbfuse.config import Config
from uwbfuse.streams import AnchorMap

if TYPE_CHECKING:
    from uwbfuse.estimator import Estimator


class Method(StrEnum):
    """Estimation methods of `uwbfuse run --method`."""

    ISAM2 = "isam2"
    ISAM2_SMOOTHED = "isam2-smoothed"
    BATCH = "batch"
    EKF = "ekf"
    UKF = "ukf"
    WLS = "wls"
    LKF = "lkf"
    IMU = "imu"
    ODOM = "odom"

    @property
    def spec(self) -> MethodSpec:
        return METHODS[self]

    @property
    def uses_ranges(self) -> bool:
        return METHODS[self].uses_ranges


@dataclass(frozen=True)
class MethodSpec:
    """What the pipeline, tables and plots need to know of one method."""

    module: str  # implementation module (its `make` builds the estimator)
    required: frozenset[str]  # streams it cannot do without
    uses_ranges: bool = True  # ranges, and so an anchor map (dead reckoning: neither)
    # streams with which a ranging method also runs on a log without ranges (no anchor map:
    # it starts at the map origin, heading zero), None: it needs the ranges
    without_ranges: frozenset[str] | None = None
    smoothed: bool = False  # writes its final (smoothed) trajectory, not the causal one
    classifies_ranges: bool = False  # reports a per-range LOS/NLOS classification
    # fuses external poses (role `pose`: `add_poses`); with them it also runs without
    # ranges on any log that has an IMU or wheels
    uses_pose: bool = False
    # rank as a reference (0 best): residuals without ground truth, the plots' frame
    reference_rank: int | None = None


_GRAPH = "uwbfuse.graph.estimator"
_UWB = frozenset({"uwb"})
_IMU_WHEEL = frozenset({"imu", "wheel"})
METHODS: dict[Method, MethodSpec] = {
    Method.BATCH: MethodSpec(_GRAPH, _UWB, without_ranges=_IMU_WHEEL, smoothed=True,
                             classifies_ranges=True, uses_pose=True, reference_rank=0),
    Method.ISAM2_SMOOTHED: MethodSpec(_GRAPH, _UWB, without_ranges=_IMU_WHEEL, smoothed=True,
                                      classifies_ranges=True, uses_pose=True,
                                      reference_rank=1),
    Method.ISAM2: MethodSpec(_GRAPH, _UWB, without_ranges=_IMU_WHEEL, classifies_ranges=True,
                             uses_pose=True, reference_rank=2),
    Method.EKF: MethodSpec("uwbfuse.filters.ekf", _UWB, without_ranges=_IMU_WHEEL,
                           uses_pose=True, reference_rank=3),
    Method.UKF: MethodSpec("uwbfuse.filters.ukf", _UWB, without_ranges=_IMU_WHEEL,
                           uses_pose=True, reference_rank=4),
    Method.LKF: MethodSpec("uwbfuse.filters.lkf", _UWB, reference_rank=5),
    Method.WLS: MethodSpec("uwbfuse.filters.wls", _UWB, reference_rank=6),
    Method.IMU: MethodSpec("uwbfuse.filters.dead_reckoning", frozenset({"imu"}),
                           uses_ranges=False),
    Method.ODOM: MethodSpec("uwbfuse.filters.dead_reckoning", frozenset({"wheel"}),
                            uses_ranges=False),
}

# Which sensor streams each method cannot do without, and what a ranging method runs on
# without ranges (views of `METHODS`).
REQUIRED_STREAMS: dict[Method, frozenset[str]] = {m: s.required for m, s in METHODS.items()}
WITHOUT_RANGES: dict[Method, frozenset[str]] = {
    m: s.without_ranges for m, s in METHODS.items() if s.without_ranges is not None}


def by_reference_rank(methods: list[Method] | None = None, *,
                      classifying: bool = False) -> list[Method]:
    """Ranked methods, best reference first (of `methods`, default all); `classifying`:
    only those that classify ranges."""
    pool = list(METHODS) if methods is None else methods
    ranked = [m for m in pool if METHODS[m].reference_rank is not None
              and (METHODS[m].classifies_ranges or not classifying)]
    return sorted(ranked, key=lambda m: METHODS[m].reference_rank)


def available_methods() -> list[Method]:
    """Methods whose implementation module is importable in this installation."""
    return [m for m, s in METHODS.items() if importlib.util.find_spec(s.module) is not None]


def make_estimator(
    method: Method, config: Config, anchors: AnchorMap | None, streams: frozenset[str]
) -> Estimator:
    """Build the estimator for `method` (streams: which sensors the log has)."""
    module = importlib.import_module(METHODS[method].module)
    return module.make(method, config, anchors, streams)
