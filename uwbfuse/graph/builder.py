# SPDX-License-Identifier: BSD-3-Clause
"""Incremental construction of the fusion graph, one keyframe at a time.

Keyframes sit on a fixed grid (config.graph.keyframe_rate) starting at the initial state's
time. Keyframe k holds X(k) (and V(k), B(k) when the log has an IMU). Building keyframe k
adds: the IMU factor (CombinedImuFactor over [t_{k-1}, t_k]), the wheel factor (a
BetweenFactorPose3 from the integrated twist), the soft planar prior, and every range with
a stamp in [t_{k-1}, t_k), each attached to X(k-1) through the transform
`delta(t_{k-1} -> t_range) * tag_in_base`, where delta is the motion of the base frame from
the keyframe to the range's own time according to the wheel track (or the IMU prediction
from the keyframe's current state estimate). So every range is used at its own time, with
native factors only.

The builder is shared by the online smoother (which feeds each keyframe to a fixed-lag
iSAM2) and the batch solver (which also keeps every factor: `record=True`).
"""

from __future__ import annotations

import bisect
import copy
import logging
import math
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import gtsam
import numpy as np

from uwbfuse.config import Config, GraphConfig
from uwbfuse.constants import (
    ANCHOR_SIGMA,
    GYRO_HOLD_AGE_S,
    IMU_INFLATION_MAX_LOG2,
    IMU_INFLATION_START_NO_WHEELS_LOG2,
    LOG_OUTLIER,
    LOS_SIGMA_PRIOR_RANGES,
    MAX_SCALE,
    MIN_PREQUENTIAL_RANGES,
    MIN_WEIGHT,
    MOTION_ACCEL_DENSITY_START,
    NORMAL_MAD_SCALE,
    ONLINE_ANCHOR_BIAS_SIGMA,
    ONLINE_COMMON_BIAS_SIGMA,
    ONLINE_MAX_START_SPEED,
    PREQUENTIAL_WINDOW,
    PREQUENTIAL_Z,
    REPEAT_WINDOW_NS,
    SCALE_BLOCK,
    SIGMA_LOS_MIN,
    UNOBSERVED_COMMON_BIAS_SIGMA,
    VIRTUAL_BIAS_SIGMA,
    WHEEL_HUBER_K,
    WHEEL_SCALE_MAX_ERROR,
    WHEEL_SCALE_SIGMA,
)
from uwbfuse.graph import imu as imu_mod
from uwbfuse.graph.keys import B, C, D, L, V, X, nlos_key
from uwbfuse.graph.noise import diagonal, pose_sigmas, range_noise_maker, robust_weight
from uwbfuse.graph.pose_factor import PoseQueue, pose_factors
from uwbfuse.graph.rest import RestEvidence
from uwbfuse.graph.uwb import (
    los_bias_key,
    nlos_state_factors,
    range_factor_keyed,
    robust_log_density,
)
from uwbfuse.graph.values import insert_bias, insert_double, insert_pose3
from uwbfuse.graph.wheel import (
    FEW_QUERIES,
    WheelTrack,
    between_factor,
    between_factors,
    planar_covariance6,
    se2_between,
    se2_to_pose3,
    wheel_scale_evidence,
)
from uwbfuse.nlos import (
    NO_PREVIOUS_RANGE,
    NlosModel,
    hmm_filter_by_anchor,
    jump_log_likelihoods,
    residual_jumps_by_anchor,
    switch_probabilities,
)
from uwbfuse.positioning.initialisation import applied_lever, range_scale_applies
from uwbfuse.positioning.nlos_classifier import RangePriors
from uwbfuse.positioning.start import anchors_observe_height, planar_height
from uwbfuse.streams import NS_PER_S, AnchorMap

log = logging.getLogger(__name__)



@dataclass
class Increment:
    """New factors, new values and key timestamps (s since the first keyframe) of one step."""

    graph: gtsam.NonlinearFactorGraph = field(default_factory=gtsam.NonlinearFactorGraph)
    values: gtsam.Values = field(default_factory=gtsam.Values)
    stamps: dict[int, float] = field(default_factory=dict)
    # range factors to review later: (review batch, positions of each range's factors)
    reviews: list[tuple[ReviewBatch, list[list[int]]]] = field(default_factory=list)
    remove: list[int] = field(default_factory=list)  # smoother factor indices to remove
    # reviewed ranges whose factors were replaced: (batch, range, positions of new factors)
    replaced: list[tuple[ReviewBatch, int, list[int]]] = field(default_factory=list)

    def merge(self, other: Increment) -> None:
        """Append `other` (factor positions of its reviews shift by this graph's size)."""
        off = self.graph.size()
        self.graph.push_back(other.graph)
        self.values.insert(other.values)
        self.stamps.update(other.stamps)
        self.remove.extend(other.remove)
        for batch, slots in other.reviews:
            self.reviews.append((batch, [[p + off for p in ps] for ps in slots]))
        for batch, j, ps in other.replaced:
            self.replaced.append((batch, j, [p + off for p in ps]))


@dataclass
class ReviewBatch:
    """Ranges of one keyframe interval, re-classified while they are in the lag window."""

    ka: int  # keyframe the ranges are attached to
    anchor: np.ndarray
    z: np.ndarray
    seg: np.ndarray
    tag_kf: np.ndarray
    prior: np.ndarray  # HMM prior P(NLOS) at insertion
    g: np.ndarray  # responsibility used for the factors
    record: int  # index of the batch in RangeRecords
    t_ns: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # range stamps
    # the learned classifier's NLOS log-odds per range (nats; 0 without a classifier)
    evidence: np.ndarray = field(default_factory=lambda: np.zeros(0))
    # each range's share of one independent range's evidence (`rest.RestEvidence`)
    ess: np.ndarray = field(default_factory=lambda: np.zeros(0))
    # each range's factors' share of their information (`GraphBuilder.range_factors`)
    share: np.ndarray | None = None
    factors: list[list[int]] = field(default_factory=list)  # smoother indices per range
    counted: bool = False  # its smoothed residuals have gone into `add_smoothed_residuals`


@dataclass
class RangeRecords:
    """Every range put in the graph (for batch EM and the outlier report)."""

    k: list[np.ndarray] = field(default_factory=list)
    anchor: list[np.ndarray] = field(default_factory=list)
    z: list[np.ndarray] = field(default_factory=list)
    t_ns: list[np.ndarray] = field(default_factory=list)
    tag_in_kf: list[np.ndarray] = field(default_factory=list)
    g_online: list[np.ndarray] = field(default_factory=list)
    w_online: list[np.ndarray] = field(default_factory=list)
    r_online: list[np.ndarray] = field(default_factory=list)
    evidence: list[np.ndarray] = field(default_factory=list)  # classifier log-odds, nats
    _forgotten: int = 0  # entries before this one have been emptied (`forget`)

    def forget(self, before_k: int) -> None:
        """Empty the records of keyframes before `before_k` (live use: their ranges are out
        of every window); the entries stay, empty, so record indices keep their meaning."""
        i = self._forgotten
        names = ("k", "anchor", "z", "t_ns", "tag_in_kf", "g_online", "w_online", "r_online",
                 "evidence")
        empty: dict[str, np.ndarray] = {}  # one shared empty array per column (a view
        # `x[:0]` would keep x alive)
        while i < len(self.k) and (len(self.k[i]) == 0 or int(self.k[i][0]) < before_k):
            for name in names:
                col = getattr(self, name)
                if name not in empty:
                    empty[name] = np.zeros((0, *col[i].shape[1:]), col[i].dtype)
                col[i] = empty[name]
            i += 1
        self._forgotten = i

    def arrays(self) -> dict[str, np.ndarray]:
        if not self.k:
            return {"k": np.zeros(0, np.int64), "anchor": np.zeros(0, np.int64),
                    "z": np.zeros(0), "t_ns": np.zeros(0, np.int64),
                    "tag_in_kf": np.zeros((0, 3)), "g_online": np.zeros(0),
                    "w_online": np.zeros(0), "r_online": np.zeros(0),
                    "evidence": np.zeros(0)}
        return {name: np.concatenate(getattr(self, name)) for name in
                ("k", "anchor", "z", "t_ns", "tag_in_kf", "g_online", "w_online", "r_online",
                 "evidence")}


@dataclass
class WheelRecords:
    """Every wheel factor of the recorded (batch) graph, so that batch can rebuild them with
    a calibrated odometry scale: keyframe pair (k, k + 1), planar delta (x m, y m, theta
    rad) in the base frame at k as integrated (scale 1), its (x, y, theta) covariance, and
    the factor's index in `GraphBuilder.full_graph`."""

    k: list[int] = field(default_factory=list)
    delta: list[np.ndarray] = field(default_factory=list)
    cov: list[np.ndarray] = field(default_factory=list)
    index: list[int] = field(default_factory=list)
    out_of_plane: tuple[float, float, float] = (0.01, 0.01, 0.01)

    def arrays(self) -> dict[str, np.ndarray]:
        if not self.k:
            return {"k": np.zeros(0, np.int64), "delta": np.zeros((0, 3)),
                    "cov": np.zeros((0, 3, 3)), "index": np.zeros(0, np.int64)}
        return {"k": np.asarray(self.k, np.int64), "delta": np.asarray(self.delta),
                "cov": np.asarray(self.cov), "index": np.asarray(self.index, np.int64)}


@dataclass
class RecentMotion:
    """The motion factors (the IMU factor first, then the wheel factor and the planar
    prior; no external-pose factors) and the ranges of the newest `keep` keyframe
    intervals, for the online IMU noise fit over the data received so far
    (`noise_fit.fit_imu_window`). `ka[i]` is the first keyframe of interval i; the ranges
    are raw (anchor index, metres) with the tag in the frame of their keyframe."""

    keep: int
    ka: deque[int] = field(default_factory=deque)
    factors: deque[list[gtsam.NonlinearFactor]] = field(default_factory=deque)
    ranges: deque[tuple[np.ndarray, np.ndarray, np.ndarray]] = field(default_factory=deque)
    imu: imu_mod.ImuRecords = field(default_factory=imu_mod.ImuRecords)

    def add(self, ka: int, factors: list[gtsam.NonlinearFactor],
            bias: gtsam.imuBias.ConstantBias,
            pieces: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]) -> None:
        """Keyframe interval `ka` -> `ka` + 1: its motion factors, the bias, pieces and
        dropout covariance of its IMU factor (`factors[0]`; `ImuRecords.add`); the oldest
        interval beyond `keep` leaves."""
        self.ka.append(ka)
        self.factors.append(factors)
        self.ranges.append((np.zeros(0, np.int64), np.zeros(0), np.zeros((0, 3))))
        self.imu.add(ka, -1, bias, *pieces)
        while len(self.ka) > self.keep:
            self.ka.popleft()
            self.factors.popleft()
            self.ranges.popleft()
        self.imu.drop_before(self.ka[0])

    def add_ranges(self, ka: int, anchor: np.ndarray, z: np.ndarray, tag: np.ndarray) -> None:
        """The ranges attached to keyframe `ka` (the newest interval's first keyframe)."""
        if self.ka and self.ka[-1] == ka:
            self.ranges[-1] = (anchor, z, tag)


def held_anchor_bias_sigma(configured: float, cap: float) -> float:
    """Per-anchor range bias std (m) where the graph holds it tighter than configured: the
    smaller of `configured` and `cap`, unless `configured` was widened past the default
    (anchors known to differ by more: then it is used as given)."""
    if configured > GraphConfig.model_fields["range_bias_anchor_sigma"].default:
        return configured
    return min(configured, cap)


class ResidualWindow:
    """The last `size` range residuals and responsibilities, handed out every `every`."""

    def __init__(self, size: int = 3000, every: int = 200) -> None:
        self.size, self.every = size, every
        self._r: list[np.ndarray] = []
        self._g: list[np.ndarray] = []
        self._since = 0

    def add(self, r: np.ndarray, g: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        """Append; return (residuals, responsibilities) of the window when one is due."""
        self._r.append(r)
        self._g.append(g)
        self._since += len(g)
        if self._since < self.every:
            return None
        rr = np.concatenate(self._r)[-self.size:]
        gg = np.concatenate(self._g)[-self.size:]
        self._r, self._g = [rr], [gg]
        self._since = 0
        return rr, gg




class MedianRing:
    """The last `size` values (NaN: none yet) and the median of the finite ones, kept in
    sorted order as they come and go (bisect): np.median's partition of the whole ring
    per keyframe was a third of the online range-model scoring. The same value as
    np.median (the same order statistics; of two, their sum halved)."""

    def __init__(self, size: int) -> None:
        self._ring = [math.nan] * size
        self._i = 0
        self._sorted: list[float] = []

    def add(self, values: list[float]) -> None:
        """Values in order; each replaces the oldest once the ring is full."""
        for x in values:
            old = self._ring[self._i]
            if math.isfinite(old):
                del self._sorted[bisect.bisect_left(self._sorted, old)]
            if math.isfinite(x):
                bisect.insort(self._sorted, x)
            self._ring[self._i] = x
            self._i = (self._i + 1) % len(self._ring)

    def median(self) -> float | None:
        """Median of the finite values held, None without any."""
        v = self._sorted
        h = len(v) // 2
        if not v:
            return None
        return v[h] if len(v) % 2 else (v[h - 1] + v[h]) / 2


def robust_los_sigma(r: np.ndarray, g: np.ndarray, prior: float, n0: float) -> float | None:
    """LOS sigma (m) from the MAD of LOS residuals `r` (m; responsibility g < 0.5, |r| < 1 m),
    the prior counting as n0 ranges; within [SIGMA_LOS_MIN, prior]."""
    r = r[(g < 0.5) & (np.abs(r) < 1.0)]
    if len(r) < 20:
        return None
    # scipy.stats.median_abs_deviation gives the same value but costs ~275 us a call
    # against ~30 us (its array-API wrapper); called twice per keyframe it was 12 % of isam2
    mad = NORMAL_MAD_SCALE * float(np.median(np.abs(r - np.median(r))))
    s = math.sqrt((len(r) * mad**2 + n0 * prior**2) / (len(r) + n0))
    return min(max(s, SIGMA_LOS_MIN), prior)


_ROT_IDENTITY = gtsam.Rot3()  # the range factors' tag offset is a pure translation


class GraphBuilder:
    """Turns buffered sensor data into keyframes and factors (see the module docstring)."""

    def __init__(
        self,
        config: Config,
        anchors: AnchorMap,
        streams: frozenset[str],
        start: Any,
        imu: imu_mod.ImuBuffer,
        wheel: WheelTrack,
        record: bool,
        seeding: bool | None = None,
        recent_s: float | None = None,
        rest: RestEvidence | None = None,
    ) -> None:
        """Declares the builder's state, group by group (`_init_*`); every attribute the
        smoother reads is set here once. `recent_s`: keep the newest seconds of motion
        factors and ranges for the online IMU noise fit (`recent`), where one runs (the
        IMU noise or the constant-velocity prior's density `auto`, with ranges). `rest`:
        the standstill tracker that weighs each range's LOS/NLOS evidence and holds the
        base at rest (None: every range counts as independent, no zero velocity)."""
        self.cfg = config
        self.g = config.graph
        self.anchors = anchors
        self.has_wheel = "wheel" in streams
        self.has_pose = "pose" in streams  # a localiser's absolute poses (`[topics] pose`)
        # neither IMU nor wheels: a constant-velocity prior carried by a virtual IMU (the
        # IMU factor path with V and B keys; `imu.motion_prior_params`)
        self.cv_motion = "imu" not in streams and not self.has_wheel
        self.has_imu = "imu" in streams or self.cv_motion
        self.planar = self.g.planar == "on" or (self.g.planar == "auto" and self.has_wheel)
        # the ranges tell a common range offset from the position (`class_offset`): the
        # height is held, or the anchors spread off one plane enough to observe it
        self.offset_observable = self.planar or anchors_observe_height(anchors.positions)
        self.period_ns = round(NS_PER_S / self.g.keyframe_rate)
        self.t0 = int(start.t_ns)
        self.k = -1
        self.start = start
        self.imu = imu
        self.wheel = wheel
        self.tag = applied_lever(config.extrinsics.tag_in_base, frozenset(streams))
        self.with_bias = self.g.estimate_range_bias
        self.nlos = self.g.nlos
        self.rest = rest
        self.z0 = planar_height(anchors, float(start.position[2]))
        self._planar_noise: gtsam.noiseModel.Diagonal | None = None  # `_planar_prior`'s
        self._init_nlos_state()
        # the IMU noise inflation of the factors built from now on (`set_imu_inflation`).
        # `auto` with ranges starts loose until the log has shown its noise (`noise_fit`):
        # with wheels as loose as the fit may go (a tight IMU factor at a start still
        # uncertain is ill-conditioned, a loose one costs little while the wheels carry the
        # motion and the ranges hold the track); without wheels the IMU is the only motion
        # model, so no looser than the loosest real IMU measured
        # (IMU_INFLATION_START_NO_WHEELS_LOG2). Without ranges nothing absolute tells the
        # noise: the configured one
        setting = self.g.imu_noise_inflation
        ranged = "uwb" in streams and len(anchors) > 0
        fit = setting == "auto" and "imu" in streams and ranged
        # without IMU and wheels the factor is on the constant-velocity prior's
        # acceleration density (`motion_prior_params`), fitted alike from 1 (`auto`)
        cv_fit = self.cv_motion and self.g.motion_accel_density == "auto" and ranged
        start_log2 = (IMU_INFLATION_MAX_LOG2 if self.has_wheel
                      else IMU_INFLATION_START_NO_WHEELS_LOG2)
        self.imu_inflation = (2.0 ** start_log2 if fit
                              else 1.0 if setting == "auto" or self.cv_motion
                              else float(setting))
        # with wheels, from GYRO_HOLD_AGE_S after the start until the first fit, the gyroscope's
        # white noise is held at its configured density (`_hold_gyro`); `gyro_hold`: still
        # to come (None: never or over)
        self.gyro_hold: bool | None = False if fit and self.has_wheel else None
        self.pim_params = self._preintegration_params()
        # the newest keyframes for the online IMU noise fit (`recent_s` s of them), or None
        self.recent = (RecentMotion(max(round(recent_s * self.g.keyframe_rate), 1),
                                    imu=imu_mod.ImuRecords(params_at=self._cv_params()))
                       if recent_s is not None and (fit or cv_fit) else None)
        self._init_estimate(start)
        self._init_pending()
        self._init_records(record, seeding)
        self._init_range_scale(start)
        self._init_wheel_scale()
        self._init_online_choice()
        # what every range factor takes: its noise model maker, each anchor's L(a) and LOS
        # bias key (`range_factors`)
        self._range_keys = (
            range_noise_maker(config.uwb.robust_kernel, config.uwb.kernel_threshold),
            [L(a) for a in range(len(anchors))],
            [los_bias_key(a, self.with_bias) for a in range(len(anchors))])

    def _preintegration_params(self) -> gtsam.PreintegrationCombinedParams | None:
        """The IMU factors' preintegration parameters: the constant-velocity prior's virtual
        IMU without IMU and wheels, the configured (inflated) IMU noise with an IMU, else
        None (wheels only)."""
        if self.cv_motion:
            return self.motion_prior_params(self.imu_inflation)
        if self.has_imu:
            return imu_mod.preintegration_params(self.cfg.imu, self.cfg.extrinsics,
                                                 self.imu_inflation,
                                                 1.0 if self.gyro_hold else None)
        return None

    def motion_accel_density(self, factor: float) -> float:
        """The constant-velocity prior's acceleration density (m/s^2/sqrt(Hz)) at `factor`
        times the configured one (MOTION_ACCEL_DENSITY_START where `graph.
        motion_accel_density = "auto"`: the online pass and batch fit the factor,
        `noise_fit`)."""
        density = self.g.motion_accel_density
        return factor * (MOTION_ACCEL_DENSITY_START if density == "auto" else float(density))

    def motion_prior_params(self, factor: float) -> gtsam.PreintegrationCombinedParams:
        """The constant-velocity prior's virtual IMU (`imu.motion_prior_params`) at
        `motion_accel_density(factor)`."""
        return imu_mod.motion_prior_params(self.motion_accel_density(factor),
                                           self.g.motion_turn_density, self.cfg.imu.gravity)

    def _cv_params(self) -> Callable[[float], gtsam.PreintegrationCombinedParams] | None:
        """`motion_prior_params` for the records of the constant-velocity prior's factors
        (`imu.ImuRecords.params_at`), None where the factors are a real IMU's."""
        return self.motion_prior_params if self.cv_motion else None

    def set_imu_inflation(self, inflation: float) -> None:
        """The IMU factors built from now on (and the predictions) take the `[imu]` noise
        times `inflation`, the gyroscope's white noise included; without IMU and wheels,
        the constant-velocity prior's acceleration density times `inflation`; ends
        `_hold_gyro`."""
        held = self.gyro_hold is not None
        self.gyro_hold = None
        if not self.has_imu or (inflation == self.imu_inflation and not held):
            return
        self.imu_inflation = float(inflation)
        self.pim_params = self._preintegration_params()

    def _hold_gyro(self) -> None:
        """With wheels and the IMU noise still to be fitted (`auto`), from GYRO_HOLD_AGE_S
        after the start: the IMU factors keep the loose start inflation but the gyroscope's
        white noise at its configured density, until the first fit (`set_imu_inflation`).

        The wheel factor's robust kernel rejects a slip only against an independent yaw
        rate, which a gyroscope at 256x its noise does not give: a slip in the graph's
        first 10 s turned the track (factory seed 2: two slips of -40 and -37 degrees,
        0.15 m ATE). Not from the start: a tight gyroscope with the start's keyframes
        in the window left iSAM2 indeterminate (room seed 0; docs/results.md, "A wheel slip
        before the first IMU noise fit"); not from one lag, which at lag 10 is the first
        fit's own time (docs/results.md, session 40)."""
        if self.gyro_hold is False and self.k >= 0 and self.stamp(self.k) >= GYRO_HOLD_AGE_S:
            self.gyro_hold = True
            self.pim_params = self._preintegration_params()

    def complete_imu_records(self, inflation: float) -> None:
        """batch, once the whole log is in: the recorded IMU factors at the noise
        inflation `inflation` (`noise_fit.fit_imu_noise`), and the predictions after
        the last keyframe with them."""
        rec = self.imu_records
        if self.full_graph is None or not rec.k:
            return
        cov = rec.covariances(self.cfg.imu, self.cfg.extrinsics, inflation)
        for idx, factor in zip(rec.index, rec.factors_at(self.full_graph, cov), strict=True):
            self.full_graph.replace(idx, factor)
        self.set_imu_inflation(inflation)

    def _init_nlos_state(self) -> None:
        """The NLOS model and each anchor's online NLOS state (the newest excess state's
        segment, estimate and stamp)."""
        self.mixture = NlosModel.from_config(self.cfg)
        self.mixture_prior = copy.copy(self.mixture)
        # LOS sigma of the range factors, from residuals at the smoothed estimate (the
        # mixture's is the one-step prediction's, wider by the prediction error)
        self.smoothed_sigma_los: float | None = None
        self.smoothed_robust_sigma: float | None = None  # the same over all ranges, uncapped
        self._smoothed_window = ResidualWindow()
        m = len(self.anchors)
        self.anchor_p = np.full(m, self.mixture.p_nlos)
        self.range_bias = np.zeros(m)
        self.seg_ns = round(self.mixture.segment_s * NS_PER_S)
        self.e_seg = np.full(m, -1, dtype=np.int64)  # newest NLOS state segment per anchor
        self.e_est = np.zeros(m)  # its estimate (m)
        self.e_stamp = np.zeros(m)  # its smoother timestamp (s since t0)
        # NLOS states in the current smoother: (anchor, segment) -> smoother timestamp (s)
        self.e_created: dict[tuple[int, int], float] = {}
        self.review = True  # delayed re-classification of ranges (online)

    def _init_estimate(self, start: Any) -> None:
        """The newest keyframe's estimate (map frame), from the start; the smoother updates it."""
        self.pose = gtsam.Pose3(gtsam.Rot3(np.asarray(start.R_map_base, dtype=np.float64)),
                                np.asarray(start.position, dtype=np.float64))
        self.vel = np.asarray(start.velocity, dtype=np.float64).copy()
        self.bias = gtsam.imuBias.ConstantBias(np.asarray(start.accel_bias, dtype=np.float64),
                                               np.asarray(start.gyro_bias, dtype=np.float64))

    def _init_pending(self) -> None:
        """The queues of data waiting for the keyframes to come: ranges, their classifier
        priors, external poses."""
        self._rt: list[np.ndarray] = []  # pending ranges: (t, anchor, z) chunks
        self._ra: list[np.ndarray] = []
        self._rz: list[np.ndarray] = []
        self._rq: list[np.ndarray] = []  # the classifier's P(NLOS) of the pending ranges
        # the learned NLOS classifier's P(NLOS) per range (`use_range_priors`), or None
        self.priors: RangePriors | None = None
        self.poses = PoseQueue(self.t0)  # external poses for the keyframes to come

    def _init_records(self, record: bool, seeding: bool | None) -> None:
        """What the online pass records for isam2-smoothed and batch (`record`: the whole graph)."""
        self.record = record
        # the online pass only seeds batch (default: whenever the graph is recorded): its
        # anchor offsets keep the configured prior (see `first`)
        self.seeding = record if seeding is None else seeding
        self.records = RangeRecords()
        # roll, pitch (rad) and z (m) sigmas of the wheel factor
        self.wheel_records = WheelRecords(
            out_of_plane=(0.01, 0.01, 0.01) if self.planar else (0.2, 0.2, 0.2))
        # the IMU factors, or the constant-velocity prior's (its virtual IMU's noise fitted
        # alike, `noise_fit.imu_family`)
        self.imu_records = imu_mod.ImuRecords(params_at=self._cv_params())
        self.full_graph = gtsam.NonlinearFactorGraph() if record else None
        # indices in `full_graph` of the external-pose factors (`pose_factor`)
        self.pose_index: list[int] = []
        self.full_values = gtsam.Values() if record else None

    def _init_wheel_scale(self) -> None:
        """The online odometry scale factors (v, omega) its wheel factors are built with
        (`learn_wheel_scale`; 1 until the smoothed track has shown them). Batch's seeding
        pass keeps them at 1: batch fits its own over the whole log (`offline._WheelScale`)."""
        self.wheel_scale = np.ones(2)
        self.online_wheel_scale = (self.has_wheel and self.g.estimate_wheel_scale
                                   and not self.seeding)
        self._ws_num = np.zeros(2)
        self._ws_den = np.zeros(2)
        # integrated (scale 1) delta and covariance of each wheel factor X(k) -> X(k + 1)
        # not yet learnt from, by k (bounded: `learn_wheel_scale` drops what leaves the lag)
        self._wheel_raw: dict[int, tuple[np.ndarray, np.ndarray]] = {}

    def learn_wheel_scale(self, poses: dict[int, gtsam.Pose3], upto: int) -> None:
        """Add the evidence of the wheel factors X(k) -> X(k + 1), k + 1 <= `upto`, against
        the smoothed keyframe poses `poses` (map frame; as they leave the fixed lag) to the
        online odometry scales: the recursive form of batch's refit (`wheel_scale_evidence`,
        prior N(1, WHEEL_SCALE_SIGMA^2)); a radius or track error is a constant, so each
        keyframe pair adds its share of all the evidence. Factors whose poses are gone
        (re-anchored) are dropped."""
        if not self.online_wheel_scale:
            return
        ks = [k for k in self._wheel_raw if k + 1 <= upto]
        use = ([k for k in ks if k in poses and k + 1 in poses]
               if self.wheel_scale_applies() else [])
        if use:
            rot = np.array([[poses[k].rotation().matrix() for k in use],
                            [poses[k + 1].rotation().matrix() for k in use]])
            trans = np.array([[poses[k].translation() for k in use],
                              [poses[k + 1].translation() for k in use]])
            delta = np.array([self._wheel_raw[k][0] for k in use])
            cov = np.array([self._wheel_raw[k][1] for k in use])
            num, den = wheel_scale_evidence(rot[0], trans[0], rot[1], trans[1], delta, cov,
                                            self.wheel_scale, WHEEL_HUBER_K)
            self._ws_num += num
            self._ws_den += den
            prior = WHEEL_SCALE_SIGMA**-2
            self.wheel_scale = np.clip((self._ws_num + prior) / (self._ws_den + prior),
                                       1.0 - WHEEL_SCALE_MAX_ERROR,
                                       1.0 + WHEEL_SCALE_MAX_ERROR)
        for k in ks:
            del self._wheel_raw[k]

    def _odometry_scale(self) -> np.ndarray | None:
        """The (x, y, theta) factors of the online odometry scales where they apply
        (`wheel_scale_applies`), else None (the track as integrated)."""
        if not (self.online_wheel_scale and self.wheel_scale_applies()):
            return None
        sv, sw = float(self.wheel_scale[0]), float(self.wheel_scale[1])
        return np.array([sv, sv, sw])

    def odometry(self, rel: np.ndarray) -> np.ndarray:
        """Wheel-track motions rel (N,3) (x m, y m, theta rad, base frame) at the online
        odometry scales where they apply, else as integrated."""
        c = self._odometry_scale()
        return rel if c is None else rel * c

    def wheel_scale_applies(self) -> bool:
        """Batch's rule online: the odometry scale is learnt and used only under the NLOS
        mixture, where ranges float on excess states and the track follows the odometry;
        under a robust range model (configured, or the online prequential verdict) every
        range holds the track, and a scale fitted to that track only moves what the ranges
        placed (docs/results.md, "Batch against the plain estimator: the wheel-scale
        refit under a robust range model")."""
        return self.nlos and not self.robust_online and self.prequential_verdict() != "robust"

    def _init_range_scale(self, start: Any) -> None:
        """The per-anchor range scale errors and whether they are estimated (`auto`: from
        the start solve's common scale)."""
        m = len(self.anchors)
        self.scale = np.zeros(m)  # per-anchor range scale error k: z = (1 + k) d + b
        self.with_scale = self.g.estimate_range_scale is True
        start_k = float(getattr(start, "range_scale", 1.0)) - 1.0
        if self.g.estimate_range_scale == "auto" and range_scale_applies(
                start_k, self.anchors, np.asarray(start.position)):
            # The start solve fits one common scale with the pose; residuals after the
            # fact cannot show it (the trajectory absorbs a scale error), so `auto` decides
            # here, as the filters do.
            self.with_scale = True
            log.info("the start solve finds ranges %.1f %% %s than the distance: "
                     "estimating per-anchor range scales", 100 * abs(start_k),
                     "longer" if start_k > 0 else "shorter")
        if self.with_scale:
            self.scale[:] = float(np.clip(start_k, -MAX_SCALE, MAX_SCALE))
        self._sc_num = np.zeros(m)
        self._sc_den = np.zeros(m)
        self._sc_n = np.zeros(m)
        self._sc_info = np.zeros(m)  # sum(w h^2) of every step so far (m^2): `_update_scale`

    def _init_online_choice(self) -> None:
        """Range bookkeeping (dropped, repeated, jumps) and the online range-model choice's
        prequential scores."""
        m = len(self.anchors)
        self.dropped_ranges = 0
        self.repeated_ranges = 0
        self._last_range: dict[int, tuple[int, float]] = {}
        self.jumps = True  # use residual jumps between consecutive ranges in the HMM
        self._jump_r = np.zeros(m)  # per anchor: last range residual (m) and its stamp
        self._jump_t = np.full(m, np.iinfo(np.int64).min // 2, dtype=np.int64)
        # per anchor: the stamp of its newest range in the chain (`switch_probabilities`)
        self._switch_t = np.full(m, NO_PREVIOUS_RANGE, dtype=np.int64)
        self._predicted_window = ResidualWindow()
        # online choice of the range model by prequential score: the log predictive density
        # (nats) of each new range under the mixture and under the robust model, summed
        self.prequential = np.zeros(2)
        self.prequential_n = 0  # ranges seen (their |residual| feeds the robust sigma)
        self._pq_n = 0  # ranges scored, and the sums of their score differences d, d^2
        self._pq_sum = 0.0
        self._pq_sum2 = 0.0
        # new ranges weighted as the robust model (no NLOS states) where it is configured;
        # `auto` keeps the mixture online (batch chooses by held-out ranges): switched online on
        # early evidence, the graph lost more where the mixture later proved right (factory)
        # than it gained where it did not (Plaza)
        self.robust_online = self.nlos and not self.g.range_model.startswith(
            ("auto", "mixture"))
        self._abs_r = MedianRing(PREQUENTIAL_WINDOW)  # |one-step residual| ring (m)
        self._robust_sigma: float | None = None  # cached robust_sigma() of the ring

    # ---------------------------------------------------------------- data
    def add_ranges(self, t_ns: np.ndarray, anchor: np.ndarray, rng: np.ndarray) -> None:
        """Queue ranges (stamps ns, anchor index, metres) for the keyframes to come.

        A range that repeats its anchor's previous value exactly within REPEAT_WINDOW_NS
        is a re-published copy (some radios publish each epoch twice) and is dropped, so it
        is not counted twice.
        """
        t_ns, anchor, rng = np.asarray(t_ns), np.asarray(anchor), np.asarray(rng)
        q = (self.priors.take(t_ns, anchor) if self.priors is not None
             else np.full(len(t_ns), np.nan))
        dup = np.zeros(len(t_ns), dtype=bool)
        for i, (t, a, r) in enumerate(zip(t_ns.tolist(), anchor.tolist(), rng.tolist(),
                                          strict=True)):
            last = self._last_range.get(a)
            if last is not None and r == last[1] and t - last[0] < REPEAT_WINDOW_NS:
                dup[i] = True
            else:
                self._last_range[a] = (t, r)
        self.repeated_ranges += int(np.count_nonzero(dup))
        t_ns, anchor, rng, q = t_ns[~dup], anchor[~dup], rng[~dup], q[~dup]
        keep = np.asarray(t_ns) >= self.t0
        self.dropped_ranges += int(np.count_nonzero(~keep))
        if keep.any():
            self._rt.append(np.asarray(t_ns, np.int64)[keep])
            self._ra.append(np.asarray(anchor, np.int64)[keep])
            self._rz.append(np.asarray(rng, np.float64)[keep])
            self._rq.append(q[keep])

    def add_poses(self, t_ns: np.ndarray, position: np.ndarray, quat_xyzw: np.ndarray,
                  covariance: np.ndarray) -> None:
        """Queue external poses (base in map, ROS-order covariance) for the keyframes."""
        self.poses.add(t_ns, position, quat_xyzw, covariance)

    def _take_ranges(
        self, t_end: int
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Pending ranges before `t_end`: stamps, anchors, ranges and classifier P(NLOS)."""
        if not self._rt:
            return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0), np.zeros(0)
        t = np.concatenate(self._rt)
        a = np.concatenate(self._ra)
        z = np.concatenate(self._rz)
        q = np.concatenate(self._rq)
        order = np.argsort(t, kind="stable")
        t, a, z, q = t[order], a[order], z[order], q[order]
        n = int(np.searchsorted(t, t_end, side="left"))
        if n < len(t):
            self._rt, self._ra, self._rz, self._rq = [t[n:]], [a[n:]], [z[n:]], [q[n:]]
        else:
            self._rt, self._ra, self._rz, self._rq = [], [], [], []
        return t[:n], a[:n], z[:n], q[:n]

    # ---------------------------------------------------------------- time
    def time_of(self, k: int) -> int:
        return self.t0 + k * self.period_ns

    def next_time(self) -> int:
        return self.time_of(self.k + 1)

    def stamp(self, k: int) -> float:
        return (self.time_of(k) - self.t0) / NS_PER_S

    # ---------------------------------------------------------------- motion
    def delta(
        self, t_a: int, t_b: np.ndarray, pose_a: gtsam.Pose3, vel_a: np.ndarray
    ) -> list[gtsam.Pose3]:
        """Base-frame motion from t_a to each t_b (>= t_a), from wheels, else IMU, else none.

        The IMU prediction starts from the state (pose_a, vel_a) at t_a and the current bias.
        """
        if self.has_wheel and len(self.wheel):
            if len(t_b) < FEW_QUERIES:  # one epoch's prediction: Python floats, bit-identical
                rel = self.wheel.between_few(t_a, np.asarray(t_b, np.int64).tolist())
            else:
                dd = self.wheel.at(np.concatenate([[t_a], t_b]).astype(np.int64))
                rel = se2_between(dd[0][None, :], dd[1:])
            return [se2_to_pose3(r) for r in self.odometry(np.asarray(rel))]
        if self.cv_motion:  # constant velocity (map frame) carried into the base frame
            step = pose_a.rotation().unrotate(np.asarray(vel_a, np.float64))
            dts = (np.asarray(t_b, np.int64) - t_a).astype(np.float64) / NS_PER_S
            return [gtsam.Pose3(gtsam.Rot3(), step * d) for d in dts.tolist()]
        if self.has_imu and self.pim_params is not None and len(self.imu):
            out = []
            nav = gtsam.NavState(pose_a, vel_a)
            pim = gtsam.PreintegratedCombinedMeasurements(self.pim_params, self.bias)
            t_cur = t_a
            inv = pose_a.inverse()
            rest = self._rest(pose_a, self.bias)
            for tb in t_b.tolist():
                gy, ac, dt = self.imu.pieces(t_cur, tb, rest)
                imu_mod.integrate(pim, gy, ac, dt)
                t_cur = max(t_cur, tb)
                out.append(inv.compose(pim.predict(nav, self.bias).pose()))
            return out
        return [gtsam.Pose3() for _ in range(len(t_b))]

    def _guess_covariance(self, guess_s: float, bias: gtsam.imuBias.ConstantBias,
                          pieces: tuple[np.ndarray, np.ndarray, np.ndarray]
                          ) -> np.ndarray | None:
        """What an IMU dropout's guess of `guess_s` seconds adds to the keyframe's IMU
        factor (`imu.guess_covariance`): the motion unseen, at the constant-velocity prior's
        densities (MOTION_ACCEL_DENSITY_START, `graph.motion_turn_density`; the filters'
        `dropout_noise` alike), where wheels carry the motion through it; None without a
        dropout or without wheels (there the still guess at the IMU's noise is the only
        motion model: session 29)."""
        if guess_s <= 0.0 or self.cv_motion or self.pim_params is None or not self.has_wheel:
            return None
        return imu_mod.guess_covariance(self.pim_params, bias, pieces, guess_s,
                                        MOTION_ACCEL_DENSITY_START,
                                        self.g.motion_turn_density)

    def _rest(self, pose: gtsam.Pose3, bias: gtsam.imuBias.ConstantBias
              ) -> Callable[[], tuple[np.ndarray, np.ndarray]]:
        """What the IMU reads through a dropout from `pose`, `bias` (`ImuBuffer.pieces`)."""
        return lambda: imu_mod.rest_reading(self.pim_params, pose.rotation(), bias)

    def tag_in_keyframe(
        self, t_a: int, t_b: np.ndarray, pose_a: gtsam.Pose3, vel_a: np.ndarray
    ) -> np.ndarray:
        """Tag antenna position (N,3) at each time t_b in the base frame at t_a (metres)."""
        if self.has_wheel and len(self.wheel):  # vectorised planar case
            return self._wheel_tag(np.array([t_a], np.int64), t_b, scaled=True)
        return np.array([d.transformFrom(self.tag) for d in self.delta(t_a, t_b, pose_a, vel_a)]
                        ).reshape(-1, 3)

    def _wheel_tag(self, t_a: np.ndarray, t_b: np.ndarray, scaled: bool = False) -> np.ndarray:
        """Tag antenna position (N,3) at each time t_b (N,) in the base frame at t_a ((N,) or
        (1,) for all) by the wheel track (metres): as integrated, or (`scaled`) at the online
        odometry scales where they apply (`odometry`)."""
        rel = se2_between(self.wheel.at(t_a), self.wheel.at(np.asarray(t_b, np.int64)))
        return self._tag_from(self.odometry(rel) if scaled else rel)

    def _tag_from(self, rel: np.ndarray) -> np.ndarray:
        """Tag antenna positions (N,3) in the base frame at t_a from the wheel track's
        motion rel (N,3) (x m, y m, theta rad) from t_a to each range's time."""
        c, s = np.cos(rel[:, 2]), np.sin(rel[:, 2])
        tx, ty, tz = self.tag
        out = np.empty((len(rel), 3))
        out[:, 0] = rel[:, 0] + c * tx - s * ty
        out[:, 1] = rel[:, 1] + s * tx + c * ty
        out[:, 2] = tz
        return out

    def use_priors(self, priors: RangePriors | None) -> None:
        """The learned NLOS classifier's per-range priors (None: the mixture's own)."""
        self.priors = priors

    def set_head(self, pose: gtsam.Pose3, vel: np.ndarray | None = None,
                 bias: gtsam.imuBias.ConstantBias | None = None,
                 range_bias: np.ndarray | None = None) -> None:
        """The newest keyframe's solved state, which `predict` and the next keyframe's
        factors start from: base pose in the map frame, velocity m/s (map), IMU bias,
        per-anchor range biases m; None keeps the current value."""
        self.pose = pose
        if vel is not None:
            self.vel = vel
        if bias is not None:
            self.bias = bias
        if range_bias is not None:
            self.range_bias = range_bias

    def predict(self, t: int) -> gtsam.Pose3:
        """Causal pose at t from the newest keyframe estimate plus odometry/IMU motion."""
        if self.k < 0:
            return self.pose
        tk = self.time_of(self.k)
        if t <= tk:
            return self.pose
        return self.pose.compose(self.delta(tk, np.array([t], np.int64), self.pose, self.vel)[0])

    def motion_noise(self, t_a: int, t_b: int) -> np.ndarray:
        """Pose3 tangent covariance (rot, trans) of the motion from t_a to t_b as `delta`
        predicts it: the wheel track's propagated noise (the wheel factor's), else the
        (real or constant-velocity virtual) IMU's white noise over the interval (rotation
        sigma_g^2 tau, translation sigma_a^2 tau^3 / 3; the velocity's own uncertainty is
        the caller's)."""
        tau = max(t_b - t_a, 0) / NS_PER_S
        if self.has_wheel and len(self.wheel):
            oop = self.wheel_records.out_of_plane
            cov = planar_covariance6(self.wheel.covariance(t_a, t_b, self.cfg.wheel), oop)
            # out-of-plane sigmas are per keyframe interval
            cov[[0, 1, 5], [0, 1, 5]] *= tau * self.g.keyframe_rate
            return cov
        if self.pim_params is not None:
            sg = float(self.pim_params.getGyroscopeCovariance()[0, 0])
            sa = float(self.pim_params.getAccelerometerCovariance()[0, 0])
            return np.diag([sg * tau] * 3 + [sa * tau**3 / 3.0] * 3)
        return np.eye(6) * 1e-12  # no motion model: the prediction is the keyframe

    # ---------------------------------------------------------------- factors
    def _planar_prior(self, k: int, pose: gtsam.Pose3) -> gtsam.NonlinearFactor:
        ypr = pose.rotation().ypr()
        mean = gtsam.Pose3(gtsam.Rot3.Ypr(float(ypr[0]), 0.0, 0.0),
                           np.array([pose.x(), pose.y(), self.z0]))
        if self._planar_noise is None:  # the config's: one (immutable) model for every prior
            big = 1e3
            self._planar_noise = diagonal(pose_sigmas(
                (self.g.planar_sigma_tilt, self.g.planar_sigma_tilt, big),
                (big, big, self.g.planar_sigma_z)))
        return gtsam.PriorFactorPose3(X(k), mean, self._planar_noise)

    def first(self) -> Increment:
        """Keyframe 0: priors from the initial state, anchors and range biases."""
        inc = Increment()
        self.k = 0
        st = self.start
        tilt = 0.05 if self.has_imu else 0.02
        # the start comes from a few seconds of data: widen its stated uncertainty
        pos_s = max(3.0 * float(st.position_sigma), 0.3)
        yaw_s = min(max(3.0 * float(st.yaw_sigma), 0.05), np.pi)
        z_s = self.g.planar_sigma_z if self.planar else max(pos_s, 0.3)
        if self.planar:
            t = self.pose.translation()
            self.pose = gtsam.Pose3(self.pose.rotation(), np.array([t[0], t[1], self.z0]))
        inc.graph.add(gtsam.PriorFactorPose3(
            X(0), self.pose, diagonal(pose_sigmas((tilt, tilt, yaw_s), (pos_s, pos_s, z_s)))))
        inc.values.insert(X(0), self.pose)
        keys = [X(0)]
        if self.planar:
            inc.graph.add(self._planar_prior(0, self.pose))
        if self.has_imu:
            # `still` says the log *started* still; the state may be taken while moving
            speed = float(np.linalg.norm(self.vel))
            if speed > ONLINE_MAX_START_SPEED:  # implausible for an indoor vehicle or walker
                log.warning("initial speed %.1f m/s is implausible: starting from rest, "
                            "velocity sigma 1 m/s", speed)
                self.vel = np.zeros(3)
                v_s = 1.0
            elif self.cv_motion:  # no sensor tells the start velocity: walking pace
                v_s = 1.0
            else:
                v_s = 0.1 if speed < 0.05 else 0.5
            inc.graph.add(gtsam.PriorFactorVector(V(0), self.vel, diagonal([v_s] * 3)))
            inc.graph.add(gtsam.PriorFactorConstantBias(
                B(0), self.bias, diagonal(self.bias_prior_sigmas())))
            inc.values.insert(V(0), self.vel)
            inc.values.insert(B(0), self.bias)
            keys += [V(0), B(0)]
        for a in range(len(self.anchors)):
            p = self.anchors.positions[a]
            inc.graph.add(gtsam.PriorFactorPoint3(L(a), p, diagonal([ANCHOR_SIGMA] * 3)))
            inc.values.insert(L(a), p)
            if self.with_bias:
                inc.values.insert(D(a), 0.0)
        if self.with_bias:
            inc.values.insert(C, 0.0)
        for key in keys:
            inc.stamps[key] = 0.0
        self._stamp_globals(inc, 0.0)
        self._record(inc)
        if self.with_bias:
            # Online, the common bias may only move slowly: at the start of a log every
            # anchor can be in NLOS at once, and a loose prior would take that shared excess
            # for a calibration offset. The batch graph gets the configured prior.
            # Likewise each anchor's offset from the common bias: a few seconds of ranges
            # barely separate it from the position, and a loosely held D(a) wanders by
            # centimetres (see ONLINE_ANCHOR_BIAS_SIGMA).
            s_on = min(self.g.range_bias_sigma, ONLINE_COMMON_BIAS_SIGMA)
            s_common = self.g.range_bias_sigma
            if not self.offset_observable:
                # the common offset and the height are one null direction of the ranges:
                # left free, the fixed-lag smoother drifts along it (docs/results.md, "The
                # common range offset where the height is free")
                s_on = s_common = UNOBSERVED_COMMON_BIAS_SIGMA
            # (not in batch's seeding pass: its EM was tuned from that seed; docs/results.md,
            # "Constants in one module")
            s_a = self.g.range_bias_anchor_sigma
            if not self.seeding:
                s_a = held_anchor_bias_sigma(s_a, ONLINE_ANCHOR_BIAS_SIGMA)
            inc.graph.add(gtsam.PriorFactorDouble(
                C, 0.0, gtsam.noiseModel.Isotropic.Sigma(1, s_on)))
            for a in range(len(self.anchors)):
                inc.graph.add(gtsam.BetweenFactorDouble(
                    C, D(a), 0.0, gtsam.noiseModel.Isotropic.Sigma(1, s_a)))
            if self.full_graph is not None:
                self.full_graph.add(gtsam.PriorFactorDouble(
                    C, 0.0, gtsam.noiseModel.Isotropic.Sigma(1, s_common)))
                for a in range(len(self.anchors)):
                    self.full_graph.add(gtsam.BetweenFactorDouble(
                        C, D(a), 0.0,
                        gtsam.noiseModel.Isotropic.Sigma(1, self.g.range_bias_anchor_sigma)))
        return inc

    def restart_priors(self, k: int, pose: gtsam.Pose3, vel: np.ndarray | None,
                       bias: gtsam.imuBias.ConstantBias | None, anchors: bool = True,
                       position_sigma: float = 0.5, velocity_sigma: float = 0.5,
                       ) -> gtsam.NonlinearFactorGraph:
        """Loose priors on keyframe k's state at `pose` (and `vel`, `bias` with an IMU)
        and (`anchors`) the anchors at their positions: where a smoother starts afresh
        (re-anchoring) or a window of the graph begins (the online IMU noise fit; batch's
        evidence windows, whose graph holds the anchor priors already). Position sigma m,
        velocity sigma m/s (map frame)."""
        graph = gtsam.NonlinearFactorGraph()
        graph.add(gtsam.PriorFactorPose3(
            X(k), pose, diagonal(pose_sigmas((0.05, 0.05, 0.2), (position_sigma,) * 3))))
        if self.has_imu and vel is not None and bias is not None:
            graph.add(gtsam.PriorFactorVector(V(k), vel, diagonal([velocity_sigma] * 3)))
            graph.add(gtsam.PriorFactorConstantBias(B(k), bias,
                                                    diagonal(self.bias_prior_sigmas())))
        for a in range(len(self.anchors) if anchors else 0):
            graph.add(gtsam.PriorFactorPoint3(L(a), self.anchors.positions[a],
                                              diagonal([ANCHOR_SIGMA] * 3)))
        return graph

    def bias_prior_sigmas(self) -> np.ndarray:
        """IMU bias prior sigmas (m/s^2, rad/s): the IMU's, or the virtual IMU's tight ones."""
        if self.cv_motion:
            return np.full(6, VIRTUAL_BIAS_SIGMA)
        return imu_mod.bias_prior_sigmas(self.cfg.imu)

    def _stamp_globals(self, inc: Increment, s: float) -> None:
        """Anchors and range biases never leave the smoother's window."""
        for a in range(len(self.anchors)):
            inc.stamps[L(a)] = s
            if self.with_bias:
                inc.stamps[D(a)] = s
        if self.with_bias:
            inc.stamps[C] = s

    def next(self) -> Increment:
        """Build keyframe k+1 (the data up to its time must have been added)."""
        self._hold_gyro()
        inc = Increment()
        k = self.k + 1
        ka = k - 1
        t_a, t_b = self.time_of(ka), self.time_of(k)
        dt = (t_b - t_a) / NS_PER_S
        pose_a, vel_a, bias_a = self.pose, self.vel, self.bias
        motion: list[gtsam.NonlinearFactor] = []  # this interval's motion factors (`recent`)
        pieces = None
        new_pose = pose_a
        new_vel = vel_a
        ranges = self._take_ranges(t_b)
        # the wheel track's motion from t_a to t_b and to the ranges' stamps, one query
        # (`WheelTrack.between`, `_wheel_tag`)
        rel = None
        if self.has_wheel and len(ranges[0]) < FEW_QUERIES:
            rel = self.wheel.between_few(t_a, [t_b, *ranges[0].tolist()])
        elif self.has_wheel:
            track = self.wheel.at(np.concatenate([[t_a, t_b], ranges[0]]).astype(np.int64))
            rel = se2_between(track[:1], track[1:])
        if self.has_imu:
            gy, ac, dts, guess_s = self.imu.pieces_with_guess(t_a, t_b,
                                                              self._rest(pose_a, bias_a))
            if len(dts) == 0:
                gy, ac, dts = np.zeros((1, 3)), np.array([[0, 0, self.cfg.imu.gravity]]), [dt]
                dts = np.asarray(dts, dtype=np.float64)
            pim = imu_mod.preintegrate(self.pim_params, bias_a, gy, ac, dts)
            guess = self._guess_covariance(guess_s, bias_a, (gy, ac, dts))
            if self.record and self.full_graph is not None:
                self.imu_records.add(ka, self.full_graph.size() + inc.graph.size(), bias_a,
                                     gy, ac, dts, guess)  # pushed by `_record` below
            factor = gtsam.CombinedImuFactor(X(ka), V(ka), X(k), V(k), B(ka), B(k), pim)
            if guess is not None:
                factor = factor.cloneWithNewNoiseModel(gtsam.noiseModel.Gaussian.Covariance(
                    np.asarray(pim.preintMeasCov()) + guess))
            motion.append(factor)
            inc.graph.add(motion[-1])
            pieces = (gy, ac, dts, guess)
            pred = pim.predict(gtsam.NavState(pose_a, vel_a), bias_a)
            new_pose, new_vel = pred.pose(), pred.velocity()
            inc.values.insert(V(k), new_vel)
            if self.rest is not None and self.rest.at_rest(t_a, t_b):
                self.zero_velocity(inc.graph, k)
            insert_bias(inc.values, B(k), bias_a)
            inc.stamps[V(k)] = self.stamp(k)
            inc.stamps[B(k)] = self.stamp(k)
        if rel is not None:
            d = np.asarray(rel[0])  # as integrated: the scale's evidence and batch's records
            c = self._odometry_scale()
            if c is not None:  # the keyframe's motion and its ranges' tags at the scales
                rel = np.asarray(rel) * c
            cov = self.wheel.covariance(t_a, t_b, self.cfg.wheel)
            oop = self.wheel_records.out_of_plane
            if self.record and self.full_graph is not None:  # pushed by `_record` below
                wr = self.wheel_records
                wr.k.append(ka)
                wr.delta.append(d)
                wr.cov.append(cov)
                wr.index.append(self.full_graph.size() + inc.graph.size())
            if self.online_wheel_scale:
                self._wheel_raw[ka] = (d, cov)
            if c is not None:
                d, cov = rel[0], cov * np.outer(c, c)
            motion.append(between_factor(X(ka), X(k), d, cov, oop, WHEEL_HUBER_K))
            inc.graph.add(motion[-1])
            wp = pose_a.compose(se2_to_pose3(d))
            if self.has_imu:
                xyz = np.array([wp.x(), wp.y(), new_pose.z()])
                new_pose = gtsam.Pose3(new_pose.rotation(), xyz)
            else:
                new_pose = wp
        if self.cv_motion:  # the virtual IMU assumes a level base: hold roll and pitch
            ypr = new_pose.rotation().ypr()
            level = gtsam.Pose3(gtsam.Rot3.Ypr(float(ypr[0]), 0.0, 0.0), new_pose.translation())
            big = 1e3
            inc.graph.add(gtsam.PriorFactorPose3(X(k), level, diagonal(pose_sigmas(
                (self.g.planar_sigma_tilt, self.g.planar_sigma_tilt, big), (big, big, big)))))
        if self.planar:
            motion.append(self._planar_prior(k, new_pose))
            inc.graph.add(motion[-1])
        if self.recent is not None and pieces is not None:
            self.recent.add(ka, motion, bias_a, pieces)
        insert_pose3(inc.values, X(k), new_pose)
        inc.stamps[X(k)] = self.stamp(k)
        t_p, p_p, q_p, c_p = self.poses.take(t_b)
        if len(t_p):  # each at its own time, through the motion since X(ka) (as ranges)
            for f in pose_factors(X(ka), p_p, q_p, c_p, self.delta(t_a, t_p, pose_a, vel_a),
                                  [self.motion_noise(t_a, int(t)) for t in t_p.tolist()],
                                  self.planar, self.cfg.pose):
                if self.record and self.full_graph is not None:  # pushed by `_record`
                    self.pose_index.append(self.full_graph.size() + inc.graph.size())
                inc.graph.add(f)
        self._record(inc)  # batch keeps the non-range factors; ranges are rebuilt by EM
        self._add_ranges(inc, ka, t_a, pose_a, vel_a, ranges,
                         None if rel is None or not len(self.wheel) else rel[1:])
        self._stamp_globals(inc, self.stamp(k))
        self.k = k
        self.pose, self.vel = new_pose, new_vel
        if self.imu is not None:
            self.imu.drop_before(t_a)
        return inc

    def complete_wheel_records(self, offset_ns: int = 0,
                               noise_scale: tuple[float, float] = (1.0, 1.0)) -> None:
        """batch, once the whole log is in: the recorded wheel factors and the ranges' tag
        offsets from the complete wheel track.

        A keyframe is built as soon as the data up to its time are in, but a wheel sample is
        the mean over the interval that ends at its stamp: the sample covering the end of
        the keyframe interval (and the later ranges of it) arrives after the keyframe, so
        the online factors extrapolate the previous sample's velocity over that stretch.
        Offline the sample is there; a wrong extrapolation (a change of speed, a sample
        stamped late) otherwise stays in batch's graph (docs/results.md, "Plaza").
        `offset_ns`: the wheel stamps lag the range clock by this (the track at range time
        t is the wheel track at t - offset). `noise_scale` (f_v, f_omega): the configured
        wheel noise's translation and heading sigmas times these (`offline.fit_wheel_noise`)."""
        if not (self.record and self.has_wheel and len(self.wheel)) or self.full_graph is None:
            return
        wr = self.wheel_records
        if wr.k:  # the whole track at once; per factor only its GTSAM construction
            t_a = np.array([self.time_of(ka) - offset_ns for ka in wr.k], np.int64)
            t_b = t_a + self.period_ns
            delta = self.wheel.between(t_a, t_b)
            c = np.array([noise_scale[0], noise_scale[0], noise_scale[1]])
            cov = self.wheel.covariance(t_a, t_b, self.cfg.wheel) * np.outer(c, c)
            wr.delta[:], wr.cov[:] = list(delta), list(cov)
            factors = between_factors([X(ka) for ka in wr.k], [X(ka + 1) for ka in wr.k],
                                      delta, cov, wr.out_of_plane, WHEEL_HUBER_K)
            for idx, factor in zip(wr.index, factors, strict=True):
                self.full_graph.replace(idx, factor)
        rec = self.records
        full = [j for j, ks in enumerate(rec.k) if len(ks)]
        if full:  # every range's tag from its keyframe at once
            n = [len(rec.k[j]) for j in full]
            t_a = np.repeat([self.time_of(int(rec.k[j][0])) - offset_ns for j in full], n)
            tags = self._wheel_tag(t_a, np.concatenate([rec.t_ns[j] for j in full]) - offset_ns)
            for j, tag in zip(full, np.split(tags, np.cumsum(n)[:-1]), strict=True):
                rec.tag_in_kf[j] = tag

    def _add_ranges(
        self, inc: Increment, ka: int, t_a: int, pose_a: gtsam.Pose3, vel_a: np.ndarray,
        ranges: tuple[np.ndarray, ...], wheel_rel: np.ndarray | None,
    ) -> None:
        """The keyframe's `ranges` (`_take_ranges`) as factors; `wheel_rel`: the wheel
        track's motion (N,3) from t_a to each range (None: `tag_in_keyframe`)."""
        t, a, z_raw, q = ranges
        # the learned classifier's evidence (nats) adds to each range's NLOS log-likelihood:
        # with it the range's prior odds of NLOS are the classifier's
        evidence = (self.priors.log_odds(q) if self.priors is not None
                    else np.zeros(len(t)))
        if len(t) == 0:
            return
        z = z_raw / (1.0 + self.scale[a]) if self.with_scale else z_raw
        tag_kf = (self.tag_in_keyframe(t_a, t, pose_a, vel_a) if wheel_rel is None
                  else self._tag_from(wheel_rel))
        m = pose_a.matrix()
        p_world = tag_kf @ m[:3, :3].T + m[:3, 3]
        pred = np.linalg.norm(p_world - self.anchors.positions[a], axis=1)
        d_a = self.class_offset(a)
        r_los = z - pred - d_a
        mix = self.mixture
        # at a standstill an anchor's repeated ranges share one error (`rest`); where the
        # base is held at rest its factors keep that share of their information too
        ess = (self.rest.weights(t, a, z, mix.sigma_los) if self.rest is not None
               else np.ones(len(t)))
        held = self.rest.held(t) if self.rest is not None else None
        share = np.where(held, ess, 1.0) if held is not None and held.any() else None
        seg = (t - self.t0) // self.seg_ns
        g = np.zeros(len(t))
        prior = np.full(len(t), self.mixture.p_nlos)
        if self.nlos:
            e_pred, e_var = self._predict_nlos_state(a, seg)
            r_nlos = z - pred - e_pred
            ll_l, ll_n = mix.log_likelihoods(r_los, r_nlos, e_var)
            ll_n = ll_n + evidence
            p_switch = switch_probabilities(t, a, mix.switch_time, self._switch_t)
            self._switch_t[a] = t  # t is time-sorted: each anchor's last stamp is written last
            jump = self._jump_evidence(t, a, r_los, e_pred - d_a) if self.jumps else None
            g, prior = hmm_filter_by_anchor(a, ll_l * ess, ll_n * ess, p_switch, mix.p_nlos,
                                            self.anchor_p, jump)
            # the excess over the anchor's whole LOS offset (the NLOS states' reference)
            r_exc = r_los + d_a - self.range_bias[a] if self.with_bias else r_los
            self._online_m_step(r_los, r_nlos, r_exc, g)
            settled = t >= int(self.start.t_ns) + round(self.g.lag * NS_PER_S)
            if settled.any():
                self._prequential_choice(r_los[settled], ll_l[settled], ll_n[settled],
                                         prior[settled])
            if self.robust_online:
                g[:] = 0.0
        else:
            e_pred = np.zeros(len(t))
        slots = self.range_factors(inc, ka, a, z, tag_kf, seg, g, e_pred, share=share)
        sig_l = self.robust_sigma() if self.robust_online else (
            mix.sigma_los if self.nlos else self.cfg.uwb.sigma)
        uwb = self.cfg.uwb
        w = robust_weight(uwb.robust_kernel, uwb.kernel_threshold, r_los / sig_l)
        if self.with_scale:
            self._update_scale(a, r_los, pred, (1.0 - g) * w)
        rec = self.records
        if self.nlos and self.review and not self.robust_online:
            inc.reviews.append((ReviewBatch(ka, a, z, seg, tag_kf, prior, g.copy(),
                                            len(rec.k), t_ns=t, evidence=evidence, ess=ess,
                                            share=share),
                                slots))
        if self.recent is not None:
            self.recent.add_ranges(ka, a, z_raw, tag_kf)
        rec.k.append(np.full(len(t), ka, np.int64))
        rec.anchor.append(a)
        rec.z.append(z_raw)
        rec.t_ns.append(t)
        rec.tag_in_kf.append(tag_kf)
        rec.g_online.append(g)
        rec.w_online.append(w)
        rec.r_online.append(r_los)
        rec.evidence.append(evidence)

    def zero_velocity(self, graph: gtsam.NonlinearFactorGraph, k: int) -> None:
        """Add a zero velocity on V(k), a keyframe the standstill tracker holds at rest
        (`rest.RestEvidence.at_rest`), std `zero_velocity_sigma` m/s."""
        assert self.rest is not None
        graph.add(gtsam.PriorFactorVector(V(k), np.zeros(3), gtsam.noiseModel.Isotropic.Sigma(
            3, self.rest.zero_velocity_sigma)))

    def class_offset(self, a: np.ndarray) -> np.ndarray:
        """The LOS range offset (m) each range of anchors `a` is classified LOS/NLOS against.

        NLOS only lengthens a range: where every anchor is blocked at once, the offsets
        take up the shared excess (the common one trades with the excess states) and
        ranges classified against them pass NLOS for LOS from then on, a basin the fixed
        lag never leaves (docs/results.md, "isam2 and the causal bound"). Online, a range
        is therefore judged against the part of its anchor's offset that NLOS cannot have
        made, the negative one, as batch's EM judges it against none (`offline.solve`);
        the range factors keep the estimated offset. Batch's seeding pass keeps it whole,
        and so does a graph whose height is free with coplanar anchors: there the common
        offset is held at zero (it trades with the height), and what each anchor's offset
        differs from it by may take either sign. So does a graph with a localiser's poses:
        they place the tag apart from the ranges, each offset is measured against them, and
        a positive one so learnt must hold through the localiser's dropouts, where judging
        the ranges against none of it calls the anchor's LOS ranges NLOS (docs/results.md,
        "The LiDAR scenario's online classes", session 33).
        """
        if not self.with_bias:
            return np.zeros(len(a))
        d = self.range_bias[a]
        whole = self.seeding or not self.offset_observable or self.has_pose
        return d if whole else np.minimum(d, 0.0)

    def _jump_evidence(
        self, t: np.ndarray, a: np.ndarray, r: np.ndarray, excess: np.ndarray
    ) -> np.ndarray:
        """Jump log-likelihoods (N,2,2) of each range against its anchor's previous one
        (`nlos.residual_jumps_by_anchor`; the anchor's last range of the previous keyframe
        leads)."""
        delta = residual_jumps_by_anchor(t, a, r, self._jump_t, self._jump_r)
        # each anchor's newest range leads its next keyframe's chain (t is time-sorted)
        last = {anc: i for i, anc in enumerate(a.tolist())}  # each anchor's last row
        for anc, i in last.items():
            self._jump_r[anc], self._jump_t[anc] = r[i], t[i]
        return jump_log_likelihoods(delta, excess, self.mixture)

    def range_factors(
        self, inc: Increment, ka: int, a: np.ndarray, z: np.ndarray, tag_kf: np.ndarray,
        seg: np.ndarray, g: np.ndarray, e_guess: np.ndarray, rows: list[int] | None = None,
        share: np.ndarray | None = None,
    ) -> list[list[int]]:
        """Add the LOS and NLOS factors (weights 1-g, g) of ranges attached to X(ka), in
        order: anchors `a`, ranges `z` m, tag positions (N,3) in the keyframe's base frame,
        NLOS segments, responsibilities `g` and NLOS state guesses `e_guess` m (N,), of
        the `rows` given (default all); return each range's factor positions in
        `inc.graph`. `share` (N,): each range's factors keep that share of their
        information (a range held at rest, `rest.RestEvidence.held`; None: all of it)."""
        mix = self.mixture
        uwb = self.cfg.uwb
        if self.robust_online:
            sig_l = self.smoothed_robust_sigma or self.robust_sigma()
        else:
            sig_l = (self.smoothed_sigma_los or mix.sigma_los) if self.nlos else uwb.sigma
        graph = inc.graph
        pose_key = X(ka)
        noise, anchor_key, los_key = self._range_keys
        slots = []
        # Python floats: a keyframe has a few ranges, where numpy's per-call cost would
        # exceed the arithmetic (the same IEEE operations either way)
        a_l, z_l = np.asarray(a).tolist(), np.asarray(z, np.float64).tolist()
        seg_l, g_l = np.asarray(seg).tolist(), np.asarray(g, np.float64).tolist()
        e_l = np.asarray(e_guess, np.float64).tolist()
        sh_l = [1.0] * len(a_l) if share is None else np.asarray(share, np.float64).tolist()
        for j in range(len(a_l)) if rows is None else rows:
            aj, zj, sj, gj, ej, sh = a_l[j], z_l[j], seg_l[j], g_l[j], e_l[j], sh_l[j]
            t_tag = gtsam.Pose3(_ROT_IDENTITY, tag_kf[j])
            out = []
            w_l, w_n = (1.0 - gj) * sh, gj * sh
            if w_l > MIN_WEIGHT:
                out.append(graph.size())
                graph.add(range_factor_keyed(pose_key, anchor_key[aj], los_key[aj], zj,
                                             noise(sig_l / math.sqrt(w_l)), t_tag))
            if w_n > MIN_WEIGHT:
                key = self._nlos_state(inc, aj, sj, ej)
                out.append(graph.size())
                graph.add(range_factor_keyed(pose_key, anchor_key[aj], key, zj,
                                             noise(mix.sigma_nlos / math.sqrt(w_n)), t_tag))
            slots.append(out)
        return slots

    def _update_scale(self, a: np.ndarray, r: np.ndarray, h: np.ndarray, w: np.ndarray) -> None:
        """Recursive least squares of each anchor's range scale error k from LOS-weighted
        residuals r (m) at predicted distances h (m), the start's k as prior mean
        (`range_scale_sigma`).

        Every SCALE_BLOCK ranges of an anchor, one Gauss-Newton step of z / (1 + k) = d + b
        on the ranges since the last step, k <- (1 + k)(1 + delta) - 1 with
        delta = sum(w r h) / (I + sigma_los^2 / sigma_k^2), where I = sum(w h^2) over every
        step so far: a radio's scale is a constant, so each new block moves it by its share
        of all the evidence (the gain falls as 1/n, a Kalman filter of a constant). Weighed
        against its own block only, k followed the online track's errors from block to
        block (docs/results.md, "The online range scale as a constant").
        """
        np.add.at(self._sc_num, a, w * r * h)
        np.add.at(self._sc_den, a, w * h * h)
        np.add.at(self._sc_n, a, 1.0)
        lam = (self.mixture.sigma_los / self.g.range_scale_sigma) ** 2
        for anc in np.flatnonzero(self._sc_n >= SCALE_BLOCK):
            self._sc_info[anc] += self._sc_den[anc]
            delta = self._sc_num[anc] / (self._sc_info[anc] + lam)
            k = (1.0 + self.scale[anc]) * (1.0 + delta) - 1.0
            self.scale[anc] = float(np.clip(k, -MAX_SCALE, MAX_SCALE))
            self._sc_num[anc] = self._sc_den[anc] = self._sc_n[anc] = 0.0

    def _predict_nlos_state(self, a: np.ndarray, seg: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Mean (m) and variance (m^2) of E(a, s) for each range, from the newest estimates."""
        mix = self.mixture
        d = self.range_bias[a] if self.with_bias else np.zeros(len(a))
        base = d + mix.mu_nlos
        last = self.e_seg[a]
        gap = np.maximum(seg - last, 0).astype(np.float64)
        phi = np.exp(-gap * mix.segment_s / mix.tau_s)
        known = last >= 0
        mean = np.where(known, base + phi * (self.e_est[a] - base), base)
        var = np.where(known, mix.sigma_slow**2 * (1.0 - phi * phi) + 0.03**2,
                       mix.sigma_slow**2)
        return mean, var

    def _nlos_state(self, inc: Increment, anchor: int, seg: int, guess: float) -> int:
        """Key of E(anchor, seg), creating it (value, priors, stamp) when new."""
        key = nlos_key(anchor, seg)
        now = self.stamp(self.k + 1)
        if self.e_seg[anchor] == seg:
            inc.stamps[key] = now
            self.e_stamp[anchor] = now
            self.e_created[(anchor, seg)] = now
            return key
        if seg < self.e_seg[anchor] or (anchor, seg) in self.e_created:
            # an older segment (delayed review): create it alone if it never existed
            if (anchor, seg) not in self.e_created:
                nlos_state_factors(inc.graph, key, float(self.range_bias[anchor]), None,
                                   self.mixture)
                insert_double(inc.values, key, guess)
            self.e_created[(anchor, seg)] = now
            inc.stamps[key] = now
            # the anchor's later states chain back to this one: they stay as long
            self._restamp_later_states(inc, anchor, seg, now)
            return key
        prev = None
        # link only while the previous state is surely still inside the smoother window
        if self.e_seg[anchor] >= 0 and self.e_stamp[anchor] > now - self.g.lag + 1.0:
            prev = nlos_key(anchor, int(self.e_seg[anchor]))
        nlos_state_factors(inc.graph, key, float(self.range_bias[anchor]), prev, self.mixture)
        insert_double(inc.values, key, guess)
        inc.stamps[key] = now
        self.e_created[(anchor, seg)] = now
        self.e_stamp[anchor] = now
        self.e_seg[anchor] = seg
        self.e_est[anchor] = guess
        return key

    def _restamp_later_states(self, inc: Increment, anchor: int, seg: int, now: float) -> None:
        """Stamp the anchor's NLOS states after segment `seg` `now` (s) too.

        A state links to the one before it, so along an anchor's chain the smoother must
        marginalise the older first: a later state leaving the window while an earlier one
        it hangs on stays (re-stamped by a delayed review) makes GTSAM 4.3's fixed-lag
        smoother fail the marginalisation ("Asking to remove variables from the variable
        index that are not unused"), and the online graph re-anchor."""
        inside = now - self.g.lag + 1.0  # stamped after this: surely still in the window
        newest = int(self.e_seg[anchor])
        for s in range(seg + 1, newest + 1):
            if self.e_created.get((anchor, s), -math.inf) > inside:
                inc.stamps[nlos_key(anchor, s)] = now
                self.e_created[(anchor, s)] = now
        if newest > seg and self.e_stamp[anchor] > inside:
            self.e_stamp[anchor] = now

    def _online_m_step(self, r_los: np.ndarray, r_nlos: np.ndarray, r_exc: np.ndarray,
                       g: np.ndarray) -> None:
        """Adapt the noise model to the last few thousand one-step residuals (prior: the
        config); sigma_los from their MAD (`robust_los_sigma`); the NLOS excess mean from
        `r_exc` (m, against the whole LOS offsets) except in batch's seeding pass (batch's
        EM keeps the configured one).

        The NLOS states revert to D(a) + mu_nlos: at the configured 0.3 m where the log's
        excess is smaller, the newest states sit high, the short end of a blocked
        anchor's ranges passes for LOS and pulls the track (docs/results.md, "The NLOS
        excess mean learnt online", session 39)."""
        window = self._predicted_window.add(np.stack([r_los, r_nlos, r_exc], axis=1), g)
        if window is None:
            return
        rr, gg = window
        self.mixture.m_step(rr[:, 0], rr[:, 1], gg, self.mixture_prior, n0=200.0)
        if not self.seeding:
            self.mixture.excess_mean_step(rr[:, 2], gg, self.mixture_prior, n0=200.0)
        s = robust_los_sigma(rr[:, 0], gg, self.mixture_prior.sigma_los, LOS_SIGMA_PRIOR_RANGES)
        if s is not None:
            self.mixture.sigma_los = s

    def robust_sigma(self) -> float:
        """LOS sigma (m) of the robust model: 1.4826 x the median |one-step residual| (one
        median per batch of new residuals, not per range)."""
        if self._robust_sigma is None:
            med = self._abs_r.median()
            self._robust_sigma = self.cfg.uwb.sigma if med is None else min(
                max(NORMAL_MAD_SCALE * med, SIGMA_LOS_MIN), 1.0)
        return self._robust_sigma

    def prequential_verdict(self) -> str | None:
        """"robust" or "mixture" where the prequential scores favour one significantly
        (`prequential_z` beyond PREQUENTIAL_Z), else None (too little evidence, or a
        configured model)."""
        if self.g.range_model != "auto" or not self.nlos:
            return None
        z = self.prequential_z()
        if z > PREQUENTIAL_Z:
            return "robust"
        return "mixture" if z < -PREQUENTIAL_Z else None

    def prequential_z(self) -> float:
        """Mean per-range score advantage of the robust model over the mixture (nats) in
        units of its standard error: a paired test on the ranges scored so far."""
        n = self._pq_n
        if n < MIN_PREQUENTIAL_RANGES:
            return 0.0
        mean = self._pq_sum / n
        var = max(self._pq_sum2 / n - mean * mean, 1e-12)
        return mean / math.sqrt(var / n)

    def _prequential_choice(
        self, r_los: np.ndarray, ll_l: np.ndarray, ll_n: np.ndarray, prior: np.ndarray
    ) -> None:
        """Score the new ranges (before they are used) under both range models
        (prequential): the online counterpart of batch's held-out choice, reported only
        (`prequential_verdict`): it depends on how far ahead the one-step predictions
        reach, that is on the update cadence (docs/results.md). Only ranges a
        lag after the start are scored (before, the one-step predictions come from a graph
        still settling its start), once the robust sigma has MIN_PREQUENTIAL_RANGES
        residuals behind it."""
        if self.g.range_model.startswith("mixture"):
            return
        n = len(r_los)
        if self.prequential_n + n >= MIN_PREQUENTIAL_RANGES:
            p = np.minimum(np.maximum(prior, 1e-3), 1.0 - 1e-3)  # np.clip's, cheaper
            lp_mix = np.logaddexp(np.log1p(-p) + ll_l, np.log(p) + ll_n)
            lp_rob = np.logaddexp(robust_log_density(r_los, self.robust_sigma(), self.cfg.uwb),
                                  LOG_OUTLIER)
            # ndarray.sum: np.sum's reduction without its wrapper (~1 us a call, six
            # reductions a keyframe)
            self.prequential[0] += float(lp_mix.sum())
            self.prequential[1] += float(lp_rob.sum())
            d = lp_rob - lp_mix
            self._pq_n += n
            self._pq_sum += float(d.sum())
            self._pq_sum2 += float((d * d).sum())
        self._abs_r.add(np.abs(r_los).tolist())
        self._robust_sigma = None  # the ring moved
        self.prequential_n += n

    def add_smoothed_residuals(self, r_los: np.ndarray, g: np.ndarray) -> None:
        """Update `smoothed_sigma_los` from LOS residuals (m) at the smoothed estimate and
        the ranges' responsibilities (last 3000 ranges, every 200).

        The smoothed residuals are narrower than the one-step ones (docs/results.md,
        "Constants in one module"): classifying new ranges needs the wider one, the factors
        the narrower."""
        window = self._smoothed_window.add(r_los, g)
        if window is None:
            return
        rr, gg = window
        s = robust_los_sigma(rr, gg, self.mixture_prior.sigma_los, LOS_SIGMA_PRIOR_RANGES)
        if s is not None:
            self.smoothed_sigma_los = s
        if len(rr) >= MIN_PREQUENTIAL_RANGES:  # the robust model's: every range, no cap
            mad = NORMAL_MAD_SCALE * float(np.median(np.abs(rr - np.median(rr))))
            self.smoothed_robust_sigma = float(np.clip(mad, SIGMA_LOS_MIN, 1.0))

    def _record(self, inc: Increment) -> None:
        if self.record and self.full_graph is not None and self.full_values is not None:
            self.full_graph.push_back(inc.graph)
            self.full_values.insert(inc.values)
