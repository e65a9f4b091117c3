# SPDX-License-Identifier: BSD-3-Clause
"""End-to-end tests of the factor-graph estimators (isam2, isam2-smoothed, batch).

Short simulated logs with known truth. Tolerances are about 1.5x the errors measured on
these exact logs (seed 0) when the tests were written, so a regression fails while run-to-
run noise from the machine does not matter (everything here is deterministic).
"""

from __future__ import annotations

import logging
from dataclasses import replace

import numpy as np
import pytest

from uwbfuse.config import Config
from uwbfuse.errors import EstimatorError
from uwbfuse.estimator import Method, output_epochs, run_streaming
from uwbfuse.eval.evaluate import evaluate
from uwbfuse.pipeline import estimate
from uwbfuse.sim.simulator import simulate, simulate_with_truth
from uwbfuse.streams import NS_PER_S, SensorLog

gtsam = pytest.importorskip("gtsam")


def _drop(log: SensorLog, *streams: str) -> SensorLog:
    """A copy of `log` without the named streams ('imu', 'wheel')."""
    out = replace(log)
    for s in streams:
        setattr(out, s, None)
    return out


def _ate(res_traj, log: SensorLog) -> float:
    return evaluate(res_traj, log.ground_truth, max_dt=0.02).ate_2d.rmse


@pytest.fixture(scope="module")
def factory():
    """30 s of the factory scenario (3 anchors, NLOS behind machines, wheel slip)."""
    return simulate_with_truth("factory", 30.0, 0)


# measured (seed 0, isam2/batch): all 0.16/0.04, no imu 0.20/0.28, no wheel 0.30/0.25
# (30 s with 3 anchors, one in NLOS from the start, and wheel slip: the start dominates)
@pytest.mark.parametrize(
    ("drop", "tol_isam2", "tol_batch"),
    [((), 0.25, 0.06), (("imu",), 0.30, 0.43), (("wheel",), 0.45, 0.38)],
    ids=["imu+wheel+uwb", "wheel+uwb", "imu+uwb"],
)
def test_sensor_combinations(factory, drop, tol_isam2, tol_batch):
    """Test that every sensor combination with UWB initialises and tracks the truth."""
    log = _drop(factory.log, *drop)
    cfg = Config()
    online = estimate(log, Method.ISAM2, cfg)
    batch = estimate(log, Method.BATCH, cfg)
    assert _ate(online.trajectory, log) < tol_isam2
    assert _ate(batch.trajectory, log) < tol_batch
    # at least 10 poses per second from the first fix to the end, never before the fix
    t = online.trajectory.t_ns
    span = (t[-1] - t[0]) / NS_PER_S
    assert len(t) >= 10 * span
    assert np.all(np.diff(t) > 0)
    assert online.report["reanchor_events"] == []


def test_wheels_alone_without_uwb_is_rejected(factory):
    """Test that a graph method refuses a log with neither ranges nor an IMU (IMU + wheels
    without ranges it fuses: tests/test_filters_no_uwb.py)."""
    log = factory.log
    no_uwb = SensorLog(wheel=log.wheel, anchors=log.anchors, source="x")
    with pytest.raises(EstimatorError):
        estimate(no_uwb, Method.ISAM2, Config())


def test_initialisation_from_sensors_only(factory):
    """Test that the start comes from the sensors: None before the fix, close to truth after."""
    from uwbfuse.graph.estimator import make

    log = factory.log
    est = make(Method.ISAM2, Config(), log.anchors, frozenset({"imu", "wheel", "uwb"}))
    sensors = SensorLog(imu=log.imu, wheel=log.wheel, ranges=log.ranges, anchors=log.anchors)
    assert est.estimate() is None
    res = run_streaming(est, sensors, output_epochs(sensors, 10.0))
    first = res.causal.t_ns[0]
    assert first > log.imu.t_ns[0]  # the initialiser needed data first
    ev = evaluate(res.causal, log.ground_truth, max_dt=0.02)
    assert ev.ate_2d_errors[0] < 0.6  # measured 0.03 at the first fix


def test_smoothed_and_batch_improve_on_causal(factory):
    """Test that isam2-smoothed and batch are no worse than the causal isam2 output."""
    log = factory.log
    cfg = Config()
    causal = _ate(estimate(log, Method.ISAM2, cfg).trajectory, log)
    smoothed = _ate(estimate(log, Method.ISAM2_SMOOTHED, cfg).trajectory, log)
    batch = _ate(estimate(log, Method.BATCH, cfg).trajectory, log)
    assert smoothed < 1.2 * causal
    assert batch < 1.2 * causal


def test_outage_is_bridged():
    """Test that a 10 s UWB outage is bridged by odometry and the track recovers after it."""
    sim = simulate_with_truth("factory", 40.0, 1, outage=(15.0, 25.0))
    log = sim.log
    res = estimate(log, Method.ISAM2, Config())
    ev = evaluate(res.trajectory, log.ground_truth, max_dt=0.02)
    assert res.report["reanchor_events"] == []
    t = ev.t_s - log.ground_truth.t_s[0]
    during = (t > 15.0) & (t < 25.0)
    after = t > 32.0
    assert np.max(ev.ate_2d_errors[during]) < 0.45  # measured 0.26 (odometry drift)
    assert np.sqrt(np.mean(ev.ate_2d_errors[after] ** 2)) < 0.11  # measured 0.072


@pytest.mark.parametrize("method", [Method.ISAM2, Method.BATCH])
def test_an_imu_gap_is_carried_by_the_wheels(method):
    """Test that a 10 s IMU dropout on a wheeled log leaves the track to the wheels and the
    ranges: the IMU factors through it carry the unseen motion's noise, not a rest guess at
    the IMU's own (which held the vehicle unturned against the wheels: 0.93 / 0.71 m)."""
    log = simulate_with_truth("factory", 40.0, 3).log
    assert log.imu is not None
    s = (log.imu.t_ns - log.imu.t_ns[0]) / NS_PER_S
    keep = (s < 15.0) | (s > 25.0)
    gap = replace(log, imu=replace(log.imu, t_ns=log.imu.t_ns[keep], gyro=log.imu.gyro[keep],
                                   accel=log.imu.accel[keep]))
    res = estimate(gap, method, Config(), covariance=False)
    ev = evaluate(res.trajectory, log.ground_truth, max_dt=0.05)
    assert ev.ate_2d.rmse < 0.15  # measured isam2 0.073, batch 0.008


def test_batch_starts_nlos_first_on_light_nlos_wheeled_log():
    """Test that batch EM starts NLOS-first on a wheeled log whatever its NLOS share (room:
    online NLOS share ~0.12, below the removed 0.27 threshold, which started it online)."""
    log = simulate_with_truth("room", 20.0, 0).log
    res = estimate(log, Method.BATCH, Config())
    assert res.report["batch"]["em_start"] == "nlos-first"


def test_nlos_modelling_beats_huber_alone():
    """Test that NLOS bursts (2/3 of ranges biased +0.3 m) are handled by the NLOS model."""
    sim = simulate_with_truth("warehouse-nlos", 60.0, 0)
    log = sim.log
    with_model = Config()
    huber_only = Config()
    huber_only.graph.nlos = False
    res = estimate(log, Method.BATCH, with_model)
    assert res.report["batch"]["em_start"] == "nlos-first"  # wheeled log
    a = _ate(res.trajectory, log)
    b = _ate(estimate(log, Method.BATCH, huber_only).trajectory, log)
    e = _ate(estimate(log, Method.EKF, with_model).trajectory, log)
    # measured (seeds 0/1): 0.104/0.147 with the NLOS model (NLOS-first EM start), 0.29/0.32
    # Huber alone (issue 3: about 0.30 against 0.12), EKF 0.48/0.37
    assert a < 0.15
    assert a < 0.5 * b
    assert a < 0.6 * e  # issue 3: batch at least 40 % below the EKF


@pytest.mark.slow  # 19 s: keeps the default suite under 8 min on a slow machine
def test_range_bias_is_recovered():
    """Test that batch finds simulated per-anchor range offsets (+-0.2 m, no NLOS).

    The per-anchor prior is widened to 0.3 m: the default (0.05 m around a common offset)
    expects anchors of one make, as in the real logs.
    """
    sim = simulate_with_truth("room", 80.0, 2, anchor_offset_max=0.2, boxes=())
    log = sim.log
    cfg = Config()
    cfg.graph.range_bias_anchor_sigma = 0.3
    res = estimate(log, Method.BATCH, cfg)
    # no NLOS in this log: the held-out choice takes a model that calibrates the offsets
    # (measured: the calibrated mixture 2.183, robust 2.163, the mixture, its offsets held
    # at zero through EM, 2.117 nats per range), every range LOS
    assert res.report["batch"]["range_model"] in ("robust", "mixture, calibrated")
    assert all(v["nlos"] == 0 for v in res.report["anchors"].values())
    est = np.array([res.report["anchors"][a]["bias_m"] for a in log.anchors.ids])
    assert np.max(np.abs(est - sim.anchor_offset)) < 0.03  # measured 0.003
    # widened past the default, the prior is used as given online too (not held to 2 cm)
    online = estimate(log, Method.ISAM2, cfg)
    est = np.array([online.report["anchors"][a]["bias_m"] for a in log.anchors.ids])
    assert np.max(np.abs(est - sim.anchor_offset)) < 0.03  # measured 0.008


def test_isam2_is_causal():
    """Test that the isam2 estimate at t does not change when later data are appended."""
    sim = simulate_with_truth("factory", 30.0, 3)
    log = sim.log
    cut = log.imu.t_ns[0] + 20 * NS_PER_S

    def head(s):
        return None if s is None else s.slice(0, int(np.searchsorted(s.t_ns, cut, "right")))

    short = SensorLog(imu=head(log.imu), wheel=head(log.wheel), ranges=head(log.ranges),
                      anchors=log.anchors)
    full = SensorLog(imu=log.imu, wheel=log.wheel, ranges=log.ranges, anchors=log.anchors)
    a = estimate(short, Method.ISAM2, Config()).trajectory
    b = estimate(full, Method.ISAM2, Config()).trajectory
    n = int(np.searchsorted(a.t_ns, cut - NS_PER_S // 5, "right"))  # well inside the cut
    np.testing.assert_array_equal(a.t_ns[:n], b.t_ns[:n])
    np.testing.assert_allclose(a.position[:n], b.position[:n], atol=1e-9)


@pytest.mark.parametrize(("method", "exc"), [(Method.ISAM2, RuntimeError),
                                             (Method.ISAM2_SMOOTHED, ValueError)])
def test_gtsam_failure_reanchors_with_a_warning(factory, monkeypatch, caplog, method, exc):
    """Test that an iSAM2 failure mid-run re-anchors the graph instead of crashing, and
    that the smoothed output keeps the lag window's keyframes (GTSAM raises RuntimeError
    or ValueError, e.g. 'Asking to remove variables ... that are not unused')."""
    from uwbfuse.graph import online

    orig = online.OnlineSmoother.update
    calls = {"n": 0}

    def flaky(self, inc):
        calls["n"] += 1
        if calls["n"] == 50:
            raise exc("Indeterminant linear system detected (injected)")
        return orig(self, inc)

    monkeypatch.setattr(online.OnlineSmoother, "update", flaky)
    with caplog.at_level(logging.WARNING, logger="uwbfuse.graph.estimator"):
        res = estimate(factory.log, method, Config())
    assert len(res.report["reanchor_events"]) == 1
    assert "re-anchoring" in caplog.text
    # measured 0.150 (isam2) and 0.116 (smoothed; 0.58 when the window was lost), the
    # same as without the failure
    assert _ate(res.trajectory, factory.log) < 0.2


def test_marginalisation_failure_rebuilds_the_smoother_without_loss(factory, monkeypatch):
    """Test that GTSAM's marginalisation failure ("... not unused", raised at the end of a
    fixed-lag update whose factor bookkeeping is complete) rebuilds the smoother from its
    own factors instead of re-anchoring: no re-anchor, one rebuild reported, and the
    trajectory that of the run without the failure (injected after a completed update, so
    the rebuilt posterior is the same: measured 1e-11 m apart)."""
    from uwbfuse.graph import online

    clean = estimate(factory.log, Method.ISAM2, Config())
    orig_init = online.OnlineSmoother.__init__
    calls = {"n": 0}

    class FailingOnce:
        """The GTSAM smoother, whose 40th update completes and then raises."""

        def __init__(self, inner):
            self.inner = inner

        def __getattr__(self, name):
            return getattr(self.inner, name)

        def update(self, *args):
            self.inner.update(*args)
            calls["n"] += 1
            if calls["n"] == 40:
                raise ValueError("Asking to remove variables from the variable index that "
                                 "are not unused (injected)")

    def init(self, lag_s):
        orig_init(self, lag_s)
        self.smoother = FailingOnce(self.smoother)

    monkeypatch.setattr(online.OnlineSmoother, "__init__", init)
    res = estimate(factory.log, Method.ISAM2, Config())
    assert calls["n"] >= 40
    assert res.report["reanchor_events"] == []
    assert len(res.report["smoother_rebuilds"]) == 1
    assert clean.report["smoother_rebuilds"] == []
    assert len(res.trajectory) == len(clean.trajectory)
    np.testing.assert_allclose(res.trajectory.position, clean.trajectory.position, atol=1e-6)


def test_diverged_solve_reanchors_from_the_prediction(factory, monkeypatch, caplog):
    """Test that an update whose solve puts the newest keyframe at an impossible speed
    (injected: 50 m/s read back once) re-anchors the graph at the keyframe's prediction
    instead of carrying the diverged solve on, and says why."""
    from uwbfuse.graph import online

    orig_update, orig_velocity = online.OnlineSmoother.update, online.OnlineSmoother.velocity
    state = {"n": 0}

    def update(self, inc):
        state["n"] += 1
        return orig_update(self, inc)

    def velocity(self, k):
        v = orig_velocity(self, k)
        return v + np.array([50.0, 0.0, 0.0]) if state["n"] == 50 else v

    monkeypatch.setattr(online.OnlineSmoother, "update", update)
    monkeypatch.setattr(online.OnlineSmoother, "velocity", velocity)
    log = factory.log  # with an IMU: its velocity state is what is read
    with caplog.at_level(logging.WARNING, logger="uwbfuse.graph.estimator"):
        res = estimate(log, Method.ISAM2, Config())
    events = res.report["reanchor_events"]
    assert len(events) == 1
    assert "diverged" in events[0]["reason"] and "m/s" in events[0]["reason"]
    assert "re-anchoring" in caplog.text
    assert np.all(np.isfinite(res.trajectory.position))
    # measured 0.050 (0.042 without the injection)
    assert _ate(res.trajectory, log) < 0.08


def test_report_has_outliers_and_biases(factory):
    """Test that report() lists per-anchor ranges, NLOS, down-weighted counts and biases."""
    res = estimate(factory.log, Method.BATCH, Config())
    anchors = res.report["anchors"]
    assert set(anchors) == set(factory.log.anchors.ids)
    for a in anchors.values():
        assert a["ranges"] > 0
        assert 0 <= a["nlos"] <= a["ranges"]
        assert 0 <= a["downweighted"] <= a["ranges"]
        assert isinstance(a["bias_m"], float)
    assert res.report["update_latency_ms"]["p99"] > 0


def test_online_los_sigma_is_estimated_robustly():
    """Test the online LOS sigmas on the room log (true LOS std 0.026 m, 17 % NLOS).

    Measured (seeds 0/1, 60 s): one-step 0.0289/0.0295, smoothed 0.0280/0.0283. The RMS of
    the one-step residuals classified LOS, which the M-step used before the MAD, is
    0.033 m on 120 s of seed 0.
    """
    res = estimate(simulate_with_truth("room", 60.0, 0).log, Method.ISAM2, Config())
    mix = res.report["nlos_mixture"]
    assert 0.022 < mix["sigma_los_smoothed"] <= mix["sigma_los"] < 0.032


def test_online_nlos_excess_mean_is_learnt_and_batch_keeps_the_configured_one():
    """Test that the online graph learns the NLOS excess mean from the log (warehouse, seed
    0, 60 s: NLOS ranges 0.173 m long on average against the configured 0.3 m) and that
    batch, whose seeding pass must not learn it, reports the configured one.

    Measured: isam2 0.128 m; room seeds 0/1 0.216/0.191, factory 0.226 (fewer NLOS ranges,
    so the configured mean weighs more)."""
    log = simulate_with_truth("warehouse", 60.0, 0).log
    online = estimate(log, Method.ISAM2, Config()).report["nlos_mixture"]["mu_nlos"]
    assert 0.08 < online < 0.2
    batch = estimate(log, Method.BATCH, Config()).report["nlos_mixture"]["mu_nlos"]
    assert batch == Config().nlos.excess_mean


def test_without_bias_estimation_reports_none(factory):
    """Test that with bias estimation off the report says so (bias None)."""
    cfg = Config()
    cfg.graph.estimate_range_bias = False
    res = estimate(factory.log, Method.ISAM2, cfg)
    assert all(a["bias_m"] is None for a in res.report["anchors"].values())


def test_online_los_search_escapes_a_wrong_nlos_classification(monkeypatch):
    """Test the online LOS/NLOS hypothesis search on a log where EM alone settles with LOS
    anchors taken for NLOS (warehouse, seed 3, 120 s).

    Measured isam2: 0.105 m with the search, 0.130 m without it (0.113 and 0.152 m while
    the online ranges were classified against offsets that had taken up NLOS excess:
    docs/results.md, "isam2 and the causal bound"). (Seed 1,
    which this test used, needs it no more since the start is taken once no rival heading
    is left: 0.156 and 0.164 m, against 0.173 and 0.390 m before; room seed 3 none since
    the LOS sigma is a MAD estimate: 0.014 m either way.)
    """
    from uwbfuse.graph import estimator as graph_estimator

    sim = simulate_with_truth("warehouse", 120.0, 3)
    res = estimate(sim.log, Method.ISAM2, Config())
    assert res.report["los_hypothesis_switches"] > 0
    with_search = _ate(res.trajectory, sim.log)
    monkeypatch.setattr(graph_estimator, "REVIEW_SEARCH", False)
    without = _ate(estimate(sim.log, Method.ISAM2, Config()).trajectory, sim.log)
    assert with_search < 0.14
    assert without > 1.15 * with_search


@pytest.mark.slow  # 28 s: keeps the default suite under 8 min on a slow machine
def test_batch_los_search_escapes_a_wrong_nlos_classification(monkeypatch):
    """Test batch's per-stretch LOS/NLOS hypothesis search (warehouse-nlos, seed 1, 120 s).

    Measured batch: 0.149 m with the search, 0.185 m without it. (Room seed 3, which this
    test used, gets 0.005 m either way since the online LOS sigma is a MAD estimate; over
    warehouse-nlos seeds 0-4 the error without the search is 0.90 to 1.24 times the error
    with it.)
    """
    from uwbfuse.graph import offline

    sim = simulate_with_truth("warehouse-nlos", 120.0, 1)
    with_search = _ate(estimate(sim.log, Method.BATCH, Config()).trajectory, sim.log)
    monkeypatch.setattr(offline, "BATCH_SEARCH", False)
    without = _ate(estimate(sim.log, Method.BATCH, Config()).trajectory, sim.log)
    assert with_search < 0.17
    assert without > 1.15 * with_search


def _wheel_scale_runs(method: Method) -> tuple[dict, dict, float, float, tuple, object]:
    """`method` on factory (seed 0, 60 s) with encoders reading v 3 % fast, wheel-scale
    calibration on and off: (report on, report off, 2-D ATE on, off, the true (v, omega)
    scales that undo the encoders' errors, the log)."""
    sim = simulate_with_truth("factory", 60.0, 0)
    log = replace(sim.log, wheel=replace(sim.log.wheel, v=sim.log.wheel.v * 1.03))
    truth = 1.0 / (1.03 * sim.wheel_scale[0]), 1.0 / sim.wheel_scale[1]
    off = Config()
    off.graph = off.graph.model_copy(update={"estimate_wheel_scale": False})
    res_off = estimate(log, method, off)
    res_on = estimate(log, method, Config())
    ate_off = evaluate(res_off.trajectory, log.ground_truth).ate_2d.rmse
    ate_on = evaluate(res_on.trajectory, log.ground_truth).ate_2d.rmse
    return res_on.report, res_off.report, ate_on, ate_off, truth, log


def test_batch_calibrates_a_wheel_speed_scale_error():
    """Test that batch's wheel-scale calibration finds encoders reading 3 % fast and beats
    the uncalibrated batch.

    Measured (factory, seed 0, 60 s; the simulated encoders already read v x 1.008, so v
    reads x 1.038 in all): 2-D ATE 0.049 m uncalibrated, 0.030 m calibrated, v scale 0.971
    (truth 0.963), omega 1.018 (truth 1.019)."""
    on, off, ate_on, ate_off, truth, _ = _wheel_scale_runs(Method.BATCH)
    assert "wheel_scale" not in off["batch"]
    est = on["batch"]["wheel_scale"]
    assert est["v"] == pytest.approx(truth[0], abs=0.015)
    assert est["omega"] == pytest.approx(truth[1], abs=0.01)
    assert ate_on < 0.75 * ate_off


def test_isam2_learns_the_wheel_speed_scale_online():
    """Test that the online graph learns encoders reading 3 % fast from the keyframes
    leaving its lag, builds its later wheel factors with the scale, beats the unscaled
    isam2, that `graph.estimate_wheel_scale = false` turns it off and that a robust range
    model neither learns nor uses it.

    Measured (factory, seed 0, 60 s; v reads x 1.038 in all, as in the batch test above):
    2-D ATE 0.057 m unscaled, 0.037 m scaled; v scale 0.965 (truth 0.963), omega 1.018
    (truth 1.019)."""
    on, off, ate_on, ate_off, truth, log = _wheel_scale_runs(Method.ISAM2)
    assert "online_wheel_scale" not in off
    est = on["online_wheel_scale"]
    assert est["applied"]
    assert est["v"] == pytest.approx(truth[0], abs=0.01)
    assert est["omega"] == pytest.approx(truth[1], abs=0.01)
    assert ate_on < 0.75 * ate_off
    # under a robust range model every range holds the track: no scale is learnt or used
    robust = Config()
    robust.graph = robust.graph.model_copy(update={"range_model": "robust"})
    held = estimate(log, Method.ISAM2, robust).report["online_wheel_scale"]
    assert not held["applied"]
    assert held["v"] == 1.0
    assert held["omega"] == 1.0


def test_batch_fits_the_wheel_noise_from_the_log(factory):
    """Test that batch loosens the configured wheel noise where the encoders are noisier
    than it (0.4 m/s white noise added to v at 50 Hz, 8x `wheel.sigma_v`), keeps it where
    they are not, and that `graph.estimate_wheel_noise = false` turns the fit off.

    Measured (factory, seed 0, 30 s; noise seed 1): v factor 4.09, omega 1.0; 2-D ATE
    0.043 m fitted against 0.053 m configured; (1, 1) on the log as simulated."""
    w = factory.log.wheel
    rng = np.random.default_rng(1)
    noisy = replace(factory.log, wheel=replace(
        w, v=w.v + rng.normal(0.0, 0.4, w.v.shape) * (np.abs(w.v) > 1e-3)))
    off = Config()
    off.graph = off.graph.model_copy(update={"estimate_wheel_noise": False})
    res_on = estimate(noisy, Method.BATCH, Config())
    res_off = estimate(noisy, Method.BATCH, off)
    assert "wheel_noise_factor" not in res_off.report["batch"]
    fac = res_on.report["batch"]["wheel_noise_factor"]
    assert fac["v"] > 2.5
    assert fac["omega"] == pytest.approx(1.0, abs=0.2)
    assert _ate(res_on.trajectory, noisy) < _ate(res_off.trajectory, noisy)
    clean = estimate(factory.log, Method.BATCH, Config()).report["batch"]
    assert clean["wheel_noise_factor"] == {"v": 1.0, "omega": 1.0}


def test_batch_fits_the_wheel_time_offset():
    """Test that batch finds wheel stamps that run early against the ranges (the
    simulated encoders' stamps moved 15 ms earlier, 3/4 of their 20 ms period) and none
    where there is none.

    Measured (factory, seed 0, 60 s): 0.0138 s and -0.00006 s."""
    sim = simulate_with_truth("factory", 60.0, 0)
    w = sim.log.wheel
    early = replace(sim.log, wheel=replace(w, t_ns=w.t_ns - round(0.015 * NS_PER_S)))
    found = estimate(early, Method.BATCH, Config()).report["batch"]["wheel_time_offset_s"]
    none = estimate(sim.log, Method.BATCH, Config()).report["batch"]["wheel_time_offset_s"]
    assert found == pytest.approx(0.015, abs=0.004)
    assert none == pytest.approx(0.0, abs=0.004)


def test_wheel_time_offset_search_steps_past_its_edge(factory, monkeypatch):
    """Test that the offset search goes on past +1 period while the edge scores best and
    places the vertex between grid points, scoring no offset on the side that loses (from
    0 and +-0.5 periods): a motion-fit error (x - 2.3)^2 in periods."""
    from uwbfuse.graph import offline
    from uwbfuse.graph.builder import GraphBuilder

    offsets: list[int] = []
    complete = GraphBuilder.complete_wheel_records

    def spy(self, offset_ns=0, noise_scale=(1.0, 1.0)):
        offsets.append(offset_ns)
        return complete(self, offset_ns, noise_scale)

    period = float(np.median(np.diff(factory.log.wheel.t_ns)))
    monkeypatch.setattr(GraphBuilder, "complete_wheel_records", spy)
    monkeypatch.setattr(offline, "motion_fit_error",
                        lambda *a, **k: ((offsets[-1] / period - 2.3) ** 2, a[2]))
    cfg = Config()
    cfg.graph = cfg.graph.model_copy(update={"estimate_wheel_noise": False})
    found = estimate(factory.log, Method.BATCH, cfg).report["batch"]["wheel_time_offset_s"]
    assert found * NS_PER_S / period == pytest.approx(2.3, abs=0.02)
    assert min(offsets) / period == pytest.approx(-0.5, abs=0.01)


def test_batch_on_a_mostly_static_room_keeps_the_range_scale_off():
    """Test that the room-static log (20 s dwells; the graph starts at 54 s, once the tag has
    moved) does not take the start solve's 2.5 % range scale for the radios'.

    Measured (seed 0, 60 s): batch 2-D ATE 0.110 m with the per-anchor scales switched on
    (k x 4.9 m = 0.12 m), 0.021 m without."""
    sim = simulate_with_truth("room-static", 60.0, 0)
    res = estimate(sim.log, Method.BATCH, Config())
    assert all(a["scale"] is None for a in res.report["anchors"].values())
    assert evaluate(res.trajectory, sim.log.ground_truth).ate_2d.rmse < 0.04


def test_smoothed_output_on_a_wheeled_log_chooses_its_range_model_again_like_batch():
    """Test that isam2-smoothed's whole-log refit on a wheeled log chooses its range model
    again over the whole log (EM starts NLOS-first there, free of the online pass's classes)
    instead of keeping the first pass's robust choice.

    Measured (room-static seed 0, 60 s; the first pass starts at 54 s and picks robust):
    0.065 m when the robust choice was kept, 0.010 m chosen again (mixture; batch 0.010)."""
    sim = simulate_with_truth("room-static", 60.0, 0)
    res = estimate(sim.log, Method.ISAM2_SMOOTHED, Config(), covariance=False)
    assert res.report["whole_log_refit"]["first_pass_range_model"] == "robust"
    assert res.report["final_smoothing"]["range_model"] == "mixture"
    assert evaluate(res.trajectory, sim.log.ground_truth).ate_2d.rmse < 0.03


@pytest.mark.slow
def test_uwb_only_log_is_smoothed_with_a_constant_velocity_prior():
    """Test that a log with neither IMU nor wheels gets the constant-velocity motion prior
    (V keys, white-noise acceleration) and that batch then beats per-epoch WLS on it."""
    sim = simulate_with_truth("room", 40.0, 1)
    log = _drop(sim.log, "imu", "wheel")
    cfg = Config()
    smoothed = _ate(estimate(log, Method.ISAM2_SMOOTHED, cfg).trajectory, log)
    batch = _ate(estimate(log, Method.BATCH, cfg).trajectory, log)
    wls = _ate(estimate(log, Method.WLS, cfg).trajectory, log)
    # measured (seed 1): isam2-smoothed 0.050, batch 0.061, wls 0.061 m
    assert smoothed < 0.9 * wls, (smoothed, wls)
    assert batch < 1.05 * wls, (batch, wls)


def test_uwb_only_slow_round_robin_starts_the_graph():
    """Test that a UWB-only log from a slow round robin (four anchors at 1 Hz each: one
    multilateration fix per cycle) starts the graph, whose smoothing then beats the
    per-epoch fixes. The UWB-only start once needed five fixes within 2 s: such a log
    never started, and every method wrote the provisional fixes (the same ATE as wls)."""
    log = _drop(simulate("warehouse", 40.0, 0, uwb_rate=4.0), "imu", "wheel")
    res = estimate(log, Method.BATCH, Config(), covariance=False)
    assert res.report["initialised"], res.report
    assert res.report["provisional_epochs"] < 0.1 * len(res.trajectory.t_ns)
    wls = _ate(estimate(log, Method.WLS, Config()).trajectory, log)
    # measured: batch 0.150 m, wls 0.545 m (60 s, seeds 0-2: batch 0.14-0.22, wls 0.42-0.46)
    assert _ate(res.trajectory, log) < 0.5 * wls


def test_uwb_only_batch_fits_the_motion_prior_density():
    """Test that without IMU and wheels batch takes the constant-velocity prior's
    acceleration density from the log (`graph.motion_accel_density = "auto"`): the room's
    robot, at 0.1 m/s, gets one well below the walking-pace start of 1 m/s^2/sqrt(Hz), and
    its track is better than at that start held fixed."""
    sim = simulate_with_truth("room", 30.0, 0)
    log = _drop(sim.log, "imu", "wheel")
    fitted = estimate(log, Method.BATCH, Config(), covariance=False)
    density = fitted.report["batch"]["motion_accel_density"]
    assert 0.01 < density < 0.5, density
    fixed = estimate(log, Method.BATCH, Config(graph={"motion_accel_density": 1.0}),
                     covariance=False)
    assert "motion_accel_density" not in fixed.report["batch"]
    assert _ate(fitted.trajectory, log) < 0.8 * _ate(fixed.trajectory, log)


def test_uwb_only_online_pass_fits_the_motion_prior_density_causally():
    """Test that without IMU and wheels isam2 fits the constant-velocity prior's density as
    it fits an IMU's noise online (over its newest keyframes, causally): the room's slow
    robot gets a density below the start of 1 m/s^2/sqrt(Hz), and the online track is
    better than at that start held fixed."""
    sim = simulate_with_truth("room", 30.0, 0)
    log = _drop(sim.log, "imu", "wheel")
    fitted = estimate(log, Method.ISAM2, Config(), covariance=False)
    online = fitted.report["online_motion_prior"]
    assert online["fits"] and online["accel_density"] < 0.5, online
    fixed = estimate(log, Method.ISAM2, Config(graph={"motion_accel_density": 1.0}),
                     covariance=False)
    assert "online_motion_prior" not in fixed.report
    assert _ate(fitted.trajectory, log) < 0.8 * _ate(fixed.trajectory, log)


def test_motion_prior_densities_set_how_smooth_a_uwb_only_track_is():
    """Test that `graph.motion_accel_density` and `motion_turn_density` reach the
    constant-velocity prior: a smaller acceleration density gives a smoother track, a
    smaller turn density a steadier heading."""
    sim = simulate_with_truth("room", 20.0, 1)
    log = _drop(sim.log, "imu", "wheel")

    def run(acc: float, turn: float):
        cfg = Config(graph={"motion_accel_density": acc, "motion_turn_density": turn})
        return estimate(log, Method.ISAM2_SMOOTHED, cfg).final

    def roughness(traj) -> float:  # RMS second difference of the position, m
        return float(np.sqrt(np.mean(np.diff(traj.position[:, :2], 2, axis=0) ** 2)))

    def heading_spread(traj) -> float:  # RMS change of the quaternion between epochs
        return float(np.sqrt(np.mean(np.diff(traj.quat_xyzw, axis=0) ** 2)))

    smooth, loose = run(0.2, 0.5), run(5.0, 0.5)
    assert roughness(smooth) < 0.8 * roughness(loose)
    steady, turning = run(1.0, 0.01), run(1.0, 2.0)
    assert heading_spread(steady) < 0.8 * heading_spread(turning)


@pytest.mark.parametrize(("peak_log2", "expected"), [(2.0, 4.0), (None, 1.0)],
                         ids=["peak-at-4x", "rising-to-the-edge"])
def test_wheel_noise_fit_keeps_the_configured_noise_at_its_edge(monkeypatch, peak_log2,
                                                                expected):
    """Test that the wheel noise search finds an evidence peak inside its range (4x, log2
    2) and keeps the configured noise where the evidence still rises at its 16x edge (a
    misfit of another model, not odometry noise)."""
    from uwbfuse.graph import noise_fit
    from uwbfuse.graph.builder import WheelRecords

    def evidence(graph, initial, family, factors, max_iterations):
        u = np.log2(factors[0])
        ev = 50.0 * u if peak_log2 is None else -50.0 * (u - peak_log2) ** 2
        return ev - 50.0 * np.log2(factors[1]) ** 2, initial

    monkeypatch.setattr(noise_fit, "noise_log_evidence", evidence)
    rec = {"k": np.array([0]), "anchor": np.array([0]), "z": np.array([5.0]),
           "tag_in_kf": np.zeros((1, 3))}
    wheel = WheelRecords(k=[0], delta=[np.zeros(3)], cov=[np.eye(3) * 1e-4], index=[0])
    fac = noise_fit.fit_wheel_noise(Config(), gtsam.NonlinearFactorGraph(), gtsam.Values(),
                                    rec, None, 0.1, False, wheel)
    assert fac[0] == pytest.approx(expected, rel=0.05)
    assert fac[1] == pytest.approx(1.0)


@pytest.mark.parametrize(("curve", "expected", "origin_solved"), [
    (lambda u: -20.0 * (u - 5.6) ** 2, 2.0 ** (224.0 / 40.25), False),  # a peak at ~48x
    (lambda u: -20.0 * (u - 0.3) ** 2, 1.0, True),  # best at 1x: the configured noise
    (lambda u: -0.5 * (u - 1.0) ** 2, 1.0, True),  # 2x by less than the test's 1.92 nats
    (lambda u: 50.0 * u, None, False),  # still rising at the 256x edge: no verdict
], ids=["peak", "at-the-origin", "not-rejected", "rising-to-the-edge"])
def test_imu_noise_search_from_the_loose_edge(monkeypatch, curve, expected, origin_solved):
    """Test the one-factor noise search from the grid's top (256x), as the online IMU fit
    starts it: the parabola's vertex of a peak inside the grid (the hyperprior shifts it
    from 5.6 to 5.565 in log2), the configured noise where the evidence does not reject it,
    no verdict at the edge, and no solve at the origin where a concave evidence has
    already rejected it."""
    from uwbfuse.graph import noise_fit

    solved: list[float] = []

    def evidence(graph, initial, family, factors, max_iterations):
        solved.append(float(np.log2(factors[0])))
        return curve(solved[-1]), initial

    monkeypatch.setattr(noise_fit, "noise_log_evidence", evidence)
    family = noise_fit.NoiseFamily("imu", lambda graph, f: 0.0, 1, noise_fit.IMU_NOISE_MAX_LOG2,
                                   noise_fit.IMU_NOISE_TEST_NATS)
    out = noise_fit.fit_noise(gtsam.NonlinearFactorGraph(), gtsam.Values(), family, 5, (8.0,))
    if expected is None:
        assert out is None
    else:
        assert out[0] == pytest.approx(expected, rel=1e-3)
    assert (0.0 in solved) == origin_solved
    assert len(solved) == len(set(solved))  # every grid point solved once


def _understated_imu(factor: float) -> Config:
    """The default config with every `[imu]` noise density and bias random walk divided by
    `factor`: the simulated IMU is then `factor` times noisier than configured."""
    imu = Config().imu
    return Config(imu={"accel_noise_density": imu.accel_noise_density / factor,
                       "gyro_noise_density": imu.gyro_noise_density / factor,
                       "accel_bias_random_walk": imu.accel_bias_random_walk / factor,
                       "gyro_bias_random_walk": imu.gyro_bias_random_walk / factor})


def test_batch_fits_the_imu_noise_from_the_log(factory):
    """Test that batch keeps the configured IMU noise on a simulated IMU that follows it
    (white noise at the `[imu]` figures), loosens it by about the factor a configuration
    understates it by, and takes a number for `graph.imu_noise_inflation` as given.

    Measured (factory, seed 0, 30 s): 1.0 as configured, 10.7 with the noise understated
    8x."""
    clean = estimate(factory.log, Method.BATCH, Config()).report["batch"]
    assert clean["imu_noise_inflation"] < 1.6
    under = estimate(factory.log, Method.BATCH, _understated_imu(8.0)).report["batch"]
    assert 5.0 < under["imu_noise_inflation"] < 13.0
    fixed = Config(graph={"imu_noise_inflation": 3.0})
    assert "imu_noise_inflation" not in estimate(factory.log, Method.BATCH, fixed).report["batch"]


def test_isam2_fits_the_imu_noise_from_the_data_so_far(factory):
    """Test that the online graph starts its IMU factors loose (256x) and, from 10 s of
    keyframes on, takes the loosest inflation the evidence over the data received so far
    does not reject: near 1 where the IMU follows its configuration, near the factor it
    understates it by.

    Measured (factory, seed 0, 30 s): fits at graph ages 10 and 20 s, 1.39 and 2.16 as
    configured, 5.7 and 17.3 understated 8x (the most likely figures of the second window:
    2 and 11.5; in the first one, understated, 1x to 4x lie within 1 nat)."""
    for cfg, lo, hi in ((Config(), 1.0, 2.6), (_understated_imu(8.0), 4.0, 24.0)):
        online = estimate(factory.log, Method.ISAM2, cfg).report["online_imu_noise"]
        assert [f["graph_age_s"] >= 10.0 for f in online["fits"]] == [True, True]
        assert all(lo <= f["inflation"] <= hi for f in online["fits"]), online
        assert online["inflation"] == online["fits"][-1]["inflation"]
    fixed = Config(graph={"imu_noise_inflation": 3.0})
    online = estimate(factory.log, Method.ISAM2, fixed).report["online_imu_noise"]
    assert online == {"inflation": 3.0, "fits": []}


def _imu_noise_by_age(log: SensorLog, monkeypatch, config: Config | None = None
                      ) -> tuple[list[tuple[float, float, float]], dict]:
    """isam2 on `log` (default config): per keyframe interval, its first keyframe's graph
    age (s) and the inflations (gyroscope, accelerometer white noise, std) of its IMU factor;
    the report's online IMU noise fits."""
    from uwbfuse.graph.builder import GraphBuilder

    imu = Config().imu
    seen: list[tuple[float, float, float]] = []
    orig = GraphBuilder.next

    def next_(self):
        inc = orig(self)
        p = self.pim_params
        seen.append((self.stamp(self.k - 1),
                     np.sqrt(p.getGyroscopeCovariance()[0, 0]) / imu.gyro_noise_density,
                     np.sqrt(p.getAccelerometerCovariance()[0, 0]) / imu.accel_noise_density))
        return inc

    monkeypatch.setattr(GraphBuilder, "next", next_)
    return seen, estimate(log, Method.ISAM2, config or Config()).report["online_imu_noise"]


@pytest.mark.parametrize("lag", [5.0, 10.0])
def test_isam2_holds_the_gyroscope_against_wheel_slip_until_the_first_fit(factory,
                                                                           monkeypatch, lag):
    """Test that with wheels the online graph's IMU factors start loose (256x), keep the
    gyroscope's white noise at its configured density from GYRO_HOLD_AGE_S (5 s) after the
    start until the first noise fit, whatever the lag (at lag 10 one lag after the start
    was the first fit itself), and take the fitted inflation for both after it; without
    wheels the gyroscope stays with the rest (docs/results.md, "A wheel slip before the
    first IMU noise fit") and both start at 64x, not 256x: the IMU is then the only motion
    model (docs/results.md, "The online IMU noise without wheels starts at 64x")."""
    from uwbfuse.constants import GYRO_HOLD_AGE_S

    cfg = Config()
    cfg.graph.lag = lag
    seen, online = _imu_noise_by_age(factory.log, monkeypatch, cfg)
    first = online["fits"][0]["graph_age_s"]
    f = online["fits"][0]["inflation"]
    start = [(g, a) for t, g, a in seen if t < GYRO_HOLD_AGE_S]
    held = [(g, a) for t, g, a in seen if GYRO_HOLD_AGE_S <= t < first]
    after = [(g, a) for t, g, a in seen if first <= t < online["fits"][1]["graph_age_s"]]
    assert start and after
    assert len(held) >= 0.5 * (first - GYRO_HOLD_AGE_S) * cfg.graph.keyframe_rate
    assert np.allclose(start, 256.0)
    assert np.allclose([g for g, _ in held], 1.0) and np.allclose([a for _, a in held], 256.0)
    assert np.allclose(after, f)
    monkeypatch.undo()
    if lag != Config().graph.lag:
        return
    seen, online = _imu_noise_by_age(_drop(factory.log, "wheel"), monkeypatch)
    assert all(g == pytest.approx(a) for _, g, a in seen)
    first = online["fits"][0]["graph_age_s"]
    before = [a for t, _, a in seen if t < first]
    assert before and np.allclose(before, 64.0)
    assert np.allclose([a for t, _, a in seen if t >= first][:1], online["fits"][0]["inflation"])


@pytest.mark.parametrize(("curve", "expected_log2"), [
    # best 6; 7 falls 37.6 nats below it (with the hyperprior u^2 / 8)
    (lambda u: -20.0 * (u - 5.6) ** 2, 6.0 + 1.9205 / 37.625),
    # flat: 1x .. 4x within the 1.92 nats of the best (1x), 8x 3.375 nats below
    (lambda u: -0.25 * u**2, 2.0 + (1.9205 - 1.5) / (3.375 - 1.5)),
    (lambda u: 3.0 - 0.5 * (u - 1.0) ** 2 - 0.01 * u**4, None),  # crossing past 2^3
], ids=["peak", "flat", "three-steps"])
def test_online_imu_noise_takes_the_loosest_factor_the_evidence_allows(
        monkeypatch, curve, expected_log2):
    """Test that the online IMU fit takes the upper end of the evidence's likelihood
    interval: the loosest factor within 1.92 nats of the best grid point, linear between
    grid points, so that a window that cannot decide does not tighten the factors."""
    from uwbfuse.graph import noise_fit

    def evidence(graph, initial, family, factors, max_iterations):
        return curve(float(np.log2(factors[0]))), initial

    monkeypatch.setattr(noise_fit, "noise_log_evidence", evidence)
    family = noise_fit.NoiseFamily("imu", lambda graph, f: 0.0, 1, noise_fit.IMU_NOISE_MAX_LOG2,
                                   noise_fit.IMU_NOISE_TEST_NATS)
    out = noise_fit.fit_noise(gtsam.NonlinearFactorGraph(), gtsam.Values(), family, 5, (8.0,),
                              loosest=True)

    def with_prior(u: float) -> float:
        return curve(u) - u * u / 8.0

    grid = np.arange(0.0, 9.0)
    best = grid[np.argmax([with_prior(u) for u in grid])]
    floor = with_prior(best) - noise_fit.IMU_NOISE_TEST_NATS
    u = best
    while with_prior(u + 1.0) >= floor:
        u += 1.0
    crossing = u + (with_prior(u) - floor) / (with_prior(u) - with_prior(u + 1.0))
    assert np.log2(out[0]) == pytest.approx(crossing, abs=1e-9)
    if expected_log2 is not None:
        assert np.log2(out[0]) == pytest.approx(expected_log2, abs=0.02)


def test_online_ranges_are_classified_against_the_offset_nlos_cannot_make():
    """Test that the online graph judges a range LOS/NLOS against the negative part of its
    anchor's estimated offset only (NLOS only lengthens a range; a positive offset may be
    shared NLOS excess taken up), while batch's seeding pass, a graph that cannot tell
    the offset from the height, and a graph with a localiser's poses (which place the tag
    apart from the ranges) use the whole estimate."""
    from uwbfuse.graph.builder import GraphBuilder
    from uwbfuse.graph.imu import ImuBuffer
    from uwbfuse.graph.wheel import WheelTrack
    from uwbfuse.positioning.initialisation import InitialState
    from uwbfuse.streams import AnchorMap

    anchors = AnchorMap(ids=("a", "b", "c"), positions=np.array(
        [[0.0, 0, 2], [10.0, 0, 2], [0, 10.0, 2]]))
    start = InitialState(t_ns=0, position=np.zeros(3), R_map_base=np.eye(3),
                         velocity=np.zeros(3), gyro_bias=np.zeros(3), accel_bias=np.zeros(3),
                         position_sigma=0.1, yaw_sigma=0.1, still=False)
    a = np.array([0, 1, 2, 0])
    whole = [0.15, -0.08, 0.0, 0.15]
    # batch's seeding pass, and a free height with coplanar anchors (no wheels: the common
    # offset trades with the height), keep the whole estimate
    for seeding, streams, expected in (
            (False, {"wheel", "uwb"}, [0.0, -0.08, 0.0, 0.0]), (True, {"wheel", "uwb"}, whole),
            (False, {"imu", "uwb"}, whole), (False, {"wheel", "uwb", "pose"}, whole),
            (False, {"imu", "wheel", "uwb", "pose"}, whole)):
        b = GraphBuilder(Config(), anchors, frozenset(streams), start, ImuBuffer(),
                         WheelTrack(), record=seeding, seeding=seeding)
        b.range_bias[:] = [0.15, -0.08, 0.0]
        np.testing.assert_allclose(b.class_offset(a), expected)


@pytest.mark.slow
def test_isam2_calibrates_no_nlos_excess_into_the_range_offsets():
    """Test that isam2 on the NLOS-heavy racetrack (seed 3: every anchor blocked from 5 to
    40 s, then two in LOS until 80 s) tracks the LOS stretch: with its ranges classified
    against the estimated offsets, the offsets took up ~0.15 m of shared excess in the
    blocked start, the LOS anchors' ranges then passed for NLOS and the stretch was 0.27 m
    off (RMS over 50-85 s; the causal batch ~0.04 m at its cut epochs). Measured 0.040 m."""
    sim = simulate_with_truth("warehouse-nlos", 120.0, 3)
    log = sim.log
    res = estimate(log, Method.ISAM2, Config(), covariance=False)
    traj = res.trajectory
    t0 = int(log.ranges.t_ns[0])
    sel = (traj.t_ns >= t0 + 50 * NS_PER_S) & (traj.t_ns <= t0 + 85 * NS_PER_S)
    gt = log.ground_truth
    g = np.column_stack([np.interp(traj.t_ns[sel], gt.t_ns, gt.position[:, k])
                         for k in range(2)])
    err = np.linalg.norm(traj.position[sel, :2] - g, axis=1)
    assert np.sqrt(np.mean(err**2)) < 0.12
    # no anchor offset ends up holding the excess (truth 0; measured 0.00-0.05 m, against
    # 0.13-0.16 m when classified against the whole estimate)
    bias = [v["bias_m"] for v in res.report["anchors"].values()]
    assert max(bias) < 0.1


def test_keyframes_per_update_solves_every_keyframe_only_under_an_imu_alone():
    """Test `graph.update_every = "auto"`: 1 keyframe per iSAM2 update where an IMU without
    wheels predicts between updates, 3 with wheels or without IMU, and a number as set."""
    from uwbfuse.config import GraphConfig
    from uwbfuse.graph.estimator import keyframes_per_update

    auto = GraphConfig()
    assert keyframes_per_update(auto, frozenset({"uwb", "imu"})) == 1
    assert keyframes_per_update(auto, frozenset({"uwb", "imu", "pose"})) == 1
    assert keyframes_per_update(auto, frozenset({"uwb", "imu", "wheel"})) == 3
    assert keyframes_per_update(auto, frozenset({"uwb"})) == 3
    assert keyframes_per_update(GraphConfig(update_every=2), frozenset({"uwb", "imu"})) == 2
    with pytest.raises(ValueError):
        GraphConfig(update_every=0)


def test_imu_and_uwb_without_wheels_gain_from_solving_every_keyframe():
    """Test that on an IMU + UWB log (no wheels) the default (every keyframe solved) beats
    three keyframes per update, whose output in between is an IMU prediction from the
    newest solved keyframe (measured, room seed 0, 60 s: 0.026 against 0.030 m since session
    41's start velocity fix, 0.034 m before it; seeds 1, 2 0.031 / 0.034, 0.036 / 0.037
    before it. Before session 39's start fix, whose 0.9 m start error
    every keyframe solved took out faster: 0.067 against 0.136 m)."""
    log = _drop(simulate("room", 60.0, 0), "wheel")
    auto = estimate(log, Method.ISAM2, Config(), covariance=False)
    three = estimate(log, Method.ISAM2, Config(graph={"update_every": 3}), covariance=False)
    assert _ate(auto.trajectory, log) < 0.9 * _ate(three.trajectory, log)


def _class_flips(rc) -> int:
    """LOS/NLOS changes along each anchor's ranges (time order) of `RangeClasses`."""
    flips = 0
    for a in np.unique(rc.anchor):
        sel = rc.anchor == a
        cls = rc.p_nlos[sel][np.argsort(rc.t_ns[sel], kind="stable")] > 0.5
        flips += int(np.count_nonzero(cls[1:] != cls[:-1]))
    return flips


def test_nlos_switch_time_sets_how_long_the_online_classes_persist():
    """Test that `[nlos] switch_time` reaches isam2's LOS/NLOS chain: on a heavy-NLOS log,
    a chain that forgets in 0.02 s (about memoryless at 10 ranges per anchor per second)
    changes its ranges' classes more often than the default 2 s one, and one that holds for
    a minute less often."""
    log = simulate("warehouse-nlos", 40.0, 0)
    flips = {}
    for st in (0.02, 2.0, 60.0):
        cfg = Config.model_validate({"nlos": {"switch_time": st}})
        res = estimate(log, Method.ISAM2, cfg, covariance=False)
        assert res.range_classes is not None
        flips[st] = _class_flips(res.range_classes)
    assert flips[0.02] > flips[2.0] > flips[60.0], flips


def test_review_search_holds_an_adopted_hypothesis_and_looks_at_its_span_only(monkeypatch):
    """Test the online review's LOS/NLOS search (`_search_switch`): a better hypothesis is
    adopted after SEARCH_PERSIST reviews in a row (the ranges of the span against its
    shifted track), is held while the search still finds it the best once it is the
    current classes (without a hold, EM against the unshifted track reverted it at the
    next review and the search re-adopted it three reviews later, a limit cycle:
    docs/results.md, session 40), is let go when another is best, and never touches the
    ranges outside the span."""
    from types import SimpleNamespace

    from uwbfuse.constants import SEARCH_PERSIST
    from uwbfuse.graph import estimator as est_mod
    from uwbfuse.graph.uwb import LosHypothesis
    from uwbfuse.nlos import NlosModel
    from uwbfuse.streams import AnchorMap

    anchors = AnchorMap(("a", "b"), np.array([[0.0, 0.0, 2.0], [10.0, 0.0, 2.0]]))
    est = est_mod.make(Method.ISAM2, Config(), anchors, frozenset({"uwb"}))
    mix = NlosModel.from_config(Config())
    n = 8
    anchor = np.arange(n) % 2
    p = np.column_stack([np.full(n, 5.0), np.full(n, 3.0), np.full(n, 2.0)])
    h = np.linalg.norm(p - anchors.positions[anchor], axis=1)
    r_los, r_nlos = np.full(n, 0.2), np.full(n, -0.1)
    span = np.arange(n) >= 4  # the newest four ranges
    u = (p - anchors.positions[anchor])[:, :2] / h[:, None]
    delta = np.array([0.1, -0.05])
    ids = np.array([0, 1])
    los_b = np.array([True, False])  # anchor b NLOS with a 0.25 m excess

    def hyp(current: list[bool], los: np.ndarray = los_b, gain: float = 20.0):
        return LosHypothesis(ids, los, np.array(current), delta,
                             np.where(los, 0.0, 0.25), gain)

    seen: list[int] = []
    script = iter([hyp([True, True])] * SEARCH_PERSIST            # better: adopted on the 3rd
                  + [hyp([True, False], gain=0.0)]                # adopted, now current: held
                  + [hyp([True, True], np.array([True, True]), 0.0)])  # another best: let go

    def search(a, r, u_, g, model, moment=True, weights=None):
        seen.append(len(a))
        assert weights is not None and len(weights) == len(a)
        return next(script)

    monkeypatch.setattr(est_mod, "los_subset_search", search)
    b = SimpleNamespace(range_bias=np.zeros(2))
    out = [est._search_switch(b, mix, anchor, p, h, r_los, r_nlos, np.zeros(n), span,
                              np.ones(n))
           for _ in range(SEARCH_PERSIST + 2)]
    assert seen == [4] * len(out)
    shifted = r_los[span] - u[span] @ delta
    for i, (rl, rn) in enumerate(out):
        np.testing.assert_array_equal(rl[~span], r_los[~span])
        np.testing.assert_array_equal(rn[~span], r_nlos[~span])
        if i in (SEARCH_PERSIST - 1, SEARCH_PERSIST):  # adopted, then held
            np.testing.assert_allclose(rl[span], shifted)
            np.testing.assert_allclose(rn[span], shifted - np.where(anchor[span] == 1,
                                                                    0.25, mix.mu_nlos))
        else:
            np.testing.assert_array_equal(rl, r_los)
            np.testing.assert_array_equal(rn, r_nlos)


def test_review_search_span_does_not_grow_with_the_lag(monkeypatch):
    """Test that the review's LOS/NLOS search looks at the ranges of the anchors' mean time
    between class changes (`NlosModel.class_change_time`), not at the whole lag window: at
    lag 10 it took twice the lag-5 window, where one class per anchor and one rigid shift
    held too seldom (docs/results.md, session 40)."""
    from uwbfuse.graph import estimator as est_mod

    log = simulate_with_truth("warehouse", 30.0, 0).log
    orig = est_mod.los_subset_search
    sizes: dict[float, list[int]] = {}

    for lag in (5.0, 10.0):
        seen = sizes.setdefault(lag, [])

        def search(a, *args, seen=seen, **kwargs):
            seen.append(len(a))
            return orig(a, *args, **kwargs)

        monkeypatch.setattr(est_mod, "los_subset_search", search)
        cfg = Config()
        cfg.graph.lag = lag
        estimate(log, Method.ISAM2, cfg, covariance=False)
    assert sizes[5.0] and sizes[10.0]
    # the window has filled by mid-log at either lag: the late searches' sizes
    late5, late10 = np.median(sizes[5.0][-20:]), np.median(sizes[10.0][-20:])
    assert late10 < 1.4 * late5
