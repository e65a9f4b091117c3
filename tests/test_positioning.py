# SPDX-License-Identifier: BSD-3-Clause
"""Multilateration, NLOS weighting and NLOS calibration (uwbfuse.positioning)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from tests.synth_positioning import ROOM
from uwbfuse.config import Config, RobustKernel
from uwbfuse.nlos import NlosModel, NlosParams, nlos_probability
from uwbfuse.positioning.multilateration import (
    anchor_plane,
    epochs_by_window,
    gauss_newton,
    group_epochs,
    linear_ls,
    multilaterate,
    off_plane_spread,
    project_ranges,
    robust_weights,
    select_nearest,
)
from uwbfuse.positioning.nlos_weighting import calibrate_nlos, weighted_fix
from uwbfuse.positioning.start import anchors_observe_height
from uwbfuse.streams import AnchorMap

A3D = np.vstack([ROOM.positions, [[2.5, 3.0, 3.0]]])  # one anchor off the plane
# the room's anchors on one plane tilted about x: A1, A3 at 0.5 m, A2, A4 at 2.6 m (and the
# plane tilted the other way); TWISTED: the same heights crossed over, on no plane
_H = {"up": (0.5, 2.6, 0.5, 2.6), "down": (2.6, 0.5, 2.6, 0.5), "twisted": (0.5, 2.6, 2.6, 0.5)}
TILTED, TILTED_DOWN, TWISTED = (np.column_stack([ROOM.positions[:, :2], h])
                                for h in _H.values())


def _points(n: int, z: float | None = 0.3, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    zz = np.full(n, z) if z is not None else rng.uniform(0.0, 1.2, n)
    return np.column_stack([rng.uniform(0.2, 4.8, n), rng.uniform(0.2, 5.8, n), zz])


def _ranges(p: np.ndarray, anchors: np.ndarray) -> np.ndarray:
    return np.linalg.norm(p[:, None, :] - anchors[None, :, :], axis=2)


def test_linear_ls_exact_3d() -> None:
    """test that Qiu eq. 3-6 recovers 3-D positions exactly from noiseless ranges"""
    p = _points(40, z=None)
    x, ok = linear_ls(A3D, _ranges(p, A3D))
    assert ok.all()
    np.testing.assert_allclose(x, p, atol=1e-9)


def test_height_projection_2d_exact() -> None:
    """test that 2-D fixes with anchor height projection are exact at the known tag height"""
    p = _points(40, z=0.3)
    r = _ranges(p, ROOM.positions)
    d = project_ranges(r, ROOM.positions[:, 2], 0.3)
    xy, ok = linear_ls(ROOM.positions[:, :2], d)
    assert ok.all()
    np.testing.assert_allclose(xy, p[:, :2], atol=1e-9)
    fx = multilaterate(ROOM.positions, r, dim=2, tag_z=0.3)
    assert fx.ok.all()
    np.testing.assert_allclose(fx.position, p, atol=1e-9)


@pytest.mark.parametrize("anchors", [A3D, ROOM.positions], ids=["non-coplanar", "coplanar"])
def test_gauss_newton_exact_3d(anchors: np.ndarray) -> None:
    """test that the robust 3-D solve is exact (coplanar anchors: the solution below them)"""
    p = _points(30, z=None, seed=1)
    fx = multilaterate(anchors, _ranges(p, anchors), dim=3)
    assert fx.ok.all()
    np.testing.assert_allclose(fx.position, p, atol=1e-6)
    assert np.all(fx.dop > 0) and np.all(np.isfinite(fx.cov))


@pytest.mark.parametrize(
    ("anchors", "level", "coplanar"),
    [(ROOM.positions, True, True),
     (ROOM.positions + np.outer([0.1, -0.1, 0.05, 0.0], [0, 0, 1]), True, True),
     (TILTED, False, True), (TILTED_DOWN, False, True),
     (TILTED + np.outer([0.05, -0.05, -0.05, 0.05], [0, 0, 1]), False, True),
     (TWISTED, None, False), (A3D, None, False)],
    ids=["level", "level-within-spread", "tilted", "tilted-down", "tilted-within-spread",
         "twisted", "one-off-the-plane"])
def test_anchor_plane_is_a_plane_test(anchors: np.ndarray, level: bool | None,
                                      coplanar: bool) -> None:
    """test that coplanarity is a plane test: level and tilted planes (within
    COPLANAR_SPREAD) are planes, the normal points up and is normal to every anchor
    difference; crossed-over heights and an anchor 1.5 m off the plane are not"""
    plane = anchor_plane(anchors)
    assert (plane is not None) == coplanar
    if plane is None:
        return
    assert plane.level == level
    np.testing.assert_allclose(plane.axes @ plane.axes.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(plane.axes) == pytest.approx(1.0)
    assert plane.axes[2, 2] > 0.0  # the floor is on the normal's negative side
    if not level:
        offsets = (anchors - plane.origin) @ plane.axes[2]
        assert np.ptp(offsets) < 0.3


@pytest.mark.parametrize(("anchors", "observe"),
                         [(ROOM.positions, False), (TILTED, False), (TILTED_DOWN, False),
                          (TWISTED, True), (A3D, True)],
                         ids=["level", "tilted", "tilted-down", "twisted", "one-off-the-plane"])
def test_height_is_observed_off_a_plane_only(anchors: np.ndarray, observe: bool) -> None:
    """test that anchors observe the tag's height apart from a common range offset only when
    they spread off every plane, not when their heights differ on one tilted plane"""
    assert (off_plane_spread(anchors) >= 1.0) == observe
    assert anchors_observe_height(anchors) == observe


@pytest.mark.parametrize("anchors", [TILTED, TILTED_DOWN], ids=["tilted", "tilted-down"])
def test_tilted_plane_fix_takes_the_floor_side_not_the_mirror(anchors: np.ndarray) -> None:
    """test that a 3-D fix with the anchors on one tilted plane, whose 3-D linear system is
    singular, is found on the floor's side of the plane: its mirror image across the plane
    has the same ranges and is at least 0.7 m away"""
    p = _points(30, z=None, seed=2) * [1.0, 1.0, 0.1]  # tags at 0-0.12 m, near the floor
    r = _ranges(p, anchors)
    _, ok = linear_ls(anchors, r)
    assert not ok.any()  # all four anchor differences lie in the plane
    plane = anchor_plane(anchors)
    assert plane is not None
    n = plane.axes[2]
    mirror = p - 2.0 * ((p - plane.origin) @ n)[:, None] * n
    np.testing.assert_allclose(_ranges(mirror, anchors), r, atol=1e-9)
    assert np.all(np.linalg.norm(mirror - p, axis=1) > 0.7)
    fx = multilaterate(anchors, r, dim=3)
    assert fx.ok.all()
    np.testing.assert_allclose(fx.position, p, atol=1e-6)
    noisy = multilaterate(anchors, r + np.random.default_rng(3).normal(0.0, 0.05, r.shape))
    assert noisy.ok.all()
    assert np.all(np.linalg.norm(noisy.position - p, axis=1) < 0.5)


def test_huber_refinement_resists_one_outlier() -> None:
    """test that IRLS Huber Gauss-Newton beats the linear solution with one gross outlier"""
    p = _points(50, z=None, seed=2)
    r = _ranges(p, A3D) + np.random.default_rng(3).normal(0, 0.02, (50, 5))
    r[:, 4] += 1.5
    lin, _ = linear_ls(A3D, r)
    fx = gauss_newton(A3D, r, lin, 0.05, dim=3, kernel=RobustKernel.CAUCHY, threshold=2.0,
                      iterations=30)
    e_lin = np.linalg.norm(lin - p, axis=1)
    e_gn = np.linalg.norm(fx.position - p, axis=1)
    assert np.median(e_gn) < 0.5 * np.median(e_lin)


def test_too_few_ranges_is_degenerate() -> None:
    """test that an epoch with two ranges gives a degenerate fix, not numbers"""
    p = np.array([[3.0, 2.0, 0.3]])
    two = _ranges(p, ROOM.positions)
    two[0, 2:] = np.nan
    fx = multilaterate(ROOM.positions, two, dim=2, tag_z=0.3)
    assert fx.degenerate[0] and not fx.ok[0]


def test_collinear_anchors_linear_step_fails() -> None:
    """test that the linear system reports failure for collinear anchors in 2-D"""
    line = np.array([[0, 0], [5, 0], [10, 0]], dtype=float)
    _, ok = linear_ls(line, np.array([[3.6, 2.8, 7.3]]))
    assert not ok[0]


def test_nearest_three_mask() -> None:
    """test that nearest-three keeps the three shortest finite ranges of each epoch"""
    r = np.array([[4.0, 1.0, np.nan, 2.0, 3.0], [1.0, 2.0, 3.0, np.nan, np.nan]])
    m = select_nearest(r, 3)
    assert m.tolist() == [[False, True, False, True, True], [True, True, True, False, False]]


def test_robust_weights_shapes() -> None:
    """test that every kernel gives weight 1 at zero and downweights large residuals"""
    u = np.array([0.0, 10.0])
    for k in RobustKernel:
        w = robust_weights(u, k, 1.345)
        assert w[0] == pytest.approx(1.0)
        if k is not RobustKernel.NONE:
            assert w[1] < 0.2


def test_group_epochs_latest_per_anchor_in_window() -> None:
    """test that an epoch takes the latest range per anchor inside (t - window, t]"""
    t = np.array([0, 10, 20, 30, 40], dtype=np.int64) * 1_000_000
    a = np.array([0, 1, 0, 2, 1], dtype=np.int32)
    r = np.array([1.0, 2.0, 3.0, 4.0, 5.0])
    grid, stamps = group_epochs(t, a, r, 3, np.array([35_000_000, 45_000_000]), 20_000_000)
    np.testing.assert_array_equal(grid, [[3.0, np.nan, 4.0], [np.nan, 5.0, 4.0]])
    assert stamps[1].tolist() == [-1, 40_000_000, 30_000_000]
    ep = epochs_by_window(t, 25_000_000)
    assert ep.tolist() == [20_000_000, 40_000_000]


def test_nlos_probability_increases_with_residual() -> None:
    """test that the posterior NLOS probability rises with a positive residual"""
    res = np.array([[-0.05, 0.0, 0.05, 0.2, 0.5]])
    p = nlos_probability(res, np.full(5, 0.026), np.full(5, 0.114), np.full(5, 0.145),
                         np.full(5, 0.2))
    assert np.all(np.diff(p[0, 1:]) > 0)
    assert p[0, 1] < 0.2 < p[0, 3]


# Qiu et al. 2022, Table 2: static points in the 6 m x 5 m room of Table 1 (north, east).
QIU_POINTS = [(0.6, 0.6), (0.6, 0.27), (0.6, 4.8), (1.8, 4.8), (3.0, 4.8)]


@pytest.mark.parametrize("point", QIU_POINTS)
def test_weighted_ls_beats_plain_ls_on_nlos_ranges(point: tuple[float, float]) -> None:
    """test that NLOS-weighted LS (eq. 10-11) has a lower RMSE than plain LS (eq. 6) when the
    farthest anchor is NLOS with N(0.114, 0.145) and LOS noise is N(0, 0.026) (Qiu 5.1)"""
    anchors = AnchorMap(("1", "2", "3", "4"), ROOM.positions)
    rng = np.random.default_rng(42)
    p = np.array([point[0], point[1], 0.3])
    n = 200
    true = np.linalg.norm(p - anchors.positions, axis=1)
    r = true + rng.normal(0, 0.026, (n, 4))
    far = int(np.argmax(true))
    r[:, far] += rng.normal(0.114, 0.145, n)
    plain, _ = linear_ls(anchors.positions[:, :2], project_ranges(r, anchors.positions[:, 2], 0.3))
    base = NlosModel.from_config(Config())
    # The calibrated model of Qiu: the obstructed anchor has a high NLOS probability.
    per = {anchors.ids[far]: NlosParams(0.026, 0.114, 0.145, 0.95)}
    model = replace(base, per_anchor=per)
    wf = weighted_fix(anchors, r, model, dim=2, tag_z=0.3)
    rmse_plain = np.sqrt(np.mean(np.sum((plain - p[:2]) ** 2, axis=1)))
    rmse_w = np.sqrt(np.mean(np.sum((wf.fixes.position[:, :2] - p[:2]) ** 2, axis=1)))
    # Measured: plain 0.12-0.19 m, weighted 0.033-0.035 m.
    assert rmse_w < 0.5 * rmse_plain
    assert rmse_w < 0.06


def test_calibrate_nlos_recovers_simulated_distributions() -> None:
    """test that calibrate-nlos (eq. 8-9) recovers per-anchor NLOS mean and share"""
    from uwbfuse.sim.simulator import simulate_with_truth

    res = simulate_with_truth("warehouse-nlos", 90.0, 3)
    cfg = Config()
    model = calibrate_nlos(res.log, cfg)
    toml = model.per_range_toml()
    assert set(toml) == {"range_los_std", "range_nlos_mean", "range_nlos_std",
                         "range_nlos_prior", "anchor"}
    Config(nlos=toml)  # TOML-ready: validates as [nlos]
    rs = res.log.ranges
    assert rs is not None and res.log.anchors is not None
    good = ~res.outlier
    err = rs.range - res.true_range
    fitted = 0
    for i, aid in enumerate(res.log.anchors.ids):
        s = (rs.anchor == i) & good
        los = s & ~res.nlos
        nl = s & res.nlos
        par = model.per_anchor[aid]
        if los.sum() > 0.2 * s.sum():  # the LOS curve needs LOS ranges to be fitted
            assert par.los_std == pytest.approx(np.std(err[los]), abs=0.03)
        if par.nlos_std >= 2 * par.los_std and nl.sum() > 200 and par.nlos_mean != 0.114:
            fitted += 1
            assert par.nlos_mean == pytest.approx(np.mean(err[nl]), abs=0.07)
            assert par.nlos_prior == pytest.approx(nl.sum() / s.sum(), abs=0.2)
    assert fitted >= 2


def test_nlos_section_keys_change_the_weighted_fix() -> None:
    """test that the [nlos] per-range keys reach wls's weighting: with the NLOS excess of the
    obstructed anchor given as its mean and a high prior, the fix is closer to the truth
    than with a zero mean and zero prior (plain LOS weights)"""
    anchors = AnchorMap(("1", "2", "3", "4"), ROOM.positions)
    rng = np.random.default_rng(7)
    p = np.array([0.6, 0.6, 0.3])
    true = np.linalg.norm(p - anchors.positions, axis=1)
    r = true + rng.normal(0, 0.026, (200, 4))
    far = int(np.argmax(true))
    r[:, far] += 0.4 + rng.normal(0, 0.05, 200)
    informed = Config(nlos={"range_nlos_mean": 0.4, "range_nlos_std": 0.05,
                            "range_nlos_prior": 0.6})
    blind = Config(nlos={"range_nlos_mean": 0.0, "range_nlos_prior": 0.0})

    def rmse(cfg: Config) -> float:
        wf = weighted_fix(anchors, r, NlosModel.from_config(cfg), dim=2, tag_z=0.3)
        return float(np.sqrt(np.mean(np.sum((wf.fixes.position[:, :2] - p[:2]) ** 2,
                                            axis=1))))

    assert rmse(informed) < 0.5 * rmse(blind)
