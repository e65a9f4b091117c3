# SPDX-License-Identifier: BSD-3-Clause
"""A LOG argument to the list of MCAP files to read: a `.mcap` file or a rosbag2 directory.

A rosbag2 directory holds `metadata.yaml` (written by `ros2 bag record -s mcap` or the
`rosbags` library) and the files it lists under `relative_file_paths`, read in that order.
Only the few keys needed are parsed (no YAML dependency). Per-file compression
(`compression_mode: FILE`, files ending `.mcap.zstd`) is decompressed in memory.
"""

from __future__ import annotations

import mmap
import os
import re
from pathlib import Path

from uwbfuse.errors import LogReadError

_LIST_ITEM = re.compile(r"^\s*-\s*(.+?)\s*$")


def _metadata_value(text: str, key: str) -> str | None:
    m = re.search(rf"^\s*{key}:\s*(.*?)\s*$", text, re.MULTILINE)
    return None if m is None else m.group(1).strip("'\"")


def _relative_file_paths(text: str) -> list[str]:
    lines = text.splitlines()
    for i, line in enumerate(lines):
        if line.strip().startswith("relative_file_paths:"):
            rest = line.split(":", 1)[1].strip()
            if rest.startswith("["):  # flow style: [a.mcap, b.mcap]
                return [p.strip().strip("'\"") for p in rest.strip("[]").split(",") if p.strip()]
            out = []
            for item in lines[i + 1 :]:
                m = _LIST_ITEM.match(item)
                if m is None:
                    break
                out.append(m.group(1).strip("'\""))
            return out
    return []


def log_files(path: str | Path) -> list[Path]:
    """The MCAP files of LOG `path`, in reading order. Raises LogReadError (one line)."""
    p = Path(path)
    if not p.exists():
        raise LogReadError(f"{p}: no such file or directory")
    if p.is_file():
        return [p]
    if not p.is_dir():
        raise LogReadError(f"{p}: not a file or directory")
    meta = p / "metadata.yaml"
    if not meta.is_file():
        found = sorted(p.glob("*.mcap"))
        if not found:
            raise LogReadError(
                f"{p}: not a rosbag2 directory (no metadata.yaml and no .mcap files)"
            )
        return found
    text = meta.read_text(encoding="utf-8", errors="replace")
    storage = _metadata_value(text, "storage_identifier")
    if storage is not None and storage not in ("mcap", ""):
        raise LogReadError(
            f"{meta}: storage {storage!r} is not supported (only mcap; convert with "
            "`ros2 bag convert` or `rosbags-convert --dst-storage mcap`)"
        )
    rel = _relative_file_paths(text)
    if not rel:
        rel = [f.name for f in sorted(p.glob("*.mcap"))]
    if not rel:
        raise LogReadError(f"{p}: metadata.yaml lists no files and there are no .mcap files")
    files = []
    for name in rel:
        f = p / name
        if not f.is_file():
            raise LogReadError(f"{f}: listed in metadata.yaml but missing")
        files.append(f)
    return files


def read_bytes(path: Path) -> bytes | mmap.mmap:
    """The MCAP bytes of `path`: memory-mapped (read-only); a `.zstd` file decompressed whole."""
    if path.suffix == ".zstd":
        import zstandard

        try:
            return zstandard.ZstdDecompressor().decompressobj().decompress(path.read_bytes())
        except zstandard.ZstdError as e:
            raise LogReadError(f"{path}: cannot decompress: {e}") from None
    try:
        with path.open("rb") as f:
            if os.fstat(f.fileno()).st_size == 0:
                return b""
            return mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ)
    except (OSError, ValueError) as e:
        raise LogReadError(f"{path}: cannot read: {e}") from None
