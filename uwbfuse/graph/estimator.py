# SPDX-License-Identifier: BSD-3-Clause
"""The streaming graph estimator behind `isam2`, `isam2-smoothed` and `batch`.

Data arrive in time-sorted batches (`add_imu`, `add_wheel`, `add_ranges`). Until the
sensors determine a start (`positioning.initialisation.Initialiser`; for wheeled logs whose
sparse round-robin ranges give it no fixes, `start.solve_start` after a few seconds: both
through `sparse_start.SparseStartInitialiser`, which the filters share), `estimate()` is
None, except that a wheeled log without an IMU standing still since its first range gets a
provisional position from all its ranges with a common range scale (`start.solve_static`).
From then on each `step(t)` builds every keyframe with time <= t (`GraphBuilder`) and
feeds them to a fixed-lag iSAM2 (`OnlineSmoother`) every `graph.update_every` keyframes;
`estimate()` is the newest keyframe (solved or predicted from the last solved one by
wheels/IMU) composed with the motion up to t: causal.
After every update the LOS/NLOS responsibilities of the ranges in the lag window are
recomputed against the smoothed keyframes (forward-backward per anchor over the window);
ranges that changed class get their factors replaced (iSAM2 factor removal), a fixed-lag
EM step.

`finish()`:
- isam2: None (the causal estimates are the output).
- isam2-smoothed and batch: the whole log as one graph (every non-range factor recorded
  while streaming, range factors rebuilt per EM round), solved by Levenberg-Marquardt with
  NLOS EM, range model, range scales and offsets chosen and fitted over the whole log,
  from the keyframe estimates as they left the fixed-lag window (`offline.solve`).
  isam2-smoothed smooths its own online pass (the one isam2 runs, less the standstill
  weights of `graph.rest`: `graph.update_every`, anchor offsets held as online); the
  online pass of `batch` updates iSAM2 once per
  `BATCH_CHUNK` keyframes and keeps the configured anchor-offset prior (it only seeds LM).
  Smoothing only within the lag left each keyframe with the range scale, offsets and
  LOS/NLOS classes of its window (docs/results.md, "isam2-smoothed: the whole graph").
Both offline outputs are carried back from the start to the first wheel sample by the
wheel track, so they cover the log from the first motion.

A GTSAM failure in an update (indeterminant system after an outage, say) re-anchors: a
fresh smoother starts from the newest keyframe's prediction with loose priors, a warning
is logged and counted in `report()`; it never raises.
"""

from __future__ import annotations

import copy
import dataclasses
import logging
import math
import time
from typing import Any

import gtsam
import numpy as np

from uwbfuse.config import Config, GraphConfig
from uwbfuse.constants import (
    BACKDATE_YAW_DRIFT,
    BATCH_CHUNK,
    LIVE_LATENCY_KEPT,
    MAX_SOLVED_SPEED,
    ONLINE_MAX_START_SPEED,
    ONLINE_WINDOW_S,
    PREDICTED_UPDATE_EVERY,
    PROVISIONAL_FIX_S,
    REVIEW_CHANGE,
    REVIEW_MARGIN_S,
    REVIEW_MIN_AGE_S,
    REVIEW_SEARCH,
    SEARCH_PERSIST,
    SEARCH_SWITCH_NATS,
    SMOOTHED_STAT_AGE_S,
    WHEEL_OFFSET_MAX_PERIODS,
)
from uwbfuse.errors import EstimatorError
from uwbfuse.estimator import Estimator, EstimatorBase, Method, PoseEstimate, RangeClasses
from uwbfuse.graph import covariance, noise_fit, offline
from uwbfuse.graph.builder import GraphBuilder, Increment
from uwbfuse.graph.evidence_window import EvidenceWindows, window_mask
from uwbfuse.graph.imu import ImuBuffer, pose_from_xyzq
from uwbfuse.graph.keys import B, C, D, L, V, X, nlos_key
from uwbfuse.graph.online import OnlineSmoother
from uwbfuse.graph.rest import RestEvidence
from uwbfuse.graph.review_queue import ReviewQueue
from uwbfuse.graph.uwb import los_subset_search, unique_inverse
from uwbfuse.graph.wheel import WheelTrack, se2_between, se2_to_pose3
from uwbfuse.nlos import (
    NlosModel,
    hmm_smooth_by_anchor,
    jump_log_likelihoods,
    residual_jumps_by_anchor,
    switch_probabilities,
)
from uwbfuse.positioning.nlos_classifier import RangePriors
from uwbfuse.positioning.pose_start import PoseStartInitialiser
from uwbfuse.streams import NS_PER_S, AnchorMap, PoseStream

log = logging.getLogger(__name__)

# the report's key for the whole-graph solve of `finish` (see the module docstring)
FULL_GRAPH_REPORT = {Method.BATCH: "batch", Method.ISAM2_SMOOTHED: "final_smoothing"}
_PAIR = 1 << 40  # (anchor, NLOS segment) -> anchor * _PAIR + segment (segments < 2^40)


def _quat_xyzw(pose: gtsam.Pose3) -> np.ndarray:
    q = pose.rotation().toQuaternion()
    return np.array([q.x(), q.y(), q.z(), q.w()])


def keyframes_per_update(graph: GraphConfig, streams: frozenset[str]) -> int:
    """Keyframes per iSAM2 update of the online pass (isam2, and the same run for
    isam2-smoothed): `graph.update_every`, whose "auto" is 1 where an IMU without wheels
    predicts between updates (double integration drifts by centimetres over 0.3 s on a
    walker), else PREDICTED_UPDATE_EVERY."""
    if graph.update_every != "auto":
        return int(graph.update_every)
    return 1 if "imu" in streams and "wheel" not in streams else PREDICTED_UPDATE_EVERY


class GraphEstimator(EstimatorBase):
    """Factor-graph estimator (see the module docstring). Implements `Estimator`."""

    def __init__(
        self,
        method: Method,
        config: Config,
        anchors: AnchorMap,
        streams: frozenset[str],
        initialiser: PoseStartInitialiser,
    ) -> None:
        self.method = method
        self.cfg = config
        self.anchors = anchors
        self.streams = streams
        self.init = initialiser
        self.imu = ImuBuffer()
        self.wheel = WheelTrack()
        # standstills, which weigh the LOS/NLOS evidence of repeated ranges (`graph.rest`;
        # with an IMU, isam2 only: the online passes of isam2-smoothed and batch seed a
        # whole-log solve that weighs every range alike, and isam2-smoothed's held-out
        # range-model choice on ISAS-Walk1, a near tie, flipped from the seed's classes)
        self._rest = (RestEvidence(config.init, "wheel" in streams)
                      if "imu" in streams and method is Method.ISAM2 else None)
        self.builder: GraphBuilder | None = None
        self._range_priors: RangePriors | None = None  # the NLOS classifier's, if any
        self.smoother: OnlineSmoother | None = None
        self._chunk = (BATCH_CHUNK if method is Method.BATCH
                       else keyframes_per_update(config.graph, streams))
        self._pending: list[Increment] = []
        self._last_t: int | None = None
        self._all_steps: list[int] = []  # every step epoch (offline back-fill)
        # per keyframe: smoothed (as it left the window) pose/velocity/bias
        self._kf_pose: dict[int, gtsam.Pose3] = {}
        self._kf_vel: dict[int, np.ndarray] = {}
        self._kf_bias: dict[int, gtsam.imuBias.ConstantBias] = {}
        self._saved_upto = 0
        self._kf_pred: dict[int, gtsam.Pose3] = {}  # keyframe poses as first predicted
        self._pred_upto = 0
        self._reanchors: list[dict[str, Any]] = []
        self._rebuilds: list[dict[str, Any]] = []  # smoother rebuilt, nothing lost
        self._update_latency: list[float] = []
        self._init_t: int | None = None
        self._batch: offline.BatchResult | None = None
        # the first keyframe's final pose and covariance, for `pre_start` (set by `finish`)
        self._first_kf: tuple[gtsam.Pose3, np.ndarray | None] | None = None
        self._reviews = ReviewQueue()
        self._review_inc: Increment | None = None
        self._n_reviewed = 0
        self._n_switches = 0
        self._hyp_key: tuple | None = None
        self._hyp_count = 0
        # the hypothesis (anchors, LOS flags) the search adopted, while it holds it
        self._adopted: tuple | None = None
        self._batch_wall = 0.0
        self._wheel_offset_s: float | None = None  # batch: the wheel time offset chosen, s
        # batch: the wheel noise factors (translation, heading) fitted, times the configured
        self._wheel_noise: tuple[float, float] | None = None
        # batch: the IMU noise inflation fitted (times the [imu] noise)
        self._imu_inflation: float | None = None
        # batch: the keyframes its noise and time-offset fits look at (`_evidence_windows`)
        self._windows: EvidenceWindows | None = None
        # batch: what its fits start from, built once per solve (`batch_inputs`), and the
        # motion fit's solution at the chosen wheel offset (a start for the IMU noise fit)
        self._initial: gtsam.Values | None = None
        self._motion_fit: gtsam.Values | None = None
        # online IMU noise fits (`_fit_imu_online`): the last one's graph age, s, and each
        self._imu_fit_age: float | None = None
        self._imu_fits: list[dict[str, Any]] = []
        self._online_imu_inflation: float | None = None  # the online graph's, once started
        self._static: PoseEstimate | None = None  # standstill fix before the start
        # pose covariances (ROS order, map axes; `graph.marginal_covariances`): the newest
        # solved keyframe's (time, position, covariance, velocity covariance) that the
        # causal output carries (the offline outputs': `_batch_covariances`)
        self._with_cov = config.graph.marginal_covariances is not False  # auto: on
        self._head_cov: tuple[int, np.ndarray, np.ndarray, np.ndarray | None] | None = None
        self._cov_latency: list[float] = []
        # the lag window's spread in map x, y over its LOS/NLOS assignments (m^2, from the
        # review's `los_subset_search`), added to the marginals as batch adds its stretches'
        self._shift_moment = np.zeros((2, 2))

    # ------------------------------------------------------------------ input
    def add_imu(self, t_ns: np.ndarray, gyro: np.ndarray, accel: np.ndarray) -> None:
        """IMU batch: stamps (N,) ns, gyro (N,3) rad/s, specific force (N,3) m/s^2."""
        self.imu.add(t_ns, gyro, accel)
        if self._rest is not None:
            self._rest.add_imu(t_ns, gyro, accel)
        if self.builder is None:
            self.init.add_imu(t_ns, gyro, accel)

    def add_wheel(self, t_ns: np.ndarray, v: np.ndarray, omega: np.ndarray) -> None:
        """Wheel batch: stamps (N,) ns, forward speed (N,) m/s, yaw rate (N,) rad/s."""
        self.wheel.add(t_ns, v, omega)
        if self._rest is not None:
            self._rest.add_wheel(t_ns, v, omega)
        if self.builder is None:
            self.init.add_wheel(t_ns, v, omega)

    def use_range_priors(self, priors: RangePriors) -> None:
        """Take the learned NLOS classifier's P(NLOS) per range as each range's prior
        odds in the LOS/NLOS mixture (online and batch)."""
        self._range_priors = priors
        if self.builder is not None:
            self.builder.use_priors(priors)

    def add_ranges(self, t_ns: np.ndarray, anchor: np.ndarray, rng: np.ndarray) -> None:
        """Range batch: stamps (N,) ns, anchor index (N,), range (N,) m."""
        if self.builder is None:
            self.init.add_ranges(t_ns, anchor, rng)
        else:
            self.builder.add_ranges(t_ns, anchor, rng)

    def add_poses(self, t_ns: np.ndarray, position: np.ndarray, quat_xyzw: np.ndarray,
                  covariance: np.ndarray) -> None:
        """External poses: stamps (N,) ns, base position (N,3) m and quaternion (N,4) xyzw
        in the map frame, covariance (N,6,6) ROS order (`graph.pose_factor`)."""
        if self.builder is None:
            self.init.add_poses(t_ns, position, quat_xyzw, covariance)
        else:
            self.builder.add_poses(t_ns, position, quat_xyzw, covariance)

    # ------------------------------------------------------------------ processing
    def step(self, t_ns: int) -> None:
        """Process all data with stamps <= t_ns (see the module docstring)."""
        self._last_t = int(t_ns)
        self._all_steps.append(int(t_ns))
        if self.builder is None:
            state = self.init.try_initialise(int(t_ns))
            if state is None:
                fix = self.init.standstill_fix(int(t_ns))
                self._static = None if fix is None else PoseEstimate(int(t_ns), *fix)
                return
            self._static = None
            self._start(state)
        b = self.builder
        assert b is not None
        while b.next_time() <= t_ns:
            self._pending.append(b.next())
            if len(self._pending) >= self._chunk:
                self._flush()

    def _backdated(self, state: Any) -> Any:
        """The start state carried back along the wheel track by `graph.start_backdate`
        seconds (no earlier than the first wheel sample, range and IMU sample), so that the
        graph's first keyframe precedes the data buffered while the start was found (with
        an IMU and no wheels: `_backdated_imu`); `state` itself with neither or when there
        is nothing to gain.

        Off by default for the online pass: where the start is poor (NLOS, three anchors)
        the buffered ranges are classified against a poor prediction and pull the track
        (docs/results.md, "Backdated starts"); the whole-log refit turns it on.
        """
        w = self.wheel
        back_ns = round(self.cfg.graph.start_backdate * NS_PER_S)
        if back_ns > 0 and "wheel" not in self.streams and dataclasses.is_dataclass(state):
            return self._backdated_imu(state, back_ns)
        if (back_ns <= 0 or "wheel" not in self.streams or len(w) < 2
                or not dataclasses.is_dataclass(state)):
            return state
        t_init = int(state.t_ns)
        floor = [t_init - back_ns, int(w.t[0])]
        t_pre = self.init.pre_range_arrays()[0] if self.init.pre_ranges else np.zeros(0)
        if len(t_pre):
            floor.append(int(t_pre.min()))
        if "imu" in self.streams and self.imu.first_t is not None:
            floor.append(self.imu.first_t)
        t_back = max(floor)
        if t_back > t_init - round(NS_PER_S / self.cfg.graph.keyframe_rate):
            return state
        rel = se2_between(w.at(np.array([t_init], np.int64)), w.at(np.array([t_back], np.int64)))
        pose = gtsam.Pose3(gtsam.Rot3(np.asarray(state.R_map_base, np.float64)),
                           np.asarray(state.position, np.float64)).compose(se2_to_pose3(rel[0]))
        i = int(np.clip(np.searchsorted(w.t, t_back, side="left"), 0, len(w) - 1))
        rot = pose.rotation().matrix()
        vel = rot @ np.array([float(w.v[i]), 0.0, 0.0])
        return dataclasses.replace(state, t_ns=t_back, position=np.asarray(pose.translation()),
                                   R_map_base=rot, velocity=vel)

    def _backdated_imu(self, state: Any, back_ns: int) -> Any:
        """An IMU log without wheels: the start carried back by `back_ns` (no earlier than
        the first range and IMU sample): the attitude by the gyro integrated backwards (at
        the start's gyro bias), the position the initialiser's UWB fix there (its spread as
        sigma, no tighter than the start's), the velocity from that fix and the one
        2 x PROVISIONAL_FIX_S later, the heading sigma widened by BACKDATE_YAW_DRIFT.
        `state` itself where no fix is available there."""
        if "imu" not in self.streams or self.imu.first_t is None:
            return state
        t_init = int(state.t_ns)
        floor = [t_init - back_ns, self.imu.first_t]
        t_pre = self.init.pre_range_arrays()[0] if self.init.pre_ranges else np.zeros(0)
        if len(t_pre):
            floor.append(int(t_pre.min()))
        t_back = max(floor)
        if t_back > t_init - round(NS_PER_S / self.cfg.graph.keyframe_rate):
            return state
        fix = self.init.provisional(t_back + round(PROVISIONAL_FIX_S * NS_PER_S))
        later = self.init.provisional(t_back + round(3 * PROVISIONAL_FIX_S * NS_PER_S))
        if fix is None or later is None:
            return state
        vel = (np.asarray(later.position, np.float64) - np.asarray(fix.position, np.float64)
               ) / (2 * PROVISIONAL_FIX_S)
        r_bs = pose_from_xyzq(self.cfg.extrinsics.imu_in_base).rotation().matrix()
        turn = self.imu.rotation_between(t_back, t_init, state.gyro_bias, r_bs)
        r_back = np.asarray(state.R_map_base, np.float64) @ turn.T
        return dataclasses.replace(
            state, t_ns=t_back, position=np.asarray(fix.position, np.float64),
            R_map_base=r_back, velocity=vel,
            position_sigma=max(float(fix.position_sigma), float(state.position_sigma)),
            yaw_sigma=min(float(state.yaw_sigma) + BACKDATE_YAW_DRIFT, np.pi))

    def _start(self, state: Any) -> None:
        self._init_t = int(state.t_ns)
        state = self._backdated(state)
        self.builder = GraphBuilder(
            self.cfg, self.anchors, self.streams, state, self.imu, self.wheel,
            record=self.method is not Method.ISAM2, seeding=self.method is Method.BATCH,
            recent_s=ONLINE_WINDOW_S, rest=self._rest,
        )
        self._online_imu_inflation = self.builder.imu_inflation
        self.builder.use_priors(self._range_priors)
        for t, a, r in self.init.pre_ranges:
            self.builder.add_ranges(t, a, r)
        self.init.pre_ranges.clear()
        self.builder.add_poses(*self.init.pose_arrays())
        self.smoother = OnlineSmoother(self.cfg.graph.lag)
        self._pending.append(self.builder.first())
        self._flush()
        log.info("graph initialised at t=%.3f s (position sigma %.2f m, yaw sigma %.2f rad)",
                 state.t_ns * 1e-9, state.position_sigma, state.yaw_sigma)

    def _merge_pending(self) -> Increment:
        inc = self._pending[0]
        for p in self._pending[1:]:
            inc.merge(p)
        self._pending.clear()
        if self._review_inc is not None:
            inc.merge(self._review_inc)
            self._review_inc = None
        return inc

    def _flush(self) -> None:
        if not self._pending:
            return
        b, sm = self.builder, self.smoother
        assert b is not None and sm is not None
        inc = self._merge_pending()
        for kk in range(self._pred_upto, b.k + 1):  # keyframes as predicted when built
            if inc.values.exists(X(kk)):
                self._kf_pred[kk] = inc.values.atPose3(X(kk))
        self._pred_upto = b.k + 1
        tic = time.perf_counter()
        try:
            idx, remap = sm.update(inc)
            if remap is not None:
                self._smoother_rebuilt(b, remap)
            diverged = self._diverged(sm, b)
            if diverged:
                self._reanchor(diverged, solved=False)
                self._update_latency.append(time.perf_counter() - tic)
                return
            for batch, slots in inc.reviews:
                batch.factors = [[idx[p] for p in ps] for ps in slots]
                self._reviews.append(batch)
            for batch, j, ps in inc.replaced:
                batch.factors[j] = [idx[p] for p in ps]
            k = b.k
            b.set_head(sm.pose(k),
                       sm.velocity(k) if b.has_imu else None,
                       sm.bias(k) if b.has_imu else None,
                       np.array([sm.range_bias(a) for a in range(len(self.anchors))])
                       if b.with_bias else None)
            self._read_nlos_states(sm, b)
            self._save_head_covariance(sm, b)
            self._save_leaving(sm, b)
            self._review(sm, b)
            self._judge_rest(sm, b)
            self._fit_imu_online(sm, b)
        except (RuntimeError, ValueError) as exc:  # GTSAM raises both
            self._reanchor(f"{type(exc).__name__}: {exc}")
        self._update_latency.append(time.perf_counter() - tic)

    def _smoother_rebuilt(self, b: GraphBuilder, remap: dict[int, int]) -> None:
        """The smoother was rebuilt after GTSAM's marginalisation failure
        (`OnlineSmoother._rebuild`): move the queued reviews' factor indices to the new
        smoother's (-1: the factor was summarised, nothing left to replace)."""
        log.info("iSAM2 marginalisation failed at keyframe %d: smoother rebuilt from its "
                 "factors (nothing lost)", b.k)
        self._rebuilds.append({"keyframe": b.k, "t_ns": b.time_of(b.k)})
        for rb in self._reviews:
            rb.factors = [[remap.get(i, -1) for i in fs] for fs in rb.factors]

    @staticmethod
    def _diverged(sm: OnlineSmoother, b: GraphBuilder) -> str:
        """Why the update just solved cannot be a motion ('' when it can): the newest
        keyframe's speed (its velocity state, else the step from the keyframe before)
        above MAX_SOLVED_SPEED, the mark of a diverged Gauss-Newton step."""
        k = b.k
        try:
            if b.has_imu:
                speed = float(np.linalg.norm(sm.velocity(k)))
            elif k < 1:
                return ""
            else:
                dt = (b.time_of(k) - b.time_of(k - 1)) / NS_PER_S
                step = sm.pose(k).translation() - sm.pose(k - 1).translation()
                speed = float(np.linalg.norm(step)) / dt if dt > 0 else 0.0
        except (RuntimeError, IndexError, ValueError):  # k - 1 not in this smoother
            return ""
        if not speed <= MAX_SOLVED_SPEED:  # NaN too
            return f"the solve diverged: keyframe {k} at {speed:.3g} m/s"
        return ""

    def _fit_imu_online(self, sm: OnlineSmoother, b: GraphBuilder) -> None:
        """`graph.imu_noise_inflation = "auto"`: when one is due (`noise_fit.online_fit_due`),
        the IMU noise inflation of the evidence over the newest keyframes
        (`noise_fit.fit_imu_window`, from their estimates so far: causal) for the IMU
        factors built from now on; each fit's graph age, result and wall time go into the
        report."""
        rec = b.recent
        age = b.stamp(b.k)
        if rec is None or not rec.ka or not noise_fit.online_fit_due(age, self._imu_fit_age):
            return
        self._imu_fit_age = age
        tic = time.perf_counter()
        values = self._window_values(sm, b, rec.ka[0])
        f = None
        if values is not None:
            k0 = rec.ka[0]
            priors = b.restart_priors(k0, values.atPose3(X(k0)), values.atVector(V(k0)),
                                      values.atConstantBias(B(k0)))
            f = noise_fit.fit_imu_window(
                self.cfg, rec, priors, values, b.scale if b.with_scale else None,
                b.range_bias if b.with_bias else None, b.robust_sigma(), b.imu_inflation)
        if f is not None:
            b.set_imu_inflation(f)
            self._online_imu_inflation = f
        self._imu_fits.append({"graph_age_s": round(age, 3), "inflation": b.imu_inflation,
                               "fitted": f is not None,
                               "wall_ms": round(1e3 * (time.perf_counter() - tic), 1)})

    def _window_values(self, sm: OnlineSmoother, b: GraphBuilder, k0: int
                       ) -> gtsam.Values | None:
        """The estimates so far of keyframes k0 .. newest (as they left the smoother, or
        its current ones) and the anchors; None where one is missing."""
        values = gtsam.Values()
        try:
            for k in range(k0, b.k + 1):
                if k < self._saved_upto:
                    values.insert(X(k), self._kf_pose[k])
                    values.insert(V(k), self._kf_vel[k])
                    values.insert(B(k), self._kf_bias[k])
                else:
                    values.insert(X(k), sm.pose(k))
                    values.insert(V(k), sm.velocity(k))
                    values.insert(B(k), sm.bias(k))
        except (KeyError, RuntimeError, IndexError, ValueError):
            return None
        for a in range(len(self.anchors)):
            values.insert(L(a), self.anchors.positions[a])
        return values

    def _review(self, sm: OnlineSmoother, b: GraphBuilder) -> None:
        """Re-classify the ranges in the lag window with the smoothed estimate (fixed-lag EM).

        At insertion a range is classified by the forward filter against a one-step
        prediction. After each update, every range at least REVIEW_MIN_AGE_S old and
        still REVIEW_MARGIN_S (plus one update) inside the lag window is classified again:
        residuals at the smoothed keyframes and NLOS states, then forward-backward per
        anchor over the window (from the forward prior of its first range, with the
        residual jumps), so
        the ranges that followed a range weigh in as they do in batch. Ranges whose
        responsibility moved by more than REVIEW_CHANGE get their factors replaced in the
        next update (iSAM2 factor removal).

        Before that, `uwb.los_subset_search` tests every LOS/NLOS assignment of the
        window's newer ranges (`_search_switch`: those within the anchors' mean time
        between class changes) with a rigid shift of their track: when another assignment
        beats the current one by SEARCH_SWITCH_NATS in SEARCH_PERSIST consecutive reviews,
        those ranges are classified against the shifted track and its NLOS excesses
        instead, while the search still finds it the best (an escape from the local
        optimum that EM alone stays in).
        """
        now = b.time_of(b.k)
        queued, poses = self._reviewable(sm, b, now)
        if not queued:
            return
        mix = b.mixture
        if b.smoothed_sigma_los is not None:  # residuals at the smoothed estimate
            mix = copy.copy(mix)
            mix.sigma_los = b.smoothed_sigma_los
        q = self._reviews
        cols = q.columns()
        if queued[-1] == len(queued) - 1:  # the queue's first batches (all but on a failure)
            rows: slice | np.ndarray = slice(0, q.rows(queued[-1]).stop)
        else:
            rows = np.concatenate([np.arange(q.rows(i).start, q.rows(i).stop) for i in queued])
        anchor, z, t, prior = (cols[c][rows] for c in ("anchor", "z", "t_ns", "prior"))
        batches = [q[i] for i in queued]
        # batch by batch: the same products as the keyframes' (BLAS rounds by shape)
        p = np.concatenate([rb.tag_kf @ poses[rb.ka][0] + poses[rb.ka][1] for rb in batches])
        h = np.linalg.norm(p - self.anchors.positions[anchor], axis=1)
        d = b.class_offset(anchor)
        e = self._smoothed_excess(sm, b, anchor, cols["seg"][rows], d + mix.mu_nlos)
        r_los = z - h - d
        r_nlos = z - h - e
        g_cur = cols["g"][rows].copy()
        if REVIEW_SEARCH:
            span = t >= now - round(mix.class_change_time * NS_PER_S)
            r_los, r_nlos = self._search_switch(b, mix, anchor, p, h, r_los, r_nlos, g_cur,
                                                span, cols["ess"][rows])
        ll_l, ll_n = mix.log_likelihoods(r_los, r_nlos, 0.03**2)
        ll_n = ll_n + cols["evidence"][rows]  # the classifier's
        ess = cols["ess"][rows]  # repeated ranges at rest share one error (`rest`)
        ll_l, ll_n = ll_l * ess, ll_n * ess
        jl = jump_log_likelihoods(residual_jumps_by_anchor(t, anchor, r_los), e - d, mix)
        p_switch = switch_probabilities(t, anchor, mix.switch_time)  # first: `prior` given
        g = hmm_smooth_by_anchor(anchor, ll_l, ll_n, p_switch, mix.p_nlos, jl, prior)
        self._replace_moved(b, queued, now, g, g_cur, e, r_los)

    def _reviewable(self, sm: OnlineSmoother, b: GraphBuilder, now: int
                    ) -> tuple[list[int], dict[int, tuple[np.ndarray, np.ndarray]]]:
        """The range batches `_review` classifies again (their positions in the queue: old
        enough, clear of what the next update marginalises; older ones leave the queue)
        and their keyframes' smoothed poses (rotation transposed (3,3) and translation (3,)
        m of the base in the map frame)."""
        # the replacements go in with the next update, which adds `_chunk` keyframes and
        # marginalises by as much: stay clear of what it will remove
        margin = REVIEW_MARGIN_S + self._chunk / self.cfg.graph.keyframe_rate
        oldest = now - round((self.cfg.graph.lag - margin) * NS_PER_S)
        q = self._reviews
        while q and b.time_of(q[0].ka) < oldest:
            q.popleft()
        # time_of(ka) > horizon: ka > last_ka
        last_ka = (now - round(REVIEW_MIN_AGE_S * NS_PER_S) - b.t0) // b.period_ns
        poses: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        queued = []
        for i, rb in enumerate(q):
            if rb.ka > last_ka:
                break
            if rb.ka not in poses:
                try:
                    m = sm.pose(rb.ka).matrix()
                except (RuntimeError, IndexError):
                    continue
                poses[rb.ka] = (m[:3, :3].T, m[:3, 3])
            queued.append(i)
        return queued, poses

    def _judge_rest(self, sm: OnlineSmoother, b: GraphBuilder) -> None:
        """A still run of the IMU (`rest.RestEvidence.pending`) judged rest or glide from
        the smoothed velocity at its first keyframe (`decide`); a rest's keyframes so far,
        clear of what the next update marginalises, get their zero velocities with it (the
        later ones get theirs as they are built). The velocity must have come from before
        the run (the keyframe before it solved): a run the graph started in is no rest."""
        rest = self._rest
        if rest is None:
            return
        k = b.k
        now = b.time_of(k)
        run = rest.pending(now)
        if run is None:
            return
        j0 = max(-(-(run - b.t0) // b.period_ns), 0)  # the run's first keyframe
        v = cov = None
        if j0 >= 1:
            try:
                sm.velocity(j0 - 1)  # raises where the smoother has no keyframe before it
                v, cov = sm.velocity(j0), sm.velocity_covariance(j0)
            except (RuntimeError, IndexError, ValueError):
                v = cov = None
        if not rest.decide(run, v, cov):
            return
        margin = REVIEW_MARGIN_S + self._chunk / self.cfg.graph.keyframe_rate
        oldest = now - round((self.cfg.graph.lag - margin) * NS_PER_S)
        if self._review_inc is None:  # the factors the next update adds
            self._review_inc = Increment()
        for j in range(j0 + 1, k + 1):
            if b.time_of(j) >= oldest and rest.at_rest(b.time_of(j - 1), b.time_of(j)):
                b.zero_velocity(self._review_inc.graph, j)

    def _smoothed_excess(self, sm: OnlineSmoother, b: GraphBuilder, anchor: np.ndarray,
                         seg: np.ndarray, default: np.ndarray) -> np.ndarray:
        """Per range, the smoothed NLOS state of its (anchor, segment) where the smoother
        holds one, else `default` (m)."""
        # the (anchor, segment) pairs, sorted by anchor then segment (segments >= 0: the
        # builder drops ranges before its first keyframe), as one int64 code each
        code, inv = unique_inverse(anchor.astype(np.int64) * _PAIR + seg)
        created, value = b.e_created, sm.double
        e_pair = []
        for a, sg in zip((code // _PAIR).tolist(), (code % _PAIR).tolist(), strict=True):
            e = math.nan
            if (a, sg) in created:
                try:
                    e = value(nlos_key(a, sg))
                except (RuntimeError, IndexError):
                    pass
            e_pair.append(e)
        e_r = np.array(e_pair, dtype=np.float64)[inv]
        return np.where(np.isnan(e_r), default, e_r)

    def _search_switch(
        self, b: GraphBuilder, mix: NlosModel, anchor: np.ndarray, p: np.ndarray,
        h: np.ndarray, r_los: np.ndarray, r_nlos: np.ndarray, g_cur: np.ndarray,
        span: np.ndarray, ess: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray]:
        """`uwb.los_subset_search` over the ranges of the window at `span` (bool mask: those
        newer than the anchors' mean time between class changes, `NlosModel.
        class_change_time`; tag positions `p`, predicted ranges `h`, each range's share of
        one range's evidence `ess`, `graph.rest`): the LOS and NLOS residuals of those
        ranges against the better hypothesis' shifted track and NLOS
        excesses once it has won SEARCH_PERSIST reviews in a row, and for as long after as
        the search still finds it the best; else as given.

        The span: the search takes each anchor as in one class with one excess, and the
        track as shifted rigidly, over it; over a whole 10 s lag window that held too seldom
        and the switches it adopted were mostly wrong. The hold: an adopted hypothesis
        becomes the current classes, and if the smoother has not yet moved the track to
        it, EM against the current track reverted it at the next review and the search
        adopted it again SEARCH_PERSIST reviews later, a limit cycle of factor replacements
        (docs/results.md, session 40)."""
        a_s = anchor[span]
        u = (p[span] - self.anchors.positions[a_s])[:, :2] / np.maximum(h[span], 1e-6)[:, None]
        # the shift's moment goes only into the head covariance (`_save_head_covariance`)
        hyp = los_subset_search(a_s, r_los[span], u, g_cur[span], mix,
                                moment=self._head_cov_wanted(), weights=ess[span])
        self._shift_moment = np.zeros((2, 2)) if hyp is None else hyp.shift_moment
        better = (hyp is not None and hyp.gain > SEARCH_SWITCH_NATS
                  and bool(np.any(hyp.los != hyp.current)))
        found = None if hyp is None else (tuple(hyp.anchors.tolist()), tuple(hyp.los.tolist()))
        key = found if better else None
        self._hyp_count = self._hyp_count + 1 if better and key == self._hyp_key else 1
        self._hyp_key = key
        held = not better and found is not None and found == self._adopted
        if not held:
            self._adopted = None
        if not (held or (better and self._hyp_count >= SEARCH_PERSIST)):
            return r_los, r_nlos
        assert hyp is not None
        if not held:
            self._n_switches += 1
            self._adopted = found
        r_los, r_nlos = r_los.copy(), r_nlos.copy()
        r_los[span] -= u @ hyp.delta
        exc = np.full(len(b.range_bias), mix.mu_nlos)
        exc[hyp.anchors] = np.where(hyp.los, mix.mu_nlos, hyp.excess)
        r_nlos[span] = r_los[span] - exc[a_s]
        return r_los, r_nlos

    def _replace_moved(self, b: GraphBuilder, queued: list[int], now: int,
                       g: np.ndarray, g_cur: np.ndarray, e: np.ndarray,
                       r_los: np.ndarray) -> None:
        """After `_review`'s E-step (responsibilities `g`, were `g_cur`, of the batches at
        `queued` in the queue): the ranges whose responsibility moved by more than
        REVIEW_CHANGE get new factors in the next update; the batches old enough feed the
        smoothed LOS sigma once."""
        off = 0
        stat_age = now - round(SMOOTHED_STAT_AGE_S * NS_PER_S)
        # which batches have a range to replace, in one pass (most have none)
        moved = np.abs(g - g_cur) > REVIEW_CHANGE
        q = self._reviews
        sizes = [len(q[i].z) for i in queued]
        any_moved = np.add.reduceat(moved, np.cumsum([0, *sizes[:-1]])) > 0
        for i, n, has in zip(queued, sizes, any_moved.tolist(), strict=True):
            rb = q[i]
            start, off = off, off + n
            if not rb.counted and b.time_of(rb.ka) <= stat_age:
                rb.counted = True
                b.add_smoothed_residuals(r_los[start:off], g[start:off])
            if not has:
                continue
            gb, eb = g[start:off], e[start:off]
            changed = np.flatnonzero(np.abs(gb - rb.g) > REVIEW_CHANGE)
            if self._review_inc is None:
                self._review_inc = Increment()
            inc = self._review_inc
            rows = changed.tolist()
            for j in rows:
                inc.remove.extend(i for i in rb.factors[j] if i >= 0)
            slots = b.range_factors(inc, rb.ka, rb.anchor, rb.z, rb.tag_kf, rb.seg, gb, eb, rows,
                                    share=rb.share)
            inc.replaced.extend((rb, j, pos) for j, pos in zip(rows, slots, strict=True))
            q.set_g(i, changed, gb[changed])
            b.records.g_online[rb.record][changed] = gb[changed]
            self._n_reviewed += len(changed)

    def _read_nlos_states(self, sm: OnlineSmoother, b: GraphBuilder) -> None:
        """Refresh the newest NLOS state estimate of each anchor still in the window."""
        horizon = b.stamp(b.k) - self.cfg.graph.lag + 0.5
        for a in np.flatnonzero(b.e_seg >= 0):
            if b.e_stamp[a] < horizon:
                continue
            try:
                b.e_est[a] = sm.double(nlos_key(int(a), int(b.e_seg[a])))
            except (RuntimeError, IndexError):
                b.e_seg[a] = -1

    def _save_leaving(self, sm: OnlineSmoother, b: GraphBuilder) -> None:
        """Store the estimates of keyframes about to be marginalised."""
        keep = int(self.cfg.graph.lag * self.cfg.graph.keyframe_rate) - self._chunk - 1
        upto = b.k - max(keep, 0)
        for k in range(self._saved_upto, upto + 1):
            self._save_kf(sm, b, k)
        self._saved_upto = max(self._saved_upto, upto + 1)
        b.learn_wheel_scale(self._kf_pose, upto)

    def _save_kf(self, sm: OnlineSmoother, b: GraphBuilder, k: int) -> None:
        try:
            self._kf_pose[k] = sm.pose(k)
            if b.has_imu:
                self._kf_vel[k] = sm.velocity(k)
                self._kf_bias[k] = sm.bias(k)
        except (RuntimeError, IndexError, ValueError):
            return  # not in this smoother (re-anchored): keep the earlier estimate if any

    def _head_cov_wanted(self) -> bool:
        """Whether the online head covariance (`_save_head_covariance`) is kept."""
        return self._with_cov and self.method is Method.ISAM2

    def _save_head_covariance(self, sm: OnlineSmoother, b: GraphBuilder) -> None:
        """isam2: the newest solved keyframe's marginal (plus the window's LOS/NLOS spread
        in x, y), carried to each epoch by `estimate()`; its cost (one marginal per
        update) is in `report()`."""
        if not self._head_cov_wanted():
            return
        tic = time.perf_counter()
        k = b.k
        try:
            cov = covariance.to_map(b.pose.rotation().matrix(), sm.pose_covariance(k))
            cov[:2, :2] += self._shift_moment
            vel = sm.velocity_covariance(k) if b.has_imu and not b.has_wheel else None
            self._head_cov = (b.time_of(k), np.asarray(b.pose.translation()), cov, vel)
        except (RuntimeError, IndexError, ValueError):
            self._head_cov = None
        self._cov_latency.append(time.perf_counter() - tic)

    def _reanchor(self, reason: str, solved: bool = True) -> None:
        """Restart the smoother at the newest keyframe with loose priors (never raises).
        `solved`: the failed smoother's estimates of the window still hold. After a
        diverged solve they do not: the window's keyframes are kept as predicted when
        built, and the newest is restarted as a lost track, its velocity zero within
        ONLINE_MAX_START_SPEED (as unknown as at a start) and its position within the
        anchor layout's radius of the prediction (the ranges, not a prediction that
        ran away, then place it)."""
        b = self.builder
        assert b is not None
        k = b.k
        log.warning("iSAM2 update failed at keyframe %d (%s): re-anchoring the graph",
                    k, reason.splitlines()[0] if reason else "error")
        self._reanchors.append({"keyframe": k, "t_ns": b.time_of(k), "reason": reason[:200]})
        # keep the window's keyframes: as the failed smoother last had them where it can
        # still tell, else as predicted when they were built
        old = self.smoother
        for kk in range(self._saved_upto, k + 1):
            if old is not None and solved:
                self._save_kf(old, b, kk)
            if kk not in self._kf_pose and kk in self._kf_pred:
                self._kf_pose[kk] = self._kf_pred[kk]
        self._saved_upto = k + 1
        b.e_seg[:] = -1
        b.e_created.clear()
        self._reviews.clear()
        self._review_inc = None
        self.smoother = OnlineSmoother(self.cfg.graph.lag)
        self._head_cov = None
        inc = Increment()
        s = b.stamp(k)
        vel = b.vel if solved or b.vel is None else np.zeros(3)
        inc.graph.push_back(
            b.restart_priors(k, b.pose, b.vel, b.bias) if solved else
            b.restart_priors(k, b.pose, vel, b.bias, position_sigma=self._layout_radius(),
                             velocity_sigma=ONLINE_MAX_START_SPEED))
        inc.values.insert(X(k), b.pose)
        inc.stamps[X(k)] = s
        if b.has_imu:
            inc.values.insert(V(k), vel)
            inc.values.insert(B(k), b.bias)
            inc.stamps[V(k)] = s
            inc.stamps[B(k)] = s
        for a in range(len(self.anchors)):
            inc.values.insert(L(a), self.anchors.positions[a])
            inc.stamps[L(a)] = s
            if b.with_bias:
                inc.graph.add(gtsam.PriorFactorDouble(
                    D(a), float(b.range_bias[a]), gtsam.noiseModel.Isotropic.Sigma(1, 0.05)))
                inc.values.insert(D(a), float(b.range_bias[a]))
                inc.stamps[D(a)] = s
        if b.with_bias:
            c = float(np.mean(b.range_bias))
            inc.graph.add(gtsam.PriorFactorDouble(C, c, gtsam.noiseModel.Isotropic.Sigma(1, 0.05)))
            inc.values.insert(C, c)
            inc.stamps[C] = s
        try:
            self.smoother.update(inc)
        except RuntimeError as exc:  # pragma: no cover - priors on every key: cannot fail
            raise EstimatorError(f"graph re-anchoring failed: {exc}") from None

    def _layout_radius(self) -> float:
        """The anchors' largest distance from their centroid, m (at least the 0.5 m of
        an ordinary re-anchor): how far the ranges reach to place a lost track."""
        p = self.anchors.positions
        return max(float(np.max(np.linalg.norm(p - p.mean(axis=0), axis=1))), 0.5)

    def forget_before(self, t_ns: int) -> None:
        """isam2 only (live use, `uwbfuse.Localizer`): drop what only the offline outputs
        (isam2-smoothed, batch) and the report's totals keep of the time before `t_ns`,
        which must lie before the lag window: keyframe estimates (but those of the online
        IMU noise fit's window, `_window_values`), range records, wheel samples, step
        epochs; latency samples are kept for the last LIVE_LATENCY_KEPT updates. Memory
        then stays flat however long the run; `report()` counts the ranges since `t_ns`
        only. The causal estimates are unchanged."""
        b = self.builder
        if self.method is not Method.ISAM2 or b is None:
            return
        t_ns = min(int(t_ns), b.time_of(b.k) - round(self.cfg.graph.lag * NS_PER_S))
        k_old = min((t_ns - b.t0) // b.period_ns, self._saved_upto)
        # the online IMU noise fit's window (`_window_values`) keeps its estimates
        k_kf = min(k_old, b.recent.ka[0]) if b.recent is not None and b.recent.ka else k_old
        for kf in (self._kf_pose, self._kf_vel, self._kf_bias, self._kf_pred):
            for k in [k for k in kf if k < k_kf]:
                del kf[k]
        b.records.forget(int(k_old))
        self.wheel.drop_before(t_ns)
        self._all_steps = [s for s in self._all_steps if s >= t_ns]
        for lat in (self._update_latency, self._cov_latency):
            del lat[:-LIVE_LATENCY_KEPT]

    # ------------------------------------------------------------------ output
    @property
    def provisional(self) -> bool:
        """`estimate()` is a standstill fix from before the start (see `prestart.PreStart`)."""
        return self.builder is None

    def estimate(self) -> PoseEstimate | None:
        """Causal pose at the last step time, or None before initialisation."""
        if self.builder is None:
            return self._static
        if self._last_t is None:
            return None
        p = self.builder.predict(self._last_t)
        pos = np.asarray(p.translation())
        return PoseEstimate(self._last_t, pos, _quat_xyzw(p),
                            self._causal_covariance(self._last_t, p))

    def _causal_covariance(self, t: int, pose: gtsam.Pose3) -> np.ndarray | None:
        """The newest solved keyframe's covariance carried to `pose` at t by the motion
        model's noise over the gap (`covariance.carry`), or None without one."""
        if self._head_cov is None:
            return None
        b = self.builder
        assert b is not None
        t_k, p_k, cov_k, vel_cov = self._head_cov
        noise = covariance.to_map(pose.rotation().matrix(), b.motion_noise(t_k, t))
        if vel_cov is not None:  # IMU only: the keyframe velocity's error over the gap
            noise[:3, :3] += vel_cov * ((t - t_k) / NS_PER_S) ** 2
        return covariance.carry(cov_k, p_k, np.asarray(pose.translation()), noise[None])[0]

    def _finalise_online(self) -> None:
        b, sm = self.builder, self.smoother
        assert b is not None and sm is not None
        self._flush()
        for k in range(self._saved_upto, b.k + 1):
            self._save_kf(sm, b, k)
        self._saved_upto = b.k + 1

    def finish(self) -> PoseStream | None:
        """Final trajectory (isam2-smoothed, batch) at the step epochs, or None (isam2)."""
        if self.method is Method.ISAM2 or self.builder is None:
            return None
        self._finalise_online()
        b = self.builder
        n = b.k + 1
        tic = time.perf_counter()
        self._run_batch()
        self._batch_wall = time.perf_counter() - tic
        assert self._batch is not None
        vals = self._batch.values
        poses = [vals.atPose3(X(k)) for k in range(n)]
        covs = self._batch_covariances(n)
        return self._interpolate(poses, covs)

    def _batch_covariances(self, n: int) -> np.ndarray | None:
        """Keyframe covariances from the marginals of `BatchResult.marginals`' graph (the
        final LM round's factors at the solution, each range's weighted by the information
        its LOS/NLOS ambiguity leaves) plus, in x, y, the spread of the track over the
        stretches' LOS/NLOS assignments; None when off or singular."""
        res = self._batch
        if not self._with_cov or res is None or res.marginals is None:
            return None
        tic = time.perf_counter()
        try:
            graph, moment = res.marginals()
            covs = covariance.keyframe_marginals(graph, res.values, n)
            covs[:, :2, :2] += moment  # the LOS/NLOS assignments' spread in x, y
        except RuntimeError as exc:  # indeterminant system: no covariance, said so
            log.warning("batch: no pose covariance (marginals failed: %s)",
                        str(exc).splitlines()[0] if str(exc) else "error")
            covs = None
        self._cov_latency.append(time.perf_counter() - tic)
        return covs

    def _run_batch(self) -> None:
        b = self.builder
        assert b is not None
        # the online pass built its IMU factors at the inflations of its time (`auto`):
        # one, its last, for the wheel fits, then the whole log's own
        b.complete_imu_records(b.imu_inflation)
        self._windows = None
        self._initial = self._motion_fit = None
        self._complete_wheel_records()
        self._fit_imu_noise()
        graph, initial, rec = self.batch_inputs()
        self._batch = offline.solve(self.cfg, graph, initial, rec,
                                    self.anchors.positions, b.k + 1, b.mixture, b.t0, b.scale,
                                    has_wheel=b.has_wheel, with_scale=b.with_scale,
                                    wheel=b.wheel_records,
                                    planar=b.planar, windows=self._evidence_windows())

    def _complete_wheel_records(self) -> None:
        """The offline solve's wheel factors from the complete track
        (`complete_wheel_records`), at the wheel-to-range time offset that fits best: the
        maximum-likelihood one on a grid of half wheel periods (which interval a sample
        covers is what logs disagree on), from 0 and +-0.5 periods, stepping on past an edge
        while the edge scores best (to WHEEL_OFFSET_MAX_PERIODS), each scored by the error
        after one Huber LM of the recorded graph with the ranges at the online robust sigma
        (`offline.motion_fit_error`); then, at that offset, the wheel noise of greatest
        evidence (`noise_fit.fit_wheel_noise`, `graph.estimate_wheel_noise`)."""
        b = self.builder
        assert b is not None
        if not (b.has_wheel and len(self.wheel) > 1):
            b.complete_wheel_records()
            return
        period = float(np.median(np.diff(self.wheel.t)))
        graph, initial, _ = self.batch_inputs()  # the offset changes only factors and tags
        win = self._evidence_windows()
        errs: dict[float, float] = {}
        solved: dict[float, gtsam.Values] = {}

        def score(f: float) -> float:
            if f not in errs:  # from the solution at the nearest offset scored (warm start)
                near = min(solved, key=lambda x: abs(x - f), default=None)
                b.complete_wheel_records(round(f * period))
                errs[f], solved[f] = offline.motion_fit_error(
                    self.cfg, win.graph(graph, initial), initial if near is None else solved[near],
                    win.ranges(b.records.arrays()), b.scale if b.with_scale else None,
                    b.robust_sigma(), b.with_bias)
            return errs[f]

        for f in (0.0, 0.5, -0.5):
            score(f)
        # while the best offset is the search's edge, step on past it
        while True:
            best = min(errs, key=errs.get)
            lo, hi = min(errs), max(errs)
            if best == hi and hi < WHEEL_OFFSET_MAX_PERIODS:
                score(hi + 0.5)
            elif best == lo and lo > -WHEEL_OFFSET_MAX_PERIODS:
                score(lo - 0.5)
            else:
                break
        f = best
        if best - 0.5 in errs and best + 0.5 in errs:  # the parabola through the best three
            e0, e1, e2 = errs[best - 0.5], errs[best], errs[best + 0.5]
            curv = e0 - 2.0 * e1 + e2
            if curv > 0:
                f += 0.25 * (e0 - e2) / curv
        steps = sorted(errs)
        log.debug("batch wheel time offset: errors %s at %s periods -> %.3f",
                  [round(errs[x], 2) for x in steps], steps, f)
        self._wheel_offset_s = float(f * period / NS_PER_S)
        self._motion_fit = solved[best]
        b.complete_wheel_records(round(f * period))
        if self.cfg.graph.estimate_wheel_noise:
            graph, _, rec = self.batch_inputs()  # from the motion fit at the best offset
            fac = noise_fit.fit_wheel_noise(self.cfg, win.graph(graph, initial),
                                            solved[best], win.ranges(rec),
                                            b.scale if b.with_scale else None,
                                            b.robust_sigma(), b.with_bias,
                                            win.wheel(b.wheel_records),
                                            win.pose_index(b.pose_index))
            self._wheel_noise = (float(fac[0]), float(fac[1]))
            b.complete_wheel_records(round(f * period), self._wheel_noise)

    def _fit_imu_noise(self) -> None:
        """`graph.imu_noise_inflation = "auto"`: the offline solve's IMU factors at the
        inflation of greatest evidence over the whole log (`noise_fit.fit_imu_noise`,
        searched from the one the online pass used; its wheel factors as completed; its LM
        from the wheel offset search's solution when there was one). Without IMU and
        wheels, `graph.motion_accel_density = "auto"`: the constant-velocity prior's
        factors alike, at the acceleration density of greatest evidence."""
        b = self.builder
        assert b is not None
        g = self.cfg.graph
        auto = (g.motion_accel_density if b.cv_motion else g.imu_noise_inflation) == "auto"
        if not auto or not b.imu_records.k:
            return
        graph, initial, rec = self.batch_inputs()
        win = self._evidence_windows()
        self._imu_inflation = noise_fit.fit_imu_noise(
            self.cfg, win.graph(graph, initial),
            initial if self._motion_fit is None else self._motion_fit,
            win.ranges(rec), b.scale if b.with_scale else None, b.robust_sigma(),
            b.with_bias, win.imu(b.imu_records), win.pose_index(b.pose_index),
            b.imu_inflation)
        b.complete_imu_records(self._imu_inflation)

    def _evidence_windows(self) -> EvidenceWindows:
        """batch's noise and time-offset fits: the keyframes they look at
        (`graph.evidence_window`), computed once per solve (the recorded graph's factor
        structure does not change with the noise or the offset)."""
        b = self.builder
        assert b is not None and b.full_graph is not None
        if self._windows is None:
            stamps = np.array([b.stamp(k) for k in range(b.k + 1)])
            n_ranges = len(b.records.arrays()["z"])
            self._windows = EvidenceWindows.of(b.full_graph, window_mask(stamps, n_ranges),
                                               self._window_priors)
        return self._windows

    def _window_priors(self, k: int, values: gtsam.Values) -> gtsam.NonlinearFactorGraph:
        """Loose priors on keyframe k's state in `values` where an evidence window
        begins."""
        b = self.builder
        assert b is not None
        return b.restart_priors(k, values.atPose3(X(k)),
                                values.atVector(V(k)) if b.has_imu else None,
                                values.atConstantBias(B(k)) if b.has_imu else None,
                                anchors=False)

    def batch_inputs(self) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values,
                                    dict[str, np.ndarray]]:
        """isam2-smoothed and batch, after the online pass: what `offline.solve` starts from: the
        recorded non-range factors, the initial values (the online pass's keyframes as
        they left the window, anchors, range biases) and the range records
        (`RangeRecords.arrays`). `graph.reference` solves the same problem plainly."""
        b = self.builder
        assert b is not None and b.full_graph is not None and b.full_values is not None
        if self._initial is not None:
            return b.full_graph, self._initial, b.records.arrays()
        n = b.k + 1
        initial = gtsam.Values()
        for k in range(n):
            initial.insert(X(k), self._kf_pose.get(k, b.full_values.atPose3(X(k))))
            if b.has_imu:
                initial.insert(V(k), self._kf_vel.get(k, b.full_values.atVector(V(k))))
                initial.insert(B(k), self._kf_bias.get(
                    k, b.full_values.atConstantBias(B(k))))
        for a in range(len(self.anchors)):
            initial.insert(L(a), self.anchors.positions[a])
            if b.with_bias:
                initial.insert(D(a), float(b.range_bias[a]))
        if b.with_bias:
            initial.insert(C, float(np.mean(b.range_bias)) if len(b.range_bias) else 0.0)
        self._initial = initial
        return b.full_graph, initial, b.records.arrays()

    def _interpolate(self, poses: list[gtsam.Pose3], covs: np.ndarray | None) -> PoseStream:
        """Keyframe poses -> poses at the step epochs (linear position, nlerp attitude).

        Keyframe covariances `covs` (n,6,6, ROS order, map axes) blend linearly between
        the two keyframes (`covariance.blend`); epochs after the last keyframe carry its
        covariance by the motion model (`covariance.carry`)."""
        b = self.builder
        assert b is not None
        n = len(poses)
        pos = np.array([p.translation() for p in poses])
        quat = np.array([_quat_xyzw(p) for p in poses])
        for i in range(1, n):  # consistent quaternion hemisphere
            if np.dot(quat[i], quat[i - 1]) < 0:
                quat[i] = -quat[i]
        # every epoch from the first keyframe on (it precedes the start when backdated)
        t = np.array([s for s in self._all_steps if s >= b.t0], dtype=np.int64)
        u = (t - b.t0) / b.period_ns
        k0 = np.clip(np.floor(u).astype(np.int64), 0, n - 1)
        k1 = np.clip(k0 + 1, 0, n - 1)
        f = np.clip(u - k0, 0.0, 1.0)[:, None]
        f = np.where((k1 == k0)[:, None], 0.0, f)
        p = (1 - f) * pos[k0] + f * pos[k1]
        q = (1 - f) * quat[k0] + f * quat[k1]
        q /= np.linalg.norm(q, axis=1, keepdims=True)
        c = None if covs is None else covariance.blend(covs[k0], covs[k1], f[:, 0])
        # epochs after the last keyframe: odometry from the last keyframe
        late = np.flatnonzero(t > b.time_of(n - 1))
        if len(late):
            b.set_head(poses[-1])
            for i in late:
                pp = b.predict(int(t[i]))
                p[i] = pp.translation()
                q[i] = _quat_xyzw(pp)
                if c is not None and covs is not None:
                    noise = covariance.to_map(pp.rotation().matrix(),
                                              b.motion_noise(b.time_of(n - 1), int(t[i])))
                    c[i] = covariance.carry(covs[-1], pos[-1], p[i], noise[None])[0]
        self._first_kf = (poses[0], None if covs is None else covs[0])
        return PoseStream(t, p, q, True, c)

    def pre_start(self, t_ns: np.ndarray) -> PoseStream | None:
        """After `finish()` (isam2-smoothed, batch): poses at the epochs `t_ns` before the
        first keyframe from the wheel track, backwards, or None (no wheels, or none of
        `t_ns` inside the track).

        The start needs some motion, but the output should cover the log from the first
        motion; with wheels the relative track before the start is known, so the first
        keyframe's smoothed pose carries it back. (IMU-only logs keep their start.) Its
        covariance (ROS order, map axes) is carried back likewise, with the wheel noise of
        the track in between.
        """
        b = self.builder
        if b is None or self._first_kf is None or not b.has_wheel or len(self.wheel) == 0:
            return None
        first, first_cov = self._first_kf
        t_ns = np.asarray(t_ns, np.int64)
        t_pre = t_ns[(t_ns >= int(self.wheel.t[0])) & (t_ns < b.t0)]
        if len(t_pre) == 0:
            return None
        p0 = self.wheel.at(np.int64(b.t0))
        rel = se2_between(p0[None, :], self.wheel.at(t_pre))
        pos = np.empty((len(t_pre), 3))
        quat = np.empty((len(t_pre), 4))
        cov = None if first_cov is None else np.empty((len(t_pre), 6, 6))
        for i, r in enumerate(rel):
            delta = se2_to_pose3(r)
            pose = first.compose(delta)
            pos[i] = pose.translation()
            quat[i] = _quat_xyzw(pose)
            if cov is not None and first_cov is not None:
                # the track's noise from t_pre to the first keyframe is in the tangent at
                # the keyframe; the motion back (its inverse) has it at t_pre, turned by
                # Ad(delta^-1)
                ad = delta.inverse().AdjointMap()
                noise = ad @ b.motion_noise(int(t_pre[i]), b.t0) @ ad.T
                noise = covariance.to_map(pose.rotation().matrix(), noise)
                cov[i] = covariance.carry(first_cov, np.asarray(first.translation()), pos[i],
                                          noise[None])[0]
        return PoseStream(t_pre, pos, quat, True, cov)

    # ------------------------------------------------------------------ report
    def range_classes(self) -> RangeClasses | None:
        """P(NLOS) of every range in the graph as the report counts it (batch: the final EM
        responsibilities; online: the lag-window review's); None without the NLOS model."""
        b = self.builder
        if b is None or not b.nlos:
            return None
        rec = b.records.arrays()
        g, w = ((self._batch.nlos_prob, self._batch.weight) if self._batch is not None
                else (rec["g_online"], rec["w_online"]))
        return RangeClasses(rec["t_ns"], rec["anchor"], np.asarray(g, dtype=np.float64),
                            np.asarray(w, dtype=np.float64))

    def report(self) -> dict[str, Any]:
        """Outliers and bias per anchor, mixture parameters, update latency, re-anchors.

        `covariance_ms`: time of the pose marginals, per update (isam2: the newest
        keyframe's) or once (isam2-smoothed, batch: all keyframes)."""
        out: dict[str, Any] = {"method": self.method.value}
        out["standstill_fix_epochs"] = self.init.standstill_epochs
        b = self.builder
        if b is None:
            out["initialised"] = False
            return out
        out["initialised"] = True
        out["init_t_ns"] = self._init_t
        out["first_keyframe_t_ns"] = b.t0  # before init_t_ns when backdated
        out["fallback_start"] = self.init.fallback_used
        out["pose_start"] = self.init.pose_start_used
        out["poses_used"] = b.poses.used
        out["keyframes"] = b.k + 1
        lat = np.asarray(self._update_latency)
        if len(lat):
            out["update_latency_ms"] = {
                "p50": float(np.percentile(lat, 50) * 1e3),
                "p95": float(np.percentile(lat, 95) * 1e3),
                "p99": float(np.percentile(lat, 99) * 1e3),
                "max": float(lat.max() * 1e3),
                "n": len(lat),
            }
        if self._cov_latency:
            cl = np.asarray(self._cov_latency)
            out["covariance_ms"] = {"p50": float(np.percentile(cl, 50) * 1e3),
                                    "p95": float(np.percentile(cl, 95) * 1e3),
                                    "max": float(cl.max() * 1e3), "n": len(cl)}
        out["reanchor_events"] = list(self._reanchors)
        out["smoother_rebuilds"] = list(self._rebuilds)
        out["ranges_reclassified_online"] = self._n_reviewed
        out["los_hypothesis_switches"] = self._n_switches
        # ranges at a standstill whose LOS/NLOS evidence weighed less than one (`graph.rest`)
        out["standstill_ranges"] = 0 if self._rest is None else self._rest.weighed
        # keyframes held at rest by a zero velocity (`graph.rest`)
        out["standstill_keyframes"] = 0 if self._rest is None else self._rest.zero_velocities
        rec = b.records.arrays()
        if self._batch is not None:
            g, w = self._batch.nlos_prob, self._batch.weight
            mix = self._batch.mixture
            bias = np.array([self._batch.values.atDouble(D(a)) for a in range(len(self.anchors))]
                            ) if b.with_bias else np.zeros(len(self.anchors))
            key = FULL_GRAPH_REPORT[self.method]
            out[key] = {"em_rounds": self._batch.rounds,
                        "lm_iterations": self._batch.lm_iterations,
                        "em_start": "nlos-first" if self._batch.nlos_first else "online",
                        "range_model": self._batch.range_model,
                        "heldout_log_score": self._batch.heldout_score,
                        "wall_s": self._batch_wall}
            if self._batch.classifier_weight is not None:
                out[key]["nlos_classifier_weight"] = round(self._batch.classifier_weight, 3)
            if self._wheel_offset_s is not None:
                out[key]["wheel_time_offset_s"] = self._wheel_offset_s
            if self._wheel_noise is not None:
                out[key]["wheel_noise_factor"] = {"v": self._wheel_noise[0],
                                                  "omega": self._wheel_noise[1]}
            if self._imu_inflation is not None and b.cv_motion:
                out[key]["motion_accel_density"] = b.motion_accel_density(
                    self._imu_inflation)
            elif self._imu_inflation is not None:
                out[key]["imu_noise_inflation"] = self._imu_inflation
            if self._windows is not None:  # share of keyframes the fits looked at
                out[key]["evidence_share"] = round(float(self._windows.keep.mean()), 4)
            if self._batch.wheel_scale is not None:
                out[key]["wheel_scale"] = {"v": float(self._batch.wheel_scale[0]),
                                               "omega": float(self._batch.wheel_scale[1])}
            scale = self._batch.scale
        else:
            g, w = rec["g_online"], rec["w_online"]
            mix = b.mixture
            bias = b.range_bias
            scale = b.scale
        anchors: dict[str, Any] = {}
        for a, aid in enumerate(self.anchors.ids):
            sel = rec["anchor"] == a
            anchors[aid] = {
                "ranges": int(np.count_nonzero(sel)),
                "nlos": int(np.count_nonzero(g[sel] > 0.5)),
                "downweighted": int(np.count_nonzero(w[sel] < 0.999)),
                "bias_m": float(bias[a]) if b.with_bias else None,
                "scale": float(scale[a]) if b.with_scale else None,
            }
        out["anchors"] = anchors
        out["nlos_mixture"] = {"sigma_los": mix.sigma_los, "mu_nlos": mix.mu_nlos,
                               "sigma_nlos": mix.sigma_nlos, "p_nlos": mix.p_nlos}
        if self._batch is None:  # online: sigma_los is the one-step prediction's
            out["nlos_mixture"]["sigma_los_smoothed"] = b.smoothed_sigma_los
        out["online_range_model"] = {
            "model": "robust" if b.robust_online else "mixture",
            "prequential_log_score": {"mixture": float(b.prequential[0]),
                                      "robust": float(b.prequential[1])},
            "ranges": b.prequential_n, "z": b.prequential_z(),
            "verdict": b.prequential_verdict()}
        if b.has_imu and not b.cv_motion:
            out["online_imu_noise"] = {"inflation": self._online_imu_inflation,
                                       "fits": self._imu_fits}
        elif b.cv_motion and b.recent is not None and self._online_imu_inflation is not None:
            # the factor on the constant-velocity prior's density (`fits`: factors too)
            out["online_motion_prior"] = {
                "accel_density": b.motion_accel_density(self._online_imu_inflation),
                "fits": self._imu_fits}
        if b.online_wheel_scale:  # the odometry scales learnt, and whether the newest
            # wheel factors take them (`GraphBuilder.wheel_scale_applies`)
            out["online_wheel_scale"] = {"v": float(b.wheel_scale[0]),
                                         "omega": float(b.wheel_scale[1]),
                                         "applied": b.wheel_scale_applies()}
        out["dropped_ranges_before_init"] = b.dropped_ranges
        out["repeated_ranges_dropped"] = b.repeated_ranges
        return out


def make(
    method: Method, config: Config, anchors: AnchorMap | None, streams: frozenset[str]
) -> Estimator:
    """The graph estimator for `method` (isam2, isam2-smoothed or batch)."""
    if method not in (Method.ISAM2, Method.ISAM2_SMOOTHED, Method.BATCH):
        raise EstimatorError(f"uwbfuse.graph does not implement method {method.value}")
    if "uwb" not in streams and ({"imu", "wheel"} <= streams or (
            "pose" in streams and streams & {"imu", "wheel"})):
        # IMU + wheels without UWB: the graph starts at the map origin, heading zero, as
        # the filters and dead reckoning do, and fuses the two
        anchors = AnchorMap((), np.zeros((0, 3)))
    elif anchors is None or len(anchors) == 0 or "uwb" not in streams:
        raise EstimatorError(f"method {method.value} needs UWB ranges and an anchor map")
    from uwbfuse.positioning.initialisation import Initialiser

    init = PoseStartInitialiser(Initialiser(config, anchors, streams), config, anchors,
                                streams)
    return GraphEstimator(method, config, anchors, streams, init)
