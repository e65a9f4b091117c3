# SPDX-License-Identifier: BSD-3-Clause
"""Kalman baselines, UWB-only positioning and dead reckoning (no GTSAM graph)."""
