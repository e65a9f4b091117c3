# SPDX-License-Identifier: BSD-3-Clause
"""The simulated fleet end to end: logs with their map, the check, the truth scores."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from mcap.writer import Writer

from uwbfuse.cli import main
from uwbfuse.config import Config, VehicleConfig
from uwbfuse.errors import LogReadError
from uwbfuse.io.reader import read_log
from uwbfuse.safety.classify import Check, Kind
from uwbfuse.safety.command import collisions
from uwbfuse.safety.evaluate import TruthClearance, score_check, score_fleet, truth_clearances
from uwbfuse.safety.fleet import Track, check_fleet
from uwbfuse.safety.geometry import ObstacleMap
from uwbfuse.safety.motion import motion_from_poses
from uwbfuse.sim.fleet import simulate_fleet
from uwbfuse.streams import NS_PER_S, PoseStream

SEED, DURATION = 1, 32.0  # agv0 meets pallet P2 at ~22 s, agv2 pallet P0 at ~26 s


@pytest.fixture(scope="module")
def fleet_logs(tmp_path_factory: pytest.TempPathFactory) -> list[Path]:
    out = tmp_path_factory.mktemp("fleet") / "f.mcap"
    assert main(["simulate", str(out), "--scenario", "warehouse-fleet",
                 "--duration", str(DURATION), "--seed", str(SEED)]) == 0
    return sorted(out.parent.glob("f.agv*.mcap"))


def test_simulate_writes_one_log_per_agv_with_map(fleet_logs: list[Path]) -> None:
    """test that the fleet scenario writes one log per AGV on one clock, each with its
    ground truth and the map's map_obstacles record (shelves and pallets)"""
    assert [p.name for p in fleet_logs] == [f"f.agv{k}.mcap" for k in range(4)]
    logs = [read_log(p, Config()) for p in fleet_logs]
    assert len({lg.imu.t_ns[0] for lg in logs}) == 1
    assert all(lg.ground_truth is not None and lg.map is not None for lg in logs)
    assert len(logs[0].map.obstacles) == 6 + 5
    toml = fleet_logs[0].parent / "f.fleet.toml"
    assert "[map]" in toml.read_text()
    # a config [map] takes precedence over the metadata
    cfg = Config.model_validate({"map": {"obstacles": [[[0, 0], [1, 0], [1, 1]]]}})
    assert len(read_log(fleet_logs[0], cfg).map.obstacles) == 1


def test_bad_map_metadata_is_a_read_error(tmp_path: Path) -> None:
    """test that a map_obstacles record that is not polygons is a one-line read error"""
    p = tmp_path / "bad.mcap"
    with p.open("wb") as f:
        w = Writer(f)
        w.start()
        sid = w.register_schema("s", "jsonschema", b"{}")
        cid = w.register_channel("/uwb/range", "json", sid)
        w.add_message(cid, log_time=1, publish_time=1,
                      data=json.dumps({"anchor_id": "A", "range": 1.0}).encode())
        w.add_metadata("map_obstacles", {"o1": "[[0, 0], [1, 1]]"})
        w.finish()
    with pytest.raises(LogReadError, match=r"map_obstacles.*not a closed polygon"):
        read_log(p, Config())


@pytest.mark.slow
def test_collisions_on_logs_takes_the_map_from_metadata(fleet_logs: list[Path],
                                                       tmp_path: Path) -> None:
    """test that `collisions LOG... --method odom` estimates first, takes the map from the
    logs and writes the events (two of the AGVs: ~5 s per log on a loaded machine)"""
    logs = [str(fleet_logs[0]), str(fleet_logs[2])]
    res = collisions(logs, out_dir=tmp_path / "c", method="odom")
    assert "map_obstacles metadata" in res.map_source
    assert [t.name for t in res.tracks] == ["f.agv0", "f.agv2"]
    assert len(res.checks) == 2 + 1
    assert (tmp_path / "c" / "events.csv").exists()


def test_truth_tracks_detect_every_true_conflict() -> None:
    """test that the predictor on the ground truth (10 Hz) detects the simulated contacts
    with at least the control delay of lead time and no false alarm"""
    fleet = simulate_fleet("warehouse-fleet", DURATION, SEED)
    site = ObstacleMap.from_config(fleet[0][1].log.map)
    vehicle = VehicleConfig()
    truth = {n: r.log.ground_truth for n, r in fleet}
    clear = truth_clearances(truth, site, vehicle)
    tracks = []
    for n, g in truth.items():
        sl = slice(None, None, 20)
        poses = PoseStream(g.t_ns[sl], g.position[sl], g.quat_xyzw[sl], True)
        tracks.append(Track(n, motion_from_poses(poses, vehicle.velocity_window)))
    score = score_fleet(check_fleet(tracks, site, vehicle, use_dask=False), clear, vehicle)
    assert score.conflicts >= 2
    assert score.detection_rate == 1.0
    assert score.lead_s.min() >= vehicle.control_delay
    assert score.false_alarms == 0


def test_score_check_counts_detection_lead_and_false_alarm() -> None:
    """test the scoring on a hand-made clearance: one contact at 10 s, alarms from 9.2 s
    (lead 0.8 s) and one stray alarm at 3 s where the truth is clear"""
    vehicle = VehicleConfig(control_delay=0.5, safety_margin=0.2)
    grid = np.arange(0, 20 * 50) * (NS_PER_S // 50)
    t_grid = grid / NS_PER_S
    clearance = np.clip(np.abs(t_grid - 10.5) - 0.5, 0.0, None)  # contact 10.0 .. 11.0 s
    tc = TruthClearance("a", "map", grid, clearance)
    t_ns = np.arange(0, 190) * (NS_PER_S // 10)
    kind = np.zeros(len(t_ns), dtype=np.int8)
    kind[92:105] = Kind.WARNING
    kind[95:105] = Kind.COLLISION
    kind[30] = Kind.WARNING
    n = len(t_ns)
    check = Check("a", "map", t_ns, t_ns / NS_PER_S, kind, np.zeros(n), np.full(n, np.nan),
                  np.full(n, 0.2))
    s = score_check(check, tc, vehicle)
    assert (s.conflicts, s.detected, s.false_alarms) == (1, 1, 1)
    np.testing.assert_allclose(s.lead_s, [0.8], atol=1e-9)
    # near: true clearance below 1 m, 9.0 .. 12.0 s (open) at 10 Hz
    assert s.near_epochs == 29
