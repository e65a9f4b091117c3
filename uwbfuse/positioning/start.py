# SPDX-License-Identifier: BSD-3-Clause
"""Fallback start for wheeled logs with sparse, round-robin ranges.

The positioning `Initialiser` builds its heading solve on per-epoch multilateration fixes;
when a radio ranges to one anchor at a time at a few Hz (the Labyrinth and Plaza logs),
there are no fixes and it never answers. Then this module solves the start directly from
the raw ranges with the start's one model (`initialisation.StartProblem`): the wheel
dead-reckoning track d(t) (base frame at its first sample) is placed in the map by an
unknown planar pose (x0, y0, yaw0), a common range offset c and a common range scale
error k, fitted by the start's one optimiser (`initialisation.solve_seeds`, soft-L1 robust
LM) from several yaw seeds to (1 + k) |p0 + R(yaw0) d(t) + R(t) tag - anchor| + c for
every range so far; a minimum with |c| or |k| past the radios' physical range
(START_MAX_OFFSET_M, START_MAX_SCALE) is no start. The answer is accepted by the start's
one rule (`initialisation.best_minimum`) once the vehicle has travelled `MIN_TRAVEL_M`:
the best solution's residuals are consistent and no other local minimum comes close.
Sensors only: no ground truth, no given pose.
"""

from __future__ import annotations

import math

import numpy as np

from uwbfuse.constants import (
    HEIGHT_SPREAD_M,
    HELD_HEIGHT_SIGMAS,
    MIN_TRAVEL_M,
    N_SEEDS,
    SOFT_L1_M,
    START_MAX_OFFSET_M,
    START_MAX_SCALE,
    START_MIN_RANGES,
    STATIC_MAX_RANGES,
    STATIC_MAX_SCALE,
    STATIC_MAX_SPEED,
    STATIC_MAX_YAW_RATE,
    STATIC_MIN_ANCHORS,
    STATIC_MIN_RANGES,
)
from uwbfuse.positioning.initialisation import (
    RIVAL_MARGIN,
    SOFT_L1_SIGMAS,
    InitialState,
    StartProblem,
    best_minimum,
    rival_margin,
    robust_lm,
    solve_seeds,
    start_consistent,
)
from uwbfuse.positioning.multilateration import off_plane_spread
from uwbfuse.positioning.wheel_track import WheelTrack, se2_compose
from uwbfuse.streams import AnchorMap


def _rot_z(yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def track_travel(track: WheelTrack, t_now: int) -> float:
    """Path length (m) the wheels have covered up to t_now."""
    upto = track.t <= t_now
    return float(np.sum(np.abs(track.v[upto])[1:] * np.diff(track.t[upto]) / 1e9))


def solve_start(
    track: WheelTrack,
    anchors: AnchorMap,
    t_r: np.ndarray,
    a_r: np.ndarray,
    z_r: np.ndarray,
    tag: np.ndarray,
    base_z: float,
    t_now: int,
) -> InitialState | None:
    """The base pose at t_now from the wheel track and the raw ranges, or None."""
    if len(track) < 2 or len(t_r) < START_MIN_RANGES:
        return None
    sel = (t_r >= track.t[0]) & (t_r <= t_now)
    t_r, a_r, z_r = t_r[sel], a_r[sel], z_r[sel]
    if len(t_r) < START_MIN_RANGES or len(np.unique(a_r)) < 3:
        return None
    if track_travel(track, t_now) < MIN_TRAVEL_M:
        return None
    d = track.at(t_r)  # (n,3) x, y, theta in the track frame
    c, s = np.cos(d[:, 2]), np.sin(d[:, 2])
    tag_xy = np.column_stack([d[:, 0] + c * tag[0] - s * tag[1], d[:, 1] + s * tag[0] + c * tag[1]])
    n_r = len(z_r)
    sig = SOFT_L1_M / SOFT_L1_SIGMAS  # the range sigma the soft-L1 scale is counted in
    # the start's one model (`initialisation.StartProblem`) on the wheel track (the base at
    # the track's first sample, so the yaw-zero frame is the track frame): one common range
    # offset without a prior, the scale without one (both bounded below), the base height
    # held on the floor
    problem = StartProblem(
        w0=np.column_stack([tag_xy, np.full(n_r, float(tag[2]))]), sens=np.zeros((n_r, 3, 0)),
        dtr=np.zeros(n_r), anc=anchors.positions[a_r], anc_col=np.zeros(n_r, np.int64),
        rr=z_r, sig=sig, lev0=np.zeros(3), prior=None, sens_sigma=np.zeros(0),
        b_sigma=math.inf, z_prior=base_z, z_sigma=HELD_HEIGHT_SIGMAS * sig, solve_v=False,
        n_k=1, n_s=0, n_b=1, k_sigma=math.inf)
    i_k, i_b = problem.i_k, problem.i_b
    centre = anchors.positions[:, :2].mean(axis=0)
    mid = tag_xy[len(tag_xy) // 2]
    seeds = []
    for k in range(N_SEEDS):
        yaw0 = 2.0 * math.pi * k / N_SEEDS
        # seed the position so that the track's middle sits at the anchors' centre
        p0 = centre - _rot_z(yaw0)[:2, :2] @ mid
        seeds.append(np.array([p0[0], p0[1], base_z, yaw0, 0.0, 0.0]))
    # a minimum outside the radios' physical offset and scale is no start
    sols = [r for r in solve_seeds(problem, seeds)
            if abs(r.x[i_b]) <= START_MAX_OFFSET_M and abs(r.x[i_k]) <= START_MAX_SCALE]
    if not sols:
        return None
    found = best_minimum(sols, problem)
    if not (found.consistent and found.margin >= RIVAL_MARGIN):
        return None
    best = found.best.x
    rms = sig * math.sqrt(2.0 * found.best.cost / n_r)
    pose_now = se2_compose(np.array([best[0], best[1], best[3]]), track.at(t_now))
    r_now = _rot_z(float(pose_now[2]))
    if len(track.t) and track.t[-1] <= t_now:
        v_now = float(track.v[-1])
    else:
        v_now = float(track.v[min(np.searchsorted(track.t, t_now), len(track) - 1)])
    return InitialState(
        t_ns=int(t_now),
        position=np.array([pose_now[0], pose_now[1], base_z]),
        R_map_base=r_now,
        velocity=r_now @ np.array([v_now, 0.0, 0.0]),
        gyro_bias=np.zeros(3),
        accel_bias=np.zeros(3),
        position_sigma=max(rms, 0.1),
        yaw_sigma=0.1,
        still=False,
        range_scale=1.0 + float(best[i_k]),
        range_sigma=rms,
        range_scale_sigma=_scale_std(*problem.fun_jac(best), n_r, i_k, rms / sig),
    )


def _accepted(res: np.ndarray, z_r: np.ndarray, best_cost: float, rivals: list[float]) -> bool:
    """The acceptance rule of the start (`initialisation.start_consistent`, `rival_margin`,
    as `best_minimum` applies them) for the standstill fix, on residuals `res` (m) of
    ranges `z_r` (m) and soft-L1 costs (m^2) at SOFT_L1_M, SOFT_L1_SIGMAS range sigmas."""
    sig = SOFT_L1_M / SOFT_L1_SIGMAS
    consistent, _, _ = start_consistent(res / sig, float(np.median(z_r)), sig)
    return consistent and rival_margin(
        best_cost / sig**2, [c / sig**2 for c in rivals]) >= RIVAL_MARGIN


def _scale_std(f: np.ndarray, jac: np.ndarray, n_r: int, i_k: int, rms: float) -> float:
    """Least-squares std of the start solve's scale (unknown `i_k`) from the whitened
    residuals `f` (the first `n_r` of them ranges, soft-L1) and their Jacobian at the
    solution, scaled by the ranges' rms (in range sigmas); inf where the solve is singular.
    The range rows carry the soft-L1 cost's Gauss-Newton Hessian weights rho' + 2 rho'' z
    = (1 + z)^-3/2, z = (f / SOFT_L1_SIGMAS)^2 (as scipy's `least_squares`)."""
    w = np.ones(len(f))
    w[:n_r] = (1.0 + (f[:n_r] / SOFT_L1_SIGMAS) ** 2) ** -0.75
    jac = jac * w[:, None]
    try:
        cov = np.linalg.inv(jac.T @ jac) * rms * rms
    except np.linalg.LinAlgError:
        return math.inf
    return float(math.sqrt(cov[i_k, i_k])) if cov[i_k, i_k] > 0.0 else math.inf




def wheels_still(v: np.ndarray, omega: np.ndarray) -> np.ndarray:
    """Per wheel sample (speed m/s, yaw rate rad/s): standing still, within the
    STATIC_MAX_* speeds; the one test of the start, the standstill fix and the pre-start
    poses."""
    return (np.abs(v) <= STATIC_MAX_SPEED) & (np.abs(omega) <= STATIC_MAX_YAW_RATE)




def solve_static(
    anchors: AnchorMap, a_r: np.ndarray, z_r: np.ndarray, tag_z: float
) -> tuple[np.ndarray, float, float] | None:
    """Tag position (x, y) in the map frame, common range scale error k and robust residual
    rms (m) from the ranges of a tag that has not moved, or None.

    The provisional answer of a wheeled log without an IMU before `solve_start` can fix a
    heading: while the wheels say the vehicle stands still every range so far comes from one
    point, so (1 + k) |p - anchor| = z is fitted to all of them (soft-L1, tag height
    `tag_z` in the map frame, |k| <= 15 %). Per-epoch multilateration cannot see a common
    scale error, which it turns into metres of position error far from the anchors (Plaza2:
    ranges 7 % long, WLS fixes ~9 m off; this fit 0.15-0.3 m). Needs STATIC_MIN_ANCHORS
    anchors; rejected when the residuals are inconsistent or another minimum comes close.
    """
    if len(z_r) < STATIC_MIN_RANGES or len(np.unique(a_r)) < STATIC_MIN_ANCHORS:
        return None
    a_r, z_r = a_r[-STATIC_MAX_RANGES:], z_r[-STATIC_MAX_RANGES:]
    anc = anchors.positions[a_r]
    dz2 = (tag_z - anc[:, 2]) ** 2

    n_r = len(z_r)

    def fun_jac(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        ex, ey = p[0] - anc[:, 0], p[1] - anc[:, 1]
        d = np.sqrt(ex**2 + ey**2 + dz2)
        g = (1.0 + p[2]) / np.maximum(d, 1e-9)
        return (1.0 + p[2]) * d - z_r, np.column_stack([g * ex, g * ey, d])

    used = anchors.positions[np.unique(a_r), :2]
    seeds = [used.mean(axis=0)] + [p + 1.0 for p in used]  # centroid, beside each anchor
    sols = []
    for s in seeds:
        r = robust_lm(fun_jac, np.array([s[0], s[1], 0.0]), n_r, SOFT_L1_M)
        if r is not None and abs(r.x[2]) <= STATIC_MAX_SCALE:  # as in `solve_start`
            sols.append((r.cost, r.x))
    if not sols:
        return None
    sols.sort(key=lambda c_x: c_x[0])
    best_cost, best = sols[0]
    rivals = [c for c, x in sols[1:] if np.hypot(*(x[:2] - best[:2])) > 1.0]
    if not _accepted(fun_jac(best)[0], z_r, best_cost, rivals):
        return None
    rms = math.sqrt(2.0 * best_cost / len(z_r))
    return best[:2].copy(), float(best[2]), rms




def anchors_observe_height(positions: np.ndarray) -> bool:
    """True when the anchors (N,3, m, map frame) spread HEIGHT_SPREAD_M off one plane
    (`off_plane_spread`; level or tilted): only then do ranges tell the tag's offset from
    the anchors' plane, and so its height, apart from a common range offset."""
    return len(positions) > 0 and off_plane_spread(positions) >= HEIGHT_SPREAD_M


def planar_height(anchors: AnchorMap, z_start: float) -> float:
    """Base height (m) held by the planar constraint.

    When the anchors are (nearly) coplanar, level or tilted, the ranges barely observe
    height, so a start height solved from them is unreliable: the floor is then taken at
    the map frame's z = 0 (anchor heights are measured from the floor). With anchors that
    observe height (`anchors_observe_height`) the start height is used.
    """
    return z_start if anchors_observe_height(anchors.positions) else 0.0
