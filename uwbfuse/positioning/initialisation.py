# SPDX-License-Identifier: BSD-3-Clause
"""The initial state from the sensors alone: no ground truth, no given pose.

`Initialiser` is fed the same batches as an estimator and answers `try_initialise(t_ns)`
with an `InitialState` at t_ns once the data determine one, else None.

Steps:

1. Standstill at the start (IMU gyro norm and accel std, wheel speed, per `[init]`;
   without wheels the UWB fixes must not have moved either):
   gravity direction gives roll/pitch, the mean gyro gives the gyro bias, the ranges of
   the still period give a static robust multilateration fix. Without a still start,
   roll/pitch come from the mean specific force over the first `level_window` seconds.
2. Heading: once the UWB track has moved `min_displacement`, a small robust nonlinear
   least squares (`robust_lm`: Levenberg-Marquardt with soft-L1 IRLS weights) on the raw
   ranges of the motion window solves the start pose: unknowns p0 (base origin, map
   frame), yaw0, per-anchor range biases, for wheeled logs a common range scale (radios
   that read a few percent long: metres at the Plaza sites' tens of metres), weak height
   priors, and for an IMU-only track
   the start velocity (unless it starts at rest) and first-order corrections of the
   accelerometer bias, gyro bias and (no still start) level tilt. The
   vehicle's relative track comes from dead reckoning (wheels, with the IMU yaw rate when
   there is one; else IMU strapdown with the standstill bias), so the tag is at
   p0 + Rz(yaw0) (d(t) + R'(t) tag_in_base). Eight yaw seeds avoid local minima; the
   solution is accepted when the heading std and the residuals are consistent (robust
   spread within 3 range sigmas or 3 % of the median range, whichever is larger: large
   sites) and no other minimum comes close. This model (`StartProblem`), its solve from
   the seeds (`solve_seeds`) and its acceptance rule (`best_minimum`) are the start's only
   ones: `positioning/start.py` places the wheel track with them for round-robin ranges
   (one common offset, the height held), where there are no fixes to seed from.
3. UWB only: position from the fixes; heading is the UWB track direction once moving
   (or unknown, yaw_sigma = pi, after `heading_timeout` seconds without motion).

The returned state refers to the latest `t_ns` given (propagated with the dead-reckoned
track) so a streaming estimator can start from it at once. `provisional(t_ns)` gives a
best-effort state (heading possibly unknown, yaw_sigma = pi) for the time before that.
Reported stds are 2x the least-squares ones (time-correlated range errors).

Frames: map = anchor frame (z up); base per REP-103; yaw-zero frame W' = level frame whose
yaw is 0 at the start of dead reckoning.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from uwbfuse.config import Config
from uwbfuse.constants import RANGE_SCALE_MIN_EFFECT_M, RANGE_SCALE_MIN_ERROR
from uwbfuse.positioning.multilateration import (
    default_tag_z,
    epoch_window_ns,
    epochs_by_window,
    group_epochs,
    multilaterate,
)
from uwbfuse.positioning.wheel_track import arc_steps
from uwbfuse.streams import NS_PER_S, AnchorMap

log = logging.getLogger(__name__)

F64 = NDArray[np.float64]

BLOCK_S = 0.1  # standstill test block length, s
_RETRY_S = 0.5  # data time between two heading solves, s
_N_SEEDS = 8
_GYRO_BIAS_MAX = 0.1  # largest gyro turn-on bias a standstill may show, rad/s
_MIN_STILL_IMU_SAMPLES = 20  # IMU samples in the standstill to take biases from it
SOFT_L1_SIGMAS = 2.0  # soft-L1 scale of the heading solve, in range sigmas
_MAX_RANGES = 480  # ranges used by one heading solve (evenly thinned beyond)
_IMU_WINDOW_S = 8.0  # longest window of an IMU-only (strapdown) track, s
_TILT_SIGMA = 0.05  # prior std of the level error without a still start, rad
_V0_SIGMA = 5.0  # prior std of an unknown start velocity, m/s
_Z_SIGMA_PLANAR = 0.5  # prior std of a wheeled base's height about init.base_height, m
_Z_SIGMA_FREE = 1.5  # prior std of a free tag's start height about default_tag_z, m
_PROVISIONAL_S = 0.5  # span of recent fixes for a provisional position, s
_UWB_TRACK_S = 2.0  # UWB only: span of recent fixes fitted for position and track, s
# UWB only: fewest fixes in that fit (position and velocity in 2-D: 4 unknowns, one spare);
# a slow round robin (4 anchors at 1 Hz each) gives one fix per cycle, so the fit then
# reaches back over the last this many fixes instead of the span
_UWB_TRACK_MIN_FIXES = 5
_SCALE_SIGMA = 0.1  # prior std of the common range scale error (radio clock, calibration)
_MAX_MAD_REL = 0.03  # consistency: robust residual spread allowed, fraction of median range
RIVAL_MARGIN = 9.0  # chi-square by which the best start solution must beat a rival yaw (3 sigma)
RIVAL_SEPARATION = math.radians(20.0)  # rad: yaw minima closer than this are one basin


def applied_lever(tag_in_base: Sequence[float], streams: frozenset[str]) -> F64:
    """The tag antenna's lever arm (m, base frame) the start and the graph apply: all of
    `tag_in_base` where a sensor tells the heading (IMU, wheels or external poses); without
    one its height only. The horizontal part would turn with a heading nothing measures
    (the ranges see it only through the lever itself), and the base's best estimate is then
    the tag's own position, the lever's mean over an unknown heading."""
    lever = np.asarray(tag_in_base, dtype=np.float64).copy()
    if not streams & {"imu", "wheel", "pose"}:
        lever[:2] = 0.0
    return lever


def range_scale_applies(k: float, anchors: AnchorMap, position: np.ndarray) -> bool:
    """Whether a start solve's common range scale error k (ranges read (1 + k) x the
    distance) is the radios' and not the solve's noise: beyond RANGE_SCALE_MIN_ERROR and
    moving the ranges at `position` (map frame, m) by RANGE_SCALE_MIN_EFFECT_M."""
    if abs(k) <= RANGE_SCALE_MIN_ERROR:
        return False
    d = np.linalg.norm(anchors.positions - np.asarray(position, np.float64)[None, :], axis=1)
    return abs(k) * float(np.median(d)) > RANGE_SCALE_MIN_EFFECT_M


@dataclass(frozen=True)
class InitialState:
    """Initial state of the base frame, from sensors only.

    t_ns: time the state refers to (ns); position (3,) base origin in the map frame, m;
    R_map_base (3,3) attitude (roll/pitch from gravity, yaw solved); velocity (3,) map
    frame, m/s; gyro_bias (3,) IMU frame, rad/s; accel_bias (3,) IMU frame, m/s^2;
    position_sigma (m) and yaw_sigma (rad) 1-sigma uncertainties (yaw_sigma = pi: heading
    unknown); still: the log started with a detected standstill; range_scale: common
    scale of the ranges found by the start solve (ranges read range_scale x the distance;
    1.0 where not solved), for estimators that want to correct radios that read long;
    range_sigma: robust spread (MAD) of the start solve's range residuals, m, never below
    `uwb.sigma` (0 where not solved): the range noise the site actually shows;
    range_scale_sigma: 1-sigma of range_scale (relative) as the start solve determined it
    (its least-squares std; inf where it did not solve a scale).
    """

    t_ns: int
    position: np.ndarray
    R_map_base: np.ndarray
    velocity: np.ndarray
    gyro_bias: np.ndarray
    accel_bias: np.ndarray
    position_sigma: float
    yaw_sigma: float
    still: bool
    range_scale: float = 1.0
    range_sigma: float = 0.0
    range_scale_sigma: float = math.inf

    @property
    def yaw(self) -> float:
        """Heading of the base x axis in the map frame, rad."""
        return float(math.atan2(self.R_map_base[1, 0], self.R_map_base[0, 0]))

    @property
    def quat_xyzw(self) -> np.ndarray:
        """Attitude as a quaternion (x, y, z, w)."""
        return Rotation.from_matrix(self.R_map_base).as_quat()


def rot_z(yaw: float | F64) -> F64:
    """Rotation(s) about z by yaw (rad): (3,3) or (N,3,3)."""
    c, s = np.cos(yaw), np.sin(yaw)
    z, o = np.zeros_like(c), np.ones_like(c)
    return np.moveaxis(np.array([[c, -s, z], [s, c, z], [z, z, o]]), (0, 1), (-2, -1))


def level_from_accel(f_base: F64) -> F64:
    """R_map_base with yaw 0 from the mean specific force in the base frame (m/s^2)."""
    fx, fy, fz = f_base
    roll = math.atan2(fy, fz)
    pitch = math.atan2(-fx, math.hypot(fy, fz))
    return Rotation.from_euler("ZYX", [0.0, pitch, roll]).as_matrix()


def integrate_gyro(r0: F64, t_s: F64, gyro_base: F64) -> F64:
    """Attitudes (N,3,3) from r0 at t_s[0] by integrating body rates (N,3) rad/s.

    Sample k's rate applies over (t_{k-1}, t_k]; the first sample keeps r0.
    """
    dt = np.diff(t_s, prepend=t_s[0])
    inc = Rotation.from_rotvec(gyro_base * dt[:, None]).as_matrix()
    out = np.empty((len(t_s), 3, 3))
    r = np.array(r0, dtype=np.float64)
    for k in range(len(t_s)):
        r = r @ inc[k]
        out[k] = r
    return out


def block_still(
    t: F64, x: F64, block_end: F64, thr_norm: float | None, thr_std: float | None
) -> NDArray[np.bool_]:
    """Per block (ending at block_end, length BLOCK_S): max norm < thr and std < thr.

    Vectorised with cumulative sums; empty blocks count as still.
    """
    idx = np.searchsorted(t, block_end, side="right")
    start = np.concatenate([[0], idx[:-1]])
    cnt = idx - start
    still = np.ones(len(block_end), dtype=bool)
    if thr_norm is not None:
        big = (np.linalg.norm(x, axis=1) >= thr_norm).astype(np.int64)
        cb = np.concatenate([[0], np.cumsum(big)])
        still &= (cb[idx] - cb[start]) == 0
    if thr_std is not None:
        c1 = np.vstack([np.zeros((1, x.shape[1])), np.cumsum(x, axis=0)])
        c2 = np.vstack([np.zeros((1, x.shape[1])), np.cumsum(x * x, axis=0)])
        n = np.maximum(cnt, 1)[:, None]
        mean = (c1[idx] - c1[start]) / n
        var = np.maximum((c2[idx] - c2[start]) / n - mean**2, 0.0)
        std = np.sqrt(np.sum(var, axis=1))
        still &= (cnt < 2) | (std < thr_std)
    return still


@dataclass
class _Track:
    """Dead-reckoned relative track in the yaw-zero frame W', sampled at query times."""

    d: F64  # (N,3) base-origin displacement from the window start, m
    rot: F64  # (N,3,3) R_W'_base
    vel: F64  # (N,3) velocity in W', m/s (relative to the start velocity if that is free)
    free_velocity: bool  # start velocity unknown (IMU-only track not starting at rest)
    sens: F64  # (N,3,P) d(d)/d(params): accel bias, gyro bias, [tilt] (IMU-only track)
    sens_sigma: F64  # (P,) prior std of those parameters
    # (3,P) d(vel)/d(params) and the rotation vector (W' axes) of rot's change per unit
    # parameter, at the last query time: the solved corrections move the end state too
    vel_sens: F64
    rot_sens: F64


@dataclass
class StartProblem:
    """Whitened residuals and Jacobian of the start solve, the one model of every start:
    a dead-reckoned relative track placed in the map by the raw ranges
    (`Initialiser._solve_heading` with the IMU or wheel track, `start.solve_start` with the
    wheel track of a sparse round-robin radio).

    Unknowns x: start base position p0 (3) m and yaw0 rad in the map frame, then the
    common range scale error k (n_k = 1: ranges read (1 + k) x the distance), the start
    velocity (3, m/s, when `solve_v`), the track's sensitivity parameters (n_s: accel
    bias, gyro bias, tilt) and the range offsets (n_b, m; `anc_col` maps each range to
    its offset: one per anchor, or one common offset). Residuals: each range over `sig`,
    then the priors (start fix, velocity, sensitivities, offsets, scale, height); a prior
    of infinite std is no prior (its rows are zero).
    """

    w0: F64  # (N,3) tag relative to the window-start base, yaw-zero frame, m
    sens: F64  # (N,3,P) sensitivities of w0
    dtr: F64  # (N,) s since the window start
    anc: F64  # (N,3) anchor of each range, m
    anc_col: np.ndarray  # (N,) column of each range's anchor among the biases
    rr: F64  # (N,) ranges, m
    sig: float  # range sigma, m
    lev0: F64  # (3,) tag where `prior` holds it, from the window-start base, yaw-zero frame, m
    prior: tuple[F64, float] | None  # standstill fix (tag position m, std m)
    sens_sigma: F64  # (P,) prior std of the sensitivity parameters
    b_sigma: float  # prior std of the range biases, m
    z_prior: float  # start height prior, m
    z_sigma: float  # its std, m
    solve_v: bool
    n_k: int
    n_s: int
    n_b: int
    k_sigma: float = _SCALE_SIGMA  # prior std of the range scale error

    @property
    def i_k(self) -> int:
        return 4

    @property
    def i_v(self) -> int:
        return 4 + self.n_k

    @property
    def i_s(self) -> int:
        return self.i_v + 3 * self.solve_v

    @property
    def i_b(self) -> int:
        return self.i_s + self.n_s

    @property
    def n(self) -> int:
        """Number of unknowns."""
        return self.i_b + self.n_b

    def fun_jac(self, x: F64) -> tuple[F64, F64]:
        """Residuals (n_r + priors,) and their Jacobian at x."""
        w0, sens, dtr, anc, anc_col, rr, sig, lev0, prior = (
            self.w0, self.sens, self.dtr, self.anc, self.anc_col, self.rr, self.sig,
            self.lev0, self.prior)
        solve_v, n_k, n_s, n_b = self.solve_v, self.n_k, self.n_s, self.n_b
        i_k, i_v, i_s, i_b, n_unk = self.i_k, self.i_v, self.i_s, self.i_b, self.n
        n_r = len(rr)
        n_prior = (3 if prior is not None else 0) + 3 * solve_v + n_s + n_b + n_k + 1
        p0, yaw0 = x[:3], x[3]
        rz = rot_z(yaw0)
        drz = np.array([[-math.sin(yaw0), -math.cos(yaw0), 0.0],
                        [math.cos(yaw0), -math.sin(yaw0), 0.0], [0.0, 0.0, 0.0]])
        w = w0 + (sens @ x[i_s:i_b] if n_s else 0.0)
        tag = p0 + w @ rz.T
        if solve_v:
            tag = tag + np.outer(dtr, x[i_v:i_v + 3])
        diff = tag - anc
        dist = np.maximum(np.linalg.norm(diff, axis=1), 1e-6)
        u = diff / dist[:, None]
        b = x[i_b:][anc_col] if n_b else 0.0
        sc = 1.0 + x[i_k] if n_k else 1.0
        f = np.empty(n_r + n_prior)
        jac = np.zeros((n_r + n_prior, n_unk))
        f[:n_r] = (sc * dist + b - rr) / sig
        jac[:n_r, :3] = sc * u / sig
        jac[:n_r, 3] = sc * np.einsum("ni,ni->n", u, w @ drz.T) / sig
        if n_k:
            jac[:n_r, i_k] = dist / sig
        if solve_v:
            jac[:n_r, i_v:i_v + 3] = sc * u * dtr[:, None] / sig
        if n_s:
            jac[:n_r, i_s:i_b] = sc * np.einsum("ni,ij,njk->nk", u, rz, sens) / sig
        if n_b:
            jac[np.arange(n_r), i_b + anc_col] = 1.0 / sig
        row = n_r
        if prior is not None:
            sp = max(prior[1], 0.02)
            f[row:row + 3] = (p0 + rz @ lev0 - prior[0]) / sp
            jac[row:row + 3, :3] = np.eye(3) / sp
            jac[row:row + 3, 3] = drz @ lev0 / sp
            row += 3
        if solve_v:
            f[row:row + 3] = x[i_v:i_v + 3] / _V0_SIGMA
            jac[row:row + 3, i_v:i_v + 3] = np.eye(3) / _V0_SIGMA
            row += 3
        if n_s:
            f[row:row + n_s] = x[i_s:i_b] / self.sens_sigma
            jac[row:row + n_s, i_s:i_b] = np.diag(1.0 / self.sens_sigma)
            row += n_s
        if n_b:
            f[row:row + n_b] = x[i_b:] / self.b_sigma
            jac[row:row + n_b, i_b:] = np.eye(n_b) / self.b_sigma
            row += n_b
        if n_k:
            f[row] = x[i_k] / self.k_sigma
            jac[row, i_k] = 1.0 / self.k_sigma
            row += 1
        f[row] = (x[2] - self.z_prior) / self.z_sigma
        jac[row, 2] = 1.0 / self.z_sigma
        return f, jac


class Initialiser:
    """Initial state from IMU / wheels / UWB, whichever the log has (see module doc).

    config: the run's `Config` (`[init]`, `[uwb]`, `[imu]`, `[extrinsics]`); anchors: the
    anchor map (None: no ranges, start at the map origin heading zero); streams: the
    sensor streams the log has, subset of {"imu", "wheel", "uwb"}.
    """

    def __init__(
        self,
        config: Config,
        anchors: AnchorMap | None,
        streams: frozenset[str],
        *,
        estimate_range_bias: bool = True,
        corrects_heading: bool = True,
    ) -> None:
        """`corrects_heading`: the consumer corrects its heading from later data (the
        graph, the filters); dead reckoning does not, so its start waits for a heading
        pinned down (`accept_start`'s `narrow_basin`)."""
        self.corrects_heading = corrects_heading
        self.config = config
        self.anchors = anchors
        self.streams = frozenset(streams)
        self.has_imu = "imu" in self.streams
        self.has_wheel = "wheel" in self.streams
        self.has_uwb = "uwb" in self.streams and anchors is not None and len(anchors) > 0
        self.planar = self.has_wheel
        self.estimate_range_bias = estimate_range_bias
        self.lever = applied_lever(config.extrinsics.tag_in_base, self.streams)
        q = config.extrinsics.imu_in_base[3:]
        self.R_base_imu = Rotation.from_quat(q).as_matrix()
        self._imu: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        self._wheel: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        self._rng: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        self._cache: dict[str, tuple[np.ndarray, ...]] = {}
        self._last_attempt_ns: int | None = None
        self._f_level = np.array([0.0, 0.0, config.imu.gravity])  # mean f used to level
        self._still_s = 0.0
        self._candidate: InitialState | None = None
        self._r_level: F64 | None = None
        self.attempts = 0
        self.last_reason = "no data"
        self.range_scale = 1.0  # common range scale of the latest heading solve

    # ------------------------------------------------------------------ input
    def add_imu(self, t_ns: np.ndarray, gyro: np.ndarray, accel: np.ndarray) -> None:
        """IMU batch: stamps (N,) ns, gyro (N,3) rad/s, specific force (N,3) m/s^2, IMU frame."""
        if len(t_ns):
            self._imu.append((np.asarray(t_ns), np.asarray(gyro), np.asarray(accel)))
            self._cache.pop("imu", None)

    def add_wheel(self, t_ns: np.ndarray, v: np.ndarray, omega: np.ndarray) -> None:
        """Wheel batch: stamps (N,) ns, forward speed (N,) m/s, yaw rate (N,) rad/s."""
        if len(t_ns):
            self._wheel.append((np.asarray(t_ns), np.asarray(v), np.asarray(omega)))
            self._cache.pop("wheel", None)

    def add_ranges(self, t_ns: np.ndarray, anchor: np.ndarray, rng: np.ndarray) -> None:
        """Range batch: stamps (N,) ns, anchor index (N,), range (N,) m."""
        if len(t_ns):
            self._rng.append((np.asarray(t_ns), np.asarray(anchor), np.asarray(rng)))
            self._cache.pop("rng", None)

    def _cat(self, name: str) -> tuple[np.ndarray, ...]:
        if name not in self._cache:
            src = {"imu": self._imu, "wheel": self._wheel, "rng": self._rng}[name]
            if not src:
                return ()
            cols = tuple(np.concatenate(c) for c in zip(*src, strict=True))
            order = np.argsort(cols[0], kind="stable")
            cols = tuple(c[order] for c in cols)
            src[:] = [cols]
            self._cache[name] = cols
        return self._cache[name]

    # ------------------------------------------------------------------ main
    def try_initialise(self, t_ns: int) -> InitialState | None:
        """The initial state at t_ns from data with stamps <= t_ns, or None if undetermined."""
        imu = self._upto(self._cat("imu"), t_ns)
        wheel = self._upto(self._cat("wheel"), t_ns)
        rng = self._upto(self._cat("rng"), t_ns)
        if self.has_imu and (not imu or len(imu[0]) < 2):
            self.last_reason = "waiting for IMU data"
            return None
        if self.has_wheel and (not wheel or len(wheel[0]) < 2):
            self.last_reason = "waiting for wheel data"
            return None
        still = self._standstill(imu, wheel, t_ns)
        if still is None:
            return None
        still_end_ns, still_ok, r_level, gyro_bias, accel_bias = still
        self._r_level = r_level
        if not self.has_uwb:
            return self._no_ranges_state(t_ns, r_level, gyro_bias, accel_bias, still_ok)
        if not rng or len(rng[0]) < 3:
            self.last_reason = "waiting for ranges"
            return None
        if not self.has_imu and not self.has_wheel:
            return self._uwb_only(t_ns, rng)
        at_rest = still_ok
        if still_ok and not self.has_wheel:
            # Constant velocity looks still to an IMU: the UWB track decides.
            t_first = int(min(imu[0][0], rng[0][0]))
            at_rest = not self._uwb_moving(rng, t_first, still_end_ns or t_ns)
        if at_rest and still_end_ns is None:
            self.last_reason = "standing still"
            return None
        if self._last_attempt_ns is not None and t_ns - self._last_attempt_ns < _RETRY_S * NS_PER_S:
            return None
        motion_start = still_end_ns if at_rest and still_end_ns is not None else None
        return self._solve_heading(
            t_ns, imu, wheel, rng, r_level, gyro_bias, accel_bias, still_ok, motion_start,
            at_rest,
        )

    def _uwb_moving(self, rng: tuple, t_from: int, t_to: int) -> bool:
        """True when the UWB fixes in [t_from, t_to] show a speed above `min_motion`, or
        the tag's position has moved `min_displacement` between the first and the last
        _UWB_TRACK_S of them: a tag that went that far was not standing still, however
        slowly it went (the room's 0.1 m/s loop is no faster than `min_motion` and too
        smooth for the IMU's standstill test: its 17 s "standstill" put the start's static
        fix, the fixes' median over it, 0.9 m behind the tag)."""
        tf, pf, okf = self._fixes(rng, t_from)
        sel = okf & (tf <= t_to / NS_PER_S)
        tf, pf = tf[sel], pf[sel]
        if len(tf) < 10 or tf[-1] - tf[0] < 1.0:
            return False
        a_mat = np.column_stack([np.ones_like(tf), tf - tf[0]])
        coef, *_ = np.linalg.lstsq(a_mat, pf[:, :2], rcond=None)
        res = pf[:, :2] - a_mat @ coef
        s2 = float(np.sum(res**2) / max(2 * len(tf) - 4, 1))
        sv = math.sqrt(s2 * np.linalg.inv(a_mat.T @ a_mat)[1, 1])
        speed = float(np.linalg.norm(coef[1]))
        # the tag's net move: its position (the fixes' median) over the last _UWB_TRACK_S
        # against the first (medians: an NLOS fix's jump is no move)
        head = np.median(pf[tf <= tf[0] + _UWB_TRACK_S, :2], axis=0)
        tail = np.median(pf[tf >= tf[-1] - _UWB_TRACK_S, :2], axis=0)
        moved = float(np.linalg.norm(tail - head))
        return (speed > self.config.init.min_motion and speed > 4.0 * sv) or (
            moved >= self.config.init.min_displacement)

    def provisional(self, t_ns: int) -> InitialState | None:
        """A best-effort state at t_ns before `try_initialise` succeeds, or None.

        For estimators that must write poses from the first motion while the heading is not
        yet determined: the latest heading solution (even if not accepted) when it was made
        at t_ns; otherwise the tag position from the recent UWB fixes with the attitude of a
        heading candidate less than `_RETRY_S` * 2 old, else the levelled attitude with yaw
        0 and yaw_sigma = pi. The state always refers to t_ns. Never use it as a filter's
        start state without its yaw_sigma.
        """
        c = self._candidate
        if c is not None and c.t_ns == t_ns:
            return c
        recent = c is not None and 0 <= t_ns - c.t_ns <= 2 * _RETRY_S * NS_PER_S
        if not self.has_uwb:
            return None
        rng = self._upto(self._cat("rng"), t_ns)
        if not rng or len(rng[0]) < 3:
            return None
        _tf, pf, okf = self._fixes(rng, int(t_ns - _PROVISIONAL_S * NS_PER_S))
        if not np.any(okf):
            return None
        tag = np.median(pf[okf], axis=0)
        spread = float(np.median(np.linalg.norm(pf[okf] - tag, axis=1))) * 1.4826
        r_level = self._r_level if self._r_level is not None else np.eye(3)
        yaw_sigma = math.pi
        if recent:
            # The last heading candidate's attitude (not accepted yet, but better than 0).
            assert c is not None
            r_level, yaw_sigma = np.asarray(c.R_map_base), float(c.yaw_sigma)
        return InitialState(
            t_ns=int(t_ns), position=tag - r_level @ self.lever, R_map_base=r_level,
            velocity=np.zeros(3), gyro_bias=np.zeros(3), accel_bias=np.zeros(3),
            position_sigma=max(spread, float(np.linalg.norm(self.lever[:2])), 0.05),
            yaw_sigma=yaw_sigma, still=False,
        )

    @staticmethod
    def _upto(cols: tuple[np.ndarray, ...], t_ns: int) -> tuple[np.ndarray, ...]:
        if not cols:
            return ()
        n = int(np.searchsorted(cols[0], t_ns, side="right"))
        return tuple(c[:n] for c in cols)

    # ------------------------------------------------------------------ standstill
    def _standstill(
        self, imu: tuple, wheel: tuple, t_ns: int
    ) -> tuple[int | None, bool, F64, F64, F64] | None:
        """(still_end_ns or None if still ongoing, still start?, R_level, b_g, b_a) or None.

        None means: not enough data yet to level the IMU.
        """
        cfg = self.config.init
        t0_candidates = [int(c[0][0]) for c in (imu, wheel) if c]
        zeros = np.zeros(3)
        if not t0_candidates:
            return None, False, np.eye(3), zeros, zeros  # UWB only: nothing to level
        t0 = min(t0_candidates)
        t_end = t_ns
        n_blocks = int((t_end - t0) / (BLOCK_S * NS_PER_S))
        block_end = (t0 + (np.arange(1, n_blocks + 1) * BLOCK_S * NS_PER_S)).astype(np.int64)
        still = np.ones(n_blocks, dtype=bool)
        if imu and n_blocks:
            # Gyro: the spread about the block mean (noise) below the threshold; the block
            # mean itself may hold a turn-on bias up to _GYRO_BIAS_MAX.
            gyro_thr = cfg.standstill_gyro_max
            still &= block_still(imu[0], imu[1], block_end, None, gyro_thr)
            still &= block_still(imu[0], imu[2], block_end, None, cfg.standstill_accel_std_max)
        if wheel and n_blocks:
            wv = np.column_stack([wheel[1], np.zeros_like(wheel[1])])
            wo = np.column_stack([wheel[2], np.zeros_like(wheel[2])])
            still &= block_still(wheel[0], wv, block_end, cfg.min_motion, None)
            still &= block_still(wheel[0], wo, block_end, cfg.standstill_gyro_max * 3, None)
        if imu and n_blocks:
            # Smooth accelerations hide from the per-block std: also compare each block's
            # mean specific force with the mean of the blocks before it.
            idx = np.searchsorted(imu[0], block_end, side="right")
            csum = np.vstack([np.zeros((1, 3)), np.cumsum(imu[2], axis=0)])
            cnt = np.maximum(np.diff(np.concatenate([[0], idx])), 1)
            prev = np.concatenate([[0], idx[:-1]])
            bmean = (csum[idx] - csum[prev]) / cnt[:, None]
            ref = csum[prev] / np.maximum(prev, 1)[:, None]
            dev = np.linalg.norm(bmean - ref, axis=1)
            dev[0] = 0.0
            still &= dev < cfg.standstill_accel_std_max
            gsum = np.vstack([np.zeros((1, 3)), np.cumsum(imu[1], axis=0)])
            gmean = (gsum[idx] - gsum[prev]) / cnt[:, None]
            gref = gsum[prev] / np.maximum(prev, 1)[:, None]
            gdev = np.linalg.norm(gmean - gref, axis=1)
            gdev[0] = 0.0
            still &= (gdev < cfg.standstill_gyro_max) & (
                np.linalg.norm(gmean, axis=1) < _GYRO_BIAS_MAX)
        moving = np.flatnonzero(~still)
        n_still = int(moving[0]) if len(moving) else n_blocks
        still_s = n_still * BLOCK_S
        ended = len(moving) > 0
        still_ok = still_s >= cfg.standstill_window
        self._still_s = still_s
        if not still_ok and not ended:
            self.last_reason = "waiting for a standstill window or motion"
            return None
        still_end = int(t0 + n_still * BLOCK_S * NS_PER_S)
        r_level = np.eye(3)
        bg, ba = zeros, zeros
        if imu:
            g = self.config.imu.gravity
            sel = imu[0] < still_end
            if still_ok and np.count_nonzero(sel) >= _MIN_STILL_IMU_SAMPLES:
                bg = np.mean(imu[1][sel], axis=0)
                f_imu = np.mean(imu[2][sel], axis=0)
                f_norm = float(np.linalg.norm(f_imu))
                ba = (f_norm - g) * f_imu / max(f_norm, 1e-9)
            else:  # moving start, or an IMU that began after the (wheel) standstill
                lw = int(cfg.level_window * NS_PER_S)
                if imu[0][-1] - imu[0][0] < lw:
                    self.last_reason = "levelling: waiting for level_window of IMU data"
                    return None
                sel = imu[0] <= imu[0][0] + lw
                f_imu = np.mean(imu[2][sel], axis=0)
            self._f_level = f_imu
            r_level = level_from_accel(self.R_base_imu @ f_imu)
        return (still_end if ended else None), still_ok, r_level, bg, ba

    # ------------------------------------------------------------------ pieces
    def _range_sigma(self) -> float:
        return float(self.config.uwb.sigma)

    def _fix_dim(self) -> tuple[int, float]:
        """Fix dimension and tag height: 2-D for wheeled logs or < 4 anchors, else 3-D."""
        assert self.anchors is not None
        if self.planar:
            return 2, self.config.init.base_height + float(self.lever[2])
        if len(self.anchors) < 4:
            return 2, default_tag_z(self.anchors.positions)
        return 3, default_tag_z(self.anchors.positions)

    def _fixes(self, rng: tuple, t_from: int | None = None) -> tuple[F64, F64, F64]:
        """Per-epoch 3-D fixes (tag) over the range data: (t_s (K,), pos (K,3), ok (K,))."""
        assert self.anchors is not None
        t, a, r = rng
        if t_from is not None:
            sel = t >= t_from
            t, a, r = t[sel], a[sel], r[sel]
        window_ns = epoch_window_ns(t, a, int(self.config.wls.window * NS_PER_S))
        ep = epochs_by_window(t, window_ns)
        if not len(ep):
            return np.zeros(0), np.zeros((0, 3)), np.zeros(0, dtype=bool)
        grid, stamps = group_epochs(t, a, r, len(self.anchors), ep, window_ns)
        dim, tag_z = self._fix_dim()
        fx = multilaterate(
            self.anchors.positions, grid, dim=dim, tag_z=tag_z, sigma=self._range_sigma(),
            kernel=self.config.uwb.robust_kernel, threshold=self.config.uwb.kernel_threshold,
        )
        # a fix is where the tag was while its ranges were taken: at their mean stamp, not
        # at the epoch's end (a slow round robin spreads them over a second of motion)
        got = stamps >= 0
        n_got = np.maximum(got.sum(axis=1), 1)
        t_fix = np.where(got, stamps - ep[:, None], 0).sum(axis=1) / n_got + ep
        return t_fix.astype(np.float64) / NS_PER_S, fx.position, fx.ok

    def _static_fix(self, rng: tuple, t_from: int, t_to: int) -> tuple[F64, float] | None:
        """Robust fix of the tag from the ranges in [t_from, t_to): (pos (3,), sigma m)."""
        assert self.anchors is not None
        t, a, r = rng
        sel = (t >= t_from) & (t < t_to)
        m = len(self.anchors)
        if np.count_nonzero(sel) < 3:
            return None
        med = np.full(m, np.nan)
        cnt = np.bincount(a[sel], minlength=m)
        for k in np.flatnonzero(cnt):
            med[k] = np.median(r[sel][a[sel] == k])
        sig = self._range_sigma() / np.sqrt(np.maximum(cnt, 1))
        dim, tag_z = self._fix_dim()
        fx = multilaterate(self.anchors.positions, med[None, :], dim=dim, tag_z=tag_z,
                           sigma=np.where(cnt > 0, sig, 1.0)[None, :])
        if not fx.ok[0]:
            return None
        return fx.position[0], float(np.sqrt(np.trace(fx.cov[0])))

    def _imu_strapdown(
        self, imu: tuple, gyro_bias: F64, accel_bias: F64, r_level: F64, t_start_s: float,
        tq: F64, rot_i: F64 | None = None,
    ) -> tuple[F64, F64, F64]:
        """IMU-only track in W' at tq: (d (N,3) from t_start_s at rest, rot (N,3,3), vel).

        rot_i: attitudes at the IMU samples if already integrated (same gyro bias/level).
        """
        g = self.config.imu.gravity
        ti = imu[0].astype(np.float64) / NS_PER_S
        if rot_i is None:
            rot_i = integrate_gyro(r_level, ti, (imu[1] - gyro_bias) @ self.R_base_imu.T)
        f_base = (imu[2] - accel_bias) @ self.R_base_imu.T
        acc = np.einsum("nij,nj->ni", rot_i, f_base) - np.array([0.0, 0.0, g])
        sel = ti > t_start_s
        ts = np.concatenate([[t_start_s], ti[sel]])
        acc_s = acc[sel]
        # Sample k's specific force applies over (t_{k-1}, t_k].
        dt = np.diff(ts)
        vel = np.vstack([np.zeros((1, 3)), np.cumsum(acc_s * dt[:, None], axis=0)])
        pos = np.vstack([np.zeros((1, 3)),
                         np.cumsum(0.5 * (vel[1:] + vel[:-1]) * dt[:, None], axis=0)])
        d = np.column_stack([np.interp(tq, ts, pos[:, k]) for k in range(3)])
        vq = np.column_stack([np.interp(tq, ts, vel[:, k]) for k in range(3)])
        idx = np.clip(np.searchsorted(ti, tq, side="right") - 1, 0, len(ti) - 1)
        return d, rot_i[idx], vq

    def _track(
        self, imu: tuple, wheel: tuple, r_level: F64, gyro_bias: F64, accel_bias: F64,
        t_start_s: float, tq: F64, v0_known: bool, still_ok: bool,
    ) -> _Track:
        """Dead-reckoned track at query times tq (s) relative to the window start t_start_s.

        For an IMU-only track, `sens` holds the first-order sensitivities of d to the
        accelerometer bias, gyro bias and (without a still start) the level tilt, each
        found by re-running the strapdown with the parameter perturbed (finite
        differences); the heading solve estimates these small corrections, and
        `vel_sens`, `rot_sens` (the same runs' end velocity and attitude) carry them into
        the start state.
        """
        if self.has_wheel:
            tw = wheel[0].astype(np.float64) / NS_PER_S
            v, om = wheel[1], wheel[2]
            dtw = np.diff(tw, prepend=tw[0])
            if imu:
                ti = imu[0].astype(np.float64) / NS_PER_S
                w_base = (imu[1] - gyro_bias) @ self.R_base_imu.T
                rot_i = integrate_gyro(r_level, ti, w_base)
                yaw_i = np.unwrap(np.arctan2(rot_i[:, 1, 0], rot_i[:, 0, 0]))
                yaw_w = np.interp(tw, ti, yaw_i)
            else:
                yaw_w = np.cumsum(om * dtw)
            yaw_prev = np.concatenate([[yaw_w[0]], yaw_w[:-1]])
            sx, sy = arc_steps(v, dtw, yaw_prev, yaw_w - yaw_prev)
            step = np.column_stack([sx, sy, np.zeros_like(v)])
            pos = np.cumsum(step, axis=0)
            p_start = np.array([np.interp(t_start_s, tw, pos[:, k]) for k in range(3)])
            d = np.column_stack([np.interp(tq, tw, pos[:, k]) for k in range(3)]) - p_start
            yq = np.interp(tq, tw, yaw_w)
            rq = np.einsum("nij,jk->nik", rot_z(yq), r_level) if imu else rot_z(yq)
            k_last = np.clip(np.searchsorted(tw, tq, side="left"), 0, len(tw) - 1)
            vel = np.column_stack(
                [v[k_last] * np.cos(yq), v[k_last] * np.sin(yq), np.zeros_like(yq)]
            )
            return _Track(d, rq, vel, False, np.zeros((len(tq), 3, 0)), np.zeros(0),
                          np.zeros((3, 0)), np.zeros((3, 0)))
        ti = imu[0].astype(np.float64) / NS_PER_S
        rot0 = integrate_gyro(r_level, ti, (imu[1] - gyro_bias) @ self.R_base_imu.T)
        d0, rq, vq = self._imu_strapdown(imu, gyro_bias, accel_bias, r_level, t_start_s, tq,
                                         rot0)
        icfg = self.config.imu
        cols, sigmas, v_cols, r_cols = [], [], [], []

        def add(d1: F64, r1: F64, v1: F64, h: float) -> None:
            cols.append((d1 - d0) / h)
            v_cols.append((v1[-1] - vq[-1]) / h)
            r_cols.append(Rotation.from_matrix(r1[-1] @ rq[-1].T).as_rotvec() / h)

        h_a, h_g, h_t = 0.01, 1e-3, 1e-3
        f_lvl = self._f_level
        for k in range(3):
            e = np.zeros(3)
            e[k] = 1.0
            ba = accel_bias + h_a * e
            # With a still start the level follows the bias: gravity = mean f - bias.
            rl = level_from_accel(self.R_base_imu @ (f_lvl - ba)) if still_ok else r_level
            rot1 = np.einsum("ij,njk->nik", rl @ r_level.T, rot0)
            add(*self._imu_strapdown(imu, gyro_bias, ba, rl, t_start_s, tq, rot1), h_a)
            sigmas.append(icfg.accel_bias_sigma)
        # Gyro bias left after the standstill mean (3 sigma of its noise plus drift).
        bg_sigma = (3.0 * icfg.gyro_noise_density / math.sqrt(max(self._still_s, 1e-3))
                    + icfg.gyro_bias_random_walk * math.sqrt(self.config.init.max_window)
                    ) if still_ok else icfg.gyro_bias_sigma
        for k in range(3):
            e = np.zeros(3)
            e[k] = 1.0
            add(*self._imu_strapdown(imu, gyro_bias + h_g * e, accel_bias, r_level,
                                     t_start_s, tq), h_g)
            sigmas.append(bg_sigma)
        if not still_ok:
            for k in range(2):
                e = np.zeros(3)
                e[k] = h_t
                tilt = Rotation.from_rotvec(e).as_matrix()
                rot1 = np.einsum("ij,njk->nik", tilt, rot0)
                add(*self._imu_strapdown(imu, gyro_bias, accel_bias, tilt @ r_level,
                                         t_start_s, tq, rot1), h_t)
                sigmas.append(_TILT_SIGMA)
        sens = np.stack(cols, axis=2)
        return _Track(d0, rq, vq, not v0_known, sens, np.array(sigmas),
                      np.stack(v_cols, axis=1), np.stack(r_cols, axis=1))

    # ------------------------------------------------------------------ heading
    def _heading_window(self, t_ns: int, imu: tuple, wheel: tuple, rng: tuple,
                        motion_start: int | None) -> tuple[int, int, float, bool]:
        """The heading solve's window at `t_ns`: the first sample's time (ns), the window's
        start (ns), its longest length (s), and whether the velocity at its start is known
        (zero: the window starts where the motion did)."""
        t_first = min(int(c[0][0]) for c in (imu, wheel, rng) if c)
        w_start = motion_start if motion_start is not None else t_first
        max_win = self.config.init.max_window
        if not self.has_wheel:
            # Strapdown drifts (bias, tilt): IMU-only tracks use a shorter window.
            max_win = min(max_win, _IMU_WINDOW_S)
        w_start = max(w_start, int(t_ns - max_win * NS_PER_S))
        # the track needs its motion data: not before the later of the first wheel and IMU
        # samples (wheels that began 10 s late, their track carried back at constant
        # velocity, took the start 2 m and a 7 % range scale off)
        w_start = max([w_start] + [int(c[0][0]) for c in (imu, wheel) if c])
        v0_known = motion_start is not None and w_start == motion_start
        return t_first, w_start, max_win, v0_known

    def _heading_prior(
        self, t_ns: int, imu: tuple, wheel: tuple, rng: tuple, r_level: F64,
        gyro_bias: F64, accel_bias: F64, still_ok: bool, motion_start: int | None,
        t_first: int, w_start: int, v0_known: bool, lev0: F64,
    ) -> tuple[tuple[F64, float] | None, F64]:
        """The static fix (tag position prior, map frame) that holds the heading solve's
        window, if any, and the lever arm (m, window frame W') at the time it holds: the
        standstill before the motion, or a later standstill that ended inside the window."""
        prior = None
        if motion_start is not None and v0_known:
            prior = self._static_fix(rng, t_first, motion_start)
        elif self.has_wheel:
            # a later standstill that ended inside the window: its fix holds the tag where
            # the track has it at the standstill's end (room-static: a 20 s stop ends 1 s
            # into the window; without it the solve's position was 0.25-0.34 m off)
            last = _last_standstill(wheel, w_start, t_ns, self.config.init.standstill_window)
            if last is not None:
                prior = self._static_fix(rng, *last)
                if prior is not None:
                    ts0 = w_start / NS_PER_S
                    at = self._track(imu, wheel, r_level, gyro_bias, accel_bias, ts0,
                                     np.array([ts0, last[1] / NS_PER_S]), v0_known, still_ok)
                    lev0 = at.d[1] + at.rot[1] @ self.lever
        return prior, lev0

    def _solve_heading(
        self, t_ns: int, imu: tuple, wheel: tuple, rng: tuple, r_level: F64,
        gyro_bias: F64, accel_bias: F64, still_ok: bool, motion_start: int | None,
        at_rest: bool = True,
    ) -> InitialState | None:
        assert self.anchors is not None
        cfg = self.config.init
        t_first, w_start, max_win, v0_known = self._heading_window(t_ns, imu, wheel, rng,
                                                                   motion_start)
        tf, pf, okf = self._fixes(rng, w_start)
        pf, tf = pf[okf], tf[okf]
        if len(pf) < 4:
            self.last_reason = "too few UWB fixes in the motion window"
            return None
        head = np.median(pf[: max(1, min(3, len(pf) // 2)), :2], axis=0)
        disp = float(np.percentile(np.linalg.norm(pf[:, :2] - head, axis=1), 90))
        if disp < cfg.min_displacement:
            self.last_reason = f"UWB track moved {disp:.2f} m < min_displacement"
            return None
        self._last_attempt_ns = t_ns
        self.attempts += 1
        t, a, r = rng
        sel = np.flatnonzero(t >= w_start)
        if len(sel) > _MAX_RANGES:
            # Evenly thinned: the solve's cost grows with the ranges, its accuracy hardly.
            sel = sel[np.round(np.linspace(0, len(sel) - 1, _MAX_RANGES)).astype(int)]
        tr = t[sel].astype(np.float64) / NS_PER_S
        ar, rr = a[sel], r[sel]
        ts0 = w_start / NS_PER_S
        t_now = t_ns / NS_PER_S
        tq = np.concatenate([[ts0], tr, [t_now]])
        trk = self._track(imu, wheel, r_level, gyro_bias, accel_bias, ts0, tq, v0_known,
                          still_ok)
        lev = np.einsum("nij,j->ni", trk.rot, self.lever)
        w0 = trk.d[1:-1] + lev[1:-1]  # tag in W' relative to the base at the window start
        sens = trk.sens[1:-1]
        lev0 = lev[0]
        dtr = tr - ts0
        anc = self.anchors.positions[ar]
        sig = self._range_sigma()
        prior, lev0 = self._heading_prior(t_ns, imu, wheel, rng, r_level, gyro_bias,
                                          accel_bias, still_ok, motion_start, t_first,
                                          w_start, v0_known, lev0)
        solve_v = trk.free_velocity
        # Per-anchor range biases (slow NLOS, antenna delay) over the window.
        anc_ids, anc_col = np.unique(ar, return_inverse=True)
        n_b = len(anc_ids) if self.estimate_range_bias else 0
        b_sigma = self.config.nlos.range_nlos_std
        n_s = len(trk.sens_sigma)
        # Common range scale error k (ranges read (1 + k) x the distance): a few percent
        # of tens of metres is metres on large sites. Wheeled logs only: the wheel track
        # carries the metric scale; a free 3-D tag would trade it against its height.
        n_k = 1 if self.planar else 0
        # Weak prior on the start height: the floor for wheeled logs, else below the anchors.
        if self.planar:
            z_prior, z_sigma = self.config.init.base_height, _Z_SIGMA_PLANAR
        else:
            z_prior = default_tag_z(self.anchors.positions) - float(self.lever[2])
            z_sigma = _Z_SIGMA_FREE

        problem = StartProblem(
            w0=w0, sens=sens, dtr=dtr, anc=anc, anc_col=anc_col, rr=rr, sig=sig, lev0=lev0,
            prior=prior, sens_sigma=trk.sens_sigma, b_sigma=b_sigma, z_prior=z_prior,
            z_sigma=z_sigma, solve_v=solve_v, n_k=n_k, n_s=n_s, n_b=n_b)
        i_v, n_unk = problem.i_v, problem.n

        seeds = _heading_seeds(prior, tf, pf, lev0, solve_v, n_unk, i_v, sig)
        sols = solve_seeds(problem, seeds)
        if not sols:
            self.last_reason = "heading solve failed"
            return None
        verdict = accept_start(sols, problem, trk, t_ns, w_start, motion_start, max_win,
                               gyro_bias, accel_bias, still_ok and at_rest,
                               narrow_basin=not self.corrects_heading)
        return self._take(verdict)

    def _take(self, verdict: StartVerdict) -> InitialState | None:
        """Record a start solve's verdict (candidate, range scale, reason); its state if
        accepted."""
        self.last_reason = verdict.reason
        if verdict.state is None:
            return None
        self.range_scale = verdict.state.range_scale
        if verdict.consistent:
            self._candidate = verdict.state
        if not verdict.accepted:
            return None
        log.debug("initialised at %.3f s: yaw %.1f deg", verdict.state.t_ns / NS_PER_S,
                  math.degrees(verdict.state.yaw))
        return verdict.state

    # ------------------------------------------------------------------ UWB only
    def _uwb_only(self, t_ns: int, rng: tuple) -> InitialState | None:
        cfg = self.config.init
        tf, pf, okf = self._fixes(rng)
        tf, pf = tf[okf], pf[okf]
        if len(tf) < _UWB_TRACK_MIN_FIXES:
            self.last_reason = "too few UWB fixes"
            return None
        t_now = t_ns / NS_PER_S
        # the newest fix is recent: within the span, or two of the fixes' own periods
        period = float(np.median(np.diff(tf[-_UWB_TRACK_MIN_FIXES:])))
        if tf[-1] < t_now - max(_UWB_TRACK_S, 2.0 * period):
            self.last_reason = "no recent UWB fix"
            return None
        sel = tf >= min(t_now - _UWB_TRACK_S, tf[-_UWB_TRACK_MIN_FIXES])
        ts, ps = tf[sel] - t_now, pf[sel]
        sig = self._range_sigma()
        coef, w = fit_line(ts, ps, sig)
        a_mat = np.column_stack([np.ones_like(ts), ts])
        p_now, v = coef[0], coef[1]
        resid = ps - a_mat @ coef
        s2 = float(np.sum((w[:, None] * resid[:, :2]) ** 2) / max(2 * len(ts) - 4, 1))
        cov_pv = s2 * np.linalg.inv(a_mat.T @ (a_mat * (w**2)[:, None]))
        cov_v = cov_pv[1, 1]
        speed = float(np.linalg.norm(v[:2]))
        moved = speed * (ts[-1] - ts[0])
        since_first = t_now - tf[0]
        yaw_sigma = math.sqrt(cov_v) / max(speed, 1e-9)
        if speed >= cfg.min_motion and moved >= cfg.min_displacement * 0.5 and (
            yaw_sigma <= 2 * cfg.max_yaw_sigma
        ):
            yaw = math.atan2(v[1], v[0])
        elif since_first >= cfg.heading_timeout:
            yaw, yaw_sigma = 0.0, math.pi
            if speed >= cfg.min_motion:
                yaw = math.atan2(v[1], v[0])
                yaw_sigma = min(math.pi, yaw_sigma)
        else:
            self.last_reason = "UWB only: waiting for motion to give the track direction"
            return None
        rz = rot_z(yaw)
        vel = np.array([v[0], v[1], 0.0 if self.planar else v[2]])
        pos = p_now - rz @ self.lever
        # the line's position at t_now (its intercept: the fixes' times count from t_now),
        # std over both horizontal axes: it grows as t_now lies past the fixes (a slow
        # round robin's newest fix is a second old)
        pos_sigma = math.sqrt(2.0 * cov_pv[0, 0])
        self.last_reason = "initialised (UWB only)"
        return InitialState(
            t_ns=int(t_ns), position=pos, R_map_base=rz, velocity=vel,
            gyro_bias=np.zeros(3), accel_bias=np.zeros(3),
            position_sigma=float(max(pos_sigma, sig / 3)), yaw_sigma=float(yaw_sigma),
            still=False,
        )

    # ------------------------------------------------------------------ no ranges
    def _no_ranges_state(
        self, t_ns: int, r_level: F64, gyro_bias: F64, accel_bias: F64, still_ok: bool
    ) -> InitialState:
        """Without ranges: the map origin, heading zero, at t_ns (dead reckoning frame)."""
        self.last_reason = "initialised at the map origin (no ranges)"
        return InitialState(
            t_ns=int(t_ns), position=np.zeros(3), R_map_base=r_level, velocity=np.zeros(3),
            gyro_bias=gyro_bias.copy(), accel_bias=accel_bias.copy(), position_sigma=0.0,
            yaw_sigma=0.0, still=still_ok,
        )


@dataclass
class LmResult:
    """`robust_lm` result: solution x, robust cost, residuals fun and the Jacobian `jac`
    scaled by the square roots of the final IRLS weights (J^T J approximates the Hessian)."""

    x: F64
    cost: float
    fun: F64
    jac: F64


def _soft_l1(f: F64, n_r: int, scale: float) -> tuple[float, F64]:
    """Cost 0.5 sum rho and IRLS weights: soft-L1 on the first n_r residuals, L2 after."""
    z = (f[:n_r] / scale) ** 2
    cost = float(np.sum(scale**2 * (np.sqrt(1.0 + z) - 1.0)) + 0.5 * np.sum(f[n_r:] ** 2))
    w = np.ones_like(f)
    w[:n_r] = 1.0 / np.sqrt(1.0 + z)
    return cost, w


def robust_lm(
    fun_jac: Callable[[F64], tuple[F64, F64]], x0: F64, n_r: int, scale: float,
    max_iter: int = 40, tol: float = 1e-7,
) -> LmResult | None:
    """Levenberg-Marquardt with IRLS soft-L1 weights (scale in residual units) on the first
    n_r residuals and plain least squares on the rest (priors).

    Solves the small normal equations directly: no dense SVD per iteration, whose
    multi-threaded BLAS cost dominated scipy's least_squares for this problem.
    """
    x = np.array(x0, dtype=np.float64)
    f, jac = fun_jac(x)
    cost, w = _soft_l1(f, n_r, scale)
    lam = 1e-3
    eye = np.eye(len(x))
    for _ in range(max_iter):
        jw = jac * w[:, None]
        a_mat = jac.T @ jw
        g = jw.T @ f
        try:
            dx = np.linalg.solve(a_mat + lam * (np.diag(np.diag(a_mat)) + 1e-9 * eye), -g)
        except np.linalg.LinAlgError:
            return None
        x_new = x + dx
        f_new, jac_new = fun_jac(x_new)
        cost_new, w_new = _soft_l1(f_new, n_r, scale)
        if np.isfinite(cost_new) and cost_new <= cost:
            x, f, jac, w = x_new, f_new, jac_new, w_new
            done = cost - cost_new < tol * max(cost, 1.0) and np.max(np.abs(dx)) < 1e-4
            cost = cost_new
            lam = max(lam / 3.0, 1e-9)
            if done:
                break
        else:
            lam *= 5.0
            if lam > 1e8:
                break
    if not np.all(np.isfinite(x)):
        return None
    return LmResult(x, cost, f, jac * np.sqrt(w)[:, None])


@dataclass(frozen=True)
class StartVerdict:
    """`accept_start` result: the best solution's state at t_ns (None when the solve was
    singular), whether its residuals are consistent, whether it is accepted as the start,
    and the reason (for logs and `Initialiser.last_reason`)."""

    state: InitialState | None
    consistent: bool
    accepted: bool
    reason: str


def solve_seeds(problem: StartProblem, seeds: list[F64]) -> list[LmResult]:
    """The start solve: `robust_lm` (soft-L1 at SOFT_L1_SIGMAS range sigmas) from each
    seed x0 of `problem`'s unknowns; the local minima found."""
    sols = []
    for x0 in seeds:
        sol = robust_lm(problem.fun_jac, x0, len(problem.rr), SOFT_L1_SIGMAS)
        if sol is not None:
            sols.append(sol)
    return sols


def accept_start(
    sols: list[LmResult], problem: StartProblem, trk: _Track, t_ns: int, w_start: int,
    motion_start: int | None, max_win: float, gyro_bias: F64, accel_bias: F64, still: bool,
    narrow_basin: bool = False,
) -> StartVerdict:
    """`Initialiser`'s heading solve judged by the start's acceptance rule (`best_minimum`):
    the state at t_ns from the local minima `sols` of `problem`
    over the window from `w_start` ns, accepted when its residuals are consistent (robust
    spread within 3 range sigmas or _MAX_MAD_REL of the median range, 60 % inliers) and its
    yaw is determined (no rival
    minimum RIVAL_SEPARATION away within RIVAL_MARGIN of chi-square; with `narrow_basin`,
    for a consumer that cannot correct its heading later, also the best minimum's own
    basin: a yaw std of at most a third of the separation) or a full window of max_win s
    has been waited. The least-squares stds are reported with the state as they are."""
    rr, sig = problem.rr, problem.sig
    i_k, i_v, i_s, i_b, n_unk = problem.i_k, problem.i_v, problem.i_s, problem.i_b, problem.n
    n_r, n_k, n_s, solve_v = len(rr), problem.n_k, problem.n_s, problem.solve_v
    ts0 = w_start / NS_PER_S
    t_now = t_ns / NS_PER_S
    found = best_minimum(sols, problem)
    best, consistent, mad, inliers, margin = (found.best, found.consistent, found.mad,
                                              found.inliers, found.margin)
    dof = max(n_r - n_unk, 1)
    scale2 = max(1.0, 2.0 * best.cost / dof)
    try:
        cov = np.linalg.inv(best.jac.T @ best.jac) * scale2
    except np.linalg.LinAlgError:
        return StartVerdict(None, False, False, "heading solve singular")
    yaw_sigma = min(float(np.sqrt(max(cov[3, 3], 0.0))), math.pi)
    x = best.x
    p0, yaw0 = x[:3], float(x[3])
    v0 = x[i_v:i_v + 3] if solve_v else np.zeros(3)
    dt_now = t_now - ts0
    rz = rot_z(yaw0)
    d_now = trk.d[-1] + (trk.sens[-1] @ x[i_s:i_b] if n_s else 0.0)
    pos = p0 + v0 * dt_now + rz @ d_now
    # the end attitude and velocity with the solved bias and tilt corrections (first order,
    # as the position's): a gyro bias b left in a strapdown window of t seconds tilts its end
    # by b t and its velocity by g b t^2 / 2 (0.02 rad/s over 7 s: 8 deg, 4.8 m/s)
    r_now = rz @ trk.rot[-1]
    vel = v0 + rz @ trk.vel[-1]
    if n_s:
        r_now = rz @ Rotation.from_rotvec(trk.rot_sens @ x[i_s:i_b]).as_matrix() @ trk.rot[-1]
        vel = vel + rz @ (trk.vel_sens @ x[i_s:i_b])
    ba, bg = accel_bias.copy(), gyro_bias.copy()
    if n_s:
        ba = ba + x[i_s:i_s + 3]
        bg = bg + x[i_s + 3:i_s + 6]
    # Position std at t_ns: the solved covariance mapped through pos(x).
    grad = np.zeros((3, n_unk))
    grad[:, :3] = np.eye(3)
    drz = np.array([[-math.sin(yaw0), -math.cos(yaw0), 0.0],
                    [math.cos(yaw0), -math.sin(yaw0), 0.0], [0.0, 0.0, 0.0]])
    grad[:, 3] = drz @ d_now
    if solve_v:
        grad[:, i_v:i_v + 3] = np.eye(3) * dt_now
    if n_s:
        grad[:, i_s:i_b] = rz @ trk.sens[-1]
    pcov = grad @ cov @ grad.T
    pos_sigma = float(np.sqrt(max(np.trace(pcov[:2, :2]), 0.0)))
    # The least-squares stds (scaled by the residuals' spread), as they are: a wider report
    # makes a filter overreact to its first ranges (docs/results.md, session 15)
    state = InitialState(
        t_ns=int(t_ns), position=pos, R_map_base=r_now, velocity=vel,
        gyro_bias=bg, accel_bias=ba, position_sigma=pos_sigma,
        yaw_sigma=min(yaw_sigma, math.pi), still=still,
        range_scale=1.0 + float(x[i_k]) if n_k else 1.0,
        range_sigma=max(mad, 1.0) * sig,
        range_scale_sigma=float(np.sqrt(max(cov[i_k, i_k], 0.0))) if n_k else math.inf,
    )
    # After a full window without a determined heading, start anyway with the best
    # solution and its (large) yaw std: the estimator must start from what it has.
    waited = t_ns - w_start >= max_win * NS_PER_S * 0.99 or (
        motion_start is not None and t_ns - motion_start >= max_win * NS_PER_S)
    # narrow basin: a heading RIVAL_SEPARATION off costs RIVAL_MARGIN in the best
    # minimum's own basin too (quadratic: (separation / std)^2)
    determined = margin >= RIVAL_MARGIN and (
        not narrow_basin or yaw_sigma <= RIVAL_SEPARATION / math.sqrt(RIVAL_MARGIN))
    if not consistent or not (determined or waited):
        reason = (f"heading not yet determined (yaw std {math.degrees(yaw_sigma):.1f} deg, "
                  f"MAD {mad:.1f} sigma, inliers {inliers:.2f}, rival margin {margin:.1f})")
        return StartVerdict(state, consistent, False, reason)
    return StartVerdict(state, consistent, True, "initialised")


@dataclass(frozen=True)
class StartMinimum:
    """The acceptance rule's reading of a start solve's local minima (`best_minimum`)."""

    best: LmResult  # the lowest cost
    consistent: bool  # its residuals pass `start_consistent`
    mad: float  # their robust spread, range sigmas
    inliers: float  # their share inside the consistency limit
    margin: float  # `rival_margin` over the minima of other yaw basins


def best_minimum(sols: list[LmResult], problem: StartProblem) -> StartMinimum:
    """The acceptance rule of every start solve on the local minima `sols` of `problem`:
    the best one's consistency (`start_consistent`) and its margin over the best rival, a
    minimum whose yaw lies more than RIVAL_SEPARATION away (`rival_margin`); a start
    needs both (consistent, margin >= RIVAL_MARGIN)."""
    n_r = len(problem.rr)
    sols = sorted(sols, key=lambda s: s.cost)
    best = sols[0]
    yaw_best = _wrap(best.x[3])
    rival = [s.cost for s in sols[1:] if abs(_wrap(s.x[3] - yaw_best)) > RIVAL_SEPARATION]
    consistent, mad, inliers = start_consistent(best.fun[:n_r], float(np.median(problem.rr)),
                                                problem.sig)
    return StartMinimum(best, consistent, mad, inliers, rival_margin(best.cost, rival))


def start_consistent(res: F64, median_range: float, sig: float) -> tuple[bool, float, float]:
    """The consistency rule of every start solve: residuals `res` (in range sigmas `sig`, m)
    whose robust spread (1.4826 MAD) is within the larger of 3 sigmas and _MAX_MAD_REL of
    the median range (`median_range`, m; on large sites range errors grow with the range:
    multipath, scale), with at least 60 % of them inside it. (consistent, MAD, inlier
    share)."""
    mad = float(np.median(np.abs(res))) * 1.4826
    lim = max(3.0, _MAX_MAD_REL * median_range / sig)
    inliers = float(np.mean(np.abs(res) < lim))
    return mad <= lim and inliers >= 0.6, mad, inliers


def rival_margin(best_cost: float, rival_costs: list[float]) -> float:
    """Chi-square (twice the cost difference, costs in range sigmas squared) by which the
    best start solution beats the best rival (a minimum of another basin); inf without
    one. The rule of every start solve: a start needs RIVAL_MARGIN."""
    return 2.0 * (min(rival_costs) - best_cost) if rival_costs else math.inf


def fit_line(ts: F64, ps: F64, sig: float) -> tuple[F64, F64]:
    """Robust straight-line fit p(t) = p + v t to fixes `ps` (K,D) m at times `ts` (K,) s
    (IRLS, Huber at 2 `sig` m, five rounds): (coef (2,D): p at t = 0 and v m/s, the final
    square-root weights (K,))."""
    a_mat = np.column_stack([np.ones_like(ts), ts])
    w = np.ones(len(ts))
    for _ in range(5):
        aw = a_mat * w[:, None]
        coef, *_ = np.linalg.lstsq(aw, ps * w[:, None], rcond=None)
        res = np.linalg.norm(ps - a_mat @ coef, axis=1)
        w = np.sqrt(np.where(res < 2 * sig, 1.0, 2 * sig / np.maximum(res, 1e-9)))
    return coef, w


def _heading_seeds(prior: tuple[F64, float] | None, tf: F64, pf: F64, lev0: F64, solve_v: bool,
                   n_unk: int, i_v: int, sig: float) -> list[F64]:
    """The heading solve's start points: _N_SEEDS headings evenly around the circle, the
    base placed so the tag sits at the prior fix (else the first fixes' median, map
    frame m), and the velocity (when solved) from the line through the fixes of the
    window's first _UWB_TRACK_S (`fit_line`, range sigma `sig` m)."""
    tag_seed = prior[0] if prior is not None else np.median(pf[:3], axis=0)
    v_seed = np.zeros(3)
    first = tf <= tf[0] + _UWB_TRACK_S
    if solve_v and np.ptp(tf[first]) > 0:
        v_seed = fit_line(tf[first] - tf[0], pf[first], sig)[0][1]
    seeds = []
    for yaw_s in np.linspace(-np.pi, np.pi, _N_SEEDS, endpoint=False):
        x0 = np.zeros(n_unk)
        x0[:3] = tag_seed - rot_z(yaw_s) @ lev0
        x0[3] = yaw_s
        if solve_v:
            x0[i_v:i_v + 3] = v_seed
        seeds.append(x0)
    return seeds


def _last_standstill(wheel: tuple, w_start: int, t_ns: int,
                     min_s: float) -> tuple[int, int] | None:
    """[start, end) ns of the last standstill of the wheels (every sample still,
    `start.wheels_still`, at least `min_s` s long) that ended after w_start and
    before t_ns, or None."""
    from uwbfuse.positioning.start import wheels_still

    t, v, om = wheel
    sel = t <= t_ns
    t, v, om = t[sel], v[sel], om[sel]
    if len(t) < 3:
        return None
    still = wheels_still(v, om)
    # runs of still samples j..k (k not the newest: the standstill has ended); a sample
    # averages the interval that ends at its stamp, so run j..k is still over (t[j-1], t[k]]
    edge = np.diff(np.concatenate([[0], still.astype(np.int8), [0]]))
    first, last = np.flatnonzero(edge == 1), np.flatnonzero(edge == -1) - 1
    for j, k in zip(first[::-1].tolist(), last[::-1].tolist(), strict=True):
        if k == len(t) - 1:
            continue
        if t[k] <= w_start:
            return None
        s0 = int(t[j - 1]) if j > 0 else int(t[0])
        if t[k] - s0 >= min_s * NS_PER_S:
            return s0, int(t[k])
    return None


def _wrap(a: float) -> float:
    """Angle wrapped to [-pi, pi), rad."""
    return float((a + math.pi) % (2 * math.pi) - math.pi)
