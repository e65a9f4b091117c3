# SPDX-License-Identifier: BSD-3-Clause
"""Sensor noise levels from the log: type-II maximum likelihood of inflation factors.

The configured noise of a sensor (`wheel.sigma_v`, `wheel.sigma_omega`; the `[imu]`
densities and random walks) is a guess. The graph scales the covariance of every factor of
the sensor by the factors f (one per coordinate: (f_v, f_omega) for the wheels, one for the
IMU) of greatest Laplace evidence of the motion-fit graph (`offline.motion_fit_error`'s:
the recorded non-range factors plus every range as a Huber factor at one common sigma):

    log p(z | f) ~ -E(x*) - 1/2 sum log det Sigma(f) - 1/2 log det H(x*)

the graph error at the optimum, the sensor's factors' Gaussian normalisers and the
Hessian's log-determinant (`GaussianBayesNet.logDeterminant` of the eliminated
linearisation is 1/2 log det H). Unlike the error alone it does not favour the loosest
noise, and unlike an in-sample chi-square it is not biased where the sensor's factors alone
hold the track (a range outage: there their residuals carry no information about their
noise). Huber kernels enter through their loss and their weights at x*.

The search (`fit_noise`) runs on a grid of NOISE_STEP (log2) steps from the configured
noise upwards, one coordinate at a time, then takes the vertex of the parabola through each
factor's best three. One-sided: the configured noise also stands for the sensor's
correlated errors (scale, slip, misalignment) that a white-noise evidence cannot see, so
the log may loosen it but not tighten it. An evidence still rising at the grid's top edge
is no noise of that sensor but another model's misfit that the loose factors absorb
(docs/results.md, "Wheel noise fit: an evidence that rises to the edge"): the configured
noise is then kept.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import gtsam
import numpy as np

from uwbfuse.config import Config
from uwbfuse.constants import (
    IMU_INFLATION_MAX_LOG2,
    IMU_NOISE_TEST_NATS,
    MOTION_NOISE_MAX_LOG2,
    MOTION_NOISE_MIN_LOG2,
    NOISE_PRIOR_LOG2,
    NOISE_STEP,
    ONLINE_FIRST_S,
    WHEEL_NOISE_MAX_LOG2,
    WHEEL_NOISE_TEST_NATS,
)
from uwbfuse.graph.builder import RecentMotion, WheelRecords
from uwbfuse.graph.imu import ImuRecords
from uwbfuse.graph.offline import replace_wheel_factors, run_lm, with_robust_ranges
from uwbfuse.graph.wheel import planar_covariance6

log = logging.getLogger(__name__)

# log2: the IMU within 1 .. 256 of the configured densities (`constants.IMU_INFLATION_MAX_LOG2`)
IMU_NOISE_MAX_LOG2 = IMU_INFLATION_MAX_LOG2


@dataclass(frozen=True)
class NoiseFamily:
    """The factors of one sensor whose noise the evidence may loosen.

    `apply(graph, f)` puts them into `graph` (at their indices) with their covariances
    scaled by the factors `f` (on the standard deviations, one per coordinate) and returns
    the sum of their Gaussian normalisers 1/2 log det Sigma(f)."""

    name: str
    apply: Callable[[gtsam.NonlinearFactorGraph, tuple[float, ...]], float]
    size: int  # coordinates (factors fitted)
    max_log2: float
    test_nats: float
    # log2 of the smallest factor: 0 for a sensor (loosen only, see the module docstring);
    # below 0 for the constant-velocity prior, which is no sensor and may be held tighter
    min_log2: float = 0.0


def wheel_family(wheel: WheelRecords) -> NoiseFamily:
    """The wheel factors, their (x, y, theta) covariances scaled by (f_v, f_v, f_omega)."""

    def apply(graph: gtsam.NonlinearFactorGraph, f: tuple[float, ...]) -> float:
        c = np.array([f[0], f[0], f[1]])
        scaled = np.asarray(wheel.cov) * np.outer(c, c)
        logdet = np.linalg.slogdet(planar_covariance6(scaled, wheel.out_of_plane))[1]
        replace_wheel_factors([graph], wheel.k, np.asarray(wheel.delta), scaled, wheel.index,
                              wheel.out_of_plane)
        return sum((0.5 * logdet).tolist())

    return NoiseFamily("wheel", apply, 2, WHEEL_NOISE_MAX_LOG2, WHEEL_NOISE_TEST_NATS)


def imu_family(imu: ImuRecords, cfg: Config) -> NoiseFamily:
    """The IMU factors, their noise densities and bias random walks times f (their
    preintegrated covariances f^2 N + I, `ImuRecords.covariance_parts`); for the
    constant-velocity prior's virtual IMU (`ImuRecords.params_at`), its acceleration
    density times f, searched both ways (MOTION_NOISE_MIN_LOG2 .. MOTION_NOISE_MAX_LOG2):
    how smoothly a tag moves is a property of the vehicle, not a sensor's noise floor."""
    n_part, i_part = imu.covariance_parts(cfg.imu, cfg.extrinsics)

    def apply(graph: gtsam.NonlinearFactorGraph, f: tuple[float, ...]) -> float:
        cov = f[0] ** 2 * n_part + i_part
        for idx, factor in zip(imu.index, imu.factors_at(graph, cov), strict=True):
            graph.replace(idx, factor)
        return 0.5 * float(np.sum(np.linalg.slogdet(cov)[1]))

    if imu.params_at is not None:
        return NoiseFamily("motion prior", apply, 1, MOTION_NOISE_MAX_LOG2, IMU_NOISE_TEST_NATS,
                           MOTION_NOISE_MIN_LOG2)
    return NoiseFamily("imu", apply, 1, IMU_NOISE_MAX_LOG2, IMU_NOISE_TEST_NATS)


def noise_log_evidence(
    graph: gtsam.NonlinearFactorGraph, initial: gtsam.Values, family: NoiseFamily,
    factors: tuple[float, ...], max_iterations: int,
) -> tuple[float, gtsam.Values]:
    """Laplace log-evidence (nats, up to a constant) of `graph` with `family`'s factors
    (replaced in place) at noise `factors`, and the LM solution it is taken at (see the
    module docstring)."""
    half_logdet_cov = family.apply(graph, factors)
    opt = run_lm(graph, initial, max_iterations)
    log.debug("%s noise %s: %d LM iterations", family.name, factors, opt.iterations)
    values = opt.values
    half_logdet_h = graph.linearize(values).eliminateSequential().logDeterminant()
    return -graph.error(values) - half_logdet_cov - half_logdet_h, values


def evidence_graph(
    cfg: Config, base_graph: gtsam.NonlinearFactorGraph, rec: dict[str, np.ndarray],
    scale: np.ndarray | None, sigma: float, with_bias: bool, pose_index: Sequence[int] = (),
) -> gtsam.NonlinearFactorGraph:
    """The graph the evidence is taken over: `base_graph` (copied, indices kept) plus every
    recorded range as in `offline.motion_fit_error`, without the external-pose factors
    (`pose_index`, their indices in `base_graph`): a localiser's wrong match is an offset
    held for seconds (the matcher locked onto the wrong place), which a white-noise
    evidence explains as a loose motion model."""
    graph = with_robust_ranges(cfg, base_graph, rec, scale, sigma, with_bias)
    for i in pose_index:
        graph.remove(i)  # a null slot: every other factor keeps its index
    return graph


class _GridSearch:
    """The evidence (`noise_log_evidence`) times the hyperprior (NOISE_PRIOR_LOG2) on the
    log2 grid of one family's factors, each grid point solved once, each solve starting
    from the best solution so far."""

    def __init__(self, graph: gtsam.NonlinearFactorGraph, initial: gtsam.Values,
                 family: NoiseFamily, max_iterations: int) -> None:
        self.graph, self.family, self.max_iterations = graph, family, max_iterations
        self.seen: dict[tuple[float, ...], float] = {}
        self.values = initial

    def score(self, u: tuple[float, ...]) -> float:
        if u not in self.seen:
            ev, vals = noise_log_evidence(self.graph, self.values, self.family,
                                          tuple(2.0 ** x for x in u), self.max_iterations)
            ev -= 0.5 * sum(x * x for x in u) / NOISE_PRIOR_LOG2**2
            self.seen[u] = ev
            log.debug("%s noise %s: %.2f", self.family.name, u, ev)
            if ev >= max(self.seen.values()):
                self.values = vals
        return self.seen[u]

    def climb(self, start: tuple[float, ...]) -> tuple[float, ...]:
        """The best grid point by coordinate ascent from `start`."""
        best = start
        self.score(best)
        moved = True
        while moved:
            moved = False
            for j in range(self.family.size):
                for sign in (1.0, -1.0):
                    while True:
                        cand = list(best)
                        cand[j] += sign * NOISE_STEP
                        if not self.family.min_log2 <= cand[j] <= self.family.max_log2 or \
                                self.score(tuple(cand)) <= self.seen[best]:
                            break
                        best = tuple(cand)
                        moved = True
        return best

    def vertex(self, best: tuple[float, ...]) -> np.ndarray:
        """Per factor, the vertex of the parabola through the best and its two neighbours
        (the best itself where one is missing)."""
        out = np.array(best)
        for j in range(self.family.size):
            lo, hi = list(best), list(best)
            lo[j] -= NOISE_STEP
            hi[j] += NOISE_STEP
            e0, e2 = self.seen.get(tuple(lo)), self.seen.get(tuple(hi))
            if e0 is None or e2 is None:
                continue
            curv = e0 - 2.0 * self.seen[best] + e2
            if curv < 0:
                out[j] += 0.5 * NOISE_STEP * (e0 - e2) / curv
        return np.clip(out, self.family.min_log2, self.family.max_log2)

    def upper_end(self, best: tuple[float, ...]) -> float:
        """One factor: the largest (log2) whose evidence lies within `family.test_nats` of
        the best's, linear between grid points (the grid's top if none above falls out)."""
        floor = self.seen[best] - self.family.test_nats
        u = best[0]
        while u + NOISE_STEP <= self.family.max_log2:
            e_in, e_out = self.seen[(u,)], self.score((u + NOISE_STEP,))
            if e_out < floor:
                return u + NOISE_STEP * (e_in - floor) / (e_in - e_out)
            u += NOISE_STEP
        return u


def fit_noise(
    graph: gtsam.NonlinearFactorGraph, initial: gtsam.Values, family: NoiseFamily,
    max_iterations: int, start: Sequence[float] | None = None, loosest: bool = False,
) -> np.ndarray | None:
    """The factors (times the configured noise) of greatest posterior density: the
    evidence (`noise_log_evidence`) over `graph` times the hyperprior (NOISE_PRIOR_LOG2),
    searched from `start` (log2 factors on the grid, default the configured noise), at the
    vertex of the parabola through the best grid point and its neighbours; ones when the
    configured noise is not rejected (`family.test_nats`); None when the graph is singular
    or the evidence still rises at the grid's edge (no verdict on the sensor's noise).

    `loosest` (one factor, the online IMU fit): the loosest factor whose evidence lies
    within `family.test_nats` of the best instead (the upper end of its likelihood
    interval, no test against the configured noise): for a causal smoother an IMU held
    too loose costs little and one held too tight much, and a window whose evidence
    cannot decide then does not tighten the factors (docs/results.md, "IMU noise from the
    log")."""
    origin = (0.0,) * family.size
    search = _GridSearch(graph, initial, family, max_iterations)
    try:
        best = search.climb(origin if start is None else tuple(float(x) for x in start))
        if max(best) >= family.max_log2:  # see the module docstring
            log.warning("%s noise: the evidence still rises at %gx the configured noise, "
                        "a misfit of another model rather than %s noise: not fitted",
                        family.name, 2.0 ** family.max_log2, family.name)
            return None
        if loosest:
            return np.array([2.0 ** search.upper_end(best)])
        if not _rejects_origin(search.seen, best, family.test_nats):
            search.score(origin)
    except RuntimeError as exc:  # indeterminant linear system: keep the configured noise
        log.warning("%s noise: not fitted (%s)", family.name,
                    str(exc).splitlines()[0] if str(exc) else "error")
        return None
    seen = search.seen
    if origin in seen and seen[best] - seen[origin] <= family.test_nats:
        return np.ones(family.size)
    out = search.vertex(best)
    log.debug("%s noise: log2 factors %s -> %s (%d solves)", family.name, best, out, len(seen))
    return 2.0 ** out


def _rejects_origin(seen: dict[tuple[float, ...], float], best: tuple[float, ...],
                    test_nats: float) -> bool:
    """One factor, its best grid point above the origin and the one below scored: the gain
    from the origin to the best is at least the best's distance in steps times the gain of
    its last step (a concave log-evidence, as the search already takes it to be unimodal),
    so the configured noise is rejected without its solve (the slowest: the stiffest
    graph, farthest from the best's solution) when that bound exceeds `test_nats`."""
    if len(best) != 1 or best[0] < 2 * NOISE_STEP:
        return False
    below = seen.get((best[0] - NOISE_STEP,))
    return below is not None and best[0] / NOISE_STEP * (seen[best] - below) > test_nats


def fit_wheel_noise(
    cfg: Config, base_graph: gtsam.NonlinearFactorGraph, initial: gtsam.Values,
    rec: dict[str, np.ndarray], scale: np.ndarray | None, sigma: float, with_bias: bool,
    wheel: WheelRecords, pose_index: Sequence[int] = (),
) -> np.ndarray:
    """(f_v, f_omega): the wheel noise factors of the evidence over `base_graph` plus the
    recorded ranges (`evidence_graph`, `fit_noise`); (1, 1) without wheel factors or
    ranges (nothing absolute is left to tell the wheels' noise by) or without a verdict."""
    if not wheel.k or not len(rec["z"]):
        return np.ones(2)
    graph = evidence_graph(cfg, base_graph, rec, scale, sigma, with_bias, pose_index)
    out = fit_noise(graph, initial, wheel_family(wheel), cfg.graph.lm_max_iterations)
    return np.ones(2) if out is None else out


def fit_imu_noise(
    cfg: Config, base_graph: gtsam.NonlinearFactorGraph, initial: gtsam.Values,
    rec: dict[str, np.ndarray], scale: np.ndarray | None, sigma: float, with_bias: bool,
    imu: ImuRecords, pose_index: Sequence[int] = (), start: float = 1.0,
) -> float:
    """batch: the IMU noise inflation of the evidence over `base_graph` plus the recorded
    ranges (`evidence_graph`, `fit_noise`), searched from the grid point nearest `start`
    (the inflation the online pass ended with); 1 (the configured noise) without IMU
    factors or ranges, or without a verdict."""
    if not imu.k or not len(rec["z"]):
        return 1.0
    graph = evidence_graph(cfg, base_graph, rec, scale, sigma, with_bias, pose_index)
    family = imu_family(imu, cfg)
    out = fit_noise(graph, initial, family, cfg.graph.lm_max_iterations,
                    (_grid_point(start, family),))
    return 1.0 if out is None else float(out[0])


def _grid_point(inflation: float, family: NoiseFamily) -> float:
    """The log2 grid point nearest `inflation`, within `family`'s grid."""
    u = np.round(np.log2(inflation) / NOISE_STEP) * NOISE_STEP
    return float(np.clip(u, family.min_log2, family.max_log2))


# The online graph's IMU noise (causal): the same evidence over the newest
# ONLINE_WINDOW_S of the graph (`builder.RecentMotion`: its motion factors and ranges, a
# loose prior on its first keyframe), first once ONLINE_FIRST_S of keyframes are in, then
# each time the graph's age has doubled since the last fit; the result is used for the IMU
# factors built afterwards. The work of one fit is bounded by the window, and the fits
# become rarer as the log goes on (a sensor's noise level does not change with time).


def online_fit_due(age_s: float, last_fit_age_s: float | None) -> bool:
    """A fit is due at graph age `age_s` (s since the first keyframe), the last one having
    been at `last_fit_age_s` (None: none yet)."""
    if last_fit_age_s is None:
        return age_s >= ONLINE_FIRST_S
    return age_s >= 2.0 * last_fit_age_s


def fit_imu_window(
    cfg: Config, recent: RecentMotion, priors: gtsam.NonlinearFactorGraph,
    values: gtsam.Values, scale: np.ndarray | None, range_bias: np.ndarray | None,
    sigma: float, start: float,
) -> float | None:
    """The online graph's IMU noise inflation over `recent` (causal: only data received so
    far): its motion factors, `priors` (on its first keyframe and the anchors) and its
    ranges as Huber factors at `sigma` (m; scale- and offset-corrected by the online
    estimates `scale`, `range_bias`), from `values`; searched from the grid point nearest
    `start` (the inflation in use). None without a verdict (`fit_noise`) or without
    ranges."""
    graph = gtsam.NonlinearFactorGraph(priors)
    index = []
    for factors in recent.factors:
        index.append(graph.size())  # the interval's IMU factor comes first
        for f in factors:
            graph.add(f)
    ka = np.array(recent.ka, np.int64)
    n = np.array([len(r[1]) for r in recent.ranges], np.int64)
    if not n.sum():
        return None
    anchor = np.concatenate([r[0] for r in recent.ranges]).astype(np.int64)
    z = np.concatenate([r[1] for r in recent.ranges])
    if scale is not None:
        z = z / (1.0 + scale[anchor])
    if range_bias is not None:
        z = z - range_bias[anchor]
    rec = {"k": np.repeat(ka, n), "anchor": anchor, "z": z,
           "tag_in_kf": np.concatenate([r[2] for r in recent.ranges])}
    graph = with_robust_ranges(cfg, graph, rec, None, sigma, False)
    family = imu_family(recent.imu.reindexed(index), cfg)
    out = fit_noise(graph, values, family, cfg.graph.lm_max_iterations,
                    (_grid_point(start, family),), loosest=True)
    return None if out is None else float(out[0])
