# SPDX-License-Identifier: BSD-3-Clause
"""Collision prediction for AGV fleets (the INS-UWB paper, section 3.3 and Figure 6).

From each estimated pose and its velocity and yaw rate, the vehicle's footprint is moved
over [t, t + control_delay] at constant velocity and turn rate; the swept area is tested
against the map's obstacles and against the other vehicles' swept areas of the same time:
`clear`, `warning` (clearance below the margin, widened by k sigma of the position
covariance where one is known) or `collision`, with the clearance and time to contact.

Modules: `geometry` (map and footprint, shapely 2), `motion` (state from a trajectory and
its prediction), `sweep` (swept slots), `classify` (the three outcomes), `fleet` (all
vehicles and pairs, loop or Dask), `events` (the events table), `plot`, `evaluate`
(against ground truth), `command` (`uwbfuse collisions`).
"""
