# SPDX-License-Identifier: BSD-3-Clause
"""Files written whole or not at all: a temporary file beside the target, then a rename.

Every output of uwbfuse (trajectories, MCAP logs, tables, plots, metrics) goes through
`atomic_open`, so an interrupted or failed write never leaves a half-written file under
the target name, and an existing target stays untouched. The file gets the permissions of
an ordinary new file (0666 less the umask), not `mkstemp`'s 0600.

Several outputs of one command are written all or none with `all_or_none()`: inside it,
each `atomic_open` keeps its finished temporary file, and the renames happen together when
the block ends without an error (on an error, or an interrupt, every temporary is removed).
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from contextvars import ContextVar
from pathlib import Path
from typing import IO, Any

from uwbfuse.errors import UwbfuseError

_pending: ContextVar[list[tuple[str, Path, type[UwbfuseError], str]] | None] = ContextVar(
    "uwbfuse_atomic_pending", default=None)


def current_umask() -> int:
    """The process umask, read without changing it where /proc tells it (Linux)."""
    try:
        with open("/proc/self/status", encoding="ascii") as f:
            for line in f:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError):
        pass
    mask = os.umask(0o022)  # elsewhere: set and restore (not thread-safe, but brief)
    os.umask(mask)
    return mask


def new_file_mode() -> int:
    """Permission bits of an ordinary new file: 0666 less the umask (0644 for umask 022)."""
    return 0o666 & ~current_umask()


def _commit(tmp_name: str, p: Path, error: type[UwbfuseError], what: str) -> None:
    try:
        os.replace(tmp_name, p)
    except OSError as e:
        Path(tmp_name).unlink(missing_ok=True)
        raise error(f"{p}: cannot write {what}: {e.strerror or e}") from None


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
    Inside `all_or_none()` the rename waits for the end of that block.
    """
    p = Path(path)
    directory = p.parent if str(p.parent) else Path(".")
    tmp_name: str | None = None
    try:
        fd, tmp_name = tempfile.mkstemp(prefix=f".{p.name}.", suffix=".tmp", dir=directory)
        os.fchmod(fd, new_file_mode())
        encoding = None if "b" in mode else "utf-8"
        with os.fdopen(fd, mode, encoding=encoding) as f:
            yield f
            if fsync:
                f.flush()
                os.fsync(f.fileno())
        group = _pending.get()
        if group is not None:
            group.append((tmp_name, p, error, what))
        else:
            os.replace(tmp_name, p)
        tmp_name = None
    except OSError as e:
        raise error(f"{p}: cannot write {what}: {e.strerror or e}") from None
    finally:
        if tmp_name is not None:
            Path(tmp_name).unlink(missing_ok=True)


@contextmanager
def all_or_none() -> Iterator[None]:
    """Write every `atomic_open` file of the block, or (on any exception) none of them."""
    group: list[tuple[str, Path, type[UwbfuseError], str]] = []
    token = _pending.set(group)
    try:
        yield
    except BaseException:
        for tmp_name, *_ in group:
            Path(tmp_name).unlink(missing_ok=True)
        raise
    finally:
        _pending.reset(token)
    for k, (tmp_name, p, error, what) in enumerate(group):
        try:
            _commit(tmp_name, p, error, what)
        except BaseException:
            for later, *_ in group[k + 1 :]:
                Path(later).unlink(missing_ok=True)
            raise


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


def check_output_paths(paths: dict[str, str | Path | None], error: type[UwbfuseError]) -> None:
    """Raise `error` (one line) unless every given output path can be written.

    paths: option name -> path (None: not asked for). Checks, before any work is done, that
    no path is a directory, that each parent is an existing, writable directory, and that
    no two options name the same file.
    """
    seen: dict[Path, str] = {}
    for option, raw in paths.items():
        if raw is None:
            continue
        p = Path(raw)
        parent = p.parent if str(p.parent) else Path(".")
        if p.is_dir():
            raise error(f"{p}: {option} names a directory, not a file")
        if not parent.is_dir():
            raise error(f"{p}: {option}: folder {parent} does not exist")
        if not os.access(parent, os.W_OK | os.X_OK):
            raise error(f"{p}: {option}: folder {parent} is not writable")
        key = p.resolve()
        if key in seen:
            raise error(f"{p}: {option} and {seen[key]} name the same file")
        seen[key] = option
