# SPDX-License-Identifier: BSD-3-Clause
"""UWB positioning without a filter: multilateration, NLOS weighting, initialisation.

- `multilateration`: per-epoch linear / weighted / robust Gauss-Newton fixes (vectorised).
- `nlos_weighting`: NLOS-weighted fixes (Qiu 2022) on the per-range view of the NLOS model
  (`uwbfuse.nlos`), `calibrate_nlos`.
- `initialisation`: `Initialiser` -> `InitialState`, the start state from sensors alone.
"""

from uwbfuse.positioning.initialisation import Initialiser, InitialState
from uwbfuse.positioning.multilateration import Fixes, group_epochs, multilaterate
from uwbfuse.positioning.nlos_weighting import calibrate_nlos, weighted_fix

__all__ = [
    "Fixes",
    "InitialState",
    "Initialiser",
    "calibrate_nlos",
    "group_epochs",
    "multilaterate",
    "weighted_fix",
]
