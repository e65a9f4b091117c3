# SPDX-License-Identifier: BSD-3-Clause
"""A fleet on a common clock: every vehicle against the map, every pair against each other.

Pairs are checked at the epochs of the first vehicle of the pair inside the time both
trajectories cover, the second vehicle's state interpolated there. A fleet of a few
vehicles runs in a plain loop; many (or any with a scheduler given) as Dask tasks through
`uwbfuse.fleet.run_jobs`, as `uwbfuse batch` does: the vehicles are cut into contiguous
blocks and each task checks one block against the map and itself, or two blocks'
pairs.
"""

from __future__ import annotations

import itertools
import logging
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from uwbfuse.config import VehicleConfig
from uwbfuse.errors import CollisionCheckError
from uwbfuse.safety.classify import Check, check_map, check_pair
from uwbfuse.safety.geometry import Footprint, ObstacleMap
from uwbfuse.safety.motion import MotionState

log = logging.getLogger(__name__)

DASK_MIN_VEHICLES = 64
"""Vehicles from which the checks go to Dask without a scheduler given: a local cluster's
start and the states' transfer cost more than the checks of smaller fleets on one machine
(see scripts/bench_collisions.py and docs/results.md)."""
MIN_BLOCKS = 4
"""Fewest blocks the vehicles are split into for Dask (4 blocks: 10 tasks)."""


@dataclass(frozen=True)
class Track:
    """One vehicle: its name and motion state at its trajectory's epochs."""

    name: str
    state: MotionState


@dataclass(frozen=True)
class _BlockJob:
    """The checks among two blocks of vehicles (one block: its map checks and inner pairs);
    a Dask task's argument: everything it needs, picklable."""

    rows: tuple[Track, ...]
    cols: tuple[Track, ...] | None  # None: the diagonal block (rows against themselves)
    pairs: frozenset[tuple[str, str]]  # the overlapping pairs to check
    names: tuple[str, ...]
    geoms: Any
    vehicle: VehicleConfig


def _pair(ta: Track, tb: Track, footprint: Footprint, vehicle: VehicleConfig) -> Check:
    """`ta` against `tb` at the epochs of `ta` inside the span both cover."""
    lo, hi = max(ta.state.t_ns[0], tb.state.t_ns[0]), min(ta.state.t_ns[-1], tb.state.t_ns[-1])
    sa = ta.state.take(np.flatnonzero((ta.state.t_ns >= lo) & (ta.state.t_ns <= hi)))
    return check_pair(ta.name, tb.name, footprint, sa, tb.state.at(sa.t_ns), vehicle)


def run_block_job(job: _BlockJob) -> list[Check]:
    """Run one block (a Dask task: module level, picklable argument)."""
    footprint = Footprint.from_config(job.vehicle)
    out = []
    if job.cols is None:
        obstacles = ObstacleMap.build(list(zip(job.names, job.geoms, strict=True)))
        out += [check_map(t.name, footprint, t.state, obstacles, job.vehicle) for t in job.rows]
        candidates = list(itertools.combinations(job.rows, 2))
    else:
        candidates = [(a, b) for a in job.rows for b in job.cols]
    out += [_pair(a, b, footprint, job.vehicle) for a, b in candidates
            if (a.name, b.name) in job.pairs]
    return out


def overlapping_pairs(tracks: list[Track]) -> list[tuple[str, str]]:
    """Pairs (in input order) whose trajectories overlap in time; CollisionCheckError when
    a vehicle overlaps with none (with more than one vehicle)."""
    pairs = []
    for ta, tb in itertools.combinations(tracks, 2):
        if min(ta.state.t_ns[-1], tb.state.t_ns[-1]) > max(ta.state.t_ns[0], tb.state.t_ns[0]):
            pairs.append((ta.name, tb.name))
    seen = {n for p in pairs for n in p}
    alone = [t for t in tracks if t.name not in seen]
    if len(tracks) > 1 and alone:
        t = alone[0]
        raise CollisionCheckError(
            f"{t.name}: its trajectory ({t.state.t[0]:.3f}-{t.state.t[-1]:.3f} s) does "
            "not overlap in time with any other vehicle's")
    return pairs


def _blocks(tracks: list[Track], pairs: list[tuple[str, str]], obstacles: ObstacleMap,
            vehicle: VehicleConfig) -> list[_BlockJob]:
    """Contiguous blocks of about sqrt(n) vehicles (at least `MIN_BLOCKS`): every task then
    carries two blocks' states, not one pair's, so the states travel (blocks + 1) times."""
    n_blocks = min(len(tracks), max(MIN_BLOCKS, math.ceil(math.sqrt(len(tracks)))))
    blocks = [tuple(b) for b in np.array_split(np.array(tracks, dtype=object), n_blocks)]
    wanted = frozenset(pairs)
    jobs = []
    for i, rows in enumerate(blocks):
        for j in range(i, len(blocks)):
            cols = None if i == j else blocks[j]
            names = {t.name for t in rows} | {t.name for t in (cols or ())}
            sub = frozenset(p for p in wanted if p[0] in names and p[1] in names)
            jobs.append(_BlockJob(rows, cols, sub, obstacles.names, obstacles.geoms, vehicle))
    return jobs


def check_fleet(
    tracks: list[Track],
    obstacles: ObstacleMap,
    vehicle: VehicleConfig,
    *,
    use_dask: bool | None = None,
    scheduler: str | None = None,
    workers: int | None = None,
) -> list[Check]:
    """Every vehicle against the map and every overlapping pair: the map checks in vehicle
    order, then the pairs in input order. `use_dask` None: Dask from `DASK_MIN_VEHICLES`
    vehicles or when a scheduler is given."""
    names = [t.name for t in tracks]
    if len(set(names)) != len(names):
        raise CollisionCheckError(f"vehicle names must differ, got {', '.join(names)}")
    pairs = overlapping_pairs(tracks)
    if use_dask is None:
        use_dask = scheduler is not None or len(tracks) >= DASK_MIN_VEHICLES
    if not use_dask:
        return run_block_job(_BlockJob(tuple(tracks), None, frozenset(pairs), obstacles.names,
                                       obstacles.geoms, vehicle))

    from uwbfuse.fleet import Job, run_jobs

    jobs = [Job(f"collisions-block{k}", run_block_job, b)
            for k, b in enumerate(_blocks(tracks, pairs, obstacles, vehicle))]
    results: dict[tuple[str, str], Check] = {}

    def on_result(job: Job, value: Any, error: BaseException | None) -> None:
        if error is not None:
            raise CollisionCheckError(f"collision check {job.name} did not complete: {error}")
        results.update(((c.a, c.b), c) for c in value)

    run_jobs(jobs, on_result, scheduler=scheduler, workers=workers)
    return [results[(n, "map")] for n in names] + [results[p] for p in pairs]
