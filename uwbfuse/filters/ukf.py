# SPDX-License-Identifier: BSD-3-Clause
"""`ukf`: the unscented Kalman filter of the odometer/IMU/LiDAR/UWB AGV paper, same inputs.

The paper ("AGV indoor navigation ... multi-sensor fusion of odometer, IMU, LiDAR and UWB",
HSET vol. 7, AIEA 2022, sec. 4.1) runs the scaled unscented transform (eq. 11-13: 2n+1
sigma points around the mean, spread sqrt((n + lambda) P)), propagates every sigma point
through the process (eq. 14-16, additive Q), redraws them (eq. 17), predicts the
measurements per sigma point (eq. 18-21) and updates with K = Pxz Pzz^-1 (eq. 22-24).
Weights are the standard scaled (Merwe) ones from `[ukf] alpha, beta, kappa`:
lambda = alpha^2 (n + kappa) - n, Wm0 = lambda / (n + lambda),
Wc0 = Wm0 + 1 - alpha^2 + beta, Wi = 1 / (2 (n + lambda)).

Adapted to the inputs the graph and the EKF see (the paper's constant-acceleration point
mass with UWB position fixes and no LiDAR here):

- With an IMU: the state is the EKF's navigation state (position, velocity, attitude, gyro
  and accelerometer biases); sigma points are drawn in the 15-D error state around it
  (attitude as a rotation vector, R_i = Exp(dtheta_i) R) and each one is mechanised through
  the IMU samples, all sigma points at once (`models.mechanise` is batched).
- Without an IMU: the paper's odometer model (eq. 3, planar unicycle x, y, yaw) driven by
  the wheels.
- UWB ranges are scalar measurements (tag lever arm included), each weighted and gated
  on its innovation and predicted variance as in the EKF (`adaptive_noise.RangeNoise`),
  then updated together; where the tag height is held (wheels) the state carries the
  EKF's per-anchor range biases (`base.StreamingFilter`: `RANGE_BIAS`, `bias_decay`),
  drawn as sigma points with the rest, but not its common range-scale state (with it the
  UKF did better on the real logs but missed three of its tests: docs/results.md);
  wheel speeds are base-frame velocity measurements (forward v, zero lateral/vertical
  speed); soft planar height and roll/pitch constraint with wheels, as in the EKF.

Where the attitude is as good as unknown (a still start sees no heading: std pi), a
window runs the EKF's first-order update instead: the scaled unscented transform's mean is
exact to second order, which for a rotated vector is (1 - sigma^2 / 2) of it and turns
back beyond sigma = sqrt(2) rad (`UT_MAX_ATTITUDE_SIGMA`; docs/results.md, "The UKF from a
start with an unknown heading").

Windows: as in the EKF, the time since the last step is cut into windows of at most 0.1 s.
One sigma-point set is drawn at the window start and propagated through the window; every
measurement of the window is predicted on each sigma point's trajectory at its own stamp,
and the update corrects the state at the window end through the sigma points' cross
covariance (a UKF over the window; the process noise of the window, added to the end
covariance, is not seen by the window's own measurements).

Pose covariance (IMU-driven, with range-bias states, where pose covariances are wanted):
the EKF's consider analysis (`filters.consider`: an anchor's NLOS excess persists over
its episode), applied by statistical linearisation: the window's transition from the
sigma points' cross covariance of end and start, each update through its composite gain
Pxz (Pzz + R)^-1 and rows Pxz^T P^-1. The estimate is the filter's either way.
"""

from __future__ import annotations

import math

import numpy as np

from uwbfuse.config import Config
from uwbfuse.constants import UT_MAX_ATTITUDE_SIGMA
from uwbfuse.errors import EstimatorError
from uwbfuse.estimator import Estimator, Method
from uwbfuse.filters.adaptive_noise import (
    InnovationVariance,
    RangeNoise,
    gaussian_log_density,
    sequential_ranges,
)
from uwbfuse.filters.base import InitialiserLike, build_filter
from uwbfuse.filters.consider import ConsiderCovariance
from uwbfuse.filters.ekf import ErrorStateEkf, UnicycleEkf
from uwbfuse.filters.models import (
    BA,
    BG,
    F64,
    N_ERR,
    P_,
    TH,
    V_,
    augment,
    joseph_update,
    mechanise,
    so3_exp,
    so3_log,
    unicycle_transition,
)
from uwbfuse.positioning.wheel_track import unicycle_track
from uwbfuse.streams import AnchorMap


class MerweWeights:
    """Scaled unscented transform for dimension n: spread and weights (Wm, Wc)."""

    def __init__(self, n: int, alpha: float, beta: float, kappa: float) -> None:
        lam = alpha * alpha * (n + kappa) - n
        if n + lam <= 0:
            raise EstimatorError(
                f"ukf: alpha^2 (n + kappa) must be positive (n={n}, alpha={alpha}, kappa={kappa})"
            )
        self.n = n
        self.scale = math.sqrt(n + lam)
        self.wm = np.full(2 * n + 1, 0.5 / (n + lam))
        self.wc = self.wm.copy()
        self.wm[0] = lam / (n + lam)
        self.wc[0] = lam / (n + lam) + 1.0 - alpha * alpha + beta

    def offsets(self, p: F64) -> F64:
        """Sigma-point offsets (2n+1, n): 0, +columns and -columns of sqrt((n + lambda) P)."""
        try:
            l_ = np.linalg.cholesky(p)
        except np.linalg.LinAlgError:
            w, v = np.linalg.eigh(0.5 * (p + p.T))
            l_ = v * np.sqrt(np.maximum(w, 1e-12))
        cols = self.scale * l_.T
        return np.concatenate([np.zeros((1, self.n)), cols, -cols])


def _linearise_instead(attitude_var: F64) -> bool:
    """True where an attitude variance (rad^2) exceeds UT_MAX_ATTITUDE_SIGMA^2: there the
    unscented mean of a rotated vector turns back (module docstring), and the window is the
    EKF's."""
    return float(np.max(attitude_var)) > UT_MAX_ATTITUDE_SIGMA**2


def _unscented_update(
    wts: MerweWeights, ex: F64, zs: F64, z: F64, r: F64, p_prior: F64,
    noise: RangeNoise, anchor: np.ndarray,
    row_noise: list[tuple[InnovationVariance, int]] | None = None,
    evidence: F64 | None = None,
    consider: ConsiderCovariance | None = None,
) -> tuple[F64, F64, F64, np.ndarray, F64, np.ndarray, float]:
    """Update from sigma-point states and predicted measurements.

    ex (2n+1, n): sigma-point state deviations from the central point; zs (2n+1, m):
    predicted measurements; z (m,) measured; r (m,) variances; p_prior (n,n) the predicted
    covariance (already with Q). The first len(anchor) rows are ranges of those anchors,
    the rows after them (wheel speeds, planar constraint) feed `row_noise` in order:
    (estimator, number of rows) per block.

    The sigma points give the joint Gaussian of the state error and the predicted
    measurements (cross covariance Pxz, Pzz); the update conditions it as the EKF does
    (`ErrorStateEkf._window`): first on the rows after the ranges (one stacked Joseph
    update), then on the ranges one by one (`adaptive_noise.sequential_ranges`: each
    weighed by `noise` on the innovation and prediction variance left after the
    measurements before it, NLOS mixture posterior as the measurement, chi-square gate),
    so that the ranges of one window that share the state's error are not weighed, gated
    and scored (the noise bank's likelihood) as if each were the only one. Returns the
    correction of the central point (n,), the posterior covariance, the innovation y (m,)
    before the update, the accepted-row mask, the normalised innovations squared of the
    ranges, which of those measured short (negative innovation) and the log density
    (nats) of the rows after the ranges. `evidence` (len(anchor),): the NLOS classifier's
    log-odds per range, nats. `consider`: the consider analysis (`filters.consider`) the
    same update is applied to, by statistical linearisation.
    """
    nr = len(anchor)
    n, m = ex.shape[1], zs.shape[1]
    ex_mean = wts.wm @ ex
    dz0 = zs - zs[0]
    z_mean = zs[0] + wts.wm @ dz0
    dx = ex - ex_mean
    dz = zs - z_mean
    # joint covariance of (state error, predicted measurements): the measurements are
    # states n.. of an augmented linear system, each observed by a unit row
    c = np.empty((n + m, n + m))
    c[:n, :n] = p_prior
    pxz = (dx.T * wts.wc) @ dz
    c[:n, n:] = pxz
    c[n:, :n] = pxz.T
    c[n:, n:] = (dz.T * wts.wc) @ dz
    y = z - z_mean
    keep = np.ones(m, dtype=bool)
    short = y[:nr] < 0.0
    nis = np.zeros(nr)
    unit = np.eye(n + m)[n:]
    corr = np.zeros(n + m)
    row_ll = 0.0
    c0 = c.copy() if consider is not None else None
    gains: list | None = [] if consider is not None else None
    if m > nr:
        s_all = np.diag(c)[n:]
        start = nr
        for est, n_rows in row_noise or ():
            est.update(y[start : start + n_rows], s_all[start : start + n_rows])
            start += n_rows
        corr, c, s_rows, _ = joseph_update(c, unit[nr:], r[nr:], y[nr:])
        row_ll = gaussian_log_density(y[nr:], s_rows)
    if nr:
        c, corr, keep[:nr], nis = sequential_ranges(
            noise, c, corr, unit[:nr], y[:nr], anchor, z[:nr], evidence, gains)
    if consider is not None and c0 is not None:
        var = np.asarray(r, float).copy()
        for i, _, v in gains or ():  # the variance each accepted range was weighed at
            var[i] = v
        used = np.flatnonzero(keep)
        row_anchor = np.full(len(used), -1, np.int64)  # the rows after the ranges: none
        ranges = used < nr
        row_anchor[ranges] = np.asarray(anchor, np.int64)[used[ranges]]
        consider.update_linearised(c0, used, var[used], row_anchor)
    return ex_mean + corr[:n], c[:n, :n], y, keep, nis, short, row_ll


class ErrorStateUkf(ErrorStateEkf):
    """UKF on the IMU-driven navigation state (modes 'imu+wheel' and 'imu').

    Shares the EKF's state layout, start, injection and outputs; `_window` replaces the
    linearisation by sigma points.
    """

    RANGE_SCALE = False  # range biases, no common scale state (module docstring)
    # the consider analysis by statistical linearisation of its sigma points (transition
    # and measurement rows from their cross covariances)
    CONSIDER = True

    def __init__(
        self,
        config: Config,
        anchors: AnchorMap,
        streams: frozenset[str],
        initialiser: InitialiserLike | None = None,
    ) -> None:
        super().__init__(config, anchors, streams, initialiser)
        u = config.ukf
        self.weights = MerweWeights(self.n_x, u.alpha, u.beta, u.kappa)

    def _window(
        self, t_b: int, rt: np.ndarray, ra: np.ndarray, rr: np.ndarray,
        wt: np.ndarray, wv: np.ndarray,
    ) -> np.ndarray:
        """Draw sigma points, mechanise them to t_b, update with the window's measurements.

        With the attitude known to no better than UT_MAX_ATTITUDE_SIGMA (a start with an
        unknown heading) the unscented mean is no mean (at a heading std of pi the wheel
        rows' predicted forward speed came out -4 times the central sigma point's): the
        EKF's first-order window runs instead until the updates narrow the attitude.
        """
        if _linearise_instead(np.diag(self.P)[TH]):
            return super()._window(t_b, rt, ra, rr, wt, wv)
        nr, nw = len(rt), len(wt)
        gyro, accel, dt, kidx = self.imu_grid(t_b, np.concatenate([rt, wt]))
        guess_s = 0.0
        if np.isnan(gyro[:, 0]).any():
            nan = np.isnan(gyro[:, 0])
            gyro[nan] = self.bg
            accel[nan] = self.R.T @ np.array([0.0, 0.0, self.gravity]) + self.ba
            guess_s = float(dt[nan].sum())
        off = self.weights.offsets(self.P)                      # (S,15 + biases)
        r0 = so3_exp(off[:, TH]) @ self.R
        rs, vs, ps, _ = mechanise(
            r0, self.v + off[:, V_], self.p + off[:, P_], self.bg + off[:, BG],
            self.ba + off[:, BA], gyro, accel, dt, self.gravity,
        )
        t = float(dt.sum())
        # End-state deviations from the central sigma point (error-state coordinates).
        ex = np.empty_like(off)
        ex[:, P_] = ps[:, -1] - ps[0, -1]
        ex[:, V_] = vs[:, -1] - vs[0, -1]
        ex[:, TH] = so3_log(rs[:, -1] @ rs[0, -1].T)
        ex[:, BG] = off[:, BG]
        ex[:, BA] = off[:, BA]
        nb = self.n_bias
        if nb:  # per-anchor range biases (Gauss-Markov): the EKF's model
            f, qb = self.bias_decay(t)
            bias = self.rbias + off[:, N_ERR:]              # at the window start
            ex[:, N_ERR:] = off[:, N_ERR:] * f
        wts = self.weights
        ex_mean = wts.wm @ ex
        dxx = ex - ex_mean
        q = self._q(t)
        if guess_s > 0.0 and self.has_wheel:  # a dropout's still guess: what it cannot see
            q = q + self.dropout_noise(guess_s)
        q_full = augment(q, qb) if nb else q
        p_prior = (dxx.T * wts.wc) @ dxx + q_full
        if self.consider is not None:
            self._consider_propagate(off, dxx, q_full, f)
        zs: list[F64] = []
        zm: list[F64] = []
        rv: list[F64] = []
        noise: list[tuple[InnovationVariance, int]] = []
        if nr:
            k = kidx[:nr]
            d = ps[:, k] + rs[:, k] @ self.tag_b - self.anchor_pos[ra]
            dist = np.sqrt(np.einsum("smi,smi->sm", d, d))
            if nb:
                dist = dist + bias[:, ra]
            zs.append(dist)
            zm.append(rr)
            rv.append(np.zeros(nr))  # replaced by the range noise's weights
        if nw:
            k = kidx[nr:]
            vb = np.einsum("smji,smj->smi", rs[:, k], vs[:, k])   # R^T v per point and stamp
            zs.append(vb.reshape(len(off), 3 * nw))
            z = np.zeros((nw, 3))
            z[:, 0] = wv
            zm.append(z.reshape(-1))
            rv.append(np.tile(self.wheel_noise.r, nw))
            noise.append((self.wheel_noise, 3 * nw))
        if self.planar:  # height z0 and level, at the window start
            zs.append(np.concatenate([self.p[2] + off[:, 2:3], r0[:, :2, 2]], axis=1))
            zm.append(np.array([self.z0, 0.0, 0.0]))
            rv.append(self.planar_noise.r)
            noise.append((self.planar_noise, 3))
        used = np.ones(nr, dtype=bool)
        corr = ex_mean
        if zs:
            corr, p_prior, self.y, keep, nis, self.short, row_ll = _unscented_update(
                wts, ex, np.concatenate(zs, axis=1), np.concatenate(zm), np.concatenate(rv),
                p_prior, self.range_noise, ra, noise, self.range_evidence(rt, ra),
                self.consider,
            )
            used = keep[:nr]
            self.nis = nis
            self.row_log_likelihood += row_ll
        self.P = p_prior
        self.R, self.v, self.p = rs[0, -1], vs[0, -1], ps[0, -1]
        self._inject(corr[:N_ERR])
        if nb:
            self.rbias = f * self.rbias + corr[N_ERR:]
        return used

    def _consider_propagate(self, off: F64, dxx: F64, q_full: F64, f: F64) -> None:
        """The window's transition in the consider analysis: F = P_(end,start) P^-1 from the
        sigma points' start offsets `off` and end deviations `dxx` (their start covariance
        is P exactly), the filter's noise `q_full`, each anchor's excess decaying by f."""
        assert self.consider is not None
        cross = (dxx.T * self.weights.wc) @ off
        t_eff = np.linalg.lstsq(self.P, cross.T, rcond=None)[0].T  # P symmetric
        fc = np.full(len(self.anchors), f[0])
        self.consider.propagate(t_eff, q_full, fc, (1.0 - fc * fc) * self.consider_variance())

    def _q(self, t: float) -> F64:
        """Discrete process noise over t s: white accel/gyro noise and bias random walks.

        Velocity random walk qa t with its integrated position part (qa t^3/3, qa t^2/2);
        attitude qg t; biases qbg t, qba t. The cross terms through the attitude (gyro
        noise into velocity) are third order in t and dropped.
        """
        q = np.diag(self.q_diag * t)
        qa = self.q_diag[3]
        q[P_, P_] += np.eye(3) * qa * t**3 / 3.0
        q[P_, V_] += np.eye(3) * qa * t * t / 2.0
        q[V_, P_] += np.eye(3) * qa * t * t / 2.0
        return q


class UnicycleUkf(UnicycleEkf):
    """UKF on the planar unicycle (x, y, yaw) driven by wheel odometry: the paper's eq. 3."""

    RANGE_SCALE = False  # range biases, no common scale state (module docstring)

    def __init__(
        self,
        config: Config,
        anchors: AnchorMap,
        streams: frozenset[str],
        initialiser: InitialiserLike | None = None,
    ) -> None:
        super().__init__(config, anchors, streams, initialiser)
        u = config.ukf
        self.weights = MerweWeights(3 + self.n_bias, u.alpha, u.beta, u.kappa)

    def _window(
        self, t_b: int, rt: np.ndarray, ra: np.ndarray, rr: np.ndarray,
        wt: np.ndarray, wv: np.ndarray,
    ) -> np.ndarray:
        """Propagate the 7 sigma points along the wheels to t_b; update with the ranges
        (the EKF's window while the yaw std exceeds UT_MAX_ATTITUDE_SIGMA, as in
        `ErrorStateUkf._window`: the unscented mean of the window's motion turns back)."""
        if _linearise_instead(np.diag(self.P)[2:3]):
            return super()._window(t_b, rt, ra, rr, wt, wv)
        nr = len(rt)
        v, w, dt, k, guess = self.wheel_grid(t_b, rt)
        off = self.weights.offsets(self.P)
        pts = self.x + off[:, :3]
        xb, yb, yawb, mid = unicycle_track(pts[:, 0], pts[:, 1], pts[:, 2], v, w, dt)
        _, q = unicycle_transition(
            np.diff(xb[0]), np.diff(yb[0]), v, dt, mid[0], self.sigma_v, self.sigma_w, guess
        )
        ex = np.zeros_like(off)
        ex[:, 0] = xb[:, -1] - xb[0, -1]
        ex[:, 1] = yb[:, -1] - yb[0, -1]
        ex[:, 2] = yawb[:, -1] - yawb[0, -1]
        nb = self.n_bias
        if nb:  # per-anchor range biases (Gauss-Markov): the EKF's model
            f, qb = self.bias_decay(float(dt.sum()))
            bias = self.rbias + off[:, 3:]                  # at the window start
            ex[:, 3:] = off[:, 3:] * f
            q = augment(q, qb)
        wts = self.weights
        ex_mean = wts.wm @ ex
        dxx = ex - ex_mean
        p_prior = (dxx.T * wts.wc) @ dxx + q
        used = np.ones(nr, dtype=bool)
        corr = ex_mean
        if nr:
            tx, ty, tz = self.tag_b
            cy, sy = np.cos(yawb[:, k]), np.sin(yawb[:, k])
            a = self.anchor_pos[ra]
            dx_ = xb[:, k] + cy * tx - sy * ty - a[:, 0]
            dy_ = yb[:, k] + sy * tx + cy * ty - a[:, 1]
            dz_ = self.z0 + tz - a[:, 2]
            zs = np.sqrt(dx_ * dx_ + dy_ * dy_ + dz_ * dz_)
            if nb:
                zs = zs + bias[:, ra]
            corr, p_prior, y, used, self.nis, self.short, _ = _unscented_update(
                wts, ex, zs, rr, np.zeros(nr), p_prior, self.range_noise, ra,
                evidence=self.range_evidence(rt, ra),
            )
            self.y = y
        self.P = p_prior
        self.x = np.array([xb[0, -1], yb[0, -1], yawb[0, -1]]) + corr[:3]
        if nb:
            self.rbias = f * self.rbias + corr[3:]
        return used


def make_filter(
    config: Config,
    anchors: AnchorMap | None,
    streams: frozenset[str],
    initialiser: InitialiserLike | None = None,
) -> ErrorStateUkf | UnicycleUkf:
    """The UKF variant for the sensor combination: IMU-driven when there is an IMU."""
    return build_filter(
        Method.UKF, ErrorStateUkf, UnicycleUkf, config, anchors, streams, initialiser
    )


def make(
    method: Method, config: Config, anchors: AnchorMap | None, streams: frozenset[str]
) -> Estimator:
    """Factory of the method registry (`uwbfuse.methods`)."""
    if method is not Method.UKF:
        raise EstimatorError(f"uwbfuse.filters.ukf cannot build method {method.value}")
    est = make_filter(config, anchors, streams)
    if isinstance(est, ErrorStateUkf):  # the IMU process-noise level from the log
        from uwbfuse.filters.noise_bank import ProcessNoiseBank

        return ProcessNoiseBank(est)
    return est
