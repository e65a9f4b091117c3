# SPDX-License-Identifier: BSD-3-Clause
"""Fleet scenarios: several AGVs on one site and one clock, one log each with its own truth.

`warehouse-fleet` (the Qiu warehouse, 40 m x 20 m, shelves and corner anchors as in
`warehouse`): four AGVs on counter-clockwise loops whose lanes cross and share aisles.

| AGV  | loop x, y (m)   | m/s  | encounters                                                |
|------|-----------------|------|-----------------------------------------------------------|
| agv0 | 6-34, 2.5-7.25  | 0.50 | meets agv1 head-on in the middle aisle, 0.5 m apart; P2  |
| agv1 | 6-34, 7.75-12.5 | 0.55 | meets agv3 head-on on y 12-12.5, 0.5 m apart; P3         |
| agv2 | 19-37, 1-18.5   | 0.50 | crosses all lanes at x = 19; drives through pallet P0    |
| agv3 | 3-19.9, 12-17.5 | 0.45 | 0.3 m beside P1; P4; passes agv2 in the cross aisle 0.3 m |

Pallets are mapped obstacles too low to block UWB (0.8 m squares): P0, P2, P3 and P4 stand
in a lane (a contact every lap), P1 beside one. The AGVs do not avoid
anything (the simulator has no planner): a conflict in the truth is a true conflict. Each
AGV stands still for 2 s plus a seed-dependent 0-20 s before it starts, so the seeds give
different encounters; the speeds differ so the encounters drift from lap to lap.

`uwbfuse simulate OUT.mcap --scenario warehouse-fleet` writes `OUT.agv0.mcap` ... (one log
per AGV, the same stamp clock, each with its ground truth and the map's `map_obstacles`
metadata) and `OUT.fleet.toml` (the `[map]` for `uwbfuse collisions` on TUM files).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from uwbfuse.errors import LogWriteError, SimulationError
from uwbfuse.sim.nlos import Box
from uwbfuse.sim.scenarios import WAREHOUSE, Scenario, _rect_loop
from uwbfuse.sim.simulator import SimResult, simulate_with_truth

START_JITTER_S = 20.0
"""s: the seed-dependent extra standstill of each AGV is uniform in [0, this)."""


@dataclass(frozen=True)
class FleetScenario:
    """Named AGV scenarios (same site, anchors and map; own route, start and speed)."""

    name: str
    description: str
    vehicles: tuple[tuple[str, Scenario], ...]


PALLETS = (
    Box(27.0, 0.6, 27.8, 1.4),  # P0: in agv2's lane y = 1.0
    Box(12.0, 18.1, 12.8, 18.9),  # P1: 0.3 m beside agv3's lane y = 17.5
    Box(11.6, 2.1, 12.4, 2.9),  # P2: in agv0's lane y = 2.5
    Box(28.6, 12.1, 29.4, 12.9),  # P3: in agv1's lane y = 12.5
    Box(2.6, 14.6, 3.4, 15.4),  # P4: in agv3's lane x = 3
)


def _agv(x0: float, y0: float, x1: float, y1: float, speed: float,
         station: float) -> Scenario:
    route, start = _rect_loop(x0, y0, x1, y1, l90=3.0, station=station, dwell=3.0)
    return replace(WAREHOUSE, route=route, start=start, speed=speed, map_boxes=PALLETS)


WAREHOUSE_FLEET = FleetScenario(
    name="warehouse-fleet",
    description="four AGVs in the Qiu warehouse on crossing loops: head-on and crossing "
    "conflicts, side-by-side passes, a pallet in one route and one beside another",
    vehicles=(
        ("agv0", _agv(6.0, 2.5, 34.0, 7.25, 0.50, station=3.0)),
        ("agv1", _agv(6.0, 7.75, 34.0, 12.5, 0.55, station=6.0)),
        ("agv2", _agv(19.0, 1.0, 37.0, 18.5, 0.50, station=3.0)),
        ("agv3", _agv(3.0, 12.0, 19.9, 17.5, 0.45, station=3.0)),
    ),
)

FLEETS: dict[str, FleetScenario] = {f.name: f for f in (WAREHOUSE_FLEET,)}


def get_fleet(name: str) -> FleetScenario | None:
    """The fleet scenario `name`, or None when it names a single-vehicle scenario."""
    return FLEETS.get(name)


def simulate_fleet(
    fleet: str | FleetScenario, duration_s: float = 120.0, seed: int = 0,
    n_vehicles: int | None = None,
) -> list[tuple[str, SimResult]]:
    """(name, SimResult) per AGV, all on the same stamp clock; deterministic in `seed`
    (each AGV its own child seed). `n_vehicles` keeps the first n AGVs."""
    fl = FLEETS.get(fleet) if isinstance(fleet, str) else fleet
    if fl is None:
        raise SimulationError(f"unknown fleet scenario {fleet!r}; known: {', '.join(FLEETS)}")
    vehicles = fl.vehicles[:n_vehicles] if n_vehicles else fl.vehicles
    seq = np.random.SeedSequence(seed)
    jitter_rng = np.random.default_rng(seq.spawn(1)[0])
    delays = jitter_rng.uniform(0.0, START_JITTER_S, size=len(vehicles))
    out = []
    for (name, sc), delay, child in zip(vehicles, delays, seq.spawn(len(vehicles)),
                                        strict=True):
        sub_seed = int(child.generate_state(1)[0])
        res = simulate_with_truth(sc, duration_s, sub_seed,
                                  still_start_s=sc.still_start_s + float(delay))
        out.append((name, res))
    return out


def fleet_paths(out: str | Path, names: list[str]) -> list[Path]:
    """`OUT.mcap` -> `OUT.<name>.mcap` per vehicle (the same folder)."""
    p = Path(out)
    stem = p.name.removesuffix(".mcap")
    return [p.with_name(f"{stem}.{n}.mcap") for n in names]


def write_fleet(out: str | Path, fleet: str, duration_s: float, seed: int
                ) -> tuple[list[tuple[str, SimResult]], list[Path]]:
    """Simulate `fleet` and write one contract log per AGV (`fleet_paths`) and
    `OUT.fleet.toml` (its `[map]`); returns the simulations and the files written."""
    from uwbfuse.config import Config, dump_config
    from uwbfuse.io.atomic import write_atomic
    from uwbfuse.io.writer import write_contract_log

    sims = simulate_fleet(fleet, duration_s, seed)
    paths = fleet_paths(out, [n for n, _ in sims])
    for (_, res), path in zip(sims, paths, strict=True):
        write_contract_log(path, res.log)
    toml = Path(out).with_name(Path(out).name.removesuffix(".mcap") + ".fleet.toml")
    site = sims[0][1].log.map
    cfg = Config(map=site) if site is not None else Config()
    text = dump_config(cfg)
    map_only = text[text.index("[map]"):text.index("[vehicle]")]
    write_atomic(toml, f"# {fleet}: the site map for uwbfuse collisions (m, map frame)\n\n"
                 + map_only, error=LogWriteError, what="fleet config")
    return sims, [*paths, toml]
