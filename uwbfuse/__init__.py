# SPDX-License-Identifier: BSD-3-Clause
"""uwbfuse: factor-graph localisation for indoor vehicles (IMU + wheels + UWB ranges).

`uwbfuse.Localizer` is the live API (samples in as they arrive, the pose out at any time;
see `uwbfuse.localizer`); it is imported on first use, so `import uwbfuse` stays light.
"""

import logging
from typing import Any

from uwbfuse.errors import UwbfuseError

__version__ = "0.1.0"
__all__ = ["Localizer", "Pose", "UwbfuseError", "__version__"]

logging.getLogger(__name__).addHandler(logging.NullHandler())


def __getattr__(name: str) -> Any:
    if name in ("Localizer", "Pose"):
        from uwbfuse import localizer

        return getattr(localizer, name)
    raise AttributeError(f"module 'uwbfuse' has no attribute {name!r}")
