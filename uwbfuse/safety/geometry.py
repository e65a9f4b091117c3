# SPDX-License-Identifier: BSD-3-Clause
"""The electronic map (obstacles in the map frame) and the vehicle footprint, as shapely 2.

Map frame: the anchors' frame, metres, z ignored (the floor plan). The footprint is a
rectangle `length` x `width` (base x, base y) centred at `footprint_center` in the base
frame; its corners at a pose (x, y, yaw) are the paper's left and right edge points at the
front and back (section 3.3, with the heading measured from +x as REP-103 does).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import shapely
from numpy.typing import NDArray

from uwbfuse.config import MapConfig, VehicleConfig
from uwbfuse.errors import CollisionCheckError

F64 = NDArray[np.float64]

BOUNDARY_PAD_M = 1000.0
"""m: how far past the hall outline the 'outside' obstacle reaches (any hall is smaller)."""


def polygons(rings: F64) -> NDArray[np.object_]:
    """Polygons (shape rings.shape[:-2]) from rings (..., K, 2) given open (the first vertex
    is repeated to close them); built from one flat coordinate array (shapely's ragged-array
    constructor: about twice as fast as `shapely.polygons` on many small rings)."""
    lead, k = rings.shape[:-2], rings.shape[-2]
    flat = rings.reshape(-1, k, 2)
    closed = np.concatenate([flat, flat[:, :1]], axis=1).reshape(-1, 2)
    n = len(flat)
    geoms = shapely.from_ragged_array(
        shapely.GeometryType.POLYGON, np.ascontiguousarray(closed),
        (np.arange(n + 1) * (k + 1), np.arange(n + 1)))
    return geoms.reshape(lead)


@dataclass(frozen=True)
class Footprint:
    """Vehicle rectangle in the base frame: length (x) and width (y) in m, centre (m)."""

    length: float
    width: float
    center: tuple[float, float] = (0.0, 0.0)

    def __post_init__(self) -> None:
        if not (self.length > 0 and self.width > 0
                and math.isfinite(self.length) and math.isfinite(self.width)):
            raise CollisionCheckError(
                f"[vehicle]: footprint must have a positive size, got length "
                f"{self.length} m, width {self.width} m")

    @classmethod
    def from_config(cls, v: VehicleConfig) -> Footprint:
        return cls(v.length, v.width, (float(v.footprint_center[0]),
                                       float(v.footprint_center[1])))

    @property
    def corners(self) -> F64:
        """(4,2) corners in the base frame, counter-clockwise from back right, m."""
        cx, cy = self.center
        hl, hw = 0.5 * self.length, 0.5 * self.width
        return np.array([[cx - hl, cy - hw], [cx + hl, cy - hw],
                         [cx + hl, cy + hw], [cx - hl, cy + hw]])

    @property
    def reach(self) -> float:
        """Largest distance of a footprint point from the base origin, m."""
        return float(np.max(np.hypot(self.corners[:, 0], self.corners[:, 1])))

    def corners_at(self, x: F64, y: F64, yaw: F64) -> F64:
        """Corners (..., 4, 2) in the map frame at poses x, y (m), yaw (rad) of any shape."""
        c, s = np.cos(yaw)[..., None], np.sin(yaw)[..., None]
        bx, by = self.corners[:, 0], self.corners[:, 1]
        out = np.empty((*np.shape(x), 4, 2))
        out[..., 0] = x[..., None] + c * bx - s * by
        out[..., 1] = y[..., None] + s * bx + c * by
        return out

    def polygons(self, x: F64, y: F64, yaw: F64) -> NDArray[np.object_]:
        """Footprint polygons (same shape as x) at the given poses."""
        return polygons(self.corners_at(np.asarray(x), np.asarray(y), np.asarray(yaw)))


@dataclass(frozen=True)
class ObstacleMap:
    """Obstacles of the map frame: names and shapely geometries, with an STRtree."""

    names: tuple[str, ...]
    geoms: NDArray[np.object_]
    tree: shapely.STRtree = field(compare=False, repr=False)

    @classmethod
    def build(cls, named: list[tuple[str, Any]]) -> ObstacleMap:
        geoms = np.array([g for _, g in named], dtype=object)
        shapely.prepare(geoms)
        return cls(tuple(n for n, _ in named), geoms, shapely.STRtree(geoms))

    @classmethod
    def from_config(cls, m: MapConfig) -> ObstacleMap:
        """Obstacles, walls (lines) and the outside of the boundary, as the config gives."""
        named: list[tuple[str, Any]] = [
            (f"obstacle{i}", shapely.Polygon(p)) for i, p in enumerate(m.obstacles)]
        named += [(f"wall{i}", shapely.LineString(w)) for i, w in enumerate(m.walls)]
        if m.boundary:
            hall = shapely.Polygon(m.boundary)
            outside = shapely.difference(hall.buffer(BOUNDARY_PAD_M, join_style="mitre"), hall)
            named.append(("boundary", outside))
        return cls.build(named)

    def __len__(self) -> int:
        return len(self.names)

    def outlines(self) -> list[tuple[F64, bool]]:
        """(ring (K,2), filled) per obstacle for plots: polygons filled, walls and the hall
        boundary (the hole of the 'outside' obstacle) as lines."""
        out = []
        for g in self.geoms:
            if isinstance(g, shapely.Polygon) and len(g.interiors):
                out += [(np.asarray(r.coords)[:, :2], False) for r in g.interiors]
            elif isinstance(g, shapely.Polygon):
                out.append((np.asarray(g.exterior.coords)[:, :2], True))
            else:
                out.append((np.asarray(g.coords)[:, :2], False))
        return out
