# SPDX-License-Identifier: BSD-3-Clause
"""Comparison plots (matplotlib, Agg backend): trajectories over the anchor map with NLOS
ranges marked, error against time per method (the papers' Fig. 5-8), error CDF, range
residuals per anchor. All positions in the map frame, metres; times in seconds from the
log's first stamp.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from uwbfuse.config import Config
from uwbfuse.streams import NS_PER_S, PoseStream, SensorLog

if TYPE_CHECKING:
    from uwbfuse.compare import MethodRow

# A range counts as NLOS in the plots when it is this many sigmas longer than predicted.
NLOS_SIGMAS = 3.0
# Smoothers are the best reference for residuals when the log has no ground truth.
_REFERENCE_ORDER = ("batch", "isam2-smoothed", "isam2", "ekf", "ukf")


def _pyplot():  # returns the matplotlib.pyplot module
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _reference(log_data: SensorLog, rows: list[MethodRow]) -> tuple[PoseStream | None, str]:
    if log_data.ground_truth is not None and len(log_data.ground_truth) > 1:
        return log_data.ground_truth, "ground truth"
    by_name = {r.method: r for r in rows if r.trajectory is not None}
    for name in _REFERENCE_ORDER:
        if name in by_name:
            return by_name[name].trajectory, name
    return None, ""


def plot_comparison(
    log_data: SensorLog, rows: list[MethodRow], config: Config, out: Path
) -> list[Path]:
    """Write the four comparison PNGs into `out`; returns their paths."""
    from uwbfuse.compare import range_residuals

    plt = _pyplot()
    t0_ns = log_data.time_span_ns()[0]
    ref, ref_name = _reference(log_data, rows)
    files: list[Path] = []
    ok = [r for r in rows if r.trajectory is not None and len(r.trajectory)]
    colors = {r.method: f"C{i}" for i, r in enumerate(ok)}

    if ref is not None:
        t_r, anchor_r, resid, tag_xy = range_residuals(log_data, ref, config)
    else:
        t_r = resid = np.zeros(0)
        anchor_r = np.zeros(0, dtype=int)
        tag_xy = np.zeros((0, 2))
    nlos = resid > NLOS_SIGMAS * config.uwb.sigma

    # 1. Trajectories over the anchor map.
    fig, ax = plt.subplots(figsize=(9, 7))
    if log_data.anchors is not None:
        a = log_data.anchors
        ax.scatter(a.positions[:, 0], a.positions[:, 1], marker="^", s=90, c="k", zorder=5,
                   label="anchors")
        for aid, p in zip(a.ids, a.positions, strict=True):
            ax.annotate(aid, (p[0], p[1]), textcoords="offset points", xytext=(4, 4))
    gt = log_data.ground_truth
    if gt is not None and len(gt):
        ax.plot(gt.position[:, 0], gt.position[:, 1], "k-", lw=2.0, alpha=0.6,
                label="ground truth")
    for r in ok:
        tr = r.trajectory
        ax.plot(tr.position[:, 0], tr.position[:, 1], "-", lw=1.0, c=colors[r.method],
                label=r.method)
    if np.any(nlos):
        ax.scatter(tag_xy[nlos, 0], tag_xy[nlos, 1], marker="x", s=12, c="r", alpha=0.5,
                   label=f"NLOS range (> {NLOS_SIGMAS:g} sigma long vs {ref_name})")
    _frame_on_site(ax, log_data, ref)
    ax.set_xlabel("x [m] (map frame)")
    ax.set_ylabel("y [m] (map frame)")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="best", fontsize=8)
    ax.set_title("Trajectories over the anchor map")
    files.append(_save(fig, out / "trajectories.png", plt))

    scored = [r for r in ok if r.metrics is not None]
    # 2. Error against time per method.
    fig, ax = plt.subplots(figsize=(10, 4.5))
    for r in scored:
        m = r.metrics
        ax.plot((m.t_ns - t0_ns) / NS_PER_S, m.ate_2d_errors, lw=1.0, c=colors[r.method],
                label=f"{r.method} (RMSE {m.ate_2d.rmse:.3f} m)")
    ax.set_xlabel("time [s]")
    ax.set_ylabel("2-D position error [m]")
    if scored and _wide_range(scored):
        ax.set_yscale("log")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="best", fontsize=8)
    ax.set_title("Position error against time" if scored else "No ground truth in this log")
    files.append(_save(fig, out / "error_vs_time.png", plt))

    # 3. Error CDF.
    fig, ax = plt.subplots(figsize=(7, 4.5))
    for r in scored:
        e = np.sort(r.metrics.ate_2d_errors)
        ax.plot(e, np.arange(1, len(e) + 1) / len(e), c=colors[r.method], label=r.method)
    ax.set_xlabel("2-D position error [m]")
    ax.set_ylabel("fraction of epochs")
    if scored and _wide_range(scored):
        ax.set_xscale("log")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="best", fontsize=8)
    ax.set_title("Error CDF")
    files.append(_save(fig, out / "error_cdf.png", plt))

    # 4. Range residuals per anchor.
    n_anchor = len(log_data.anchors) if log_data.anchors is not None else 0
    fig, axes = plt.subplots(max(n_anchor, 1), 1, figsize=(10, 1.8 * max(n_anchor, 1) + 1),
                             sharex=True, squeeze=False)
    for k in range(n_anchor):
        ax = axes[k, 0]
        sel = anchor_r == k
        tt = t_r[sel] - (t0_ns / NS_PER_S)
        ax.plot(tt, resid[sel], ".", ms=2, c="C0")
        ax.plot(tt[nlos[sel]], resid[sel][nlos[sel]], ".", ms=3, c="r")
        ax.axhline(0.0, c="k", lw=0.5)
        ax.set_ylabel(f"{log_data.anchors.ids[k]} [m]")
        ax.grid(True, alpha=0.3)
    axes[-1, 0].set_xlabel("time [s]")
    axes[0, 0].set_title(f"Range residuals per anchor (measured - predicted from {ref_name}; "
                         f"red: NLOS > {NLOS_SIGMAS:g} sigma)" if ref is not None
                         else "Range residuals: no reference trajectory")
    files.append(_save(fig, out / "range_residuals.png", plt))
    return files


def _frame_on_site(ax: object, log_data: SensorLog, ref: PoseStream | None) -> None:
    """Limit the axes to the anchors and the reference track (a diverged dead-reckoning
    track would otherwise shrink the site to a dot); equal scale on x and y."""
    pts = []
    if log_data.anchors is not None:
        pts.append(log_data.anchors.positions[:, :2])
    if ref is not None:
        pts.append(ref.position[:, :2])
    if pts:
        xy = np.vstack(pts)
        lo, hi = xy.min(axis=0), xy.max(axis=0)
        margin = 0.1 * max(float(np.max(hi - lo)), 1.0)
        ax.set_xlim(lo[0] - margin, hi[0] + margin)
        ax.set_ylim(lo[1] - margin, hi[1] + margin)
    ax.set_aspect("equal", adjustable="box")


def _wide_range(rows: list[MethodRow]) -> bool:
    rmse = [r.metrics.ate_2d.rmse for r in rows if r.metrics is not None]
    return bool(rmse) and max(rmse) / max(min(rmse), 1e-6) > 30


def _save(fig: object, path: Path, plt: object) -> Path:
    from uwbfuse.errors import ConfigError
    from uwbfuse.io.atomic import atomic_open

    fig.tight_layout()
    try:
        with atomic_open(path, "wb", error=ConfigError, what="plot") as f:
            fig.savefig(f, dpi=110, format="png")
    finally:
        plt.close(fig)
    return path
