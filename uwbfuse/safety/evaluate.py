# SPDX-License-Identifier: BSD-3-Clause
"""Collision prediction scored against ground truth.

Truth: the true footprints (ground-truth poses, no prediction) on a common `TRUTH_RATE_HZ`
grid, their clearance to the map and to each other. A *true conflict* is a contact
episode (a run of grid samples where the true footprints touch: the simulated AGVs drive on
as ghosts); its contact time t_c is its first sample. An epoch t of a prediction has a
*true hazard* when the true clearance drops below the nominal `safety_margin` somewhere in
[t, t + control_delay].

Scores of one run of the predictor (per vehicle-target pair, pooled over the fleet):

- detected: an alarm (warning or collision) for that pair at an epoch in
  [t_c - control_delay, t_c]; *lead time*: t_c minus the first epoch of the unbroken run of
  alarm epochs that holds the last alarm before t_c (at most `MAX_LEAD_S` back);
- false alarm: an alarm epoch with no true hazard that is not part of such a lead run;
  the rate is false alarms over the epochs *near* the target (true clearance below
  `NEAR_M` at the epoch).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import shapely
from numpy.lib.stride_tricks import sliding_window_view
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from uwbfuse.config import VehicleConfig
from uwbfuse.safety.classify import Check, Kind
from uwbfuse.safety.geometry import Footprint, ObstacleMap
from uwbfuse.streams import NS_PER_S, PoseStream

F64 = NDArray[np.float64]

TRUTH_RATE_HZ = 50.0
"""Hz: grid of the true clearances (0.02 s: 1 cm of travel at the AGVs' 0.5 m/s)."""
NEAR_M = 1.0
"""m: an epoch is near a target when the true clearance to it is below this."""
MAX_LEAD_S = 10.0
"""s: a lead time is counted back at most this far (an aisle of warnings is no lead)."""


@dataclass(frozen=True)
class TruthClearance:
    """True clearance (m) of vehicle `a` to target `b` on the grid t_ns."""

    a: str
    b: str
    t_ns: NDArray[np.int64]
    clearance: F64


def _grid(truth: dict[str, PoseStream]) -> NDArray[np.int64]:
    lo = max(int(p.t_ns[0]) for p in truth.values())
    hi = min(int(p.t_ns[-1]) for p in truth.values())
    step = round(NS_PER_S / TRUTH_RATE_HZ)
    return np.arange(lo, hi + 1, step, dtype=np.int64)


def _footprints_at(fp: Footprint, poses: PoseStream, t_ns: NDArray[np.int64]) -> np.ndarray:
    t = (t_ns - poses.t_ns[0]).astype(np.float64)
    own = (poses.t_ns - poses.t_ns[0]).astype(np.float64)
    yaw = np.unwrap(Rotation.from_quat(poses.quat_xyzw).as_euler("ZYX")[:, 0])
    x = np.interp(t, own, poses.position[:, 0])
    y = np.interp(t, own, poses.position[:, 1])
    return fp.polygons(x, y, np.interp(t, own, yaw))


def truth_clearances(truth: dict[str, PoseStream], obstacles: ObstacleMap,
                     vehicle: VehicleConfig) -> dict[tuple[str, str], TruthClearance]:
    """True clearances of every vehicle to the map and of every pair (both orders)."""
    fp = Footprint.from_config(vehicle)
    grid = _grid(truth)
    polys = {n: _footprints_at(fp, p, grid) for n, p in truth.items()}
    out: dict[tuple[str, str], TruthClearance] = {}
    for n, geoms in polys.items():
        if len(obstacles):
            _, dist = obstacles.tree.query_nearest(geoms, return_distance=True,
                                                   all_matches=False)
        else:
            dist = np.full(len(grid), np.inf)
        out[(n, "map")] = TruthClearance(n, "map", grid, np.asarray(dist, dtype=np.float64))
    names = list(polys)
    for i, a in enumerate(names):
        for b in names[i + 1:]:
            d = shapely.distance(polys[a], polys[b])
            out[(a, b)] = TruthClearance(a, b, grid, d)
            out[(b, a)] = TruthClearance(b, a, grid, d)
    return out


@dataclass(frozen=True)
class PairScore:
    """Scores of one check (vehicle against a target) against the truth."""

    conflicts: int
    detected: int
    lead_s: F64  # one per detected conflict
    false_alarms: int
    near_epochs: int
    alarm_epochs: int


def contact_times(tc: TruthClearance) -> NDArray[np.int64]:
    """First sample of every run of true contact (clearance 0), ns."""
    touch = tc.clearance <= 0.0
    starts = touch & ~np.concatenate([[False], touch[:-1]])
    return tc.t_ns[starts]


def score_check(check: Check, tc: TruthClearance, vehicle: VehicleConfig) -> PairScore:
    """Detections, lead times and false alarms of `check` against the true clearance."""
    horizon_ns = round(vehicle.control_delay * NS_PER_S)
    inside = (check.t_ns >= tc.t_ns[0]) & (check.t_ns <= tc.t_ns[-1] - horizon_ns)
    t = check.t_ns[inside]
    alarm = check.kind[inside] != Kind.CLEAR
    # true hazard: the windowed minimum of the true clearance over [t, t + horizon]
    k = round(vehicle.control_delay * TRUTH_RATE_HZ) + 1
    idx = np.clip(np.searchsorted(tc.t_ns, t), 0, len(tc.t_ns) - 1)
    padded = np.concatenate([tc.clearance, np.full(k - 1, np.inf)])
    window_min = sliding_window_view(padded, k).min(axis=1)
    hazard = window_min[idx] < vehicle.safety_margin
    near = tc.clearance[idx] < NEAR_M
    # runs of consecutive alarm epochs (gap below 1.5 epoch spacings)
    spacing = np.median(np.diff(t)) if len(t) > 1 else NS_PER_S
    new_run = np.ones(len(t), dtype=bool)
    new_run[1:] = ~alarm[:-1] | (np.diff(t) > 1.5 * spacing)
    run_start = t[np.maximum.accumulate(np.where(new_run, np.arange(len(t)), 0))]
    in_lead = np.zeros(len(t), dtype=bool)
    leads = []
    contacts = contact_times(tc)
    contacts = contacts[(contacts >= t[0] + horizon_ns) & (contacts <= t[-1])] if len(t) \
        else contacts[:0]
    for tcn in contacts:
        win = np.flatnonzero(alarm & (t >= tcn - horizon_ns) & (t <= tcn))
        if len(win) == 0:
            continue
        last = win[-1]
        start = max(run_start[last], tcn - int(MAX_LEAD_S * NS_PER_S))
        leads.append((tcn - start) / NS_PER_S)
        in_lead |= alarm & (t >= start) & (t <= tcn)
    false_alarm = alarm & ~hazard & ~in_lead
    return PairScore(len(contacts), len(leads), np.array(leads), int(false_alarm.sum()),
                     int(near.sum()), int(alarm.sum()))


@dataclass(frozen=True)
class FleetScore:
    """Scores pooled over every check of a fleet run."""

    conflicts: int
    detected: int
    lead_s: F64
    false_alarms: int
    near_epochs: int
    alarm_epochs: int

    @property
    def detection_rate(self) -> float:
        return self.detected / self.conflicts if self.conflicts else float("nan")

    @property
    def false_alarm_rate(self) -> float:
        return self.false_alarms / self.near_epochs if self.near_epochs else float("nan")

    @property
    def median_lead_s(self) -> float:
        return float(np.median(self.lead_s)) if len(self.lead_s) else float("nan")

    def __add__(self, other: FleetScore) -> FleetScore:
        return FleetScore(self.conflicts + other.conflicts, self.detected + other.detected,
                          np.concatenate([self.lead_s, other.lead_s]),
                          self.false_alarms + other.false_alarms,
                          self.near_epochs + other.near_epochs,
                          self.alarm_epochs + other.alarm_epochs)


def score_fleet(checks: Sequence[Check], truth: dict[tuple[str, str], TruthClearance],
                vehicle: VehicleConfig) -> FleetScore:
    """Pool `score_check` over every check (each pair once, as the checks give it)."""
    parts = [score_check(c, truth[(c.a, c.b)], vehicle) for c in checks]
    return FleetScore(
        sum(p.conflicts for p in parts), sum(p.detected for p in parts),
        np.concatenate([p.lead_s for p in parts]) if parts else np.zeros(0),
        sum(p.false_alarms for p in parts), sum(p.near_epochs for p in parts),
        sum(p.alarm_epochs for p in parts))
