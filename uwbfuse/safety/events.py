# SPDX-License-Identifier: BSD-3-Clause
"""The events table (CONTRACT.md: `events.csv` and `events.md`) and the per-pair summary.

One event per epoch and target that is not clear: `t` (TUM time of the epoch, s, 9
decimals), `kind` (warning | collision), `a` (vehicle), `b` (other vehicle or `map`),
`distance_m` (clearance of the predicted footprints, 0 on contact), `ttc_s` (time to
contact, empty when none within the control delay). Rows in time order. The summary counts
per pair the warning and collision epochs and the episodes (runs of consecutive collision
epochs) and gives the smallest clearance and time to contact.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from uwbfuse.safety.classify import Check, Kind
from uwbfuse.streams import NS_PER_S

EVENT_COLUMNS: tuple[str, ...] = ("t", "kind", "a", "b", "distance_m", "ttc_s")
SUMMARY_COLUMNS: tuple[str, ...] = (
    "a", "b", "epochs", "warning_epochs", "collision_epochs", "collision_episodes",
    "min_distance_m", "min_ttc_s",
)


def format_stamp(t_ns: int) -> str:
    """A stamp in ns as seconds with 9 decimals (as TUM files write it)."""
    sign = "-" if t_ns < 0 else ""
    q, r = divmod(abs(int(t_ns)), NS_PER_S)
    return f"{sign}{q}.{r:09d}"


def episodes(kind: np.ndarray, which: int = Kind.COLLISION) -> int:
    """Number of runs of consecutive epochs of `which` kind."""
    on = np.asarray(kind) == which
    return int(np.count_nonzero(on[1:] & ~on[:-1]) + (1 if len(on) and on[0] else 0))


def event_rows(checks: Sequence[Check]) -> list[dict[str, Any]]:
    """Every non-clear epoch of every check, in time order (then a, b)."""
    rows: list[tuple[int, str, str, dict[str, Any]]] = []
    for c in checks:
        for i in np.flatnonzero(c.kind != Kind.CLEAR):
            k = Kind(int(c.kind[i]))
            ttc = float(c.ttc[i])
            rows.append((int(c.t_ns[i]), c.a, c.b, {
                "t": format_stamp(int(c.t_ns[i])),
                "kind": k.name.lower(),
                "a": c.a,
                "b": c.b,
                "distance_m": f"{float(c.distance[i]):.3f}",
                "ttc_s": "" if math.isnan(ttc) else f"{ttc:.3f}",
            }))
    rows.sort(key=lambda r: r[:3])
    return [r[3] for r in rows]


def summary_rows(checks: Sequence[Check]) -> list[dict[str, Any]]:
    """One row per check (vehicle against the map, or a pair)."""
    out = []
    for c in checks:
        finite = c.distance[np.isfinite(c.distance)]
        ttc = c.ttc[np.isfinite(c.ttc)]
        out.append({
            "a": c.a, "b": c.b, "epochs": len(c),
            "warning_epochs": int(np.count_nonzero(c.kind == Kind.WARNING)),
            "collision_epochs": int(np.count_nonzero(c.kind == Kind.COLLISION)),
            "collision_episodes": episodes(c.kind),
            "min_distance_m": round(float(finite.min()), 3) if len(finite) else None,
            "min_ttc_s": round(float(ttc.min()), 3) if len(ttc) else None,
        })
    return out


def events_markdown(summary: list[dict[str, Any]], events: list[dict[str, Any]]) -> str:
    """`events.md`: the summary table, then the events table."""
    from uwbfuse.fleet import table_markdown

    return ("# Collision prediction\n\n## Summary\n\n" + table_markdown(SUMMARY_COLUMNS, summary)
            + f"\n## Events ({len(events)})\n\n" + table_markdown(EVENT_COLUMNS, events))
