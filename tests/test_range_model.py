# SPDX-License-Identifier: BSD-3-Clause
"""Batch's choice of range error model by held-out prediction (`graph.range_model`)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import integrate

from tests.helpers import real
from uwbfuse.config import Config, load_config
from uwbfuse.estimator import Method
from uwbfuse.eval.evaluate import evaluate
from uwbfuse.graph.uwb import huber_log_density
from uwbfuse.io.reader import read_log
from uwbfuse.io.tum import read_tum
from uwbfuse.pipeline import estimate
from uwbfuse.sim.simulator import simulate_with_truth
from uwbfuse.streams import NS_PER_S

offline = pytest.importorskip("uwbfuse.graph.offline")


def test_heldout_phases_partition_the_log_after_its_first_stretch():
    """Test that the eight phases hold out disjoint eighths covering every stretch but the
    first (the start keeps its ranges)."""
    t0 = 1_700_000_000 * NS_PER_S
    t = t0 + np.arange(0, 200 * NS_PER_S, NS_PER_S // 10, dtype=np.int64)
    masks = np.array([offline.heldout_mask(t, t0, p) for p in offline.HELDOUT_PHASES])
    assert sorted(offline.HELDOUT_PHASES) == list(range(offline.HELDOUT_EVERY))
    assert np.all(masks.sum(axis=0) <= 1)
    first = (t - t0) < offline.HELDOUT_BLOCK_S * NS_PER_S
    assert not np.any(masks[:, first])
    assert np.all(masks.sum(axis=0)[~first] == 1)
    share = masks.mean(axis=1)
    assert np.all(np.abs(share - 1 / offline.HELDOUT_EVERY) < 0.02)


@pytest.mark.parametrize("k", [0.5, 1.345, 3.0])
def test_huber_density_is_normalised(k):
    """Test that the robust model's predictive density integrates to one."""
    total, _ = integrate.quad(lambda r: np.exp(huber_log_density(np.array([r]), 0.07, k)[0]),
                              -5, 5, points=[-k * 0.07, 0.0, k * 0.07], limit=200)
    assert total == pytest.approx(1.0, abs=1e-6)


def test_labyrinth_real_radios_choose_the_robust_model():
    """Test that on the real Labyrinth log (a common ~0.1 m range offset, no persistent
    NLOS) the held-out ranges favour the robust model, which calibrates the offset instead
    of reading it as NLOS excess. Measured: robust 0.881 against mixture 0.753 nats per
    range, 2-D ATE 0.057 m (the mixture alone 0.086 m)."""
    cfg = load_config(real("labyrinth/config.toml"))
    log = read_log(real("labyrinth/labyrinth.mcap"), cfg)
    res = estimate(log, Method.BATCH, cfg)
    batch = res.report["batch"]
    assert batch["range_model"].startswith("robust")
    assert batch["heldout_log_score"]["robust"] > batch["heldout_log_score"]["mixture"]
    ev = evaluate(res.trajectory, read_tum(real("labyrinth/gt.tum")), max_dt=0.1)
    assert ev.ate_2d.rmse < 0.07
    biases = [a["bias_m"] for a in res.report["anchors"].values()]
    assert np.median(biases) > 0.06  # the radios read about 0.1 m long


@pytest.mark.slow
def test_heavy_nlos_simulation_chooses_the_mixture():
    """Test that under heavy, persistent NLOS (simulated warehouse-nlos) the held-out
    ranges favour the LOS/NLOS mixture, and that the choice costs nothing there."""
    sim = simulate_with_truth("warehouse-nlos", 60.0, 0)
    auto = estimate(sim.log, Method.BATCH, Config())
    chosen = auto.report["batch"]["range_model"]
    assert chosen.startswith("mixture")
    mixture = estimate(sim.log, Method.BATCH, Config(graph={"range_model": chosen}))
    gt = sim.log.ground_truth
    a = evaluate(auto.trajectory, gt, max_dt=0.02).ate_2d.rmse
    m = evaluate(mixture.trajectory, gt, max_dt=0.02).ate_2d.rmse
    # (0.1 mm: the wheel time offset is fitted from each run's own online pass)
    assert a == pytest.approx(m, abs=1e-4)


def test_a_configured_range_model_is_fitted_without_the_choice():
    """Test that `graph.range_model = "robust"` fits the robust model alone (no held-out
    scores) and weights the online pass's ranges by it too."""
    cfg = load_config(real("labyrinth/config.toml"))
    cfg = cfg.model_copy(update={"graph": cfg.graph.model_copy(update={"range_model": "robust"})})
    log = read_log(real("labyrinth/labyrinth.mcap"), cfg)
    res = estimate(log, Method.BATCH, cfg)
    assert res.report["batch"]["range_model"] == "robust"
    assert res.report["batch"]["heldout_log_score"] is None
    assert res.report["online_range_model"]["model"] == "robust"
    assert all(a["nlos"] == 0 for a in res.report["anchors"].values())


def _choice_case(gain: float, spread: float, seed: int = 0) -> tuple[dict, np.ndarray]:
    """Held-out scores of three candidates on 40 stretches of 10 ranges: the calibrated
    mixture `gain` nats per range over the mixture, whose per-stretch differences spread
    by `spread`; the robust model 0.05 below the mixture."""
    rng = np.random.default_rng(seed)
    block = np.repeat(np.arange(40), 10)
    mix = rng.normal(1.0, 0.5, len(block))
    cal = mix + gain + rng.normal(0.0, spread, 40)[block]
    return {"mixture": mix, "mixture, calibrated": cal, "robust": mix - 0.05}, block


def test_the_calibrated_mixture_must_beat_the_mixture_by_one_standard_error():
    """Test the one-standard-error rule of the held-out choice: the calibrated mixture
    (a refinement of the mixture) is chosen for a gain well beyond the stretches' spread,
    not for one inside it, and then the best of the others wins."""
    models = list(offline.RANGE_MODELS[:3])
    score, block = _choice_case(gain=0.2, spread=0.1)
    assert offline._one_se_choice(models, score, block).name == "mixture, calibrated"
    score, block = _choice_case(gain=0.01, spread=0.3)
    assert np.mean(score["mixture, calibrated"]) > np.mean(score["mixture"])
    assert offline._one_se_choice(models, score, block).name == "mixture"
    score["robust"] = score["mixture"] + 0.005
    assert offline._one_se_choice(models, score, block).name == "robust"


def test_clustered_standard_error_counts_a_stretch_once():
    """Test that ranges sharing a stretch count as one sample: ten identical copies of
    each of 30 values give the error of 30 samples, not of 300."""
    x = np.random.default_rng(1).normal(0.0, 1.0, 30)
    mean, se = offline.clustered_mean_se(np.repeat(x, 10), np.repeat(np.arange(30), 10))
    assert mean == pytest.approx(np.mean(x))
    assert se == pytest.approx(np.std(x, ddof=1) / np.sqrt(30), rel=1e-9)
    assert offline.clustered_mean_se(x, np.zeros(30))[1] == np.inf


def test_the_calibrated_mixture_recovers_constant_anchor_offsets():
    """Test that on a simulated room whose radios read up to 0.15 m long or short
    (constant per anchor), the calibrated mixture finds each anchor's offset where the
    mixture (EM with the offsets held at zero until its last round) lacks part of it, and
    tracks better."""
    sim = simulate_with_truth("room", 60.0, 0, anchor_offset_max=0.15)
    gt = sim.log.ground_truth
    out = {}
    for name in ("mixture", "mixture, calibrated"):
        res = estimate(sim.log, Method.BATCH, Config(graph={"range_model": name}))
        bias = np.array([a["bias_m"] for a in res.report["anchors"].values()])
        err = (bias - bias.mean()) - (sim.anchor_offset - sim.anchor_offset.mean())
        out[name] = (np.sqrt(np.mean(err**2)),
                     evaluate(res.trajectory, gt, max_dt=0.02).ate_2d.rmse)
    (off_mix, ate_mix), (off_cal, ate_cal) = out["mixture"], out["mixture, calibrated"]
    assert off_cal < 0.6 * off_mix
    assert ate_cal < ate_mix


# the room's anchors on one tilted plane (A1, A3 at 0.5 m, A2, A4 at 2.6 m): coplanar too
TILTED = {"anchors": (("A1", (0.0, 0.0, 0.5)), ("A2", (0.0, 6.0, 2.6)),
                      ("A3", (5.0, 0.0, 0.5)), ("A4", (5.0, 6.0, 2.6)))}
PLANES = pytest.mark.parametrize("site", [{}, TILTED], ids=["level", "tilted"])


@PLANES
def test_uwb_only_coplanar_anchors_keep_the_robust_model_out(site):
    """Test that where the height is free and the anchors coplanar (a UWB-only room, its
    anchors level or on one tilted plane), the robust candidates, whose per-anchor offsets
    are free from the start, are not fitted: between them the offsets trade against the
    height there, which no held-out range shows. The two mixtures are."""
    log = simulate_with_truth("room", 30.0, 0, streams=("uwb",), **site).log
    res = estimate(log, Method.BATCH, Config(), covariance=False)
    assert set(res.report["batch"]["heldout_log_score"]) == {"mixture", "mixture, calibrated"}


@PLANES
@pytest.mark.parametrize("method", [Method.ISAM2, Method.BATCH])
def test_uwb_only_coplanar_anchors_hold_the_common_offset(method, site):
    """Test that where the height is free and the anchors coplanar (a UWB-only room whose
    radios have no offsets, its anchors level or on one tilted plane), the common range
    offset is held at zero: each anchor's reported offset stays within a few centimetres
    and the height near the truth, where a free common offset drifted with the height
    (0.25 m and 0.48 m too high online)."""
    sim = simulate_with_truth("room", 30.0, 0, streams=("uwb",), **site)
    res = estimate(sim.log, method, Config(), covariance=False)
    offsets = np.array([a["bias_m"] for a in res.report["anchors"].values()])
    assert np.all(np.abs(offsets) < 0.05), offsets
    gt = sim.log.ground_truth
    traj = res.trajectory
    i = np.clip(np.searchsorted(gt.t_ns, traj.t_ns), 0, len(gt.t_ns) - 1)
    dz = traj.position[:, 2] - gt.position[i, 2]
    assert abs(float(np.mean(dz))) < 0.05, float(np.mean(dz))
