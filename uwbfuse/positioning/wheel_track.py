# SPDX-License-Identifier: BSD-3-Clause
"""Planar wheel dead reckoning (SE(2)), free of GTSAM: the track the starts, the graph's
wheel factors and the filters share.

Each wheel sample (v m/s, omega rad/s, base frame) is the mean velocity over the interval
that ends at its stamp; the track integrates those exactly as constant-velocity arcs, so
the relative motion between any two times is one SE(2) composition.
"""

from __future__ import annotations

import itertools
import math
from typing import Any

import numpy as np

from uwbfuse.config import WheelConfig
from uwbfuse.constants import MAX_EXTRAPOLATION_S, WHEEL_GUESS_ACCEL, WHEEL_GUESS_YAW_ACCEL
from uwbfuse.streams import NS_PER_S


def arc_steps(v: np.ndarray, dt: np.ndarray, yaw0: np.ndarray | float,
              dyaw: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(dx, dy), m, of constant-velocity arcs: speed v m/s for dt s while the heading
    turns by dyaw rad from yaw0 rad, in the frame yaw0 is measured in (broadcasting).

    The project's one wheel integrator, exact for a constant twist: in the arc's own
    frame (s sin(th) / th, s (1 - cos(th)) / th) for path length s = v dt, turned by yaw0.
    """
    s = v * dt
    small = np.abs(dyaw) < 1e-6  # rad: below it the series (error ~ th^4) replaces 0 / 0
    th_safe = np.where(small, 1.0, dyaw)
    lx = np.where(small, s * (1.0 - dyaw * dyaw / 6.0), s * np.sin(th_safe) / th_safe)
    ly = np.where(small, s * dyaw / 2.0, s * (1.0 - np.cos(th_safe)) / th_safe)
    c, sn = np.cos(yaw0), np.sin(yaw0)
    return c * lx - sn * ly, sn * lx + c * ly


def arc_step(v: float, dt: float, yaw0: float, dyaw: float) -> tuple[float, float]:
    """`arc_steps` for one arc in Python floats (the same formula, operation for operation:
    bit-identical, tests/test_wheel_track.py): the per-keyframe paths, where numpy's per-call
    cost is ~10x the arithmetic."""
    s = v * dt
    if abs(dyaw) < 1e-6:  # rad, as in `arc_steps`
        lx, ly = s * (1.0 - dyaw * dyaw / 6.0), s * dyaw / 2.0
    else:
        lx, ly = s * math.sin(dyaw) / dyaw, s * (1.0 - math.cos(dyaw)) / dyaw
    c, sn = math.cos(yaw0), math.sin(yaw0)
    return c * lx - sn * ly, sn * lx + c * ly


def _arcs(v: np.ndarray, w: np.ndarray, tau: np.ndarray) -> tuple[np.ndarray, ...]:
    """Local (dx, dy, dtheta) of constant-velocity arcs (vectorised, `arc_steps`)."""
    th = w * tau
    dx, dy = arc_steps(v, tau, 0.0, th)
    return dx, dy, th


def unicycle_track(
    x: np.ndarray, y: np.ndarray, yaw: np.ndarray, v: np.ndarray, w: np.ndarray,
    dt: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Planar unicycle over N intervals (`arc_steps`), batched over B start states.

    x, y, yaw (B,) m, m, rad; v (N,) m/s, w (N,) rad/s, dt (N,) s. Returns x, y, yaw at
    the N+1 boundaries (B,N+1) and the heading at each interval's middle (B,N).
    """
    dth = w * dt
    cum = np.concatenate([[0.0], np.cumsum(dth)])
    yaw_b = yaw[:, None] + cum[None, :]
    dx, dy = arc_steps(v[None, :], dt[None, :], yaw_b[:, :-1], dth[None, :])
    n = len(dt)
    xb = np.empty((len(x), n + 1))
    yb = np.empty((len(x), n + 1))
    xb[:, 0] = x
    yb[:, 0] = y
    np.cumsum(dx, axis=1, out=xb[:, 1:])
    np.cumsum(dy, axis=1, out=yb[:, 1:])
    xb[:, 1:] += x[:, None]
    yb[:, 1:] += y[:, None]
    return xb, yb, yaw_b, yaw_b[:, :-1] + 0.5 * dth[None, :]


def _se2_out(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The (..., 3) result array of a broadcast SE(2) operation on a and b (filled column by
    column: np.stack's per-call cost was a third of these functions on keyframe-sized input)."""
    sa, sb = np.shape(a)[:-1], np.shape(b)[:-1]
    return np.empty((*(sa if sa == sb else np.broadcast_shapes(sa, sb)), 3))


def se2_compose(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a (+) b for SE(2) poses (x, y, theta), broadcasting over leading axes."""
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    out = _se2_out(a, b)
    out[..., 0] = a[..., 0] + c * b[..., 0] - s * b[..., 1]
    out[..., 1] = a[..., 1] + s * b[..., 0] + c * b[..., 1]
    out[..., 2] = a[..., 2] + b[..., 2]
    return out


def se2_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a^-1 (+) b for SE(2) poses (x, y, theta)."""
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    dx, dy = b[..., 0] - a[..., 0], b[..., 1] - a[..., 1]
    out = _se2_out(a, b)
    out[..., 0] = c * dx + s * dy
    out[..., 1] = -s * dx + c * dy
    out[..., 2] = np.arctan2(np.sin(b[..., 2] - a[..., 2]), np.cos(b[..., 2] - a[..., 2]))
    return out


# samples per `WheelTrack.add` integrated in Python floats (online a batch holds the few
# samples of one output epoch; numpy's per-call cost is then ~10x the arithmetic)
FEW_SAMPLES = 8
# query times below which `WheelTrack.between_few` (Python floats) beats the array pass
FEW_QUERIES = 16


def _integrate(start: np.ndarray, v: np.ndarray, w: np.ndarray, tau: np.ndarray
               ) -> np.ndarray:
    """Track poses (m, 3) after each of m arcs (v m/s, w rad/s for tau s) from `start`
    (x m, y m, theta rad): the arcs turned into the start frame and summed cumulatively."""
    dx, dy, dth = _arcs(v, w, tau)
    th_prev = start[2] + np.concatenate([[0.0], np.cumsum(dth)[:-1]])
    c, s = np.cos(th_prev), np.sin(th_prev)
    gx, gy = c * dx - s * dy, s * dx + c * dy
    out = np.empty((len(tau), 3))
    out[:, 0] = start[0] + np.cumsum(gx)
    out[:, 1] = start[1] + np.cumsum(gy)
    out[:, 2] = start[2] + np.cumsum(dth)
    return out


def _integrate_few(start: np.ndarray, v: np.ndarray, w: np.ndarray, tau: np.ndarray
                   ) -> np.ndarray:
    """`_integrate` in Python floats, the same operations in the same order (`arc_step`;
    the running sums as np.cumsum adds them): bit-identical, tests/test_wheel_track.py."""
    x0, y0, th0 = start.tolist()
    out = []
    cx = cy = cth = None  # the running sums (np.cumsum starts from the first term itself)
    for vi, wi, ti in zip(v.tolist(), w.tolist(), tau.tolist(), strict=True):
        th_prev = th0 + (0.0 if cth is None else cth)
        dth = wi * ti
        dx, dy = arc_step(vi, ti, 0.0, dth)
        c, s = math.cos(th_prev), math.sin(th_prev)
        gx, gy = c * dx - s * dy, s * dx + c * dy
        cx = gx if cx is None else cx + gx
        cy = gy if cy is None else cy + gy
        cth = dth if cth is None else cth + dth
        out.append((x0 + cx, y0 + cy, th0 + cth))
    return np.array(out, dtype=np.float64).reshape(-1, 3)


class WheelTrack:
    """Cumulative planar dead reckoning from wheel samples, queryable at any time.

    The track starts at (0, 0, 0) at the first sample's stamp; before it and after the
    last sample it extrapolates with the first/last velocity.
    """

    def __init__(self) -> None:
        # storage with spare capacity: a log feeds its samples in small batches (one per
        # output epoch), and re-concatenating the whole track for each was quadratic in the
        # log's length (a 1-hour log: 36,000 copies of up to 180,000 samples)
        self._n = 0
        self._t = np.zeros(0, dtype=np.int64)
        self._v = np.zeros(0)
        self._w = np.zeros(0)
        self._pose = np.zeros((0, 3))

    @property
    def t(self) -> np.ndarray:
        """Sample stamps (n,), ns."""
        return self._t[: self._n]

    @property
    def v(self) -> np.ndarray:
        """Forward speeds (n,), m/s."""
        return self._v[: self._n]

    @property
    def w(self) -> np.ndarray:
        """Yaw rates (n,), rad/s."""
        return self._w[: self._n]

    @property
    def pose(self) -> np.ndarray:
        """Track pose (x m, y m, theta rad) at each stamp (n, 3)."""
        return self._pose[: self._n]

    def __len__(self) -> int:
        return self._n

    def _reserve(self, extra: int) -> None:
        need = self._n + extra
        if need <= len(self._t):
            return
        cap = max(need, 2 * len(self._t), 1024)
        for name in ("_t", "_v", "_w", "_pose"):
            old = getattr(self, name)
            new = np.empty((cap, *old.shape[1:]), dtype=old.dtype)
            new[: self._n] = old[: self._n]
            setattr(self, name, new)

    def add(self, t_ns: np.ndarray, v: np.ndarray, omega: np.ndarray) -> None:
        """Append a time-sorted batch of samples (stamps ns, v m/s, omega rad/s)."""
        t_ns = np.asarray(t_ns, np.int64)
        if len(t_ns) == 0:
            return
        v, omega = np.asarray(v, float), np.asarray(omega, float)
        if self._n:
            keep = t_ns > self._t[self._n - 1]
            t_ns, v, omega = t_ns[keep], v[keep], omega[keep]
            if len(t_ns) == 0:
                return
            prev_t = np.concatenate([[self._t[self._n - 1]], t_ns[:-1]])
            start = self._pose[self._n - 1]
        else:
            prev_t = np.concatenate([[t_ns[0]], t_ns[:-1]])
            start = np.zeros(3)
        tau = (t_ns - prev_t).astype(np.float64) / NS_PER_S
        m = len(t_ns)
        poses = (_integrate_few if m <= FEW_SAMPLES else _integrate)(start, v, omega, tau)
        self._reserve(m)
        sl = slice(self._n, self._n + m)
        self._t[sl], self._v[sl], self._w[sl], self._pose[sl] = t_ns, v, omega, poses
        self._n += m

    def drop_before(self, t_ns: int) -> None:
        """Forget the samples no longer needed for queries at or after `t_ns` (the one
        before it stays); the track's poses are absolute, so `at`, `between` and
        `covariance` from `t_ns` on are unchanged. Compacts only when at least half the
        samples (and 1000) can go, so the copying stays linear in the samples added."""
        i = int(np.searchsorted(self.t, t_ns, side="left")) - 1
        if i < max(1000, self._n // 2):
            return
        m = self._n - i
        for name in ("_t", "_v", "_w", "_pose"):
            a = getattr(self, name)
            a[:m] = a[i:self._n].copy()
        self._n = m

    def at(self, t_ns: np.ndarray | int) -> np.ndarray:
        """Track pose(s) (x, y, theta) at `t_ns` (scalar or array of ns)."""
        tq = np.atleast_1d(np.asarray(t_ns, np.int64))
        n = self._n
        if n == 0:
            return np.zeros((len(tq), 3)) if np.ndim(t_ns) else np.zeros(3)
        t = self._t[:n]
        i = np.searchsorted(t, tq, side="left")  # t[i-1] < tq <= t[i], 0 <= i <= n
        # the sample before: i - 1; before the first stamp, sample 0 (the track goes
        # backwards from it with its velocity); the velocity: of the interval ending at
        # t[i], the last one after the last stamp
        base_i = np.maximum(i - 1, 0)
        vel_i = np.minimum(i, n - 1)
        tau = (tq - t[base_i]).astype(np.float64) / NS_PER_S
        step = np.empty((len(tq), 3))
        step[:, 0], step[:, 1], step[:, 2] = _arcs(self._v[vel_i], self._w[vel_i], tau)
        out = se2_compose(self._pose[base_i], step)
        return out if np.ndim(t_ns) else out[0]

    def between_few(self, t_a: int, t_b: list[int]) -> np.ndarray:
        """`between(t_a, t_b)` (n, 3) for a few times t_b ns (one keyframe's: its end and
        its ranges' stamps) in Python floats: `at` and `se2_between` operation for operation
        (bit-identical, tests/test_wheel_track.py); numpy's per-call cost was ~10x the
        arithmetic there."""
        (xa, ya, tha), *rest = self._at_few([t_a, *t_b])
        c, s = math.cos(tha), math.sin(tha)
        out = []
        for xb, yb, thb in rest:
            dx, dy = xb - xa, yb - ya
            out.append((c * dx + s * dy, -s * dx + c * dy,
                        float(np.arctan2(math.sin(thb - tha), math.cos(thb - tha)))))
        return np.array(out, dtype=np.float64).reshape(-1, 3)

    def _at_few(self, t_ns: list[int]) -> list[tuple[float, float, float]]:
        """`at` of a few times (ns) in Python floats (`between_few`)."""
        n = self._n
        if n == 0:
            return [(0.0, 0.0, 0.0)] * len(t_ns)
        t = self._t[:n]
        i = t.searchsorted(t_ns, side="left")  # as in `at`
        base_i, vel_i = np.maximum(i - 1, 0), np.minimum(i, n - 1)
        out = []
        for tq, tb, (x, y, th), v, w in zip(t_ns, t[base_i].tolist(),
                                            self._pose[base_i].tolist(),
                                            self._v[vel_i].tolist(), self._w[vel_i].tolist(),
                                            strict=True):
            tau = float(tq - tb) / NS_PER_S
            dth = w * tau
            dx, dy = arc_step(v, tau, 0.0, dth)
            c, s = math.cos(th), math.sin(th)
            out.append((x + c * dx - s * dy, y + s * dx + c * dy, th + dth))
        return out

    def between(self, t_a: np.ndarray | int, t_b: np.ndarray | int) -> np.ndarray:
        """Relative planar motion (x, y, theta) from time t_a to t_b, in the base frame at t_a
        (scalars, or arrays of ns: (n, 3), one per pair)."""
        return se2_between(self.at(t_a), self.at(t_b))

    def covariance(self, t_a: np.ndarray | int, t_b: np.ndarray | int,
                   cfg: WheelConfig) -> np.ndarray:
        """3x3 covariance of `between(t_a, t_b)` in (x, y, theta), from per-sample noise
        (scalars, or arrays of ns: (n, 3, 3), one per pair)."""
        q = (cfg.sigma_v**2, cfg.sigma_lateral**2, cfg.sigma_omega**2)
        if np.ndim(t_a) == 0 and np.ndim(t_b) == 0:
            return self._covariance_one(int(t_a), int(t_b), q)
        ta = np.atleast_1d(np.asarray(t_a, np.int64))
        tb = np.atleast_1d(np.asarray(t_b, np.int64))
        out = np.zeros((len(ta), 3, 3))
        still = tb <= ta if len(self.t) else np.ones(len(ta), bool)
        out[still] = np.diag([1e-6, 1e-6, 1e-6])
        go = np.flatnonzero(~still)
        if len(go) == 0:
            return out
        # P <- F P F^T + G Q G^T per piece (`_propagate_piece`), the pairs side by side
        dx, dy, dth, tau, guess = self._pieces(ta[go], tb[go])
        st = (np.zeros(len(go)),) * 7
        for i in range(tau.shape[1]):  # a padding piece (tau 0) leaves its pair as it is
            new = _propagate_piece(st, dx[:, i], dy[:, i], dth[:, i], tau[:, i], q,
                                   np.cos, np.sin, guess[:, i])
            st = tuple(np.where(tau[:, i] > 0, a, b) for a, b in zip(new, st, strict=True))
        p00, p01, p02, p11, p12, p22, _ = st
        out[go] = np.moveaxis(np.array([[p00, p01, p02], [p01, p11, p12], [p02, p12, p22]]),
                              -1, 0)
        return out

    def _covariance_one(self, t_a: int, t_b: int, q: tuple[float, float, float]) -> np.ndarray:
        """`covariance` of one pair in Python floats (one keyframe interval online: a few
        pieces, where numpy's per-call cost is ~10x the arithmetic; equal to the pairs'
        pass, tests/test_wheel_track.py)."""
        if t_b <= t_a or self._n == 0:
            return np.diag([1e-6, 1e-6, 1e-6])
        st: tuple = (0.0,) * 7
        for dx, dy, dth, tau, guess in self._pieces_one(t_a, t_b):
            st = _propagate_piece(st, dx, dy, dth, tau, q, math.cos, math.sin, guess)
        p00, p01, p02, p11, p12, p22, _ = st
        return np.array([[p00, p01, p02], [p01, p11, p12], [p02, p12, p22]])

    def _pieces(self, t_a: np.ndarray, t_b: np.ndarray) -> tuple[np.ndarray, ...]:
        """Local (dx, dy, dtheta) arcs and durations tau s (n, m) of the constant-velocity
        pieces of each interval t_a < t_b (n,) ns, cut at the samples strictly inside it;
        the intervals with fewer pieces end in padding pieces of tau 0."""
        t = self.t
        n = len(t)
        i0 = np.searchsorted(t, t_a, side="right")  # the first sample after t_a
        m = np.searchsorted(t, t_b, side="left") - i0  # samples strictly inside
        j = np.arange(1, int(m.max()) + 2)
        edges = np.empty((len(t_a), len(j) + 1), np.int64)
        edges[:, 0] = t_a
        edges[:, 1:] = np.where(j[None, :] <= m[:, None],
                                t[np.minimum(i0[:, None] + j[None, :] - 1, n - 1)], t_b[:, None])
        mid = (edges[:, :-1] + edges[:, 1:]) // 2
        idx = np.clip(np.searchsorted(t, mid, side="left"), 0, n - 1)
        tau = np.diff(edges, axis=1).astype(np.float64) / NS_PER_S
        dx, dy, dth = _arcs(self.v[idx], self.w[idx], tau)
        reach = np.maximum(np.abs(edges[:, :-1] - t[idx]), np.abs(edges[:, 1:] - t[idx]))
        guess = np.maximum(reach.astype(np.float64) / NS_PER_S - MAX_EXTRAPOLATION_S, 0.0)
        return dx, dy, dth, tau, np.where(tau > 0, guess, 0.0)

    def _pieces_one(self, t_a: int, t_b: int) -> list[tuple[float, float, float, float]]:
        """`_pieces` of one interval t_a < t_b ns in Python floats, without the padding:
        (dx, dy, dtheta, tau) per piece, by `arc_step` (bit-identical, tested)."""
        n = self._n
        t = self._t[:n]
        i0 = int(t.searchsorted(t_a, side="right"))
        i1 = int(t.searchsorted(t_b, side="left"))
        edges = [t_a, *t[i0:i1].tolist(), t_b]
        pairs = list(itertools.pairwise(edges))
        idx = [min(i, n - 1) for i in  # >= 0
               t.searchsorted([(e0 + e1) // 2 for e0, e1 in pairs], side="left").tolist()]
        out = []
        for (e0, e1), v, w, ts in zip(pairs, self._v[idx].tolist(), self._w[idx].tolist(),
                                      t[idx].tolist(), strict=True):
            tau = float(e1 - e0) / NS_PER_S
            th = w * tau
            dx, dy = arc_step(v, tau, 0.0, th)
            reach = max(abs(e0 - ts), abs(e1 - ts))
            out.append((dx, dy, th, tau, max(float(reach) / NS_PER_S - MAX_EXTRAPOLATION_S,
                                             0.0)))
        return out


def unseen_twist_variance(guess: Any) -> tuple[Any, Any]:
    """Variances ((m/s)^2, (rad/s)^2) to add to the wheel speed and turn rate of a stretch
    that carries a held twist `guess` s beyond MAX_EXTRAPOLATION_S from the sample it came
    from (a dropout): the vehicle may have changed its speed and turn rate unseen by
    WHEEL_GUESS_ACCEL and WHEEL_GUESS_YAW_ACCEL per second since (floats or arrays)."""
    return (WHEEL_GUESS_ACCEL * guess) ** 2, (WHEEL_GUESS_YAW_ACCEL * guess) ** 2


def _propagate_piece(st: tuple, dx: Any, dy: Any, dth: Any, tau: Any,
                     q: tuple[float, float, float], cos: Any, sin: Any,
                     guess: Any = 0.0) -> tuple:
    """One piece of `WheelTrack.covariance`'s propagation, state (p00, p01, p02, p11, p12,
    p22, theta) (floats or arrays): P <- F P F^T + G Q G^T, F = [[1, 0, a], [0, 1, b],
    [0, 0, 1]] (a, b: the piece's translation (dx, dy) in the frame at t_a, turned by 90
    deg), G = rot(theta) (+) 1, Q = diag(q) tau^2; theta += dth. `guess` s: how far the
    piece reaches beyond MAX_EXTRAPOLATION_S from the sample whose twist it carries (a
    dropout), its `unseen_twist_variance` added to q's speed and turn-rate variances."""
    p00, p01, p02, p11, p12, p22, th = st
    q0, q1, q2 = q
    add_v, add_w = unseen_twist_variance(guess)
    q0 = q0 + add_v
    q2 = q2 + add_w
    c, s = cos(th), sin(th)
    a = -s * dx - c * dy
    b = c * dx - s * dy
    r00, r01, r02 = p00 + a * p02, p01 + a * p12, p02 + a * p22
    n00 = r00 + a * r02
    n01 = r01 + b * r02
    n11 = (p11 + b * p12) + b * (p12 + b * p22)
    t2 = tau * tau
    g0, g1 = q0 * t2, q1 * t2
    return (n00 + c * c * g0 + s * s * g1, n01 + c * s * (g0 - g1), r02,
            n11 + s * s * g0 + c * c * g1, p12 + b * p22, p22 + q2 * t2, th + dth)
