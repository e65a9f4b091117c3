# SPDX-License-Identifier: BSD-3-Clause
"""Shared test helpers: paths to the real datasets (skip when absent)."""

from __future__ import annotations

from pathlib import Path

import pytest

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
