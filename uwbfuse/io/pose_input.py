# SPDX-License-Identifier: BSD-3-Clause
"""External poses (role `pose`, a LiDAR / scan-matching localiser) into a `PoseStream`.

The reader hands over the decoded columns of the pose topic (stamps cleaned, sorted, exact
duplicates and non-finite rows already dropped and counted): position (N,3) m and
orientation (N,4) (x, y, z, w) of the base frame in the frame of the poses, the covariance
(N,6,6) in ROS order (x, y, z in m, rotation about the x, y, z axes of that frame in rad)
and whether the message carried one (`PoseWithCovarianceStamped`; `PoseStamped` has none).

Per message, vectorised:
- a zero quaternion is a counted skip, others are normalised;
- a covariance that is not symmetric or has a negative eigenvalue (not positive
  semi-definite beyond rounding) is a counted skip; an all-zero covariance is "unknown"
  (ROS convention) and gets the `PoseStamped` sigmas, as `PoseStamped` messages do
  (`[pose] sigma_position`, `sigma_rotation`);
- every covariance is floored: in units of the floors (`[pose] min_sigma_position`,
  `min_sigma_rotation`) its eigenvalues are raised to at least 1, so the result is
  positive definite and at least the floor in every direction (a localiser such as AMCL
  publishes zero variance for the z, roll and pitch it does not estimate);
- the poses are carried into the map frame by `[extrinsics] lidar_map_in_map` (the pose of
  the poses' frame in the map frame): p = R_L p' + t_L, R = R_L R', and the covariance's
  position and rotation blocks are rotated by R_L.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from uwbfuse.config import Config
from uwbfuse.streams import PoseStream, ReadReport

F64 = NDArray[np.float64]

SKIP_ZERO_QUAT = "pose message with a zero quaternion"
SKIP_BAD_COVARIANCE = "pose message whose covariance is not positive definite"
# relative tolerance of the symmetry and eigenvalue checks: float64 rounding of a
# covariance written by another program, far below any real negative variance
_REL_TOL = 1e-9


def floor_covariance(cov: F64, floors: F64) -> F64:
    """(N,6,6) covariances with every direction's variance raised to at least the floors
    (N,6,6; `floors` (6,) stds in the units of the rows): the eigenvalues of
    cov / (f f^T) clamped at 1 from below."""
    scale = np.outer(floors, floors)
    eig, vec = np.linalg.eigh(cov / scale)
    eig = np.maximum(eig, 1.0)
    out = np.einsum("nij,nj,nkj->nik", vec, eig, vec)
    return out * scale


def covariance_ok(cov: F64) -> np.ndarray:
    """Per message, whether its (6,6) covariance is symmetric and positive semi-definite
    (to rounding)."""
    if not len(cov):
        return np.zeros(0, dtype=bool)
    mag = np.max(np.abs(cov), axis=(1, 2))
    sym = np.max(np.abs(cov - np.swapaxes(cov, 1, 2)), axis=(1, 2)) <= _REL_TOL * mag + 1e-300
    eig = np.linalg.eigvalsh(0.5 * (cov + np.swapaxes(cov, 1, 2)))
    return sym & (eig[:, 0] >= -_REL_TOL * np.maximum(mag, 1e-300))


def external_poses(
    t_ns: np.ndarray, position: F64, quat_xyzw: F64, covariance: F64, has_cov: np.ndarray,
    config: Config, report: ReadReport,
) -> PoseStream:
    """The external poses in the map frame, with floored covariances (module docstring);
    bad messages are counted in `report` and left out."""
    pc = config.pose
    norm = np.linalg.norm(quat_xyzw, axis=1)
    keep = norm > 0
    report.skip(SKIP_ZERO_QUAT, int((~keep).sum()))
    has_cov = has_cov.astype(bool)
    unknown = has_cov & np.all(covariance == 0.0, axis=(1, 2))
    given = has_cov & ~unknown
    bad = np.zeros(len(t_ns), dtype=bool)
    if np.any(given):
        bad[given] = ~covariance_ok(covariance[given])
    report.skip(SKIP_BAD_COVARIANCE, int((keep & bad).sum()))
    keep &= ~bad
    t_ns, p, q, c, given = (t_ns[keep], position[keep], quat_xyzw[keep], covariance[keep],
                            given[keep])
    q = q / np.linalg.norm(q, axis=1)[:, None]
    default = np.diag([pc.sigma_position**2] * 3 + [pc.sigma_rotation**2] * 3)
    cov = np.where(given[:, None, None], c, default)
    floors = np.array([pc.min_sigma_position] * 3 + [pc.min_sigma_rotation] * 3)
    cov = floor_covariance(cov, floors) if len(cov) else np.zeros((0, 6, 6))
    ext = np.asarray(config.extrinsics.lidar_map_in_map, dtype=np.float64)
    if np.any(ext != np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0])) and len(t_ns):
        r_l = Rotation.from_quat(ext[3:])
        m = r_l.as_matrix()
        p = r_l.apply(p) + ext[:3]
        q = (r_l * Rotation.from_quat(q)).as_quat()
        blk = np.zeros((6, 6))
        blk[:3, :3] = m
        blk[3:, 3:] = m
        cov = blk @ cov @ blk.T
    return PoseStream(np.asarray(t_ns, np.int64), np.ascontiguousarray(p),
                      np.ascontiguousarray(q), True, np.ascontiguousarray(cov))
