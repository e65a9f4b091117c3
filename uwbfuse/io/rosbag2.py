# SPDX-License-Identifier: BSD-3-Clause
"""A LOG argument to raw messages: a `.mcap` file, a `.db3` file or a rosbag2 directory.

A rosbag2 directory holds `metadata.yaml` (written by `ros2 bag record` or the `rosbags`
library, parsed with a YAML parser) and the storage files it lists under
`relative_file_paths`, read in that order. Where the fast vectorised MCAP scan applies
(storage `mcap`, no compression or per-file zstd compression `x.mcap.zstd`) it is used;
per-message zstd compression (`compression_mode: message`) decompresses each payload before
the same scan hands it on; `sqlite3` storage (`.db3`, plain or compressed) is read through
`rosbags.rosbag2.Reader`, with schemas from the bag's embedded message definitions (or the
`rosbags` type store for bags recorded without them). Every path ends in the same
`ScanResult`s, so the reader decodes messages the same way whatever the storage.
"""

from __future__ import annotations

import io
import mmap
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from uwbfuse.errors import LogReadError
from uwbfuse.io.mcap_raw import (
    ChannelMessages,
    MessageRefs,
    RawChannel,
    RawSchema,
    ScanResult,
    Sink,
    WantFn,
    scan_mcap,
)

STORAGE_MCAP = "mcap"
STORAGE_SQLITE = "sqlite3"
_SUFFIX = {".mcap": STORAGE_MCAP, ".db3": STORAGE_SQLITE}
MAX_METADATA_BYTES = 16 * 1024 * 1024  # a metadata.yaml is ~1 KB per topic; bigger is not one
MAX_MESSAGE_BYTES = 256 * 1024 * 1024  # one decompressed message; a 4K image is ~25 MB
_BLOCK = 16384  # messages handed to a sink at once (bounds the per-block arrays)


@dataclass(frozen=True)
class Bag:
    """What a LOG argument holds: its storage files in reading order and their format."""

    source: Path
    files: tuple[Path, ...]
    storage: str = STORAGE_MCAP  # "mcap" or "sqlite3"
    compression_mode: str = ""  # "", "file" or "message"
    compression_format: str = ""  # "" or "zstd"


def _metadata(meta: Path) -> dict[str, Any]:
    """The `rosbag2_bagfile_information` mapping of `meta` (one-line LogReadError)."""
    from ruamel.yaml import YAML
    from ruamel.yaml.error import YAMLError

    try:
        if meta.stat().st_size > MAX_METADATA_BYTES:
            raise LogReadError(f"{meta}: larger than {MAX_METADATA_BYTES} bytes; not a "
                               "rosbag2 metadata file")
        text = meta.read_text(encoding="utf-8", errors="replace")
        doc = YAML(typ="safe", pure=True).load(text)
    except OSError as e:
        raise LogReadError(f"{meta}: cannot read: {e.strerror or e}") from None
    except (YAMLError, RecursionError, ValueError) as e:
        first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        raise LogReadError(f"{meta}: not valid YAML: {first}") from None
    info = doc.get("rosbag2_bagfile_information") if isinstance(doc, dict) else None
    if not isinstance(info, dict):
        raise LogReadError(f"{meta}: no 'rosbag2_bagfile_information' mapping; not a rosbag2 "
                           "metadata file")
    return info


def _text(info: dict[str, Any], key: str, meta: Path) -> str:
    value = info.get(key)
    if value is None:
        return ""
    if not isinstance(value, str):
        raise LogReadError(f"{meta}: {key} is {value!r}, expected a string")
    return value.strip().lower()


def _bag_dir(p: Path) -> Bag:
    meta = p / "metadata.yaml"
    info = _metadata(meta)
    storage = _text(info, "storage_identifier", meta) or STORAGE_MCAP
    if storage not in (STORAGE_MCAP, STORAGE_SQLITE):
        raise LogReadError(f"{meta}: storage {storage!r} is not supported (mcap or sqlite3)")
    mode = _text(info, "compression_mode", meta)
    mode = "" if mode == "none" else mode
    fmt = _text(info, "compression_format", meta)
    if mode not in ("", "file", "message"):
        raise LogReadError(f"{meta}: compression_mode {mode!r} is not one of none, file, "
                           "message")
    if mode and fmt != "zstd":
        raise LogReadError(f"{meta}: compression_format {fmt!r} is not supported (zstd)")
    rel = info.get("relative_file_paths") or []
    if not isinstance(rel, list) or not all(isinstance(x, str) for x in rel):
        raise LogReadError(f"{meta}: relative_file_paths is not a list of file names")
    suffix = ".db3" if storage == STORAGE_SQLITE else ".mcap"
    if not rel:
        rel = [f.name for f in sorted(p.glob(f"*{suffix}*"))]
    if not rel:
        raise LogReadError(f"{p}: metadata.yaml lists no files and there are no {suffix} "
                           "files")
    files = []
    for name in rel:
        f = p / Path(name).name  # rosbag2 lists names relative to the bag directory
        if not f.is_file():
            raise LogReadError(f"{f}: listed in metadata.yaml but missing")
        files.append(f)
    return Bag(p, tuple(files), storage, mode, fmt if mode else "")


def open_bag(path: str | Path) -> Bag:
    """What LOG `path` holds. Raises LogReadError (one line naming the path)."""
    p = Path(path)
    if not p.exists():
        raise LogReadError(f"{p}: no such file or directory")
    if p.is_file():
        return Bag(p, (p,), _SUFFIX.get(p.suffix.lower(), STORAGE_MCAP))
    if not p.is_dir():
        raise LogReadError(f"{p}: not a file or directory")
    if (p / "metadata.yaml").is_file():
        return _bag_dir(p)
    found = sorted(p.glob("*.mcap"))
    if not found:
        raise LogReadError(f"{p}: not a rosbag2 directory (no metadata.yaml and no .mcap files)")
    return Bag(p, tuple(found))


def log_files(path: str | Path) -> list[Path]:
    """The storage files of LOG `path`, in reading order. Raises LogReadError (one line)."""
    return list(open_bag(path).files)


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


# ------------------------------------------------------------------------------------------
# messages to sinks


def message_refs(datas: list[bytes], log_time: np.ndarray) -> MessageRefs:
    """Payloads `datas` (with their log times, ns) as one MessageRefs over a joined buffer."""
    n = len(datas)
    length = np.fromiter(map(len, datas), dtype=np.int64, count=n)
    offset = np.zeros(n, dtype=np.int64)
    if n > 1:
        np.cumsum(length[:-1], out=offset[1:])
    buf = b"".join(datas)
    return MessageRefs(buf, np.frombuffer(buf, dtype=np.uint8), offset, length,
                       np.asarray(log_time, dtype=np.int64))


def unzstd(data: bytes, limit: int = MAX_MESSAGE_BYTES) -> bytes | None:
    """One zstd-compressed payload, decompressed; None if corrupt or over `limit` bytes."""
    import zstandard

    try:
        with zstandard.ZstdDecompressor().stream_reader(io.BytesIO(data)) as r:
            out = r.read(limit + 1)
    except zstandard.ZstdError:
        return None
    return out if len(out) <= limit else None


class _Decompressing:
    """A sink in front of another: each message's payload zstd-decompressed first."""

    def __init__(self, inner: Sink) -> None:
        self.inner = inner
        self.failed = 0

    def add(self, refs: MessageRefs) -> None:
        plain = [unzstd(d) for d in refs.payloads()]
        ok = np.array([d is not None for d in plain], dtype=bool)
        self.failed += int((~ok).sum())
        if ok.any():
            self.inner.add(message_refs([d for d in plain if d is not None], refs.log_time[ok]))


def _scan_message_compressed(f: Path, want: WantFn) -> ScanResult:
    wrappers: dict[str, _Decompressing] = {}

    def wrapped(channel: RawChannel) -> Sink | None:
        inner = want(channel)
        if inner is None:
            return None
        w = wrappers[channel.topic] = _Decompressing(inner)
        return w

    scan = scan_mcap(f, wrapped, read_bytes(f))
    for topic, w in wrappers.items():
        if w.failed:
            scan.warnings.append(f"{w.failed} messages on {topic} skipped: their zstd "
                                 "message compression does not decompress")
    return scan


def _schema(conn: Any, typestore: Any) -> RawSchema | None:
    """The `ros2msg` schema of a rosbags connection: the bag's definition, else the store's."""
    from rosbags.interfaces import MessageDefinitionFormat

    if conn.msgdef.format == MessageDefinitionFormat.MSG and conn.msgdef.data:
        return RawSchema(conn.id, conn.msgtype, "ros2msg", conn.msgdef.data.encode())
    try:
        text, _ = typestore.generate_msgdef(conn.msgtype, ros_version=2)
    except Exception:  # a type the store does not know: the generic decoder will say so
        return None
    return RawSchema(conn.id, conn.msgtype, "ros2msg", text.encode())


def _scan_rosbags(bag: Bag, want: WantFn) -> ScanResult:
    """All messages of `bag` through `rosbags.rosbag2.Reader` (sqlite3 storage)."""
    import sqlite3

    from rosbags.rosbag2 import Reader
    from rosbags.rosbag2.errors import ReaderError
    from rosbags.typesys import Stores, get_typestore

    result = ScanResult(path=bag.source)
    try:
        with Reader(bag.source) as reader:
            store = get_typestore(Stores.LATEST)
            sinks: dict[int, Sink] = {}
            for conn in reader.connections:
                channel = RawChannel(conn.id, conn.topic, "cdr", _schema(conn, store))
                sink = want(channel)
                result.channels[conn.id] = ChannelMessages(
                    channel, count=0 if sink is not None else int(conn.msgcount), sink=sink)
                if sink is not None:
                    sinks[conn.id] = sink
            wanted = [c for c in reader.connections if c.id in sinks]
            pending: dict[int, tuple[list[int], list[bytes]]] = {}

            def flush(cid: int) -> None:
                times, datas = pending.pop(cid)
                result.channels[cid].count += len(datas)
                sinks[cid].add(message_refs(datas, np.asarray(times, dtype=np.int64)))

            for conn, t, data in reader.messages(connections=wanted) if wanted else ():
                times, datas = pending.setdefault(conn.id, ([], []))
                times.append(t)
                datas.append(data)
                if len(datas) >= _BLOCK:
                    flush(conn.id)
            for cid in list(pending):
                flush(cid)
    except (ReaderError, sqlite3.Error, OSError, KeyError, ValueError) as e:
        first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        raise LogReadError(f"{bag.source}: cannot read rosbag2 ({bag.storage}): {first}"
                           ) from None
    result.complete = True
    return result


def scan_log(path: str | Path, want: WantFn) -> list[ScanResult]:
    """Scan every storage file of LOG `path`, handing wanted channels' messages to sinks."""
    bag = open_bag(path)
    if bag.storage == STORAGE_SQLITE:
        return [_scan_rosbags(bag, want)]
    if bag.compression_mode == "message":
        return [_scan_message_compressed(f, want) for f in bag.files]
    return [scan_mcap(f, want, read_bytes(f)) for f in bag.files]
