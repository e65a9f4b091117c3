# SPDX-License-Identifier: BSD-3-Clause
"""Collision prediction: the paper's Figure 6 cases, geometry, time to contact, pairs."""

from __future__ import annotations

import numpy as np
import pytest
import shapely

from uwbfuse.config import MapConfig, VehicleConfig
from uwbfuse.errors import CollisionCheckError
from uwbfuse.safety.classify import Kind, check_map, check_pair
from uwbfuse.safety.geometry import Footprint, ObstacleMap
from uwbfuse.safety.motion import MotionState, motion_from_poses, position_sigma, predict
from uwbfuse.safety.sweep import sweep
from uwbfuse.streams import NS_PER_S, UNKNOWN_VARIANCE, PoseStream

VEHICLE = VehicleConfig(length=1.0, width=0.6, control_delay=1.0, safety_margin=0.2,
                        prediction_steps=10)
FOOTPRINT = Footprint.from_config(VEHICLE)
# a shelf whose near face is at x = 3.0 m, in front of an AGV driving along +x on y = 0
SHELF = ObstacleMap.from_config(MapConfig(obstacles=[[(3.0, -2.0), (4.0, -2.0), (4.0, 2.0),
                                                      (3.0, 2.0)]]))


def state(x: float, y: float = 0.0, yaw: float = 0.0, vx: float = 1.0, vy: float = 0.0,
          omega: float = 0.0, sigma: float = np.nan) -> MotionState:
    a = lambda v: np.array([v], dtype=np.float64)  # noqa: E731
    return MotionState(np.zeros(1, np.int64), a(0.0), a(x), a(y), a(yaw), a(vx), a(vy),
                       a(omega), a(sigma))


# Figure 6: (a) no collision, (b) about to collide, (c) will collide. Footprint front at
# x + 0.5; after the 1 s delay at 1 m/s it is at x + 1.5; the shelf face is at 3.0 m.
@pytest.mark.parametrize(("x", "kind", "distance", "ttc"), [
    (0.0, Kind.CLEAR, np.inf, np.nan),     # (a): front reaches 1.5 m, 1.5 m short
    (1.35, Kind.WARNING, 0.15, np.nan),    # (b): reaches 2.85 m, 0.15 m < 0.2 m margin
    (2.05, Kind.COLLISION, 0.0, 0.45),     # (c): the face is met after 0.45 m, 0.45 s
])
def test_figure6_cases(x: float, kind: Kind, distance: float, ttc: float) -> None:
    """test that the three situations of the paper's Figure 6 are told apart, with the
    clearance and time to contact of the hand-made footprint"""
    c = check_map("agv", FOOTPRINT, state(x), SHELF, VEHICLE)
    assert c.kind[0] == kind
    np.testing.assert_allclose(c.distance[0], distance, atol=1e-9)
    # time to contact: the start of the first 0.1 s slot that touches (never late)
    if np.isnan(ttc):
        assert np.isnan(c.ttc[0])
    else:
        assert ttc - 0.1 - 1e-9 <= c.ttc[0] <= ttc


def test_paper_quadrilateral_is_one_slot() -> None:
    """test that with one slot the swept area is the paper's quadrilateral of the left and
    right edge points now and after the delay"""
    sw = sweep(FOOTPRINT, state(0.0), 1.0, 1)
    quad = shapely.box(-0.5, -0.3, 1.5, 0.3)  # back edge now .. front edge after 1 m
    assert sw.slots.shape == (1, 1)
    assert shapely.equals(shapely.normalize(sw.slots[0, 0]), shapely.normalize(quad))


def test_widened_margin_turns_clear_into_warning() -> None:
    """test that a known position std widens the margin by sigma_factor sigmas"""
    c = check_map("agv", FOOTPRINT, state(1.0), SHELF, VEHICLE)  # 0.5 m clearance
    assert c.kind[0] == Kind.CLEAR
    c = check_map("agv", FOOTPRINT, state(1.0, sigma=0.2), SHELF, VEHICLE)  # 0.2 + 2 x 0.2
    assert c.kind[0] == Kind.WARNING
    np.testing.assert_allclose(c.margin[0], 0.6)
    np.testing.assert_allclose(c.distance[0], 0.5, atol=1e-9)


def test_turning_prediction_follows_the_arc() -> None:
    """test that constant speed and turn rate move the vehicle on the circle of radius v/w"""
    s = state(0.0, vx=1.0, omega=np.pi / 2)
    _, x, y, yaw = predict(s, 1.0, 4)
    r = 1.0 / (np.pi / 2)
    np.testing.assert_allclose(x[0, -1], r, atol=1e-12)  # a quarter circle to (r, r)
    np.testing.assert_allclose(y[0, -1], r, atol=1e-12)
    np.testing.assert_allclose(yaw[0, -1], np.pi / 2)
    np.testing.assert_allclose(np.hypot(x[0], y[0] - r), r, atol=1e-12)


def test_turn_away_from_shelf_is_clear() -> None:
    """test that a vehicle turning away in time is not flagged as it would be straight"""
    straight = check_map("agv", FOOTPRINT, state(1.6), SHELF, VEHICLE)
    turning = check_map("agv", FOOTPRINT, state(1.6, y=2.6, omega=2.0), SHELF, VEHICLE)
    assert straight.kind[0] == Kind.COLLISION
    assert turning.kind[0] != Kind.COLLISION


def test_pair_head_on_and_crossing_ahead() -> None:
    """test that two vehicles meeting head-on collide at the time their fronts meet, while a
    vehicle crossing the other's path just ahead of it is a near miss, not a collision"""
    a = state(0.0, vx=0.5)
    b = state(2.0, yaw=np.pi, vx=-0.5)  # fronts 1.0 m apart, closing at 1 m/s
    c = check_pair("a", "b", FOOTPRINT, a, b, VEHICLE)
    assert c.kind[0] == Kind.COLLISION
    assert 0.9 - 1e-9 <= c.ttc[0] <= 1.0  # fronts meet at 1.0 s, in the slot from 0.9 s
    # b crosses a's lane ahead of a (1.0 m/s across, its side 0.1 m beyond a's front x
    # range after 0.8 s): b has left a's lane (y > 0.3) at tau = 0.6 s, before a's front
    # reaches b's side (x = 0.9 m) at tau = 0.8 s: no contact, a 0.1 m near miss
    a = state(0.0, vx=0.5)
    b = state(1.2, y=0.2, yaw=np.pi / 2, vx=0.0, vy=1.0)
    c = check_pair("a", "b", FOOTPRINT, a, b, VEHICLE)
    assert c.kind[0] == Kind.WARNING
    assert 0.0 < c.distance[0] < 0.2
    # while the swept areas themselves overlap: only the same time slots are compared
    wa, wb = sweep(FOOTPRINT, a, 1.0, 1), sweep(FOOTPRINT, b, 1.0, 1)
    assert shapely.intersects(wa.slots[0, 0], wb.slots[0, 0])


def _poses(t: np.ndarray, xy: np.ndarray, yaw: np.ndarray | None = None,
           cov: np.ndarray | None = None) -> PoseStream:
    n = len(t)
    q = np.zeros((n, 4))
    q[:, 3] = 1.0
    if yaw is not None:
        q[:, 2], q[:, 3] = np.sin(0.5 * yaw), np.cos(0.5 * yaw)
    pos = np.column_stack([xy, np.zeros(n)])
    return PoseStream((t * NS_PER_S).astype(np.int64), pos, q, yaw is not None, cov)


def test_velocity_from_jittery_track() -> None:
    """test that the causal line fit recovers speed and turn rate from a noisy circle"""
    rng = np.random.default_rng(0)
    t = np.arange(0, 20, 0.1)
    w, r = 0.2, 2.5
    xy = np.column_stack([r * np.sin(w * t), r * (1 - np.cos(w * t))])
    xy += rng.normal(0, 0.01, xy.shape)
    st = motion_from_poses(_poses(t, xy, yaw=w * t), window=1.0)
    np.testing.assert_allclose(np.median(st.speed[20:]), r * w, rtol=0.03)
    np.testing.assert_allclose(np.median(st.omega[20:]), w, rtol=1e-6)
    # position only: the heading is the direction of motion
    st = motion_from_poses(_poses(t, xy), window=1.0)
    np.testing.assert_allclose(np.median(st.omega[20:]), w, rtol=0.05)


def test_position_sigma_from_covariance() -> None:
    """test that the largest xy std is taken and an unknown variance gives the fallback"""
    cov = np.zeros((2, 6, 6))
    cov[0, :2, :2] = [[0.04, 0.0], [0.0, 0.01]]
    cov[1, :2, :2] = UNKNOWN_VARIANCE * np.eye(2)
    np.testing.assert_allclose(position_sigma(cov, 2), [0.2, np.nan])
    np.testing.assert_allclose(position_sigma(cov, 2, assumed=0.1), [0.2, 0.1])
    np.testing.assert_allclose(position_sigma(None, 1), [np.nan])


def test_single_pose_and_bad_footprint() -> None:
    """test that a one-pose trajectory and a non-positive footprint are one-line errors"""
    with pytest.raises(CollisionCheckError, match="at least 2"):
        motion_from_poses(_poses(np.array([0.0]), np.zeros((1, 2))), 0.5, name="x.tum")
    with pytest.raises(CollisionCheckError, match="positive size"):
        Footprint(0.0, 0.5)


def test_walls_and_boundary() -> None:
    """test that a wall (a polyline) and the hall boundary are obstacles: leaving the hall
    is a collision, driving along its wall inside the margin a warning"""
    hall = ObstacleMap.from_config(MapConfig(
        boundary=[(0.0, 0.0), (10.0, 0.0), (10.0, 5.0), (0.0, 5.0)],
        walls=[[(5.0, 1.0), (5.0, 4.0)]]))
    assert hall.names == ("wall0", "boundary")
    inside = check_map("agv", FOOTPRINT, state(2.0, y=2.5, vx=0.0), hall, VEHICLE)
    assert inside.kind[0] == Kind.CLEAR
    along = check_map("agv", FOOTPRINT, state(7.0, y=4.55, vx=0.5), hall, VEHICLE)
    assert along.kind[0] == Kind.WARNING  # 0.15 m from the wall at y = 5
    np.testing.assert_allclose(along.distance[0], 0.15, atol=1e-9)
    out = check_map("agv", FOOTPRINT, state(9.0, y=2.5, vx=1.0), hall, VEHICLE)
    assert out.kind[0] == Kind.COLLISION
    wall = check_map("agv", FOOTPRINT, state(4.0, y=2.5, vx=1.0), hall, VEHICLE)
    assert wall.kind[0] == Kind.COLLISION and wall.ttc[0] <= 0.5


@pytest.mark.slow
def test_dask_path_matches_the_loop() -> None:
    """test that the Dask path gives the loop's checks (one worker, in-process data)"""
    pytest.importorskip("distributed")
    from uwbfuse.safety.fleet import Track, check_fleet

    t = np.arange(0, 20, 0.1)
    tracks = [Track(n, motion_from_poses(_poses(t, np.column_stack([x0 + s * t, 0 * t]),
                                                yaw=np.full_like(t, yaw)), 0.5))
              for n, x0, s, yaw in (("a", 0.0, 0.5, 0.0), ("b", 12.0, -0.5, np.pi),
                                    ("c", 0.0, 0.1, 0.0))]
    loop = check_fleet(tracks, SHELF, VEHICLE, use_dask=False)
    dask = check_fleet(tracks, SHELF, VEHICLE, use_dask=True, workers=1)
    assert [(c.a, c.b) for c in loop] == [(c.a, c.b) for c in dask]
    for lc, dc in zip(loop, dask, strict=True):
        np.testing.assert_array_equal(lc.kind, dc.kind)
        np.testing.assert_array_equal(lc.distance, dc.distance)
    assert any(np.any(c.kind == Kind.COLLISION) for c in loop if c.b == "b")
