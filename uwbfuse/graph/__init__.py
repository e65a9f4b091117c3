# SPDX-License-Identifier: BSD-3-Clause
"""The factor-graph fusion core. GTSAM is imported only inside this subpackage."""
