# SPDX-License-Identifier: BSD-3-Clause
"""One root error type and a subclass per module.

The CLI turns any `UwbfuseError` into one line on stderr and exit status 2; anything else
escaping to the CLI is a bug.
"""


class UwbfuseError(Exception):
    """Root of every error uwbfuse raises on purpose (bad input, bad config, ...)."""


class ConfigError(UwbfuseError):
    """The TOML config is unreadable, has an unknown key or a bad value."""


class LogReadError(UwbfuseError):
    """A log cannot be read: missing, not MCAP, truncated beyond use, missing topic."""


class LogWriteError(UwbfuseError):
    """A log (MCAP) cannot be written: folder missing, no permission, disk full."""


class AnchorMapError(UwbfuseError):
    """No anchor map (neither `[anchors]` nor the `uwb_anchors` metadata record)."""


class EstimatorError(UwbfuseError):
    """An estimator cannot run on this input (e.g. a sensor it needs is absent)."""


class TrajectoryFileError(UwbfuseError):
    """A trajectory file (TUM) cannot be read or written."""


class EvaluationError(UwbfuseError):
    """Evaluation impossible: no overlap in time, too few associated poses, ..."""


class SimulationError(UwbfuseError):
    """Unknown scenario or impossible simulation parameters."""


class FleetError(UwbfuseError):
    """A batch or Monte Carlo study cannot run: no dask, unreachable scheduler, no workers."""


class CollisionCheckError(UwbfuseError):
    """A collision check cannot run: bad map or footprint, trajectories too short or not
    overlapping in time."""
