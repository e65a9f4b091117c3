# SPDX-License-Identifier: BSD-3-Clause
""""Did you mean" for misspelt names (config keys and sections, methods), via difflib."""

from __future__ import annotations

import difflib
from collections.abc import Iterable

CUTOFF = 0.6  # difflib similarity ratio below which a name is not offered


def did_you_mean(name: str, choices: Iterable[str]) -> str:
    """`"; did you mean 'x'?"` for the closest of `choices` to `name`, or ""."""
    known = list(choices)
    close = difflib.get_close_matches(name, known, n=1, cutoff=CUTOFF)
    if not close:  # `imu_topic` for `imu`: a known name inside the given one, or around it
        close = sorted((c for c in known if min(len(c), len(name)) >= 3
                        and (c in name or name in c)), key=len, reverse=True)[:1]
    return f"; did you mean {close[0]!r}?" if close else ""
