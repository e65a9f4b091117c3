# SPDX-License-Identifier: BSD-3-Clause
"""Per-epoch UWB multilateration, vectorised over epochs.

Ranges of one epoch are a row of an (N, M) array over the M anchors of the `AnchorMap`,
NaN where an anchor has no range in that epoch. Positions are of the tag antenna in the map
frame (anchor frame, z up), metres.

- `linear_ls`: the linearised least squares of Qiu et al. 2022 (eq. 3-6): one anchor's
  equation is subtracted from the others, leaving a linear system H x = B; with weights it
  is their weighted form (eq. 10-11), x = (H^T beta H)^-1 H^T beta B.
- `gauss_newton`: iteratively reweighted Gauss-Newton on the range residuals with a robust
  kernel (Huber by default), started from the linear solution. Gives the covariance
  (J^T W J)^-1, the geometric DOP and a degeneracy flag.
- 2-D with a known tag height: the anchor height projection of the INS-UWB paper,
  d = sqrt(l^2 - (h_anchor - h_tag)^2), for the linear step; Gauss-Newton uses the exact
  3-D range with z held at the tag height.
- 3-D with coplanar anchors (`anchor_plane`: level, or on one tilted plane): the 3-D linear
  system is singular (every anchor difference lies in the plane) and the ranges have a
  mirror solution across the plane, so the linear step is the projected 2-D solve in the
  plane's frame at the offset of a tag below the anchors (the floor's side), and
  Gauss-Newton refines x, y, z from there.
- `select_nearest`: keep the k anchors with the shortest ranges (INS-UWB paper, k = 3).
- `group_epochs`: ranges arrive round robin, anchor by anchor; an epoch takes the latest
  range per anchor within a window ending at the epoch time.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from uwbfuse.config import RobustKernel
from uwbfuse.constants import COPLANAR_SPREAD, MAX_DOP

F64 = NDArray[np.float64]
BoolArr = NDArray[np.bool_]



@dataclass(frozen=True)
class Fixes:
    """Multilateration results for N epochs (tag antenna, map frame).

    position: (N,3) m (in 2-D mode z is the given tag height); cov: (N,d,d) m^2 over the
    solved coordinates (d = 2 or 3); dop: (N,) geometric dilution of precision (unitless,
    sqrt(trace((J^T J)^-1))); degenerate: (N,) True when too few anchors or the geometry is
    singular/ill-conditioned (position then unreliable or NaN); n_used: (N,) ranges used;
    residual_rms: (N,) weighted RMS of the range residuals, m; weights: (N,M) final robust
    weights (0 for unused ranges).
    """

    position: F64
    cov: F64
    dop: F64
    degenerate: BoolArr
    n_used: NDArray[np.int64]
    residual_rms: F64
    weights: F64

    def __len__(self) -> int:
        return len(self.position)

    @property
    def ok(self) -> BoolArr:
        """(N,) True where the fix is usable (finite and not degenerate)."""
        return ~self.degenerate & np.all(np.isfinite(self.position), axis=1)


def robust_weights(u: F64, kernel: RobustKernel | str, k: float) -> F64:
    """IRLS weights w(u) of a robust kernel for normalised residuals u (unitless)."""
    kernel = RobustKernel(kernel)
    a = np.abs(u)
    if kernel is RobustKernel.NONE:
        return np.ones_like(a)
    if kernel is RobustKernel.HUBER:
        return np.where(a <= k, 1.0, k / np.maximum(a, 1e-12))
    if kernel is RobustKernel.CAUCHY:
        return 1.0 / (1.0 + (a / k) ** 2)
    if kernel is RobustKernel.TUKEY:
        return np.where(a < k, (1.0 - (a / k) ** 2) ** 2, 0.0)
    if kernel is RobustKernel.GEMAN_MCCLURE:
        return k**4 / (k**2 + a**2) ** 2
    # DCS: dynamic covariance scaling, scale s = min(1, 2k/(k + u^2)), weight s^2.
    s = np.minimum(1.0, 2.0 * k / (k + a**2))
    return s**2


def project_ranges(rng: F64, anchor_z: F64, tag_z: F64 | float) -> F64:
    """Horizontal distances d = sqrt(l^2 - (h_anchor - h_tag)^2), clipped at 0 (m).

    rng (N,M) slant ranges, anchor_z (M,) anchor heights, tag_z scalar or (N,) tag height.
    """
    dz = np.asarray(anchor_z)[None, :] - np.reshape(tag_z, (-1, 1))
    return np.sqrt(np.maximum(rng**2 - dz**2, 0.0))


def select_nearest(rng: F64, k: int = 3) -> BoolArr:
    """(N,M) mask of the k shortest finite ranges of each epoch (all when fewer)."""
    r = np.where(np.isfinite(rng), rng, np.inf)
    order = np.argsort(r, axis=1, kind="stable")
    mask = np.zeros(rng.shape, dtype=bool)
    np.put_along_axis(mask, order[:, :k], True, axis=1)
    return mask & np.isfinite(rng)


def linear_ls(anchors: F64, rng: F64, weights: F64 | None = None) -> tuple[F64, BoolArr]:
    """Linearised (weighted) least squares, Qiu eq. 3-6 (eq. 10-11 with weights).

    anchors (M,d) anchor coordinates (d = 2 with projected ranges, or 3); rng (N,M) ranges
    (m), NaN = missing; weights (N,M) per-range weights 1/sigma^2 (1/m^2) or None for the
    plain method. The reference (subtracted) equation is the best-weighted range of each
    epoch; the differenced rows get weights 1/(r_i^2 s_i^2 + r_ref^2 s_ref^2), their
    first-order variances. Returns positions (N,d) and ok (N,) (enough anchors, solvable).
    """
    anchors = np.asarray(anchors, dtype=np.float64)
    rng = np.atleast_2d(np.asarray(rng, dtype=np.float64))
    n, m = rng.shape
    d = anchors.shape[1]
    valid = np.isfinite(rng)
    w = np.ones((n, m)) if weights is None else np.asarray(weights, dtype=np.float64)
    w = np.where(valid & (w > 0), w, 0.0)
    ref = np.argmax(w, axis=1)
    rows = np.arange(n)
    r = np.where(valid, rng, 0.0)
    sq = np.sum(anchors**2, axis=1)  # (M,)
    r_ref = r[rows, ref]
    h = anchors[None, :, :] - anchors[ref][:, None, :]  # (N,M,d)
    b = 0.5 * ((sq[None, :] - r**2) - (sq[ref] - r_ref**2)[:, None])  # (N,M)
    if weights is None:
        beta = (w > 0).astype(np.float64)
    else:
        var = r**2 / np.maximum(w, 1e-300) + (r_ref**2 / np.maximum(w[rows, ref], 1e-300))[:, None]
        beta = np.where(w > 0, 1.0 / np.maximum(var, 1e-12), 0.0)
    beta[rows, ref] = 0.0
    a_mat = np.einsum("nmi,nm,nmj->nij", h, beta, h)
    rhs = np.einsum("nmi,nm,nm->ni", h, beta, b)
    n_used = np.sum(w > 0, axis=1)
    ok = n_used >= d + 1
    # Scale-aware conditioning test before solving.
    eig = np.linalg.eigvalsh(a_mat)
    ok &= eig[:, 0] > 1e-9 * np.maximum(eig[:, -1], 1e-300)
    pos = np.full((n, d), np.nan)
    if np.any(ok):
        pos[ok] = np.linalg.solve(a_mat[ok], rhs[ok][..., None])[..., 0]
    return pos, ok


def gauss_newton(
    anchors: F64,
    rng: F64,
    x0: F64,
    sigma: F64 | float,
    *,
    dim: int = 3,
    kernel: RobustKernel | str = RobustKernel.HUBER,
    threshold: float = 1.345,
    iterations: int = 10,
) -> Fixes:
    """Robust (IRLS) Gauss-Newton on the ranges, vectorised over epochs.

    anchors (M,3) map frame, m; rng (N,M) ranges, m (NaN = missing); x0 (N,3) start (in 2-D
    mode x0[:, 2] is the known tag height and stays fixed); sigma scalar or (N,M) range std,
    m; dim 2 or 3 solved coordinates; kernel/threshold: robust kernel on residual/sigma.
    """
    anchors = np.asarray(anchors, dtype=np.float64)
    rng = np.atleast_2d(np.asarray(rng, dtype=np.float64))
    n, m = rng.shape
    valid = np.isfinite(rng)
    sig = np.broadcast_to(np.asarray(sigma, dtype=np.float64), (n, m))
    info = np.where(valid, 1.0 / sig**2, 0.0)
    r = np.where(valid, rng, 0.0)
    p = np.array(x0, dtype=np.float64, copy=True)
    bad0 = ~np.all(np.isfinite(p), axis=1)
    p[bad0] = 0.0
    w = valid.astype(np.float64)
    eye = np.eye(dim)
    for _ in range(iterations):
        diff = p[:, None, :] - anchors[None, :, :]
        pred = np.maximum(np.linalg.norm(diff, axis=2), 1e-6)
        res = r - pred
        w = np.where(valid, robust_weights(res * np.sqrt(info), kernel, threshold), 0.0)
        jac = diff[:, :, :dim] / pred[:, :, None]  # d pred / d p
        wi = w * info
        a_mat = np.einsum("nmi,nm,nmj->nij", jac, wi, jac)
        g = np.einsum("nmi,nm,nm->ni", jac, wi, res)
        damp = 1e-9 * np.trace(a_mat, axis1=1, axis2=2)[:, None, None] + 1e-12
        step = np.linalg.solve(a_mat + damp * eye, g[..., None])[..., 0]
        p[:, :dim] += step
        if np.max(np.abs(step), initial=0.0) < 1e-6:
            break
    diff = p[:, None, :] - anchors[None, :, :]
    pred = np.maximum(np.linalg.norm(diff, axis=2), 1e-6)
    res = np.where(valid, r - pred, 0.0)
    jac = diff[:, :, :dim] / pred[:, :, None]
    wi = w * info
    a_mat = np.einsum("nmi,nm,nmj->nij", jac, wi, jac)
    g_mat = np.einsum("nmi,nm,nmj->nij", jac, valid.astype(np.float64), jac)
    n_used = np.sum(w > 1e-6, axis=1)
    eig_a = np.linalg.eigvalsh(a_mat)
    eig_g = np.linalg.eigvalsh(g_mat)
    singular = (eig_a[:, 0] <= 1e-9 * np.maximum(eig_a[:, -1], 1e-300)) | (eig_g[:, 0] < 1e-9)
    safe_a = np.where(singular[:, None, None], eye, a_mat)
    safe_g = np.where(singular[:, None, None], eye, g_mat)
    cov = np.linalg.inv(safe_a)
    dop = np.sqrt(np.trace(np.linalg.inv(safe_g), axis1=1, axis2=2))
    cov[singular] = np.nan
    dop[singular] = np.inf
    sw = np.maximum(np.sum(wi, axis=1), 1e-300)
    rms = np.sqrt(np.sum(wi * res**2, axis=1) / sw)
    degenerate = singular | (n_used < dim + 1) | (dop > MAX_DOP) | bad0
    p[~np.isfinite(p).all(axis=1)] = np.nan
    return Fixes(p, cov, dop, degenerate, n_used.astype(np.int64), rms, w)


@dataclass(frozen=True)
class AnchorPlane:
    """The plane coplanar anchors lie on (map frame, m).

    origin (3,): the anchors' centroid; axes (3,3): rows e1, e2 in the plane and the normal
    n, a right-handed rotation from the map frame into the plane's frame, n pointing up
    (n_z >= 0: the floor is on its negative side). level: the anchors' heights are within
    COPLANAR_SPREAD, and the map frame itself serves as the plane's frame (each anchor's
    own height goes into the projection).
    """

    origin: F64
    axes: F64
    level: bool


def off_plane_spread(anchors: F64) -> float:
    """How far the anchors (M,3, m, map frame) spread off one plane (m): the smaller of
    their height spread (the level plane) and their spread along the normal of their
    best-fit plane (the smallest singular vector of the centred positions). 0 for three or
    fewer anchors."""
    anchors = np.asarray(anchors, dtype=np.float64).reshape(-1, 3)
    if not len(anchors):
        return 0.0
    centred = anchors - anchors.mean(axis=0)
    normal = np.linalg.svd(centred)[2][-1]
    return min(float(np.ptp(anchors[:, 2])), float(np.ptp(centred @ normal)))


def anchor_plane(anchors: F64) -> AnchorPlane | None:
    """The plane of the anchors (M,3, m, map frame), or None when they are not coplanar
    (`off_plane_spread` at least COPLANAR_SPREAD): level when their heights are within
    COPLANAR_SPREAD, else the best-fit plane at any tilt."""
    anchors = np.asarray(anchors, dtype=np.float64).reshape(-1, 3)
    if not len(anchors) or float(np.ptp(anchors[:, 2])) < COPLANAR_SPREAD:
        return AnchorPlane(np.zeros(3), np.eye(3), level=True)
    origin = anchors.mean(axis=0)
    centred = anchors - origin
    _, _, vt = np.linalg.svd(centred)
    # the heights spread past COPLANAR_SPREAD: `off_plane_spread` is the normal's spread
    if float(np.ptp(centred @ vt[-1])) >= COPLANAR_SPREAD:
        return None
    normal = vt[-1] if vt[-1, 2] >= 0.0 else -vt[-1]
    e1 = vt[0]
    return AnchorPlane(origin, np.vstack([e1, np.cross(normal, e1), normal]), level=False)


def default_tag_z(anchors: F64) -> float:
    """Start height for 3-D solves: 1 m below the mean anchor height (m, map frame).

    With coplanar anchors (`anchor_plane`, level or tilted) the range equations have a
    mirror solution across the anchor plane; starting below selects the tag on the floor's
    side of the (ceiling or wall mounted) anchors.
    """
    return float(np.mean(anchors[:, 2])) - 1.0


def _plane_start(
    plane: AnchorPlane, anchors: F64, rng: F64, tag_z: F64, w_lin: F64
) -> F64:
    """Start (N,3) of a 3-D solve with coplanar anchors: the 2-D solve in the plane's frame
    at the offset from the plane of a tag at height `tag_z` (N,) below the anchors' centroid
    (on the floor's side when tag_z is below them), back in the map frame (m)."""
    if plane.level:
        d = project_ranges(rng, anchors[:, 2], tag_z)
        xy, _ = linear_ls(anchors[:, :2], d, w_lin)
        return np.column_stack([xy, tag_z])
    local = (anchors - plane.origin) @ plane.axes.T
    w = (tag_z - plane.origin[2]) * plane.axes[2, 2]
    uv, _ = linear_ls(local[:, :2], project_ranges(rng, local[:, 2], w), w_lin)
    return plane.origin + np.column_stack([uv, w]) @ plane.axes


def multilaterate(
    anchors: F64,
    rng: F64,
    *,
    dim: int = 3,
    tag_z: F64 | float | None = None,
    sigma: F64 | float = 0.1,
    weights: F64 | None = None,
    kernel: RobustKernel | str = RobustKernel.HUBER,
    threshold: float = 1.345,
    nearest: int | None = None,
    refine: bool = True,
) -> Fixes:
    """Tag positions from ranges: linear (weighted) LS, then robust Gauss-Newton.

    anchors (M,3) map frame, m; rng (N,M) ranges, m, NaN = missing (a (M,) row is one
    epoch). dim 2: solve x, y with the tag height `tag_z` (scalar or (N,), m; required)
    by anchor height projection; dim 3: solve x, y, z (`tag_z` is then only the start
    height for coplanar anchors, level or tilted, default `default_tag_z`). sigma: range
    std (scalar or (N,M), m); weights (N,M) for the linear step (default 1/sigma^2);
    nearest: use only the k shortest ranges per epoch (INS-UWB paper: 3). refine=False
    returns the linear solution with its covariance from the range Jacobian at that point.
    """
    anchors = np.asarray(anchors, dtype=np.float64)
    rng = np.atleast_2d(np.asarray(rng, dtype=np.float64)).copy()
    n, m = rng.shape
    if nearest is not None:
        rng[~select_nearest(rng, nearest)] = np.nan
    sig = np.broadcast_to(np.asarray(sigma, dtype=np.float64), (n, m))
    w_lin = 1.0 / sig**2 if weights is None else np.asarray(weights, dtype=np.float64)
    if dim == 2:
        if tag_z is None:
            raise ValueError("2-D multilateration needs the tag height tag_z")
        z = np.broadcast_to(np.asarray(tag_z, dtype=np.float64), (n,)).astype(np.float64)
        d = project_ranges(rng, anchors[:, 2], z)
        xy, _ = linear_ls(anchors[:, :2], d, w_lin)
        x0 = np.column_stack([xy, z])
    elif dim == 3:
        plane = anchor_plane(anchors)
        if plane is not None:
            z0 = default_tag_z(anchors) if tag_z is None else tag_z
            z = np.broadcast_to(np.asarray(z0, dtype=np.float64), (n,)).astype(np.float64)
            x0 = _plane_start(plane, anchors, rng, z, w_lin)
        else:
            x0, _ = linear_ls(anchors, rng, w_lin)
    else:
        raise ValueError(f"dim must be 2 or 3, not {dim}")
    iters = 15 if refine else 0
    return gauss_newton(
        anchors, rng, x0, sig, dim=dim, kernel=kernel, threshold=threshold, iterations=iters
    )


def group_epochs(
    t_ns: NDArray[np.int64],
    anchor: NDArray[np.integer],
    rng: F64,
    n_anchors: int,
    epoch_t_ns: NDArray[np.int64],
    window_ns: int,
) -> tuple[F64, NDArray[np.int64]]:
    """Latest range per anchor in the window (t_k - window, t_k] of each epoch t_k.

    t_ns (R,) sorted stamps, anchor (R,) indices, rng (R,) m. Returns ranges (K,M), NaN
    where an anchor has no range in the window, and their stamps (K,M) (ns, -1 if none).
    """
    epoch_t_ns = np.asarray(epoch_t_ns, dtype=np.int64)
    k = len(epoch_t_ns)
    out = np.full((k, n_anchors), np.nan)
    stamps = np.full((k, n_anchors), -1, dtype=np.int64)
    for a in range(n_anchors):
        sel = np.flatnonzero(anchor == a)
        if not len(sel):
            continue
        ta = t_ns[sel]
        idx = np.searchsorted(ta, epoch_t_ns, side="right") - 1
        has = idx >= 0
        idx_c = np.maximum(idx, 0)
        fresh = has & (epoch_t_ns - ta[idx_c] < window_ns)
        out[fresh, a] = rng[sel[idx_c[fresh]]]
        stamps[fresh, a] = ta[idx_c[fresh]]
    return out, stamps


def epochs_by_window(t_ns: NDArray[np.int64], window_ns: int) -> NDArray[np.int64]:
    """Epoch times for a whole log: the stamp of each range that completes a window.

    Consecutive, non-overlapping windows of length `window_ns` starting at the first
    stamp; each epoch is the last stamp inside its window (so `group_epochs` at these times
    sees every range once). Returns sorted int64 ns.
    """
    if not len(t_ns):
        return np.zeros(0, dtype=np.int64)
    bins = (t_ns - t_ns[0]) // window_ns
    last = np.flatnonzero(np.diff(bins, append=bins[-1] + 1) != 0)
    return t_ns[last].astype(np.int64)


def epoch_window_ns(
    t_ns: NDArray[np.int64], anchor: NDArray[np.integer], base_window_ns: int,
    max_window_ns: int = 2_000_000_000,
) -> int:
    """Epoch length for `group_epochs`: at least `base_window_ns`, and long enough for one
    round-robin cycle (1.2 x the median per-anchor range period), capped at max_window_ns.

    Slow round robins (e.g. 4 anchors at 2 Hz each) otherwise leave every epoch with fewer
    ranges than a fix needs.
    """
    periods = []
    for a in np.unique(anchor):
        ta = t_ns[anchor == a]
        if len(ta) >= 3:
            periods.append(float(np.median(np.diff(ta))))
    if not periods:
        return int(base_window_ns)
    cycle = 1.2 * float(np.median(periods))
    return int(min(max(base_window_ns, cycle), max(max_window_ns, base_window_ns)))

