# SPDX-License-Identifier: BSD-3-Clause
"""Comparison plots (matplotlib, Agg backend), one PNG each:

- `trajectories.png`: the site view (anchors, every track) beside an auto-zoomed view of
  the stretch where the methods disagree most, both with equal x/y scale;
- `error_track.png`: one method's track coloured by its position error (evo's
  `--plot_colormap`);
- `xy_yaw_vs_time.png`: x, y and yaw of every method and the ground truth against time;
- `error_vs_time.png`, `error_cdf.png`: 2-D position error per method (the papers' Fig. 5-8);
- `range_residuals.png`: range residuals per anchor, NLOS marked as an estimator classified
  them (never by a rule of the plot's own).

Every method keeps one colour in every plot (`METHOD_COLORS`, Paul Tol's colour-blind safe
"muted" scheme); NLOS ranges are black crosses, a colour and marker no method uses; the
ground truth is a wide grey line. Positions in the map frame, metres; times in seconds from
the log's first stamp.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from uwbfuse.config import Config
from uwbfuse.eval.metrics import wrap_angle, yaw_of
from uwbfuse.methods import by_reference_rank
from uwbfuse.streams import NS_PER_S, PoseStream, SensorLog

if TYPE_CHECKING:
    from uwbfuse.compare import MethodRow, RangeResiduals
    from uwbfuse.estimator import RangeClasses

METHOD_COLORS = {
    "isam2": "#332288",  # indigo
    "batch": "#117733",  # green
    "ekf": "#CC6677",  # rose
    "ukf": "#88CCEE",  # cyan
    "wls": "#DDCC77",  # sand: light, the noisy per-epoch fixes stay in the background
    "lkf": "#44AA99",  # teal
    "isam2-smoothed": "#AA4499",  # purple
    "imu": "#882255",  # wine
    "odom": "#999933",  # olive
}
"""Fixed colour per method (Tol muted); none is black or grey, kept for NLOS marks and GT."""
METHOD_DASHES = {"ukf": (0, (5, 3)), "isam2-smoothed": (0, (5, 3)), "lkf": (0, (1, 2))}
"""Dashed lines for the methods whose tracks often lie on another's (ukf on ekf,
isam2-smoothed on batch, lkf on wls), so both stay visible."""
OTHER_COLOR = "#BBBBBB"
GT_STYLE: dict[str, Any] = {"c": "#555555", "lw": 3.0, "alpha": 0.45, "zorder": 1}
NLOS_STYLE: dict[str, Any] = {"marker": "x", "c": "black", "linewidths": 0.9, "zorder": 6}
# The best reference for residuals when the log has no ground truth (smoothers first), and
# whose NLOS classification the plots show, best informed first: the registry's ranks.
_REFERENCE_ORDER = tuple(m.value for m in by_reference_rank())
_CLASSIFIER_ORDER = tuple(m.value for m in by_reference_rank(classifying=True))
ZOOM_ERROR_MULTIPLE = 10.0
"""Zoom window side in multiples of the typical method error (median over the methods of
their 90th percentile): errors then take a tenth of the window, enough to see which track
is where."""
ZOOM_MIN_M = 1.0
"""Smallest zoom window side, m (about a vehicle's length)."""
DIVERGED_SHARE = 0.25
"""A track whose median error exceeds this share of the site's size is left out of choosing
the zoom (a dead-reckoning drift would otherwise set the window)."""
NOISY_YAW_DEG = 20.0
"""Yaw RMSE above which a method's heading is drawn as dots (a track-direction heading
from noisy fixes), deg."""
SMOOTH_S = 2.0
"""Window of the moving median that picks the zoom's time, s (a few range epochs)."""


def method_color(name: str) -> str:
    """The method's fixed colour (grey for a name outside `METHOD_COLORS`)."""
    return METHOD_COLORS.get(name, OTHER_COLOR)


def method_style(name: str, lw: float = 1.0) -> dict[str, Any]:
    """Line keywords of the method's tracks and curves in every plot."""
    return {"c": method_color(name), "ls": METHOD_DASHES.get(name, "-"), "lw": lw, "zorder": 3}


def _pyplot():  # returns the matplotlib.pyplot module
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


@dataclass
class _Scene:
    """What every plot draws from: the log, the methods that ran, the reference."""

    log: SensorLog
    rows: list[MethodRow]  # methods with a trajectory, in the order asked for
    ref: PoseStream | None
    ref_name: str
    t0_ns: int

    def t_s(self, t_ns: np.ndarray) -> np.ndarray:
        return (np.asarray(t_ns) - self.t0_ns) / NS_PER_S


def _reference(log_data: SensorLog, rows: list[MethodRow]) -> tuple[PoseStream | None, str]:
    if log_data.ground_truth is not None and len(log_data.ground_truth) > 1:
        return log_data.ground_truth, "ground truth"
    by_name = {r.method: r for r in rows if r.trajectory is not None}
    for name in _REFERENCE_ORDER:
        if name in by_name:
            return by_name[name].trajectory, name
    return None, ""


def nlos_classifier(rows: list[MethodRow]) -> tuple[str, RangeClasses | None]:
    """The method whose own per-range NLOS classification the plots show, and it; ("",
    None) when no method in `rows` reports one."""
    by_name = {r.method: r for r in rows if r.range_classes is not None}
    for name in (*_CLASSIFIER_ORDER, *by_name):
        if name in by_name:
            return name, by_name[name].range_classes
    return "", None


def plot_comparison(
    log_data: SensorLog, rows: list[MethodRow], config: Config, out: Path,
    colormap_method: str | None = None,
) -> list[Path]:
    """Write the comparison PNGs into `out`; returns their paths.

    colormap_method: the method of `error_track.png` (default: the first scored one).
    """
    from uwbfuse.compare import RangeResiduals, range_residuals

    plt = _pyplot()
    ok = [r for r in rows if r.trajectory is not None and len(r.trajectory)]
    ref, ref_name = _reference(log_data, rows)
    scene = _Scene(log_data, ok, ref, ref_name, log_data.time_span_ns()[0])
    resid = range_residuals(log_data, ref, config) if ref is not None else RangeResiduals.empty()
    who, classes = nlos_classifier(ok)
    cls = resid.classified_nlos(classes) if classes is not None else None
    note = nlos_note(who, ok)
    files = [
        _trajectories(plt, scene, resid, cls, note, out / "trajectories.png"),
        _error_track(plt, scene, colormap_method, out / "error_track.png"),
        _xy_yaw(plt, scene, out / "xy_yaw_vs_time.png"),
        _error_vs_time(plt, scene, out / "error_vs_time.png"),
        _error_cdf(plt, scene, out / "error_cdf.png"),
        _residuals(plt, scene, resid, cls, note, out / "range_residuals.png"),
    ]
    return files


def nlos_note(classifier: str, rows: list[MethodRow]) -> str:
    """The plots' line on where their NLOS marks come from (`classifier` from
    `nlos_classifier`; empty: no marks, and which methods ran)."""
    if classifier:
        return f"NLOS: {classifier}'s own classification (P(NLOS) > 0.5)"
    names = ", ".join(r.method for r in rows) or "none"
    return (f"no NLOS marks: no method here reports a per-range NLOS classification (ran: "
            f"{names}; {', '.join(_CLASSIFIER_ORDER)} do)")


# ---------------------------------------------------------------- trajectories
def _anchors(ax: Any, log_data: SensorLog, labels: bool = True) -> None:
    a = log_data.anchors
    if a is None:
        return
    ax.scatter(a.positions[:, 0], a.positions[:, 1], marker="^", s=90, facecolors="white",
               edgecolors="black", linewidths=1.5, zorder=5, label="anchors")
    if labels:
        for aid, p in zip(a.ids, a.positions, strict=True):
            ax.annotate(aid, (p[0], p[1]), textcoords="offset points", xytext=(5, 5))


def _tracks(ax: Any, scene: _Scene, lw: float) -> None:
    gt = scene.log.ground_truth
    if gt is not None and len(gt):
        ax.plot(gt.position[:, 0], gt.position[:, 1], "-", label="ground truth", **GT_STYLE)
    for r in scene.rows:
        tr = r.trajectory
        ax.plot(tr.position[:, 0], tr.position[:, 1], label=r.method,
                **method_style(r.method, lw))


def _trajectories(
    plt: Any, scene: _Scene, resid: RangeResiduals, cls: np.ndarray | None, nlos_note: str,
    path: Path,
) -> Path:
    fig, (site, zoom) = plt.subplots(1, 2, figsize=(15, 7.2))
    window = zoom_window(scene)
    for ax, lw in ((site, 1.0), (zoom, 1.6)):
        _anchors(ax, scene.log, labels=ax is site)
        _tracks(ax, scene, lw)
        if cls is not None and np.any(cls == 1):
            nl = cls == 1
            ax.scatter(resid.tag_xy[nl, 0], resid.tag_xy[nl, 1], s=16 if ax is zoom else 8,
                       label=f"NLOS range at the tag ({scene.ref_name} position)",
                       **{**NLOS_STYLE, "alpha": 0.35, "linewidths": 0.6, "zorder": 2})
        ax.set_xlabel("x [m] (map frame)")
        ax.set_ylabel("y [m] (map frame)")
        ax.grid(True, alpha=0.3)
    _frame_on_site(site, scene.log, scene.ref)
    site.set_title("Site: anchors and all tracks")
    if window is not None:
        (cx, cy), side, when = window
        h = side / 2
        zoom.set_xlim(cx - h, cx + h)
        zoom.set_ylim(cy - h, cy + h)
        zoom.set_aspect("equal", adjustable="box")
        from matplotlib.patches import Rectangle

        site.add_patch(Rectangle((cx - h, cy - h), side, side, fill=False, ec="black",
                                 ls="--", lw=1.0, zorder=7))
        zoom.set_title(f"Zoom ({side:.1f} m square, dashed on the left): where the tracks "
                       f"differ most{when}", fontsize=10)
    else:
        zoom.set_title("Zoom: no reference track to choose a window")
    handles, labels = site.get_legend_handles_labels()
    if labels:
        fig.legend(handles, labels, loc="lower center", ncol=min(len(labels), 6), fontsize=9,
                   frameon=False)
    fig.suptitle(f"Trajectories ({nlos_note})", fontsize=11)
    fig.tight_layout(rect=(0, 0.07, 1, 1))
    return _save(fig, path, plt, tight=False)


def _tracks_at_reference(scene: _Scene) -> np.ndarray:
    """Each method's x, y (m) at the reference's stamps (methods x N x 2), NaN outside a
    method's time span."""
    ref = scene.ref
    assert ref is not None
    xy = np.full((len(scene.rows), len(ref), 2), np.nan)
    for k, r in enumerate(scene.rows):
        tr = r.trajectory
        if len(tr) < 2:
            continue
        inside = (ref.t_ns >= tr.t_ns[0]) & (ref.t_ns <= tr.t_ns[-1])
        for i in (0, 1):
            xy[k, inside, i] = np.interp(ref.t_ns[inside], tr.t_ns, tr.position[:, i])
    return xy


def zoom_window(scene: _Scene) -> tuple[tuple[float, float], float, str] | None:
    """Centre (x, y) m, side m and a caption of the auto-zoom: a square `ZOOM_ERROR_MULTIPLE`
    times the methods' typical error (90th percentile over the tracks that stay on site),
    at most half the reference track's extent, centred on the reference position where
    those tracks and the reference lie farthest apart (median distance from their median
    position, moving
    median over `SMOOTH_S`). The reference's bounding box when no track overlaps it; None
    without a reference."""
    ref = scene.ref
    if ref is None or len(ref) < 2:
        return None
    xy = ref.position[:, :2]
    lo, hi = xy.min(axis=0), xy.max(axis=0)
    extent = max(float(np.max(hi - lo)), ZOOM_MIN_M)
    whole = ((float(lo[0] + hi[0]) / 2, float(lo[1] + hi[1]) / 2), 1.1 * extent,
             " (the whole track)")
    tracks = _tracks_at_reference(scene)
    errs = np.linalg.norm(tracks - xy[None], axis=2)
    with warnings.catch_warnings():  # a track may not overlap the reference at all
        warnings.simplefilter("ignore", RuntimeWarning)
        med = np.nanmedian(errs, axis=1) if len(errs) else np.zeros(0)
        keep = np.isfinite(med) & (med < DIVERGED_SHARE * _site_size(scene.log, ref))
        if not np.any(keep):
            return whole
        e, kept = errs[keep], tracks[keep]
        typical = float(np.nanmedian(np.nanpercentile(e, 90, axis=1)))
        # how far the tracks and the reference lie from each other: median distance from
        # their median position (one jittery or drifting track does not set it)
        pts = np.concatenate([kept, xy[None]])
        spread = np.nanmedian(np.linalg.norm(pts - np.nanmedian(pts, axis=0)[None], axis=2),
                              axis=0)
    side = min(max(ZOOM_ERROR_MULTIPLE * typical, ZOOM_MIN_M), 0.5 * extent)
    every = np.all(np.isfinite(e), axis=0)  # prefer stamps where every kept track has a pose
    spread = np.where(every if np.any(every) else np.isfinite(spread), spread, 0.0)
    dt = float(np.median(np.diff(ref.t_ns))) / NS_PER_S
    k = max(round(SMOOTH_S / max(dt, 1e-3)), 1)
    if k > 1 and len(spread) > k:
        from scipy.ndimage import median_filter

        spread = median_filter(spread, size=k, mode="nearest")
    i = int(np.argmax(spread))
    t = scene.t_s(ref.t_ns[i])
    return (float(xy[i, 0]), float(xy[i, 1])), side, f", t = {float(t):.0f} s"


def _site_size(log_data: SensorLog, ref: PoseStream) -> float:
    pts = [ref.position[:, :2]]
    if log_data.anchors is not None:
        pts.append(log_data.anchors.positions[:, :2])
    xy = np.vstack(pts)
    return max(float(np.max(xy.max(axis=0) - xy.min(axis=0))), ZOOM_MIN_M)


def _frame_on_site(ax: Any, log_data: SensorLog, ref: PoseStream | None) -> None:
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


# ---------------------------------------------------------------- error-coloured track
def _error_track(plt: Any, scene: _Scene, method: str | None, path: Path) -> Path:
    from matplotlib.collections import LineCollection

    scored = [r for r in scene.rows if r.metrics is not None]
    pick = next((r for r in scored if r.method == method), None) if method else None
    pick = pick or (scored[0] if scored else None)
    fig, ax = plt.subplots(figsize=(9, 7.5))
    if pick is None:
        ax.text(0.5, 0.5, "no ground truth: no error to colour the track by",
                ha="center", va="center", transform=ax.transAxes)
        ax.set_axis_off()
        return _save(fig, path, plt)
    m = pick.metrics
    aligned = m.align.value != "none"
    both = np.vstack([m.gt_position[:, :2], m.est_position[:, :2]])
    lo, hi = both.min(axis=0), both.max(axis=0)
    margin = 0.05 * max(float(np.max(hi - lo)), ZOOM_MIN_M)
    lo, hi = lo - margin, hi + margin
    ratio = float(np.clip((hi[1] - lo[1]) / (hi[0] - lo[0]), 0.25, 1.0))
    mid, half = (lo[1] + hi[1]) / 2, max(hi[1] - lo[1], ratio * (hi[0] - lo[0])) / 2
    lo[1], hi[1] = mid - half, mid + half  # a thin track gets a box of at least 1:4
    fig.set_size_inches(11, 11 * ratio + 1.8)
    ax.plot(m.gt_position[:, 0], m.gt_position[:, 1], "-", label="ground truth", **GT_STYLE)
    p = m.est_position[:, :2]
    seg = np.stack([p[:-1], p[1:]], axis=1)
    err = 0.5 * (m.ate_2d_errors[:-1] + m.ate_2d_errors[1:])
    top = float(np.percentile(m.ate_2d_errors, 99)) if len(err) else 1.0
    lc = LineCollection(seg, cmap="viridis", linewidths=2.2, zorder=3)
    lc.set_array(err)
    lc.set_clim(0.0, max(top, 1e-3))
    ax.add_collection(lc)
    cb = fig.colorbar(lc, ax=ax, extend="max", orientation="horizontal", fraction=0.08,
                      pad=0.25 if ratio < 0.5 else 0.1, aspect=40)
    cb.set_label("2-D position error [m]")
    ax.set_xlim(lo[0], hi[0])
    ax.set_ylim(lo[1], hi[1])
    ax.set_aspect("equal", adjustable="box")
    frame = "ground-truth frame after alignment" if aligned else "map frame"
    ax.set_xlabel(f"x [m] ({frame})")
    ax.set_ylabel(f"y [m] ({frame})")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="best", fontsize=8)
    ax.set_title(f"{pick.method}: track coloured by its 2-D error "
                 f"(RMSE {m.ate_2d.rmse:.3f} m, max {m.ate_2d.max:.3f} m)")
    return _save(fig, path, plt)


# ---------------------------------------------------------------- x, y, yaw against time
def _yaw_deg_broken(t: np.ndarray, quat: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Yaw in degrees with NaN inserted at the +-180 deg wraps (no vertical lines)."""
    yaw = np.degrees(wrap_angle(yaw_of(quat)))
    jump = np.flatnonzero(np.abs(np.diff(yaw)) > 180.0) + 1
    return np.insert(t.astype(float), jump, np.nan), np.insert(yaw, jump, np.nan)


def _xy_yaw(plt: Any, scene: _Scene, path: Path) -> Path:
    fig, axes = plt.subplots(3, 1, figsize=(11, 8.5), sharex=True)
    gt = scene.log.ground_truth
    series = []
    if gt is not None and len(gt):
        series.append(("ground truth", gt, dict(GT_STYLE)))
    series += [(r.method, r.trajectory, method_style(r.method)) for r in scene.rows]
    noisy = {r.method for r in scene.rows
             if r.metrics is not None and r.metrics.yaw is not None
             and r.metrics.yaw.rmse > np.radians(NOISY_YAW_DEG)}
    for name, tr, style in series:
        t = scene.t_s(tr.t_ns)
        axes[0].plot(t, tr.position[:, 0], label=name, **style)
        axes[1].plot(t, tr.position[:, 1], **style)
        if tr.has_orientation and name in noisy:  # dots: lines would hide the others
            axes[2].plot(*_yaw_deg_broken(t, tr.quat_xyzw), ls="none", marker=".", ms=1.5,
                         c=style["c"], zorder=2)
        elif tr.has_orientation:
            axes[2].plot(*_yaw_deg_broken(t, tr.quat_xyzw), **style)
    ref = scene.ref
    if ref is not None:  # diverged tracks leave the axes rather than flatten the others
        for i in (0, 1):
            lo, hi = float(ref.position[:, i].min()), float(ref.position[:, i].max())
            pad = max(0.15 * (hi - lo), 0.5)
            axes[i].set_ylim(lo - pad, hi + pad)
    axes[0].set_ylabel("x [m] (map frame)")
    axes[1].set_ylabel("y [m] (map frame)")
    axes[2].set_ylabel("yaw [deg]")
    if ref is not None and ref.has_orientation:
        yaw = np.degrees(wrap_angle(yaw_of(ref.quat_xyzw)))
        lo, hi = float(yaw.min()), float(yaw.max())
        pad = max(0.15 * (hi - lo), 10.0)
        axes[2].set_ylim(max(lo - pad, -185.0), min(hi + pad, 185.0))
    else:
        axes[2].set_ylim(-185, 185)
        axes[2].set_yticks([-180, -90, 0, 90, 180])
    notes = []
    if gt is not None and len(gt) and not gt.has_orientation:
        notes.append("ground truth has no orientation: yaw of the methods only")
    if noisy:
        notes.append(f"dots: yaw RMSE over {NOISY_YAW_DEG:g} deg ({', '.join(sorted(noisy))})")
    if notes:
        axes[2].set_title("; ".join(notes), fontsize=9)
    axes[-1].set_xlabel("time [s]")
    for ax in axes:
        ax.grid(True, alpha=0.3)
    handles, labels = axes[0].get_legend_handles_labels()
    if labels:
        fig.legend(handles, labels, loc="lower center", ncol=min(len(labels), 8), fontsize=9,
                   frameon=False)
    fig.suptitle("Position and heading against time (base frame in the map frame)")
    fig.tight_layout(rect=(0, 0.04, 1, 1))
    return _save(fig, path, plt, tight=False)


# ---------------------------------------------------------------- errors
def _error_vs_time(plt: Any, scene: _Scene, path: Path) -> Path:
    scored = [r for r in scene.rows if r.metrics is not None]
    fig, ax = plt.subplots(figsize=(10, 4.5))
    for r in scored:
        m = r.metrics
        ax.plot(scene.t_s(m.t_ns), m.ate_2d_errors,
                label=f"{r.method} (RMSE {m.ate_2d.rmse:.3f} m)", **method_style(r.method))
    ax.set_xlabel("time [s]")
    ax.set_ylabel("2-D position error [m]")
    if scored and _wide_range(scored):
        ax.set_yscale("log")
    ax.grid(True, alpha=0.3)
    if scored:
        ax.legend(loc="best", fontsize=8)
    ax.set_title("Position error against time" if scored else "No ground truth in this log")
    return _save(fig, path, plt)


def _error_cdf(plt: Any, scene: _Scene, path: Path) -> Path:
    scored = [r for r in scene.rows if r.metrics is not None]
    fig, ax = plt.subplots(figsize=(7, 4.5))
    for r in scored:
        e = np.sort(r.metrics.ate_2d_errors)
        ax.plot(e, np.arange(1, len(e) + 1) / len(e), label=r.method, **method_style(r.method))
    ax.set_xlabel("2-D position error [m]")
    ax.set_ylabel("fraction of epochs")
    if scored and _wide_range(scored):
        ax.set_xscale("log")
    ax.grid(True, alpha=0.3)
    if scored:
        ax.legend(loc="best", fontsize=8)
    ax.set_title("Error CDF")
    return _save(fig, path, plt)


def _wide_range(rows: list[MethodRow]) -> bool:
    rmse = [r.metrics.ate_2d.rmse for r in rows if r.metrics is not None]
    return bool(rmse) and max(rmse) / max(min(rmse), 1e-6) > 30


# ---------------------------------------------------------------- range residuals
def _residuals(
    plt: Any, scene: _Scene, resid: RangeResiduals, cls: np.ndarray | None, nlos_note: str,
    path: Path,
) -> Path:
    anchors = scene.log.anchors
    n = len(anchors) if anchors is not None else 0
    fig, axes = plt.subplots(max(n, 1), 1, figsize=(10, 1.8 * max(n, 1) + 1.4), sharex=True,
                             squeeze=False)
    groups = (
        [(-1, "not classified (range not used by the method)", {"c": "#CCCCCC"}),
         (0, "LOS", {"c": "#777777"}),
         (2, "LOS, down-weighted by the robust kernel", {"c": "#777777", "marker": "o",
                                                          "mfc": "none", "ms": 5}),
         (1, "NLOS", {})]
        if cls is not None else [(None, "range", {"c": "#777777"})]
    )
    for k in range(n):
        ax = axes[k, 0]
        sel = resid.anchor == k
        tt = scene.t_s(resid.t_ns[sel])
        rr = resid.residual[sel]
        for code, _, style in groups:
            g = np.ones(len(tt), bool) if code is None else cls[sel] == code
            if code == 1:
                ax.scatter(tt[g], rr[g], s=14, **NLOS_STYLE)
            else:
                ax.plot(tt[g], rr[g], ls="none", **{"marker": ".", "ms": 2.5, **style})
        ax.axhline(0.0, c="k", lw=0.5)
        ax.set_ylabel(f"{anchors.ids[k]} [m]")
        ax.grid(True, alpha=0.3)
    axes[-1, 0].set_xlabel("time [s]")
    if scene.ref is None:
        axes[0, 0].set_title("Range residuals: no reference trajectory")
    else:
        axes[0, 0].set_title(f"Range residuals per anchor (measured - predicted from "
                             f"{scene.ref_name})\n{nlos_note}", fontsize=10)
    if n and len(resid.t_ns):
        from matplotlib.lines import Line2D

        present = [(code, label, style) for code, label, style in groups
                   if code is None or np.any(cls == code)]
        proxies = [
            Line2D([], [], ls="none", marker="x", c="black", ms=6) if code == 1 else
            Line2D([], [], ls="none", **{"marker": ".", "ms": 6, **style})
            for code, _, style in present
        ]
        fig.legend(proxies, [label for _, label, _ in present], loc="lower center",
                   ncol=len(present), fontsize=9, frameon=False)
    fig.tight_layout(rect=(0, 0.04, 1, 1))
    return _save(fig, path, plt, tight=False)


def _save(fig: Any, path: Path, plt: Any, tight: bool = True) -> Path:
    from uwbfuse.errors import ConfigError
    from uwbfuse.io.atomic import atomic_open

    if tight:
        fig.tight_layout()
    try:
        with atomic_open(path, "wb", error=ConfigError, what="plot") as f:
            fig.savefig(f, dpi=110, format="png")
    finally:
        plt.close(fig)
    return path
