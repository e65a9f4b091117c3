# SPDX-License-Identifier: BSD-3-Clause
"""Shared test helpers: paths to the real datasets (skip when absent), stream cuts."""

from __future__ import annotations

from dataclasses import fields, replace
from pathlib import Path
from typing import TypeVar

import numpy as np
import pytest

S = TypeVar("S")

ROOT = Path(__file__).resolve().parents[1]
REAL = ROOT.parent / "shared" / "data" / "real"


def real(rel: str) -> Path:
    """Path of a real dataset file under ../shared/data/real, or skip the test."""
    p = REAL / rel
    if not p.exists():
        pytest.skip(
            f"real dataset not available: {p} "
            "(shared/data/real is provided beside the repo in CI)"
        )
    return p


def keep_samples(stream: S, keep: np.ndarray) -> S:
    """`stream` (a streams dataclass with `t_ns`) with only the samples where `keep`."""
    return replace(stream, **{f.name: getattr(stream, f.name)[keep] for f in fields(stream)
                              if isinstance(getattr(stream, f.name), np.ndarray)
                              and getattr(stream, f.name).shape[:1] == keep.shape})


def silent(stream: S, t_ref_ns: int, t0_s: float, t1_s: float) -> S:
    """`stream` without its samples from t0_s to t1_s seconds after t_ref_ns (a dropout)."""
    t_s = (stream.t_ns - t_ref_ns) / 1e9  # type: ignore[attr-defined]
    return keep_samples(stream, (t_s < t0_s) | (t_s >= t1_s))
