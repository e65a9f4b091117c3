# SPDX-License-Identifier: BSD-3-Clause
""""Did you mean" for misspelt names (config keys and sections, methods), via difflib."""

from __future__ import annotations

import difflib
from collections.abc import Iterable

CUTOFF = 0.6  # difflib similarity ratio below which a name is not offered


def did_you_mean(name: str, choices: Iterable[str]) -> str:
    """`"; did you mean 'x'?"` for the closest of `choices` to `name`, or ""."""
    close = difflib.get_close_matches(name, list(choices), n=1, cutoff=CUTOFF)
    return f"; did you mean {close[0]!r}?" if close else ""
