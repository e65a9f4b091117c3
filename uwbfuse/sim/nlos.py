# SPDX-License-Identifier: BSD-3-Clause
"""Line of sight against obstacles and the NLOS range-error process.

Obstacles (shelf rows, cabinets) are axis-aligned boxes in the map frame, seen from above:
a range is NLOS when the 2-D segment from the tag antenna to the anchor (projected on the
floor) crosses the interior of a box. Shelves are assumed taller than the anchors and the tag,
so height is ignored.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.signal import lfilter

from uwbfuse.constants import NLOS_EXCESS_LAWS

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class Box:
    """Axis-aligned obstacle footprint in the map frame, metres."""

    xmin: float
    ymin: float
    xmax: float
    ymax: float

    def contains(self, xy: F64, margin: float = 0.0) -> NDArray[np.bool_]:
        """True for points (N,2) inside the box grown by `margin` metres."""
        return (
            (xy[:, 0] > self.xmin - margin)
            & (xy[:, 0] < self.xmax + margin)
            & (xy[:, 1] > self.ymin - margin)
            & (xy[:, 1] < self.ymax + margin)
        )


def segments_blocked(p: F64, q: F64, boxes: tuple[Box, ...] | list[Box]) -> NDArray[np.bool_]:
    """True where the segment p[i] -> q[i] (both (N,2), metres) crosses any box.

    Vectorised slab (Liang-Barsky) test over all segments and boxes; touching an edge or a
    corner does not count as crossing.
    """
    n = len(p)
    if not boxes or n == 0:
        return np.zeros(n, dtype=bool)
    lo = np.array([[b.xmin, b.ymin] for b in boxes])  # (B,2)
    hi = np.array([[b.xmax, b.ymax] for b in boxes])
    d = (q - p)[:, None, :]  # (N,1,2)
    p3 = p[:, None, :]
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (lo[None] - p3) / d
        t2 = (hi[None] - p3) / d
    tmin = np.minimum(t1, t2)
    tmax = np.maximum(t1, t2)
    # an axis with zero direction: inside the slab -> (-inf, inf), outside -> empty
    par = d == 0.0
    inside = (p3 > lo[None]) & (p3 < hi[None])
    tmin = np.where(par, np.where(inside, -np.inf, np.inf), tmin)
    tmax = np.where(par, np.where(inside, np.inf, -np.inf), tmax)
    enter = np.maximum(np.max(tmin, axis=2), 0.0)
    leave = np.minimum(np.min(tmax, axis=2), 1.0)
    return np.any(leave - enter > 1e-9, axis=1)


def unit_ar1(rng: np.random.Generator, n: int, dt: float, tau_s: float) -> F64:
    """A stationary AR(1) (Gauss-Markov) sequence (n,) of zero mean and unit variance, sampled
    every `dt` seconds, correlation time `tau_s` seconds (white where tau_s <= 0)."""
    if n == 0:
        return np.zeros(0)
    phi = float(np.exp(-dt / tau_s)) if tau_s > 0 else 0.0
    e = rng.standard_normal(n)
    e[0] /= np.sqrt(max(1.0 - phi * phi, 1e-12))  # start in the stationary distribution
    return lfilter([np.sqrt(1.0 - phi * phi)], [1.0, -phi], e)


def nlos_excess(x_slow: F64, x_white: F64, mean: float, std: float, slow_share: float,
                law: str = "gaussian") -> F64:
    """NLOS excess delay (m) of ranges from unit Gaussian drivers: `x_slow` per anchor
    (`unit_ar1`: the slowly varying part, `slow_share` of the variance) and `x_white` per
    range (the rest). Mean `mean` and std `std` (m) under either law:

    - "gaussian": mean + std (sqrt(c) x_slow + sqrt(1 - c) x_white), Qiu 2022's fitted
      N(0.114, 0.145) of an NLOS range's error. It reads short (negative) for about one
      range in five, for seconds at a time, which a blocked direct path cannot do.
    - "lognormal": exp of that Gaussian combination, scaled to the same mean and std: never
      negative (NLOS only lengthens a range), with many small excesses that look like LOS
      noise and a long tail; `slow_share` splits the variance of its logarithm.
    """
    c = min(max(slow_share, 0.0), 1.0)
    z = np.sqrt(c) * x_slow + np.sqrt(1.0 - c) * x_white
    if law == "gaussian":
        return mean + std * z
    if law != "lognormal":
        raise ValueError(f"unknown NLOS excess law {law!r}: one of {NLOS_EXCESS_LAWS}")
    s2 = float(np.log1p((std / mean) ** 2))  # variance of log(excess)
    return np.exp(np.log(mean) - 0.5 * s2 + np.sqrt(s2) * z)
