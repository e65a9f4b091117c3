# SPDX-License-Identifier: BSD-3-Clause
"""Shared test helpers: paths to the real datasets (skip when absent), stream cuts, the
scripts as modules."""

from __future__ import annotations

import importlib.util
import sys
from dataclasses import fields, replace
from pathlib import Path
from types import ModuleType
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


def script_module(name: str) -> ModuleType:
    """The module of `scripts/<name>.py`, loaded once (scripts/ put on sys.path, so the
    scripts' imports of each other resolve as when they are run)."""
    key = f"uwbfuse_script_{name}"
    if key not in sys.modules:
        scripts = str(ROOT / "scripts")
        if scripts not in sys.path:
            sys.path.insert(0, scripts)
        spec = importlib.util.spec_from_file_location(key, ROOT / "scripts" / f"{name}.py")
        assert spec is not None and spec.loader is not None
        module = importlib.util.module_from_spec(spec)
        sys.modules[key] = module
        spec.loader.exec_module(module)
    return sys.modules[key]


def keep_samples(stream: S, keep: np.ndarray) -> S:
    """`stream` (a streams dataclass with `t_ns`) with only the samples where `keep`."""
    return replace(stream, **{f.name: getattr(stream, f.name)[keep] for f in fields(stream)
                              if isinstance(getattr(stream, f.name), np.ndarray)
                              and getattr(stream, f.name).shape[:1] == keep.shape})


def silent(stream: S, t_ref_ns: int, t0_s: float, t1_s: float) -> S:
    """`stream` without its samples from t0_s to t1_s seconds after t_ref_ns (a dropout)."""
    t_s = (stream.t_ns - t_ref_ns) / 1e9  # type: ignore[attr-defined]
    return keep_samples(stream, (t_s < t0_s) | (t_s >= t1_s))
