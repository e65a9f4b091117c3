# SPDX-License-Identifier: BSD-3-Clause
"""Tests of the simulator: determinism, kinematic consistency, sensor error statistics."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest

from uwbfuse.errors import SimulationError
from uwbfuse.sim import SCENARIOS, simulate, simulate_with_truth
from uwbfuse.sim.fleet import FLEETS
from uwbfuse.sim.nlos import Box, nlos_excess, segments_blocked, unit_ar1
from uwbfuse.sim.scenarios import QIU_STATIC_POINTS
from uwbfuse.sim.trajectory import Straight, Turn, route_polyline
from uwbfuse.streams import NS_PER_S

ALL = sorted(SCENARIOS)


def _integrate_imu(gyro: np.ndarray, accel: np.ndarray, dt: float, yaw0: float,
                   v0: np.ndarray, p0: np.ndarray, g: float) -> tuple[np.ndarray, np.ndarray]:
    """Planar strapdown (trapezoid) of IMU-frame gyro/specific force; returns yaw, xy."""
    yaw = yaw0 + np.concatenate([[0.0], np.cumsum(0.5 * (gyro[1:, 2] + gyro[:-1, 2]) * dt)])
    c, s = np.cos(yaw), np.sin(yaw)
    aw = np.column_stack([c * accel[:, 0] - s * accel[:, 1], s * accel[:, 0] + c * accel[:, 1]])
    assert np.allclose(accel[:, 2], g)
    v = v0 + np.vstack([[0.0, 0.0], np.cumsum(0.5 * (aw[1:] + aw[:-1]) * dt, axis=0)])
    p = p0 + np.vstack([[0.0, 0.0], np.cumsum(0.5 * (v[1:] + v[:-1]) * dt, axis=0)])
    return yaw, p


def test_unknown_scenario_names_the_known_ones() -> None:
    """test that an unknown scenario raises SimulationError listing the known scenarios"""
    with pytest.raises(SimulationError, match="warehouse") as e:
        simulate("moon-base", duration_s=1.0)
    assert all(name in str(e.value) for name in ("room", "factory", "warehouse-nlos"))


def test_unknown_override_and_bad_duration() -> None:
    """test that a misspelt override and a non-positive duration are SimulationErrors"""
    with pytest.raises(SimulationError, match="spead"):
        simulate("room", duration_s=1.0, spead=0.2)
    with pytest.raises(SimulationError):
        simulate("room", duration_s=0.0)


def test_required_scenarios_exist() -> None:
    """test that the contract's scenarios and the heavy-NLOS/static variants are registered"""
    assert {"room", "warehouse", "factory", "warehouse-nlos", "room-static"} <= set(SCENARIOS)


def test_deterministic_by_seed() -> None:
    """test that one seed gives identical logs and another seed different noise"""
    a = simulate("warehouse", duration_s=20.0, seed=5)
    b = simulate("warehouse", duration_s=20.0, seed=5)
    c = simulate("warehouse", duration_s=20.0, seed=6)
    for s1, s2 in ((a.imu, b.imu), (a.wheel, b.wheel), (a.ranges, b.ranges)):
        for f in ("t_ns",):
            np.testing.assert_array_equal(getattr(s1, f), getattr(s2, f))
    np.testing.assert_array_equal(a.imu.accel, b.imu.accel)
    np.testing.assert_array_equal(a.wheel.v, b.wheel.v)
    np.testing.assert_array_equal(a.ranges.range, b.ranges.range)
    np.testing.assert_array_equal(a.ground_truth.position, c.ground_truth.position)
    assert not np.array_equal(a.imu.accel, c.imu.accel)
    assert not np.array_equal(a.ranges.range[:50], c.ranges.range[:50])


@pytest.mark.parametrize("name", ALL)
def test_log_structure(name: str) -> None:
    """test that every stream is filled, sorted, at its rate and on a non-zero stamp clock"""
    r = simulate_with_truth(name, duration_s=10.0, seed=1)
    lg, sc = r.log, r.scenario
    assert lg.imu is not None and lg.wheel is not None and lg.ranges is not None
    assert lg.anchors is not None and lg.ground_truth is not None
    for s in (lg.imu, lg.wheel, lg.ranges, lg.ground_truth):
        assert s.t_ns.dtype == np.int64 and np.all(np.diff(s.t_ns) > 0) and s.t_ns[0] > 0
    assert len(lg.imu) == 10 * 200 + 1 and len(lg.wheel) == 10 * 50
    np.testing.assert_array_equal(lg.ground_truth.t_ns, lg.imu.t_ns)
    assert lg.ranges.anchor.dtype == np.int32
    assert set(np.unique(lg.ranges.anchor)) == set(range(len(sc.anchors)))
    assert 0.85 * 400 < len(lg.ranges) <= 400
    np.testing.assert_allclose(np.linalg.norm(lg.ground_truth.quat_xyzw, axis=1), 1.0)


@pytest.mark.parametrize("name", ["warehouse", "room-static", "factory"])
def test_noiseless_imu_reproduces_truth(name: str) -> None:
    """test that strapdown integration of the noiseless IMU follows the true trajectory"""
    r = simulate_with_truth(name, duration_s=60.0, seed=0, still_start_s=0.0)
    gt = r.log.ground_truth
    yaw, p = _integrate_imu(r.imu_gyro, r.imu_accel, 1.0 / 200.0, r.yaw[0], r.velocity[0, :2],
                            gt.position[0, :2], r.scenario.gravity)
    assert np.abs(yaw - r.yaw).max() < 1e-6
    assert np.linalg.norm(p - gt.position[:, :2], axis=1).max() < 1e-3
    path_len = np.linalg.norm(np.diff(gt.position[:, :2], axis=0), axis=1).sum()
    assert path_len > 3.0


def test_noisy_imu_is_noisy_but_close() -> None:
    """test that measured minus noiseless IMU is bias plus white noise of the stated density"""
    r = simulate_with_truth("warehouse", duration_s=60.0, seed=2)
    sc = r.scenario
    res_a = r.log.imu.accel - r.imu_accel - r.accel_bias
    res_g = r.log.imu.gyro - r.imu_gyro - r.gyro_bias
    np.testing.assert_allclose(res_a.std(axis=0), sc.accel_noise_density * np.sqrt(200), rtol=0.05)
    np.testing.assert_allclose(res_g.std(axis=0), sc.gyro_noise_density * np.sqrt(200), rtol=0.05)
    assert np.abs(r.accel_bias).max() < 6 * sc.accel_bias_sigma
    assert np.abs(r.gyro_bias).max() < 6 * sc.gyro_bias_sigma


@pytest.mark.parametrize("name", ALL)
def test_gravity_sign_at_standstill(name: str) -> None:
    """test that the still IMU reads about +9.81 m/s^2 on z and no rotation"""
    r = simulate_with_truth(name, duration_s=5.0, seed=3)
    assert r.standstill_ns is not None
    t = r.log.imu.t_ns
    still = (t >= r.standstill_ns[0]) & (t < r.standstill_ns[1])
    assert still.sum() >= 200 * 1.5
    assert np.abs(r.imu_accel[still] - [0.0, 0.0, 9.81]).max() < 1e-12
    assert abs(r.log.imu.accel[still, 2].mean() - 9.81) < 0.25
    assert np.abs(r.log.imu.accel[still, :2].mean(axis=0)).max() < 0.25
    assert np.abs(r.log.imu.gyro[still].mean(axis=0)).max() < 0.03
    assert not r.moving[still].any()
    assert np.all(r.log.wheel.v[r.log.wheel.t_ns <= r.standstill_ns[1]] == 0.0)


def test_still_start_zero_starts_moving() -> None:
    """test that still_start_s=0 gives a log that begins at cruise speed"""
    r = simulate_with_truth("warehouse", duration_s=5.0, seed=0, still_start_s=0.0)
    assert r.standstill_ns is None
    assert np.linalg.norm(r.velocity[0]) == pytest.approx(r.scenario.speed)
    assert r.log.wheel.v[0] > 0.4


@pytest.mark.parametrize("name", ["warehouse", "room-static"])
def test_wheel_mean_velocity_convention(name: str) -> None:
    """test that each wheel sample is the mean velocity over the interval ending at its stamp"""
    r = simulate_with_truth(name, duration_s=120.0, seed=4)
    gt, wh = r.log.ground_truth, r.log.wheel
    dt = 1.0 / r.scenario.wheel_rate
    # yaw: the interval means integrate exactly to the truth
    yaw_w = r.yaw[0] + np.cumsum(r.wheel_omega_true * dt)
    i_gt = np.searchsorted(gt.t_ns, wh.t_ns)
    assert np.all(gt.t_ns[i_gt] == wh.t_ns)
    assert np.abs(yaw_w - r.yaw[i_gt]).max() < 1e-9
    # position: unicycle with the mid-interval heading
    yaw_mid = np.concatenate([[r.yaw[0]], yaw_w[:-1]]) + 0.5 * r.wheel_omega_true * dt
    step = r.wheel_v_true[:, None] * dt * np.column_stack([np.cos(yaw_mid), np.sin(yaw_mid)])
    p = gt.position[0, :2] + np.cumsum(step, axis=0)
    assert np.linalg.norm(p - gt.position[i_gt, :2], axis=1).max() < 2e-3
    # the reported values follow the truth up to scale, noise and slip
    ok = ~r.wheel_slip
    err = wh.v[ok] - r.wheel_scale[0] * r.wheel_v_true[ok]
    assert np.abs(err).max() < 6 * r.scenario.wheel_sigma_v
    still = (r.wheel_v_true == 0.0) & (r.wheel_omega_true == 0.0)
    assert still.any() and np.all(wh.v[still] == 0.0) and np.all(wh.omega[still] == 0.0)


def test_wheel_slip_episodes() -> None:
    """test that slip episodes exist on a long run and inflate the wheel speed"""
    r = simulate_with_truth("warehouse", duration_s=600.0, seed=1)
    assert 0 < r.wheel_slip.mean() < 0.1
    gain = r.log.wheel.v[r.wheel_slip] / (r.wheel_scale[0] * r.wheel_v_true[r.wheel_slip])
    assert np.median(gain) > 1.04


def test_los_range_statistics() -> None:
    """test that LOS residuals have zero mean and the configured sigma"""
    r = simulate_with_truth("warehouse", duration_s=600.0, seed=7)
    res = r.log.ranges.range - r.true_range
    los = ~r.nlos & ~r.outlier
    assert los.sum() > 5000
    assert abs(res[los].mean()) < 0.004
    assert res[los].std() == pytest.approx(r.scenario.los_sigma, rel=0.05)
    assert np.all(r.nlos_excess[~r.nlos] == 0.0)
    # outliers: about the configured rate, 1-4 m
    assert r.outlier.mean() == pytest.approx(r.scenario.outlier_prob, abs=0.004)
    assert np.all(np.abs(res[r.outlier]) > 0.7)


def test_warehouse_nlos_statistics() -> None:
    """test that about two thirds of warehouse-nlos ranges are NLOS, excess mean 0.3, std 0.15"""
    r = simulate_with_truth("warehouse-nlos", duration_s=900.0, seed=1)
    assert 0.6 < r.nlos_fraction < 0.8
    ex = r.nlos_excess[r.nlos]
    assert ex.mean() == pytest.approx(0.3, abs=0.05)
    assert ex.std() == pytest.approx(0.15, abs=0.05)
    res = r.log.ranges.range - r.true_range
    assert r.outlier.mean() == pytest.approx(0.02, abs=0.005)
    assert np.median(res[r.nlos & ~r.outlier]) > 0.2
    # NLOS comes in episodes lasting seconds, per anchor
    a = r.log.ranges.anchor
    runs = [np.diff(np.flatnonzero(np.diff(np.r_[0, r.nlos[a == j], 0]))) for j in range(4)]
    longest = max(int(x[::2].max()) for x in runs if len(x))
    assert longest / 10.0 > 10.0  # ~10 Hz per anchor: longer than 10 s


def test_lognormal_nlos_excess_is_never_negative_with_the_configured_moments() -> None:
    """test that the log-normal NLOS excess is positive with the configured mean and std, its
    slow share correlated over the correlation time and its white part not; the Gaussian
    law (the default) has the same moments and reads short where the log-normal cannot"""
    rng = np.random.default_rng(3)
    n, dt, tau = 200_000, 0.1, 5.0
    x_slow, x_white = unit_ar1(rng, n, dt, tau), rng.standard_normal(n)
    ex = nlos_excess(x_slow, x_white, 0.114, 0.145, 0.7, "lognormal")
    assert np.all(ex > 0.0)
    assert ex.mean() == pytest.approx(0.114, rel=0.05)
    assert ex.std() == pytest.approx(0.145, rel=0.1)
    lag = round(1.0 / dt)  # 1 s apart: the slow part (70 % of the log variance) persists
    lx = np.log(ex)
    assert np.corrcoef(lx[:-lag], lx[lag:])[0, 1] == pytest.approx(
        0.7 * np.exp(-1.0 / tau), abs=0.03)
    white = nlos_excess(x_slow, x_white, 0.114, 0.145, 0.0, "lognormal")
    assert abs(np.corrcoef(white[:-1], white[1:])[0, 1]) < 0.02
    gauss = nlos_excess(x_slow, x_white, 0.114, 0.145, 0.7)
    assert gauss.mean() == pytest.approx(0.114, rel=0.05)
    assert gauss.std() == pytest.approx(0.145, rel=0.1)
    assert 0.15 < np.mean(gauss < 0.0) < 0.30
    with pytest.raises(ValueError, match="lognormal"):
        nlos_excess(x_slow, x_white, 0.114, 0.145, 0.7, "gamma")
    # in a simulated log every NLOS range reads long under the log-normal law; the other
    # streams and the LOS ranges are the Gaussian law's draw for draw
    g = simulate_with_truth("warehouse", duration_s=60.0, seed=2)
    ln = simulate_with_truth("warehouse", duration_s=60.0, seed=2, nlos_excess="lognormal")
    assert np.all(ln.nlos_excess[ln.nlos] > 0.0) and np.any(g.nlos_excess[g.nlos] < 0.0)
    np.testing.assert_array_equal(ln.nlos, g.nlos)
    los = ~g.nlos
    np.testing.assert_array_equal(ln.log.ranges.range[los], g.log.ranges.range[los])
    np.testing.assert_array_equal(ln.log.imu.accel, g.log.imu.accel)
    with pytest.raises(SimulationError, match="nlos_excess"):
        simulate("warehouse", duration_s=10.0, seed=0, nlos_excess="gamma")


def _blocked_bruteforce(p: np.ndarray, q: np.ndarray, boxes: tuple[Box, ...]) -> np.ndarray:
    u = np.linspace(0.0, 1.0, 2001)[None, :, None]
    pts = p[:, None, :] + u * (q - p)[:, None, :]
    out = np.zeros(len(p), dtype=bool)
    for b in boxes:
        inside = ((pts[..., 0] > b.xmin) & (pts[..., 0] < b.xmax)
                  & (pts[..., 1] > b.ymin) & (pts[..., 1] < b.ymax))
        out |= inside.any(axis=1)
    return out


@pytest.mark.parametrize("name", ["warehouse", "room", "factory"])
def test_nlos_only_where_a_shelf_blocks(name: str) -> None:
    """test that a range is NLOS exactly when the tag-anchor segment crosses an obstacle"""
    r = simulate_with_truth(name, duration_s=300.0, seed=2)
    sc, rg = r.scenario, r.log.ranges
    gt = r.log.ground_truth
    tag = np.column_stack([np.interp(rg.t_ns, gt.t_ns, gt.position[:, k]) for k in (0, 1)])
    anc = np.array([p for _, p in sc.anchors])[rg.anchor, :2]
    sel = np.arange(0, len(rg), 3)
    brute = _blocked_bruteforce(tag[sel], anc[sel], sc.boxes)
    agree = brute == r.nlos[sel]
    assert agree.mean() > 0.995  # disagreements only for grazing segments
    assert r.nlos.any() and (~r.nlos).any()


def test_segments_blocked_cases() -> None:
    """test the slab test on crossing, missing, touching, axis-parallel and inside segments"""
    box = (Box(0.0, 0.0, 1.0, 1.0),)
    p = np.array([[-1, 0.5], [-1, 2.0], [-1, 1.0], [0.5, -1], [0.5, 0.5], [2, 2], [-1, -1]])
    q = np.array([[2, 0.5], [2, 2.0], [2, 1.0], [0.5, 3], [3, 3], [3, 3], [2.0, 2.0]])
    got = segments_blocked(p.astype(float), q.astype(float), box)
    np.testing.assert_array_equal(got, [True, False, False, True, True, False, True])


def test_scenario_geometry() -> None:
    """test the anchor layouts of the papers and that routes stay in the hall, off obstacles"""
    room = dict(SCENARIOS["room"].anchors)
    assert sorted(room.values()) == [(0.0, 0.0, 1.5), (0.0, 6.0, 1.5), (5.0, 0.0, 1.5),
                                     (5.0, 6.0, 1.5)]
    wh = dict(SCENARIOS["warehouse"].anchors)
    assert sorted(wh.values()) == [(0.0, 0.0, 1.5), (0.0, 20.0, 1.5), (40.0, 0.0, 1.5),
                                   (40.0, 20.0, 1.5)]
    assert SCENARIOS["warehouse"].size == (40.0, 20.0) and SCENARIOS["room"].size == (5.0, 6.0)
    fac = SCENARIOS["factory"]
    assert fac.size == (10.0, 10.0) and len(fac.anchors) == 3
    assert SCENARIOS["room"].speed == pytest.approx(0.1)
    assert SCENARIOS["warehouse"].speed == pytest.approx(0.5)
    for name, sc in SCENARIOS.items():
        xy = route_polyline(list(sc.route), sc.start)
        assert np.linalg.norm(xy[-1] - xy[0]) < 0.05, name  # closed loop
        margin = 0.25
        assert xy[:, 0].min() >= margin and xy[:, 0].max() <= sc.size[0] - margin, name
        assert xy[:, 1].min() >= margin and xy[:, 1].max() <= sc.size[1] - margin, name
        for b in sc.boxes:
            assert not b.contains(xy, margin=0.4).any(), (name, b)
        for _, a in sc.anchors:
            assert 0 <= a[0] <= sc.size[0] and 0 <= a[1] <= sc.size[1]


def test_room_static_dwells_at_qiu_points() -> None:
    """test that room-static stands still for a while at each static point of Qiu Table 2"""
    r = simulate_with_truth("room-static", duration_s=300.0, seed=0)
    gt = r.log.ground_truth
    for pt in QIU_STATIC_POINTS:
        at = np.linalg.norm(gt.position[:, :2] - np.array(pt), axis=1) < 1e-6
        assert at.sum() / 200.0 > 15.0, pt
        assert not r.moving[at].all() or at.sum() == 0


def test_outage_and_anchor_offsets() -> None:
    """test the outage window, the per-anchor offsets and the tag lever arm overrides"""
    r = simulate_with_truth("room", duration_s=30.0, seed=1, outage=(10.0, 20.0),
                            anchor_offset_max=0.1, tag_in_base=(0.2, 0.0, 0.3))
    rg = r.log.ranges
    t = (rg.t_ns - r.log.imu.t_ns[0]) / NS_PER_S
    assert not np.any((t >= 10.0) & (t < 20.0))
    assert np.any(t < 10.0) and np.any(t >= 20.0)
    assert np.all(np.abs(r.anchor_offset) <= 0.1) and np.abs(r.anchor_offset).max() > 0.01
    los = ~r.nlos & ~r.outlier
    res = rg.range - r.true_range
    for j in range(4):
        sel = los & (rg.anchor == j)
        assert res[sel].mean() == pytest.approx(r.anchor_offset[j], abs=0.015)
    # the lever arm: true range from the tag 0.3 m above the base and 0.2 m ahead
    gt = r.log.ground_truth
    i = np.searchsorted(gt.t_ns, rg.t_ns[0])
    anc = np.array(dict(r.scenario.anchors)[r.log.anchors.ids[rg.anchor[0]]])
    assert abs(r.true_range[0] - np.linalg.norm(anc - gt.position[i] - [0.2 * np.cos(r.yaw[i]),
               0.2 * np.sin(r.yaw[i]), 0.3])) < 0.01


def test_streams_override() -> None:
    """test that `streams` leaves sensors out of the log (a log without wheels)"""
    lg = simulate("factory", duration_s=3.0, streams=("imu", "uwb"))
    assert lg.wheel is None and lg.imu is not None and lg.ranges is not None
    with pytest.raises(SimulationError):
        simulate("factory", duration_s=3.0, streams=("lidar",))


def test_route_close_loop_rejects_impossible() -> None:
    """test that a route that cannot reach cruise speed is rejected"""
    with pytest.raises(SimulationError):
        simulate("room", duration_s=5.0, route=(Straight(0.01), Turn(np.pi, 1.0)))


def test_one_hour_is_fast() -> None:
    """test that an hour of warehouse logging simulates in seconds"""
    t = time.perf_counter()
    lg = simulate("warehouse", duration_s=3600.0, seed=0)
    assert time.perf_counter() - t < 15.0
    assert len(lg.imu) == 3600 * 200 + 1


@pytest.mark.parametrize("name", ALL)
def test_cli_simulate_writes_contract_log(name: str, tmp_path: Path) -> None:
    """test that `uwbfuse simulate` writes an MCAP with all four topics and the anchors"""
    pytest.importorskip("uwbfuse.io.writer")
    from mcap.reader import make_reader

    from uwbfuse.cli import main

    out = tmp_path / f"{name}.mcap"
    assert main(["simulate", str(out), "--scenario", name, "--duration", "3", "--seed", "1"]) == 0
    with out.open("rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None
        topics = {c.topic for c in summary.channels.values()}
        meta = {m.name: m.metadata for m in reader.iter_metadata()}
    assert {"/imu", "/wheel_odom", "/uwb/range", "/ground_truth"} <= topics
    assert set(meta["uwb_anchors"]) == {i for i, _ in SCENARIOS[name].anchors}


def test_cli_simulate_nlos_excess_law(tmp_path: Path, capsys: pytest.CaptureFixture[str]
                                      ) -> None:
    """test that `uwbfuse simulate --nlos-excess lognormal` writes the log-normal log, and
    that a fleet scenario refuses the option in one line (exit 2)"""
    pytest.importorskip("uwbfuse.io.writer")
    from uwbfuse.cli import main
    from uwbfuse.config import Config
    from uwbfuse.io.reader import read_log

    out = tmp_path / "ln.mcap"
    assert main(["simulate", str(out), "--duration", "20", "--seed", "4",
                 "--nlos-excess", "lognormal"]) == 0
    want = simulate_with_truth("warehouse", duration_s=20.0, seed=4, nlos_excess="lognormal")
    np.testing.assert_allclose(read_log(out, Config()).ranges.range, want.log.ranges.range,
                               atol=1e-5)  # float32
    fleet = next(iter(FLEETS))
    assert main(["simulate", str(tmp_path / "f.mcap"), "--scenario", fleet,
                 "--nlos-excess", "lognormal"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "single-vehicle" in err[0]


def test_bundled_sample_matches_simulator() -> None:
    """test that data/warehouse_60s.mcap reads back as simulate('warehouse', 60, seed=1)"""
    reader = pytest.importorskip("uwbfuse.io.reader")
    from uwbfuse.config import Config

    path = Path(__file__).resolve().parents[1] / "data" / "warehouse_60s.mcap"
    assert path.stat().st_size < 3_000_000
    got = reader.read_log(path, Config())
    want = simulate("warehouse", duration_s=60.0, seed=1)
    assert got.anchors is not None and got.anchors.ids == want.anchors.ids
    np.testing.assert_array_equal(got.anchors.positions, want.anchors.positions)
    for name in ("imu", "wheel", "ranges", "ground_truth"):
        np.testing.assert_array_equal(getattr(got, name).t_ns, getattr(want, name).t_ns)
    np.testing.assert_allclose(got.imu.accel, want.imu.accel, atol=1e-9)
    np.testing.assert_allclose(got.imu.gyro, want.imu.gyro, atol=1e-9)
    np.testing.assert_allclose(got.wheel.v, want.wheel.v, atol=1e-9)
    np.testing.assert_array_equal(got.ranges.anchor, want.ranges.anchor)
    np.testing.assert_allclose(got.ranges.range, want.ranges.range, atol=1e-5)  # float32
    np.testing.assert_allclose(got.ground_truth.position, want.ground_truth.position, atol=1e-9)
