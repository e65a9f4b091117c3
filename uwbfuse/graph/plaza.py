# SPDX-License-Identifier: BSD-3-Clause
"""The Plaza range-only datasets (Djugash et al., CMU) shipped in GTSAM's example data.

`Plaza1_.mat` / `Plaza2_.mat` hold (all 2-D, metres, seconds, radians):
- DR: dead reckoning rows (t, distance travelled, heading change) over (t_prev, t];
- TD: ranges (t, radio id, anchor id, range) from the vehicle's radio to fixed beacons;
- TL: beacons (anchor id, x, y);
- GT: ground truth (t, x, y, heading) of the vehicle (heading in another convention:
  score positions only);
- DRp: the dead-reckoned track (its first row gives the start time).

`plaza_log` turns one into a `SensorLog`: wheel samples v = distance/dt and omega =
heading change/dt (each the mean over the interval that ends at its stamp, as the contract
says), ranges with anchor indices, anchors at z = 0, and ground truth as positions only.
The radios read about 7 % long; nothing here corrects that.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from uwbfuse.errors import LogReadError
from uwbfuse.streams import (
    NS_PER_S,
    AnchorMap,
    PoseStream,
    RangeStream,
    SensorLog,
    WheelStream,
)


def plaza_path(name: str) -> Path:
    """Path of `Plaza1_.mat` or `Plaza2_.mat` ('Plaza1' / 'Plaza2') in GTSAM's data folder."""
    import gtsam

    p = Path(gtsam.__file__).parent / "Data" / f"{name}_.mat"
    if not p.exists():
        raise LogReadError(f"{p}: Plaza dataset not found in the installed gtsam package")
    return p


def _ns(t_s: np.ndarray) -> np.ndarray:
    return np.round(np.asarray(t_s, dtype=np.float64) * NS_PER_S).astype(np.int64)


def plaza_log(path: str | Path) -> SensorLog:
    """Read a Plaza `.mat` file into a SensorLog (wheels + ranges + anchors + GT)."""
    from scipy.io import loadmat

    try:
        m = loadmat(str(path))
        dr, drp, td, tl, gt = m["DR"], m["DRp"], m["TD"], m["TL"], m["GT"]
    except (OSError, KeyError, ValueError) as exc:
        raise LogReadError(f"{path}: not a Plaza dataset file ({exc})") from None
    t_dr = dr[:, 0]
    t_prev = np.concatenate([[drp[0, 0]], t_dr[:-1]])
    dt = np.maximum(t_dr - t_prev, 1e-3)
    wheel = WheelStream(_ns(t_dr), dr[:, 1] / dt, dr[:, 2] / dt)
    ids = [str(int(i)) for i in tl[:, 0]]
    anchors = AnchorMap(tuple(ids), np.column_stack([tl[:, 1], tl[:, 2], np.zeros(len(tl))]))
    index = {int(i): k for k, i in enumerate(tl[:, 0])}
    known = np.array([int(a) in index for a in td[:, 2]])
    td = td[known]
    order = np.argsort(td[:, 0], kind="stable")
    td = td[order]
    ranges = RangeStream(_ns(td[:, 0]), np.array([index[int(a)] for a in td[:, 2]], np.int32),
                         td[:, 3].astype(np.float64))
    n = len(gt)
    truth = PoseStream(_ns(gt[:, 0]), np.column_stack([gt[:, 1], gt[:, 2], np.zeros(n)]),
                       np.tile([0.0, 0.0, 0.0, 1.0], (n, 1)), has_orientation=False)
    return SensorLog(wheel=wheel, ranges=ranges, anchors=anchors, ground_truth=truth,
                     source=str(path))
