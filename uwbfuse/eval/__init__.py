# SPDX-License-Identifier: BSD-3-Clause
"""Trajectory evaluation: association, alignment, ATE, RPE, yaw error, coverage."""
