# SPDX-License-Identifier: BSD-3-Clause
"""UWB positioning without a filter: multilateration, NLOS weighting, initialisation.

- `multilateration`: per-epoch linear / weighted / robust Gauss-Newton fixes (vectorised).
- `nlos_model`: LOS/NLOS range-error model, NLOS-weighted fixes, `calibrate_nlos`.
- `initialisation`: `Initialiser` -> `InitialState`, the start state from sensors alone.
"""

from uwbfuse.positioning.initialisation import Initialiser, InitialState
from uwbfuse.positioning.multilateration import Fixes, group_epochs, multilaterate
from uwbfuse.positioning.nlos_model import NlosModel, NlosParams, calibrate_nlos, weighted_fix

__all__ = [
    "Fixes",
    "InitialState",
    "Initialiser",
    "NlosModel",
    "NlosParams",
    "calibrate_nlos",
    "group_epochs",
    "multilaterate",
    "weighted_fix",
]
