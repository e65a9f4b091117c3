# SPDX-License-Identifier: BSD-3-Clause
"""Rigid alignment of an estimate onto ground truth (least squares on associated positions).

- `none`: the estimate is scored in its own map frame (the anchor frame): what matters for
  UWB localisation, where the map frame is fixed by the anchors.
- `se2`: rotation about z and an x/y translation (z left as is), fitted on x/y only: for
  planar dead reckoning, whose start heading is arbitrary.
- `se3`: rotation and translation, no scale (Umeyama 1991, as `evo_ape -a`): for ground
  truth in another frame (a motion-capture or Vive frame).

Fits use positions only, like evo; the rotation is then also applied to orientations.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum

import numpy as np
from scipy.spatial.transform import Rotation

from uwbfuse.errors import EvaluationError
from uwbfuse.streams import F64


class Alignment(StrEnum):
    """How the estimate is aligned onto the ground truth before scoring."""

    NONE = "none"
    SE2 = "se2"
    SE3 = "se3"

    @classmethod
    def parse(cls, value: str | Alignment) -> Alignment:
        try:
            return cls(value)
        except ValueError:
            choices = ", ".join(m.value for m in cls)
            raise EvaluationError(f"unknown alignment {value!r}; one of: {choices}") from None


@dataclass(frozen=True)
class RigidTransform:
    """x_gt = rotation @ x_est + translation (rotation (3,3), translation (3,) m)."""

    rotation: F64
    translation: F64

    @classmethod
    def identity(cls) -> RigidTransform:
        return cls(np.eye(3), np.zeros(3))

    def apply(self, position: F64, quat_xyzw: F64) -> tuple[F64, F64]:
        """Transform positions (N,3) and orientations (N,4 xyzw) of the estimate."""
        pos = position @ self.rotation.T + self.translation
        rot = Rotation.from_matrix(self.rotation) * Rotation.from_quat(quat_xyzw)
        return pos, rot.as_quat()

    @property
    def yaw(self) -> float:
        """Heading of the rotation (about z), radians."""
        return float(np.arctan2(self.rotation[1, 0], self.rotation[0, 0]))


def umeyama(src: F64, dst: F64) -> tuple[F64, F64]:
    """Rotation R (d,d) and translation t (d,) minimising sum |dst - (R src + t)|^2, no scale.

    src, dst: (N,d) corresponding points. Umeyama, IEEE TPAMI 13(4), 1991, eqs. 38-42.
    """
    mu_s, mu_d = src.mean(axis=0), dst.mean(axis=0)
    cov = (dst - mu_d).T @ (src - mu_s) / len(src)
    u, _, vt = np.linalg.svd(cov)
    s = np.eye(src.shape[1])
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        s[-1, -1] = -1.0
    r = u @ s @ vt
    return r, mu_d - r @ mu_s


def fit_alignment(kind: Alignment, est_position: F64, gt_position: F64) -> RigidTransform:
    """The transform of `kind` that best maps associated estimate positions onto GT."""
    if kind is Alignment.NONE:
        return RigidTransform.identity()
    if kind is Alignment.SE3:
        r, t = umeyama(est_position, gt_position)
        return RigidTransform(r, t)
    r2, t2 = umeyama(est_position[:, :2], gt_position[:, :2])
    r = np.eye(3)
    r[:2, :2] = r2
    return RigidTransform(r, np.array([t2[0], t2[1], 0.0]))
