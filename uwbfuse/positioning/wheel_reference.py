# SPDX-License-Identifier: BSD-3-Clause
"""The NLOS classifier's causal reference on wheeled logs: the wheel track placed in the map
by a robust fit to the ranges of the last few seconds, without the range's own anchor.

For each epoch (the WLS epochs of `nlos_classifier`), the ranges of the last `REFERENCE_WINDOW_S`
seconds up to and including the epoch are fitted with one planar rigid transform (x, y,
yaw) that carries the wheel track's tag positions into the map frame: the wheel track gives
the shape of the path over the window to a few cm, the ranges only its place and heading,
so a range is checked against every range of the window, not only against its own epoch's
three or four. The fit is made once per anchor with that anchor's ranges left out (so its
own NLOS excess cannot pull the reference towards itself), with a Cauchy kernel of scale
`[uwb] sigma` (an NLOS excess is several LOS stds). A range's reference is its anchor's
transform of the latest epoch before it, applied to the tag's track position at its stamp.

Causal: the track at a stamp uses the wheel samples up to that stamp (the last one's twist
carried on), and the fit only ranges of epochs that ended before the range.

Wheel gaps: where the wheel stream stops for more than `MAX_WHEEL_GAP_S` there is no
reference, and the fits after it take only the ranges after it and start again from the
fixes.

Start: a transform needs WLS fixes that span `MIN_SPREAD_M` of track (a still vehicle's
heading is not seen by ranges); until then, and after a fit that lost the ranges (fewer
than `MIN_INLIER_SHARE` within 3 scales), the transform is the least-squares rigid fit
(Procrustes) of the window's fixes to the track, else there is none (the caller's CV line
serves).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from uwbfuse.constants import (
    MAX_WHEEL_GAP_S,
    MIN_INLIER_SHARE,
    MIN_SPREAD_M,
    REFERENCE_ITERATIONS,
    REFERENCE_MIN_RANGES,
    REFERENCE_WINDOW_S,
    STEP_INFO,
)
from uwbfuse.positioning.wheel_track import WheelTrack, arc_steps
from uwbfuse.streams import NS_PER_S, WheelStream

F64 = NDArray[np.float64]



def causal_track_points(wheel: WheelStream, t_ns: NDArray[np.int64], tag_xy: F64
                        ) -> tuple[F64, NDArray[np.bool_]]:
    """The tag antenna's planar position (N,2) in the wheel track's frame at each stamp,
    from the wheel samples stamped up to it; ok (N,) False before the first sample and after
    a gap of more than MAX_WHEEL_GAP_S."""
    wt = WheelTrack()
    wt.add(wheel.t_ns, wheel.v, wheel.omega)
    n = len(t_ns)
    if not len(wt):
        return np.zeros((n, 2)), np.zeros(n, bool)
    i = np.searchsorted(wt.t, t_ns, side="right") - 1
    ok = i >= 0
    ic = np.maximum(i, 0)
    tau = (t_ns - wt.t[ic]) / NS_PER_S
    ok &= tau <= MAX_WHEEL_GAP_S
    base = wt.pose[ic]
    dyaw = wt.w[ic] * tau
    dx, dy = arc_steps(wt.v[ic], tau, base[:, 2], dyaw)
    yaw = base[:, 2] + dyaw
    c, s = np.cos(yaw), np.sin(yaw)
    q = np.column_stack([base[:, 0] + dx + c * tag_xy[0] - s * tag_xy[1],
                         base[:, 1] + dy + s * tag_xy[0] + c * tag_xy[1]])
    return q, ok


def _apply(tf: F64, q: F64) -> F64:
    """Transforms tf (..., 3) = (x, y, yaw) applied to points q (..., n, 2)."""
    c, s = np.cos(tf[..., 2])[..., None], np.sin(tf[..., 2])[..., None]
    return np.stack([c * q[..., 0] - s * q[..., 1] + tf[..., 0, None],
                     s * q[..., 0] + c * q[..., 1] + tf[..., 1, None]], axis=-1)


def _procrustes(q: F64, p: F64) -> F64:
    """Rigid 2-D transform (x, y, yaw) taking points q (n,2) onto p (n,2), least squares;
    where q spans less than MIN_SPREAD_M (a still vehicle) the yaw is left at 0: it moves
    nothing until the track moves, and the fits find it as it does."""
    mq, mp = q.mean(0), p.mean(0)
    yaw = 0.0
    if np.sqrt(np.mean(np.sum((q - mq) ** 2, axis=1))) >= MIN_SPREAD_M:
        h = (q - mq).T @ (p - mp)
        yaw = float(np.arctan2(h[0, 1] - h[1, 0], h[0, 0] + h[1, 1]))
    c, s = np.cos(yaw), np.sin(yaw)
    t = mp - np.array([[c, -s], [s, c]]) @ mq
    return np.array([t[0], t[1], yaw])


def _fit(tf: F64, q: F64, anchor_xy: F64, d: F64, use: NDArray[np.bool_], scale: float
         ) -> tuple[F64, F64]:
    """Robust Gauss-Newton of B transforms at once: tf (B,3) warm starts, the window's track
    points q (n,2), anchors (n,2), planar ranges d (n,) m, use (B,n) which ranges each fit
    takes. Returns the transforms (B,3) and each fit's share of used ranges within 3
    scales (B,)."""
    x = tf.copy()
    nb = len(x)
    w_use = use.astype(np.float64)
    share = np.zeros(nb)
    for it in range(REFERENCE_ITERATIONS):
        m = _apply(x, np.broadcast_to(q, (nb, *q.shape)))  # (B,n,2)
        diff = m - anchor_xy
        r = np.linalg.norm(diff, axis=-1)
        u = diff / np.maximum(r, 1e-9)[..., None]
        res = r - d
        centre = (w_use[..., None] * m).sum(1) / np.maximum(w_use.sum(1), 1.0)[:, None]
        lever = m - centre[:, None, :]  # a yaw step turns about the window's centre
        jac = np.concatenate([u, (u[..., 1] * lever[..., 0] - u[..., 0] * lever[..., 1])[
            ..., None]], axis=-1)
        c = scale * (3.0 if it < 2 else 1.0)  # start wide: the warm start may be off
        w = w_use / (1.0 + (res / c) ** 2) / (scale * scale)  # Cauchy weight / std^2
        h = np.einsum("bn,bni,bnj->bij", w, jac, jac) + np.diag(STEP_INFO)
        g = np.einsum("bn,bni,bn->bi", w, jac, res) + STEP_INFO * (x - tf)
        step = -np.linalg.solve(h, g[..., None])[..., 0]
        # the yaw step turns about the centre: x' = R(dyaw)(x_map - centre) + centre + dt
        cy, sy = np.cos(step[:, 2]), np.sin(step[:, 2])
        tx, ty = x[:, 0] - centre[:, 0], x[:, 1] - centre[:, 1]
        x = np.column_stack([cy * tx - sy * ty + centre[:, 0] + step[:, 0],
                             sy * tx + cy * ty + centre[:, 1] + step[:, 1],
                             x[:, 2] + step[:, 2]])
        share = ((np.abs(res) < 3.0 * scale) & use).sum(1) / np.maximum(use.sum(1), 1)
        if np.max(np.abs(step[:, :2])) < 1e-4:
            break
    return x, share


def wheel_reference(
    t_ns: NDArray[np.int64], anchor: NDArray[np.int32], d_planar: F64, anchor_xy: F64,
    wheel: WheelStream, tag_xy: F64, ep: NDArray[np.int64], fix_xy: F64,
    fix_ok: NDArray[np.bool_], scale: float,
) -> tuple[F64, NDArray[np.bool_]]:
    """Reference tag position (N,2) of each range (module docstring) and where there is one
    (N,). t_ns (N,) sorted stamps, anchor (N,) indices, d_planar (N,) ranges projected to
    the tag height (m), anchor_xy (M,2), ep (K,) epoch stamps, fix_xy (K,2) and fix_ok (K,)
    the epochs' WLS fixes, scale m the Cauchy scale."""
    m_anchors = len(anchor_xy)
    q, q_ok = causal_track_points(wheel, t_ns, tag_xy)
    qe, qe_ok = causal_track_points(wheel, ep, tag_xy)
    k_n = len(ep)
    tf = np.full((k_n, m_anchors, 3), np.nan)  # per epoch, per left-out anchor
    # a window starts after the latest wheel gap: across one the track's shape is a guess
    wt_ns = np.asarray(wheel.t_ns, np.int64)
    gap_end = wt_ns[1:][np.diff(wt_ns) > round(MAX_WHEEL_GAP_S * NS_PER_S)]
    seg = np.searchsorted(gap_end, ep, side="right") - 1  # the wheel segment of each epoch
    start = ep - round(REFERENCE_WINDOW_S * NS_PER_S)
    if len(gap_end):
        start = np.maximum(start, np.where(seg >= 0, gap_end[np.maximum(seg, 0)] - 1, start))
    lo_r = np.searchsorted(t_ns, start, side="right")
    hi_r = np.searchsorted(t_ns, ep, side="right")
    lo_f = np.searchsorted(ep, start, side="right")
    cur: F64 | None = None  # the previous epoch's transform fitted to every anchor
    # one Python step per epoch, not per range: each fit warm-starts from the previous
    # epoch's and a lost one restarts from the fixes (a recursion in time); the fits of one
    # epoch (one per left-out anchor, and the one with all) are batched in `_fit`
    for k in range(k_n):
        if k and seg[k] != seg[k - 1]:
            cur = None  # a new wheel segment: the track's frame has moved against the map
        sel = np.arange(lo_r[k], hi_r[k])
        sel = sel[q_ok[sel]]
        if cur is None:
            fs = np.arange(lo_f[k], k + 1)
            fs = fs[fix_ok[fs] & qe_ok[fs]]
            if len(fs) < 3:
                continue
            cur = _procrustes(qe[fs], fix_xy[fs])
        # one fit per left-out anchor, and one with every anchor (the next warm start)
        use = anchor[sel][None, :] != np.arange(m_anchors + 1)[:, None]
        fit, share = _fit(np.tile(cur, (m_anchors + 1, 1)), q[sel], anchor_xy[anchor[sel]],
                          d_planar[sel], use, scale)
        enough = use.sum(1) >= REFERENCE_MIN_RANGES
        if not enough[-1]:
            continue
        if share[-1] < MIN_INLIER_SHARE:  # lost: start again from the fixes
            cur = None
            continue
        cur = fit[-1]
        tf[k] = np.where(enough[:-1, None], fit[:-1], np.nan)
    j = np.searchsorted(ep, t_ns, side="left") - 1  # the latest epoch before each range
    tj = tf[np.maximum(j, 0), anchor]
    ok = (j >= 0) & q_ok & np.isfinite(tj[:, 0])
    ref = _apply(np.where(ok[:, None], tj, 0.0), q[:, None, :])[:, 0, :]
    return ref, ok
