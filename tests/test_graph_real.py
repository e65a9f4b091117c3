# SPDX-License-Identifier: BSD-3-Clause
"""The graph estimators on the real logs: Labyrinth, ISAS-Walk1 and Plaza2 (gtsam wheel).

Default configuration plus each log's own config.toml; nothing from ground truth. Bounds
are about 1.3x the 2-D ATE RMSE measured on 2026-11-22 (deterministic runs), so a
regression fails. Logs under ../shared/data/real are skipped with a reason when absent.
"""

from __future__ import annotations

from dataclasses import fields, replace

import numpy as np
import pytest

from tests.helpers import keep_samples, real, silent
from uwbfuse.config import Config, load_config
from uwbfuse.estimator import Method
from uwbfuse.eval.evaluate import evaluate
from uwbfuse.io.reader import read_log
from uwbfuse.io.tum import read_tum
from uwbfuse.pipeline import estimate
from uwbfuse.positioning.initialisation import InitialState

gtsam = pytest.importorskip("gtsam")


# measured: isam2 0.103, isam2-smoothed 0.046, batch 0.046 (2026-12-02, session 9)
@pytest.mark.parametrize(("method", "bound"), [(Method.ISAM2, 0.14), (Method.ISAM2_SMOOTHED, 0.065),
                                                (Method.BATCH, 0.10)])
def test_labyrinth_wheels_and_uwb(method: Method, bound: float) -> None:
    """Test the graph on the real Labyrinth log (UWB + wheels, no IMU, GT in the map frame)."""
    cfg = load_config(real("labyrinth/config.toml"))
    log = read_log(real("labyrinth/labyrinth.mcap"), cfg)
    res = estimate(log, method, cfg)
    ev = evaluate(res.trajectory, read_tum(real("labyrinth/gt.tum")), max_dt=0.1)
    assert ev.ate_2d.rmse < bound
    assert ev.coverage > 0.9
    # the radios read long (antenna delay): the calibrated biases say so
    biases = [a["bias_m"] for a in res.report["anchors"].values()]
    assert np.median(biases) > 0.02


# measured: cauchy 0.107 (the mixture chosen) before the robust candidate was scored by
# its Huber density under every kernel, 0.0405 after (Huber 0.0412); geman_mcclure 0.104
# -> 0.0401
@pytest.mark.parametrize("kernel", ["cauchy", "geman_mcclure"])
def test_labyrinth_batch_range_model_choice_does_not_hang_on_the_kernel(kernel: str) -> None:
    """Test that batch's held-out choice picks the same (robust) range model on
    Labyrinth under another range kernel: the robust candidate's held-out ranges are
    scored by a density whatever kernel fitted it, not by a Gaussian."""
    cfg0 = load_config(real("labyrinth/config.toml"))
    cfg = Config.model_validate({**cfg0.model_dump(), "uwb": {
        **cfg0.uwb.model_dump(exclude={"kernel_threshold"}), "robust_kernel": kernel}})
    log = read_log(real("labyrinth/labyrinth.mcap"), cfg)
    res = estimate(log, Method.BATCH, cfg, covariance=False)
    assert res.report["batch"]["range_model"] == "robust"
    ev = evaluate(res.trajectory, read_tum(real("labyrinth/gt.tum")), max_dt=0.1)
    assert ev.ate_2d.rmse < 0.06


# measured, 2-D error RMS from 20 s on: isam2 main cd5dd5e 1.44 m (the track 3 m off at
# 18-20 s, after the wheels were back), batch 0.17 m ATE; with the dropout's factors at
# their guess's noise isam2 0.077, batch 0.070 m ATE
@pytest.mark.parametrize(("method", "bound"), [(Method.ISAM2, 0.2), (Method.BATCH, 0.2)])
def test_labyrinth_wheel_dropout(method: Method, bound: float) -> None:
    """Test the graph on Labyrinth with its wheel odometry silent from 10 to 15 s: the
    wheel factors over the dropout carry the last (online) or next (offline) twist as a
    guess whose noise grows with it, instead of 5 s of confident odometry."""
    cfg = load_config(real("labyrinth/config.toml"))
    log = read_log(real("labyrinth/labyrinth.mcap"), cfg)
    log.wheel = silent(log.wheel, int(log.ranges.t_ns[0]), 10.0, 15.0)
    res = estimate(log, method, cfg, covariance=False)
    gt = read_tum(real("labyrinth/gt.tum"))
    tr = res.trajectory
    after = (tr.t_ns - log.ranges.t_ns[0]) / 1e9 >= 20.0
    gi = np.clip(np.searchsorted(gt.t_ns, tr.t_ns[after]), 0, len(gt.t_ns) - 1)
    err = np.linalg.norm(tr.position[after, :2] - gt.position[gi, :2], axis=1)
    assert np.sqrt(np.mean(err**2)) < bound


def test_labyrinth_batch_refits_its_robust_model_over_the_whole_log() -> None:
    """Labyrinth's graph starts 7 s in; batch's held-out choice picks the robust range model,
    so batch runs again with the ranges and odometry before the start in the graph
    (measured 0.057 m with the first pass alone, 0.046 m after the refit)."""
    cfg = load_config(real("labyrinth/config.toml"))
    log = read_log(real("labyrinth/labyrinth.mcap"), cfg)
    res = estimate(log, Method.BATCH, cfg, covariance=False)
    refit = res.report["whole_log_refit"]
    assert refit["first_pass_range_model"] == "robust" and refit["start_backdate_s"] > 0
    assert res.report["batch"]["range_model"] == "robust"  # chosen again, whole log
    t0, _ = log.time_span_ns()
    assert res.report["first_keyframe_t_ns"] <= t0 + 1e8  # one keyframe period
    ev = evaluate(res.trajectory, read_tum(real("labyrinth/gt.tum")), max_dt=0.1)
    assert ev.ate_2d.rmse < 0.051  # issue 13's target for this log
    # the user's own range model or backdate is kept as given: one pass
    fixed = cfg.model_copy(update={"graph": cfg.graph.model_copy(update={"range_model": "robust"})})
    assert "whole_log_refit" not in estimate(log, Method.BATCH, fixed, covariance=False).report


def test_isas_batch_backdates_its_robust_fit_by_the_imu() -> None:
    """ISAS-Walk1 (IMU + UWB, no wheels): the graph starts 12 s in; the online pass scores
    the robust range model decisively better, so batch fits it and runs again with the
    start carried back to the first data by the gyro and a UWB fix (measured 2-D ATE, SE(2)
    against `gt_anchor_frame.tum`: 0.136 m in one pass with the mixture, 0.087 after)."""
    cfg = load_config(real("isas-walk1/config.toml"))
    log = read_log(real("isas-walk1/ISAS-Walk1"), cfg)
    res = estimate(log, Method.BATCH, cfg, covariance=False)
    refit = res.report["whole_log_refit"]
    assert refit["first_pass_range_model"] == "robust" and refit["start_backdate_s"] > 10
    assert res.report["batch"]["range_model"] == "robust"
    t0, _ = log.time_span_ns()
    assert res.report["first_keyframe_t_ns"] <= t0 + 1e8
    ev = evaluate(res.trajectory, read_tum(real("isas-walk1/gt_anchor_frame.tum")),
                  align="se2", max_dt=0.05)
    assert ev.ate_2d.rmse < 0.11  # issue 13's target for this log
    # the handheld consumer MEMS errs far beyond its [imu] white noise: the IMU noise
    # inflation from the log's evidence (measured 52.6; the online pass ended at 52.6)
    assert 16.0 < res.report["batch"]["imu_noise_inflation"] < 128.0


def test_labyrinth_smoothed_output_smooths_the_whole_graph_and_keeps_its_range_model() -> None:
    """isam2-smoothed solves its online pass's whole graph at the end as batch does; on
    Labyrinth the held-out choice picks the robust model, and the refit from the backdated
    start, choosing again over the whole log (EM starts NLOS-first on this wheeled log),
    picks it again (measured 0.042 m)."""
    cfg = load_config(real("labyrinth/config.toml"))
    log = read_log(real("labyrinth/labyrinth.mcap"), cfg)
    res = estimate(log, Method.ISAM2_SMOOTHED, cfg, covariance=False)
    assert res.report["whole_log_refit"]["first_pass_range_model"] == "robust"
    assert res.report["final_smoothing"]["range_model"] == "robust"
    assert "batch" not in res.report
    ev = evaluate(res.trajectory, read_tum(real("labyrinth/gt.tum")), max_dt=0.1)
    assert ev.ate_2d.rmse < 0.051


# measured (SE(3)-aligned to the Vive GT, IMU noise inflation `auto`, from the log: online
# fits 73, 68, 67, batch 52.6): isam2 0.180, isam2-smoothed 0.080, batch 0.082 (2026-12-05,
# session 16; with the former constant 30: 0.220, 0.077, 0.080)
@pytest.mark.parametrize(("method", "bound"), [(Method.ISAM2, 0.30), (Method.ISAM2_SMOOTHED, 0.18),
                                                (Method.BATCH, 0.16)])
def test_isas_walk_handheld_imu_and_uwb(method: Method, bound: float) -> None:
    """Test the graph on the real ISAS-Walk1 log (UWB + IMU, handheld, no wheels)."""
    cfg = load_config(real("isas-walk1/config.toml"))
    log = read_log(real("isas-walk1/ISAS-Walk1"), cfg)
    res = estimate(log, method, cfg)
    ev = evaluate(res.trajectory, read_tum(real("isas-walk1/gt.tum")), align="se3", max_dt=0.05)
    assert ev.ate_2d.rmse < bound
    # no wheels to pin a scale: `auto` leaves range scales off
    assert all(a["scale"] is None for a in res.report["anchors"].values())
    # the online IMU noise fits (from 10 s of keyframes on) find the IMU far noisier than
    # its [imu] figures (measured, isam2: 73, 68, 67; batch's backdated pass, whose first
    # window holds the 4 s the stick rests: 11, 36, 69)
    fits = res.report["online_imu_noise"]["fits"]
    assert fits and fits[-1]["inflation"] > 16.0


# measured (session 40), ISAS-Walk1's last 5 s (the stick in its holder): ranges whose
# online P(NLOS) is under 0.05 or over 0.95: main 0.92 (two anchors called NLOS at 0.86 and
# 0.89 on average), with the standstill weights 0.53; isam2 se3 0.1587, with them 0.1525 (mean of
# four runs, ranges perturbed by 0.2 mm); 174 ranges weighed
def test_isas_isam2_weighs_the_ranges_of_a_standstill_as_one() -> None:
    """Test that isam2 on ISAS-Walk1 finds the final standstill from its IMU and weighs
    the repeated ranges' LOS/NLOS evidence as correlated (`graph.rest`): the classes at
    rest stay undecided instead of locking onto one three-anchor LOS subset. Both rests
    after its start (54.7-56.5 s, 57.0-62.7 s) are entered at a velocity zero within its
    covariance: their keyframes are held at rest (71 in all)."""
    cfg = load_config(real("isas-walk1/config.toml"))
    log = read_log(real("isas-walk1/ISAS-Walk1"), cfg)
    res = estimate(log, Method.ISAM2, cfg, covariance=False)
    assert res.report["standstill_ranges"] > 100
    assert res.report["standstill_keyframes"] > 50
    rc = res.range_classes
    assert rc is not None
    last = rc.t_ns > rc.t_ns.max() - 5 * 10**9
    decided = (rc.p_nlos[last] < 0.05) | (rc.p_nlos[last] > 0.95)
    assert decided.mean() < 0.75
    ev = evaluate(res.trajectory, read_tum(real("isas-walk1/gt.tum")), align="se3", max_dt=0.05)
    assert ev.ate_2d.rmse < 0.2


# measured, 2-D ATE against gt_anchor_frame.tum (se2): without the check the none kernel's
# solve reached 50 m/s at keyframe 48 and ran to 1e9 m; with it 0.184 (one re-anchor);
# tukey at Huber's 1.345 lost the track (153 m), at its own 4.6851 0.195 (Huber 0.179)
@pytest.mark.slow  # 13 s: the kernel thresholds and the divergence check have fast tests
@pytest.mark.parametrize("kernel", ["none", "tukey"])
def test_isas_isam2_stays_on_the_track_under_any_range_kernel(kernel: str) -> None:
    """Test isam2 on ISAS-Walk1 with a kernel other than Huber: no kernel at all (a
    diverged Gauss-Newton step re-anchors the graph, said in the report) and Tukey at its
    default threshold (the kernel's own 95 %-efficiency value, not Huber's)."""
    cfg0 = load_config(real("isas-walk1/config.toml"))
    cfg = Config.model_validate({**cfg0.model_dump(), "uwb": {
        **cfg0.uwb.model_dump(exclude={"kernel_threshold"}), "robust_kernel": kernel}})
    log = read_log(real("isas-walk1/ISAS-Walk1"), cfg)
    res = estimate(log, Method.ISAM2, cfg)
    ev = evaluate(res.trajectory, read_tum(real("isas-walk1/gt_anchor_frame.tum")),
                  align="se2", max_dt=0.05)
    assert ev.ate_2d.rmse < 0.3
    events = res.report["reanchor_events"]
    assert len(events) <= 3
    assert all("diverged" in e["reason"] for e in events)


# measured, 2-D error RMS from 40 s on: main b601841 ran away to 1.2 km (isam2: 270
# re-anchors, each from a prediction already at 10 m/s; ekf 1.5 km); restarted as a lost
# track isam2 0.09-0.24 m, ekf 0.25-0.36 m, ukf 0.20-0.31 m
@pytest.mark.parametrize("method", [Method.ISAM2, Method.EKF, Method.UKF])
def test_isas_finds_the_track_again_after_a_range_outage(method: Method) -> None:
    """Test isam2 and the IMU-driven filters on ISAS-Walk1 with its ranges cut from 25 to
    35 s: the handheld IMU alone runs away (tens of metres), the track restarts as lost
    (velocity unknown, position from the ranges), and once the ranges are back it follows
    the walker again."""
    cfg = load_config(real("isas-walk1/config.toml"))
    log = read_log(real("isas-walk1/ISAS-Walk1"), cfg)
    r = log.ranges
    t_s = (r.t_ns - r.t_ns[0]) / 1e9
    keep = (t_s < 25.0) | (t_s >= 35.0)
    log.ranges = replace(r, **{f.name: getattr(r, f.name)[keep] for f in fields(r)
                               if isinstance(getattr(r, f.name), np.ndarray)
                               and getattr(r, f.name).shape[:1] == keep.shape})
    res = estimate(log, method, cfg, covariance=False)
    if method is Method.ISAM2:
        events = res.report["reanchor_events"]
        assert events and all("diverged" in e["reason"] for e in events)
    else:
        assert res.report["lost_restarts"] >= 1
    gt = read_tum(real("isas-walk1/gt_anchor_frame.tum"))
    tr = res.trajectory
    after = (tr.t_ns - r.t_ns[0]) / 1e9 >= 40.0
    gi = np.clip(np.searchsorted(gt.t_ns, tr.t_ns[after]), 0, len(gt.t_ns) - 1)
    err = np.linalg.norm(tr.position[after, :2] - gt.position[gi, :2], axis=1)
    assert np.sqrt(np.mean(err**2)) < 0.5


# measured (2026-12-06, session 29), 2-D ATE / max m: isam2 1.631 / 16.6 (four diverged
# solves and three indeterminate ones while the last IMU sample's turn rate was held 3 s),
# batch 0.272 / 1.25, ekf 1.365 / 9.76, ukf 1.423 / 10.55; with the rest guess beyond 0.5 s
# isam2 0.562 / 3.99, batch 0.138 / 0.60, ekf 0.692 / 5.28, ukf 0.711 / 5.26. Batch here has
# two basins, and a change of the online pass far below a millimetre flips between them
# (docs/results.md, "Session 39 on main: checks")
@pytest.mark.parametrize(("method", "bound"), [
    (Method.ISAM2, 1.0), pytest.param(Method.BATCH, 0.25, marks=pytest.mark.slow),
    (Method.EKF, 1.0), (Method.UKF, 1.0)])
def test_isas_through_a_blackout_of_every_sensor(method: Method, bound: float) -> None:
    """Test the graph and the IMU-driven filters on ISAS-Walk1 with the IMU and the ranges
    silent from 20 to 23 s (a logging stall): through the dropout the IMU is taken to read
    what it would with no turn and no acceleration at the estimated attitude and biases
    (`imu.rest_reading`; the filters' still sample), not the last sample's instantaneous
    turn rate, which held for seconds spins the attitude and runs the track away."""
    cfg = load_config(real("isas-walk1/config.toml"))
    log = read_log(real("isas-walk1/ISAS-Walk1"), cfg)
    t_ref = int(log.ranges.t_ns[0])
    log.imu = silent(log.imu, t_ref, 20.0, 23.0)
    log.ranges = silent(log.ranges, t_ref, 20.0, 23.0)
    res = estimate(log, method, cfg, covariance=False)
    ev = evaluate(res.trajectory, read_tum(real("isas-walk1/gt_anchor_frame.tum")),
                  align="se2", max_dt=0.05)
    assert ev.ate_2d.rmse < bound


@pytest.mark.slow  # the default suite's longest test (39 s)
def test_plaza2_batch_calibrates_the_range_scale_on_default_config() -> None:
    """Test Plaza2 (radios ~7 % long) on default config: below 1.5 m, scales reported.

    Measured 0.297 m, anchor scales +6.6 to +7.8 % (1.64 m with `estimate_range_scale =
    false`).
    """
    try:
        from uwbfuse.graph.plaza import plaza_log, plaza_path

        log = plaza_log(plaza_path("Plaza2"))
    except Exception as e:  # any failure to find the data file
        pytest.skip(f"Plaza2 not in this gtsam wheel: {e}")
    res = estimate(log, Method.BATCH, Config())
    ev = evaluate(res.trajectory, log.ground_truth, max_dt=0.1)
    assert ev.ate_2d.rmse < 0.4
    scales = np.array([a["scale"] for a in res.report["anchors"].values()])
    assert np.all(np.isfinite(scales))
    assert 0.03 < np.median(scales) < 0.12  # reads long by several per cent


@pytest.mark.slow
def test_plaza1_isam2_online_range_scales_settle_as_constants() -> None:
    """Test that isam2's online per-anchor range scales converge on Plaza1 (radios ~7 %
    long, one clock: batch finds one common scale, +7.3 %) instead of wandering.

    Measured (2026-12-06, session 25): final online scales +7.3 to +7.6 %, 2-D ATE 0.548 m;
    before, each scale step weighed only its own 20 ranges: +5.5 to +7.4 %, 0.666 m.
    """
    try:
        from uwbfuse.graph.plaza import plaza_log, plaza_path

        log = plaza_log(plaza_path("Plaza1"))
    except Exception as e:  # any failure to find the data file
        pytest.skip(f"Plaza1 not in this gtsam wheel: {e}")
    res = estimate(log, Method.ISAM2, Config())
    scales = np.array([a["scale"] for a in res.report["anchors"].values()])
    assert np.ptp(scales) < 0.01
    assert np.all(np.abs(scales - 0.073) < 0.01)
    assert evaluate(res.trajectory, log.ground_truth, max_dt=0.1).ate_2d.rmse < 0.62
    # GTSAM's fixed-lag marginalisation failed once here (at 634.8 s, session 39): the
    # smoother is rebuilt from its factors, the graph not re-anchored
    assert res.report["reanchor_events"] == []


def test_plaza2_isam2_holds_a_standstill_fix_until_the_start() -> None:
    """Test Plaza2 isam2 (causal): the 21 s standstill before the graph can fix a heading
    gets the scale-aware standstill fix, not per-epoch WLS fixes.

    Measured: standstill fixes 0.16-0.35 m off for 21 s (the WLS provisional fixes were
    ~9 m off: ranges 7 % long); from the first wheel motion to the graph start at 24 s the
    last standstill position is held (1.3 m RMS) in place of the discredited WLS fixes;
    whole-log 2-D ATE 0.492 m (2.157 m before).
    """
    try:
        from uwbfuse.graph.plaza import plaza_log, plaza_path

        log = plaza_log(plaza_path("Plaza2"))
    except Exception as e:  # any failure to find the data file
        pytest.skip(f"Plaza2 not in this gtsam wheel: {e}")
    res = estimate(log, Method.ISAM2, Config())
    assert res.report["standstill_fix_epochs"] > 150
    tr, gt = res.trajectory, log.ground_truth
    gp = np.column_stack([np.interp(tr.t_ns, gt.t_ns, gt.position[:, i]) for i in range(2)])
    err = np.linalg.norm(tr.position[:, :2] - gp, axis=1)
    early = tr.t_ns < log.ranges.t_ns[0] + 20 * 10**9
    assert np.count_nonzero(early) > 150
    assert np.max(err[early]) < 0.6
    # contract: poses at 10 Hz from the first one to the end, no gap at the start
    assert np.max(np.diff(tr.t_ns)) <= 101_000_000
    assert res.report["held_provisional_epochs"] > 0
    assert evaluate(tr, gt, max_dt=0.1).ate_2d.rmse < 0.65
    # the radios' errors are no NLOS mixture: the new ranges' prequential scores say so
    # (measured z +35), while the online graph keeps the mixture under `auto`
    online = res.report["online_range_model"]
    assert online["verdict"] == "robust" and online["z"] > 10
    assert online["model"] == "mixture"


def _start(range_scale: float) -> InitialState:
    return InitialState(t_ns=0, position=np.zeros(3), R_map_base=np.eye(3),
                        velocity=np.zeros(3), gyro_bias=np.zeros(3), accel_bias=np.zeros(3),
                        position_sigma=0.1, yaw_sigma=0.1, still=False, range_scale=range_scale)


@pytest.mark.parametrize(("mode", "start_scale", "site_m", "on"), [
    ("auto", 1.07, 10.0, True), ("auto", 0.95, 10.0, True), ("auto", 1.01, 10.0, False),
    (False, 1.07, 10.0, False), (True, 1.0, 10.0, True),
    # 2.5 % at room size moves the ranges by ~0.12 m: the start solve's noise (room-static)
    ("auto", 1.025, 5.0, False), ("auto", 1.025, 40.0, True)])
def test_range_scale_auto_follows_the_start_solve(mode, start_scale: float, site_m: float,
                                                  on: bool) -> None:
    """Test that `estimate_range_scale = "auto"` switches scales on past 2 % at the start
    when the scale moves the ranges by more than half a metre."""
    from uwbfuse.graph.builder import GraphBuilder
    from uwbfuse.graph.imu import ImuBuffer
    from uwbfuse.graph.wheel import WheelTrack
    from uwbfuse.streams import AnchorMap

    cfg = Config(graph={"estimate_range_scale": mode})
    anchors = AnchorMap(ids=("a", "b", "c"), positions=np.array(
        [[0.0, 0, 2], [site_m, 0, 2], [0, site_m, 2]]))
    b = GraphBuilder(cfg, anchors, frozenset({"wheel", "uwb"}), _start(start_scale),
                     ImuBuffer(), WheelTrack(), record=False)
    assert b.with_scale is on
    if on:
        np.testing.assert_allclose(b.scale, start_scale - 1.0)


def test_plaza1_nlos_states_leave_the_window_in_chain_order() -> None:
    """Test that isam2 on Plaza1's first 150 s (wheels + sparse ranges, NLOS reviews that
    reach back to older segments) never re-anchors.

    A delayed review re-stamped an anchor's older NLOS state to the present while the later
    state chained to it kept its own stamp; the later one then left the window first and
    GTSAM's fixed-lag smoother failed its marginalisation ("Asking to remove variables
    from the variable index that are not unused"): the graph re-anchored at 82 s and again
    at 1189 s (measured 2026-12-06, session 29: whole log 0.548 -> 0.534 m 2-D ATE).
    """
    try:
        from uwbfuse.graph.plaza import plaza_log, plaza_path

        log = plaza_log(plaza_path("Plaza1"))
    except Exception as e:  # any failure to find the data file
        pytest.skip(f"Plaza1 not in this gtsam wheel: {e}")
    t_end = int(log.ranges.t_ns[0]) + 150 * 1_000_000_000
    log = replace(log, **{name: keep_samples(getattr(log, name), getattr(log, name).t_ns <= t_end)
                          for name in ("wheel", "ranges", "ground_truth")})
    res = estimate(log, Method.ISAM2, Config())
    assert res.report["reanchor_events"] == []
    # measured: 0.900 m (0.943 with the re-anchor); the first 40 s stand still before a start
    assert evaluate(res.trajectory, log.ground_truth, max_dt=0.1).ate_2d.rmse < 1.1
