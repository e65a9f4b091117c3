# SPDX-License-Identifier: BSD-3-Clause
"""rosbag2 directories in every storage and compression `rosbags` writes read the same."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from tests.helpers import real
from tests.test_io_reader import assert_same_log
from uwbfuse.config import Config, config_from_dict, load_config
from uwbfuse.errors import LogReadError
from uwbfuse.io.reader import read_log
from uwbfuse.io.rosbag2 import open_bag, unzstd
from uwbfuse.io.writer import _encode_streams, write_contract_log
from uwbfuse.sim.simulator import simulate
from uwbfuse.streams import SensorLog


@pytest.fixture(scope="module")
def sim() -> SensorLog:
    return simulate("room", duration_s=4.0, seed=3)


def _anchor_config(log: SensorLog) -> Config:
    """The log's anchors as a config (a sqlite3 bag has no MCAP metadata records)."""
    return config_from_dict({"anchors": {
        a: [float(c) for c in p]
        for a, p in zip(log.anchors.ids, log.anchors.positions, strict=True)}})


def _writer(path: Path, storage: str, mode: str) -> Any:
    """A rosbags rosbag2 Writer of `storage` ("sqlite3", "mcap") and compression `mode`."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.rosbag2.enums import CompressionFormat, CompressionMode

    plugin = {"sqlite3": StoragePlugin.SQLITE3, "mcap": StoragePlugin.MCAP}[storage]
    w = Writer(path, version=9, storage_plugin=plugin)
    if mode:
        w.set_compression({"file": CompressionMode.FILE, "message": CompressionMode.MESSAGE}[mode],
                          CompressionFormat.ZSTD)
    return w


def _write_bag(path: Path, log: SensorLog, storage: str, mode: str) -> None:
    """`log` as a rosbag2 directory written by rosbags.rosbag2.Writer."""
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    w = _writer(path, storage, mode)
    rows = []
    with w:
        for topic, type_name, stamps, datas in _encode_streams(log, Config().topics):
            conn = w.add_connection(topic, type_name, typestore=ts)
            rows += [(int(t), k, conn, d) for k, (t, d) in enumerate(zip(stamps, datas,
                                                                          strict=True))]
        for t, _, conn, d in sorted(rows, key=lambda r: (r[0], r[1])):
            w.write(conn, t, d)


@pytest.mark.parametrize("storage", ["sqlite3", "mcap"])
@pytest.mark.parametrize("mode", ["", "file", "message"])
def test_rosbags_written_bags_read_the_same(
    tmp_path: Path, sim: SensorLog, storage: str, mode: str
) -> None:
    """test db3 / mcap storage with none / file / message compression: the same streams."""
    ref_path = tmp_path / "ref.mcap"
    write_contract_log(ref_path, sim)
    cfg = _anchor_config(sim)
    want = read_log(ref_path, cfg)
    bag = tmp_path / "bag"
    _write_bag(bag, sim, storage, mode)
    info = open_bag(bag)
    assert (info.storage, info.compression_mode) == (storage, mode)
    assert all(f.name.endswith(".zstd") == (mode == "file") for f in info.files)
    got = read_log(bag, cfg)
    assert_same_log(got, want)
    assert got.report.messages == want.report.messages
    assert not got.report.skipped


def test_single_db3_file_reads(tmp_path: Path, sim: SensorLog) -> None:
    """test that a LOG argument naming the .db3 file itself reads like its directory."""
    cfg = _anchor_config(sim)
    bag = tmp_path / "bag"
    _write_bag(bag, sim, "sqlite3", "")
    (db3,) = bag.glob("*.db3")
    assert_same_log(read_log(db3, cfg), read_log(bag, cfg))


def test_corrupt_db3_is_one_line(tmp_path: Path, sim: SensorLog) -> None:
    """test that a .db3 that is not an sqlite database gives one line naming the bag."""
    bag = tmp_path / "bag"
    _write_bag(bag, sim, "sqlite3", "")
    (db3,) = bag.glob("*.db3")
    db3.write_bytes(b"not a database" * 100)
    with pytest.raises(LogReadError) as e:
        read_log(bag, Config())
    assert "\n" not in str(e.value) and str(bag) in str(e.value)


def test_message_compression_bomb_is_skipped() -> None:
    """test that a payload decompressing past the limit (or corrupt) is refused, not read."""
    import zstandard

    big = zstandard.ZstdCompressor().compress(b"\0" * 1_000_000)
    assert unzstd(big, limit=100_000) is None
    assert unzstd(b"garbage") is None
    assert unzstd(big) == b"\0" * 1_000_000


def _convert(src: Path, dst: Path, storage: str, mode: str) -> None:
    """Rewrite the rosbag2 `src` with rosbags (what `rosbags-convert` does)."""
    from rosbags.rosbag2 import Reader
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.EMPTY)
    w = _writer(dst, storage, mode)
    with Reader(src) as r, w:
        conns = {c.id: w.add_connection(c.topic, c.msgtype, msgdef=c.msgdef.data,
                                        rihs01=c.digest, typestore=ts)
                 for c in r.connections}
        for c, t, data in r.messages():
            w.write(conns[c.id], t, data)


@pytest.mark.parametrize(("storage", "mode"), [("sqlite3", "message"), ("mcap", "message")])
def test_real_isas_bag_converted_reads_the_same(tmp_path: Path, storage: str, mode: str) -> None:
    """test ISAS-Walk1 (custom RTLS messages) rewritten as db3 / message-compressed mcap."""
    src = real("isas-walk1/ISAS-Walk1")
    cfg = load_config(real("isas-walk1/config.toml"))
    want = read_log(src, cfg)
    dst = tmp_path / "conv"
    _convert(src, dst, storage, mode)
    got = read_log(dst, cfg)
    for stream, cols in (("imu", ("t_ns", "gyro", "accel")), ("ranges", ("t_ns", "anchor",
                                                                         "range"))):
        for col in cols:
            np.testing.assert_array_equal(getattr(getattr(got, stream), col),
                                          getattr(getattr(want, stream), col))
    assert len(got.ranges) > 1000
    assert got.report.messages == want.report.messages
    assert got.report.skipped == want.report.skipped


def _bomb(n_mib: int = 80) -> bytes:
    """zstd data of a few KB that decompresses to `n_mib` MiB of zeros."""
    import zstandard

    c = zstandard.ZstdCompressor().compressobj()
    block = b"\0" * (1 << 20)
    return b"".join(c.compress(block) for _ in range(n_mib)) + c.flush()


def test_file_compressed_bomb_is_refused(tmp_path: Path, sim: SensorLog) -> None:
    """test that an .mcap.zstd decompressing past 1000x its size is a one-line error."""
    bag = tmp_path / "bag"
    _write_bag(bag, sim, "mcap", "file")
    (f,) = bag.glob("*.zstd")
    f.write_bytes(_bomb())
    with pytest.raises(LogReadError, match="zstd bomb") as e:
        read_log(bag, Config())
    assert "\n" not in str(e.value)


def test_message_compressed_db3_skips_bombs_and_corrupt_payloads(
    tmp_path: Path, sim: SensorLog
) -> None:
    """test a message-compressed db3 with one bomb and one corrupt payload among the IMU
    messages: both skipped with a warning, everything else read."""
    import zstandard
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    z = zstandard.ZstdCompressor()
    hostile = {3: _bomb(), 5: b"not zstd"}
    bag = tmp_path / "bag"
    with _writer(bag, "sqlite3", "") as w:
        for topic, type_name, stamps, datas in _encode_streams(sim, Config().topics):
            conn = w.add_connection(topic, type_name, typestore=ts)
            for k, (t, d) in enumerate(zip(stamps.tolist(), datas, strict=True)):
                bad = hostile.get(k) if topic == "/imu" else None
                w.write(conn, t, bad if bad is not None else z.compress(d))
    meta = bag / "metadata.yaml"
    text = meta.read_text().replace("compression_mode: ''", "compression_mode: message")
    meta.write_text(text.replace("compression_format: ''", "compression_format: zstd"))
    assert open_bag(bag).compression_mode == "message"
    got = read_log(bag, _anchor_config(sim))
    assert len(got.imu) == len(sim.imu) - 2
    np.testing.assert_array_equal(got.imu.t_ns, np.delete(sim.imu.t_ns, [3, 5]))
    assert any("2 messages on /imu skipped" in w for w in got.report.warnings)
    assert len(got.ranges) == len(sim.ranges)


def test_db3_without_message_definitions_uses_the_type_store(
    tmp_path: Path, sim: SensorLog
) -> None:
    """test a db3 of schema version 3 (no message_definitions table, as Humble recorded)."""
    import sqlite3

    cfg = _anchor_config(sim)
    bag = tmp_path / "bag"
    _write_bag(bag, sim, "sqlite3", "")
    (db3,) = bag.glob("*.db3")
    with sqlite3.connect(db3) as db:
        db.execute("DROP TABLE message_definitions")
        db.execute("UPDATE schema SET schema_version = 3")
    ref = tmp_path / "ref.mcap"
    write_contract_log(ref, sim)
    assert_same_log(read_log(bag, cfg), read_log(ref, cfg))


def _relax_not_null(db: Any, table: str) -> None:
    """Rebuild `table` of an sqlite3 connection without its NOT NULL constraints (a db3
    written by another tool, or damaged, may hold NULLs rosbags' schema forbids)."""
    (sql,) = db.execute("SELECT sql FROM sqlite_master WHERE type = 'table' AND name = ?",
                        (table,)).fetchone()
    db.execute(f"ALTER TABLE {table} RENAME TO old_{table}")
    db.execute(sql.replace("NOT NULL", ""))
    db.execute(f"INSERT INTO {table} SELECT * FROM old_{table}")
    db.execute(f"DROP TABLE old_{table}")


@pytest.mark.parametrize("mode", ["", "message"])
def test_db3_rows_without_a_number_stamp_or_a_blob_payload_are_counted_skips(
    tmp_path: Path, sim: SensorLog, mode: str
) -> None:
    """test db3 message rows whose timestamp is NULL, text or beyond int64 (a REAL 1e300) or
    whose data is NULL, text or an integer (sqlite's columns are dynamically typed): each
    skipped and counted in a warning, the rest read (they raised TypeError / OverflowError
    tracebacks)."""
    import sqlite3

    cfg = _anchor_config(sim)
    bag = tmp_path / "bag"
    _write_bag(bag, sim, "sqlite3", "")
    (db3,) = bag.glob("*.db3")
    if mode:  # every payload zstd-compressed, as a message-compressed bag holds them
        import zstandard

        z = zstandard.ZstdCompressor()
        with sqlite3.connect(db3) as db:
            rows = db.execute("SELECT id, data FROM messages").fetchall()
            db.executemany("UPDATE messages SET data = ? WHERE id = ?",
                           [(z.compress(d), i) for i, d in rows])
        meta = bag / "metadata.yaml"
        text = meta.read_text().replace("compression_mode: ''", "compression_mode: message")
        meta.write_text(text.replace("compression_format: ''", "compression_format: zstd"))
    with sqlite3.connect(db3) as db:
        _relax_not_null(db, "messages")
        (imu_id,) = db.execute("SELECT id FROM topics WHERE name = '/imu'").fetchone()
        ids = [i for (i,) in db.execute(
            "SELECT id FROM messages WHERE topic_id = ? ORDER BY timestamp, id LIMIT 40",
            (imu_id,))]
        bad = {ids[3]: ("timestamp", None), ids[5]: ("timestamp", "abc"),
               ids[7]: ("timestamp", 1e300), ids[9]: ("data", None),
               ids[11]: ("data", "hello"), ids[13]: ("data", 7)}
        for i, (col, value) in bad.items():
            db.execute(f"UPDATE messages SET {col} = ? WHERE id = ?", (value, i))
    got = read_log(bag, cfg)
    assert len(got.imu) == len(sim.imu) - len(bad)
    assert any(f"{len(bad)} messages on /imu skipped" in w for w in got.report.warnings)
    assert len(got.ranges) == len(sim.ranges) and len(got.wheel) == len(sim.wheel)



@pytest.mark.parametrize("qos", ["x: 1", "- 5", "abc", "- history: [1]"])
def test_db3_offered_qos_not_a_list_of_mappings_is_one_line(
    tmp_path: Path, sim: SensorLog, qos: str
) -> None:
    """test a db3 whose topics' offered_qos_profiles YAML is not a list of QoS mappings
    (rosbags' parse_qos raised TypeError / AttributeError: a traceback): one line naming
    the file and the column."""
    import sqlite3

    bag = tmp_path / "bag"
    _write_bag(bag, sim, "sqlite3", "")
    (db3,) = bag.glob("*.db3")
    with sqlite3.connect(db3) as db:
        db.execute("UPDATE topics SET offered_qos_profiles = ?", (qos,))
    with pytest.raises(LogReadError) as e:
        read_log(bag, _anchor_config(sim))
    assert "\n" not in str(e.value) and str(db3) in str(e.value)
    assert "offered_qos_profiles" in str(e.value)


def test_db3_rows_of_no_topic_are_counted_skips(tmp_path: Path, sim: SensorLog) -> None:
    """test db3 message rows whose topic_id is not in the topics table (or is NULL): each a
    counted skip in the read report, as an MCAP message on an undefined channel is, the
    rest read (the reader's join with the topics table dropped them uncounted)."""
    import sqlite3

    cfg = _anchor_config(sim)
    bag = tmp_path / "bag"
    _write_bag(bag, sim, "sqlite3", "")
    (db3,) = bag.glob("*.db3")
    with sqlite3.connect(db3) as db:
        _relax_not_null(db, "messages")
        (top,) = db.execute("SELECT MAX(id) FROM topics").fetchone()
        (t0,) = db.execute("SELECT MIN(timestamp) FROM messages").fetchone()
        rows = [(top + 1, t0 + 1), (top + 1, t0 + 2), (top + 7, t0 + 3), (None, t0 + 4)]
        db.executemany("INSERT INTO messages (topic_id, timestamp, data) VALUES (?, ?, ?)",
                       [(i, t, b"\x00\x01\x00\x00") for i, t in rows])
    got = read_log(bag, cfg)
    assert got.report.skipped["message on an undefined channel"] == len(rows)
    assert len(got.imu) == len(sim.imu) and len(got.ranges) == len(sim.ranges)
    assert len(got.wheel) == len(sim.wheel)
