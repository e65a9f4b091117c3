# SPDX-License-Identifier: BSD-3-Clause
"""`uwbfuse collisions` as a library function: read the tracks, check, write the events.

`collisions` reads as its steps: load the config, read every input (a TUM trajectory, or a
log estimated with `method` first), take the map (the config's `[map]`, else a log's
`map_obstacles` metadata), turn each trajectory into its motion state, check every vehicle
against the map and every pair, write `events.csv`, `events.md` and `collisions.png`.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from uwbfuse.config import Config, MapConfig, load_config
from uwbfuse.errors import CollisionCheckError
from uwbfuse.safety.classify import Check
from uwbfuse.safety.events import (
    EVENT_COLUMNS,
    SUMMARY_COLUMNS,
    event_rows,
    events_markdown,
    summary_rows,
)
from uwbfuse.safety.fleet import Track, check_fleet
from uwbfuse.safety.geometry import ObstacleMap
from uwbfuse.safety.motion import motion_from_poses
from uwbfuse.streams import PoseStream

log = logging.getLogger(__name__)

COV_MATCH_NS = 1_000_000
"""ns: a covariance row belongs to the pose whose stamp is within 1 ms of its t."""


@dataclass
class CollisionsResult:
    """What `collisions` found and wrote."""

    tracks: list[Track]
    checks: list[Check]
    events: list[dict[str, Any]]
    summary: list[dict[str, Any]]
    map_source: str
    files: list[Path]
    wall_s: float

    def table(self) -> str:
        from uwbfuse.fleet import table_markdown

        return table_markdown(SUMMARY_COLUMNS, self.summary)


def is_log(path: str | Path) -> bool:
    """An MCAP file or a rosbag2 directory (anything else is read as a TUM trajectory)."""
    p = Path(path)
    return p.is_dir() or p.suffix.lower() == ".mcap"


def default_name(path: str | Path) -> str:
    """The file stem: `agv0.isam2.tum` -> `agv0.isam2`, `fleet.agv0.mcap` -> `fleet.agv0`."""
    p = Path(str(path).rstrip("/"))
    return p.name.removesuffix(".tum").removesuffix(".mcap").removesuffix(".txt")


def read_covariance_csv(path: str | Path, poses: PoseStream) -> PoseStream:
    """`poses` with the covariance of a `--cov-out` CSV (t, 36 entries, one header line)."""
    p = Path(path)
    try:
        data = np.loadtxt(p, delimiter=",", skiprows=1, ndmin=2)
    except (OSError, ValueError) as e:
        raise CollisionCheckError(f"{p}: cannot read covariance CSV: {e}") from None
    if data.shape[1] != 37:
        raise CollisionCheckError(
            f"{p}: expected 37 columns (t and a row-major 6x6 covariance), got {data.shape[1]}")
    t_ns = np.round(data[:, 0] * 1e9).astype(np.int64)
    idx = np.clip(np.searchsorted(t_ns, poses.t_ns), 0, len(t_ns) - 1)
    prev = np.clip(idx - 1, 0, len(t_ns) - 1)
    best = np.where(np.abs(t_ns[prev] - poses.t_ns) < np.abs(t_ns[idx] - poses.t_ns), prev, idx)
    if np.any(np.abs(t_ns[best] - poses.t_ns) > COV_MATCH_NS):
        raise CollisionCheckError(f"{p}: its stamps do not match the trajectory's poses")
    cov = data[best, 1:].reshape(-1, 6, 6)
    return PoseStream(poses.t_ns, poses.position, poses.quat_xyzw, poses.has_orientation, cov)


def _read_input(path: str, method: str | None, config: Config
                ) -> tuple[PoseStream, MapConfig | None]:
    if not is_log(path):
        from uwbfuse.io.tum import read_tum

        return read_tum(path), None
    if method is None:
        raise CollisionCheckError(
            f"{path}: a log needs --method M to estimate its trajectory first")
    from uwbfuse.estimator import Method
    from uwbfuse.io.reader import read_log
    from uwbfuse.pipeline import estimate

    sensor_log = read_log(path, config)
    return estimate(sensor_log, Method(method), config).trajectory, sensor_log.map


def _names(paths: Sequence[str], names: Sequence[str] | None) -> list[str]:
    if names is None:
        out = [default_name(p) for p in paths]
    elif len(names) != len(paths):
        raise CollisionCheckError(
            f"--names gives {len(names)} names for {len(paths)} trajectories")
    else:
        out = list(names)
    dup = sorted({n for n in out if out.count(n) > 1})
    if dup:
        raise CollisionCheckError(
            f"two trajectories are both named {dup[0]!r}; give --names A,B,...")
    return out


def collisions(
    paths: Sequence[str],
    config_path: str | Path | None = None,
    *,
    names: Sequence[str] | None = None,
    out_dir: str | Path = "collisions_out",
    method: str | None = None,
    cov_paths: Sequence[str] | None = None,
    scheduler: str | None = None,
    workers: int | None = None,
    use_dask: bool | None = None,
) -> CollisionsResult:
    """Check the trajectories in `paths` (TUM files, or logs estimated with `method`) for
    predicted collisions with the map and among each other; write the events under
    `out_dir`. `cov_paths`: one `--cov-out` CSV per trajectory ("" for none)."""
    tic = time.perf_counter()
    if not paths:
        raise CollisionCheckError("no trajectories given")
    config = load_config(config_path)
    vehicle_names = _names(paths, names)
    if cov_paths is not None and len(cov_paths) != len(paths):
        raise CollisionCheckError(
            f"--cov gives {len(cov_paths)} files for {len(paths)} trajectories")
    site: MapConfig | None = None
    map_source = "none"
    if config.map.obstacles or config.map.walls or config.map.boundary:
        site, map_source = config.map, f"[map] of {config_path}"
    tracks = []
    for k, (path, name) in enumerate(zip(paths, vehicle_names, strict=True)):
        poses, log_map = _read_input(path, method, config)
        if cov_paths is not None and cov_paths[k]:
            poses = read_covariance_csv(cov_paths[k], poses)
        if site is None and log_map is not None:
            site, map_source = log_map, f"map_obstacles metadata of {path}"
        state = motion_from_poses(poses, config.vehicle.velocity_window,
                                  config.vehicle.position_sigma, name=path)
        tracks.append(Track(name, state))
    if site is None:
        log.warning("no map ([map] in the config or map_obstacles in a log): only the "
                    "vehicles are checked against each other")
    obstacles = ObstacleMap.from_config(site or MapConfig())
    checks = check_fleet(tracks, obstacles, config.vehicle, use_dask=use_dask,
                         scheduler=scheduler, workers=workers)
    events = event_rows(checks)
    summary = summary_rows(checks)

    from uwbfuse.fleet import table_csv, write_atomic
    from uwbfuse.safety.plot import plot_events

    out = Path(out_dir)
    files = [out / "events.csv", out / "events.md"]
    write_atomic(files[0], table_csv(EVENT_COLUMNS, events))
    write_atomic(files[1], events_markdown(summary, events))
    files.append(plot_events(out / "collisions.png", tracks, obstacles, checks))
    return CollisionsResult(tracks, checks, events, summary, map_source, files,
                            time.perf_counter() - tic)
