# SPDX-License-Identifier: BSD-3-Clause
"""Process and measurement models shared by the EKF and the UKF baselines.

Conventions (both filters):
- Navigation state of the base frame in the map frame (z up): position p (3,) m, velocity
  v (3,) m/s, attitude R = R_map_base (3,3), gyro bias bg (3,) rad/s and accelerometer bias
  ba (3,) m/s^2, both expressed in the base frame (IMU samples are rotated into the base
  frame on arrival, see `imu_to_base`).
- Error state (15,) = [dp, dv, dtheta, dbg, dba]; the attitude error is global (map frame):
  R_true = Exp(dtheta) R_est.
- Planar unicycle state (no IMU): [x, y, yaw] of the base in the map frame, m and rad; the
  base height stays at the initial z.

Every function is vectorised over a leading batch axis where noted (the UKF pushes all sigma
points through one call).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.special import gammaincinv

from uwbfuse.positioning.wheel_track import unseen_twist_variance
from uwbfuse.streams import UNKNOWN_VARIANCE

F64 = NDArray[np.float64]

NS_PER_S = 1_000_000_000
I3 = np.eye(3)
I15 = np.eye(15)

# Error-state layout.
P_ = slice(0, 3)
V_ = slice(3, 6)
TH = slice(6, 9)
BG = slice(9, 12)
BA = slice(12, 15)
N_ERR = 15


def skew(w: F64) -> F64:
    """Cross-product matrices [w]x for w (..., 3) -> (..., 3, 3)."""
    w = np.asarray(w, dtype=np.float64)
    out = np.zeros((*w.shape[:-1], 3, 3))
    out[..., 0, 1] = -w[..., 2]
    out[..., 0, 2] = w[..., 1]
    out[..., 1, 0] = w[..., 2]
    out[..., 1, 2] = -w[..., 0]
    out[..., 2, 0] = -w[..., 1]
    out[..., 2, 1] = w[..., 0]
    return out


def cross(a: F64, b: F64) -> F64:
    """Row-wise cross products of (M,3) arrays (cheaper than np.cross for small M)."""
    out = np.empty(np.broadcast_shapes(a.shape, b.shape))
    out[..., 0] = a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1]
    out[..., 1] = a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2]
    out[..., 2] = a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]
    return out


def so3_exp(phi: F64) -> F64:
    """Rodrigues: rotation vectors (..., 3) rad -> rotation matrices (..., 3, 3).

    R = cos(t) I + a [phi]x + b phi phi^T, t = |phi|, a = sin(t)/t, b = (1 - cos t)/t^2;
    a and b by their Taylor series when every angle is below 0.05 rad (the per-sample
    increments of the mechanisation; truncation error < 1e-13), else by sinc.
    """
    phi = np.asarray(phi, dtype=np.float64)
    if phi.ndim == 1:
        return _exp_one(float(phi[0]), float(phi[1]), float(phi[2]))
    th2 = np.einsum("...i,...i->...", phi, phi)
    if th2.size and float(th2.max()) < 2.5e-3:
        a = 1.0 - th2 / 6.0 * (1.0 - th2 / 20.0 * (1.0 - th2 / 42.0))
        b = 0.5 - th2 / 24.0 * (1.0 - th2 / 30.0 * (1.0 - th2 / 56.0))
        c = 1.0 - th2 * b
    else:
        th = np.sqrt(th2)
        a = np.sinc(th / np.pi)
        h = np.sinc(th / (2.0 * np.pi))
        b = 0.5 * h * h
        c = np.cos(th)
    x, y, z = phi[..., 0], phi[..., 1], phi[..., 2]
    bx, by, bz = b * x, b * y, b * z
    ax, ay, az = a * x, a * y, a * z
    out = np.empty((*phi.shape[:-1], 3, 3))
    out[..., 0, 0] = c + bx * x
    out[..., 1, 1] = c + by * y
    out[..., 2, 2] = c + bz * z
    bxy, bxz, byz = bx * y, bx * z, by * z
    out[..., 0, 1] = bxy - az
    out[..., 1, 0] = bxy + az
    out[..., 0, 2] = bxz + ay
    out[..., 2, 0] = bxz - ay
    out[..., 1, 2] = byz - ax
    out[..., 2, 1] = byz + ax
    return out


def _exp_one(x: float, y: float, z: float) -> F64:
    """so3_exp of one rotation vector with Python floats (cheaper than numpy for one)."""
    th2 = x * x + y * y + z * z
    if th2 < 1e-8:
        a = 1.0 - th2 / 6.0
        b = 0.5 - th2 / 24.0
        c = 1.0 - 0.5 * th2
    else:
        th = math.sqrt(th2)
        a = math.sin(th) / th
        c = math.cos(th)
        b = (1.0 - c) / th2
    bx, by, bz = b * x, b * y, b * z
    return np.array([
        [c + bx * x, bx * y - a * z, bx * z + a * y],
        [bx * y + a * z, c + by * y, by * z - a * x],
        [bx * z - a * y, by * z + a * x, c + bz * z],
    ])


def cumulative_product(m: F64) -> F64:
    """Inclusive prefix products m_0 m_1 ... m_k along axis -3 of (..., N, 3, 3).

    Hillis-Steele scan: ceil(log2 N) batched matrix products instead of N Python steps.
    """
    out = m.copy()
    n = m.shape[-3]
    step = 1
    while step < n:
        out[..., step:, :, :] = out[..., :-step, :, :] @ out[..., step:, :, :]
        step *= 2
    return out


def so3_log(r: F64) -> F64:
    """Rotation matrices (..., 3, 3) -> rotation vectors (..., 3) rad (angles < pi)."""
    r = np.asarray(r, dtype=np.float64)
    tr = np.trace(r, axis1=-2, axis2=-1)
    c = np.clip(0.5 * (tr - 1.0), -1.0, 1.0)
    th = np.arccos(c)
    v = np.stack(
        [r[..., 2, 1] - r[..., 1, 2], r[..., 0, 2] - r[..., 2, 0], r[..., 1, 0] - r[..., 0, 1]],
        axis=-1,
    )
    s = np.sin(th)
    small = s < 1e-9
    scale = np.where(small, 0.5 + th * th / 12.0, th / (2.0 * np.where(small, 1.0, s)))
    return v * scale[..., None]


def quat_xyzw_from_matrix(r: F64) -> F64:
    """One rotation matrix (3,3) -> unit quaternion (x, y, z, w), w >= 0."""
    m = r
    tr = m[0, 0] + m[1, 1] + m[2, 2]
    if tr > 0.0:
        s = math.sqrt(tr + 1.0) * 2.0
        q = [(m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, 0.25 * s]
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = math.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2]) * 2.0
        q = [0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s, (m[2, 1] - m[1, 2]) / s]
    elif m[1, 1] > m[2, 2]:
        s = math.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2]) * 2.0
        q = [(m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s, (m[0, 2] - m[2, 0]) / s]
    else:
        s = math.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1]) * 2.0
        q = [(m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s, (m[1, 0] - m[0, 1]) / s]
    qa = np.array(q)
    qa /= np.linalg.norm(qa)
    return -qa if qa[3] < 0 else qa


def quat_xyzw_from_yaw(yaw: float) -> F64:
    """Quaternion (x, y, z, w) of a rotation by `yaw` rad about the map z axis."""
    return np.array([0.0, 0.0, math.sin(0.5 * yaw), math.cos(0.5 * yaw)])


def rot_z(yaw: float) -> F64:
    """Rotation matrix of `yaw` rad about z."""
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def gate_threshold(probability: float, dof: int) -> float:
    """Chi-square innovation gate: squared Mahalanobis distance accepted with `probability`.

    `scipy.stats.chi2.ppf` computes the same 2 * gammaincinv(dof / 2, p), but importing
    scipy.stats (~0.3 s) was part of every `run`."""
    return float(2 * gammaincinv(dof / 2, probability))


def imu_rotation(imu_in_base: tuple[float, ...]) -> F64:
    """R_base_imu (3,3) from the `imu_in_base` extrinsic (x y z qx qy qz qw)."""
    q = np.asarray(imu_in_base[3:7], dtype=np.float64)
    qx, qy, qz, qw = q / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (qy * qy + qz * qz), 2 * (qx * qy - qz * qw), 2 * (qx * qz + qy * qw)],
        [2 * (qx * qy + qz * qw), 1 - 2 * (qx * qx + qz * qz), 2 * (qy * qz - qx * qw)],
        [2 * (qx * qz - qy * qw), 2 * (qy * qz + qx * qw), 1 - 2 * (qx * qx + qy * qy)],
    ])


def imu_to_base(
    gyro: F64, accel: F64, imu_in_base: tuple[float, ...]
) -> tuple[F64, F64]:
    """Rotate IMU samples (N,3) into the base frame; remove the lever-arm centripetal term.

    gyro rad/s, accel specific force m/s^2. The angular-acceleration term of the lever arm
    is neglected (it needs a derivative of the gyro; small for a rigidly mounted IMU near the
    base origin).
    """
    x, y, z = imu_in_base[:3]
    if tuple(imu_in_base[:6]) == (0.0, 0.0, 0.0, 0.0, 0.0, 0.0):
        return gyro, accel
    r_bi = imu_rotation(imu_in_base)
    w = gyro @ r_bi.T
    f = accel @ r_bi.T
    lever = np.array([x, y, z])
    if np.any(lever != 0.0):
        f = f - np.cross(w, np.cross(w, lever))
    return w, f


@dataclass(frozen=True)
class ImuNoise:
    """Continuous-time IMU noise (from `ImuConfig`), all as spectral densities squared.

    qa: (m/s^2)^2/Hz, qg: (rad/s)^2/Hz, qba: (m/s^3)^2/Hz, qbg: (rad/s^2)^2/Hz.
    """

    qa: float
    qg: float
    qba: float
    qbg: float

    @classmethod
    def from_config(cls, imu: object) -> ImuNoise:
        return cls(
            qa=imu.accel_noise_density**2,  # type: ignore[attr-defined]
            qg=imu.gyro_noise_density**2,  # type: ignore[attr-defined]
            qba=imu.accel_bias_random_walk**2,  # type: ignore[attr-defined]
            qbg=imu.gyro_bias_random_walk**2,  # type: ignore[attr-defined]
        )

    def diag(self) -> F64:
        """Diagonal of the continuous process noise on the error state (15,)."""
        return np.concatenate([
            np.zeros(3), np.full(3, self.qa), np.full(3, self.qg),
            np.full(3, self.qbg), np.full(3, self.qba),
        ])


def mechanise(
    r0: F64, v0: F64, p0: F64, bg: F64, ba: F64,
    gyro: F64, accel: F64, dt: F64, gravity: float,
) -> tuple[F64, F64, F64, F64]:
    """Strapdown IMU mechanisation over a block of N zero-order-hold intervals.

    Batched over a leading axis B (sigma points): r0 (B,3,3), v0/p0/bg/ba (B,3); samples
    gyro/accel (N,3) in the base frame (rad/s, m/s^2), dt (N,) s. Attitude is integrated
    exactly per interval (Rodrigues), velocity and position with the specific force rotated
    by the attitude at the start of each interval (first order in dt; at 100-200 Hz the
    error is far below the UWB noise). Earth rate and transport rate are neglected.

    Returns the states at the N+1 interval boundaries: R (B,N+1,3,3), v (B,N+1,3) m/s,
    p (B,N+1,3) m, and the map-frame specific forces s (B,N,3) m/s^2 of each interval.
    """
    n = len(dt)
    w = gyro[None, :, :] - bg[:, None, :]
    f = accel[None, :, :] - ba[:, None, :]
    d_r = cumulative_product(so3_exp(w * dt[None, :, None]))
    rs = np.empty((r0.shape[0], n + 1, 3, 3))
    rs[:, 0] = r0
    rs[:, 1:] = r0[:, None] @ d_r
    s = np.einsum("bnij,bnj->bni", rs[:, :-1], f)
    adt = s * dt[None, :, None]
    adt[..., 2] -= gravity * dt
    v = np.empty((r0.shape[0], n + 1, 3))
    v[:, 0] = v0
    np.cumsum(adt, axis=1, out=v[:, 1:])
    v[:, 1:] += v0[:, None, :]
    dp = v[:, :-1] * dt[None, :, None] + 0.5 * adt * dt[None, :, None]
    p = np.empty_like(v)
    p[:, 0] = p0
    np.cumsum(dp, axis=1, out=p[:, 1:])
    p[:, 1:] += p0[:, None, :]
    return rs, v, p, s


_ROWS0 = np.eye(N_ERR)[:9]


@dataclass(frozen=True)
class Prefix:
    """Error-state transitions from the block start to every boundary k = 0..N.

    Per interval k (first order, plus the 0.5 a dt^2 terms of the position): dtheta +=
    -R_k dt_k dbg; dv += -[s_k]x dtheta dt_k - R_k dt_k dba; dp += dv dt_k. The dynamics
    are nilpotent (p <- v <- theta <- bg, v <- ba), so the products of the per-interval
    transitions are cumulative sums: with C_k = sum_{j<k} R_j dt_j, D_k = sum_{j<k}
    [s_j]x dt_j, E_k = sum_{j<k} [s_j]x dt_j C_j, the blocks of Phi(k) are vtheta = -D_k,
    vbg = E_k, vba = -C_k, thetabg = -C_k, pv = T_k, ptheta = -PD_k, pbg = PE_k,
    pba = -PC_k (PD, PE, PC: the time integrals of D, E, C).

    `rows[k]` (9,15) holds the p, v and theta rows of Phi(k); the bias rows are identity.
    """

    t: F64       # (N+1,) elapsed time, s
    rows: F64    # (N+1, 9, 15)

    @classmethod
    def build(cls, rs: F64, s: F64, dt: F64) -> Prefix:
        """From the attitudes at interval starts rs (N,3,3), specific forces s (N,3), dt (N,)."""
        n = len(dt)
        dtc = dt[:, None, None]
        # Three levels of cumulative sums, each level stacked into one cumsum call.
        lv1 = np.zeros((n + 1, 2, 3, 3))
        sx = skew(s) * dtc
        lv1[1:, 0] = rs * dtc
        lv1[1:, 1] = sx
        np.cumsum(lv1[1:], axis=0, out=lv1[1:])
        c, d = lv1[:, 0], lv1[:, 1]
        lv2 = np.zeros((n + 1, 3, 3, 3))
        sxc = sx @ c[:-1]
        lv2[1:, 0] = sxc
        lv2[1:, 1] = (d[:-1] + 0.5 * sx) * dtc             # 0.5 a dt^2 of the position
        lv2[1:, 2] = 0.5 * (c[:-1] + c[1:]) * dtc
        np.cumsum(lv2[1:], axis=0, out=lv2[1:])
        e, pd, pc = lv2[:, 0], lv2[:, 1], lv2[:, 2]
        t = np.zeros(n + 1)
        np.cumsum(dt, out=t[1:])
        rows = np.empty((n + 1, 9, N_ERR))
        rows[:] = _ROWS0
        rows[0, P_, BG] = 0.0
        np.cumsum((e[:-1] + 0.5 * sxc) * dtc, axis=0, out=rows[1:, P_, BG])
        rows[:, P_, V_] = t[:, None, None] * I3
        rows[:, P_, TH] = -pd
        rows[:, P_, BA] = -pc
        rows[:, V_, TH] = -d
        rows[:, V_, BG] = e
        rows[:, V_, BA] = -c
        rows[:, TH, BG] = -c
        return cls(t, rows)

    def phi(self, k: int = -1) -> F64:
        """Transition (15,15) from the block start to boundary k."""
        phi = I15.copy()
        phi[:9] = self.rows[k]
        return phi


def block_noise(phi: F64, q_diag: F64, t: float) -> F64:
    """Discrete process noise over a block of length t s: trapezoidal 0.5 (Phi Qc Phi^T + Qc) t.

    Exact for white noise when Phi is constant over the block; with isotropic IMU noise the
    rotation of the noise into the map frame drops out.
    """
    qc = np.diag(q_diag * t)
    q = 0.5 * (phi @ qc @ phi.T + qc)
    return 0.5 * (q + q.T)


def unicycle_transition(
    dx: F64, dy: F64, v: F64, dt: F64, yaw_mid: F64, sigma_v: float, sigma_w: float,
    guess: F64 | None = None,
) -> tuple[F64, F64]:
    """Block transition Phi (3,3) and discrete noise Q (3,3) of the planar unicycle.

    dx, dy (N,) displacements of each interval, v (N,) m/s, dt (N,) s, yaw_mid (N,) rad.
    Wheel noise per sample: sigma_v m/s on speed and sigma_w rad/s on yaw rate, each
    integrated over its interval and carried to the block end by the exact transition.
    `guess` (N,) s: how far each interval carries a held twist beyond the wheels' last
    sample (a dropout; `wheel_track.unseen_twist_variance` adds to its noise), None: none.
    """
    sx = dx.sum()
    sy = dy.sum()
    phi = np.array([[1.0, 0.0, -sy], [0.0, 1.0, sx], [0.0, 0.0, 1.0]])
    # Displacement still to go after interval k (for yaw noise entering at interval k).
    rest_x = sx - np.cumsum(dx)
    rest_y = sy - np.cumsum(dy)
    g_v = np.stack([dt * np.cos(yaw_mid), dt * np.sin(yaw_mid), np.zeros_like(dt)], axis=1)
    # A yaw-rate error over interval k rotates the half of interval k and everything after.
    g_w = np.stack(
        [-(rest_y + 0.5 * dy) * dt, (rest_x + 0.5 * dx) * dt, dt], axis=1
    )
    if guess is None or not np.any(guess > 0.0):
        q = sigma_v**2 * g_v.T @ g_v + sigma_w**2 * g_w.T @ g_w
        return phi, q
    add_v, add_w = unseen_twist_variance(guess)
    q = ((sigma_v**2 + add_v)[:, None] * g_v).T @ g_v + (
        (sigma_w**2 + add_w)[:, None] * g_w).T @ g_w
    return phi, q


def cap_variances(p: F64, caps: F64) -> None:
    """Scale the leading rows/columns of covariance p in place so that p_ii <= caps[i].

    Scaling row and column i by the same factor keeps p positive semi-definite.
    """
    n = len(caps)
    d = np.diagonal(p)[:n]
    if np.any(d > caps):
        f = np.sqrt(np.minimum(caps / np.maximum(d, 1e-300), 1.0))
        p[:n, :] *= f[:, None]
        p[:, :n] *= f[None, :]


def joseph_update(
    p: F64, h: F64, r: F64, y: F64
) -> tuple[F64, F64, F64, F64]:
    """Kalman update with the Joseph-form covariance (filterpy's `update` vocabulary).

    p (n,n) prior covariance, h (m,n) Jacobian, r (m,) independent measurement variances,
    y (m,) innovation. Returns the correction dx = K y (n,), the posterior covariance
    (I - K H) P (I - K H)^T + K R K^T, the innovation covariance S (m,m) and the gain K.
    """
    ph = p @ h.T
    s = h @ ph
    s.flat[:: len(r) + 1] += r
    k = np.linalg.solve(s, ph.T).T
    a = (I15 if p.shape[0] == 15 else np.eye(p.shape[0])) - k @ h
    p_new = a @ p @ a.T + (k * r) @ k.T
    return k @ y, 0.5 * (p_new + p_new.T), s, k


def pose_covariance(p: F64, index: tuple[int | None, ...]) -> F64:
    """(6,6) pose covariance in ROS order (x, y, z m, rotation about the map x, y, z rad)
    from a state covariance p: `index[k]` is the state index of pose component k, or None
    for a component the estimator does not estimate (variance `UNKNOWN_VARIANCE`, no
    correlation)."""
    out = np.zeros((6, 6))
    known = [k for k, i in enumerate(index) if i is not None]
    idx = [index[k] for k in known]
    out[np.ix_(known, known)] = p[np.ix_(idx, idx)]
    for k, i in enumerate(index):
        if i is None:
            out[k, k] = UNKNOWN_VARIANCE
    return out


def augment(p: F64, var: F64) -> F64:
    """Covariance p (n,n) extended by len(var) uncorrelated states of variances var."""
    n, m = len(p), len(var)
    out = np.zeros((n + m, n + m))
    out[:n, :n] = p
    out[n:, n:] = np.diag(var)
    return out


def pad_rows(h: F64, width: int) -> F64:
    """Jacobian rows h (k,n) extended with zero columns to (k, width)."""
    out = np.zeros((len(h), width))
    out[:, : h.shape[1]] = h
    return out


def propagate_with_biases(p: F64, n: int, phi: F64, q: F64, f: F64, qb: F64) -> F64:
    """Propagate a covariance whose first n states move with transition phi (n,n) and
    noise q (n,n) and whose remaining states are first-order Gauss-Markov (each multiplied
    by f (m,), plus independent noise of variances qb (m,))."""
    out = np.empty_like(p)
    out[:n, :n] = phi @ p[:n, :n] @ phi.T + q
    cross_ = (phi @ p[:n, n:]) * f
    out[:n, n:] = cross_
    out[n:, :n] = cross_.T
    out[n:, n:] = p[n:, n:] * np.outer(f, f)
    out[n:, n:] += np.diag(qb)
    return out
