# SPDX-License-Identifier: BSD-3-Clause
"""`evaluate(est, gt)`: associate, align, score. The library function behind `uwbfuse eval`.

The result keeps the per-pose error arrays and their times (for error-vs-time and CDF
plots) beside the summary statistics; `table()` renders it for the terminal and
`write_json()` writes the metrics.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from uwbfuse.errors import EvaluationError
from uwbfuse.eval.align import Alignment, RigidTransform, fit_alignment
from uwbfuse.eval.associate import Association, associate
from uwbfuse.eval.metrics import (
    COVERAGE_MAX_GAP_S,
    Stats,
    ate_errors,
    coverage,
    pairs_by_path,
    pairs_by_time,
    rpe_errors,
    stats,
    yaw_errors,
)
from uwbfuse.io.atomic import write_atomic
from uwbfuse.streams import F64, I64, NS_PER_S, PoseStream

MIN_PAIRS = 3
"""Fewest associated poses an evaluation accepts (an SE(3) fit needs three)."""


@dataclass(frozen=True)
class RpeResult:
    """Relative pose error over one delta: `delta` in `unit` ("s" = time, "m" = GT path).

    `relation` is "translation_part" (evo's, with GT orientation) or "map_displacement"
    (GT without orientation). `i`, `j` index the associated pairs; `t_ns` is the start
    stamp of each pair and `errors` its translation error in metres.
    """

    delta: float
    unit: str
    relation: str
    i: I64
    j: I64
    t_ns: I64
    errors: F64
    stats: Stats

    @property
    def label(self) -> str:
        return f"RPE {self.delta:g} {self.unit}"


@dataclass
class EvalResult:
    """Metrics of one estimate against ground truth, with per-pose arrays for plots.

    Positions in metres (map frame, estimate after alignment), angles in radians, times
    are GT stamps of the associated pairs (int64 ns; `t_s` in seconds).
    """

    est_name: str
    gt_name: str
    align: Alignment
    max_dt: float
    n_est: int
    n_gt: int
    transform: RigidTransform
    t_ns: I64
    est_position: F64
    gt_position: F64
    ate_3d_errors: F64
    ate_2d_errors: F64
    ate_3d: Stats
    ate_2d: Stats
    rpe: list[RpeResult]
    yaw_errors: F64 | None
    yaw: Stats | None
    coverage: float
    gt_span_s: float
    est_rate_hz: float
    notes: list[str] = field(default_factory=list)

    @property
    def n_pairs(self) -> int:
        return len(self.t_ns)

    @property
    def t_s(self) -> F64:
        return self.t_ns.astype(np.float64) / NS_PER_S

    def as_dict(self) -> dict[str, Any]:
        """The metrics (no per-pose arrays) as plain JSON-ready values; NaN -> None."""

        def clean(d: dict[str, Any]) -> dict[str, Any]:
            return {
                k: (None if isinstance(v, float) and not math.isfinite(v) else v)
                for k, v in d.items()
            }

        return {
            "estimate": self.est_name,
            "ground_truth": self.gt_name,
            "align": self.align.value,
            "max_dt_s": self.max_dt,
            "n_est": self.n_est,
            "n_gt": self.n_gt,
            "n_pairs": self.n_pairs,
            "ate_3d_m": clean(self.ate_3d.as_dict()),
            "ate_2d_m": clean(self.ate_2d.as_dict()),
            "rpe": [
                {
                    "delta": r.delta,
                    "delta_unit": r.unit,
                    "relation": r.relation,
                    "stats_m": clean(r.stats.as_dict()),
                }
                for r in self.rpe
            ],
            "yaw_rad": None if self.yaw is None else clean(self.yaw.as_dict()),
            "coverage": self.coverage,
            "gt_span_s": self.gt_span_s,
            "est_rate_hz": self.est_rate_hz,
            "alignment": {
                "rotation": self.transform.rotation.tolist(),
                "translation_m": self.transform.translation.tolist(),
            },
            "notes": list(self.notes),
        }

    def table(self) -> str:
        """A readable multi-line summary for the terminal."""
        lines = [
            f"estimate:     {self.est_name} ({self.n_est} poses)",
            f"ground truth: {self.gt_name} ({self.n_gt} poses, {self.gt_span_s:.1f} s)",
            f"associated {self.n_pairs} pairs within {self.max_dt:.3f} s, alignment "
            f"{self.align.value}, coverage {100 * self.coverage:.1f} % of the GT span, "
            f"{self.est_rate_hz:.1f} estimate poses/s",
            "",
            f"{'metric':<16}{'n':>7}{'rmse':>10}{'mean':>10}{'median':>10}"
            f"{'std':>10}{'max':>10}",
        ]

        def row(name: str, s: Stats, scale: float = 1.0) -> str:
            vals = [s.rmse, s.mean, s.median, s.std, s.max]
            return f"{name:<16}{s.n:>7}" + "".join(f"{v * scale:>10.4f}" for v in vals)

        lines.append(row("ATE 3-D [m]", self.ate_3d))
        lines.append(row("ATE 2-D [m]", self.ate_2d))
        for r in self.rpe:
            lines.append(row(f"{r.label} [m]", r.stats))
        if self.yaw is not None:
            lines.append(row("|yaw| [deg]", self.yaw, 180.0 / math.pi))
        if self.rpe:
            over = " and ".join(
                f"{r.delta:g} s of time" if r.unit == "s" else f"{r.delta:g} m of GT path"
                for r in self.rpe
            )
            lines.append(f"(RPE: translation error of the motion over {over}; "
                         f"{self.rpe[0].relation})")
        if self.notes:
            lines.append("")
            lines.extend(f"note: {n}" for n in self.notes)
        return "\n".join(lines)

    def write_json(self, path: str | Path) -> None:
        """Write `as_dict()` to `path` as JSON, atomically (temporary file + rename)."""
        p = Path(path)
        text = json.dumps(self.as_dict(), indent=2) + "\n"
        write_atomic(p, text, error=EvaluationError, what="metrics")


def _span(p: PoseStream) -> str:
    return f"[{p.t_ns[0] / NS_PER_S:.3f}, {p.t_ns[-1] / NS_PER_S:.3f}] s"


def evaluate(
    est: PoseStream,
    gt: PoseStream,
    *,
    align: str | Alignment = "none",
    max_dt: float = 0.02,
    rpe_time_s: float = 1.0,
    rpe_dist_m: float = 10.0,
    est_name: str = "estimate",
    gt_name: str = "ground truth",
) -> EvalResult:
    """Score `est` against `gt` (both base frame in map frame).

    Steps: associate by nearest stamp within `max_dt` seconds (evo's rule), fit the
    alignment (none | se2 | se3, on positions), then ATE (3-D, 2-D), RPE over `rpe_time_s`
    seconds and over `rpe_dist_m` metres of GT path, yaw error (only when both have
    orientation) and coverage. Raises EvaluationError when the trajectories do not overlap
    in time or fewer than MIN_PAIRS poses associate.
    """
    kind = Alignment.parse(align)
    pairs = _associated(est, gt, max_dt, est_name, gt_name)
    notes: list[str] = []
    transform = fit_alignment(kind, pairs.est_position, pairs.gt_position)
    est_pos, est_quat = transform.apply(pairs.est_position, pairs.est_quat_xyzw)
    gt_pos, gt_quat = pairs.gt_position, pairs.gt_quat_xyzw
    if kind is not Alignment.NONE:
        notes.append(
            f"{kind.value} alignment: yaw {np.degrees(transform.yaw):.2f} deg, translation "
            + " ".join(f"{v:.3f}" for v in transform.translation)
            + " m"
        )

    with np.errstate(over="ignore", invalid="ignore"):  # overflow: the error just below
        e3, e2 = ate_errors(est_pos, gt_pos)
    if not (np.isfinite(e3).all() and np.isfinite(est_pos).all()):
        raise EvaluationError(f"{est_name}: errors against {gt_name} are not finite "
                              f"({kind.value} alignment): the poses are too far apart")

    oriented = gt.has_orientation and est.has_orientation
    if not oriented:
        which = "ground truth" if not gt.has_orientation else "estimate"
        notes.append(f"RPE uses map-frame displacements: {which} has no orientation")
    rpe = _relative_errors(pairs.t_ns, est_pos, est_quat, gt_pos,
                           gt_quat if oriented else None, rpe_time_s, rpe_dist_m, notes)

    yaw_err: F64 | None = None
    yaw_stats: Stats | None = None
    if not gt.has_orientation:
        notes.append("yaw error skipped: ground truth has no orientation (position only)")
    elif not est.has_orientation:
        notes.append("yaw error skipped: estimate has no orientation (position only)")
    else:
        yaw_err = yaw_errors(est_quat, gt_quat)
        yaw_stats = stats(np.abs(yaw_err))

    span_ns = int(gt.t_ns[-1] - gt.t_ns[0])
    span_s = span_ns / NS_PER_S
    in_span = np.count_nonzero((est.t_ns >= gt.t_ns[0]) & (est.t_ns <= gt.t_ns[-1]))
    cov = coverage(pairs.t_ns, int(gt.t_ns[0]), int(gt.t_ns[-1]))
    if cov < 0.9:
        notes.append(
            f"associated poses cover only {100 * cov:.1f} % of the GT span "
            f"(gaps over {COVERAGE_MAX_GAP_S} s count as uncovered)"
        )
    return EvalResult(
        est_name=est_name,
        gt_name=gt_name,
        align=kind,
        max_dt=max_dt,
        n_est=len(est),
        n_gt=len(gt),
        transform=transform,
        t_ns=pairs.t_ns,
        est_position=est_pos,
        gt_position=gt_pos,
        ate_3d_errors=e3,
        ate_2d_errors=e2,
        ate_3d=stats(e3),
        ate_2d=stats(e2),
        rpe=rpe,
        yaw_errors=yaw_err,
        yaw=yaw_stats,
        coverage=cov,
        gt_span_s=span_s,
        est_rate_hz=in_span / span_s if span_s > 0 else math.nan,
        notes=notes,
    )


def _associated(est: PoseStream, gt: PoseStream, max_dt: float, est_name: str,
                gt_name: str) -> Association:
    """The associated pose pairs (`associate`), or EvaluationError when either stream is
    empty, they do not overlap in time or fewer than MIN_PAIRS poses associate."""
    if max_dt < 0:
        raise EvaluationError(f"max_dt must be >= 0 s, got {max_dt}")
    if len(est) == 0:
        raise EvaluationError(f"{est_name}: no poses")
    if len(gt) == 0:
        raise EvaluationError(f"{gt_name}: no poses")
    max_dt_ns = round(max_dt * NS_PER_S)
    if est.t_ns[-1] < gt.t_ns[0] - max_dt_ns or est.t_ns[0] > gt.t_ns[-1] + max_dt_ns:
        raise EvaluationError(
            f"no overlap in time: {est_name} covers {_span(est)}, {gt_name} covers {_span(gt)}"
        )
    pairs = associate(est, gt, max_dt)
    if len(pairs) < MIN_PAIRS:
        raise EvaluationError(
            f"too few associated poses: {len(pairs)} of {est_name} lie within {max_dt} s of "
            f"{gt_name} (need {MIN_PAIRS}); check the stamps or raise --max-dt"
        )
    return pairs


def _relative_errors(
    t_ns: np.ndarray, est_pos: F64, est_quat: F64, gt_pos: F64, gt_quat: F64 | None,
    rpe_time_s: float, rpe_dist_m: float, notes: list[str],
) -> list[RpeResult]:
    """RPE over `rpe_time_s` seconds and over `rpe_dist_m` metres of GT path (translation
    part with `gt_quat`, map-frame displacements without); a note per empty one."""
    relation = "translation_part" if gt_quat is not None else "map_displacement"
    rpe: list[RpeResult] = []
    for delta, unit, (i, j) in (
        (rpe_time_s, "s", pairs_by_time(t_ns, rpe_time_s)),
        (rpe_dist_m, "m", pairs_by_path(gt_pos, rpe_dist_m)),
    ):
        errs = rpe_errors(i, j, est_pos, est_quat, gt_pos, gt_quat) if len(i) else np.zeros(0)
        if len(i) == 0:
            what = "time span" if unit == "s" else "ground-truth path"
            notes.append(f"RPE {delta:g} {unit}: no pose pairs ({what} too short)")
        rpe.append(RpeResult(delta, unit, relation, i, j, t_ns[i], errs, stats(errs)))
    return rpe
