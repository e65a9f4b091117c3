# SPDX-License-Identifier: BSD-3-Clause
"""Logs in, trajectories out: MCAP / rosbag2 reading, TUM and MCAP pose writing."""
