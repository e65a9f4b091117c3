# SPDX-License-Identifier: BSD-3-Clause
"""Bounded windows of the recorded graph for batch's noise and time-offset fits.

A sensor's noise level and the wheel-to-range time offset are properties of the sensors,
not of the moment, so the evidence for them need not span the whole log (as the online IMU
fit's does not, `noise_fit.fit_imu_window`): batch takes it over windows of
ONLINE_WINDOW_S spread evenly from the log's start to its end (so a change of conditions
along the log is still sampled), as many as hold about EVIDENCE_RANGES ranges: the ranges
are what tells a motion model's noise and timing (between them the motion factors fit
their own track exactly). Each window after the first starts from loose priors on its
first keyframe, as a re-anchored smoother does (`GraphBuilder.restart_priors`). A log
with no more ranges than that is taken whole. The work of every fit is then bounded by
the budget instead of growing with the log.

The windowed graph is the recorded graph with every factor that touches a keyframe outside
the windows made a null slot, so the factor indices the fits replace by (`WheelRecords`,
`ImuRecords`, `pose_index`) stay valid.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import gtsam
import numpy as np

from uwbfuse.constants import EVIDENCE_RANGES, ONLINE_WINDOW_S
from uwbfuse.graph.builder import WheelRecords
from uwbfuse.graph.imu import ImuRecords

# the per-keyframe variables (`graph.keys`): pose, velocity, IMU bias
_KEYFRAME_CHARS = frozenset(ord(c) for c in "xvb")


def window_mask(stamps_s: np.ndarray, n_ranges: int, budget: int | None = None,
                window_s: float = ONLINE_WINDOW_S) -> np.ndarray:
    """Per keyframe (stamps in s, increasing), True inside the evidence windows: all of
    them when the log holds no more than `budget` ranges (`n_ranges` in all), else as many
    windows of `window_s` as hold about `budget` ranges at the log's mean range rate,
    their starts spread evenly from the first stamp to the last minus one window
    (`budget` None: EVIDENCE_RANGES)."""
    budget = EVIDENCE_RANGES if budget is None else budget
    stamps = np.asarray(stamps_s, float)
    span = float(stamps[-1] - stamps[0]) if len(stamps) else 0.0
    if n_ranges <= budget or span <= window_s:
        return np.ones(len(stamps), bool)
    n = int(np.ceil(budget * span / (n_ranges * window_s)))
    if n * window_s >= span:
        return np.ones(len(stamps), bool)
    starts = stamps[0] + (span - window_s) * np.arange(n) / max(n - 1, 1)
    keep = np.zeros(len(stamps), bool)
    for s in starts:
        keep |= (stamps >= s) & (stamps <= s + window_s)
    return keep


@dataclass
class EvidenceWindows:
    """The windows (`keep`, per keyframe) of one recorded graph, and what is dropped."""

    keep: np.ndarray
    drop: list[int]  # indices of the recorded graph's factors outside the windows
    firsts: list[int]  # the first keyframe of each window after keyframe 0
    # loose priors on keyframe k's state at its value in the given values (window starts)
    priors: Callable[[int, gtsam.Values], gtsam.NonlinearFactorGraph]

    @classmethod
    def of(cls, graph: gtsam.NonlinearFactorGraph, keep: np.ndarray,
           priors: Callable[[int, gtsam.Values], gtsam.NonlinearFactorGraph]
           ) -> EvidenceWindows:
        """The windows `keep` of the recorded `graph` (its factors' keys read once), each
        after keyframe 0 starting from `priors`."""
        keep = np.asarray(keep, bool)
        drop = []
        if not keep.all():
            for i in range(graph.size()):
                f = graph.at(i)
                if f is None:
                    continue
                for key in f.keys():
                    s = gtsam.Symbol(key)
                    if s.chr() in _KEYFRAME_CHARS and not keep[s.index()]:
                        drop.append(i)
                        break
        starts = np.flatnonzero(keep[1:] & ~keep[:-1]) + 1
        return cls(keep, drop, starts.tolist(), priors)

    @property
    def whole(self) -> bool:
        return bool(self.keep.all())

    def graph(self, graph: gtsam.NonlinearFactorGraph, initial: gtsam.Values
              ) -> gtsam.NonlinearFactorGraph:
        """A copy of the recorded `graph` with the factors outside the windows as null
        slots (indices kept) and, appended, `priors` at each window's first keyframe after
        keyframe 0 (at its value in `initial`). LM carries the values of the keyframes
        outside unchanged, so one set of values serves the windows and the whole log."""
        if self.whole:
            return graph
        out = gtsam.NonlinearFactorGraph(graph)
        for i in self.drop:
            out.remove(i)
        for k in self.firsts:
            out.push_back(self.priors(k, initial))
        return out

    def ranges(self, rec: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        """The range records whose keyframe lies inside the windows."""
        if self.whole:
            return rec
        inside = self.keep[np.asarray(rec["k"], np.int64)]
        return {name: v[inside] for name, v in rec.items()}

    def _pair_inside(self, k: np.ndarray) -> np.ndarray:
        k = np.asarray(k, np.int64)
        nxt = np.minimum(k + 1, len(self.keep) - 1)
        return self.keep[k] & self.keep[nxt]

    def wheel(self, wheel: WheelRecords) -> WheelRecords:
        """The wheel records of the intervals inside the windows."""
        if self.whole or not wheel.k:
            return wheel
        sel = np.flatnonzero(self._pair_inside(np.asarray(wheel.k))).tolist()
        return WheelRecords([wheel.k[i] for i in sel], [wheel.delta[i] for i in sel],
                            [wheel.cov[i] for i in sel], [wheel.index[i] for i in sel],
                            wheel.out_of_plane)

    def imu(self, imu: ImuRecords) -> ImuRecords:
        """The IMU records of the intervals inside the windows (sharing `parts`)."""
        if self.whole or not imu.k:
            return imu
        sel = np.flatnonzero(self._pair_inside(np.asarray(imu.k))).tolist()
        return imu.selected(sel)

    def pose_index(self, index: list[int]) -> list[int]:
        """External-pose factor indices still in the windowed graph."""
        dropped = set(self.drop)
        return [i for i in index if i not in dropped]
