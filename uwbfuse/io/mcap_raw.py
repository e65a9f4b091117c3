# SPDX-License-Identifier: BSD-3-Clause
"""Raw MCAP scanning: schemas, channels, metadata and message bytes, without decoding.

The data section is read front to back (the summary section is never needed), so files
with or without a summary/index, chunked or not, zstd/lz4/uncompressed, and files cut off
mid-write are all read the same way. The only per-record Python work is one loop step
that finds each record's start; everything else (opcodes, channel ids, log times, message
byte rows) is gathered with numpy. A channel's messages come out as (n, L) uint8 matrices,
one per message length, ready for the vectorised CDR decoder.

Record layouts: MCAP specification (https://mcap.dev/spec), all integers little-endian.
"""

from __future__ import annotations

import mmap
import struct
import zlib
from array import array
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from uwbfuse.errors import LogReadError

MAGIC = b"\x89MCAP0\r\n"

OP_HEADER = 0x01
OP_FOOTER = 0x02
OP_SCHEMA = 0x03
OP_CHANNEL = 0x04
OP_MESSAGE = 0x05
OP_CHUNK = 0x06
OP_MESSAGE_INDEX = 0x07
OP_METADATA = 0x0C
OP_DATA_END = 0x0F

_U16 = struct.Struct("<H")
_U32 = struct.Struct("<I")
_U64 = struct.Struct("<Q")
_CHUNK_HEAD = struct.Struct("<QQQII")  # start, end, uncompressed size, crc, len(compression)
_MESSAGE_HEAD = 2 + 4 + 8 + 8  # channel id, sequence, log time, publish time
_BLOCK = 16384  # message records gathered at once (bounds the index arrays)
# bytes one chunk may decompress to: 32x the 4 MiB chunks of `ros2 bag record` and the mcap
# CLI; a larger declared size is a decompression bomb or a corrupt header, not a real chunk
MAX_CHUNK_BYTES = 128 * 1024 * 1024
_READ_PIECE = 16 * 1024 * 1024  # streaming decompression output per read, bytes


@dataclass(frozen=True)
class RawSchema:
    """A Schema record: `encoding` e.g. "ros2msg", "jsonschema"; `data` the schema text."""

    id: int
    name: str
    encoding: str
    data: bytes


@dataclass(frozen=True)
class RawChannel:
    """A Channel record with its schema resolved (None for schema id 0 or unknown)."""

    id: int
    topic: str
    message_encoding: str
    schema: RawSchema | None


@dataclass(frozen=True)
class MessageRefs:
    """Messages of one channel inside one buffer (a chunk's records or the file).

    Payload i is `buf[offset[i] : offset[i] + length[i]]`; `arr` is `buf` as uint8.
    """

    buf: bytes | memoryview
    arr: NDArray[np.uint8]
    offset: NDArray[np.int64]
    length: NDArray[np.int64]
    log_time: NDArray[np.int64]

    def __len__(self) -> int:
        return len(self.offset)

    def payloads(self, mask: NDArray[np.bool_] | None = None) -> list[bytes]:
        """The payloads (selected by `mask`) as bytes objects."""
        offs, lens = self.offset, self.length
        if mask is not None:
            offs, lens = offs[mask], lens[mask]
        buf = self.buf
        return [bytes(buf[o : o + n]) for o, n in zip(offs.tolist(), lens.tolist(), strict=True)]


class Sink(Protocol):
    """Receives the messages of one channel as they are scanned."""

    def add(self, refs: MessageRefs) -> None:
        """Messages found in one buffer; `refs` is valid only during the call."""


@dataclass
class ChannelMessages:
    """One channel: its message count and the sink its messages went to (None: counted)."""

    channel: RawChannel
    count: int = 0
    sink: Sink | None = None


@dataclass
class ScanResult:
    """What one MCAP file holds: channels with messages, metadata records, warnings."""

    path: Path
    channels: dict[int, ChannelMessages] = field(default_factory=dict)
    metadata: list[tuple[str, dict[str, str]]] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)
    lost_messages_unknown_channel: int = 0
    complete: bool = False


WantFn = Callable[[RawChannel], Sink | None]


def _string(buf: bytes | memoryview, pos: int) -> tuple[str, int]:
    n = _U32.unpack_from(buf, pos)[0]
    end = pos + 4 + n
    if end > len(buf):
        raise struct.error("string runs past the record")
    return bytes(buf[pos + 4 : end]).decode("utf-8", errors="replace"), end


def _string_map(buf: bytes | memoryview, pos: int) -> tuple[dict[str, str], int]:
    size = _U32.unpack_from(buf, pos)[0]
    pos += 4
    end = pos + size
    out: dict[str, str] = {}
    while pos < end:
        k, pos = _string(buf, pos)
        v, pos = _string(buf, pos)
        out[k] = v
    return out, pos


def _walk(buf: bytes | memoryview, pos: int, end: int) -> tuple[array, int]:
    """Start offsets of the complete records in buf[pos:end], and where the walk stopped.

    The offsets are an int64 `array` (8 bytes per record, not a list of Python ints: a
    chunk of empty 9-byte records must not take 4x its size).
    """
    starts = array("q")
    append = starts.append
    unpack = _U64.unpack_from
    while pos + 9 <= end:
        nxt = pos + 9 + unpack(buf, pos + 1)[0]
        if nxt > end:
            break
        append(pos)
        pos = nxt
    return starts, pos


def _gather(arr: NDArray[np.uint8], offsets: np.ndarray, width: int) -> np.ndarray:
    """Rows arr[o : o + width] for every offset o, as an (n, width) uint8 matrix."""
    return arr[offsets[:, None] + np.arange(width, dtype=np.int64)]


class _Scanner:
    def __init__(self, path: Path, want: WantFn) -> None:
        self.result = ScanResult(path)
        self.want = want
        self.schemas: dict[int, RawSchema] = {}
        self.defs: dict[int, tuple[str, str, int]] = {}  # channel id -> topic, enc, schema

    # -- records -------------------------------------------------------------------------

    def _schema(self, buf: bytes | memoryview, pos: int) -> None:
        sid = _U16.unpack_from(buf, pos)[0]
        name, p = _string(buf, pos + 2)
        enc, p = _string(buf, p)
        n = _U32.unpack_from(buf, p)[0]
        self.schemas[sid] = RawSchema(sid, name, enc, bytes(buf[p + 4 : p + 4 + n]))

    def _channel(self, buf: bytes | memoryview, pos: int) -> None:
        cid, sid = struct.unpack_from("<HH", buf, pos)
        topic, p = _string(buf, pos + 4)
        enc, p = _string(buf, p)
        self.defs[cid] = (topic, enc, sid)

    def _metadata(self, buf: bytes | memoryview, pos: int) -> None:
        name, p = _string(buf, pos)
        data, _ = _string_map(buf, p)
        self.result.metadata.append((name, data))

    def _channel_messages(self, cid: int) -> ChannelMessages | None:
        got = self.result.channels.get(cid)
        if got is not None:
            return got
        d = self.defs.get(cid)
        if d is None:
            return None
        topic, enc, sid = d
        ch = RawChannel(cid, topic, enc, self.schemas.get(sid) if sid else None)
        got = ChannelMessages(ch, sink=self.want(ch))
        self.result.channels[cid] = got
        return got

    # -- buffers -------------------------------------------------------------------------

    def _record(self, buf: bytes | memoryview, pos: int, op: int) -> None:
        """A schema, channel or metadata record (others are not needed)."""
        try:
            if op == OP_SCHEMA:
                self._schema(buf, pos + 9)
            elif op == OP_CHANNEL:
                self._channel(buf, pos + 9)
            elif op == OP_METADATA:
                self._metadata(buf, pos + 9)
        except (struct.error, UnicodeDecodeError):
            self.result.warnings.append(f"malformed record (opcode {op}) at byte {pos}")

    def _messages(self, buf: bytes | memoryview, arr: NDArray[np.uint8], s: np.ndarray) -> None:
        """Message records starting at `s` (complete records, lengths already checked)."""
        for i in range(0, len(s), _BLOCK):
            self._message_block(buf, arr, s[i : i + _BLOCK])

    def _message_block(
        self, buf: bytes | memoryview, arr: NDArray[np.uint8], s: np.ndarray
    ) -> None:
        reclen = _u64_at(arr, s + 1)
        chan = _gather(arr, s + 9, 2).view("<u2")[:, 0]
        log_time = _u64_at(arr, s + 15)
        data_off = s + 9 + _MESSAGE_HEAD
        data_len = reclen - _MESSAGE_HEAD
        bad = data_len < 0
        if bad.any():
            self.result.warnings.append(f"{int(bad.sum())} malformed message records skipped")
        for cid in np.flatnonzero(np.bincount(chan[~bad])).tolist():
            cm = self._channel_messages(cid)
            sel = (chan == cid) & ~bad
            if cm is None:
                self.result.lost_messages_unknown_channel += int(sel.sum())
                continue
            cm.count += int(sel.sum())
            if cm.sink is not None:
                cm.sink.add(MessageRefs(buf, arr, data_off[sel], data_len[sel], log_time[sel]))

    def _chunk_records(self, data: bytes | memoryview, index: np.ndarray | None) -> None:
        """Handle a decompressed chunk, using its message-index offsets where they check out.

        With an index, only the gaps between indexed messages are walked record by record
        (schemas and channels sit there); without one, or if it does not fit the data, the
        whole chunk is walked.
        """
        arr = np.frombuffer(data, dtype=np.uint8)
        size = len(arr)
        msg = _checked_index(arr, index) if index is not None else None
        if msg is None:
            starts, stop = _walk(data, 0, size)
            if stop != size:
                self.result.warnings.append(
                    f"chunk: {size - stop} trailing bytes are not a complete record"
                )
            s = np.frombuffer(starts, dtype=np.int64) if len(starts) else np.zeros(0, np.int64)
        else:
            ends = msg + 9 + _u64_at(arr, msg + 1)
            gap_from = np.concatenate([[0], ends])
            gap_to = np.concatenate([msg, [size]])
            gaps = gap_to > gap_from
            others: list[int] = []
            for g0, g1 in zip(gap_from[gaps].tolist(), gap_to[gaps].tolist(), strict=True):
                found, _ = _walk(data, g0, g1)
                others.extend(found)
            s = np.sort(np.concatenate([msg, np.asarray(others, dtype=np.int64)]))
        if not len(s):
            return
        ops = arr[s]
        is_msg = ops == OP_MESSAGE
        defs = (ops == OP_SCHEMA) | (ops == OP_CHANNEL)  # only these (not a list of all)
        for pos, op in zip(s[defs].tolist(), ops[defs].tolist(), strict=True):
            self._record(data, pos, op)
        self._messages(data, arr, s[is_msg])

    def _chunk(
        self, buf: bytes, pos: int, index_pos: list[int], truncated_end: int | None = None
    ) -> None:
        """Decompress the chunk record at `pos` (its message indexes at `index_pos`).

        With `truncated_end`, the record is cut off there: whatever complete inner records
        can be recovered from the partial data are used.
        """
        p = pos + 9
        _, _, usize, crc, clen = _CHUNK_HEAD.unpack_from(buf, p)
        p += _CHUNK_HEAD.size
        compression = bytes(buf[p : p + clen]).decode("ascii", errors="replace")
        p += clen
        rlen = _U64.unpack_from(buf, p)[0]
        p += 8
        if compression and usize > MAX_CHUNK_BYTES:
            raise _BadChunk(f"declares {usize} bytes uncompressed, more than the "
                            f"{MAX_CHUNK_BYTES >> 20} MiB limit of a chunk")
        end = p + rlen if truncated_end is None else min(p + rlen, truncated_end)
        data = _decompress(compression, memoryview(buf)[p:end], usize,
                           partial=truncated_end is not None)
        if truncated_end is None and crc and zlib.crc32(data) != crc:
            raise ValueError("CRC mismatch of the uncompressed records")
        index = _index_offsets(buf, index_pos) if index_pos else None
        self._chunk_records(data, index)

    def _safe_chunk(self, buf: bytes, pos: int, index_pos: list[int]) -> None:
        try:
            self._chunk(buf, pos, index_pos)
        except LogReadError:
            raise
        except Exception as e:  # zstd/lz4/struct errors share no base class
            self.result.warnings.append(f"chunk at byte {pos} skipped: {e}")

    # -- file ----------------------------------------------------------------------------

    def scan(self, buf: bytes) -> None:
        starts, stop = _walk(buf, len(MAGIC), len(buf))
        arr = np.frombuffer(buf, dtype=np.uint8)
        s = np.frombuffer(starts, dtype=np.int64) if len(starts) else np.zeros(0, np.int64)
        ops = arr[s] if len(s) else np.zeros(0, np.uint8)
        ends = np.flatnonzero((ops == OP_DATA_END) | (ops == OP_FOOTER))
        complete = bool(len(ends))
        if complete:
            # the summary section repeats schemas and channels: take them first, so that
            # a damaged chunk holding the originals loses only its own messages
            for pos, op in zip(s[ends[0]:].tolist(), ops[ends[0]:].tolist(), strict=True):
                if op in (OP_SCHEMA, OP_CHANNEL):
                    self._record(buf, pos, op)
            s, ops = s[: ends[0]], ops[: ends[0]]
        is_msg = ops == OP_MESSAGE
        used = np.isin(ops, (OP_SCHEMA, OP_CHANNEL, OP_CHUNK, OP_MESSAGE_INDEX, OP_METADATA))
        other = list(zip(s[used].tolist(), ops[used].tolist(), strict=True))
        i = 0
        while i < len(other):
            pos, op = other[i]
            i += 1
            if op == OP_CHUNK:
                index_pos = []
                while i < len(other) and other[i][1] == OP_MESSAGE_INDEX:
                    index_pos.append(other[i][0])
                    i += 1
                self._safe_chunk(buf, pos, index_pos)
            else:
                self._record(buf, pos, op)
        if is_msg.any():
            self._messages(buf, arr, s[is_msg])
        self.result.complete = complete
        if complete:
            return
        lost = len(buf) - stop
        if lost == 0:
            self.result.warnings.append("file ends without a DataEnd/Footer record "
                                        "(not closed by its writer)")
            return
        self.result.warnings.append(
            f"truncated: the last {lost} bytes (from byte {stop}) are an incomplete record"
        )
        if stop + 9 + _CHUNK_HEAD.size <= len(buf) and buf[stop] == OP_CHUNK:
            before = sum(c.count for c in self.result.channels.values())
            try:
                self._chunk(buf, stop, [], truncated_end=len(buf))
            except _BadChunk as e:
                self.result.warnings.append(f"incomplete last chunk skipped: it {e}")
                return
            except LogReadError:
                raise
            except Exception:  # best effort on a cut-off chunk
                pass
            got = sum(c.count for c in self.result.channels.values()) - before
            self.result.warnings.append(
                f"recovered {got} messages from the incomplete last chunk; the rest is lost"
            )


def _u64_at(arr: NDArray[np.uint8], offs: np.ndarray) -> np.ndarray:
    return _gather(arr, offs, 8).view("<u8")[:, 0].astype(np.int64)


def _index_offsets(buf: bytes, index_pos: list[int]) -> np.ndarray | None:
    """Message offsets inside the chunk from its MessageIndex records (None if malformed)."""
    parts = []
    for pos in index_pos:
        n = _U32.unpack_from(buf, pos + 9 + 2)[0]
        if n % 16 or pos + 9 + 6 + n > len(buf):
            return None
        pairs = np.frombuffer(buf, dtype="<u8", count=n // 8, offset=pos + 9 + 6)
        parts.append(pairs[1::2].astype(np.int64))
    return np.concatenate(parts) if parts else None


def _checked_index(arr: NDArray[np.uint8], index: np.ndarray) -> np.ndarray | None:
    """Sorted message-record offsets if they are consistent with the chunk data, else None."""
    s = np.sort(index)
    size = len(arr)
    if not len(s) or s[0] < 0 or np.any(s[1:] == s[:-1]) or s[-1] + 9 + _MESSAGE_HEAD > size:
        return None
    if not np.all(arr[s] == OP_MESSAGE):
        return None
    ends = s + 9 + _u64_at(arr, s + 1)
    if ends[-1] > size or np.any(ends[:-1] > s[1:]):
        return None
    return s


class _BadChunk(ValueError):
    """A chunk that is skipped whole (declared sizes over the limits, a bomb)."""


def _read_capped(read: Callable[[int], bytes], cap: int, partial: bool) -> bytes:
    """Up to cap + 1 bytes from a decompressing `read` (more than `cap` means too much)."""
    import zstandard

    parts: list[bytes] = []
    got = 0
    while got <= cap:
        try:
            piece = read(min(cap + 1 - got, _READ_PIECE))
        except zstandard.ZstdError:
            if not partial:
                raise
            break  # a cut-off stream: keep what came out before the cut
        if not piece:
            break
        parts.append(piece)
        got += len(piece)
    return b"".join(parts)


def _decompress(
    compression: str, data: memoryview, size: int, partial: bool = False
) -> bytes | memoryview:
    """Chunk records as bytes; with `partial`, as much as a cut-off stream yields.

    Streaming, with the output capped at the chunk's declared size (itself at most
    MAX_CHUNK_BYTES): a frame that holds more than the chunk declares is a _BadChunk before
    more than that is allocated, whatever its own header says.
    """
    if compression == "":
        return data
    cap = min(size, MAX_CHUNK_BYTES)
    if compression == "zstd":
        import zstandard

        reader = zstandard.ZstdDecompressor().stream_reader(data, read_across_frames=True)
        out = _read_capped(reader.read, cap, partial)
    elif compression == "lz4":
        import lz4.frame

        dec = lz4.frame.LZ4FrameDecompressor()
        out = dec.decompress(data, max_length=cap + 1)
        if not partial and len(out) <= cap and not dec.eof:
            raise ValueError("lz4 frame ends before its end mark")
    else:
        raise LogReadError(f"unsupported chunk compression {compression!r}")
    if len(out) > cap:
        raise _BadChunk(f"decompresses to more than its declared {size} bytes")
    return out


def scan_mcap(path: Path, want: WantFn, data: bytes | mmap.mmap | None = None) -> ScanResult:
    """Scan the MCAP file at `path` (or its bytes `data`); keep message rows where `want`.

    Raises LogReadError if the file does not start with the MCAP magic.
    """
    buf = path.read_bytes() if data is None else data
    if len(buf) < len(MAGIC) or buf[: len(MAGIC)] != MAGIC:
        what = "empty file" if not buf else "bad magic"
        raise LogReadError(f"{path}: not an MCAP file ({what})")
    scanner = _Scanner(path, want)
    try:
        scanner.scan(buf)
    except LogReadError as e:
        raise LogReadError(f"{path}: {e}") from None
    except (struct.error, IndexError, ValueError, OverflowError) as e:  # malformed records
        raise LogReadError(f"{path}: corrupt MCAP data: {e}") from None
    return scanner.result
