"""The review queue's concatenated columns against the batches' own arrays."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("gtsam")

from uwbfuse.graph.builder import ReviewBatch
from uwbfuse.graph.review_queue import COLUMNS, ReviewQueue


def _batch(rng: np.random.Generator, ka: int) -> ReviewBatch:
    n = int(rng.integers(1, 6))
    return ReviewBatch(ka, rng.integers(0, 4, n), rng.normal(5.0, 1.0, n),
                       rng.integers(0, 9, n), rng.normal(size=(n, 3)), rng.uniform(size=n),
                       rng.uniform(size=n), ka, t_ns=np.sort(rng.integers(0, 10**9, n)),
                       evidence=rng.normal(size=n), ess=rng.uniform(size=n))


def test_columns_follow_appends_drops_and_responsibility_updates():
    """Test that after every append, drop and `set_g` the columns equal the queued
    batches' arrays concatenated, and `rows` finds each batch's."""
    rng = np.random.default_rng(2)
    q = ReviewQueue()
    for ka in range(40):
        q.append(_batch(rng, ka))
        if ka % 3 == 0:
            q.columns()
        if ka % 4 == 3:
            q.popleft()
        if len(q) > 2 and ka % 5 == 0:
            i = int(rng.integers(0, len(q)))
            j = np.flatnonzero(rng.uniform(size=len(q[i].z)) < 0.5)
            q.set_g(i, j, np.full(len(j), 0.75))
        cols = q.columns()
        for name in COLUMNS:
            np.testing.assert_array_equal(cols[name],
                                          np.concatenate([getattr(rb, name) for rb in q]))
        for i in range(len(q)):
            np.testing.assert_array_equal(q.columns()["z"][q.rows(i)], q[i].z)
    q.clear()
    assert len(q) == 0 and len(q.columns()["g"]) == 0
