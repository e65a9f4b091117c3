# SPDX-License-Identifier: BSD-3-Clause
import sys

from uwbfuse.cli import main

sys.exit(main())
