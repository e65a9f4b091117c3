# SPDX-License-Identifier: BSD-3-Clause
"""A fleet on a common clock: every vehicle against the map, every pair against each other.

Pairs are checked at the epochs of the first vehicle of the pair inside the time both
trajectories cover, the second vehicle's state interpolated there. The work is one job per
vehicle (map) and one per pair; a few vehicles run in a plain loop, many (or any with a
scheduler given) as Dask tasks through `uwbfuse.fleet.run_jobs`, as `uwbfuse batch` does.
"""

from __future__ import annotations

import itertools
import logging
from dataclasses import dataclass
from typing import Any

import numpy as np

from uwbfuse.config import VehicleConfig
from uwbfuse.errors import CollisionCheckError
from uwbfuse.safety.classify import Check, check_map, check_pair
from uwbfuse.safety.geometry import Footprint, ObstacleMap
from uwbfuse.safety.motion import MotionState

log = logging.getLogger(__name__)

DASK_MIN_VEHICLES = 8
"""Vehicles from which the checks go to Dask: below, a local cluster's start (~2-3 s of
worker processes) costs more than the checks themselves (see scripts/bench_collisions.py)."""


@dataclass(frozen=True)
class Track:
    """One vehicle: its name and motion state at its trajectory's epochs."""

    name: str
    state: MotionState


@dataclass(frozen=True)
class _MapJob:
    name: str
    footprint: Footprint
    state: MotionState
    names: tuple[str, ...]
    geoms: Any
    vehicle: VehicleConfig


@dataclass(frozen=True)
class _PairJob:
    a: str
    b: str
    footprint: Footprint
    sa: MotionState
    sb: MotionState
    vehicle: VehicleConfig


def run_map_job(job: _MapJob) -> Check:
    """One vehicle against the map (a Dask task: module level, picklable argument)."""
    obstacles = ObstacleMap.build(list(zip(job.names, job.geoms, strict=True)))
    return check_map(job.name, job.footprint, job.state, obstacles, job.vehicle)


def run_pair_job(job: _PairJob) -> Check:
    """One pair of vehicles (a Dask task)."""
    return check_pair(job.a, job.b, job.footprint, job.sa, job.sb, job.vehicle)


def _overlap(a: MotionState, b: MotionState) -> tuple[float, float] | None:
    lo, hi = max(a.t[0], b.t[0]), min(a.t[-1], b.t[-1])
    return (lo, hi) if hi > lo else None


def _pair_jobs(tracks: list[Track], footprint: Footprint,
               vehicle: VehicleConfig) -> list[_PairJob]:
    jobs = []
    overlapping: set[str] = set()
    for ta, tb in itertools.combinations(tracks, 2):
        span = _overlap(ta.state, tb.state)
        if span is None:
            continue
        overlapping.update((ta.name, tb.name))
        sel = np.flatnonzero((ta.state.t >= span[0]) & (ta.state.t <= span[1]))
        if len(sel) == 0:
            continue
        sa = ta.state.take(sel)
        jobs.append(_PairJob(ta.name, tb.name, footprint, sa, tb.state.at(sa.t_ns), vehicle))
    if len(tracks) > 1:
        alone = [t.name for t in tracks if t.name not in overlapping]
        if alone:
            t = next(tr for tr in tracks if tr.name == alone[0])
            raise CollisionCheckError(
                f"{alone[0]}: its trajectory ({t.state.t[0]:.3f}-{t.state.t[-1]:.3f} s) does "
                "not overlap in time with any other vehicle's")
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
    """Every vehicle against the map and every overlapping pair; the checks in job order
    (vehicles, then pairs). `use_dask` None: Dask from `DASK_MIN_VEHICLES` vehicles or
    when a scheduler is given."""
    names = [t.name for t in tracks]
    if len(set(names)) != len(names):
        raise CollisionCheckError(f"vehicle names must differ, got {', '.join(names)}")
    footprint = Footprint.from_config(vehicle)
    map_jobs = [_MapJob(t.name, footprint, t.state, obstacles.names, obstacles.geoms, vehicle)
                for t in tracks]
    pair_jobs = _pair_jobs(tracks, footprint, vehicle)
    if use_dask is None:
        use_dask = scheduler is not None or len(tracks) >= DASK_MIN_VEHICLES
    if not use_dask:
        return ([run_map_job(j) for j in map_jobs] + [run_pair_job(j) for j in pair_jobs])

    from uwbfuse.fleet import Job, run_jobs

    jobs = ([Job(f"map-{j.name}", run_map_job, j) for j in map_jobs]
            + [Job(f"pair-{j.a}-{j.b}", run_pair_job, j) for j in pair_jobs])
    results: dict[str, Check] = {}

    def on_result(job: Job, value: Any, error: BaseException | None) -> None:
        if error is not None:
            raise CollisionCheckError(f"collision check {job.name} did not complete: {error}")
        results[job.name] = value

    run_jobs(jobs, on_result, scheduler=scheduler, workers=workers)
    return [results[j.name] for j in jobs]
