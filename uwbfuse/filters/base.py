# SPDX-License-Identifier: BSD-3-Clause
"""Streaming plumbing shared by the Kalman baselines (EKF, UKF).

`StreamingFilter` implements the `Estimator` protocol once: it buffers the batches of each
stream, feeds them to the initialiser until it yields a start state, then on every
`step(t_ns)` cuts the time since the last step into windows of at most `MAX_WINDOW_NS`
(0.1 s) and hands each window's measurements, in time order, to the concrete filter's
`_window` (predict through the window, update with the window's measurements, each at its
own time), ending at t_ns exactly.

Process inputs: with an IMU, IMU samples drive the process (zero-order hold: a sample holds
from its stamp to the next one) and wheel samples are velocity measurements applied at the
middle of the interval they average. Without an IMU, the wheel samples drive a planar
unicycle (a sample covers the interval that ends at its stamp).
"""

from __future__ import annotations

import logging
import math
from collections import Counter
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from uwbfuse.config import Config
from uwbfuse.constants import (
    MAX_EXTRAPOLATION_S,
    MAX_LOST_FIX_NS,
    MAX_SOLVED_SPEED,
    MAX_WINDOW_NS,
    MOTION_ACCEL_DENSITY_START,
    REPEAT_NS,
)
from uwbfuse.errors import EstimatorError
from uwbfuse.estimator import EstimatorBase, Method, PoseEstimate
from uwbfuse.filters.adaptive_noise import RangeNoise
from uwbfuse.filters.models import (
    F64,
    NS_PER_S,
    gate_threshold,
    imu_to_base,
    quat_xyzw_from_matrix,
)
from uwbfuse.positioning.nlos_classifier import RangePriors
from uwbfuse.streams import AnchorMap, PoseStream

log = logging.getLogger(__name__)




class InitialStateLike(Protocol):
    """What the filters read from `uwbfuse.positioning.initialisation.InitialState`."""

    t_ns: int
    position: np.ndarray          # (3,) m, base origin in the map frame
    R_map_base: np.ndarray        # (3,3)
    velocity: np.ndarray          # (3,) m/s, map frame
    gyro_bias: np.ndarray         # (3,) rad/s
    accel_bias: np.ndarray        # (3,) m/s^2
    position_sigma: float         # m
    yaw_sigma: float              # rad
    still: bool
    range_scale: float            # ranges read range_scale x the distance (1 = none)
    range_sigma: float            # m, spread of the start solve's range residuals
    range_scale_sigma: float      # 1-sigma of range_scale (inf: not solved)


class InitialiserLike(Protocol):
    """The streaming initialiser: same add_* methods as an estimator."""

    def add_imu(self, t_ns: np.ndarray, gyro: np.ndarray, accel: np.ndarray) -> None: ...

    def add_wheel(self, t_ns: np.ndarray, v: np.ndarray, omega: np.ndarray) -> None: ...

    def add_ranges(self, t_ns: np.ndarray, anchor: np.ndarray, rng: np.ndarray) -> None: ...

    def add_poses(self, t_ns: np.ndarray, position: np.ndarray, quat_xyzw: np.ndarray,
                  covariance: np.ndarray) -> None: ...

    def try_initialise(self, t_ns: int) -> InitialStateLike | None: ...

    def provisional(self, t_ns: int) -> InitialStateLike | None: ...

    def standstill_fix(self, t_ns: int) -> tuple[np.ndarray, np.ndarray] | None: ...


def default_initialiser(
    config: Config, anchors: AnchorMap, streams: frozenset[str],
    corrects_heading: bool = True,
) -> InitialiserLike:
    """The project's initialiser (UWB multilateration + IMU levelling, and the start from
    sparse ranges that the graph uses too: `positioning.sparse_start`), imported lazily;
    `corrects_heading=False` for a consumer that cannot correct its heading later."""
    try:
        from uwbfuse.positioning.initialisation import Initialiser
    except ImportError as exc:  # pragma: no cover - only while the module is missing
        raise EstimatorError(f"filter initialiser unavailable: {exc}") from exc
    from uwbfuse.positioning.pose_start import PoseStartInitialiser

    # the filters take the wheel-track start only where multilateration has no fix at all
    # (fixes start the filter better where there are any: docs/results.md, "Constants in one
    # module")
    return PoseStartInitialiser(Initialiser(config, anchors, streams,
                                            corrects_heading=corrects_heading),
                                config, anchors, streams, only_without_fixes=True)


@dataclass
class _Pending:
    """Buffered batches of one stream, concatenated lazily."""

    chunks: list[tuple[np.ndarray, ...]]

    def take(self) -> tuple[np.ndarray, ...] | None:
        if not self.chunks:
            return None
        if len(self.chunks) == 1:
            out = self.chunks[0]
        else:
            out = tuple(np.concatenate(c) for c in zip(*self.chunks, strict=True))
        self.chunks = []
        return out




class StreamingFilter(EstimatorBase):
    """Base of the Kalman baselines: buffering, initialisation, event ordering, reports.

    Subclasses implement `_start`, `_window`, `_inflate` and `_pose`.
    """

    #: Divergence recovery: when at least GATED_MAX of the last RECENT ranges were gated,
    #: or the mean normalised innovation squared (NIS; 1 for a consistent filter) of the
    #: last RECENT accepted ranges exceeds NIS_FACTOR chi2.ppf(gate_probability, RECENT) /
    #: RECENT, the state is probably off (wheel slip, a bad start) rather than the ranges
    #: wrong, and the position/heading covariance is inflated (`_inflate`). Only with gating
    #: on (`[filter] gating = false` asks for the plain filter).
    RECENT = 24
    GATED_MAX = 12
    NIS_FACTOR = 3.0
    #: Variances added by `_inflate`: horizontal position m^2, yaw rad^2, velocity (m/s)^2
    #: (0.2 m, 0.1 rad, 0.2 m/s; larger steps let NLOS-biased ranges drag the estimate).
    #: A recovery within STREAK_NS of the previous one multiplies them by 4 more (a
    #: diverged filter, e.g. from a bad start state, opens up until ranges pass again),
    #: up to 4^MAX_STREAK.
    INFLATE_POS = 0.04
    INFLATE_YAW = 0.01
    INFLATE_VEL = 0.04
    STREAK_NS = 2_000_000_000
    MAX_STREAK = 2
    #: Recovery also when one anchor's ranges are gated SHORT_RUN times in a row while
    #: reading shorter than predicted. NLOS and multipath only lengthen a range, so a
    #: persistently short one means the state is off, typically in a false basin of the
    #: range geometry that the other anchors fit (ISAS-Walk1: the height drifts 1.3 m while
    #: four anchors agree and the fifth is gated for seconds); a too-long run is left alone
    #: (an anchor behind an obstacle). Such a recovery starts at streak SHORT_STREAK (4x the
    #: base steps): one base step does not reach back into the right basin.
    SHORT_RUN = 3
    SHORT_STREAK = 1
    #: The filter carries one range-bias state per anchor (`rbias`, m, appended to its
    #: error state; the last entry is the common scale error when `scale_state`): each
    #: anchor's ranges share a slowly varying error (antenna delay, the slow part of an
    #: NLOS excess) that independent per-range noise cannot describe.
    RANGE_BIAS = False
    #: ... and, with them, the common range-scale error state (`scale_state`).
    RANGE_SCALE = True
    #: External poses gated without a break for longer than this (ns) mean the state is
    #: off (drifted through a pose dropout on too tight a covariance), not the localiser:
    #: its wrong matches last a second or two. The covariance is then widened
    #: (`_inflate(POSE_INFLATE)`) and the pose tried again.
    POSE_RECOVER_NS = 3_000_000_000
    POSE_INFLATE = 4.0

    def __init__(
        self,
        config: Config,
        anchors: AnchorMap,
        streams: frozenset[str],
        initialiser: InitialiserLike | None = None,
    ) -> None:
        self.has_imu = "imu" in streams
        self.has_wheel = "wheel" in streams
        self.has_uwb = "uwb" in streams
        self.has_pose = "pose" in streams
        if not self.has_uwb and not (self.has_imu and self.has_wheel) and not (
                self.has_pose and (self.has_imu or self.has_wheel)):
            raise EstimatorError("Kalman baselines need UWB ranges or external poses, or an "
                                 "IMU and wheels")
        self.config = config
        self.anchors = anchors
        self.anchor_pos: F64 = np.asarray(anchors.positions, dtype=np.float64)
        if not self.has_imu and not self.has_wheel:
            raise EstimatorError(
                "Kalman baselines need an IMU or wheel odometry besides UWB ranges"
            )
        from uwbfuse.positioning.pose_start import PoseBuffer

        self._poses = PoseBuffer()  # external poses not yet applied (all stamps > t_cur)
        self.poses_used = 0
        self.poses_gated = 0
        self.pose_resets = 0
        self._pose_gated_since: int | None = None
        self.tag_b: F64 = np.asarray(config.extrinsics.tag_in_base, dtype=np.float64)
        self.has_tag_lever = bool(np.any(self.tag_b != 0.0))
        self.range_noise = RangeNoise(config, len(anchors))
        # per-anchor range-bias states (filters with RANGE_BIAS; see `bias_decay`) only
        # where the tag height is held (planar vehicle, or the wheel-driven filter): a tag
        # free in 3-D trades its height for a common range bias (docs/results.md)
        self.planar = self.has_wheel and config.graph.planar != "off"
        held = self.planar or not self.has_imu
        # and one common range-scale error state (ranges read (1 + ds) x the distance after
        # the start solve's scale), a random constant of prior std `[graph]
        # range_scale_sigma`: the start solve's scale is fitted to seconds of ranges
        # (1.025-1.033 and 0.973 on room-static logs without scale error) and its start
        # position with it, so the filter estimates the scale with the position rather than
        # keep it (a regression on its own predicted distances cannot undo it)
        self.scale_state = self.RANGE_BIAS and self.RANGE_SCALE and held and len(anchors) > 0
        self.n_bias = (len(anchors) + int(self.scale_state)) if self.RANGE_BIAS and held else 0
        self.rbias: F64 = np.zeros(self.n_bias)
        self.bias_tau = config.nlos.tau
        self.gating = config.filter.gating
        self.initialiser = initialiser or default_initialiser(config, anchors, streams)
        self._init_pending = True
        self._imu_in = _Pending([])
        self._wheel_in = _Pending([])
        self._range_in = _Pending([])
        # Process-input buffers (unconsumed samples) and the held IMU sample.
        self._imu_t = np.zeros(0, dtype=np.int64)
        self._imu_w = np.zeros((0, 3))
        self._imu_f = np.zeros((0, 3))
        self._imu_i = 0
        self.held_w: F64 | None = None
        self.held_f: F64 | None = None
        self.held_imu_t: int | None = None  # stamp (ns) of the sample held_w, held_f came from
        self._wheel_t = np.zeros(0, dtype=np.int64)
        self._wheel_v = np.zeros(0)
        self._wheel_w = np.zeros(0)
        self._wheel_i = 0
        self.held_v = 0.0
        self.held_omega = 0.0
        self.held_wheel_t: int | None = None  # stamp (ns) of the sample held_v, held_omega are
        self._last_wheel_t: int | None = None
        self._wheel_in_carry: list[tuple[np.ndarray, ...]] = []
        self._range_carry: list[tuple[np.ndarray, ...]] = []
        self._wheel_meas: tuple[np.ndarray, ...] | None = None
        self._ranges: tuple[np.ndarray, ...] | None = None
        self.t_cur: int | None = None
        self._provisional: InitialStateLike | None = None
        self._standstill: PoseEstimate | None = None  # standstill fix before the start
        self.t_init: int | None = None
        self.used: Counter[int] = Counter()
        self.gated: Counter[int] = Counter()
        self._recent: list[bool] = []
        self._recent_nis: list[float] = []
        self.nis: F64 = np.zeros(0)
        #: Per range of the last window: measured shorter than predicted.
        self.short: np.ndarray = np.zeros(0, dtype=bool)
        self._short_run: Counter[int] = Counter()
        self.nis_max = (
            self.NIS_FACTOR * gate_threshold(config.filter.gate_probability, self.RECENT)
            / self.RECENT
        )
        self.gate_resets = 0
        self.repeated = 0
        #: the learned NLOS classifier's P(NLOS) per range (`use_range_priors`), or None
        self.range_priors: RangePriors | None = None
        n_anchor = len(self.anchor_pos)
        self._last_t = np.full(n_anchor, np.iinfo(np.int64).min // 2, dtype=np.int64)
        self._last_r = np.full(n_anchor, np.nan)
        self._streak = 0
        self._last_reset: int | None = None
        self.stale = 0
        # lost-track restarts (`_check_lost`): the newest ranges kept for a fix, and
        # whether a restart still waits for one
        self._lost_ranges: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        self._lost = False
        self.lost_restarts = 0

    # -- Estimator protocol -------------------------------------------------------------

    def add_imu(self, t_ns: np.ndarray, gyro: np.ndarray, accel: np.ndarray) -> None:
        """IMU batch: stamps (N,) ns, gyro (N,3) rad/s, specific force (N,3) m/s^2, IMU frame."""
        if self._init_pending:
            self.initialiser.add_imu(t_ns, gyro, accel)
        w, f = imu_to_base(
            np.asarray(gyro, np.float64), np.asarray(accel, np.float64),
            self.config.extrinsics.imu_in_base,
        )
        self._imu_in.chunks.append((np.asarray(t_ns, np.int64), w, f))

    def add_wheel(self, t_ns: np.ndarray, v: np.ndarray, omega: np.ndarray) -> None:
        """Wheel batch: stamps (N,) ns, forward speed (N,) m/s, yaw rate (N,) rad/s."""
        if self._init_pending:
            self.initialiser.add_wheel(t_ns, v, omega)
        self._wheel_in.chunks.append(
            (np.asarray(t_ns, np.int64), np.asarray(v, np.float64), np.asarray(omega, np.float64))
        )

    def add_ranges(self, t_ns: np.ndarray, anchor: np.ndarray, rng: np.ndarray) -> None:
        """Range batch: stamps (N,) ns, anchor index (N,), range (N,) m."""
        if self._init_pending:
            self.initialiser.add_ranges(t_ns, anchor, rng)
        self._range_in.chunks.append(
            (np.asarray(t_ns, np.int64), np.asarray(anchor, np.int64), np.asarray(rng, np.float64))
        )

    def use_range_priors(self, priors: RangePriors) -> None:
        """Weigh each range with the learned NLOS classifier's evidence too (its log-odds
        join the prior of `RangeNoise.weigh`)."""
        self.range_priors = priors

    def range_evidence(self, t_ns: np.ndarray, anchor: np.ndarray) -> np.ndarray | None:
        """The classifier's NLOS log-odds (nats) of ranges (stamps, anchors), or None."""
        if self.range_priors is None or not len(t_ns):
            return None
        return self.range_priors.log_odds(self.range_priors.take(t_ns, anchor))
    def add_poses(self, t_ns: np.ndarray, position: np.ndarray, quat_xyzw: np.ndarray,
                  covariance: np.ndarray) -> None:
        """External poses: stamps (N,) ns, base position (N,3) m and quaternion (N,4) xyzw
        in the map frame, covariance (N,6,6) ROS order; applied at their own stamps by the
        gated update of `filters.pose_update` (`_pose_update`)."""
        if self._init_pending:
            self.initialiser.add_poses(t_ns, position, quat_xyzw, covariance)
        self._poses.add(t_ns, position, quat_xyzw, covariance)

    def _pose_edges(self, t_ns: int) -> np.ndarray:
        """Stamps of the buffered poses in (t_cur, t_ns] (sorted); older ones dropped."""
        assert self.t_cur is not None
        t = self._poses.arrays()[0]
        if not len(t):
            return t
        return np.unique(t[(t > self.t_cur) & (t <= t_ns)])

    def _apply_poses(self, t_b: int) -> None:
        """Gated pose updates with the poses stamped t_b (the state is at t_b)."""
        t, p, q, c = self._poses.arrays()
        at = t == t_b
        if not np.any(at):
            return
        for i in np.flatnonzero(at).tolist():
            ok = self._pose_update(p[i], q[i], c[i])
            if not ok:
                if self._pose_gated_since is None:
                    self._pose_gated_since = t_b
                elif t_b - self._pose_gated_since > self.POSE_RECOVER_NS:
                    self._inflate(self.POSE_INFLATE)
                    self.pose_resets += 1
                    ok = self._pose_update(p[i], q[i], c[i])
            if ok:
                self.poses_used += 1
                self._pose_gated_since = None
            else:
                self.poses_gated += 1
        self._poses.keep_after(t_b)

    def _pose_update(self, position: np.ndarray, quat_xyzw: np.ndarray,
                     covariance: np.ndarray) -> bool:
        """Update the state with one external pose at t_cur; False when gated."""
        raise NotImplementedError

    def step(self, t_ns: int) -> None:
        """Process every buffered sample with stamp <= t_ns in time order; predict to t_ns."""
        self._absorb_inputs()
        if self._init_pending:
            state = self.initialiser.try_initialise(int(t_ns))
            if state is None:
                p = self.initialiser.provisional(int(t_ns))
                # Only a pose that refers to this epoch (an older heading candidate would
                # be written at a stale stamp) and carries a heading candidate: without one
                # its position is the median of plain multilateration fixes, and the
                # pipeline's NLOS-weighted WLS fallback is the better pose (measured in
                # docs/results.md).
                self._provisional = (
                    p if p is not None and int(p.t_ns) == int(t_ns)
                    and p.yaw_sigma < math.pi else None)
                fix = (self.initialiser.standstill_fix(int(t_ns))
                       if self._provisional is None else None)
                self._standstill = None if fix is None else PoseEstimate(int(t_ns), *fix)
                return
            self._provisional = None
            self._standstill = None
            self._init_pending = False
            self._absorb_inputs()
            self.t_init = int(state.t_ns)
            self._discard_until(self.t_init)
            # Ranges as the start solve saw them: its common scale (radios that read a few
            # % long, e.g. Plaza; refined from the innovations from then on, so a scale that
            # is only the solve's noise does not stay), and at least its residual spread as
            # the LOS spread's prior.
            # (the height is held by the planar constraint, or fixed in the wheel-driven filter)
            self.range_noise.set_start_scale(
                float(state.range_scale),
                refine=(self.planar or not self.has_imu) and not self.scale_state)
            self.range_noise.widen_los_prior(float(state.range_sigma))
            self._start(state)
            self.t_cur = self.t_init
        assert self.t_cur is not None
        t_ns = int(t_ns)
        if t_ns <= self.t_cur:
            return
        rt, ra, rr, wt, wv = self._measurements(t_ns)
        if self.range_noise.scale != 1.0:
            rr = rr / self.range_noise.scale
        pose_t = self._pose_edges(t_ns) if self.has_pose else np.zeros(0, np.int64)
        if t_ns - self.t_cur <= MAX_WINDOW_NS and not len(pose_t):  # one 10 Hz output step
            used = self._window(t_ns, rt, ra, rr, wt, wv)
            if len(rt):
                self._count(ra, used)
            self.t_cur = t_ns
            self._trim_inputs()
            self._check_lost(rt, ra, rr)
            return
        n_win = -(-(t_ns - self.t_cur) // MAX_WINDOW_NS)
        edges = self.t_cur + (t_ns - self.t_cur) * np.arange(1, n_win + 1) // n_win
        if len(pose_t):  # windows end at the poses' stamps: each applied at its own time
            edges = np.union1d(edges, pose_t)
            n_win = len(edges)
        r_end = np.searchsorted(rt, edges, side="right")
        w_end = np.searchsorted(wt, edges, side="right")
        r0 = w0 = 0
        for k in range(n_win):
            t_b = int(edges[k])
            r1, w1 = int(r_end[k]), int(w_end[k])
            used = self._window(t_b, rt[r0:r1], ra[r0:r1], rr[r0:r1], wt[w0:w1], wv[w0:w1])
            if r1 > r0:
                self._count(ra[r0:r1], used)
            self.t_cur = t_b
            if len(pose_t):
                self._apply_poses(t_b)
            r0, w0 = r1, w1
        self._trim_inputs()
        self._check_lost(rt, ra, rr)

    def _check_lost(self, rt: np.ndarray, ra: np.ndarray, rr: np.ndarray) -> None:
        """Lost-track restart (IMU-driven filters): a mechanisation that runs faster than
        MAX_SOLVED_SPEED (m/s) has lost the track (an IMU alone through a range outage
        runs away by tens of metres, and the innovation gate then rejects every range).
        Its velocity restarts at zero; its position at a multilateration fix of the
        newest round robin of ranges (`rt` ns, anchor `ra`, range `rr` m: this step's,
        kept with the earlier ones of the last MAX_LOST_FIX_NS) as soon as one is found."""
        if not self.has_imu or not len(self.anchor_pos):
            return
        if len(rt):
            self._lost_ranges.append((rt, ra, rr))
        t_cur = int(self.t_cur) if self.t_cur is not None else 0
        while self._lost_ranges and self._lost_ranges[0][0][-1] < t_cur - MAX_LOST_FIX_NS:
            self._lost_ranges.pop(0)
        if not self._lost and not float(np.linalg.norm(self.velocity())) > MAX_SOLVED_SPEED:
            return
        if not self._lost:
            self.lost_restarts += 1
        self._lost = True
        fix = self._lost_fix(t_cur)
        self._restart_lost(fix)
        self._lost = fix is None

    def _lost_fix(self, t_ns: int) -> tuple[F64, F64] | None:
        """Tag position (3,) m, map frame, and its covariance (3,3) m^2 from the newest
        range of each anchor in one round robin before t_ns (robust multilateration), or
        None where too few anchors answered."""
        if not self._lost_ranges:
            return None
        from uwbfuse.positioning.multilateration import (
            epoch_window_ns,
            group_epochs,
            multilaterate,
        )

        t, a, r = (np.concatenate(x) for x in zip(*self._lost_ranges, strict=True))
        order = np.argsort(t, kind="stable")
        t, a, r = t[order], a[order], r[order]
        window = epoch_window_ns(t, a, MAX_WINDOW_NS, MAX_LOST_FIX_NS)
        rows, _ = group_epochs(t, a, r, len(self.anchor_pos), np.array([t_ns]), window)
        dim = 2 if self.planar else 3
        if int(np.sum(np.isfinite(rows[0]))) < dim + 1:
            return None
        fixes = multilaterate(
            self.anchor_pos, rows, dim=dim,
            tag_z=self.z0 + float(self.tag_b[2]) if self.planar else None,
            sigma=self.config.uwb.sigma, kernel=self.config.uwb.robust_kernel,
            threshold=self.config.uwb.kernel_threshold)
        if not bool(fixes.ok[0]):
            return None
        cov = np.eye(3) * self.config.uwb.sigma**2
        cov[:dim, :dim] = fixes.cov[0]
        return fixes.position[0], cov

    def velocity(self) -> F64:
        """The filter's velocity estimate, m/s, map frame (IMU-driven filters)."""
        raise NotImplementedError

    def _restart_lost(self, fix: tuple[F64, F64] | None) -> None:
        """Restart a lost track: velocity zero (within ONLINE_MAX_START_SPEED), and the
        position at `fix` (tag position m and covariance m^2, map frame) when there is one."""
        raise NotImplementedError

    @property
    def provisional(self) -> bool:
        """`estimate()` is a standstill fix from before the start (see `prestart.PreStart`)."""
        return self._init_pending and self._provisional is None and self._standstill is not None

    def estimate(self) -> PoseEstimate | None:
        """The causal pose (base in map) at the last step time.

        Before the filter has its start state this is the initialiser's provisional pose
        when it has a heading candidate (UWB fix, attitude of the candidate) so that outputs
        cover the log from the first motion, else its standstill fix (`provisional` is then
        true), or None (the pipeline's WLS fallback answers).
        """
        if self._init_pending:
            p = self._provisional
            if p is None:
                return self._standstill
            return PoseEstimate(
                int(p.t_ns), np.array(p.position, dtype=np.float64),
                quat_xyzw_from_matrix(np.asarray(p.R_map_base, dtype=np.float64)),
            )
        if self.t_cur is None:
            return None
        pos, quat = self._pose()
        return PoseEstimate(self.t_cur, pos, quat, self.pose_covariance())

    def finish(self) -> PoseStream | None:
        """Filters have no smoothed output: the causal poses are final."""
        return None

    def report(self) -> dict[str, Any]:
        """Ranges used/gated per anchor id, gate resets, mode, start time."""
        ids = self.anchors.ids
        return {
            "mode": self.mode,
            "initialised_at_ns": self.t_init,
            "ranges_used": {ids[i]: n for i, n in sorted(self.used.items())},
            "ranges_gated": {ids[i]: n for i, n in sorted(self.gated.items())},
            "gate_resets": self.gate_resets,
            "lost_restarts": self.lost_restarts,
            "repeated_ranges": self.repeated,
            "poses_used": self.poses_used,
            "poses_gated": self.poses_gated,
            "pose_gate_resets": self.pose_resets,
            "stale_samples": self.stale,
            "range_noise": self.range_noise.report(),
            "range_bias": {ids[i]: round(float(b), 4)
                           for i, b in enumerate(self.rbias[: len(ids)])},
            "range_scale_error": round(float(self.rbias[-1]), 5) if self.scale_state else 0.0,
        }

    # -- to implement -------------------------------------------------------------------

    @property
    def mode(self) -> str:
        """Sensor combination besides UWB: 'imu+wheel', 'imu', 'wheel' ('imu+wheel, no uwb'
        on a log without ranges)."""
        out = "+".join(n for n, on in (("imu", self.has_imu), ("wheel", self.has_wheel)) if on)
        return out if self.has_uwb else f"{out}, no uwb"

    def _start(self, state: InitialStateLike) -> None:
        raise NotImplementedError

    def _window(
        self, t_b: int, rt: np.ndarray, ra: np.ndarray, rr: np.ndarray,
        wt: np.ndarray, wv: np.ndarray,
    ) -> np.ndarray:
        """Advance from t_cur to t_b using the window's measurements.

        Ranges: stamps rt (M,) ns in (t_cur, t_b], anchor indices ra, ranges rr m; wheel
        speeds wv m/s at wt (IMU filters only). Returns the accepted mask of the ranges (M,).
        """
        raise NotImplementedError

    def _inflate(self, scale: float) -> None:
        """Widen the uncertainty after a run of gated ranges: `scale` x the INFLATE_* steps."""
        raise NotImplementedError

    def _pose(self) -> tuple[F64, F64]:
        raise NotImplementedError

    def pose_covariance(self) -> F64:
        """(6,6) covariance of `_pose` in ROS order, map axes (`models.pose_covariance`)."""
        raise NotImplementedError

    # -- helpers for subclasses ---------------------------------------------------------

    def bias_decay(self, t: float) -> tuple[F64, F64]:
        """First-order Gauss-Markov range biases over t seconds: the factor f (M,) on each
        bias and the variance (M,) m^2 of the noise added. Correlation time `bias_tau`
        (`[nlos] tau`, s); stationary variance p_a x nlos_std^2, with p_a the
        anchor's current NLOS probability (its chain state in `RangeNoise`) and nlos_std
        the NLOS spread of the mixture fitted to the log's innovations: a LOS anchor's bias
        is held (its ranges count at the radio's noise), an anchor behind an obstacle gets
        a slow excess of the fitted size, so its tens of ranges a second do not count as
        independent evidence."""
        f = np.full(self.n_bias, math.exp(-t / self.bias_tau))
        if self.scale_state:
            f[-1] = 1.0
        q = (1.0 - f * f) * self.bias_variance()
        return f, q

    def bias_variance(self) -> F64:
        """Stationary variance (M,) m^2 of each anchor's range bias now (`bias_decay`)."""
        if not self.n_bias:
            return np.zeros(0)
        var = self.range_noise.p_last * self.range_noise.model.nlos_std**2
        if self.scale_state:
            var = np.append(var, self.config.graph.range_scale_sigma**2)
        return var


    def consider_variance(self) -> F64:
        """Stationary variance (M,) m^2 of each anchor's range error that the filter treats
        as white but that persists over an NLOS episode (`filters.consider`): the NLOS
        assignment error (z - p) nlos_mean of the fitted mixture, share pi: variance
        pi (1 - pi) nlos_mean^2, with the correlation time of the range biases."""
        m = self.range_noise.model
        pi = m.nlos_prior
        return np.full(len(self.anchors), pi * (1.0 - pi) * m.nlos_mean**2)

    def start_bias_variance(self, state: InitialStateLike) -> F64:
        """`bias_variance` at the start `state`: the common range-scale error's variance is
        the start solve's own where that is smaller than `[graph] range_scale_sigma`^2 (the
        scale state has no process noise: a 5 % prior lets one gross range at the start,
        read as a 15 % scale, pass the gate and pin a wrong scale)."""
        var = self.bias_variance()
        s = float(state.range_scale_sigma)
        if self.scale_state and 0.0 < s < math.inf:
            var[-1] = min(float(var[-1]), s * s)
        return var

    def dropout_noise(self, guess_s: float) -> F64:
        """(15,15) process noise an IMU dropout's still guess adds over `guess_s` seconds
        (`imu_grid`'s NaN rows): the motion it cannot see, as the graph's guess
        (`graph.imu.guess_covariance`): white acceleration at MOTION_ACCEL_DENSITY_START on
        the velocity and the yaw rate at `[graph] motion_turn_density` on the map-frame yaw
        error; the level attitude keeps the IMU's own noise. Only where wheels carry the
        motion through the dropout: without them the still guess at the IMU's noise is the
        filter's only motion model (the UKF left the track on a loose one: warehouse seed 3,
        IMU + UWB, 0.373 -> 1.456 m)."""
        q = np.zeros((15, 15))
        q[3:6, 3:6] = np.eye(3) * MOTION_ACCEL_DENSITY_START**2 * guess_s
        q[8, 8] = self.config.graph.motion_turn_density**2 * guess_s
        return q

    def imu_grid(
        self, t_b: int, meas_t: np.ndarray
    ) -> tuple[F64, F64, F64, np.ndarray]:
        """Zero-order-hold IMU intervals from t_cur to t_b, split at the measurement stamps.

        Returns gyro (N,3) rad/s and accel (N,3) m/s^2 (base frame) per interval, dt (N,) s,
        and for each stamp of `meas_t` the index of the interval boundary (0..N) it falls
        on (boundaries may repeat; repeated ones have dt = 0). Consumes the IMU samples
        with stamps in (t_cur, t_b]; the last becomes the held sample. Before the first
        sample the first available one is held backwards; with no sample at all, or where the
        held sample is older than MAX_EXTRAPOLATION_S (an IMU dropout: its instantaneous
        turn rate held for seconds would spin the attitude), the rows are NaN (the caller
        substitutes a still sample: no turn, no acceleration at its attitude and biases).
        """
        assert self.t_cur is not None
        i0 = self._imu_i
        i1 = i0 + int(np.searchsorted(self._imu_t[i0:], t_b, side="right"))
        ts = self._imu_t[i0:i1]
        if self.held_w is None and i0 < len(self._imu_t):
            self.held_w, self.held_f = self._imu_w[i0], self._imu_f[i0]
            self.held_imu_t = int(self._imu_t[i0])
        # Boundaries need not be unique: a zero-length interval changes nothing.
        bounds = np.concatenate([[self.t_cur], ts, meas_t, [t_b]])
        bounds.sort()
        dt = (bounds[1:] - bounds[:-1]) * (1.0 / NS_PER_S)
        j = np.searchsorted(ts, bounds[:-1], side="right") - 1
        if i1 > i0:
            jj = i0 + np.maximum(j, 0)
            gyro, accel = self._imu_w[jj], self._imu_f[jj]
        else:
            gyro, accel = np.empty((len(dt), 3)), np.empty((len(dt), 3))
        if j[0] < 0:  # intervals before the first new sample hold the last one ...
            before = j < 0
            gyro[before] = np.nan if self.held_w is None else self.held_w
            accel[before] = np.nan if self.held_f is None else self.held_f
            if self.held_imu_t is not None:  # ... for MAX_EXTRAPOLATION_S at most (a dropout)
                late = before & (bounds[:-1] - self.held_imu_t > MAX_EXTRAPOLATION_S * NS_PER_S)
                gyro[late] = np.nan
                accel[late] = np.nan
        if i1 > i0:
            self.held_w, self.held_f = self._imu_w[i1 - 1], self._imu_f[i1 - 1]
            self.held_imu_t = int(self._imu_t[i1 - 1])
        self._imu_i = i1
        return gyro, accel, dt, np.searchsorted(bounds, meas_t)

    def wheel_grid(
        self, t_b: int, meas_t: np.ndarray
    ) -> tuple[F64, F64, F64, np.ndarray, F64]:
        """Wheel intervals from t_cur to t_b, split at the measurement stamps.

        A wheel sample is the mean velocity over the interval ending at its stamp, so each
        interval takes the first buffered sample stamped at or after its end, or the last
        sample seen when none is buffered yet. Returns v (N,) m/s, omega (N,) rad/s,
        dt (N,) s, the boundary index (0..N) of each stamp of `meas_t`, and how far (N,) s
        each interval that holds the last sample's twist reaches beyond
        MAX_EXTRAPOLATION_S from that sample's stamp (0 elsewhere: a wheel dropout's guess,
        `models.unicycle_transition`).
        """
        assert self.t_cur is not None
        i0 = self._wheel_i
        ts = self._wheel_t[i0:]
        i1 = i0 + int(np.searchsorted(ts, t_b, side="left"))  # consumed: stamps < t_b
        k = int(np.searchsorted(ts, t_b, side="right"))
        inner = ts[: i1 - i0]
        bounds = np.unique(np.concatenate([[self.t_cur], inner, meas_t, [t_b]]))
        dt = np.diff(bounds).astype(np.float64) / NS_PER_S
        j = np.searchsorted(ts, bounds[1:], side="left")
        have = j < len(ts)
        jj = i0 + np.minimum(j, max(len(ts) - 1, 0))
        if len(ts):
            v = np.where(have, self._wheel_v[jj], self.held_v)
            w = np.where(have, self._wheel_w[jj], self.held_omega)
        else:
            v = np.full(len(dt), self.held_v)
            w = np.full(len(dt), self.held_omega)
        guess = np.zeros(len(dt))
        if self.held_wheel_t is not None and not np.all(have):
            reach = (bounds[1:] - self.held_wheel_t).astype(np.float64) / NS_PER_S
            guess = np.where(have, 0.0, np.maximum(reach - MAX_EXTRAPOLATION_S, 0.0))
        if k > 0:
            self.held_v = float(self._wheel_v[i0 + k - 1])
            self.held_omega = float(self._wheel_w[i0 + k - 1])
            self.held_wheel_t = int(self._wheel_t[i0 + k - 1])
        self._wheel_i = i1
        return v, w, dt, np.searchsorted(bounds, meas_t), guess

    # -- internals ----------------------------------------------------------------------

    def _count(self, anchors: np.ndarray, used: np.ndarray) -> None:
        self.used.update(anchors[used].tolist())
        gated = anchors[~used]
        if len(gated):
            self.gated.update(gated.tolist())
        self._recent = (self._recent + (~used).tolist())[-self.RECENT :]
        nis = self.nis[used] if len(self.nis) == len(used) else self.nis
        self._recent_nis = (self._recent_nis + nis.tolist())[-self.RECENT :]
        full = len(self._recent_nis) == self.RECENT
        short = self.short if len(self.short) == len(used) else np.zeros(len(used), bool)
        run = self._short_run
        if run or not used.all():
            for a, ok, s in zip(anchors.tolist(), used.tolist(), short.tolist(), strict=True):
                if ok:
                    run.pop(a, None)
                elif s:
                    run[a] += 1
        off = bool(run) and max(run.values()) >= self.SHORT_RUN
        if self.gating and (off or sum(self._recent) >= self.GATED_MAX or (
            full and sum(self._recent_nis) > self.nis_max * self.RECENT
        )):
            assert self.t_cur is not None
            recent = self._last_reset is not None and self.t_cur - self._last_reset < self.STREAK_NS
            self._streak = min(self._streak + 1, self.MAX_STREAK) if recent else 0
            if off:  # the state is off, not the ranges: open up at least one step more
                self._streak = max(self._streak, self.SHORT_STREAK)
            self._last_reset = self.t_cur
            self._inflate(4.0**self._streak)
            self.gate_resets += 1
            self._recent = []
            self._recent_nis = []
            run.clear()

    def _absorb_inputs(self) -> None:
        imu = self._imu_in.take()
        if imu is not None:
            t, w, f = imu
            self._imu_t = np.concatenate([self._imu_t[self._imu_i :], t])
            self._imu_w = np.concatenate([self._imu_w[self._imu_i :], w])
            self._imu_f = np.concatenate([self._imu_f[self._imu_i :], f])
            self._imu_i = 0
        wheel = self._wheel_in.take()
        # Wheels drive the process only without an IMU; with one, the process buffer is
        # kept until the start (for the held sample and stamp), then no longer fed.
        if wheel is not None and (not self.has_imu or self._init_pending):
            t, v, w = wheel
            self._wheel_t = np.concatenate([self._wheel_t[self._wheel_i :], t])
            self._wheel_v = np.concatenate([self._wheel_v[self._wheel_i :], v])
            self._wheel_w = np.concatenate([self._wheel_w[self._wheel_i :], w])
            self._wheel_i = 0
        # Measurement copies (the IMU filters use wheels as velocity updates); before the
        # start they are carried over so that the events after the start time survive.
        if self._init_pending:
            if wheel is not None:
                self._wheel_in_carry.append(wheel)
            rng = self._range_in.take()
            if rng is not None:
                self._range_carry.append(rng)
            return
        if self._wheel_in_carry:
            if wheel is not None:
                self._wheel_in_carry.append(wheel)
            wheel = _Pending(self._wheel_in_carry).take()
            self._wheel_in_carry = []
        rng = self._range_in.take()
        if self._range_carry:
            if rng is not None:
                self._range_carry.append(rng)
            rng = _Pending(self._range_carry).take()
            self._range_carry = []
        # (a step that ended before consuming them, e.g. the start step, keeps them)
        self._wheel_meas = _Pending([c for c in (self._wheel_meas, wheel) if c is not None]).take()
        self._ranges = _Pending([c for c in (self._ranges, rng) if c is not None]).take()

    def _measurements(
        self, t_ns: int
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Ranges (t, anchor, range) and, for IMU filters, wheel speeds (t_mid, v) in
        (t_cur, t_ns], each sorted by time. Wheel speeds are placed at the middle of the
        interval they average (not before t_cur)."""
        assert self.t_cur is not None
        empty_i = np.zeros(0, dtype=np.int64)
        rt, ra, rr = empty_i, empty_i, np.zeros(0)
        if self._ranges is not None and len(self._ranges[0]):
            t, a, r = self._ranges
            in_order = len(t) < 2 or bool((t[1:] >= t[:-1]).all())
            if in_order and t[0] > self.t_cur and t[-1] <= t_ns:
                rt, ra, rr = t, a, r   # the usual case: one sorted batch of this step
            else:
                keep = (t > self.t_cur) & (t <= t_ns)
                self.stale += int(np.count_nonzero((t <= self.t_cur) & (t > (self.t_init or 0))))
                rt, ra, rr = t[keep], a[keep], r[keep]
                later = t > t_ns
                if np.any(later):  # added ahead of this step: keep for the next one
                    self._range_in.chunks.insert(0, (t[later], a[later], r[later]))
                if not in_order:
                    o = np.argsort(rt, kind="stable")
                    rt, ra, rr = rt[o], ra[o], rr[o]
        if len(rt):
            rt, ra, rr = self._drop_repeats(rt, ra, rr)
        wt, wv = empty_i, np.zeros(0)
        if self.has_imu and self._wheel_meas is not None and len(self._wheel_meas[0]):
            t, v, w = self._wheel_meas
            later = t > t_ns
            if np.any(later):
                self._wheel_in_carry.insert(0, (t[later], v[later], w[later]))
                t, v = t[~later], v[~later]
            first = t[0] if self._last_wheel_t is None else self._last_wheel_t
            prev = np.concatenate([[first], t[:-1]])
            self._last_wheel_t = int(t[-1])
            mid = np.maximum(t - (t - prev) // 2, self.t_cur + 1)
            keep = (t > self.t_cur) & (t <= t_ns)
            wt, wv = mid[keep], v[keep]
        self._ranges = None
        self._wheel_meas = None
        return rt, ra, rr, wt, wv

    def _drop_repeats(
        self, rt: np.ndarray, ra: np.ndarray, rr: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Drop re-published ranges (see `REPEAT_NS`); rt must be sorted."""
        lt, lr = self._last_t, self._last_r
        if len(np.unique(ra)) == len(ra):  # the usual case: one range per anchor
            keep = (rr != lr[ra]) | (rt - lt[ra] > REPEAT_NS)
            lt[ra[keep]] = rt[keep]
            lr[ra[keep]] = rr[keep]
        else:
            keep = np.ones(len(rt), dtype=bool)
            for i, (t, a, r) in enumerate(zip(rt.tolist(), ra.tolist(), rr.tolist(), strict=True)):
                if r == lr[a] and t - lt[a] <= REPEAT_NS:
                    keep[i] = False
                else:
                    lt[a], lr[a] = t, r
        if keep.all():
            return rt, ra, rr
        self.repeated += int(np.count_nonzero(~keep))
        return rt[keep], ra[keep], rr[keep]

    def _discard_until(self, t0: int) -> None:
        """Drop process inputs up to the start time t0 (the last IMU sample is held)."""
        i = int(np.searchsorted(self._imu_t, t0, side="right"))
        if i > 0:
            self.held_w, self.held_f = self._imu_w[i - 1], self._imu_f[i - 1]
            self.held_imu_t = int(self._imu_t[i - 1])
        self._imu_i = i
        j = int(np.searchsorted(self._wheel_t, t0, side="right"))
        if j > 0:
            self.held_v, self.held_omega = float(self._wheel_v[j - 1]), float(self._wheel_w[j - 1])
            self._last_wheel_t = self.held_wheel_t = int(self._wheel_t[j - 1])
        self._wheel_i = j
        # Ranges and wheel measurements at or before t0 are filtered by `_events`.
        self.stale = 0

    def _trim_inputs(self) -> None:
        if self._imu_i > 4096:
            self._imu_t = self._imu_t[self._imu_i :]
            self._imu_w = self._imu_w[self._imu_i :]
            self._imu_f = self._imu_f[self._imu_i :]
            self._imu_i = 0
        if self._wheel_i > 4096:
            self._wheel_t = self._wheel_t[self._wheel_i :]
            self._wheel_v = self._wheel_v[self._wheel_i :]
            self._wheel_w = self._wheel_w[self._wheel_i :]
            self._wheel_i = 0


def build_filter(
    method: Method,
    imu_cls: type[StreamingFilter],
    planar_cls: type[StreamingFilter],
    config: Config,
    anchors: AnchorMap | None,
    streams: frozenset[str],
    initialiser: InitialiserLike | None = None,
) -> StreamingFilter:
    """The filter variant for the sensor combination: IMU-driven when the log has an IMU,
    the planar wheel-driven one otherwise. Raises EstimatorError without anchors, except on
    a log without UWB that has an IMU and wheels (the filter then starts at the map origin,
    heading zero, and fuses the two)."""
    if "uwb" not in streams and ({"imu", "wheel"} <= streams or (
            "pose" in streams and streams & {"imu", "wheel"})):
        anchors = AnchorMap((), np.zeros((0, 3)))
    elif anchors is None or len(anchors) == 0:
        raise EstimatorError(f"{method.value} needs an anchor map")
    cls = imu_cls if "imu" in streams else planar_cls
    return cls(config, anchors, streams, initialiser)
