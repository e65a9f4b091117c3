# SPDX-License-Identifier: BSD-3-Clause
"""A LOG argument to raw messages: a `.mcap` file, a `.db3` file or a rosbag2 directory.

A rosbag2 directory holds `metadata.yaml` (written by `ros2 bag record` or the `rosbags`
library, parsed with a YAML parser) and the storage files it lists under
`relative_file_paths`, read in that order. Where the fast vectorised MCAP scan applies
(storage `mcap`, no compression or per-file zstd compression `x.mcap.zstd`) it is used;
per-message zstd compression (`compression_mode: message`) decompresses each payload before
the same scan hands it on; `sqlite3` storage (`.db3`, plain or compressed) is read with
`rosbags`' Sqlite3Reader, with schemas from the bag's embedded message definitions (or the
`rosbags` type store for bags recorded without them). Decompression is done here, bounded
against zstd bombs (`MAX_RATIO`). Every path ends in the same `ScanResult`s, so the reader
decodes messages the same way whatever the storage.
"""

from __future__ import annotations

import io
import mmap
import os
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

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
MAX_RATIO = 1000  # decompressed / compressed bytes: sensor data packs 2-20x, a zstd bomb ~10^4x
MIN_CAP = 64 * 1024 * 1024  # bytes always allowed, whatever the ratio (tiny inputs)
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


def _cap(compressed: int) -> int:
    """Most bytes `compressed` bytes may decompress to before they count as a bomb."""
    return max(MIN_CAP, MAX_RATIO * compressed)


def _unzstd_file(path: Path, out: IO[bytes]) -> None:
    """Stream the zstd file `path` into `out`, refusing more than `_cap` bytes."""
    import zstandard

    try:
        size = path.stat().st_size
        cap, done = _cap(size), 0
        with path.open("rb") as f, zstandard.ZstdDecompressor().stream_reader(f) as r:
            while block := r.read(1 << 20):
                done += len(block)
                if done > cap:
                    raise LogReadError(f"{path}: decompresses to more than {cap} bytes "
                                       f"({MAX_RATIO}x its {size}); refused as a zstd bomb")
                out.write(block)
    except zstandard.ZstdError as e:
        raise LogReadError(f"{path}: cannot decompress: {e}") from None
    except OSError as e:
        raise LogReadError(f"{path}: cannot read: {e.strerror or e}") from None


def read_bytes(path: Path) -> bytes | mmap.mmap:
    """The MCAP bytes of `path`: memory-mapped (read-only); a `.zstd` file decompressed whole."""
    if path.suffix == ".zstd":
        buf = io.BytesIO()
        _unzstd_file(path, buf)
        return buf.getvalue()
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
    """One zstd-compressed payload, decompressed; None if corrupt, over `limit` bytes or
    over `MAX_RATIO` times its size (a bomb)."""
    import zstandard

    limit = min(limit, _cap(len(data)))
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


@contextmanager
def _plain_file(f: Path, bag: Bag) -> Iterator[Path]:
    """`f` itself, or (file compression) its bounded decompression in a temporary folder."""
    if bag.compression_mode != "file":
        yield f
        return
    with tempfile.TemporaryDirectory(prefix="uwbfuse-bag-") as tmp:
        plain = Path(tmp) / f.name.removesuffix(".zstd")
        with plain.open("wb") as out:
            _unzstd_file(f, out)
        yield plain


def _row_stamp(t: object) -> int | None:
    """An sqlite3 row's timestamp (ns) as an int; None unless an integer or a finite real
    within int64 (sqlite keeps what a column is given: NULL, text, blob, 1e300)."""
    if isinstance(t, int):
        return t
    if isinstance(t, float) and -(2.0**63) <= t < 2.0**63:
        return int(t)
    return None


class _SqliteScan:
    """The messages of sqlite3 storage files, through `rosbags`' Sqlite3Reader."""

    def __init__(self, bag: Bag, want: WantFn) -> None:
        from rosbags.typesys import Stores, get_typestore

        self.bag = bag
        self.want = want
        self.store = get_typestore(Stores.LATEST)
        self.result = ScanResult(path=bag.source)
        self.ids: dict[tuple[str, str], int] = {}  # (topic, type) -> channel id over files
        self.sinks: dict[int, Sink] = {}
        self.failed: dict[str, int] = {}
        self.bad_rows: dict[str, int] = {}  # topic -> rows without a stamp or a payload

    def _channel(self, conn: Any) -> int:
        key = (conn.topic, conn.msgtype)
        if key not in self.ids:
            cid = self.ids[key] = len(self.ids) + 1
            channel = RawChannel(cid, conn.topic, "cdr", _schema(conn, self.store))
            sink = self.want(channel)
            self.result.channels[cid] = ChannelMessages(channel, sink=sink)
            if sink is not None:
                self.sinks[cid] = sink
        return self.ids[key]

    def _flush(self, cid: int, times: list[int], datas: list[bytes]) -> None:
        if self.bag.compression_mode == "message":
            plain = [unzstd(d) for d in datas]
            ok = [d is not None for d in plain]
            bad = len(ok) - sum(ok)
            if bad:
                topic = self.result.channels[cid].channel.topic
                self.failed[topic] = self.failed.get(topic, 0) + bad
            times = [t for t, k in zip(times, ok, strict=True) if k]
            datas = [d for d in plain if d is not None]
        self.result.channels[cid].count += len(datas)
        if datas:
            self.sinks[cid].add(message_refs(datas, np.asarray(times, dtype=np.int64)))

    def file(self, path: Path) -> None:
        from rosbags.rosbag2.storage_sqlite3 import Sqlite3Reader

        storage = Sqlite3Reader(path)
        try:
            storage.open()
        except (TypeError, AttributeError) as e:  # rosbags' parse_qos on a QoS YAML that is
            # not a list of mappings; `scan` makes it one line naming the file
            raise ValueError("its topics' offered_qos_profiles is not a list of QoS "
                             f"mappings ({type(e).__name__}: {e})") from None
        try:
            # rows whose topic_id names no row of the topics table (or is NULL): the
            # reader's join drops them, so they are counted here, as an MCAP message on an
            # undefined channel is
            (orphans,) = next(iter(storage.dbconn.execute(
                "SELECT COUNT(*) FROM messages LEFT JOIN topics"
                " ON messages.topic_id = topics.id WHERE topics.id IS NULL")))
            self.result.lost_messages_unknown_channel += int(orphans)
            ids = {conn.id: self._channel(conn) for conn in storage.connections}
            wanted = [c for c in storage.connections if ids[c.id] in self.sinks]
            for conn in storage.connections:
                if ids[conn.id] not in self.sinks:
                    self.result.channels[ids[conn.id]].count += int(conn.msgcount)
            pending: dict[int, tuple[list[int], list[bytes]]] = {}
            for conn, t, data in storage.messages(wanted) if wanted else ():
                if type(t) is not int or type(data) is not bytes:  # sqlite's dynamic types
                    t = _row_stamp(t) if isinstance(data, bytes) else None
                    if t is None:
                        self.bad_rows[conn.topic] = self.bad_rows.get(conn.topic, 0) + 1
                        continue
                times, datas = pending.setdefault(ids[conn.id], ([], []))
                times.append(t)
                datas.append(data)
                if len(datas) >= _BLOCK:
                    self._flush(ids[conn.id], *pending.pop(ids[conn.id]))
            for cid, (times, datas) in pending.items():
                self._flush(cid, times, datas)
        finally:
            storage.close()

    def scan(self) -> ScanResult:
        import apsw
        from rosbags.rosbag2.errors import ReaderError

        for f in self.bag.files:
            try:
                with _plain_file(f, self.bag) as plain:
                    self.file(plain)
            except (ReaderError, apsw.Error, KeyError, ValueError) as e:
                text = str(e).strip()
                first = text.splitlines()[0] if text else type(e).__name__
                raise LogReadError(f"{f}: cannot read sqlite3 storage: {first}") from None
        for topic, n in self.failed.items():
            self.result.warnings.append(f"{n} messages on {topic} skipped: their zstd "
                                        "message compression does not decompress")
        for topic, n in self.bad_rows.items():
            self.result.warnings.append(f"{n} messages on {topic} skipped: their sqlite3 "
                                        "row has no integer timestamp or no blob data")
        self.result.complete = True
        return self.result


def scan_log(path: str | Path, want: WantFn) -> list[ScanResult]:
    """Scan every storage file of LOG `path`, handing wanted channels' messages to sinks."""
    bag = open_bag(path)
    if bag.storage == STORAGE_SQLITE:
        return [_SqliteScan(bag, want).scan()]
    if bag.compression_mode == "message":
        return [_scan_message_compressed(f, want) for f in bag.files]
    return [scan_mcap(f, want, read_bytes(f)) for f in bag.files]
