# SPDX-License-Identifier: BSD-3-Clause
"""Simulated AGV logs with known truth: scenarios from the seed papers.

`simulate(scenario, duration_s, seed, **overrides)` gives a `SensorLog`;
`simulate_with_truth(...)` also gives the hidden truth (`SimResult`); `SCENARIOS` maps
names to `Scenario` definitions.
"""

from uwbfuse.sim.scenarios import SCENARIOS, Scenario
from uwbfuse.sim.simulator import SimResult, simulate, simulate_with_truth

__all__ = ["SCENARIOS", "Scenario", "SimResult", "simulate", "simulate_with_truth"]
