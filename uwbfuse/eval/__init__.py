# SPDX-License-Identifier: BSD-3-Clause
"""Trajectory evaluation: association, alignment, ATE, RPE, yaw error, coverage.

`evaluate(est, gt)` is the library function; `uwbfuse.eval.command.evaluate_files` reads
the files for `uwbfuse eval`.
"""

from uwbfuse.eval.align import Alignment
from uwbfuse.eval.evaluate import EvalResult, RpeResult, evaluate

__all__ = ["Alignment", "EvalResult", "RpeResult", "evaluate"]
