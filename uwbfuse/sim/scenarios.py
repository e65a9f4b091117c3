# SPDX-License-Identifier: BSD-3-Clause
"""Simulation scenarios from the seed papers: geometry, route and sensor error figures.

Map frame: x along the first ("northbound") coordinate of Qiu et al. 2022, y along the
second ("easterly") one, z up, so anchor coordinates are exactly those of Qiu's Tables 1 and
4 and the frame stays right-handed. All lengths in metres, times in seconds, angles in
radians.

| name           | x by y m | anchors, z          | route, speed       | LOS / NLOS m      | NLOS |
|----------------|----------|---------------------|--------------------|-------------------|------|
| room           | 5 x 6    | 4, Qiu Table 1, 1.5 | 13 m loop, 0.1 m/s | 0.026 / .114,.145 | 17 % |
| room-static    | 5 x 6    | as room             | Qiu Table 2 points | as room           | 20 % |
| factory        | 10 x 10  | 3 (INS-UWB), 2.5    | 26 m loop, 0.5 m/s | 0.026 / .114,.145 | 30 % |
| warehouse      | 40 x 20  | 4, Qiu Table 4, 1.5 | 165 m serpentine   | 0.05 / .114,.145  | 55 % |
| warehouse-nlos | 40 x 20  | as warehouse        | 80 m racetrack     | 0.05 / 0.3,0.15   | 71 % |
| warehouse-lidar| 40 x 20  | as warehouse        | as warehouse       | as warehouse      | 55 % |

warehouse-lidar adds a LiDAR localiser's poses (`sim.lidar`: 10 Hz, 3 cm, 0.6 deg, none in
two featureless aisle stretches, wrong matches of 0.5-2 m).

(LOS: noise std; NLOS: mean, std of the excess range; NLOS: measured share of ranges.)

Every scenario: IMU 200 Hz (MPU6050 class), wheels 50 Hz, UWB 40 Hz round robin over the
anchors, 2 s standstill at the start, a 3 s stop per lap (room-static: 20 s at each point).
Gross outliers 0.5 % (room, factory), 1 % (warehouse), 2 % (warehouse-nlos) of 1-4 m.
The room's NLOS source is a cabinet (Qiu's room has "NLOS error interference"); the
factory's anchor positions and shelf blocks are our choice (the paper gives none).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace
from typing import Any

from uwbfuse.errors import SimulationError
from uwbfuse.sim.nlos import Box
from uwbfuse.sim.trajectory import Primitive, Spin, Stop, Straight, Turn, close_loop

PI = math.pi
HALF_PI = 0.5 * math.pi

Vec3 = tuple[float, float, float]


@dataclass(frozen=True)
class Scenario:
    """A simulated site, route and sensor set. Every field can be overridden in `simulate`.

    Frames: map frame = anchor frame (z up); base frame REP-103 on the floor (z = base_height);
    the IMU frame is `imu_in_base` (x y z m, qx qy qz qw) in the base frame and the UWB tag
    antenna sits at `tag_in_base` (m). Logs carry no extrinsics, so the defaults are identity
    and zero (what an estimator assumes without a config).
    """

    name: str
    description: str
    size: tuple[float, float]  # hall extent in x and y from the origin, m
    anchors: tuple[tuple[str, Vec3], ...]  # id, position in the map frame, m
    boxes: tuple[Box, ...]  # obstacles blocking line of sight
    route: tuple[Primitive, ...]  # closed loop, driven repeatedly
    start: tuple[float, float, float]  # route start: x m, y m, yaw rad (map frame)
    static_points: tuple[tuple[float, float], ...] = ()  # where the route dwells, m
    map_boxes: tuple[Box, ...] = ()  # mapped obstacles too low to block UWB (pallets)

    # vehicle
    speed: float = 0.5  # cruise speed, m/s
    accel: float = 0.3  # peak forward acceleration, m/s^2
    spin_rate: float = 0.5  # peak yaw rate of turns in place, rad/s
    still_start_s: float = 2.0  # standstill before the first motion, s (0: start moving)
    base_height: float = 0.0  # z of the base frame in the map frame, m
    tag_in_base: Vec3 = (0.0, 0.0, 0.0)
    imu_in_base: tuple[float, float, float, float, float, float, float] = (
        0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0,
    )
    t0_ns: int = 1_700_000_000_000_000_000  # stamp of the first IMU sample, ns
    streams: tuple[str, ...] = ("imu", "wheel", "uwb")  # sensor streams put in the log

    # IMU (MPU6050 class)
    imu_rate: float = 200.0  # Hz
    gravity: float = 9.81  # m/s^2
    accel_noise_density: float = 4.0e-3  # m/s^2/sqrt(Hz)
    gyro_noise_density: float = 3.0e-4  # rad/s/sqrt(Hz)
    accel_bias_sigma: float = 0.05  # std of the constant turn-on bias per axis, m/s^2
    gyro_bias_sigma: float = 0.005  # std of the constant turn-on bias per axis, rad/s
    accel_bias_rw: float = 2.0e-4  # bias random walk, m/s^3/sqrt(Hz)
    gyro_bias_rw: float = 1.0e-5  # bias random walk, rad/s^2/sqrt(Hz)

    # wheels (encoders, nav_msgs/Odometry twist)
    wheel_rate: float = 50.0  # Hz
    wheel_scale_sigma: float = 0.01  # std of the v and omega scale errors (1 +- ...)
    wheel_sigma_v: float = 0.01  # white noise on v while moving, m/s
    wheel_sigma_omega: float = 0.01  # white noise on omega while moving, rad/s
    wheel_track: float = 0.5  # distance between the wheels, m (for slip on one side)
    slip_rate: float = 1.0 / 60.0  # slip episodes per second of motion
    slip_duration: tuple[float, float] = (0.5, 2.0)  # uniform range, s
    slip_gain: tuple[float, float] = (0.1, 0.4)  # extra wheel speed / true speed, uniform

    # UWB two-way ranging
    uwb_rate: float = 40.0  # ranges per second over all anchors (round robin), Hz
    los_sigma: float = 0.026  # LOS range noise std, m
    nlos_mean: float = 0.114  # NLOS excess range mean, m
    nlos_std: float = 0.145  # NLOS excess range std, m (total)
    nlos_corr: float = 0.7  # share of the NLOS variance that is slow (per anchor AR(1))
    nlos_tau_s: float = 5.0  # correlation time of the slow NLOS part, s
    # "gaussian" (Qiu 2022's fit; reads short ~1 range in 5) or "lognormal" (never negative)
    nlos_excess: str = "gaussian"
    outlier_prob: float = 0.005  # gross outliers per range
    outlier_range: tuple[float, float] = (1.0, 4.0)  # outlier magnitude, uniform, m
    outlier_negative: float = 0.15  # share of outliers that are too short
    dropout_prob: float = 0.01  # lost ranges (LOS)
    nlos_dropout_prob: float = 0.05  # lost ranges while NLOS
    outage: tuple[float, float] | None = None  # no ranges in [start, end), s from log start
    anchor_offset_max: float = 0.0  # constant per-anchor offset, uniform +-, m
    # write RX and first-path power with each range (`sim.signal`; a custom range type)
    signal_quality: bool = False

    # LiDAR localisation poses (`sim.lidar`; in the log when "pose" is in `streams`)
    pose_rate: float = 10.0  # Hz
    pose_sigma_xy: float = 0.03  # position noise std per axis, m
    pose_sigma_yaw: float = 0.01  # heading noise std, rad (0.6 deg)
    pose_corr: float = 0.7  # share of the pose noise variance that is slow (AR(1))
    pose_tau_s: float = 3.0  # correlation time of the slow part, s
    pose_dropouts: tuple[Box, ...] = ()  # no pose inside (featureless aisles)
    pose_wrong_rate: float = 1.0 / 30.0  # wrong matches per second
    pose_wrong_jump: tuple[float, float] = (0.5, 2.0)  # their offset, uniform, m
    pose_wrong_duration: tuple[float, float] = (0.5, 2.0)  # their length, uniform, s

    def anchor_dict(self) -> dict[str, Vec3]:
        return dict(self.anchors)

    def with_overrides(self, **overrides: Any) -> Scenario:
        """A copy with fields replaced; unknown names raise SimulationError."""
        known = {f.name for f in fields(self)}
        bad = sorted(set(overrides) - known)
        if bad:
            raise SimulationError(
                f"unknown simulation parameter(s) {', '.join(bad)}; "
                f"known: {', '.join(sorted(known))}"
            )
        return replace(self, **overrides)


# ---------------------------------------------------------------------------------------
# room: Qiu 2022 section 5.1, Table 1 (5 m along x by 6 m along y, anchors at 1.5 m)

ROOM_ANCHORS: tuple[tuple[str, Vec3], ...] = (
    ("A1", (0.0, 0.0, 1.5)),
    ("A2", (0.0, 6.0, 1.5)),
    ("A3", (5.0, 0.0, 1.5)),
    ("A4", (5.0, 6.0, 1.5)),
)
ROOM_CABINET = Box(2.1, 2.5, 2.9, 3.5)  # a cabinet in the middle: the room's NLOS source
QIU_STATIC_POINTS: tuple[tuple[float, float], ...] = (
    (0.6, 0.6), (0.6, 0.27), (0.6, 4.8), (1.8, 4.8), (3.0, 4.8),
)


def _rect_loop(x0: float, y0: float, x1: float, y1: float, l90: float, station: float,
               dwell: float) -> tuple[tuple[Primitive, ...], tuple[float, float, float]]:
    """Counter-clockwise rectangle x0..x1, y0..y1 with rounded corners (turn length l90).

    Starts at (x0 + station, y0) heading +x and stops there for `dwell` s each lap.
    """
    side_x = x1 - x0
    side_y = y1 - y0
    # a 90 degree turn advances 0.5844 l90 forward and sideways
    k = 0.5844089868985125 * l90
    prims: list[Primitive] = [
        Straight(side_x - station - k), Turn(HALF_PI, l90),
        Straight(side_y - 2 * k), Turn(HALF_PI, l90),
        Straight(side_x - 2 * k), Turn(HALF_PI, l90),
        Straight(side_y - 2 * k), Turn(HALF_PI, l90),
        Straight(station - k), Stop(dwell),
    ]
    prims = close_loop(prims, free=(6, 8), start_yaw=0.0)
    return tuple(prims), (x0 + station, y0, 0.0)


_room_route, _room_start = _rect_loop(1.0, 1.0, 4.0, 5.0, l90=1.2, station=1.0, dwell=3.0)

ROOM = Scenario(
    name="room",
    description="Qiu 2022 room: 5 m x 6 m, 4 anchors at 1.5 m (Table 1), one cabinet, "
    "AGV at 0.1 m/s on a rounded rectangle",
    size=(5.0, 6.0),
    anchors=ROOM_ANCHORS,
    boxes=(ROOM_CABINET,),
    route=_room_route,
    start=_room_start,
    speed=0.1,
    accel=0.1,
)


def _static_route() -> tuple[tuple[Primitive, ...], tuple[float, float, float]]:
    """Visit Qiu's five static test points (Table 2), dwelling 20 s at each, turning in place.

    P2 (0.6, 0.27) -> P1 (0.6, 0.6) -> P3 (0.6, 4.8) -> P4 (1.8, 4.8) -> P5 (3.0, 4.8) -> back.
    """
    dwell = 20.0
    prims: tuple[Primitive, ...] = (
        Stop(dwell),  # at P2
        Straight(0.33), Stop(dwell),  # P1
        Straight(4.2), Stop(dwell),  # P3
        Spin(-HALF_PI), Straight(1.2), Stop(dwell),  # P4
        Straight(1.2), Stop(dwell),  # P5
        Spin(PI), Straight(2.4), Spin(HALF_PI), Straight(4.53), Spin(PI),  # back to P2
    )
    return prims, (0.6, 0.27, HALF_PI)


_static_prims, _static_start = _static_route()

ROOM_STATIC = replace(
    ROOM,
    name="room-static",
    description="Qiu 2022 Table 2: the tag stands 20 s at each of the five static test "
    "points of the room, moving between them at 0.1 m/s and turning in place",
    route=_static_prims,
    start=_static_start,
    static_points=QIU_STATIC_POINTS,
)

# ---------------------------------------------------------------------------------------
# factory: INS-UWB collision-avoidance paper, 10 m x 10 m test ground, three anchors on
# shelf corners (placed here as a triangle), shelves as obstacles

FACTORY = Scenario(
    name="factory",
    description="INS-UWB factory: 10 m x 10 m, 3 anchors at 2.5 m, two shelf blocks, "
    "AGV at 0.5 m/s on a loop",
    size=(10.0, 10.0),
    anchors=(
        ("N1", (0.0, 0.0, 2.5)),
        ("N2", (10.0, 0.0, 2.5)),
        ("N3", (5.0, 10.0, 2.5)),
    ),
    boxes=(Box(3.5, 3.2, 6.5, 4.4), Box(3.5, 5.6, 6.5, 6.8)),
    route=(),
    start=(0.0, 0.0, 0.0),
)
_f_route, _f_start = _rect_loop(1.5, 1.5, 8.5, 8.5, l90=3.0, station=3.0, dwell=3.0)
FACTORY = replace(FACTORY, route=_f_route, start=_f_start)

# ---------------------------------------------------------------------------------------
# warehouse: Qiu 2022 section 5.2, 40 m x 20 m, anchors at the corners (Table 4)

WAREHOUSE_ANCHORS: tuple[tuple[str, Vec3], ...] = (
    ("A1", (0.0, 0.0, 1.5)),
    ("A2", (0.0, 20.0, 1.5)),
    ("A3", (40.0, 0.0, 1.5)),
    ("A4", (40.0, 20.0, 1.5)),
)
SHELF_DEPTH = 1.2
SHELF_ROWS_Y = (5.0, 10.0, 15.0)  # centre lines of the three shelf rows, m
SHELF_SPANS_X = ((8.0, 17.0), (23.0, 32.0))  # each row is split by a 6 m cross aisle, m
WAREHOUSE_SHELVES: tuple[Box, ...] = tuple(
    Box(x0, yc - 0.5 * SHELF_DEPTH, x1, yc + 0.5 * SHELF_DEPTH)
    for yc in SHELF_ROWS_Y
    for x0, x1 in SHELF_SPANS_X
)
U_TURN_LEN = 5.0 / 0.38864295819179034  # a U-turn of this length shifts 5 m sideways


def _warehouse_route() -> tuple[tuple[Primitive, ...], tuple[float, float, float]]:
    """Serpentine through the four aisles (y = 2.5, 7.5, 12.5, 17.5), back along x ~ 4."""
    x_left, x_right, x_station, l90 = 6.5, 33.5, 8.5, 4.0
    aisle = x_right - x_left
    prims: list[Primitive] = [
        Straight(x_right - x_station), Turn(PI, U_TURN_LEN),
        Straight(aisle), Turn(-PI, U_TURN_LEN),
        Straight(aisle), Turn(PI, U_TURN_LEN),
        Straight(aisle), Turn(HALF_PI, l90),
        Straight(10.0), Turn(HALF_PI, l90),
        Straight(2.0), Stop(3.0),
    ]
    prims = close_loop(prims, free=(8, 10), start_yaw=0.0)
    return tuple(prims), (x_station, 2.5, 0.0)


def _racetrack_route() -> tuple[tuple[Primitive, ...], tuple[float, float, float]]:
    """Racetrack around the middle shelf row: aisles y = 7.5 (+x) and 12.5 (-x)."""
    x_left, x_right, x_station = 6.5, 33.5, 10.0
    aisle = x_right - x_left
    prims: tuple[Primitive, ...] = (
        Straight(x_right - x_station), Turn(PI, U_TURN_LEN),
        Straight(aisle), Turn(PI, U_TURN_LEN),
        Straight(x_station - x_left), Stop(3.0),
    )
    return prims, (x_station, 7.5, 0.0)


_w_route, _w_start = _warehouse_route()

WAREHOUSE = Scenario(
    name="warehouse",
    description="Qiu 2022 warehouse: 40 m x 20 m hall, 4 corner anchors at 1.5 m (Table 4), "
    "three shelf rows (1.2 m deep, x 8-32 m, cross aisle at x 17-23 m), "
    "AGV at 0.5 m/s serpentine through the aisles",
    size=(40.0, 20.0),
    anchors=WAREHOUSE_ANCHORS,
    boxes=WAREHOUSE_SHELVES,
    route=_w_route,
    start=_w_start,
    los_sigma=0.05,
    outlier_prob=0.01,
    dropout_prob=0.02,
)

_r_route, _r_start = _racetrack_route()

WAREHOUSE_NLOS = replace(
    WAREHOUSE,
    name="warehouse-nlos",
    description="heavy NLOS: the AGV circles the middle shelf row, so shelf rows stand "
    "between it and most anchors; NLOS excess N(0.3, 0.15) m for seconds, 2% gross outliers",
    route=_r_route,
    start=_r_start,
    los_sigma=0.05,
    nlos_mean=0.3,
    nlos_std=0.15,
    nlos_corr=0.8,
    outlier_prob=0.02,
    dropout_prob=0.02,
    nlos_dropout_prob=0.05,
)

WAREHOUSE_LIDAR = replace(
    WAREHOUSE,
    name="warehouse-lidar",
    description="the warehouse with a LiDAR localiser (UKF paper): poses at 10 Hz, 3 cm / "
    "0.6 deg noise, none in the middle 18 m of the first and third aisles (featureless), "
    "a wrong match of 0.5-2 m for 0.5-2 s every 30 s on average",
    streams=("imu", "wheel", "uwb", "pose"),
    pose_dropouts=(Box(12.0, 1.0, 30.0, 4.0), Box(11.0, 11.0, 29.0, 14.0)),
)

SCENARIOS: dict[str, Scenario] = {
    s.name: s for s in (ROOM, ROOM_STATIC, FACTORY, WAREHOUSE, WAREHOUSE_NLOS, WAREHOUSE_LIDAR)
}


def get_scenario(name: str) -> Scenario:
    """The scenario registered as `name`; SimulationError naming the known ones otherwise."""
    try:
        return SCENARIOS[name]
    except KeyError:
        raise SimulationError(
            f"unknown scenario {name!r}; known: {', '.join(sorted(SCENARIOS))}"
        ) from None
