# SPDX-License-Identifier: BSD-3-Clause
"""uwbfuse: factor-graph localisation for indoor vehicles (IMU + wheels + UWB ranges)."""

import logging

from uwbfuse.errors import UwbfuseError

__version__ = "0.1.0"
__all__ = ["UwbfuseError", "__version__"]

logging.getLogger(__name__).addHandler(logging.NullHandler())
