# SPDX-License-Identifier: BSD-3-Clause
"""Classify each epoch's predicted motion: clear, warning or collision (the paper's Figure 6
cases a, b and c), against the map's obstacles or another vehicle.

- `collision`: a swept slot touches an obstacle (or the other vehicle's slot of the same
  time); distance 0, time to contact = start of the first slot that touches (never later
  than the contact, at most control_delay / prediction_steps early).
- `warning`: no contact, but the clearance over the horizon is below the margin:
  `safety_margin + sigma_factor * sigma`, sigma the position std of the pose (for two
  vehicles the root sum of squares of both), 0 where unknown.
- `clear`: otherwise (the distance is then only computed where it is below the margin).

Vectorised: an STRtree (map) or a distance bound from the centres (vehicles) keeps the
exact shapely distances to the epochs that can be within the margin.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum

import numpy as np
import shapely
from numpy.typing import NDArray

from uwbfuse.config import VehicleConfig
from uwbfuse.safety.geometry import Footprint, ObstacleMap
from uwbfuse.safety.motion import MotionState
from uwbfuse.safety.sweep import reach, sweep

F64 = NDArray[np.float64]


class Kind(IntEnum):
    """Outcome of one epoch (Figure 6: a no collision, b about to collide, c will collide)."""

    CLEAR = 0
    WARNING = 1
    COLLISION = 2


@dataclass(frozen=True)
class Check:
    """Per epoch of vehicle `a` against target `b` (a vehicle name or "map"): t_ns (the
    epoch's TUM stamp), t (s),
    kind (Kind values), distance (m; inf where clear beyond the margin), ttc (s, NaN when no
    contact within the horizon), margin (m, the widened warning margin used)."""

    a: str
    b: str
    t_ns: NDArray[np.int64]
    t: F64
    kind: NDArray[np.int8]
    distance: F64
    ttc: F64
    margin: F64

    def __len__(self) -> int:
        return len(self.t)


def widened_margin(vehicle: VehicleConfig, sigma: F64) -> F64:
    """safety_margin + sigma_factor * sigma (m), sigma NaN (unknown) counted as 0."""
    return vehicle.safety_margin + vehicle.sigma_factor * np.nan_to_num(sigma, nan=0.0)


def _classify(a: str, b: str, st: MotionState, margin: F64, cand: NDArray[np.intp],
              dist_slots: F64, horizon: float, steps: int) -> Check:
    """Per-epoch result from the (len(cand), S) slot distances of the candidate epochs."""
    n = len(st)
    distance = np.full(n, np.inf)
    ttc = np.full(n, np.nan)
    if len(cand):
        distance[cand] = dist_slots.min(axis=1)
        touch = dist_slots <= 0.0
        hit = touch.any(axis=1)
        first = np.argmax(touch, axis=1)
        ttc[cand[hit]] = first[hit] * (horizon / steps)
    kind = np.full(n, Kind.CLEAR, dtype=np.int8)
    kind[distance < margin] = Kind.WARNING
    kind[distance <= 0.0] = Kind.COLLISION
    distance[distance >= margin] = np.inf
    return Check(a, b, st.t_ns, st.t, kind, distance, ttc, margin)


def check_map(name: str, footprint: Footprint, state: MotionState, obstacles: ObstacleMap,
              vehicle: VehicleConfig) -> Check:
    """Every epoch of `state` against the obstacles of the map."""
    horizon, steps = vehicle.control_delay, vehicle.prediction_steps
    margin = widened_margin(vehicle, state.sigma)
    if len(obstacles) == 0:
        return _classify(name, "map", state, margin, np.zeros(0, np.intp),
                         np.zeros((0, steps)), horizon, steps)
    centres = shapely.points(np.column_stack([state.x, state.y]))
    epoch, obs = obstacles.tree.query(
        centres, predicate="dwithin", distance=reach(footprint, state, horizon) + margin)
    cand, inverse = np.unique(epoch, return_inverse=True)
    sw = sweep(footprint, state.take(cand), horizon, steps)
    d = shapely.distance(sw.slots[inverse], obstacles.geoms[obs][:, None])  # (pairs, S)
    dist_slots = np.full((len(cand), steps), np.inf)
    np.minimum.at(dist_slots, inverse, d)
    return _classify(name, "map", state, margin, cand, dist_slots, horizon, steps)


def check_pair(a: str, b: str, footprint: Footprint, sa: MotionState, sb: MotionState,
               vehicle: VehicleConfig) -> Check:
    """Vehicle `a` against vehicle `b` at the same epochs (`sb` sampled at `sa.t_ns`): each
    slot of `a` against the slot of `b` of the same time."""
    horizon, steps = vehicle.control_delay, vehicle.prediction_steps
    sigma = np.sqrt(np.nan_to_num(sa.sigma) ** 2 + np.nan_to_num(sb.sigma) ** 2)
    margin = widened_margin(vehicle, np.where(np.isnan(sa.sigma) & np.isnan(sb.sigma),
                                              np.nan, sigma))
    gap = np.hypot(sa.x - sb.x, sa.y - sb.y)
    bound = reach(footprint, sa, horizon) + reach(footprint, sb, horizon) + margin
    cand = np.flatnonzero(gap <= bound)
    if len(cand):
        wa = sweep(footprint, sa.take(cand), horizon, steps)
        wb = sweep(footprint, sb.take(cand), horizon, steps)
        d = shapely.distance(wa.slots, wb.slots)
    else:
        d = np.zeros((0, steps))
    return _classify(a, b, sa, margin, cand, d, horizon, steps)
