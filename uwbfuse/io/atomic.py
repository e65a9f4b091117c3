# SPDX-License-Identifier: BSD-3-Clause
"""Files written whole or not at all: a temporary file beside the target, then a rename.

Every output of uwbfuse (trajectories, MCAP logs, tables, plots, metrics) goes through
`atomic_open`, so an interrupted or failed write never leaves a half-written file under
the target name, and an existing target stays untouched.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import IO, Any

from uwbfuse.errors import UwbfuseError


@contextmanager
def atomic_open(
    path: str | Path,
    mode: str = "w",
    *,
    error: type[UwbfuseError] = UwbfuseError,
    what: str = "file",
    fsync: bool = False,
) -> Iterator[IO[Any]]:
    """Open a temporary file in `path`'s directory; on success rename it to `path`.

    mode: "w" (text, UTF-8) or "wb". On an OSError the temporary file is removed and
    `error` is raised as one line naming the file; any other exception is re-raised after
    the clean-up. fsync: flush to disk before the rename (for results a crash must not lose).
    """
    p = Path(path)
    directory = p.parent if str(p.parent) else Path(".")
    tmp_name: str | None = None
    try:
        fd, tmp_name = tempfile.mkstemp(prefix=f".{p.name}.", suffix=".tmp", dir=directory)
        encoding = None if "b" in mode else "utf-8"
        with os.fdopen(fd, mode, encoding=encoding) as f:
            yield f
            if fsync:
                f.flush()
                os.fsync(f.fileno())
        os.replace(tmp_name, p)
        tmp_name = None
    except OSError as e:
        raise error(f"{p}: cannot write {what}: {e.strerror or e}") from None
    finally:
        if tmp_name is not None:
            Path(tmp_name).unlink(missing_ok=True)


def write_atomic(
    path: str | Path,
    data: str | bytes,
    *,
    error: type[UwbfuseError] = UwbfuseError,
    what: str = "file",
    fsync: bool = False,
) -> None:
    """Write `data` (text as UTF-8, or bytes) to `path` whole or not at all."""
    mode = "wb" if isinstance(data, bytes) else "w"
    with atomic_open(path, mode, error=error, what=what, fsync=fsync) as f:
        f.write(data)
