# SPDX-License-Identifier: BSD-3-Clause
"""UWB signal quality: received (total) power and first-path power of each range, dBm.

Physical model (DW1000 class, channel 5, 6.5 GHz):

- LOS: log-distance path loss, P(d) = P_1m - 10 n log10(d / 1 m) with the free-space
  exponent n = 2, plus log-normal shadowing. Indoors the total received power RX also
  collects the multipath energy that arrives after the direct path, so the first-path
  power FP is a little below RX: RX - FP = a few dB (Decawave APS006: below about 6 dB
  suggests LOS).
- NLOS: the obstacle sits on the direct path, so it attenuates the first path by its full
  penetration loss, while much of the total arrives by reflections around the obstacle and
  loses only a part of that: RX - FP grows (APS006: above about 10 dB, likely NLOS). The
  penetration loss grows with the excess delay of the range (a thicker or denser obstacle
  both delays and attenuates the direct path more).

`signal_powers` draws from its own Generator, so adding the powers to a simulation leaves
every other sensor's random numbers unchanged.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]
B = NDArray[np.bool_]

P_1M_DBM = -60.0  # dBm: DW1000 RX level at 1 m, LOS (its user manual's -60 to -65 dBm)
PATH_LOSS_EXPONENT = 2.0  # free space; indoor LOS corridors measure 1.6-2.2
SHADOW_DB = 1.5  # dB: log-normal shadowing std of the total power
LOS_GAP_DB = (2.0, 1.2)  # dB: mean and std of RX - FP under LOS (dense multipath behind it)
NLOS_FP_LOSS_DB = 6.0  # dB: first-path penetration loss of the thinnest obstacle
NLOS_FP_LOSS_PER_M = 12.0  # dB per metre of NLOS excess range: denser obstacles delay more
NLOS_FP_LOSS_STD_DB = 2.5  # dB: spread of that loss between obstacles and positions
NLOS_TOTAL_SHARE = 0.35  # share of the first-path loss the total power also loses
NOISE_FLOOR_DBM = -110.0  # dBm: reported powers do not go below the receiver floor


def signal_powers(
    true_range: F64, nlos: B, excess: F64, rng: np.random.Generator
) -> tuple[F64, F64]:
    """(RX, FP) power in dBm for ranges with true range (N,) m, NLOS mask (N,) and NLOS
    excess (N,) m (0 under LOS)."""
    n = len(true_range)
    d = np.maximum(np.asarray(true_range, dtype=np.float64), 0.1)
    los_rx = P_1M_DBM - 10.0 * PATH_LOSS_EXPONENT * np.log10(d)
    shadow = rng.normal(0.0, SHADOW_DB, size=n)
    gap = np.abs(rng.normal(*LOS_GAP_DB, size=n))
    fp_loss = np.maximum(NLOS_FP_LOSS_DB + NLOS_FP_LOSS_PER_M * np.maximum(excess, 0.0)
                         + rng.normal(0.0, NLOS_FP_LOSS_STD_DB, size=n), 0.0)
    fp_loss = np.where(nlos, fp_loss, 0.0)
    rx = los_rx + shadow - NLOS_TOTAL_SHARE * fp_loss
    fp = rx - gap - (1.0 - NLOS_TOTAL_SHARE) * fp_loss
    return np.maximum(rx, NOISE_FLOOR_DBM), np.maximum(fp, NOISE_FLOOR_DBM)
