# SPDX-License-Identifier: BSD-3-Clause
"""The IMU process-noise level of the Kalman baselines, chosen by likelihood on the log.

How far a MEMS IMU errs beyond its datasheet white noise between two 0.1 s windows (scale,
misalignment, vibration, a hand's motion) depends on the device and how it is carried, and
the still-period noise floor does not show it (ISAS-Walk1 at rest: accelerometer
0.02-0.04 m/s^2 per sample at 82 Hz, the configured 4e-3 m/s^2/sqrt(Hz)). The data do show
it through the filter's one-step predictions: the log likelihood of all innovations (range
mixture densities from `adaptive_noise.RangeNoise`, wheel-speed and planar rows Gaussian)
is the prediction-error decomposition of the measurements' likelihood given the noise
level (Schweppe 1965), so the level that predicts the log's own measurements best is its
maximum-likelihood estimate.

`ProcessNoiseBank` runs the IMU-driven filter from its start state at the configured
`[filter] imu_noise_inflation` times each of `NOISE_BANK_FACTORS` (copies of one filter, split
at its start) and answers, at every step, with the member whose likelihood so far is highest
(multiple-model adaptive estimation with a flat prior over the grid, the most probable
model's estimate). A member whose likelihood falls `DROP_NATS` below the best is
dropped: its posterior probability is then below exp(-DROP_NATS) and stays so, so after
the first seconds of motion the bank costs about one filter.
"""

from __future__ import annotations

import copy
from typing import Any

import numpy as np

from uwbfuse.constants import DROP_NATS, NOISE_BANK_FACTORS
from uwbfuse.estimator import EstimatorBase, PoseEstimate
from uwbfuse.filters.ekf import ErrorStateEkf
from uwbfuse.positioning.nlos_classifier import RangePriors
from uwbfuse.streams import PoseStream


class ProcessNoiseBank(EstimatorBase):
    """Members of one IMU-driven filter that differ in the process-noise level only."""

    def __init__(self, primary: ErrorStateEkf) -> None:
        self.members: list[ErrorStateEkf] = [primary]
        self.factors: list[float] = [1.0]
        self._base: list[float] = [0.0]
        self.split = False
        self.best = 0

    # -- Estimator protocol: inputs go to every member ----------------------------------

    def add_imu(self, t_ns: np.ndarray, gyro: np.ndarray, accel: np.ndarray) -> None:
        for m in self.members:
            m.add_imu(t_ns, gyro, accel)

    def add_wheel(self, t_ns: np.ndarray, v: np.ndarray, omega: np.ndarray) -> None:
        for m in self.members:
            m.add_wheel(t_ns, v, omega)

    def add_ranges(self, t_ns: np.ndarray, anchor: np.ndarray, rng: np.ndarray) -> None:
        for m in self.members:
            m.add_ranges(t_ns, anchor, rng)

    def add_poses(self, t_ns: np.ndarray, position: np.ndarray, quat_xyzw: np.ndarray,
                  covariance: np.ndarray) -> None:
        for m in self.members:
            m.add_poses(t_ns, position, quat_xyzw, covariance)

    def use_range_priors(self, priors: RangePriors) -> None:
        for m in self.members:
            m.use_range_priors(priors)

    def step(self, t_ns: int) -> None:
        for m in self.members:
            m.step(t_ns)
        if not self.split:
            if self.members[0].t_init is None:
                return
            self._split()
            return
        ll = [m.log_likelihood() - b for m, b in zip(self.members, self._base, strict=True)]
        top = max(ll)
        keep = [i for i, v in enumerate(ll) if v > top - DROP_NATS]
        if len(keep) < len(self.members):
            self.members = [self.members[i] for i in keep]
            self.factors = [self.factors[i] for i in keep]
            self._base = [self._base[i] for i in keep]
            ll = [ll[i] for i in keep]
        self.best = int(np.argmax(ll))

    def _split(self) -> None:
        """Copy the started filter once per factor (same state, same history)."""
        primary = self.members[0]
        members, factors = [], []
        for f in NOISE_BANK_FACTORS:
            m = primary if f == 1.0 else copy.deepcopy(primary)
            if f != 1.0:
                m.scale_process_noise(f)
            members.append(m)
            factors.append(f)
        self.members, self.factors = members, factors
        self._base = [m.log_likelihood() for m in members]
        self.best = NOISE_BANK_FACTORS.index(1.0)
        self.split = True

    @property
    def provisional(self) -> bool:
        return self.members[self.best].provisional

    def estimate(self) -> PoseEstimate | None:
        return self.members[self.best].estimate()

    def finish(self) -> PoseStream | None:
        return None

    def report(self) -> dict[str, Any]:
        """The leading member's report plus the bank's: its process-noise inflation and
        the members still running."""
        out = self.members[self.best].report()
        inflation = self.members[0].config.filter.imu_noise_inflation
        out["imu_noise_inflation"] = round(inflation * self.factors[self.best], 3)
        out["noise_bank_members"] = len(self.members)
        return out
