# SPDX-License-Identifier: BSD-3-Clause
"""UWB positioning without a filter: multilateration, NLOS weighting, initialisation."""
