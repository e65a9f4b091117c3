# SPDX-License-Identifier: BSD-3-Clause
"""The map with the tracks and the predicted events (matplotlib, Agg backend), map frame."""

from __future__ import annotations

import io
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from uwbfuse.safety.classify import Check, Kind
from uwbfuse.safety.fleet import Track
from uwbfuse.safety.geometry import ObstacleMap


def plot_events(path: Path, tracks: Sequence[Track], obstacles: ObstacleMap,
                checks: Sequence[Check]) -> Path:
    """Write a PNG: obstacles grey, one line per track, warnings and collisions marked at
    the position of vehicle `a` at the epoch they were predicted."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from uwbfuse.fleet import write_atomic

    fig, ax = plt.subplots(figsize=(9, 6))
    try:
        for ring, filled in obstacles.outlines():
            if filled:
                ax.fill(ring[:, 0], ring[:, 1], color="0.75", edgecolor="0.4", lw=0.8,
                        zorder=1)
            else:
                ax.plot(ring[:, 0], ring[:, 1], color="0.3", lw=1.5, zorder=1)
        by_name = {t.name: t.state for t in tracks}
        for t in tracks:
            ax.plot(t.state.x, t.state.y, lw=0.8, label=t.name, zorder=2)
        for kind, style in ((Kind.WARNING, dict(marker="^", color="orange", s=14)),
                            (Kind.COLLISION, dict(marker="x", color="red", s=22))):
            xs, ys = [], []
            for c in checks:
                st = by_name[c.a]
                sel = c.t_ns[c.kind == kind]
                if len(sel):
                    xs.append(np.interp(sel, st.t_ns, st.x))
                    ys.append(np.interp(sel, st.t_ns, st.y))
            if xs:
                x, y = np.concatenate(xs), np.concatenate(ys)
                ax.scatter(x, y, label=f"{kind.name.lower()} ({len(x)})", zorder=3, **style)
        ax.set_aspect("equal", adjustable="datalim")
        ax.set_xlabel("x (m, map frame)")
        ax.set_ylabel("y (m, map frame)")
        ax.set_title("Predicted conflicts over the control delay")
        ax.legend(loc="upper right", fontsize=7)
        buf = io.BytesIO()
        fig.savefig(buf, dpi=110, format="png")
    finally:
        plt.close(fig)
    write_atomic(path, buf.getvalue())
    return path
