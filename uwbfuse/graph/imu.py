# SPDX-License-Identifier: BSD-3-Clause
"""IMU preintegration: the parameter factory and block integration between keyframes.

Units from `ImuConfig`: noise densities are continuous-time (accelerometer m/s^2/sqrt(Hz),
gyroscope rad/s/sqrt(Hz)); GTSAM takes their squares as covariances and discretises with
each sample's dt. Bias random walks likewise (m/s^3/sqrt(Hz), rad/s^2/sqrt(Hz)).
The body frame of the factors is the base frame; `imu_in_base` is GTSAM's body_P_sensor.
"""

from __future__ import annotations

import bisect
from collections.abc import Callable
from dataclasses import dataclass, field

import gtsam
import numpy as np

from uwbfuse.config import Extrinsics, ImuConfig
from uwbfuse.constants import MAX_EXTRAPOLATION_S, VIRTUAL_BIAS_RANDOM_WALK
from uwbfuse.streams import NS_PER_S


def pose_from_xyzq(xyzq: tuple[float, ...] | np.ndarray) -> gtsam.Pose3:
    """Pose3 from x y z (m) qx qy qz qw."""
    x, y, z, qx, qy, qz, qw = (float(c) for c in xyzq)
    return gtsam.Pose3(gtsam.Rot3.Quaternion(qw, qx, qy, qz), np.array([x, y, z]))


def preintegration_params(
    cfg: ImuConfig, ext: Extrinsics, inflation: float = 1.0,
    gyro_inflation: float | None = None,
) -> gtsam.PreintegrationCombinedParams:
    """PreintegrationCombinedParams from config (gravity along -z of the map frame).

    `inflation` multiplies the noise densities and bias random walks (standard deviations);
    `gyro_inflation`, when given, the gyroscope's white noise density instead.
    """
    p = gtsam.PreintegrationCombinedParams.MakeSharedU(cfg.gravity)
    i3 = np.eye(3)
    f2 = inflation**2
    g2 = f2 if gyro_inflation is None else gyro_inflation**2
    p.setAccelerometerCovariance(i3 * cfg.accel_noise_density**2 * f2)
    p.setGyroscopeCovariance(i3 * cfg.gyro_noise_density**2 * g2)
    # 1e-6 (m/s)^2 s: below ~1e-7 the 0.1 s factors become too ill-conditioned for Cholesky
    p.setIntegrationCovariance(i3 * 1e-6)
    p.setBiasAccCovariance(i3 * cfg.accel_bias_random_walk**2 * f2)
    p.setBiasOmegaCovariance(i3 * cfg.gyro_bias_random_walk**2 * f2)
    body_p_imu = pose_from_xyzq(ext.imu_in_base)
    if not body_p_imu.equals(gtsam.Pose3(), 1e-12):
        p.setBodyPSensor(body_p_imu)
    return p




def motion_prior_params(
    accel_density: float, turn_density: float, gravity: float
) -> gtsam.PreintegrationCombinedParams:
    """Constant-velocity (white-noise acceleration) motion prior as preintegration params.

    For a log with neither IMU nor wheels: a virtual IMU that always reads "no acceleration,
    no turn" (specific force +g on z, zero rate) whose noise densities are the motion's own
    acceleration (m/s^2/sqrt(Hz)) and turn rate (rad/s/sqrt(Hz)) spectral densities, so a
    `CombinedImuFactor` between keyframes is GTSAM's native white-noise-acceleration prior
    on position and velocity.
    """
    p = gtsam.PreintegrationCombinedParams.MakeSharedU(gravity)
    i3 = np.eye(3)
    p.setAccelerometerCovariance(i3 * accel_density**2)
    p.setGyroscopeCovariance(i3 * turn_density**2)
    p.setIntegrationCovariance(i3 * 1e-6)
    p.setBiasAccCovariance(i3 * VIRTUAL_BIAS_RANDOM_WALK**2)
    p.setBiasOmegaCovariance(i3 * VIRTUAL_BIAS_RANDOM_WALK**2)
    return p


def rest_reading(params: gtsam.PreintegrationCombinedParams, attitude: gtsam.Rot3,
                 bias: gtsam.imuBias.ConstantBias) -> tuple[np.ndarray, np.ndarray]:
    """What the IMU of `params` reads (gyro rad/s, specific force m/s^2, IMU frame) on a base
    at `attitude` (map frame) that neither turns nor accelerates, with `bias`: the guess
    held through an IMU dropout (`ImuBuffer.pieces`)."""
    f_base = attitude.unrotate(-np.asarray(params.n_gravity, np.float64))
    body_p_imu = params.getBodyPSensor()
    f_imu = body_p_imu.rotation().unrotate(f_base) if body_p_imu is not None else f_base
    return (np.asarray(bias.gyroscope(), np.float64),
            np.asarray(f_imu, np.float64) + np.asarray(bias.accelerometer(), np.float64))


def guess_covariance(
    params: gtsam.PreintegrationCombinedParams, bias: gtsam.imuBias.ConstantBias,
    pieces: tuple[np.ndarray, np.ndarray, np.ndarray], guess_s: float,
    accel_density: float, turn_density: float,
) -> np.ndarray:
    """(15,15) covariance the dropout's guess adds to an IMU factor whose `pieces` hold the
    rest reading for `guess_s` seconds (`ImuBuffer.pieces_with_guess`): the motion the guess cannot
    see, as the constant-velocity prior's white-noise acceleration `accel_density`
    (m/s^2/sqrt(Hz)) and yaw rate `turn_density` (rad/s/sqrt(Hz), about the base's
    vertical; the guess's level attitude is the IMU's own), spread over the factor's pieces
    at the guess's share of its time. `params`: the factor's preintegration parameters
    (their body_P_sensor)."""
    gy, ac, dt = pieces
    share = min(guess_s / max(float(np.sum(dt)), 1e-9), 1.0)
    g = gtsam.PreintegrationCombinedParams(params.n_gravity)
    body_p_imu = params.getBodyPSensor()
    r_bs = (body_p_imu.rotation().matrix() if body_p_imu is not None else np.eye(3))
    up = r_bs.T @ np.array([0.0, 0.0, 1.0])  # the base's vertical in the IMU frame
    g.setAccelerometerCovariance(np.eye(3) * accel_density**2 * share)
    g.setGyroscopeCovariance(np.outer(up, up) * turn_density**2 * share)
    g.setIntegrationCovariance(np.zeros((3, 3)))
    g.setBiasAccCovariance(np.zeros((3, 3)))
    g.setBiasOmegaCovariance(np.zeros((3, 3)))
    if body_p_imu is not None:
        g.setBodyPSensor(body_p_imu)
    return np.asarray(preintegrate(g, bias, gy, ac, dt).preintMeasCov(), np.float64)


def bias_prior_sigmas(cfg: ImuConfig) -> np.ndarray:
    """Sigmas of an IMU-bias prior: accelerometer (m/s^2) then gyroscope (rad/s)."""
    return np.array([cfg.accel_bias_sigma] * 3 + [cfg.gyro_bias_sigma] * 3)


class ImuBuffer:
    """IMU samples kept as growing numpy arrays; integrates time blocks into a PIM.

    Each sample is held constant from its stamp to the next one (zero-order hold); a
    block [t0, t1] integrates the pieces of the samples that cover it.
    """

    def __init__(self) -> None:
        self._t = np.zeros(0, dtype=np.int64)
        self._gyro = np.zeros((0, 3))
        self._acc = np.zeros((0, 3))
        self._chunks: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []

    def add(self, t_ns: np.ndarray, gyro: np.ndarray, accel: np.ndarray) -> None:
        """Append a time-sorted batch: stamps ns, gyro rad/s, specific force m/s^2."""
        self._chunks.append((np.asarray(t_ns, np.int64), np.asarray(gyro, float),
                             np.asarray(accel, float)))

    def _flush(self) -> None:
        if self._chunks:
            ts, gs, accs = zip(*self._chunks, strict=True)
            self._t = np.concatenate([self._t, *ts])
            self._gyro = np.concatenate([self._gyro, *gs])
            self._acc = np.concatenate([self._acc, *accs])
            self._chunks.clear()

    def __len__(self) -> int:
        self._flush()
        return len(self._t)

    @property
    def first_t(self) -> int | None:
        """Stamp (ns) of the oldest sample kept, None when empty."""
        self._flush()
        return int(self._t[0]) if len(self._t) else None

    @property
    def last_t(self) -> int | None:
        self._flush()
        return int(self._t[-1]) if len(self._t) else None

    def drop_before(self, t_ns: int) -> None:
        """Forget samples no longer needed for blocks starting at or after `t_ns`."""
        self._flush()
        i = int(np.searchsorted(self._t, t_ns, side="right")) - 1
        if i > 1000:
            self._t, self._gyro, self._acc = self._t[i:], self._gyro[i:], self._acc[i:]

    def pieces(
        self, t0: int, t1: int, rest: Callable[[], tuple[np.ndarray, np.ndarray]],
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Zero-order-hold pieces covering [t0, t1]: gyro (n,3), accel (n,3), dt (n,) s.

        A sample is held for at most MAX_EXTRAPOLATION_S; beyond that (an IMU dropout) the
        pieces hold `rest()` (gyro rad/s, specific force m/s^2, IMU frame: what the IMU
        would read with no turn and no acceleration, `rest_reading`; called only then)
        instead of the sample's instantaneous turn rate and acceleration, which held for
        seconds spin the attitude and run away."""
        return self.pieces_with_guess(t0, t1, rest)[:3]

    def pieces_with_guess(
        self, t0: int, t1: int, rest: Callable[[], tuple[np.ndarray, np.ndarray]],
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
        """`pieces` and the seconds of [t0, t1] they fill with the dropout's guess (0:
        none), from one pass over the samples."""
        cover = self._cover(t0, t1)
        if cover is None:
            return np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0), 0.0
        idx, _ts, starts, ends, held, cut = cover
        guess_s = 0.0
        gyro, acc = self._gyro[idx], self._acc[idx]
        if held.any():  # a dropout: split each long hold into the sample, then the guess
            guess_s = float(np.sum(ends[held] - cut[held])) / NS_PER_S
            starts = np.concatenate([starts, cut[held]])
            ends = np.concatenate([np.where(held, cut, ends), ends[held]])
            n = int(np.sum(held))
            g_rest, a_rest = rest()
            gyro = np.concatenate([gyro, np.tile(np.asarray(g_rest, np.float64), (n, 1))])
            acc = np.concatenate([acc, np.tile(np.asarray(a_rest, np.float64), (n, 1))])
            order = np.argsort(starts, kind="stable")
            starts, ends, gyro, acc = starts[order], ends[order], gyro[order], acc[order]
        dt = (ends - starts).astype(np.float64) / NS_PER_S
        keep = dt > 0
        return gyro[keep], acc[keep], dt[keep], guess_s

    def _cover(self, t0: int, t1: int) -> tuple[slice, np.ndarray, np.ndarray, np.ndarray,
                                                 np.ndarray, np.ndarray] | None:
        """The samples covering [t0, t1] (a slice), their stamps, the start and end (ns) of
        each one's hold inside [t0, t1], which holds run past MAX_EXTRAPOLATION_S (a
        dropout) and where each such hold turns into the guess; None without samples."""
        self._flush()
        t = self._t
        if len(t) == 0 or t1 <= t0:
            return None
        i0 = max(int(np.searchsorted(t, t0, side="right")) - 1, 0)
        i1 = int(np.searchsorted(t, t1, side="left"))
        idx = slice(i0, max(i1, i0 + 1))  # the samples covering [t0, t1] (views)
        ts = t[idx]
        starts = np.maximum(ts, t0)
        ends = np.empty_like(starts)
        ends[:-1] = ts[1:]
        ends[-1] = t1
        ends = np.minimum(ends, t1)
        hold_ns = round(MAX_EXTRAPOLATION_S * NS_PER_S)
        held = ends - ts > hold_ns
        cut = np.maximum(np.minimum(ts + hold_ns, ends), starts)
        return idx, ts, starts, ends, held, cut

    def rotation_between(self, t0: int, t1: int, gyro_bias: np.ndarray,
                         body_r_imu: np.ndarray) -> np.ndarray:
        """Base-frame attitude change (3,3) from t0 to t1 (R_t0^T R_t1): the gyro (rad/s,
        IMU frame, less `gyro_bias`) integrated over the zero-order-hold pieces, turned into
        the base frame by `body_r_imu` (3,3)."""
        bg = np.asarray(gyro_bias, np.float64)
        gy, _acc, dt = self.pieces(t0, t1, lambda: (bg, np.zeros(3)))  # a dropout: no turn
        rot = gtsam.Rot3()
        for w, d in zip(gy, dt.tolist(), strict=True):
            rot = rot.compose(gtsam.Rot3.Expmap((w - bg) * d))
        r_bs = np.asarray(body_r_imu, np.float64)
        return r_bs @ rot.matrix() @ r_bs.T

    def mean_between(self, t0: int, t1: int) -> tuple[np.ndarray, np.ndarray, int]:
        """Mean gyro (rad/s), mean accel (m/s^2) and sample count over [t0, t1]."""
        self._flush()
        i0 = int(np.searchsorted(self._t, t0, side="left"))
        i1 = int(np.searchsorted(self._t, t1, side="right"))
        if i1 <= i0:
            return np.zeros(3), np.zeros(3), 0
        return self._gyro[i0:i1].mean(0), self._acc[i0:i1].mean(0), i1 - i0


def integrate(
    pim: gtsam.PreintegratedCombinedMeasurements | gtsam.PreintegratedImuMeasurements,
    gyro: np.ndarray,
    accel: np.ndarray,
    dt: np.ndarray,
) -> None:
    """Integrate zero-order-hold pieces into `pim` (one native call per piece)."""
    f = pim.integrateMeasurement
    for a, w, d in zip(accel, gyro, dt.tolist(), strict=True):
        f(a, w, d)


def preintegrate(
    params: gtsam.PreintegrationCombinedParams, bias: gtsam.imuBias.ConstantBias,
    gyro: np.ndarray, accel: np.ndarray, dt: np.ndarray,
) -> gtsam.PreintegratedCombinedMeasurements:
    """The zero-order-hold pieces (gyro rad/s, accel m/s^2, dt s) preintegrated from
    `bias` (the factor's linearisation point)."""
    pim = gtsam.PreintegratedCombinedMeasurements(params, bias)
    integrate(pim, gyro, accel, dt)
    return pim




@dataclass
class ImuRecords:
    """IMU factors of a graph, so that they can be rebuilt at another noise inflation: the
    first keyframe k of each (the factor joins k and k + 1), its index in the graph, the
    bias it was preintegrated from and its zero-order-hold pieces.

    The preintegrated covariance is linear in the noise covariances it propagates: at an
    inflation f of the densities and random walks it is f^2 N + I, N the part of the
    configured noise and I the fixed integration covariance's (`covariance_parts`), so a
    factor at any f is the recorded one with that covariance (`factors_at`), not a new
    preintegration."""

    k: list[int] = field(default_factory=list)
    index: list[int] = field(default_factory=list)
    bias: list[gtsam.imuBias.ConstantBias] = field(default_factory=list)
    pieces: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = field(default_factory=list)
    # (N, I) of each factor by its k, computed on demand (shared by `reindexed` copies)
    parts: dict[int, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)
    # the preintegration parameters at a noise factor f, where the factors are not a real
    # IMU's: the constant-velocity prior's virtual IMU (`GraphBuilder`); None: the
    # configured IMU's (`preintegration_params`)
    params_at: Callable[[float], gtsam.PreintegrationCombinedParams] | None = None
    # the covariance (15,15) an IMU dropout's guess adds to each factor (`guess_covariance`;
    # None: a factor of measured samples), at every inflation
    guess: list[np.ndarray | None] = field(default_factory=list)

    def add(self, k: int, index: int, bias: gtsam.imuBias.ConstantBias, gyro: np.ndarray,
            accel: np.ndarray, dt: np.ndarray, guess: np.ndarray | None = None) -> None:
        self.k.append(k)
        self.index.append(index)
        self.bias.append(bias)
        self.pieces.append((gyro, accel, dt))
        self.guess.append(guess)

    def drop_before(self, k: int) -> None:
        """Forget the factors whose first keyframe is before `k`."""
        n = bisect.bisect_left(self.k, k)  # `k` is ascending (np.searchsorted's left side)
        for kk in self.k[:n]:
            self.parts.pop(kk, None)
        del self.k[:n], self.index[:n], self.bias[:n], self.pieces[:n], self.guess[:n]

    def reindexed(self, index: list[int]) -> ImuRecords:
        """The same factors at other indices (of another graph), sharing `parts`."""
        return ImuRecords(list(self.k), list(index), list(self.bias), list(self.pieces),
                          self.parts, self.params_at, list(self.guess))

    def selected(self, sel: list[int]) -> ImuRecords:
        """The factors at positions `sel` of these records (sharing `parts`)."""
        return ImuRecords([self.k[i] for i in sel], [self.index[i] for i in sel],
                          [self.bias[i] for i in sel], [self.pieces[i] for i in sel],
                          self.parts, self.params_at, [self.guess[i] for i in sel])

    def covariance_parts(self, cfg: ImuConfig, ext: Extrinsics) -> tuple[np.ndarray, np.ndarray]:
        """(N, I), each (n,15,15): the preintegrated covariance of every factor per unit
        f^2 of the configured noise, and that of the integration covariance alone plus a
        dropout's guess (`guess`; two preintegrations of each factor, at f = 1 and 2, once)."""
        if self.params_at is not None:
            one, two = self.params_at(1.0), self.params_at(2.0)
        else:
            one, two = preintegration_params(cfg, ext, 1.0), preintegration_params(cfg, ext, 2.0)
        for k, b, (gy, ac, dt), g in zip(self.k, self.bias, self.pieces, self.guess,
                                         strict=True):
            if k not in self.parts:
                c1 = preintegrate(one, b, gy, ac, dt).preintMeasCov()
                n = (preintegrate(two, b, gy, ac, dt).preintMeasCov() - c1) / 3.0
                self.parts[k] = (n, c1 - n if g is None else c1 - n + g)
        if not self.k:
            return np.zeros((0, 15, 15)), np.zeros((0, 15, 15))
        return (np.array([self.parts[k][0] for k in self.k]),
                np.array([self.parts[k][1] for k in self.k]))

    def covariances(self, cfg: ImuConfig, ext: Extrinsics, inflation: float) -> np.ndarray:
        """The factors' preintegrated covariances (n,15,15) at `inflation`."""
        n, i = self.covariance_parts(cfg, ext)
        return inflation**2 * n + i

    def factors_at(self, graph: gtsam.NonlinearFactorGraph, cov: np.ndarray
                   ) -> list[gtsam.NonlinearFactor]:
        """The factors (read from `graph` at their indices) with covariances `cov`."""
        return [graph.at(idx).cloneWithNewNoiseModel(gtsam.noiseModel.Gaussian.Covariance(c))
                for idx, c in zip(self.index, cov, strict=True)]
