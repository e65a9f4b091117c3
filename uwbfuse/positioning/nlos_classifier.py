# SPDX-License-Identifier: BSD-3-Clause
"""Learned NLOS classifier (patent CN114608572B steps S1-S2): a random forest on per-range
features, its labels from ground truth, and its model file.

Features, per range, all causal (from the range itself and what came before it):

- `residual`: measured range minus the distance from the anchor to a causal reference
  position of the tag; `residual_jump`: its change since the anchor's previous range;
- `range_jump`, `range_rate`: the change of the measured range since the anchor's previous
  range (m) and that change per second (m/s);
- `distance`: the measured range (m); `elevation`: the anchor's elevation angle seen from
  the reference position (rad);
- `fix_rms`: the RMS range residual of the reference fix (m: how consistent the epoch was);
- `residual_median`: the median residual of the anchor's last `HISTORY_RANGES` ranges
  (this one included): NLOS persists while the obstacle is in the way;
- with signal quality in the log: `rssi_dbm` (received total power), `rx_minus_fp_db`
  (total minus first-path power, dB; Decawave APS006: about 6 dB and more suggests NLOS)
  and its running median `rx_minus_fp_median` as `residual_median`.

The causal reference (the same at training and at run time, whatever the estimator): on
wheeled logs, `wheel_reference`: the wheel track placed in the map by a robust fit to the
ranges of the last seconds, the range's own anchor left out. Elsewhere (and on a wheeled
log before its first fit) the robust (Huber) multilateration fixes of the epochs that ended
before the range, with the geometry the `wls` method uses (2-D at the tag height for
wheeled logs; epochs as `wls` groups them), a constant-velocity line fitted to the last
`TRACK_FIXES` of them and evaluated at the range's stamp. It is an estimator-independent
stand-in for "the current prediction", so a model trained once serves `wls`, `ekf`, `ukf`
and the graph alike. Where no fix is younger than `MAX_REFERENCE_AGE_S` the position
features are NaN (the forest has learnt where missing values go).

Labels: a range is NLOS when |measured - true range| > `label_threshold` (default
`LABEL_THRESHOLD_M`), the true range from the ground-truth pose and `[extrinsics]
tag_in_base`.

Model file: skops (a zip of JSON and numpy arrays, never a pickle) holding a dict with the
format name, `FORMAT_VERSION`, the feature list, the label threshold and the forest; loading
refuses any type beyond `TRUSTED_TYPES`, another format or version and a feature list this
code does not compute (one-line `ConfigError`).
"""

from __future__ import annotations

import logging
import math
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from uwbfuse.config import Config, RobustKernel
from uwbfuse.constants import (
    EVIDENCE_WEIGHT,
    HISTORY_LONG,
    HISTORY_RANGES,
    LABEL_THRESHOLD_M,
    MAX_EVIDENCE_NATS,
    MAX_JUMP_GAP_S,
    MAX_REFERENCE_AGE_S,
    MIN_EPOCH_WINDOW_S,
    TRACK_FIXES,
)
from uwbfuse.errors import ConfigError, EstimatorError
from uwbfuse.positioning.multilateration import (
    default_tag_z,
    epoch_window_ns,
    epochs_by_window,
    group_epochs,
    multilaterate,
)
from uwbfuse.positioning.wheel_reference import wheel_reference
from uwbfuse.streams import NS_PER_S, AnchorMap, RangeStream, SensorLog, WheelStream

log = logging.getLogger(__name__)

F64 = NDArray[np.float64]

FORMAT = "uwbfuse-nlos-classifier"
FORMAT_VERSION = 2  # 2: wheeled logs' residuals against `wheel_reference` (1: the CV line)
# the only non-primitive type a forest's skops file holds (numpy arrays and the estimator
# classes of scikit-learn are trusted by skops itself)
TRUSTED_TYPES = ("sklearn.tree._tree.Tree",)

RESIDUAL_FEATURES = ("residual", "residual_jump", "range_jump", "range_rate", "distance",
                     "elevation", "fix_rms", "residual_median", "residual_median_long")
POWER_FEATURES = ("rssi_dbm", "rx_minus_fp_db", "rx_minus_fp_median", "rx_minus_fp_jump",
                  "fp_excess_db")
KNOWN_FEATURES = RESIDUAL_FEATURES + POWER_FEATURES



# ------------------------------------------------------------------------------ features
def _reference_fixes(
    ranges: RangeStream, anchors: AnchorMap, config: Config, planar: bool
) -> tuple[NDArray[np.int64], F64, NDArray[np.bool_], F64, float]:
    """Epoch times (K,), robust fixes (K,3) of the tag antenna (map frame), ok (K,),
    residual RMS (K,) m, and the tag height of 2-D fixes (m)."""
    wls = config.wls
    project = wls.height_projection == "on" or (wls.height_projection == "auto" and planar)
    if wls.tag_height != "auto":
        tag_z = float(wls.tag_height)
    elif project:
        tag_z = config.init.base_height + float(config.extrinsics.tag_in_base[2])
    else:
        tag_z = default_tag_z(anchors.positions)
    dim = 2 if project or len(anchors) < 4 else 3
    base = round(max(wls.window, MIN_EPOCH_WINDOW_S) * NS_PER_S)
    window = epoch_window_ns(ranges.t_ns, ranges.anchor, base)
    ep = epochs_by_window(ranges.t_ns, window)
    grid, _ = group_epochs(ranges.t_ns, ranges.anchor, ranges.range, len(anchors), ep, window)
    if not len(ep):
        return ep, np.zeros((0, 3)), np.zeros(0, bool), np.zeros(0), tag_z
    fx = multilaterate(anchors.positions, grid, dim=dim, tag_z=tag_z,
                       sigma=config.uwb.sigma, kernel=RobustKernel.HUBER, threshold=1.345)
    enough = np.count_nonzero(np.isfinite(grid), axis=1) >= dim + 1
    return ep, fx.position, fx.ok & enough, fx.residual_rms, tag_z


def _track_prediction(
    t: NDArray[np.int64], ep: NDArray[np.int64], pos: F64, good: NDArray[np.int64],
    j: NDArray[np.int64], has: NDArray[np.bool_],
) -> F64:
    """The tag position (N,3) at each range's stamp t from a constant-velocity line fitted
    to the last `TRACK_FIXES` usable fixes before it (within MAX_REFERENCE_AGE_S; their
    mean where they span no time); the latest fix where there is none before."""
    n = len(t)
    if not len(good):
        return np.zeros((n, 3))
    idx = np.maximum(j, 0)[:, None] - np.arange(TRACK_FIXES)[None, ::-1]
    valid = (idx >= 0) & has[:, None]
    gi = good[np.maximum(idx, 0)]
    tau = (ep[gi] - t[:, None]) / NS_PER_S  # s, <= 0
    valid &= tau >= -MAX_REFERENCE_AGE_S
    w = valid.astype(np.float64)
    p = pos[gi]  # (N, K, 3)
    s0, s1, s2 = w.sum(1), (w * tau).sum(1), (w * tau * tau).sum(1)
    sy = np.einsum("nk,nkc->nc", w, p)
    sty = np.einsum("nk,nkc->nc", w * tau, p)
    det = s0 * s2 - s1 * s1
    line = det > 1e-6 * np.maximum(s0, 1.0) ** 2
    with np.errstate(invalid="ignore", divide="ignore"):
        b = (s2[:, None] * sy - s1[:, None] * sty) / np.where(line, det, 1.0)[:, None]
        mean = sy / np.maximum(s0, 1.0)[:, None]
    out = np.where(line[:, None], b, mean)
    return np.where((s0 > 0)[:, None], out, pos[good[np.maximum(j, 0)]])


def _previous_same_anchor(t: NDArray[np.int64], a: NDArray[np.int32]) -> NDArray[np.int64]:
    """Index of each range's previous range from the same anchor (-1 for the first)."""
    order = np.lexsort((t, a))
    prev = np.full(len(t), -1, dtype=np.int64)
    same = a[order][1:] == a[order][:-1]
    prev[order[1:][same]] = order[:-1][same]
    return prev


def _running_median(v: F64, t: NDArray[np.int64], a: NDArray[np.int32], k: int) -> F64:
    """Per anchor, the nan-median of each value and the k - 1 values before it (causal)."""
    order = np.lexsort((t, a))
    vs, as_ = v[order], a[order]
    pad = np.full(k - 1, np.nan)
    out = np.empty(len(v))
    starts = np.flatnonzero(np.r_[True, as_[1:] != as_[:-1]])
    ends = np.r_[starts[1:], len(v)]
    for s0, e0 in zip(starts.tolist(), ends.tolist(), strict=True):  # one pass per anchor
        win = np.lib.stride_tricks.sliding_window_view(np.r_[pad, vs[s0:e0]], k)
        with warnings.catch_warnings():  # an all-NaN window gives NaN, as wanted
            warnings.simplefilter("ignore", RuntimeWarning)
            out[s0:e0] = np.nanmedian(win, axis=1)
    res = np.empty(len(v))
    res[order] = out
    return res


def range_features(
    ranges: RangeStream, anchors: AnchorMap, config: Config, planar: bool,
    wheel: WheelStream | None = None,
) -> tuple[F64, tuple[str, ...]]:
    """Features (N,F) of every range and their names (`RESIDUAL_FEATURES`, then
    `POWER_FEATURES` when the stream carries both powers). `planar`: a wheeled log (the
    reference fixes are 2-D at the tag height, as `wls` makes them); with `wheel` (a planar
    log's odometry) the reference is `wheel_reference`'s where it has one."""
    n = len(ranges)
    names = RESIDUAL_FEATURES
    with_power = ranges.rssi_dbm is not None and ranges.first_path_dbm is not None
    if with_power:
        names = names + POWER_FEATURES
    x = np.full((n, len(names)), np.nan)
    if n == 0:
        return x, names
    t, a, z = ranges.t_ns, ranges.anchor, ranges.range
    ep, pos, ok, rms, tag_z = _reference_fixes(ranges, anchors, config, planar)
    # the latest usable fix of an epoch that ended before each range
    good = np.flatnonzero(ok)
    j = np.searchsorted(ep[good], t, side="left") - 1 if len(good) else np.full(n, -1)
    has = j >= 0
    k = good[np.maximum(j, 0)] if len(good) else np.zeros(n, dtype=np.int64)
    has &= (t - ep[k]) <= round(MAX_REFERENCE_AGE_S * NS_PER_S)
    ref = _track_prediction(t, ep, pos, good, j, has)
    if wheel is not None and planar and len(wheel) and len(ep):
        dz = anchors.positions[a, 2] - tag_z
        d2 = np.sqrt(np.maximum(z * z - dz * dz, 0.0))  # horizontal distance, m
        wref, wok = wheel_reference(
            t, a, d2, anchors.positions[:, :2], wheel,
            np.asarray(config.extrinsics.tag_in_base[:2], np.float64), ep, pos[:, :2], ok,
            config.uwb.sigma)
        ref[wok] = np.column_stack([wref[wok], np.full(int(wok.sum()), tag_z)])
        has |= wok
    ap = anchors.positions[a]
    d = ap - ref
    pred = np.linalg.norm(d, axis=1)
    res = np.where(has, z - pred, np.nan)
    elev = np.where(has, np.arctan2(d[:, 2], np.hypot(d[:, 0], d[:, 1])), np.nan)
    prev = _previous_same_anchor(t, a)
    dt = np.where(prev >= 0, (t - t[np.maximum(prev, 0)]) / NS_PER_S, np.nan)
    recent = (prev >= 0) & (dt <= MAX_JUMP_GAP_S) & (dt > 0)
    jump = np.where(recent, z - z[np.maximum(prev, 0)], np.nan)
    with np.errstate(invalid="ignore", divide="ignore"):
        rate = np.where(recent, jump / np.where(recent, dt, 1.0), np.nan)
    res_jump = np.where(recent, res - res[np.maximum(prev, 0)], np.nan)
    cols = {"residual": res, "residual_jump": res_jump, "range_jump": jump,
            "range_rate": rate, "distance": z, "elevation": elev,
            "fix_rms": np.where(has, rms[k], np.nan),
            "residual_median": _running_median(res, t, a, HISTORY_RANGES),
            "residual_median_long": _running_median(res, t, a, HISTORY_LONG)}
    if with_power:
        assert ranges.rssi_dbm is not None and ranges.first_path_dbm is not None
        gap = ranges.rssi_dbm - ranges.first_path_dbm
        cols["rssi_dbm"] = ranges.rssi_dbm
        cols["rx_minus_fp_db"] = gap
        cols["rx_minus_fp_median"] = _running_median(gap, t, a, HISTORY_RANGES)
        cols["rx_minus_fp_jump"] = np.where(recent, gap - gap[np.maximum(prev, 0)], np.nan)
        # first-path power above free space (Friis, exponent 2) at the measured range: the
        # direct path of a LOS range follows it, an obstacle on that path takes dB off it
        cols["fp_excess_db"] = ranges.first_path_dbm + 20.0 * np.log10(np.maximum(z, 0.1))
    for i, name in enumerate(names):
        x[:, i] = cols[name]
    return x, names


def log_features(log: SensorLog, config: Config) -> tuple[F64, tuple[str, ...]]:
    """`range_features` of a log's ranges (planar when it has wheels)."""
    if log.ranges is None or log.anchors is None:
        raise EstimatorError(f"{log.source}: the NLOS classifier needs ranges and an anchor "
                             "map")
    return range_features(log.ranges, log.anchors, config, log.wheel is not None, log.wheel)


def range_labels(log: SensorLog, config: Config, threshold: float = LABEL_THRESHOLD_M
                 ) -> tuple[NDArray[np.int8], F64]:
    """Labels (N,) 1 = NLOS (|measured - true range| > threshold m), 0 = LOS, -1 = unknown
    (outside the ground truth's time span), and the errors (N,) m."""
    from uwbfuse.positioning.nlos_weighting import range_errors

    err, _ = range_errors(log, config)
    lab = np.where(np.isfinite(err), (np.abs(err) > threshold).astype(np.int8), -1)
    return lab.astype(np.int8), err


# --------------------------------------------------------------------------------- model
@dataclass
class NlosClassifier:
    """A trained forest and what it was made for: feature names, the label threshold (m)."""

    features: tuple[str, ...]
    forest: Any  # sklearn.ensemble.RandomForestClassifier
    label_threshold: float = LABEL_THRESHOLD_M
    info: dict[str, Any] = field(default_factory=dict)

    def predict(self, x: F64) -> F64:
        """P(NLOS) (N,) for features x (N,F) in `self.features` order."""
        if not len(x):
            return np.zeros(0)
        proba = self.forest.predict_proba(x)
        classes = list(self.forest.classes_)
        if 1 not in classes:
            return np.zeros(len(x))
        return np.asarray(proba[:, classes.index(1)], dtype=np.float64)

    def predict_log(self, log: SensorLog, config: Config) -> F64:
        """P(NLOS) of every range of `log`; a log without a feature the model needs (signal
        quality) is a ConfigError."""
        x, names = log_features(log, config)
        missing = [f for f in self.features if f not in names]
        if missing:
            raise ConfigError(
                f"{log.source}: the NLOS classifier was trained with {', '.join(missing)}, "
                "which this log's ranges do not carry (set [uwb] rssi_field and "
                "first_path_power_field, or train a model without them)")
        cols = [names.index(f) for f in self.features]
        return self.predict(x[:, cols])

    def save(self, path: str | Path) -> None:
        """Write the skops model file (atomically)."""
        import skops.io as sio

        from uwbfuse.errors import LogWriteError
        from uwbfuse.io.atomic import atomic_open

        obj = {"format": FORMAT, "version": FORMAT_VERSION, "features": list(self.features),
               "label_threshold_m": float(self.label_threshold), "info": dict(self.info),
               "forest": self.forest}
        data = sio.dumps(obj)
        with atomic_open(Path(path), "wb", error=LogWriteError, what="model") as f:
            f.write(data)


def train_classifier(
    x: F64, y: NDArray[np.integer], features: tuple[str, ...], *, n_trees: int = 100,
    min_leaf: int = 5, seed: int = 0, label_threshold: float = LABEL_THRESHOLD_M,
    info: dict[str, Any] | None = None,
) -> NlosClassifier:
    """Fit a random forest (scikit-learn) on features x (N,F) and labels y (N,) in {0, 1}."""
    from sklearn.ensemble import RandomForestClassifier

    forest = RandomForestClassifier(n_estimators=n_trees, min_samples_leaf=min_leaf,
                                    random_state=seed, n_jobs=1)
    forest.fit(x, y)
    return NlosClassifier(tuple(features), forest, label_threshold, dict(info or {}))


def load_classifier(path: str | Path) -> NlosClassifier:
    """Read a model file of `train-nlos`; ConfigError (one line) for a file that is not
    one (a pickle, a random file, another skops object), of another format version, or
    made for features this version does not compute."""
    import skops.io as sio

    p = Path(path)
    what = f"[nlos] classifier {p}"
    try:
        data = p.read_bytes()
    except OSError as e:
        raise ConfigError(f"{what}: cannot read the model file: {e.strerror or e}") from None
    try:
        untrusted = sio.get_untrusted_types(data=data)
    except Exception as e:  # not a zip, no schema: zipfile / json / key errors
        raise ConfigError(f"{what}: not an NLOS classifier model written by `uwbfuse "
                          f"train-nlos` ({type(e).__name__}: {_short(e)})") from None
    bad = [u for u in untrusted if u not in TRUSTED_TYPES]
    if bad:
        raise ConfigError(f"{what}: the file holds types a model never does "
                          f"({', '.join(bad[:3])}); refused")
    try:
        obj = sio.loads(data, trusted=list(untrusted))
    except Exception as e:  # a tampered or truncated archive
        raise ConfigError(f"{what}: unreadable model file ({type(e).__name__}: "
                          f"{_short(e)})") from None
    if not isinstance(obj, dict) or obj.get("format") != FORMAT:
        raise ConfigError(f"{what}: not an NLOS classifier model written by `uwbfuse "
                          "train-nlos`")
    if obj.get("version") != FORMAT_VERSION:
        raise ConfigError(f"{what}: model format version {obj.get('version')!r}, this "
                          f"uwbfuse reads version {FORMAT_VERSION}; train it again")
    feats = obj.get("features")
    if (not isinstance(feats, list) or not feats
            or not all(isinstance(f, str) and f in KNOWN_FEATURES for f in feats)
            or len(set(feats)) != len(feats)):
        raise ConfigError(f"{what}: made for other features ({_short(feats)}); this uwbfuse "
                          f"computes {', '.join(KNOWN_FEATURES)}")
    forest = obj.get("forest")
    from sklearn.ensemble import RandomForestClassifier

    if (not isinstance(forest, RandomForestClassifier)
            or getattr(forest, "n_features_in_", None) != len(feats)):
        raise ConfigError(f"{what}: the model's forest does not match its feature list")
    thr = obj.get("label_threshold_m", LABEL_THRESHOLD_M)
    if not _real(thr) or not thr > 0:
        raise ConfigError(f"{what}: label_threshold_m is {_short(thr)}, not a positive number")
    info = obj.get("info") if isinstance(obj.get("info"), dict) else {}
    share = info.get("nlos_share", 0.5)
    if not _real(share) or not 0.0 <= share <= 1.0:
        raise ConfigError(f"{what}: info nlos_share is {_short(share)}, not a number in [0, 1]")
    return NlosClassifier(tuple(feats), forest, float(thr), info)


def _real(v: object) -> bool:
    """A finite real number of a model file (an int or a float, not a bool)."""
    return isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(
        v, (bool, np.bool_)) and math.isfinite(v)


def _short(v: object) -> str:
    s = " ".join(str(v).split())
    return s if len(s) <= 80 else s[:77] + "..."


# -------------------------------------------------------------------- per-range lookup
class RangePriors:
    """P(NLOS) per range of a whole stream, looked up by the batches an estimator is fed.

    The driving loop hands each estimator consecutive slices of the range stream; `take`
    matches a batch by its stamps and anchors (a cursor, with a search where batches skip).
    A range it cannot match gets `default`. `base_rate`: the NLOS share of the training
    ranges (the classifier's own prior), so that a consumer with a prior of its own can
    take the classifier's evidence alone (`log_odds`).
    """

    def __init__(self, t_ns: NDArray[np.int64], anchor: NDArray[np.int32], p: F64,
                 default: float = math.nan, base_rate: float = 0.5) -> None:
        self.base_rate = min(max(float(base_rate), 0.01), 0.99)
        self.t_ns = np.asarray(t_ns, dtype=np.int64)
        self.anchor = np.asarray(anchor, dtype=np.int32)
        self.p = np.asarray(p, dtype=np.float64)
        self.default = default
        self._cursor = 0

    def take(self, t_ns: NDArray[np.int64], anchor: NDArray[np.integer]) -> F64:
        """P(NLOS) (N,) of a batch (stamps, anchor indices)."""
        n = len(t_ns)
        c = self._cursor
        if (c + n <= len(self.t_ns) and np.array_equal(self.t_ns[c:c + n], t_ns)
                and np.array_equal(self.anchor[c:c + n], anchor)):
            self._cursor = c + n
            return self.p[c:c + n].copy()
        out = np.full(n, self.default)
        lo = np.searchsorted(self.t_ns, t_ns, side="left")
        hi = np.searchsorted(self.t_ns, t_ns, side="right")
        for i in np.flatnonzero(hi > lo).tolist():  # only after a skipped batch
            hit = np.flatnonzero(self.anchor[lo[i]:hi[i]] == anchor[i])
            if len(hit):
                out[i] = self.p[lo[i] + hit[0]]
        if n:
            self._cursor = int(hi[-1])
        return out


    def log_odds(self, q: F64) -> F64:
        """The classifier's evidence for NLOS, EVIDENCE_WEIGHT x (log(q / (1 - q)) -
        log(b / (1 - b))) with b the training base rate (0 where q is unknown), clipped to
        +-MAX_EVIDENCE_NATS."""
        qc = np.clip(np.asarray(q, dtype=np.float64), 1e-3, 1.0 - 1e-3)
        b = self.base_rate
        lo = EVIDENCE_WEIGHT * (np.log(qc / (1.0 - qc)) - math.log(b / (1.0 - b)))
        return np.where(np.isfinite(q), np.clip(lo, -MAX_EVIDENCE_NATS, MAX_EVIDENCE_NATS), 0.0)


def set_range_priors(estimator: object, priors: RangePriors) -> bool:
    """Give `estimator` the classifier's priors where it takes them (`use_range_priors`);
    whether it did."""
    use = getattr(estimator, "use_range_priors", None)
    if not callable(use):
        return False
    use(priors)
    return True
