# SPDX-License-Identifier: BSD-3-Clause
"""Wheel odometry: a planar dead-reckoning track and the between-keyframe factor.

Each wheel sample (v m/s, omega rad/s, base frame) is the mean velocity over the interval
that ends at its stamp; the track integrates those exactly as constant-velocity arcs, so
the relative motion between any two times (keyframes, range stamps) is one SE(2) composition.
The factor between two keyframes is a native `BetweenFactorPose3` whose 6x6 covariance is
propagated from the per-sample noise (sigma_v, sigma_omega, sigma_lateral times each piece's
duration) through the arc composition; z, roll and pitch get `planar` sigmas.
The wheel twist is already in the base frame, so the base extrinsics are the identity.
"""

from __future__ import annotations

import math

import gtsam
import numpy as np

from uwbfuse.config import RobustKernel
from uwbfuse.graph.noise import gaussian_covariances, robust_estimator
from uwbfuse.positioning.wheel_track import (  # noqa: F401 - re-exported for the graph
    FEW_QUERIES,
    WheelTrack,
    _arcs,
    se2_between,
    se2_compose,
)

_PLANAR_IX = (3, 4, 2)
# `wheel_scale_evidence` of fewer keyframe pairs (the online graph's, three an update) in
# Python floats: numpy sums fewer than 8 numbers in order, as `_wheel_scale_evidence_few`
# does (from 8 on pairwise)
FEW_EVIDENCE_PAIRS = 8  # where `planar_covariance6` puts (x, y, theta) in the Pose3 tangent


def se2_to_pose3(d: np.ndarray) -> gtsam.Pose3:
    """Planar (x, y, theta) as a Pose3 (z = 0, roll = pitch = 0)."""
    return gtsam.Pose3(gtsam.Rot3.Yaw(float(d[2])), np.array([d[0], d[1], 0.0]))


def planar_covariance6(
    cov_xyt: np.ndarray, out_of_plane_sigmas: tuple[float, float, float]
) -> np.ndarray:
    """Pose3 tangent covariance (rot, trans) of planar deltas with covariance `cov_xyt` in
    (x, y, theta), (3,3) or (n,3,3), and out-of-plane (roll rad, pitch rad, z m) sigmas:
    (6,6) or (n,6,6)."""
    c = np.asarray(cov_xyt, dtype=np.float64)
    one = c.ndim == 2
    c = c[None] if one else c
    cov6 = np.zeros((len(c), 6, 6))
    sr, sp, sz = out_of_plane_sigmas
    cov6[:, 0, 0], cov6[:, 1, 1], cov6[:, 5, 5] = sr**2, sp**2, sz**2
    ix = np.array([3, 4, 2])
    cov6[:, ix[:, None], ix[None, :]] = c
    # floor: a perfectly still vehicle still gets a tiny (1 mm, 1 mrad) uncertainty
    cov6 += np.diag([0, 0, 1e-6, 1e-6, 1e-6, 0])
    return cov6[0] if one else cov6


def planar_gaussian6(cov_xyt: np.ndarray,
                     out_of_plane_sigmas: tuple[float, float, float]) -> np.ndarray:
    """`gaussian_covariances(planar_covariance6(cov_xyt, out_of_plane_sigmas))` of one
    (3,3) covariance in (x, y, theta): the (6,6) Pose3 tangent covariance of a wheel
    factor, in Python floats: only the 12 entries that are not zero, each by the same
    operations as the array passes (their floor, their symmetrisation, their diagonal
    floor; `+ 0.0` where they add a zero, which turns -0.0 into 0.0). numpy's per-call
    cost was most of a keyframe's wheel factor, and a 36-entry pass in Python most of
    the rest."""
    c = np.asarray(cov_xyt, dtype=np.float64).tolist()
    sr, sp, sz = out_of_plane_sigmas
    out = [0.0] * 36
    for i, var in ((0, sr**2), (1, sp**2), (5, sz**2)):  # no floor there
        a = var + 0.0
        out[7 * i] = 0.5 * (a + a) + 1e-12
    for r, i in enumerate(_PLANAR_IX):
        for s, j in enumerate(_PLANAR_IX):
            if r == s:  # `planar_covariance6`'s 1e-6 floor on x, y and theta
                a = c[r][r] + 1e-6
                out[7 * i] = 0.5 * (a + a) + 1e-12
            else:
                out[6 * i + j] = 0.5 * ((c[r][s] + 0.0) + (c[s][r] + 0.0)) + 0.0
    return np.array(out, dtype=np.float64).reshape(6, 6)


def between_factors(
    key_a: list[int] | np.ndarray,
    key_b: list[int] | np.ndarray,
    delta: np.ndarray,
    cov_xyt: np.ndarray,
    out_of_plane_sigmas: tuple[float, float, float],
    robust_k: float | None = None,
) -> list[gtsam.BetweenFactorPose3]:
    """BetweenFactorPose3 key_a[i] -> key_b[i] for planar deltas (n,3) with covariances
    (n,3,3) in (x, y, theta).

    `out_of_plane_sigmas` are (roll rad, pitch rad, z m) sigmas of the same interval;
    `robust_k` (whitened units) wraps each Gaussian in a Huber kernel against wheel slip.
    Tangent order of Pose3 in GTSAM: (rx, ry, rz, tx, ty, tz). The covariances are built
    for all factors at once (batch rebuilds every wheel factor several times: per factor,
    numpy's call overhead was half of the construction); only the GTSAM objects are made
    one by one.
    """
    cov6 = gaussian_covariances(planar_covariance6(np.asarray(cov_xyt).reshape(-1, 3, 3),
                                                   out_of_plane_sigmas))
    # wheel slip: a disagreeing interval (IMU, ranges) loses weight instead of dragging the
    # trajectory (one stateless kernel shared by the factors)
    huber = None if robust_k is None else gtsam.noiseModel.mEstimator.Huber.Create(robust_k)
    return [_between(ka, kb, d, c, huber)
            for ka, kb, d, c in zip(np.asarray(key_a).tolist(), np.asarray(key_b).tolist(),
                                    np.asarray(delta).reshape(-1, 3), cov6, strict=True)]


def _between(key_a: int, key_b: int, delta: np.ndarray, cov6: np.ndarray,
             huber: gtsam.noiseModel.mEstimator.Base | None) -> gtsam.BetweenFactorPose3:
    """The native factor of `between_factors` from a planar delta (3,) and its ready 6x6
    covariance."""
    noise = gtsam.noiseModel.Gaussian.Covariance(cov6)
    if huber is not None:
        noise = gtsam.noiseModel.Robust.Create(huber, noise)
    return gtsam.BetweenFactorPose3(key_a, key_b, se2_to_pose3(delta), noise)


def between_factor(
    key_a: int,
    key_b: int,
    delta: np.ndarray,
    cov_xyt: np.ndarray,
    out_of_plane_sigmas: tuple[float, float, float],
    robust_k: float | None = None,
) -> gtsam.BetweenFactorPose3:
    """One `between_factors` factor (a planar delta (3,) with covariance (3,3)), without
    its array passes (one per keyframe online; the same numbers)."""
    huber = None if robust_k is None else robust_estimator(RobustKernel.HUBER, robust_k)
    cov6 = planar_gaussian6(cov_xyt, out_of_plane_sigmas)
    return _between(key_a, key_b, np.asarray(delta).reshape(3), cov6, huber)


def wheel_scale_evidence(
    rot_a: np.ndarray, trans_a: np.ndarray, rot_b: np.ndarray, trans_b: np.ndarray,
    delta: np.ndarray, cov: np.ndarray, scale: np.ndarray, huber_k: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares evidence of the odometry's (v, omega) scale factors from wheel deltas
    against the same motion of an estimated track: keyframe pairs (a, b) with map-frame
    rotations (n,3,3) and translations (n,3) m, the integrated (scale 1) planar deltas
    (n,3) (x m, y m, theta rad, base frame at a) and their (n,3,3) covariances. Returns
    (numerator (2,), denominator (2,)): the weighted scale is num / den, each row weighed by
    its inverse variance and a Huber weight (threshold `huber_k` sigmas) of its residual at
    `scale` (against wheel slip). Batch's refit and the online estimate share it."""
    if len(delta) < FEW_EVIDENCE_PAIRS:
        return _wheel_scale_evidence_few(rot_a, trans_a, rot_b, trans_b, delta, cov, scale,
                                         huber_k)
    return _wheel_scale_evidence_arrays(rot_a, trans_a, rot_b, trans_b, delta, cov, scale,
                                        huber_k)


def _wheel_scale_evidence_arrays(
    rot_a: np.ndarray, trans_a: np.ndarray, rot_b: np.ndarray, trans_b: np.ndarray,
    delta: np.ndarray, cov: np.ndarray, scale: np.ndarray, huber_k: float,
) -> tuple[np.ndarray, np.ndarray]:
    """`wheel_scale_evidence` vectorised over the pairs."""
    t_rel = np.einsum("nji,nj->ni", rot_a, trans_b - trans_a)[:, :2]
    r_rel = np.einsum("nji,njk->nik", rot_a, rot_b)
    th_e = np.arctan2(r_rel[:, 1, 0], r_rel[:, 0, 0])
    var_t = 0.5 * (cov[:, 0, 0] + cov[:, 1, 1]) + 1e-6
    var_th = cov[:, 2, 2] + 1e-6
    num, den = np.zeros(2), np.zeros(2)
    for j, (est, raw, var) in enumerate((
            (t_rel, delta[:, :2], var_t), (th_e[:, None], delta[:, 2:3], var_th))):
        res = np.linalg.norm(est - scale[j] * raw, axis=1) / np.sqrt(var)
        w = np.minimum(1.0, huber_k / np.maximum(res, 1e-12)) / var
        num[j] = float(np.sum(w * np.sum(est * raw, axis=1)))
        den[j] = float(np.sum(w * np.sum(raw * raw, axis=1)))
    return num, den


def _wheel_scale_evidence_few(
    rot_a: np.ndarray, trans_a: np.ndarray, rot_b: np.ndarray, trans_b: np.ndarray,
    delta: np.ndarray, cov: np.ndarray, scale: np.ndarray, huber_k: float,
) -> tuple[np.ndarray, np.ndarray]:
    """`wheel_scale_evidence` of fewer than FEW_EVIDENCE_PAIRS pairs in Python floats,
    operation for operation (einsum's sums in index order, numpy's minimum and maximum
    with their NaN; bit-identical, tests/test_wheel_track.py): numpy's per-call cost was
    ~4x the arithmetic for the online graph's three pairs an update."""
    n = len(delta)
    if n == 0:
        return np.zeros(2), np.zeros(2)
    ra, rb = np.asarray(rot_a).tolist(), np.asarray(rot_b).tolist()
    ta, tb = np.asarray(trans_a).tolist(), np.asarray(trans_b).tolist()
    dl, cv = np.asarray(delta).tolist(), np.asarray(cov).tolist()
    # the heading from the relative rotation's first column, through numpy's arctan2 on
    # the same strided (n,) views as the vectorised form (its SIMD path rounds its own)
    r_rel = np.zeros((n, 3, 3))
    t_rel = []
    for i in range(n):
        (a00, a01, _), (a10, a11, _), (a20, a21, _) = ra[i]
        b0, b1, b2 = rb[i][0][0], rb[i][1][0], rb[i][2][0]
        r_rel[i, 0, 0] = a00 * b0 + a10 * b1 + a20 * b2
        r_rel[i, 1, 0] = a01 * b0 + a11 * b1 + a21 * b2
        d0, d1, d2 = tb[i][0] - ta[i][0], tb[i][1] - ta[i][1], tb[i][2] - ta[i][2]
        t_rel.append((a00 * d0 + a10 * d1 + a20 * d2, a01 * d0 + a11 * d1 + a21 * d2))
    th_e = np.arctan2(r_rel[:, 1, 0], r_rel[:, 0, 0]).tolist()
    num, den = np.zeros(2), np.zeros(2)
    s_t, s_th = float(scale[0]), float(scale[1])
    w_t, w_th, ee_t, ee_th, rr_t, rr_th = [], [], [], [], [], []
    for i in range(n):
        c = cv[i]
        var_t = 0.5 * (c[0][0] + c[1][1]) + 1e-6
        var_th = c[2][2] + 1e-6
        (e0, e1), (x0, x1, x2), e2 = t_rel[i], dl[i], th_e[i]
        u0, u1 = e0 - s_t * x0, e1 - s_t * x1
        u2 = e2 - s_th * x2
        for res, var, w_out in ((math.sqrt(u0 * u0 + u1 * u1) / math.sqrt(var_t), var_t, w_t),
                                (math.sqrt(u2 * u2) / math.sqrt(var_th), var_th, w_th)):
            m = res if not res < 1e-12 else 1e-12  # np.maximum (NaN kept)
            h = huber_k / m
            w_out.append((1.0 if h > 1.0 else h) / var)  # np.minimum (NaN kept)
        ee_t.append(e0 * x0 + e1 * x1)
        rr_t.append(x0 * x0 + x1 * x1)
        ee_th.append(e2 * x2)
        rr_th.append(x2 * x2)
    for j, (w, ee, rr) in enumerate(((w_t, ee_t, rr_t), (w_th, ee_th, rr_th))):
        sn, sd = w[0] * ee[0], w[0] * rr[0]  # numpy's sum of fewer than 8: in order
        for i in range(1, n):
            sn += w[i] * ee[i]
            sd += w[i] * rr[i]
        num[j], den[j] = sn, sd
    return num, den
