# SPDX-License-Identifier: BSD-3-Clause
"""The area a footprint sweeps over the control delay, as time slots.

The paper (section 3.3) tests the quadrilateral between the left and right edge points now
and after the delay. Here the horizon is cut into `steps` slots and each slot is the convex
hull of the footprint at its two ends (the paper's area when steps = 1 and the vehicle
does not turn); the union of the slots is the swept area, and keeping the slots apart
gives the time of contact (the start of the first slot that touches) and lets two vehicles
be compared slot by slot: they conflict only where they occupy the same place at the same
time, not where one crosses the other's path later.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import shapely
from numpy.typing import NDArray

from uwbfuse.safety.geometry import Footprint, polygons
from uwbfuse.safety.motion import MotionState, predict

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class Sweep:
    """Slots (N,S) of shapely polygons; slot k covers tau in [t_start[k], t_start[k+1]]."""

    slots: NDArray[np.object_]
    t_start: F64  # (S+1,) slot boundaries, s after the epoch

    @property
    def steps(self) -> int:
        return self.slots.shape[1]


def sweep(footprint: Footprint, state: MotionState, horizon: float, steps: int) -> Sweep:
    """The swept slots of `footprint` moving as `state` predicts over [t, t + horizon]."""
    tau, x, y, yaw = predict(state, horizon, steps)
    corners = footprint.corners_at(x, y, yaw)  # (N, S+1, 4, 2)
    pairs = np.concatenate([corners[:, :-1], corners[:, 1:]], axis=2)  # (N, S, 8, 2)
    # the hull of a ring through the 8 corners is the hull of the points (GEOS uses the
    # coordinates only), and a ring is much cheaper to build than a multipoint
    slots = shapely.convex_hull(polygons(pairs))
    return Sweep(slots, tau)


def reach(footprint: Footprint, state: MotionState, horizon: float) -> F64:
    """(N,) radius around each epoch's position that holds its whole swept area, m."""
    return footprint.reach + state.speed * horizon
