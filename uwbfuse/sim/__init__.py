# SPDX-License-Identifier: BSD-3-Clause
"""Simulated AGV logs with known truth: scenarios from the seed papers."""
