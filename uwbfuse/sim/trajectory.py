# SPDX-License-Identifier: BSD-3-Clause
"""Smooth planar differential-drive trajectories with analytic derivatives.

A route is a closed loop of primitives (`Straight`, `Turn`, `Spin`, `Stop`) driven from a
start pose in the map frame. It is turned into a timeline of *phases*; in every phase of
duration T (s) and local time tau in [0, T], with u = tau / T and h(u) = u - sin(2 pi u)/(2 pi):

    v(tau)     = v0 + (v1 - v0) h(u)                     forward speed, m/s
    dv/dt      = (v1 - v0) / T (1 - cos 2 pi u)          forward acceleration, m/s^2
    theta(tau) = theta0 + dtheta h(u)                    yaw in the map frame, rad
    omega(tau) = dtheta / T (1 - cos 2 pi u)             yaw rate, rad/s

so speed, yaw rate and accelerations are continuous (raised-cosine acceleration and
curvature profiles), and a phase is a standstill, an acceleration, a cruise, a turn at
constant speed with raised-cosine curvature, or a turn in place. Distance travelled and yaw
are exact closed forms; the position is the closed form on straight phases and a 16-node
Gauss-Legendre quadrature of v (cos theta, sin theta) on turning phases, so positions at any
time are accurate to ~1e-9 m and do not drift over long runs.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from uwbfuse.errors import SimulationError

F64 = NDArray[np.float64]
TWO_PI = 2.0 * math.pi

_GL_X, _GL_W = np.polynomial.legendre.leggauss(16)
_GL_U = 0.5 * (_GL_X + 1.0)  # nodes on [0, 1]
_GL_W01 = 0.5 * _GL_W  # weights on [0, 1]


# ---------------------------------------------------------------------------------------
# Route primitives (map frame, metres and radians)


@dataclass(frozen=True)
class Straight:
    """Drive straight ahead `length` metres (accelerating/braking inside it when needed)."""

    length: float


@dataclass(frozen=True)
class Turn:
    """Turn by `angle` rad (positive = left) over `length` metres of path at cruise speed.

    The curvature follows a raised cosine, peak 2 angle / length (1/m).
    """

    angle: float
    length: float


@dataclass(frozen=True)
class Spin:
    """Turn in place by `angle` rad (vehicle at rest before and after)."""

    angle: float


@dataclass(frozen=True)
class Stop:
    """Stand still for `dwell_s` seconds (the preceding `Straight` brakes to rest)."""

    dwell_s: float


Primitive = Straight | Turn | Spin | Stop


def _h(u: F64) -> F64:
    return u - np.sin(TWO_PI * u) / TWO_PI


def _hint(u: F64) -> F64:
    """Integral of h from 0 to u."""
    return 0.5 * u * u + (np.cos(TWO_PI * u) - 1.0) / (TWO_PI * TWO_PI)


def turn_displacement(angle: float) -> tuple[float, float]:
    """Displacement (forward, left) of a `Turn(angle, 1.0)` starting at heading 0, metres.

    Scales linearly with the turn length.
    """
    th = angle * _h(_GL_U)
    return float(np.sum(_GL_W01 * np.cos(th))), float(np.sum(_GL_W01 * np.sin(th)))


def close_loop(
    prims: list[Primitive], free: tuple[int, int], start_yaw: float = 0.0
) -> list[Primitive]:
    """Adjust the lengths of the two `Straight` primitives at indices `free` to close the loop.

    The loop closes when it ends at its start position; the two free straights must have
    non-parallel headings. Raises SimulationError when the solution needs a negative length.
    """
    yaw = start_yaw
    disp = np.zeros(2)
    dirs: dict[int, NDArray[np.float64]] = {}
    for i, p in enumerate(prims):
        if isinstance(p, Straight):
            d = np.array([math.cos(yaw), math.sin(yaw)])
            if i in free:
                dirs[i] = d
            else:
                disp += p.length * d
        elif isinstance(p, Turn):
            fwd, left = turn_displacement(p.angle)
            c, s = math.cos(yaw), math.sin(yaw)
            disp += p.length * np.array([c * fwd - s * left, s * fwd + c * left])
            yaw += p.angle
        elif isinstance(p, Spin):
            yaw += p.angle
    a = np.column_stack([dirs[free[0]], dirs[free[1]]])
    lengths = np.linalg.solve(a, -disp)
    if np.any(lengths < 0):
        raise SimulationError(f"route cannot close: free straight lengths {lengths.round(3)}")
    out = list(prims)
    for k, i in enumerate(free):
        out[i] = Straight(float(lengths[k]))
    return out


# ---------------------------------------------------------------------------------------
# Timeline of phases


@dataclass(frozen=True)
class Timeline:
    """Phases as columns: start time t0 (s), duration T (s), speeds v0/v1 (m/s), yaw change
    dtheta (rad), yaw theta0 (rad, unwrapped), distance s0 (m) and position p0 (x, y, m, map
    frame) at the phase start. `time_offset` (s) is added to every query time (a log that
    starts while moving begins inside the timeline)."""

    t0: F64
    dur: F64
    v0: F64
    v1: F64
    dtheta: F64
    theta0: F64
    s0: F64
    p0: F64
    time_offset: float = 0.0

    @property
    def end_time(self) -> float:
        return float(self.t0[-1] + self.dur[-1])


@dataclass(frozen=True)
class MotionParams:
    """Speed limits: cruise speed (m/s), peak acceleration (m/s^2), peak spin rate (rad/s)."""

    speed: float
    accel: float
    spin_rate: float


def _lap_phases(
    prims: list[Primitive], mp: MotionParams
) -> list[tuple[float, float, float, float]]:
    """One lap as (duration, v0, v1, dtheta) phases; the vehicle is at rest at lap start."""
    out: list[tuple[float, float, float, float]] = []
    speed = 0.0
    n = len(prims)
    for i, p in enumerate(prims):
        if isinstance(p, Straight):
            nxt = prims[(i + 1) % n]
            at_rest_start = speed == 0.0
            at_rest_end = isinstance(nxt, (Stop, Spin)) or (i == n - 1)
            vp = mp.speed
            d_ramp = vp * vp / mp.accel  # distance of one ramp 0 -> vp (peak accel mp.accel)
            need = d_ramp * (at_rest_start + at_rest_end)
            if need > p.length:
                if not (at_rest_start and at_rest_end):
                    raise SimulationError(
                        f"route: straight of {p.length:.2f} m too short to reach cruise speed"
                    )
                vp = math.sqrt(p.length * mp.accel / 2.0)
                d_ramp = vp * vp / mp.accel
                need = 2 * d_ramp
            t_ramp = 2.0 * vp / mp.accel
            if at_rest_start:
                out.append((t_ramp, 0.0, vp, 0.0))
            cruise = p.length - need
            if cruise > 1e-12:
                out.append((cruise / vp, vp, vp, 0.0))
            if at_rest_end:
                out.append((t_ramp, vp, 0.0, 0.0))
                speed = 0.0
            else:
                speed = vp
        elif isinstance(p, Turn):
            if speed == 0.0:
                raise SimulationError("route: a Turn must follow a Straight at cruise speed")
            out.append((p.length / speed, speed, speed, p.angle))
        elif isinstance(p, Spin):
            if speed != 0.0:
                raise SimulationError("route: a Spin needs the vehicle at rest")
            out.append((2.0 * abs(p.angle) / mp.spin_rate, 0.0, 0.0, p.angle))
        elif isinstance(p, Stop):
            if speed != 0.0:
                raise SimulationError("route: a Stop must follow a braking Straight")
            if p.dwell_s > 0:
                out.append((p.dwell_s, 0.0, 0.0, 0.0))
    if speed != 0.0:
        raise SimulationError("route: the lap must end at rest")
    return out


def build_timeline(
    prims: list[Primitive],
    start: tuple[float, float, float],
    mp: MotionParams,
    duration_s: float,
    still_start_s: float,
) -> Timeline:
    """Repeat the lap from `start` (x m, y m, yaw rad) until `duration_s` is covered.

    With `still_start_s` > 0 the vehicle first stands still that long; with 0 the log starts
    one second into the first cruise phase, already moving.
    """
    lap = _lap_phases(prims, mp)
    lap_time = sum(p[0] for p in lap)
    if lap_time <= 0:
        raise SimulationError("route: empty lap")
    offset = 0.0
    phases: list[tuple[float, float, float, float]] = []
    if still_start_s > 0:
        phases.append((still_start_s, 0.0, 0.0, 0.0))
    else:
        t = 0.0
        for d, v0, v1, _ in lap:
            if v0 > 0 and v1 > 0:
                offset = t + min(1.0, 0.5 * d)
                break
            t += d
    n_laps = math.ceil((duration_s + offset + 1.0) / lap_time) + 1
    phases.extend(lap * n_laps)
    arr = np.array(phases, dtype=np.float64)
    dur, v0, v1, dth = arr.T
    t0 = np.concatenate([[0.0], np.cumsum(dur)[:-1]])
    theta0 = start[2] + np.concatenate([[0.0], np.cumsum(dth)[:-1]])
    ds = 0.5 * (v0 + v1) * dur
    s0 = np.concatenate([[0.0], np.cumsum(ds)[:-1]])
    # full-phase displacements
    tl0 = Timeline(t0, dur, v0, v1, dth, theta0, s0, np.zeros((len(dur), 2)))
    disp = _displacement(tl0, np.arange(len(dur)), np.ones(len(dur)))
    p0 = np.vstack([[0.0, 0.0], np.cumsum(disp, axis=0)[:-1]]) + np.asarray(start[:2])
    return Timeline(t0, dur, v0, v1, dth, theta0, s0, p0, offset)


def _displacement(tl: Timeline, idx: NDArray[np.intp], u: F64) -> F64:
    """Displacement (N,2) from the start of phase idx to fraction u of it, map frame, m."""
    dur, v0, v1 = tl.dur[idx], tl.v0[idx], tl.v1[idx]
    dth, th0 = tl.dtheta[idx], tl.theta0[idx]
    out = np.empty((len(idx), 2))
    straight = dth == 0.0
    if np.any(straight):
        dist = dur[straight] * (v0[straight] * u[straight] + (v1 - v0)[straight] * _hint(
            u[straight]))
        out[straight, 0] = dist * np.cos(th0[straight])
        out[straight, 1] = dist * np.sin(th0[straight])
    turning = ~straight
    if np.any(turning):
        uu = u[turning, None] * _GL_U[None, :]  # (n,16)
        vv = v0[turning, None] + (v1 - v0)[turning, None] * _h(uu)
        th = th0[turning, None] + dth[turning, None] * _h(uu)
        scale = (dur[turning] * u[turning])[:, None] * _GL_W01[None, :]
        out[turning, 0] = np.sum(scale * vv * np.cos(th), axis=1)
        out[turning, 1] = np.sum(scale * vv * np.sin(th), axis=1)
    return out


@dataclass(frozen=True)
class Kinematics:
    """Vehicle state at query times: position (N,2) m and yaw (N,) rad (unwrapped) of the base
    frame in the map frame, distance travelled s (N,) m, forward speed v (N,) m/s, forward
    acceleration a (N,) m/s^2, yaw rate omega (N,) rad/s and yaw acceleration alpha (N,)
    rad/s^2. Lateral acceleration is v * omega (no side slip)."""

    position: F64
    yaw: F64
    s: F64
    v: F64
    a: F64
    omega: F64
    alpha: F64


def evaluate(
    tl: Timeline, t_s: F64, with_position: bool = True, chunk: int = 100_000
) -> Kinematics:
    """Kinematics at times `t_s` (s since log start, any order).

    With `with_position=False` the position is left as zeros (saves the quadrature).
    """
    t = np.asarray(t_s, dtype=np.float64) + tl.time_offset
    if len(t) and (t.min() < 0 or t.max() > tl.end_time):
        raise SimulationError("trajectory queried outside its timeline")
    idx = np.clip(np.searchsorted(tl.t0, t, side="right") - 1, 0, len(tl.t0) - 1)
    dur = tl.dur[idx]
    tau = t - tl.t0[idx]
    u = np.clip(tau / dur, 0.0, 1.0)
    v0, dv, dth = tl.v0[idx], tl.v1[idx] - tl.v0[idx], tl.dtheta[idx]
    c = 1.0 - np.cos(TWO_PI * u)
    sn = np.sin(TWO_PI * u)
    v = v0 + dv * _h(u)
    a = dv / dur * c
    yaw = tl.theta0[idx] + dth * _h(u)
    omega = dth / dur * c
    alpha = dth / (dur * dur) * TWO_PI * sn
    s = tl.s0[idx] + dur * (v0 * u + dv * _hint(u))
    pos = np.zeros((len(t), 2))
    for k in range(0, len(t) if with_position else 0, chunk):
        sl = slice(k, k + chunk)
        pos[sl] = tl.p0[idx[sl]] + _displacement(tl, idx[sl], u[sl])
    return Kinematics(pos, yaw, s, v, a, omega, alpha)


def moving_mask(tl: Timeline, t_s: F64) -> NDArray[np.bool_]:
    """True where the vehicle moves or turns (inside a phase that is not a standstill)."""
    t = np.asarray(t_s, dtype=np.float64) + tl.time_offset
    idx = np.clip(np.searchsorted(tl.t0, t, side="right") - 1, 0, len(tl.t0) - 1)
    return (tl.v0[idx] != 0) | (tl.v1[idx] != 0) | (tl.dtheta[idx] != 0)


def route_polyline(
    prims: list[Primitive], start: tuple[float, float, float], step: float = 0.05
) -> F64:
    """Points (N,2) along one lap of the route, map frame, m (for plots and geometry tests)."""
    mp = MotionParams(speed=0.1, accel=1.0, spin_rate=1.0)
    tl = build_timeline(prims, start, mp, duration_s=0.0, still_start_s=1e-3)
    lap_end = 1e-3 + sum(p[0] for p in _lap_phases(prims, mp))
    t = np.arange(0.0, lap_end, step)
    return evaluate(tl, t).position
