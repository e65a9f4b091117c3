# SPDX-License-Identifier: BSD-3-Clause
"""The initialiser: start state from sensors alone, per sensor combination."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tests.synth_positioning import ROOM, handheld_3d, make_log, planar_drive, truth_at
from uwbfuse.config import Config
from uwbfuse.estimator import output_epochs
from uwbfuse.positioning.initialisation import Initialiser, InitialState
from uwbfuse.streams import NS_PER_S, SensorLog

LEVER = (0.1, 0.0, 0.3)


def drive(
    log: SensorLog, streams: tuple[str, ...], config: Config | None = None
) -> tuple[InitialState | None, Initialiser]:
    """Feed `log` at 10 Hz like `run_streaming`; return the first InitialState."""
    cfg = config or Config(extrinsics={"tag_in_base": LEVER})
    init = Initialiser(cfg, log.anchors, frozenset(streams))
    srcs = []
    if "imu" in streams and log.imu is not None:
        srcs.append((init.add_imu, (log.imu.t_ns, log.imu.gyro, log.imu.accel)))
    if "wheel" in streams and log.wheel is not None:
        srcs.append((init.add_wheel, (log.wheel.t_ns, log.wheel.v, log.wheel.omega)))
    if "uwb" in streams and log.ranges is not None:
        srcs.append((init.add_ranges, (log.ranges.t_ns, log.ranges.anchor, log.ranges.range)))
    starts = [0] * len(srcs)
    for t in output_epochs(log, 10.0):
        for i, (add, cols) in enumerate(srcs):
            e = int(np.searchsorted(cols[0], t, side="right"))
            if e > starts[i]:
                add(*(c[starts[i]:e] for c in cols))
                starts[i] = e
        st = init.try_initialise(int(t))
        if st is not None:
            assert st.t_ns == int(t)
            return st, init
    return None, init


def errors(log: SensorLog, st: InitialState) -> tuple[float, float]:
    """(horizontal position error m, yaw error deg) of a state against ground truth."""
    p, yaw, _ = truth_at(log, st.t_ns)
    dyaw = (st.yaw - yaw + math.pi) % (2 * math.pi) - math.pi
    return float(np.linalg.norm(st.position[:2] - p[:2])), math.degrees(dyaw)


COMBOS = [("imu", "wheel", "uwb"), ("wheel", "uwb"), ("imu", "uwb")]


@pytest.mark.parametrize("still", [3.0, 0.0], ids=["still-start", "moving-start"])
@pytest.mark.parametrize("streams", COMBOS[:2], ids=lambda s: "+".join(s))
def test_wheeled_synthetic(streams: tuple[str, ...], still: float) -> None:
    """test that wheeled logs initialise to < 0.1 m and < 3 deg, still or moving at start"""
    log, _ = make_log(planar_drive((1.0, 1.5), 0.7, still), ROOM, 15.0, seed=1,
                      imu="imu" in streams, lever=LEVER)
    st, init = drive(log, streams)
    assert st is not None, init.last_reason
    e_pos, e_yaw = errors(log, st)
    # Measured: 0.007-0.045 m, 0.05-2.3 deg.
    assert e_pos < 0.1 and abs(e_yaw) < 3.0
    # the heading's std is reported, not required: it covers the error (measured 0.17 rad)
    assert math.radians(abs(e_yaw)) <= 3.0 * st.yaw_sigma < math.pi / 4
    # The state refers to the time asked for: base height from the floor prior and data.
    assert abs(st.position[2]) < 0.15
    t_move = log.time_span_ns()[0] + still * NS_PER_S
    assert st.t_ns > t_move  # heading needs motion


def test_imu_uwb_still_start_synthetic() -> None:
    """test that IMU + UWB (no wheels) with a still start gets heading from the first motion"""
    log, _ = make_log(planar_drive((1.0, 1.5), 0.7, 3.0), ROOM, 15.0, seed=1, wheel=False,
                      lever=LEVER)
    st, init = drive(log, ("imu", "uwb"))
    assert st is not None, init.last_reason
    e_pos, e_yaw = errors(log, st)
    assert st.still
    assert e_pos < 0.1 and abs(e_yaw) < 3.0  # measured 0.045 m, 0.5 deg
    # The standstill gyro bias is the simulated one (0.003, -0.002, 0.004) rad/s.
    np.testing.assert_allclose(st.gyro_bias, [0.003, -0.002, 0.004], atol=1e-3)


def test_handheld_3d_still_start() -> None:
    """test that a 3-D handheld (IMU + UWB) initialises position, heading and roll/pitch"""
    log, _ = make_log(handheld_3d((2.0, 1.0, 1.0), -0.5, 3.0), ROOM, 16.0, seed=2,
                      wheel=False, lever=LEVER)
    st, init = drive(log, ("imu", "uwb"))
    assert st is not None, init.last_reason
    p, _yaw, rot = truth_at(log, st.t_ns)
    e_pos, e_yaw = errors(log, st)
    # it starts once the heading has no rival (measured 0.03 m, 0.15 m in height, 0.26 m
    # and 0.22 rad reported): the errors inside what it reports
    assert e_pos < 3.0 * st.position_sigma and np.linalg.norm(st.position - p) < 0.25
    assert abs(math.radians(e_yaw)) < 3.0 * st.yaw_sigma
    tilt = np.degrees(np.arccos(np.clip((np.trace(rot.T @ st.R_map_base) - 1) / 2, -1, 1)))
    assert tilt < 5.0


def test_imu_uwb_moving_start_reports_its_uncertainty() -> None:
    """test that without a still start or wheels the heading comes with an honest std"""
    log, _ = make_log(handheld_3d((2.0, 1.0, 1.0), -0.5, 0.0), ROOM, 12.0, seed=2,
                      wheel=False, lever=LEVER)
    st, init = drive(log, ("imu", "uwb"))
    assert st is not None, init.last_reason
    e_pos, e_yaw = errors(log, st)
    assert not st.still
    assert e_pos < 0.15
    assert abs(math.radians(e_yaw)) < 3.0 * st.yaw_sigma


@pytest.mark.parametrize("anchors", ["level", "tilted-down"])
def test_imu_uwb_slow_start_is_not_a_standstill(anchors: str) -> None:
    """test that a tag moving off at 0.1 m/s (the room loop: no faster than `min_motion`,
    too smooth for the IMU's standstill test) is not taken as standing still until its
    UWB track has moved `min_displacement`: the start lands on the tag, not 0.9 m behind
    it at the median of a moving "standstill" (level: measured 0.01 m at 8.9 s); and that
    the free start velocity is seeded from the line through the first fixes (tilted-down,
    40 s: two noisy 3-D fixes gave a 0.9 m/s climb, the solve a 0.85 m error; now 0.02 m)"""
    from uwbfuse.sim.simulator import simulate_with_truth

    kw = {} if anchors == "level" else {"anchors": TILTED_ROOMS[anchors]}
    log = simulate_with_truth("room", 25.0 if anchors == "level" else 40.0, seed=0,
                              streams=("imu", "uwb"), **kw).log
    st, init = drive(log, ("imu", "uwb"), Config())
    assert st is not None, init.last_reason
    assert not st.still
    assert errors(log, st)[0] < 0.3


def test_uwb_only_track_direction() -> None:
    """test that UWB alone gives position and the track direction once moving"""
    log, _ = make_log(planar_drive((1.0, 1.5), 0.7, 0.0), ROOM, 10.0, seed=1, imu=False,
                      wheel=False, lever=LEVER)
    st, init = drive(log, ("uwb",))
    assert st is not None, init.last_reason
    e_pos, e_yaw = errors(log, st)
    assert e_pos < 0.2 and abs(e_yaw) < 10.0  # measured 0.11 m, 0.6 deg
    assert np.linalg.norm(st.velocity[:2]) > 0.2


def test_uwb_only_slow_round_robin_starts() -> None:
    """test that a slow round robin (four anchors at 1 Hz each: one fix per cycle, fewer
    than five in any 2 s) still gives position and the track direction once moving"""
    log, _ = make_log(planar_drive((1.0, 1.5), 0.7, 0.0), ROOM, 15.0, seed=1, imu=False,
                      wheel=False, lever=LEVER, range_rate=4.0)
    st, init = drive(log, ("uwb",))
    assert st is not None, init.last_reason
    e_pos, e_yaw = errors(log, st)
    # the fixes at their epochs' ends (0.6 s behind) put it 0.27 m off at a reported 0.085 m;
    # the heading (9.2 deg off: the track turns and speeds up within the fit's 6 s) is not
    # measured, so the base sits at the tag (LEVER's 0.1 m horizontal part unapplied)
    assert e_pos < 2.0 * st.position_sigma < 0.4
    assert abs(e_yaw) < 15.0 and math.radians(abs(e_yaw)) < 3.0 * st.yaw_sigma
    assert np.linalg.norm(st.velocity[:2]) > 0.2


def test_uwb_only_still_tag_has_unknown_heading() -> None:
    """test that a still UWB-only tag starts after heading_timeout with yaw_sigma = pi"""
    log, _ = make_log(planar_drive((1.0, 1.5), 0.7, 30.0), ROOM, 6.0, seed=1, imu=False,
                      wheel=False, lever=LEVER)
    st, _ = drive(log, ("uwb",))
    assert st is not None
    assert st.yaw_sigma == pytest.approx(math.pi)
    assert errors(log, st)[0] < 0.1 + np.hypot(*LEVER[:2])  # the base sits at the tag
    t0 = log.time_span_ns()[0]
    assert st.t_ns - t0 >= Config().init.heading_timeout * NS_PER_S


def test_no_initial_state_before_the_data_allow_it() -> None:
    """test that a standing vehicle never initialises, and the first state waits for motion"""
    still_log, _ = make_log(planar_drive((1.0, 1.5), 0.7, 100.0), ROOM, 8.0, seed=1,
                            lever=LEVER)
    st, init = drive(still_log, ("imu", "wheel", "uwb"))
    assert st is None and "still" in init.last_reason
    log, _ = make_log(planar_drive((1.0, 1.5), 0.7, 3.0), ROOM, 12.0, seed=1, lever=LEVER)
    init = Initialiser(Config(extrinsics={"tag_in_base": LEVER}), ROOM,
                       frozenset({"imu", "wheel", "uwb"}))
    assert init.try_initialise(int(log.time_span_ns()[0])) is None
    assert log.imu is not None and log.wheel is not None and log.ranges is not None
    t_cut = log.time_span_ns()[0] + int(3.5 * NS_PER_S)  # 0.5 s after the first motion
    k = np.searchsorted(log.imu.t_ns, t_cut, side="right")
    init.add_imu(log.imu.t_ns[:k], log.imu.gyro[:k], log.imu.accel[:k])
    k = np.searchsorted(log.wheel.t_ns, t_cut, side="right")
    init.add_wheel(log.wheel.t_ns[:k], log.wheel.v[:k], log.wheel.omega[:k])
    k = np.searchsorted(log.ranges.t_ns, t_cut, side="right")
    init.add_ranges(log.ranges.t_ns[:k], log.ranges.anchor[:k], log.ranges.range[:k])
    assert init.try_initialise(int(t_cut)) is None
    assert "min_displacement" in init.last_reason or "fixes" in init.last_reason


def test_no_anchors_starts_at_origin() -> None:
    """test that without ranges the state is the map origin, heading zero, levelled"""
    log, _ = make_log(planar_drive((1.0, 1.5), 0.7, 3.0), ROOM, 5.0, seed=1, uwb=False)
    st, _ = drive(log, ("imu", "wheel"))
    assert st is not None
    np.testing.assert_allclose(st.position, 0.0)
    assert abs(st.yaw) < 1e-2


SIM_CASES = [
    (sc, streams, still)
    for sc in ("room", "warehouse", "factory")
    for streams in COMBOS[:2]
    for still in (2.0, 0.0)
]


@pytest.mark.parametrize(("scenario", "streams", "still"), SIM_CASES,
                         ids=[f"{a}-{'+'.join(b)}-{'still' if c else 'moving'}"
                              for a, b, c in SIM_CASES])
def test_simulated_los_scenarios(scenario: str, streams: tuple[str, ...], still: float) -> None:
    """test the simulated LOS sites (obstacles removed): < 0.1 m and < 5 deg at start"""
    from uwbfuse.sim.simulator import simulate_with_truth

    res = simulate_with_truth(scenario, 30.0, 1, still_start_s=still, streams=streams,
                              tag_in_base=LEVER, boxes=(), outlier_prob=0.0)
    st, init = drive(res.log, streams)
    assert st is not None, init.last_reason
    e_pos, e_yaw = errors(res.log, st)
    # Measured over seeds 0-3: 0.007-0.058 m, |yaw| 0.06-5.6 deg (yaw std 5.6-14 deg
    # reported: the start is taken once no rival heading is left, its std not required).
    assert e_pos < 0.1
    assert abs(e_yaw) < 8.0
    assert abs(math.radians(e_yaw)) < 4.0 * st.yaw_sigma + math.radians(0.5)


def test_simulated_imu_uwb_warehouse_still_start() -> None:
    """test IMU + UWB without wheels on the simulated warehouse (LOS) with a still start"""
    from uwbfuse.sim.simulator import simulate_with_truth

    res = simulate_with_truth("warehouse", 30.0, 0, still_start_s=2.0, streams=("imu", "uwb"),
                              tag_in_base=LEVER, boxes=(), outlier_prob=0.0)
    st, init = drive(res.log, ("imu", "uwb"))
    assert st is not None, init.last_reason
    e_pos, e_yaw = errors(res.log, st)
    assert e_pos < 0.2
    assert abs(math.radians(e_yaw)) < 3.0 * st.yaw_sigma



@pytest.mark.parametrize("seed", [0, 2])
def test_imu_uwb_start_velocity_and_tilt_carry_the_solved_bias_corrections(seed: int) -> None:
    """test that the start state of an IMU + UWB track (no wheels) with a poor IMU (gyro bias
    std 0.02 rad/s, 10x an MPU6050's noise) carries the solve's bias corrections into its
    velocity and attitude, not only its position: over a 3-4 s strapdown window a 0.02 rad/s
    gyro bias tilts the track by 4 deg and its velocity by g b t^2 / 2 ~ 1-2 m/s (before:
    1.3-4.3 m/s and 4-13 deg off at start; the EKF then ran 5-10 m away on sweep seed 5
    draw 0). Bounds: half a walking pace horizontally, 8 deg of tilt."""
    from scipy.spatial.transform import Rotation

    from uwbfuse.sim.simulator import simulate_with_truth

    sim = simulate_with_truth("warehouse", 14.0, seed, streams=("imu", "uwb"),
                              still_start_s=2.0, speed=0.6, accel_noise_density=0.04,
                              gyro_noise_density=3e-3, accel_bias_sigma=0.2,
                              gyro_bias_sigma=0.02)
    st, init = drive(sim.log, ("imu", "uwb"), Config())
    assert st is not None, init.last_reason
    gt = sim.log.ground_truth
    i = int(np.searchsorted(gt.t_ns, st.t_ns))
    assert np.linalg.norm(st.velocity[:2] - sim.velocity[i, :2]) < 0.5
    up = Rotation.from_quat(gt.quat_xyzw[i]).as_matrix()[:, 2]
    assert math.degrees(math.acos(min(1.0, float(up @ st.R_map_base[:, 2])))) < 8.0

# the room's anchors on one tilted plane: A1, A3 low, A2, A4 high (or the other way round)
TILTED_ROOMS = {
    "tilted-up": (("A1", (0.0, 0.0, 0.5)), ("A2", (0.0, 6.0, 2.6)),
                  ("A3", (5.0, 0.0, 0.5)), ("A4", (5.0, 6.0, 2.6))),
    "tilted-down": (("A1", (0.0, 0.0, 2.6)), ("A2", (0.0, 6.0, 0.5)),
                    ("A3", (5.0, 0.0, 2.6)), ("A4", (5.0, 6.0, 0.5))),
}


@pytest.mark.parametrize("tilt", list(TILTED_ROOMS))
def test_anchors_on_a_tilted_plane_start_and_track(tilt: str) -> None:
    """test that isam2 and ekf start on a room whose anchors lie on one tilted plane, with
    IMU and UWB and no wheels (3-D fixes; they never started when coplanarity was a height
    test), and track on the floor's side: after the start 2-D ATE below 0.25 m and 3-D
    below 0.3 m, where the mirror image across the plane is at least 0.9 m off"""
    from uwbfuse.estimator import Method
    from uwbfuse.eval.evaluate import evaluate
    from uwbfuse.pipeline import estimate
    from uwbfuse.sim.simulator import simulate_with_truth

    sim = simulate_with_truth("room", 45.0, 0, streams=("imu", "uwb"),
                              anchors=TILTED_ROOMS[tilt])
    gt = sim.log.ground_truth
    assert gt is not None
    for method, start_key in ((Method.ISAM2, "init_t_ns"), (Method.EKF, "initialised_at_ns")):
        res = estimate(sim.log, method, Config(), covariance=False)
        t_start = res.report.get(start_key)
        assert t_start is not None, (method, res.report)
        ev = evaluate(res.trajectory, gt, max_dt=0.05)
        after = ev.t_ns >= t_start
        assert np.count_nonzero(after) > 100  # 10 s of poses after the start
        # Measured (docs/results.md, session 38): 0.02-0.16 m 2-D, 0.03-0.18 m 3-D over
        # seeds 0-4 and both tilts.
        assert np.sqrt(np.mean(ev.ate_2d_errors[after] ** 2)) < 0.25, method
        assert np.sqrt(np.mean(ev.ate_3d_errors[after] ** 2)) < 0.3, method


def test_provisional_state_before_heading() -> None:
    """test that a provisional state (position known, heading flagged unknown) exists while
    try_initialise still waits for motion"""
    log, _ = make_log(planar_drive((1.0, 1.5), 0.7, 100.0), ROOM, 4.0, seed=1, lever=LEVER)
    st, init = drive(log, ("imu", "wheel", "uwb"))
    assert st is None
    t_end = log.time_span_ns()[1]
    prov = init.provisional(int(t_end))
    assert prov is not None and prov.yaw_sigma == pytest.approx(math.pi)
    p, _, _ = truth_at(log, t_end)
    # Base position with the lever arm under yaw 0 (truth yaw 0.7 rad): within the lever.
    assert np.linalg.norm(prov.position[:2] - p[:2]) < 0.1 + np.hypot(*LEVER[:2])


def test_real_labyrinth_initialisation() -> None:
    """test the initialiser on the real labyrinth log (UWB + wheels, no IMU): position and
    heading against the ground-truth track direction"""
    from tests.helpers import real
    from uwbfuse.config import load_config
    from uwbfuse.io.reader import read_log

    cfg = load_config(real("labyrinth/config.toml"))
    log = read_log(real("labyrinth/labyrinth.mcap"), cfg)
    st, init = drive(log, ("wheel", "uwb"), cfg)
    assert st is not None, init.last_reason
    gt = log.ground_truth
    assert gt is not None
    k = int(np.argmin(np.abs(gt.t_ns - st.t_ns)))
    assert np.linalg.norm(st.position[:2] - gt.position[k, :2]) < 0.2  # measured 0.10 m
    d = gt.position[min(k + 1, len(gt) - 1)] - gt.position[max(k - 1, 0)]
    track = math.atan2(d[1], d[0])
    e_yaw = math.degrees((st.yaw - track + math.pi) % (2 * math.pi) - math.pi)
    # The robot turns at up to ~150 deg/s here and GT is 7.8 Hz: the GT direction over
    # +-1 sample is itself uncertain by ~20 deg, so this only catches gross heading errors.
    assert abs(e_yaw) < 30.0
    assert st.still


def test_real_isas_initialisation() -> None:
    """test the initialiser on the real ISAS handheld (IMU + UWB, 3-D): still start found,
    position near the ground truth in the anchor frame"""
    from tests.helpers import real
    from uwbfuse.config import load_config
    from uwbfuse.eval.command import read_ground_truth
    from uwbfuse.io.reader import read_log

    cfg = load_config(real("isas-walk1/config.toml"))
    log = read_log(real("isas-walk1/ISAS-Walk1"), cfg)
    gt = read_ground_truth(real("isas-walk1/gt_anchor_frame.tum"), cfg)
    st, init = drive(log, ("imu", "uwb"), cfg)
    assert st is not None, init.last_reason
    assert st.still  # the stick rests for the first ~4 s
    k = int(np.argmin(np.abs(gt.t_ns - st.t_ns)))
    # GT is the Vive tracker, not the IMU origin (~0.1-0.2 m apart); the stick is being
    # lifted by ~1 m while the heading is solved. Measured 0.40 m, yaw std 15.5 deg.
    assert np.linalg.norm(st.position - gt.position[k]) < 0.6
    assert st.yaw_sigma < math.radians(25.0)


def _plaza(name: str) -> SensorLog:
    """The Plaza log from the gtsam wheel, or skip when the data file is missing."""
    from uwbfuse.errors import UwbfuseError

    try:
        from uwbfuse.graph.plaza import plaza_log, plaza_path

        return plaza_log(plaza_path(name))
    except (ImportError, UwbfuseError) as exc:
        pytest.skip(f"Plaza data unavailable: {exc}")


def _trimmed(log: SensorLog, skip_s: float) -> SensorLog:
    """`log` without its first skip_s seconds (a start at another place and time)."""
    from uwbfuse.streams import RangeStream, WheelStream

    assert log.wheel is not None and log.ranges is not None
    t0 = min(int(log.wheel.t_ns[0]), int(log.ranges.t_ns[0])) + int(skip_s * NS_PER_S)
    w, r = log.wheel, log.ranges
    kw, kr = w.t_ns >= t0, r.t_ns >= t0
    return SensorLog(
        wheel=WheelStream(w.t_ns[kw], w.v[kw], w.omega[kw]),
        ranges=RangeStream(r.t_ns[kr], r.anchor[kr], r.range[kr]),
        anchors=log.anchors, ground_truth=log.ground_truth, source=log.source,
    )


# (log, seconds skipped at the start): measured init position error 4.73, 0.73, 0.59,
# 2.71, 0.38, 0.94 m; solved range scale 1.007-1.08 (the radios read ~7 % long).
PLAZA_STARTS = [("Plaza1", 0.0), ("Plaza1", 60.0), ("Plaza1", 200.0),
                ("Plaza2", 0.0), ("Plaza2", 30.0), ("Plaza2", 120.0)]


@pytest.mark.parametrize(("name", "skip_s"), PLAZA_STARTS)
def test_real_plaza_initialisation(name: str, skip_s: float) -> None:
    """test that the initialiser starts on the Plaza logs (wheels + sparse round-robin ranges
    to beacons tens of metres away) within 90 s, a few metres from the truth, with a
    plausible common range scale"""
    log = _trimmed(_plaza(name), skip_s)
    st, init = drive(log, ("wheel", "uwb"), Config())
    assert st is not None, init.last_reason
    assert log.wheel is not None and log.ground_truth is not None
    assert (st.t_ns - log.wheel.t_ns[0]) / NS_PER_S < 90.0
    gt = log.ground_truth
    p = np.array([np.interp(st.t_ns, gt.t_ns, gt.position[:, i]) for i in range(2)])
    assert np.linalg.norm(st.position[:2] - p) < 6.0
    assert 0.98 < st.range_scale < 1.12
    assert st.position_sigma < 5.0


def test_uwb_only_applies_only_the_lever_height() -> None:
    """test that without a heading sensor the start and the graph apply the lever's height
    only (the horizontal part would turn with an unmeasured heading), and all of it with one"""
    from uwbfuse.positioning.initialisation import applied_lever
    lever = (0.3, 0.1, 0.5)
    np.testing.assert_allclose(applied_lever(lever, frozenset({"uwb"})), [0.0, 0.0, 0.5])
    for heading in ("imu", "wheel", "pose"):
        np.testing.assert_allclose(applied_lever(lever, frozenset({"uwb", heading})), lever)
    init = Initialiser(Config(extrinsics={"tag_in_base": lever}), ROOM, frozenset({"uwb"}))
    np.testing.assert_allclose(init.lever, [0.0, 0.0, 0.5])
