# SPDX-License-Identifier: BSD-3-Clause
"""Batch refinement: the whole log as one graph, Levenberg-Marquardt with NLOS EM.

Starting from the online pass's keyframe estimates, each round (1) computes every range
residual at the current estimate (vectorised numpy, no factor calls), (2) E-step: per-anchor
forward-backward LOS/NLOS responsibilities, (3) M-step: noise parameters, (4) rebuilds the
range factors (LOS part on D(a), NLOS part on the anchor's NLOS state E(a, s), weighted by
the responsibilities; see `uwb`) and runs LM from the current values. Rounds stop early when
the responsibilities settle; a closing LM round then frees D(a).

Each E-step also tests, per 5 s stretch, every LOS/NLOS assignment of the anchors
(`uwb.los_subset_search`) and scores a stretch against a clearly better one.

Range factors are kept across rounds (`_RangeFactors`: rebuilt only when a range's sigma,
rounded to a 0.5 % grid, or its range changed); the base graph with the NLOS state priors is
built once."""

from __future__ import annotations

import copy
import dataclasses
import functools
import logging
import math
from collections.abc import Callable
from dataclasses import dataclass

import gtsam
import numpy as np

from uwbfuse.config import Config, GraphConfig, RobustKernel, UwbConfig
from uwbfuse.constants import (
    ANCHOR_SPREAD_MIN,
    BATCH_ANCHOR_BIAS_SIGMA,
    BATCH_SEARCH,
    BATCH_SEARCH_NATS,
    BATCH_SEARCH_WINDOW_S,
    CALIBRATION_PASSES,
    CLASSIFIER_FIT_ITERATIONS,
    CLASSIFIER_FIT_RIDGE,
    EM_ROUND_LM_ITERATIONS,
    HELDOUT_BLOCK_S,
    HELDOUT_EVERY,
    HELDOUT_PHASES,
    LM_RELATIVE_TOL,
    LOG_OUTLIER,
    MAX_ROBUST_SIGMA,
    MIN_HELDOUT_RANGES,
    MIN_SCORED_RANGES,
    MIN_WEIGHT,
    SIGMA_LOS_MIN,
    SIGMA_STEP,
    WHEEL_HUBER_K,
    WHEEL_SCALE_MAX_ERROR,
    WHEEL_SCALE_MIN_CHANGE,
    WHEEL_SCALE_SIGMA,
)
from uwbfuse.graph.builder import WheelRecords, held_anchor_bias_sigma
from uwbfuse.graph.evidence_window import EvidenceWindows
from uwbfuse.graph.keys import C, D, L, X, nlos_key
from uwbfuse.graph.noise import range_noise, robust_weight
from uwbfuse.graph.uwb import (
    los_bias_key,
    los_subset_search,
    nlos_state_factors,
    range_factor_keyed,
    robust_log_density,
)
from uwbfuse.graph.wheel import between_factors, wheel_scale_evidence
from uwbfuse.nlos import NlosModel, hmm_smooth_by_anchor, switch_probabilities
from uwbfuse.positioning.start import anchors_observe_height
from uwbfuse.streams import NS_PER_S

log = logging.getLogger(__name__)





def _cap_anchor_bias_sigma(graph: gtsam.NonlinearFactorGraph, n_anchor: int,
                           configured: float, cap: float = BATCH_ANCHOR_BIAS_SIGMA) -> None:
    """Tighten the configured C-D(a) priors (std `configured`, m) of `graph` to
    `builder.held_anchor_bias_sigma` by adding the complementary prior (information adds
    up)."""
    held = held_anchor_bias_sigma(configured, cap)
    if held >= configured:
        return
    extra = (held**-2 - configured**-2) ** -0.5
    noise = gtsam.noiseModel.Isotropic.Sigma(1, extra)
    for a in range(n_anchor):
        graph.add(gtsam.BetweenFactorDouble(C, D(a), 0.0, noise))


@dataclass
class BatchResult:
    """Optimised values, final responsibilities and kernel weights per range."""

    values: gtsam.Values
    nlos_prob: np.ndarray
    weight: np.ndarray
    residual: np.ndarray
    mixture: NlosModel
    rounds: int
    lm_iterations: int
    scale: np.ndarray
    nlos_first: bool = False  # EM started NLOS-first (wheeled logs, see `solve`)
    wheel_scale: np.ndarray | None = None  # (v, omega) odometry scale factors, None: no wheels
    # NLOS excess states (anchor index, segment, value m) of the mixture model, else None
    nlos_states: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
    range_model: str = "mixture"  # the range error model fitted: mixture or robust
    # mean held-out log score (nats per range) of each candidate, when `auto` chose
    heldout_score: dict[str, float] | None = None
    # weight (0..1) of the NLOS classifier's log-odds at EM's last E-step, None: none given
    classifier_weight: float | None = None
    # builds, on demand (only the fit that is kept needs it), the graph whose marginals are
    # the poses' covariance and the LOS/NLOS assignments' spread of each keyframe's
    # position in map x, y (n_kf,2,2, m^2, `hypothesis_shift_moments`); None when
    # `graph.marginal_covariances` is off
    marginals: Callable[[], tuple[gtsam.NonlinearFactorGraph, np.ndarray]] | None = None


# Wheel odometry scale calibration (batch). Encoders read the speed and the yaw rate with a
# scale error (wheel radius, track width: 1-3 % is ordinary); where ranges are weak (most
# in NLOS, their excess states floating) the smoothed track follows the odometry and drifts
# by the scale error times the distance. One refit after the closing LM round, then one
# more LM round (docs/results.md, "Wheel odometry scale").


class _WheelScale:
    """Odometry scale factors (v, omega) fitted to the smoothed track after LM.

    A refit is the weighted least-squares scale of the recorded keyframe-to-keyframe
    wheel deltas (translation for v, yaw for omega) against the same motion at the current
    estimate, Huber weights against slip, prior N(1, WHEEL_SCALE_SIGMA^2). Followed by an LM
    round it is one step of block coordinate descent on the joint problem (track and
    scale); further steps moved the simulated logs by under 0.5 mm. A GTSAM factor with
    the scale as a variable would need a Python CustomFactor per keyframe (about 50x a
    native factor's linearisation), so the scale stays outside the graph and the native
    `BetweenFactorPose3`s are rebuilt (`graph.replace`) when it moves.
    """

    def __init__(self, records: WheelRecords) -> None:
        wheel = records.arrays()
        self.k = wheel["k"]
        self.delta = wheel["delta"]
        self.cov = wheel["cov"]
        self.index = wheel["index"]
        self.out_of_plane = records.out_of_plane
        self.scale = np.ones(2)
        self.applied = np.ones(2)

    def refit(self, values: gtsam.Values, n_kf: int) -> None:
        """New (v, omega) scales from the keyframe poses in `values`."""
        if len(self.k) == 0:
            return
        rot, trans = keyframe_arrays(values, n_kf)
        k = self.k
        num, den = wheel_scale_evidence(rot[k], trans[k], rot[k + 1], trans[k + 1],
                                        self.delta, self.cov, self.scale, WHEEL_HUBER_K)
        prior = WHEEL_SCALE_SIGMA**-2
        out = (num + prior) / (den + prior)
        self.scale = np.clip(out, 1.0 - WHEEL_SCALE_MAX_ERROR, 1.0 + WHEEL_SCALE_MAX_ERROR)

    def apply(self, graphs: list[gtsam.NonlinearFactorGraph]) -> bool:
        """Rebuild the wheel factors of `graphs` (same indices) at the current scales when
        they moved by WHEEL_SCALE_MIN_CHANGE; True when rebuilt."""
        if np.max(np.abs(self.scale - self.applied)) < WHEEL_SCALE_MIN_CHANGE:
            return False
        sv, sw = (float(x) for x in self.scale)
        c = np.array([sv, sv, sw])
        replace_wheel_factors(graphs, self.k.tolist(), self.delta * c,
                              self.cov * np.outer(c, c),
                              self.index.tolist(), self.out_of_plane)
        self.applied = self.scale.copy()
        return True


def replace_wheel_factors(
    graphs: list[gtsam.NonlinearFactorGraph], k: list[int], delta: np.ndarray,
    cov: np.ndarray, index: list[int], out_of_plane: tuple[float, float, float],
) -> None:
    """Replace, in each of `graphs`, factor `index[i]` by the wheel factor X(k) -> X(k + 1)
    of planar delta[i] (x m, y m, theta rad) and covariance cov[i] (3x3)."""
    keys = [X(kk) for kk in k]
    factors = between_factors(keys, [X(kk + 1) for kk in k], np.asarray(delta),
                              np.asarray(cov), out_of_plane, WHEEL_HUBER_K)
    for f, idx in zip(factors, index, strict=True):
        for graph in graphs:
            graph.replace(idx, f)


def keyframe_arrays(values: gtsam.Values, n_kf: int) -> tuple[np.ndarray, np.ndarray]:
    """Rotations (n,3,3) and translations (n,3) of X(0..n-1)."""
    # one call for every Pose3 (rows in key order); the keyframes are the only poses
    m = gtsam.utilities.extractPose3(values)
    if m.shape[0] == n_kf:
        return m[:, :9].reshape(n_kf, 3, 3), m[:, 9:].copy()
    rot = np.empty((n_kf, 3, 3))
    trans = np.empty((n_kf, 3))
    for k in range(n_kf):
        p = values.atPose3(X(k))
        rot[k] = p.rotation().matrix()
        trans[k] = p.translation()
    return rot, trans


def predicted_ranges(
    values: gtsam.Values, rec: dict[str, np.ndarray], anchors: np.ndarray, n_kf: int
) -> np.ndarray:
    """Tag-to-anchor distance (m) of every recorded range at `values` (no bias)."""
    rot, trans = keyframe_arrays(values, n_kf)
    k = rec["k"]
    p = np.einsum("nij,nj->ni", rot[k], rec["tag_in_kf"]) + trans[k]
    return np.linalg.norm(p - anchors[rec["anchor"]], axis=1)




class _RangeFactors:
    """The LOS and NLOS factors of every range, kept across EM rounds.

    A factor is rebuilt only when its sigma, rounded to a SIGMA_STEP log grid, or its
    (scale-corrected) range changed, and the noise models are shared per rounded sigma.
    GTSAM has no bulk constructor for per-measurement factors, and building ~2 per range
    with their own noise models from Python every round cost more than an LM iteration.
    """

    def __init__(
        self, rec: dict[str, np.ndarray], a_r: np.ndarray, uwb: UwbConfig, with_bias: bool,
        nlos_keys: list[int] | None,
    ) -> None:
        n = len(a_r)
        self.uwb = uwb
        self.x = [X(k) for k in rec["k"].astype(np.int64).tolist()]
        self.l = [L(a) for a in a_r.tolist()]
        self.t_tag = [gtsam.Pose3(gtsam.Rot3(), t) for t in np.asarray(rec["tag_in_kf"], float)]
        self.bias_keys: list[list[int | None]] = [
            [los_bias_key(a, with_bias) for a in a_r.tolist()], list(nlos_keys or [])]
        self._q = [np.full(n, -(1 << 30), np.int64), np.full(n, -(1 << 30), np.int64)]
        self._z = [np.full(n, np.nan), np.full(n, np.nan)]
        self._f: list[list[gtsam.NonlinearFactor | None]] = [[None] * n, [None] * n]
        self._noise: dict[int, gtsam.noiseModel.Base] = {}

    def add_to(
        self, graph: gtsam.NonlinearFactorGraph, z: np.ndarray, sigma_los: float,
        w_los: np.ndarray, sigma_nlos: float | None, w_nlos: np.ndarray,
    ) -> None:
        """Add the LOS (sigma_los / sqrt(w_los)) and NLOS factors of weight > MIN_WEIGHT."""
        comps = [(0, sigma_los, w_los)]
        if sigma_nlos is not None:
            comps.append((1, sigma_nlos, w_nlos))
        step = math.log1p(SIGMA_STEP)
        for c, sigma, w in comps:
            use = w > MIN_WEIGHT
            q = np.round(np.log(sigma / np.sqrt(np.maximum(w, MIN_WEIGHT))) / step
                         ).astype(np.int64)
            stale = use & ((q != self._q[c]) | (z != self._z[c]))
            f, keys = self._f[c], self.bias_keys[c]
            for j in np.flatnonzero(stale).tolist():
                f[j] = self._factor(j, float(z[j]), int(q[j]), keys[j], step)
            self._q[c][stale] = q[stale]
            self._z[c][stale] = z[stale]
            for j in np.flatnonzero(use).tolist():
                graph.add(f[j])

    def _factor(
        self, j: int, z: float, q: int, bias_key: int | None, step: float
    ) -> gtsam.NonlinearFactor:
        """`uwb.range_factor_keyed` with the noise model shared per rounded sigma."""
        noise = self._noise.get(q)
        if noise is None:
            noise = range_noise(math.exp(q * step), self.uwb.robust_kernel,
                                self.uwb.kernel_threshold)
            self._noise[q] = noise
        return range_factor_keyed(self.x[j], self.l[j], bias_key, z, noise, self.t_tag[j])


class _NlosStates:
    """The (anchor, segment) NLOS states of the whole log and their chain structure."""

    def __init__(self, anchor: np.ndarray, seg: np.ndarray, model: NlosModel) -> None:
        pairs = np.unique(np.stack([anchor, seg], axis=1), axis=0)  # sorted by anchor, seg
        self.anchor = pairs[:, 0]
        self.seg = pairs[:, 1]
        self.keys = [nlos_key(int(a), int(s)) for a, s in pairs]
        same = np.concatenate([[False], self.anchor[1:] == self.anchor[:-1]])
        gap = np.concatenate([[0], np.diff(self.seg)])
        # chain to the previous state of the anchor unless the gap decorrelates it
        max_gap = max(int(3.0 * model.tau_s / model.segment_s), 1)
        self.prev = np.where(same & (gap <= max_gap), np.arange(len(pairs)) - 1, -1)
        code = self.anchor.astype(np.int64) * (1 << 40) + self.seg
        self._code = code
        self.values = np.zeros(len(pairs))

    def index(self, anchor: np.ndarray, seg: np.ndarray) -> np.ndarray:
        return np.searchsorted(self._code, anchor.astype(np.int64) * (1 << 40) + seg)


def solve(
    cfg: Config,
    base_graph: gtsam.NonlinearFactorGraph,
    initial: gtsam.Values,
    rec: dict[str, np.ndarray],
    anchors: np.ndarray,
    n_kf: int,
    model: NlosModel,
    t0_ns: int,
    scale0: np.ndarray | None = None,
    has_wheel: bool = True,
    with_scale: bool = False,
    wheel: WheelRecords | None = None,
    planar: bool = True,
    windows: EvidenceWindows | None = None,
) -> BatchResult:
    """EM + LM over the full graph (see the module docstring).

    `graph.range_model = "auto"`: held-out cross-validation (`_cross_validated`) chooses
    among the candidates, over the keyframes of `windows` (`graph.evidence_window`; None:
    the whole log); the chosen one is then fitted to the whole log.

    EM from the online trajectory classifies each range against a trajectory that, where
    most anchors are blocked at once, has already been pulled towards the NLOS ranges: they
    then fit as LOS and EM stays in that basin. On a wheeled log EM therefore starts
    NLOS-first: one LM round with every range on its anchor's NLOS excess state only (no
    range committed to zero bias), then the E-steps. Where the anchors' constant offsets
    pass for NLOS, the robust candidate wins the held-out choice. NLOS-first needs the
    odometry to hold the track's shape while every range floats on its excess state:
    without wheels (a handheld IMU + UWB log, or UWB alone) no motion factor holds it, so
    EM starts from the online trajectory (a rule on the sensors present, not on the data's
    figures; ISAS-Walk1: 0.19 m online, 0.24 m NLOS-first). `with_scale`: refine the
    per-anchor range scales, starting from `scale0` (the online pass's).
    """
    problem = _Problem(cfg, base_graph, anchors, n_kf, t0_ns, wheel,
                       nlos_first=cfg.graph.nlos and has_wheel)
    scale0 = scale0 if with_scale else None
    if not cfg.graph.nlos or len(rec["z"]) == 0:
        # no NLOS modelling asked for (the configured kernel and sigma), or no ranges at all
        # (IMU + wheels): one LM over the motion factors
        plain = cfg if not cfg.graph.nlos else cfg.model_copy(
            update={"graph": cfg.graph.model_copy(update={"nlos": False})})
        return _solve_em(plain, base_graph, initial, rec, anchors, n_kf, model, t0_ns, scale0,
                         nlos_first=False, wheel_scale=problem.wheel_scale())
    candidates = {m.name: m for m in RANGE_MODELS if scale0 is not None or not m.common_scale}
    if cfg.graph.range_model != "auto":
        return problem.fit(candidates[cfg.graph.range_model], rec, initial, model, scale0)
    if not (planar or anchors_observe_height(anchors)):
        # the height is free and the anchors coplanar, so a common range offset trades
        # against the tag's height: the graph holds the common offset C at zero
        # (`GraphBuilder`), but the robust model's per-anchor offsets, free from the start,
        # still take that null direction between them, which no held-out range can show
        # (docs/results.md, "The common range offset where the height is free"). The
        # mixtures free D(a) - C only after EM, around the held C.
        candidates = {n: m for n, m in candidates.items() if m.nlos}
    if len(candidates) == 1:
        out = problem.fit(next(iter(candidates.values())), rec, initial, model, scale0)
        out.range_model = next(iter(candidates))
        return out
    return _cross_validated(problem, list(candidates.values()), rec, initial, model, scale0,
                            windows)


@dataclass(frozen=True)
class RangeModel:
    """A candidate range error model of `graph.range_model`."""

    name: str
    nlos: bool  # the LOS/NLOS mixture (else Huber around the per-anchor offsets)
    common_scale: bool  # one range scale for every anchor (when scales are estimated)
    # mixture: EM run again with each anchor's LOS offset held at its calibrated value
    # (`_EmRun.recalibrate`) instead of at zero
    calibrated: bool = False


RANGE_MODELS = (
    RangeModel("mixture", nlos=True, common_scale=False),
    RangeModel("mixture, calibrated", nlos=True, common_scale=False, calibrated=True),
    RangeModel("robust", nlos=False, common_scale=False),
    # the radios' clock (one scale for all) rather than each anchor's own
    RangeModel("robust, common scale", nlos=False, common_scale=True),
)


@dataclass
class _Problem:
    """What every fit of one batch solve shares: the graph without ranges and the log."""

    cfg: Config
    base_graph: gtsam.NonlinearFactorGraph
    anchors: np.ndarray
    n_kf: int
    t0_ns: int
    wheel: WheelRecords | None
    nlos_first: bool

    def wheel_scale(self) -> _WheelScale | None:
        """A fresh odometry scale fit (each LM run rebuilds its own wheel factors), for the
        mixture's fits only (`_solve_robust` says why)."""
        if self.wheel is None or not self.wheel.k or not self.cfg.graph.estimate_wheel_scale:
            return None
        return _WheelScale(self.wheel)

    def windowed(self, windows: EvidenceWindows | None, initial: gtsam.Values) -> _Problem:
        """The same problem over the keyframes of `windows` only (their graph starts
        from `initial`); itself without windows."""
        if windows is None or windows.whole:
            return self
        return dataclasses.replace(
            self, base_graph=windows.graph(self.base_graph, initial),
            wheel=None if self.wheel is None else windows.wheel(self.wheel))

    def fit(self, m: RangeModel, rec: dict[str, np.ndarray], initial: gtsam.Values,
            mix: NlosModel, scale0: np.ndarray | None) -> BatchResult:
        """Range model `m` fitted to the ranges `rec` from `initial`."""
        return self.fit_all([m], rec, initial, mix, scale0)[m.name]

    def fit_all(self, models: list[RangeModel], rec: dict[str, np.ndarray],
                initial: gtsam.Values, mix: NlosModel, scale0: np.ndarray | None
                ) -> dict[str, BatchResult]:
        """Each of `models` fitted to the ranges `rec` from `initial`, by name. The
        calibrated mixture continues the plain mixture's EM run where both are asked for."""
        out: dict[str, BatchResult] = {}
        em = [m for m in models if m.nlos]
        if em:
            before: list[BatchResult] = []  # the plain mixture, when calibrated after it
            fit = _solve_em(self.cfg, self.base_graph, initial, rec, self.anchors,
                            self.n_kf, mix, self.t0_ns, scale0, nlos_first=self.nlos_first,
                            wheel_scale=self.wheel_scale(),
                            calibrated=any(m.calibrated for m in em), uncalibrated=before)
            for m in em:
                out[m.name] = fit if m.calibrated or not before else before[0]
        for m in models:
            if not m.nlos:
                out[m.name] = _solve_robust(self.cfg, self.base_graph, initial, rec,
                                            self.anchors, self.n_kf, mix, self.t0_ns, scale0,
                                            m.common_scale)
        return out


def _cross_validated(
    problem: _Problem, candidates: list[RangeModel], rec: dict[str, np.ndarray],
    initial: gtsam.Values, model: NlosModel, scale0: np.ndarray | None,
    windows: EvidenceWindows | None = None,
) -> BatchResult:
    """`graph.range_model = "auto"`: each candidate fitted, over the keyframes of
    `windows` (None: all), without the held-out stretches of a phase (`heldout_mask`),
    phase after phase until MIN_SCORED_RANGES are held out; the best mean held-out log
    score wins (a refinement by one standard error, `_one_se_choice`) and is fitted to
    every range of the log."""
    cfg = problem.cfg
    trial = problem.windowed(windows, initial)
    rec_cv = rec if windows is None else windows.ranges(rec)
    scored: dict[str, list[np.ndarray]] = {m.name: [] for m in candidates}
    blocks: list[np.ndarray] = []  # each held-out range's stretch
    first: dict[str, BatchResult] | None = None
    for phase in HELDOUT_PHASES:
        held = heldout_mask(rec_cv["t_ns"], problem.t0_ns, phase)
        if not np.any(held):
            continue
        train, test = _subset(rec_cv, ~held), _subset(rec_cv, held)
        fits = trial.fit_all(candidates, train, initial, model, scale0)
        blocks.append(heldout_block(test["t_ns"], problem.t0_ns))
        for name, f in fits.items():
            scored[name].append(heldout_log_score(f, train, test, problem.anchors,
                                                  problem.n_kf, cfg, problem.t0_ns))
        first = first or fits
        if sum(len(x) for x in scored[candidates[0].name]) >= MIN_SCORED_RANGES:
            break
    n_scored = sum(len(x) for x in scored[candidates[0].name])
    if first is None or n_scored < MIN_HELDOUT_RANGES:  # too short to rank: the default
        return problem.fit(candidates[0], rec, initial, model, scale0)
    per_range = {name: np.concatenate(x) for name, x in scored.items()}
    scores = {name: float(np.mean(x)) for name, x in per_range.items()}
    best = _one_se_choice(candidates, per_range, np.concatenate(blocks))
    log.info("batch range model (%d ranges held out): %s -> %s", n_scored,
             ", ".join(f"{n} {v:.3f}" for n, v in scores.items()), best.name)
    if best.nlos:  # EM from the online pass again: from the held-out fit it lands elsewhere
        out = problem.fit(best, rec, initial, model, scale0)
    else:  # the robust fit converges from its held-out solution
        f = first[best.name]
        out = _solve_em(_robust_config(cfg, f.mixture.sigma_los), problem.base_graph,
                        f.values, rec, problem.anchors, problem.n_kf, f.mixture,
                        problem.t0_ns, None if scale0 is None else f.scale,
                        nlos_first=False, wheel_scale=None,  # robust: see _solve_robust
                        common_scale=best.common_scale)
        out.mixture.sigma_los = f.mixture.sigma_los
    out.range_model = best.name
    out.heldout_score = scores
    return out


# Held-out stretches of `graph.range_model = "auto"`: every HELDOUT_EVERY-th stretch of
# HELDOUT_BLOCK_S of the log. 2 s holds out a range with its neighbours of the same NLOS
# episode (segments of about 1 s), so the candidates must predict it from the motion and
# their calibration, not from its twin a tenth of a second away; odometry bridges 2 s.


def heldout_block(t_ns: np.ndarray, t0_ns: int) -> np.ndarray:
    """Index of the HELDOUT_BLOCK_S stretch of the log each stamp (ns) falls in."""
    return (np.asarray(t_ns, np.int64) - t0_ns) // round(HELDOUT_BLOCK_S * NS_PER_S)


def heldout_mask(t_ns: np.ndarray, t0_ns: int, phase: int = HELDOUT_PHASES[0]) -> np.ndarray:
    """True for the ranges in the held-out stretches of `phase` (the first stretch is never
    held out: the start needs its ranges)."""
    block = heldout_block(t_ns, t0_ns)
    return ((block % HELDOUT_EVERY) == phase) & (block > 0)


def _one_se_choice(candidates: list[RangeModel], score: dict[str, np.ndarray],
                   block: np.ndarray) -> RangeModel:
    """The candidate of the best mean held-out log score `score` (nats per range). A
    refinement (the calibrated mixture refines the mixture) must beat what it refines by
    one standard error of their paired score difference, or it leaves the choice: the
    one-standard-error rule of cross-validation. The error counts each held-out stretch
    `block` as one sample: its ranges share an NLOS episode and the same track error."""
    best = max(candidates, key=lambda m: float(np.mean(score[m.name])))
    base = next((m for m in candidates if m.nlos and not m.calibrated), None)
    if not best.calibrated or base is None:
        return best
    gain, se = clustered_mean_se(score[best.name] - score[base.name], block)
    if gain > se:
        return best
    return _one_se_choice([m for m in candidates if m is not best], score, block)


def clustered_mean_se(x: np.ndarray, cluster: np.ndarray) -> tuple[float, float]:
    """Mean of `x` and its standard error with the samples of one `cluster` correlated
    (the cluster-robust sandwich estimate; inf with fewer than two clusters)."""
    _, inv = np.unique(cluster, return_inverse=True)
    total = np.bincount(inv, weights=x)
    count = np.bincount(inv).astype(float)
    mean = float(total.sum() / count.sum())
    k = len(count)
    if k < 2:
        return mean, math.inf
    se = math.sqrt(k / (k - 1) * float(np.sum((total - mean * count) ** 2))) / count.sum()
    return mean, float(se)


def _subset(rec: dict[str, np.ndarray], mask: np.ndarray) -> dict[str, np.ndarray]:
    return {name: v[mask] for name, v in rec.items()}


def _robust_config(cfg: Config, sigma: float) -> Config:
    """`cfg` with the NLOS mixture off and the LOS range sigma `sigma` (m)."""
    return cfg.model_copy(update={"graph": cfg.graph.model_copy(update={"nlos": False}),
                                  "uwb": cfg.uwb.model_copy(update={"sigma": sigma})})


def _solve_robust(
    cfg: Config, base_graph: gtsam.NonlinearFactorGraph, initial: gtsam.Values,
    rec: dict[str, np.ndarray], anchors: np.ndarray, n_kf: int, model: NlosModel,
    t0_ns: int, scale0: np.ndarray | None, common_scale: bool = False,
) -> BatchResult:
    """Huber LM around per-anchor offsets; then the LOS sigma from the residuals (1.4826
    MAD) and LM again at that sigma. No wheel-scale refit: no range floats on an NLOS
    excess state here, every range holds the track, so it does not drift with the
    odometry's scale error the refit is for; refitted to that range-held track the scale
    only moves what the ranges placed (docs/results.md, "Batch against the plain
    estimator")."""
    first = _solve_em(_robust_config(cfg, cfg.uwb.sigma), base_graph, initial, rec, anchors,
                      n_kf, model, t0_ns, scale0, nlos_first=False,
                      common_scale=common_scale)
    sigma = float(np.clip(1.4826 * np.median(np.abs(first.residual)), SIGMA_LOS_MIN,
                          MAX_ROBUST_SIGMA))
    out = _solve_em(_robust_config(cfg, sigma), base_graph, first.values, rec, anchors, n_kf,
                    model, t0_ns, None if scale0 is None else first.scale, nlos_first=False,
                    common_scale=common_scale)
    out.mixture.sigma_los = sigma
    out.range_model = "robust, common scale" if common_scale else "robust"
    return out




def _bias_values(values: gtsam.Values, n_anchor: int) -> np.ndarray:
    """Each anchor's LOS range offset D(a) in `values` (m); zeros when not estimated."""
    if not values.exists(D(0)):
        return np.zeros(n_anchor)
    return np.array([values.atDouble(D(a)) for a in range(n_anchor)])


def _nearest_responsibility(
    train: dict[str, np.ndarray], test: dict[str, np.ndarray], g: np.ndarray
) -> np.ndarray:
    """P(NLOS) of each test range: the mean of its anchor's training ranges just before
    and after it in time (NLOS persists), the anchor's mean where it has only one side."""
    out = np.full(len(test["z"]), float(np.mean(g)) if len(g) else 0.0)
    for a in np.unique(test["anchor"]).tolist():
        tr = np.flatnonzero(train["anchor"] == a)
        te = np.flatnonzero(test["anchor"] == a)
        if len(tr) == 0:
            continue
        order = np.argsort(train["t_ns"][tr], kind="stable")
        t_tr, g_tr = train["t_ns"][tr][order], g[tr][order]
        pos = np.searchsorted(t_tr, test["t_ns"][te])
        lo = g_tr[np.clip(pos - 1, 0, len(tr) - 1)]
        hi = g_tr[np.clip(pos, 0, len(tr) - 1)]
        out[te] = 0.5 * (lo + hi)
    return out


def heldout_log_score(
    fit: BatchResult, train: dict[str, np.ndarray], test: dict[str, np.ndarray],
    anchors: np.ndarray, n_kf: int, cfg: Config, t0_ns: int,
) -> np.ndarray:
    """Log predictive density (nats) of each held-out range under `fit`: its trajectory
    (the held-out stretches bridged by the motion factors), range calibration and error
    model. The mixture predicts a range's NLOS excess from the excess distribution its
    NLOS states show over the whole log (`fitted_excess`), and its NLOS probability from
    the neighbouring training ranges; the robust model by its Huber density
    (`robust_log_density`, whatever the kernel). Both keep the mixture's gross-outlier
    floor.

    The NLOS states are the mixture's local free parameters, one per anchor and segment:
    carried into the held-out stretch, the nearest state predicts a range from its
    neighbours' residuals whatever the track, and the held-out test no longer sees the
    track (Labyrinth's NLOS-first fit, anchors 105 and 107 in NLOS on every range, won it
    with its track 0.095 m off; docs/results.md)."""
    a = test["anchor"].astype(np.int64)
    h = predicted_ranges(fit.values, test, anchors, n_kf)
    z = test["z"] / (1.0 + fit.scale[a])
    bias = _bias_values(fit.values, len(anchors))
    r_los = z - h - bias[a]
    mix = fit.mixture
    if fit.range_model == "robust" or fit.nlos_states is None:
        return np.logaddexp(robust_log_density(r_los, mix.sigma_los, cfg.uwb), LOG_OUTLIER)
    mu, var = fitted_excess(fit, train, bias, t0_ns)
    ll_l, ll_n = mix.log_likelihoods(r_los, r_los - mu, var)
    p = np.clip(_nearest_responsibility(train, test, fit.nlos_prob), 1e-3, 1.0 - 1e-3)
    return np.logaddexp(np.log1p(-p) + ll_l, np.log(p) + ll_n)


def fitted_excess(fit: BatchResult, train: dict[str, np.ndarray], bias: np.ndarray,
                  t0_ns: int) -> tuple[float, float]:
    """Mean (m) and variance (m^2) of the NLOS excess over the LOS offset `bias` (per
    anchor, m) across the fit's NLOS states, each weighted by its training ranges'
    responsibilities; the model's prior (mu_nlos, sigma_slow^2) where the states carry
    less than one range. The variance is floored at SIGMA_LOS_MIN^2: one state's spread
    is never known better than a LOS range."""
    mix = fit.mixture
    if fit.nlos_states is None:
        return mix.mu_nlos, mix.sigma_slow**2
    st_a, st_s, st_v = fit.nlos_states
    code = st_a.astype(np.int64) * (1 << 40) + st_s
    seg_ns = round(mix.segment_s * NS_PER_S)
    q = train["anchor"].astype(np.int64) * (1 << 40) + (train["t_ns"] - t0_ns) // seg_ns
    idx = np.clip(np.searchsorted(code, q), 0, max(len(code) - 1, 0))
    hit = code[idx] == q if len(code) else np.zeros(len(q), bool)
    w = np.bincount(idx[hit], weights=fit.nlos_prob[hit], minlength=len(code))
    if w.sum() < 1.0:
        return mix.mu_nlos, mix.sigma_slow**2
    excess = st_v - bias[st_a]
    mu = float(np.sum(w * excess) / w.sum())
    var = float(np.sum(w * (excess - mu) ** 2) / w.sum())
    return mu, max(var, SIGMA_LOS_MIN**2)


@dataclass(frozen=True)
class LmSolution:
    """One LM run (`run_lm`): the values of every key it was given, the graph's error at
    them and the iterations taken."""

    values: gtsam.Values
    error: float
    iterations: int


def run_lm(graph: gtsam.NonlinearFactorGraph, initial: gtsam.Values,
           max_iterations: int) -> LmSolution:
    """Levenberg-Marquardt over `graph` from `initial` at the batch's tolerances.

    The optimiser carries only the keys `graph` touches: an evidence window's graph
    (`graph.evidence_window`) touches a fifth of a long log's keyframes, and LM's per-
    iteration work on the others (retraction, copies) is wasted. The keys it does not
    touch come back unchanged from `initial`."""
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(max_iterations)
    params.setRelativeErrorTol(LM_RELATIVE_TOL)
    params.setAbsoluteErrorTol(1e-6)
    keys = graph.keyVector()
    subset = len(keys) < initial.size()
    opt = gtsam.LevenbergMarquardtOptimizer(graph, initial.extract(keys) if subset else initial,
                                            params)
    opt.optimize()
    values = opt.values()
    if subset:
        merged = gtsam.Values(initial)
        merged.update(values)
        values = merged
    return LmSolution(values, float(opt.error()), int(opt.iterations()))


def _smooth_per_anchor(ll_los: np.ndarray, ll_nlos: np.ndarray, anchor: np.ndarray,
                       order: np.ndarray, inv: np.ndarray, mix: NlosModel,
                       p_switch: np.ndarray) -> np.ndarray:
    """E-step: each range's NLOS responsibility from its LOS and NLOS log-likelihoods, one
    two-state HMM smoothing per anchor over its ranges in time (`order` sorts the ranges
    by anchor then time, `inv` undoes it; `p_switch` (N,) in that order, the chain's step
    into each range, `nlos.switch_probabilities`)."""
    gs = hmm_smooth_by_anchor(anchor[order], ll_los[order], ll_nlos[order], p_switch,
                              mix.p_nlos)
    return gs[inv]


def classifier_weight(g_resid: np.ndarray, evidence: np.ndarray) -> float:
    """The weight (0..1) of the learned classifier's log-odds `evidence` (nats, per range)
    in EM's E-step: the slope of the logistic regression (with intercept) of the ranges'
    NLOS responsibilities from the residuals alone, `g_resid` (soft labels), on the
    log-odds. A classifier that ranks this log's ranges as its residuals do keeps its
    log-odds (1: taken at face value, the most it gets); one at chance on this log (a
    forest trained on other sites) gets ~0 and leaves EM to the residuals."""
    # two parameters on soft labels by Newton: scikit-learn's LogisticRegression takes hard
    # labels only (every range twice with weights g, 1 - g) and is regularised by default
    x = np.column_stack([np.ones(len(evidence)), evidence])
    beta = np.zeros(2)
    for _ in range(CLASSIFIER_FIT_ITERATIONS):
        p = 1.0 / (1.0 + np.exp(-np.clip(x @ beta, -30.0, 30.0)))
        grad = x.T @ (p - g_resid)
        hess = (x * (p * (1.0 - p))[:, None]).T @ x + CLASSIFIER_FIT_RIDGE * np.eye(2)
        step = np.linalg.solve(hess, grad)
        beta -= step
        if np.max(np.abs(step)) < 1e-6:
            break
    return float(np.clip(beta[1], 0.0, 1.0))


def _initial_state_values(states: _NlosStates, st_idx: np.ndarray, g: np.ndarray,
                          r_los: np.ndarray, bias: np.ndarray, mu_nlos: float) -> np.ndarray:
    """Each NLOS state's start (m, over the range's anchor offset `bias`): the
    responsibility-weighted mean excess of its ranges, `mu_nlos` where they weigh less
    than half a range."""
    num = np.bincount(st_idx, weights=g * r_los, minlength=len(states.keys))
    den = np.bincount(st_idx, weights=g, minlength=len(states.keys))
    return bias[states.anchor] + np.where(
        den > 0.5, np.clip(num / np.maximum(den, 1e-9), 0.0, 1.5), mu_nlos)


class _EmGraphs:
    """The graphs of one EM + LM run: the base graph with the LOS offsets' freeze and the
    NLOS state priors (built once per freeze setting), the ranges added at the current
    responsibilities; counts the LM iterations."""

    def __init__(self, g_cfg: GraphConfig, base_graph: gtsam.NonlinearFactorGraph,
                 d0: np.ndarray, states: _NlosStates | None, mix: NlosModel,
                 factors: _RangeFactors, with_bias: bool) -> None:
        self.g_cfg = g_cfg
        self.base_graph = base_graph
        self.d0 = d0  # LOS offsets D(a) (m) the freeze holds them at
        self.states = states
        self.mix = mix
        self.factors = factors
        self.with_bias = with_bias
        self.static: dict[bool, gtsam.NonlinearFactorGraph] = {}
        self.iterations = 0
        self.hold = BATCH_ANCHOR_BIAS_SIGMA  # m: D(a) - C when released (`hold_offsets`)

    def hold_offsets(self, d0: np.ndarray, spread: float) -> None:
        """The freeze holds the LOS offsets D(a) at `d0` (m), the NLOS states revert to
        it, and a release holds each within `spread` (m) of C: the static graphs are built
        again."""
        self.d0 = d0
        self.hold = spread
        self.static = {}

    def static_graph(self, frozen: bool) -> gtsam.NonlinearFactorGraph:
        """Base graph, the D(a) freeze (when frozen) and the NLOS state priors (built once)."""
        if frozen not in self.static:
            graph = gtsam.NonlinearFactorGraph(self.base_graph)
            if frozen:
                tight = gtsam.noiseModel.Isotropic.Sigma(1, 1e-4)
                for a in range(len(self.d0)):
                    graph.add(gtsam.PriorFactorDouble(D(a), float(self.d0[a]), tight))
            if self.states is not None:
                st = self.states
                for i, key in enumerate(st.keys):
                    prev = st.keys[st.prev[i]] if st.prev[i] >= 0 else None
                    nlos_state_factors(graph, key, float(self.d0[st.anchor[i]]), prev,
                                       self.mix)
            self.static[frozen] = graph
        return self.static[frozen]

    def with_ranges(self, frozen: bool, z: np.ndarray, sigma_los: float, w_los: np.ndarray,
                    w_nlos: np.ndarray) -> gtsam.NonlinearFactorGraph:
        """The static graph plus every range (`z` m, LOS sigma `sigma_los` m) weighted
        `w_los` on its LOS offset and `w_nlos` on its NLOS state."""
        graph = gtsam.NonlinearFactorGraph(self.static_graph(frozen))
        if not frozen and self.with_bias:
            _cap_anchor_bias_sigma(graph, len(self.d0), self.g_cfg.range_bias_anchor_sigma,
                                   self.hold)
        self.factors.add_to(graph, z, sigma_los, w_los,
                            self.mix.sigma_nlos if self.states is not None else None, w_nlos)
        return graph

    def lm_round(self, vals: gtsam.Values, z: np.ndarray, sigma_los: float, g: np.ndarray,
                 frozen: bool, max_it: int | None = None) -> gtsam.Values:
        """One LM solve at NLOS responsibilities `g` from `vals`."""
        opt = run_lm(self.with_ranges(frozen, z, sigma_los, 1.0 - g, g), vals,
                      max_it or self.g_cfg.lm_max_iterations)
        self.iterations += opt.iterations
        log.debug("batch LM: %d iterations, error %.3f, model %s", opt.iterations,
                  opt.error, self.mix)
        return opt.values


def _em_marginals(
    graphs: _EmGraphs, values: gtsam.Values, rec: dict[str, np.ndarray], anchors: np.ndarray,
    n_kf: int, h: np.ndarray, r_los: np.ndarray, g: np.ndarray, sigma_los: float,
    st_idx: np.ndarray | None,
) -> tuple[gtsam.NonlinearFactorGraph, np.ndarray]:
    """The final LM round's graph, each range's factors scaled by the share of its
    information that survives the LOS/NLOS ambiguity (`observed_information_share`),
    and the assignments' spread (`hypothesis_shift_moments`)."""
    mix, states = graphs.mix, graphs.states
    share = np.ones(len(g))
    # the robust model has no classes: its every range counts as LOS (g = 0) against
    # the mixture's NLOS alternative, with the LOS sigma it was fitted with
    search_mix = copy.copy(mix)
    search_mix.sigma_los = sigma_los
    moment = hypothesis_shift_moments(values, rec, anchors, n_kf, r_los, g, search_mix)
    if states is not None and st_idx is not None:
        e_fit = np.array([values.atDouble(k) for k in states.keys])
        share = observed_information_share(r_los, rec["z"] - h - e_fit[st_idx], g,
                                           sigma_los, mix.sigma_nlos)
    graph = graphs.with_ranges(False, rec["z"], sigma_los, (1.0 - g) * share, g * share)
    return graph, moment


def _solve_em(
    cfg: Config,
    base_graph: gtsam.NonlinearFactorGraph,
    initial: gtsam.Values,
    rec: dict[str, np.ndarray],
    anchors: np.ndarray,
    n_kf: int,
    model: NlosModel,
    t0_ns: int,
    scale0: np.ndarray | None,
    nlos_first: bool,
    wheel_scale: _WheelScale | None = None,
    common_scale: bool = False,
    calibrated: bool = False,
    uncalibrated: list[BatchResult] | None = None,
) -> BatchResult:
    """One EM + LM run from the online trajectory, or NLOS-first (see `solve`);
    `common_scale`: the range scale (when estimated) is one for every anchor. Its phases
    (`_EmRun`): the NLOS-first round, the EM rounds, the scale settling, the LOS offsets'
    release and the wheel-scale round. `calibrated`: then EM again with the LOS offsets
    held at the released ones (`_EmRun.recalibrate`), CALIBRATION_PASSES times;
    `uncalibrated` receives the result before those passes."""
    run = _EmRun(cfg, base_graph, initial, rec, anchors, n_kf, model, t0_ns, scale0,
                 nlos_first, wheel_scale, common_scale)
    if nlos_first and run.states is not None:
        run.nlos_first_round()
    run.em_rounds()
    run.settle()
    if calibrated:
        if uncalibrated is not None:
            uncalibrated.append(run.result(with_marginals=False))
        for _ in range(CALIBRATION_PASSES):
            if not run.recalibrate():
                break
            run.em_rounds()
            run.settle()
    return run.result()


class _EmRun:
    """The state one EM + LM run (`_solve_em`) carries through its phases: values,
    responsibilities, range scales, the mixture and the NLOS excess states; its graphs
    (`_EmGraphs`), E-step (`_smooth_per_anchor`) and marginals (`_em_marginals`) live
    apart."""

    def __init__(
        self, cfg: Config, base_graph: gtsam.NonlinearFactorGraph, initial: gtsam.Values,
        rec: dict[str, np.ndarray], anchors: np.ndarray, n_kf: int, model: NlosModel,
        t0_ns: int, scale0: np.ndarray | None, nlos_first: bool,
        wheel_scale: _WheelScale | None, common_scale: bool,
    ) -> None:
        g_cfg = cfg.graph
        self.g_cfg, self.uwb = g_cfg, cfg.uwb
        self.anchors, self.n_kf = anchors, n_kf
        self.nlos_first, self.common_scale = nlos_first, common_scale
        self.wheel_scale = wheel_scale
        if wheel_scale is not None:  # its wheel factors are replaced: keep the caller's intact
            base_graph = gtsam.NonlinearFactorGraph(base_graph)
        self.base_graph = base_graph
        self.with_scale = scale0 is not None  # range scales are estimated (`auto`: online)
        self.scale = np.zeros(len(anchors)) if scale0 is None else scale0.copy()
        self.z_raw = rec["z"]
        self.rec = rec = dict(rec)
        self.a_r = a_r = rec["anchor"].astype(np.int64)
        rec["z"] = self.z_raw / (1.0 + self.scale[rec["anchor"]])
        with_bias = g_cfg.estimate_range_bias
        self.prior = NlosModel.from_config(cfg)
        self.mix = mix = copy.copy(model)
        self.values = gtsam.Values(initial)
        self.n_anchor = n_anchor = len(anchors)
        seg_ns = round(mix.segment_s * NS_PER_S)
        seg_r = (rec["t_ns"] - t0_ns) // seg_ns
        self.order = np.lexsort((rec["t_ns"], a_r))
        self.inv = np.empty_like(self.order)
        self.inv[self.order] = np.arange(len(self.order))
        self.p_switch = switch_probabilities(rec["t_ns"][self.order], a_r[self.order],
                                             mix.switch_time)
        self.states = states = _NlosStates(a_r, seg_r, mix) if g_cfg.nlos else None
        self.st_idx = st_idx = states.index(a_r, seg_r) if states is not None else None
        self.h, self.r_los = self.residuals(self.values)
        self.g = rec["g_online"].copy() if g_cfg.nlos else np.zeros(len(self.h))
        if states is not None and st_idx is not None:
            states.values = _initial_state_values(states, st_idx, self.g, self.r_los,
                                                  _bias_values(self.values, n_anchor),
                                                  mix.mu_nlos)
        # EM runs with the LOS biases D(a) frozen at their prior mean (0): left free, a
        # mostly blocked anchor trades its NLOS excess against D(a) and EM settles in a
        # biased basin. One final LM round with the last responsibilities then calibrates
        # D(a) (and C).
        self.freeze = with_bias and g_cfg.nlos
        d0 = np.zeros(n_anchor) if self.freeze else _bias_values(self.values, n_anchor)
        if self.freeze:
            for a in range(n_anchor):
                self.values.update(D(a), 0.0)
        self.done = 0
        self.classifier_weight: float | None = None  # set by each E-step with a classifier
        self.sig_l = mix.sigma_los if g_cfg.nlos else self.uwb.sigma
        factors = _RangeFactors(rec, a_r, self.uwb, with_bias,
                                None if states is None or st_idx is None
                                else [states.keys[i] for i in st_idx.tolist()])
        if states is not None:
            for i, key in enumerate(states.keys):
                self.values.insert(key, float(states.values[i]))
        self.graphs = _EmGraphs(g_cfg, base_graph, d0, states, mix, factors, with_bias)
        # NLOS-first, every state has been fitted to its ranges: counted as exact, a range
        # that fits its state would look NLOS even at zero excess, so the states count as
        # uncertain by their slow std (the online start keeps 3 cm: wider, a large constant
        # anchor offset would pass for NLOS and escape calibration)
        self.e_var = mix.sigma_slow**2 if nlos_first else 0.03**2

    def residuals(self, vals: gtsam.Values) -> tuple[np.ndarray, np.ndarray]:
        """Predicted ranges and LOS residuals (m) at `vals`."""
        h = predicted_ranges(vals, self.rec, self.anchors, self.n_kf)
        return h, self.rec["z"] - h - _bias_values(vals, self.n_anchor)[self.a_r]

    def lm_round(self, g: np.ndarray, frozen: bool, max_it: int | None = None) -> None:
        """One LM solve from the current values at responsibilities `g`; the predicted
        ranges and LOS residuals follow."""
        self.values = self.graphs.lm_round(self.values, self.rec["z"], self.sig_l, g, frozen,
                                           max_it)
        self.h, self.r_los = self.residuals(self.values)

    def _read_states(self) -> None:
        assert self.states is not None
        self.states.values = np.array([self.values.atDouble(k) for k in self.states.keys])

    def _refit_scale(self) -> None:
        """The range scales from the LOS residuals (`refit_scale`), the ranges rescaled."""
        refit_scale(self.scale, self.r_los, self.h, (1.0 - self.g), self.a_r,
                    self.mix.sigma_los, self.g_cfg.range_scale_sigma, self.common_scale)
        self.rec["z"] = self.z_raw / (1.0 + self.scale[self.a_r])

    def nlos_first_round(self) -> None:
        """NLOS-first start: every range on its anchor's excess state only, so no range is
        committed to zero bias before the first E-step (see `solve`)."""
        self.lm_round(np.ones(len(self.h)), self.freeze, EM_ROUND_LM_ITERATIONS)
        self._read_states()

    def _e_step(self, it: int, g_prev: np.ndarray | None) -> None:
        """Responsibilities from the residuals at the current values, then the M-step."""
        states, st_idx, mix = self.states, self.st_idx, self.mix
        assert states is not None and st_idx is not None
        r_nlos = self.rec["z"] - self.h - states.values[st_idx]
        ll_l, ll_n = mix.log_likelihoods(self.r_los, r_nlos, self.e_var)
        if BATCH_SEARCH:
            g_cur = self.g if g_prev is not None or not self.nlos_first else np.ones(len(self.g))
            ll_l, ll_n = _search_windows(self.values, self.rec, self.anchors, self.n_kf,
                                         self.a_r, self.r_los, g_cur, mix, self.e_var, ll_l,
                                         ll_n)
        evidence = self.rec["evidence"]
        if np.any(evidence):  # the learned classifier's log-odds, at the weight the log gives
            g_resid = _smooth_per_anchor(ll_l, ll_n, self.a_r, self.order, self.inv, mix,
                                         self.p_switch)
            self.classifier_weight = classifier_weight(g_resid, evidence)
            ll_n = ll_n + self.classifier_weight * evidence
        self.g = _smooth_per_anchor(ll_l, ll_n, self.a_r, self.order, self.inv, mix,
                                    self.p_switch)
        mix.m_step(self.r_los, r_nlos, self.g, self.prior)
        self.sig_l = mix.sigma_los

    def em_rounds(self) -> None:
        """E-step and a short LM round until the responsibilities settle."""
        rounds = max(self.g_cfg.em_iterations, 0) + 1 if self.g_cfg.nlos else 1
        g_prev: np.ndarray | None = None
        for it in range(rounds):
            if self.states is not None and self.st_idx is not None:
                self._e_step(it, g_prev)
            if g_prev is not None and np.mean(np.abs(self.g - g_prev) > 0.2) < 0.01:
                break
            g_prev = self.g
            self.done = it + 1
            # intermediate EM rounds only need LM to get close: the next E-step moves anyway
            self.lm_round(self.g, self.freeze, EM_ROUND_LM_ITERATIONS)
            if self.with_scale:
                self._refit_scale()
                self.r_los = (self.rec["z"] - self.h
                              - _bias_values(self.values, self.n_anchor)[self.a_r])
            if self.states is not None:
                self._read_states()

    def settle(self) -> None:
        """The scales and the geometry settle together, the LOS offsets are released, and
        the wheel scale is refitted."""
        for _ in range(2 if self.with_scale else 0):
            self.lm_round(self.g, self.freeze)
            self._refit_scale()
        if self.freeze:
            self.lm_round(self.g, False)
        # the wheel scale is fitted once the range biases are free: fitted in the EM rounds,
        # with D(a) held at zero, it would take up the radios' range offsets
        if self.wheel_scale is not None:
            self.wheel_scale.refit(self.values, self.n_kf)
            if self.wheel_scale.apply([self.base_graph, *self.graphs.static.values()]):
                self.lm_round(self.g, False)

    def recalibrate(self) -> bool:
        """Hold EM's LOS offsets at the released ones (not at zero) from now on, and hold
        each around the common offset C, when next released, by the spread the released
        ones show (empirical Bayes: the RMS of D(a) - C, within ANCHOR_SPREAD_MIN and the
        configured `range_bias_anchor_sigma`); False when the offsets are not held (no
        NLOS model or no offsets estimated)."""
        if not self.freeze:
            return False
        d = _bias_values(self.values, self.n_anchor)
        spread = float(np.sqrt(np.mean((d - self.values.atDouble(C)) ** 2)))
        self.graphs.hold_offsets(d, float(np.clip(spread, ANCHOR_SPREAD_MIN,
                                                  self.g_cfg.range_bias_anchor_sigma)))
        return True

    def result(self, with_marginals: bool = True) -> BatchResult:
        """The run's `BatchResult` at its final values (a snapshot: later phases do not
        change it); `with_marginals`: with the marginals of its final graph."""
        uwb, states, values = self.uwb, self.states, self.values
        w = robust_weight(uwb.robust_kernel, uwb.kernel_threshold, self.r_los / self.sig_l)
        nlos_out = None
        if states is not None:
            nlos_out = (states.anchor.copy(), states.seg.copy(),
                        np.array([values.atDouble(k) for k in states.keys]))
        marginals = functools.partial(_em_marginals, self.graphs, values, self.rec,
                                      self.anchors, self.n_kf, self.h, self.r_los, self.g,
                                      self.sig_l, self.st_idx)
        return BatchResult(values, self.g, w, self.r_los, copy.copy(self.mix), self.done,
                           self.graphs.iterations, self.scale.copy(),
                           self.nlos_first and states is not None,
                           None if self.wheel_scale is None
                           else self.wheel_scale.applied.copy(),
                           nlos_states=nlos_out,
                           range_model="mixture" if states is not None else "robust",
                           classifier_weight=self.classifier_weight,
                           marginals=marginals if with_marginals
                           and self.g_cfg.marginal_covariances is not False else None)


def observed_information_share(
    r_los: np.ndarray, r_nlos: np.ndarray, g: np.ndarray, sigma_los: float,
    sigma_nlos: float,
) -> np.ndarray:
    """Per range, the observed information of its two-component likelihood about the
    predicted range over the information the EM-weighted factors give it, in [0, 1].

    EM's factors carry the complete-data information (1 - g) / sigma_los^2 + g /
    sigma_nlos^2, as if each range's LOS/NLOS class were known. The information the data
    hold is smaller by the missing information, the variance of the score over the class
    (Louis, 1982): g (1 - g) (r_los / sigma_los^2 - r_nlos / sigma_nlos^2)^2. Certain
    classes (g near 0 or 1) lose nothing; an ambiguous range, whose class the fit could
    have taken the other way, loses most of its weight in the marginals. Residuals in
    metres at the solution (`r_nlos` against the range's NLOS state).
    """
    s_l = r_los / sigma_los**2
    s_n = r_nlos / sigma_nlos**2
    complete = (1.0 - g) / sigma_los**2 + g / sigma_nlos**2
    missing = g * (1.0 - g) * (s_l - s_n) ** 2
    return np.clip(1.0 - missing / complete, 0.0, 1.0)


def _search_windows(
    values: gtsam.Values, rec: dict[str, np.ndarray], anchors: np.ndarray, n_kf: int,
    a_r: np.ndarray, r_los: np.ndarray, g: np.ndarray, mix: NlosModel, e_var: float,
    ll_l: np.ndarray, ll_n: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """E-step escape from EM's local optimum (see `uwb.los_subset_search`): in each
    BATCH_SEARCH_WINDOW_S stretch of the log, when another LOS/NLOS assignment of the
    anchors (with a rigid shift of the stretch's track) beats the current one by
    BATCH_SEARCH_NATS, the stretch's ranges are scored against that hypothesis instead."""
    u, win = _search_geometry(values, rec, anchors, n_kf, a_r)
    ll_l, ll_n = ll_l.copy(), ll_n.copy()
    for w in np.unique(win).tolist():
        sel = np.flatnonzero(win == w)
        hyp = los_subset_search(a_r[sel], r_los[sel], u[sel], g[sel], mix, moment=False)
        if hyp is None or hyp.gain <= BATCH_SEARCH_NATS or not np.any(hyp.los != hyp.current):
            continue
        rl = r_los[sel] - u[sel] @ hyp.delta
        exc = np.full(int(a_r.max()) + 1, mix.mu_nlos)
        exc[hyp.anchors] = np.where(hyp.los, mix.mu_nlos, hyp.excess)
        ll_l[sel], ll_n[sel] = mix.log_likelihoods(rl, rl - exc[a_r[sel]], e_var)
    return ll_l, ll_n


def _search_geometry(
    values: gtsam.Values, rec: dict[str, np.ndarray], anchors: np.ndarray, n_kf: int,
    a_r: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Per range: the horizontal unit vector (N,2) from its anchor to the tag at `values`,
    and its BATCH_SEARCH_WINDOW_S window index (N,) from the first range."""
    rot, trans = keyframe_arrays(values, n_kf)
    k = rec["k"]
    p = np.einsum("nij,nj->ni", rot[k], rec["tag_in_kf"]) + trans[k]
    diff = p - anchors[a_r]
    h = np.linalg.norm(diff, axis=1)
    u = diff[:, :2] / np.maximum(h, 1e-6)[:, None]
    t = rec["t_ns"]
    return u, (t - t.min()) // round(BATCH_SEARCH_WINDOW_S * NS_PER_S)


def hypothesis_shift_moments(
    values: gtsam.Values, rec: dict[str, np.ndarray], anchors: np.ndarray, n_kf: int,
    r_los: np.ndarray, g: np.ndarray, mix: NlosModel,
) -> np.ndarray:
    """Per keyframe, E[delta delta^T] (n_kf,2,2), m^2 in map x, y: the second moment of the
    rigid shift of its BATCH_SEARCH_WINDOW_S stretch over every LOS/NLOS assignment of the
    stretch's anchors, weighted by the assignment's evidence (`uwb.los_subset_search`).

    The marginals are conditional on the responsibilities EM settled on; where another
    assignment explains the stretch about as well (or better) and puts the track elsewhere,
    the model's own posterior over assignments says the position is that much less
    certain (Bayesian model averaging: the mean squared error about the reported track is
    the conditional covariance plus this moment). Near zero where the assignment is clear;
    zero where the search does not run (more than `constants.SEARCH_MAX_ANCHORS` anchors heard
    in a stretch, or too few ranges).
    """
    a_r = rec["anchor"].astype(np.int64)
    out = np.zeros((n_kf, 2, 2))
    if len(a_r) == 0:
        return out
    u, win = _search_geometry(values, rec, anchors, n_kf, a_r)
    kf_win = np.full(n_kf, -1, np.int64)
    for w in np.unique(win).tolist():
        sel = np.flatnonzero(win == w)
        hyp = los_subset_search(a_r[sel], r_los[sel], u[sel], g[sel], mix)
        kf = rec["k"][sel].astype(np.int64)
        kf_win[kf.min():kf.max() + 1] = w
        if hyp is not None:
            out[kf.min():kf.max() + 1] = hyp.shift_moment
    # keyframes between two stretches' ranges take the earlier stretch's moment
    for i in range(1, n_kf):
        if kf_win[i] < 0:
            out[i] = out[i - 1]
    return out


def refit_scale(
    scale: np.ndarray, r: np.ndarray, h: np.ndarray, w: np.ndarray, a: np.ndarray,
    sigma_los: float, sigma_k: float, common: bool = False,
) -> None:
    """One Gauss-Newton step per anchor of z / (1 + k) = d + b (in place, prior sigma_k);
    `common`: one k shared by every anchor (the radios' clock, not the anchors)."""
    lam = (sigma_los / sigma_k) ** 2
    if common:
        a = np.zeros_like(a)
        scale[:] = float(np.mean(scale))
    num = np.bincount(a, weights=w * r * h, minlength=len(scale))
    den = np.bincount(a, weights=w * h * h, minlength=len(scale))
    if common:
        num[:], den[:] = num[0], den[0]
    scale[:] = np.clip((1.0 + scale) * (1.0 + num / (den + lam)) - 1.0, -0.2, 0.2)


def motion_fit_error(
    cfg: Config, base_graph: gtsam.NonlinearFactorGraph, initial: gtsam.Values,
    rec: dict[str, np.ndarray], scale: np.ndarray | None, sigma: float, with_bias: bool,
) -> tuple[float, gtsam.Values]:
    """Graph error after one Huber LM of `base_graph` plus every recorded range (scale
    corrected by `scale`, LOS sigma `sigma` m, on its anchor's bias when `with_bias`) from
    `initial`: a negative log-likelihood (up to a constant) to compare motion factors
    built differently by; and the solution it is taken at (a start for the next)."""
    graph = with_robust_ranges(cfg, base_graph, rec, scale, sigma, with_bias)
    opt = run_lm(graph, initial, cfg.graph.lm_max_iterations)
    return opt.error, opt.values


def with_robust_ranges(
    cfg: Config, base_graph: gtsam.NonlinearFactorGraph, rec: dict[str, np.ndarray],
    scale: np.ndarray | None, sigma: float, with_bias: bool,
) -> gtsam.NonlinearFactorGraph:
    """`base_graph` (copied, its factors' indices kept) plus every recorded range as a
    Huber factor (see `motion_fit_error`)."""
    graph = gtsam.NonlinearFactorGraph(base_graph)
    a = rec["anchor"].astype(np.int64)
    z = rec["z"] / (1.0 + scale[a]) if scale is not None else rec["z"]
    noise = range_noise(sigma, RobustKernel.HUBER, cfg.uwb.kernel_threshold)
    for k, aa, zz, tag in zip(rec["k"].tolist(), a.tolist(), z.tolist(),
                              np.asarray(rec["tag_in_kf"], float), strict=True):
        graph.add(range_factor_keyed(X(k), L(aa), los_bias_key(aa, with_bias), zz, noise,
                                     gtsam.Pose3(gtsam.Rot3(), tag)))
    return graph
