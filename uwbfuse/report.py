# SPDX-License-Identifier: BSD-3-Clause
"""Plain-text rendering of an estimator's report dict for the run summary."""

from __future__ import annotations

from typing import Any

import numpy as np


def _fmt(v: Any) -> str:
    if isinstance(v, float | np.floating):
        return f"{float(v):.4g}"
    if isinstance(v, dict):
        return ", ".join(f"{k}={_fmt(x)}" for k, x in v.items())
    if isinstance(v, list | tuple):
        return ", ".join(_fmt(x) for x in v)
    return str(v)


def format_report(report: dict[str, Any]) -> list[str]:
    """One line per report entry: `key: value` with nested dicts inlined."""
    return [f"{key}: {_fmt(value)}" for key, value in report.items()]
