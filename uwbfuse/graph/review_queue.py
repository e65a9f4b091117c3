# SPDX-License-Identifier: BSD-3-Clause
"""The range batches open to the online review (fixed-lag EM), with their columns kept
concatenated.

Every iSAM2 update re-classifies the ranges of the lag window (`GraphEstimator._review`):
some forty keyframe batches, a few ranges each. Concatenating their columns batch by batch
at every review was a good part of its time; here the queue keeps each column as one array,
appending the new batches and dropping the old ones as they come and go (views and one
concatenation per update). The responsibilities `g` the factors were built with are held in
the queue's column and mirrored into each batch's own array (`set_g`).
"""

from __future__ import annotations

from collections import deque
from collections.abc import Iterator

import numpy as np

from uwbfuse.graph.builder import ReviewBatch

# per-range columns of a `ReviewBatch` the review reads (all (N,) but tag_kf (N,3))
COLUMNS = ("anchor", "z", "t_ns", "prior", "evidence", "ess", "seg", "tag_kf", "g")


class ReviewQueue:
    """Review batches in keyframe order and their concatenated columns."""

    def __init__(self) -> None:
        self._batches: deque[ReviewBatch] = deque()
        self._start: deque[int] = deque()  # each batch's first row in the columns
        self._cols: dict[str, np.ndarray] = {}
        self._new: list[ReviewBatch] = []  # appended, not yet in the columns
        self._dropped = 0  # rows at the front of the columns that have left
        self._rows = 0  # rows of every batch appended so far (the next one's start)

    def __len__(self) -> int:
        return len(self._batches)

    def __iter__(self) -> Iterator[ReviewBatch]:
        return iter(self._batches)

    def __getitem__(self, i: int) -> ReviewBatch:
        return self._batches[i]

    def append(self, rb: ReviewBatch) -> None:
        """Queue a batch (after every batch queued before it)."""
        self._batches.append(rb)
        self._start.append(self._rows)
        self._rows += len(rb.z)
        self._new.append(rb)

    def popleft(self) -> None:
        """Drop the oldest batch."""
        rb = self._batches.popleft()
        self._start.popleft()
        if self._new and self._new[0] is rb:  # never in the columns
            self._new.pop(0)
        else:
            self._dropped += len(rb.z)

    def clear(self) -> None:
        self.__init__()  # type: ignore[misc]

    def columns(self) -> dict[str, np.ndarray]:
        """Every queued batch's columns (`COLUMNS`) concatenated, in queue order."""
        if self._dropped or self._new or not self._cols:
            cols = {}
            for name in COLUMNS:
                old = self._cols.get(name)
                parts = [] if old is None else [old[self._dropped:]]
                parts += [getattr(rb, name) for rb in self._new]
                if not parts:
                    parts = [np.zeros((0, 3)) if name == "tag_kf" else np.zeros(0)]
                cols[name] = np.concatenate(parts)
            self._cols = cols
            self._dropped = 0
            self._new.clear()
        return self._cols

    def rows(self, i: int) -> slice:
        """The rows of batch `i` (position in the queue) in `columns()`."""
        self.columns()  # the columns start at the first queued batch
        s = self._start[i] - self._start[0]
        return slice(s, s + len(self._batches[i].z))

    def set_g(self, i: int, j: np.ndarray, g: np.ndarray) -> None:
        """Batch `i`'s ranges `j` now have factors at responsibilities `g`."""
        rb = self._batches[i]
        rb.g[j] = g
        self.columns()["g"][self.rows(i)][j] = g  # a view: writes the column
