# SPDX-License-Identifier: BSD-3-Clause
"""Outputs for the ROS 2 ecosystem: the MCAP channels, covariance CSV, permissions, atomicity."""

from __future__ import annotations

import json
import os
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from uwbfuse.errors import TrajectoryFileError
from uwbfuse.io.atomic import all_or_none, check_output_paths, write_atomic
from uwbfuse.io.cov_csv import COLUMNS, write_cov_csv
from uwbfuse.io.pose_mcap import (
    ANCHORS_TOPIC,
    TF_TOPIC,
    pose_topic,
    pose_with_covariance_topic,
    write_pose_mcap,
)
from uwbfuse.io.tum import write_tum
from uwbfuse.streams import UNKNOWN_VARIANCE, AnchorMap, PoseStream

ANCHORS = AnchorMap.from_dict({"A0": [0.0, 0.0, 1.5], "7475": [40.0, 0.0, 1.5],
                               "A2": [40.0, 20.0, 2.0]})


def _poses(n: int = 30, covariance: bool = True) -> PoseStream:
    rng = np.random.default_rng(1)
    t = 1_700_000_000_000_000_000 + np.arange(n, dtype=np.int64) * 100_000_000 + 7
    cov = None
    if covariance:
        a = rng.normal(size=(n, 6, 6))
        cov = a @ np.transpose(a, (0, 2, 1))
    return PoseStream(t, rng.uniform(-5, 5, (n, 3)), Rotation.random(n, random_state=2).as_quat(),
                      covariance=cov)


def _messages(path: Path) -> Iterator[tuple[object, int, object]]:
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    with AnyReader([path], default_typestore=get_typestore(Stores.EMPTY)) as r:
        conns = {c.topic: c for c in r.connections}
        yield "connections", 0, conns
        for c, t, raw in r.messages():
            yield c, t, r.deserialize(raw, c.msgtype)


def test_mcap_channels_decode_with_rosbags(tmp_path: Path) -> None:
    """test pose, pose_with_covariance, /tf and markers: types, values, frames, QoS."""
    from rosbags.interfaces import QosDurability

    poses = _poses()
    path = tmp_path / "est.mcap"
    write_pose_mcap(path, poses, "ekf", ANCHORS)
    it = _messages(path)
    _, _, conns = next(it)
    assert {t: c.msgtype for t, c in conns.items()} == {
        pose_topic("ekf"): "geometry_msgs/msg/PoseStamped",
        pose_with_covariance_topic("ekf"): "geometry_msgs/msg/PoseWithCovarianceStamped",
        TF_TOPIC: "tf2_msgs/msg/TFMessage",
        ANCHORS_TOPIC: "visualization_msgs/msg/MarkerArray",
    }
    for topic, c in conns.items():
        (qos,) = c.ext.offered_qos_profiles
        want = QosDurability.TRANSIENT_LOCAL if topic == ANCHORS_TOPIC else QosDurability.VOLATILE
        assert qos.durability == want
    got: dict[str, list] = {t: [] for t in conns}
    for c, t, msg in it:
        got[c.topic].append((t, msg))
    for topic in (pose_topic("ekf"), pose_with_covariance_topic("ekf"), TF_TOPIC):
        assert [t for t, _ in got[topic]] == poses.t_ns.tolist()
    for k, (_, m) in enumerate(got[pose_with_covariance_topic("ekf")]):
        assert m.header.frame_id == "map"
        assert m.header.stamp.sec * 10**9 + m.header.stamp.nanosec == poses.t_ns[k]
        p = m.pose.pose.position
        np.testing.assert_array_equal([p.x, p.y, p.z], poses.position[k])
        np.testing.assert_array_equal(m.pose.covariance.reshape(6, 6), poses.covariance[k])
    for k, (_, m) in enumerate(got[TF_TOPIC]):
        (tf,) = m.transforms
        assert (tf.header.frame_id, tf.child_frame_id) == ("map", "base_link")
        q = tf.transform.rotation
        np.testing.assert_array_equal([q.x, q.y, q.z, q.w], poses.quat_xyzw[k])
    ((_, markers),) = got[ANCHORS_TOPIC]
    assert len(markers.markers) == 2 * len(ANCHORS)
    labels = {m.text for m in markers.markers if m.text}
    assert labels == set(ANCHORS.ids)
    cyl = [m for m in markers.markers if m.type == 3]
    np.testing.assert_array_equal([[m.pose.position.x, m.pose.position.y, m.pose.position.z]
                                   for m in cyl], ANCHORS.positions)


def test_mcap_decodes_with_mcap_ros2_and_keeps_the_anchor_record(tmp_path: Path) -> None:
    """test every channel with the mcap_ros2 decoder; `uwb_anchors` as the reader wants it."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    path = tmp_path / "est.mcap"
    write_pose_mcap(path, _poses(5), "isam2", ANCHORS)
    with path.open("rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        n = sum(1 for _ in reader.iter_decoded_messages())
        (meta,) = list(reader.iter_metadata())
    assert n == 3 * 5 + 1
    assert meta.name == "uwb_anchors"
    assert {k: json.loads(v) for k, v in meta.metadata.items()} == {
        a: p.tolist() for a, p in zip(ANCHORS.ids, ANCHORS.positions, strict=True)}


def test_unknown_covariance_is_written_as_unknown_variance(tmp_path: Path) -> None:
    """test that poses without covariance get UNKNOWN_VARIANCE on the diagonal (MCAP, CSV)."""
    poses = _poses(4, covariance=False)
    path = tmp_path / "est.mcap"
    write_pose_mcap(path, poses, "wls")
    covs = [m.pose.covariance for c, _, m in list(_messages(path))[1:]
            if c.topic == pose_with_covariance_topic("wls")]
    np.testing.assert_array_equal(covs, [np.eye(6).ravel() * UNKNOWN_VARIANCE] * 4)
    csv = tmp_path / "cov.csv"
    write_cov_csv(csv, poses)
    rows = np.loadtxt(csv, delimiter=",", skiprows=1)
    np.testing.assert_array_equal(rows[:, 1:], np.eye(6).ravel()[None].repeat(4, 0) * 1e6)


def test_cov_csv_layout(tmp_path: Path) -> None:
    """test the covariance CSV: one header line, t then 36 row-major entries per pose."""
    poses = _poses(12)
    path = tmp_path / "cov.csv"
    write_cov_csv(path, poses)
    lines = path.read_text().splitlines()
    assert lines[0].split(",") == list(COLUMNS) and len(COLUMNS) == 37
    assert COLUMNS[1:8] == ("cov_x_x", "cov_x_y", "cov_x_z", "cov_x_rx", "cov_x_ry", "cov_x_rz",
                            "cov_y_x")
    assert len(lines) == 1 + len(poses)
    assert lines[1].split(",")[0] == "1700000000.000000007"
    rows = np.loadtxt(path, delimiter=",", skiprows=1)
    np.testing.assert_allclose(rows[:, 1:].reshape(-1, 6, 6), poses.covariance, rtol=1e-8)


@pytest.mark.parametrize(("umask", "mode"), [(0o022, 0o644), (0o077, 0o600), (0o002, 0o664)])
def test_outputs_get_the_umask_permissions(tmp_path: Path, umask: int, mode: int) -> None:
    """test that TUM, MCAP, CSV and generic outputs are created 0666 less the umask."""
    old = os.umask(umask)
    try:
        write_tum(tmp_path / "a.tum", _poses(3))
        write_pose_mcap(tmp_path / "a.mcap", _poses(3), "ekf")
        write_cov_csv(tmp_path / "a.csv", _poses(3))
        write_atomic(tmp_path / "a.txt", "x")
    finally:
        os.umask(old)
    assert {p.name: p.stat().st_mode & 0o777 for p in tmp_path.iterdir()} == {
        n: mode for n in ("a.tum", "a.mcap", "a.csv", "a.txt")}


def test_all_or_none_writes_nothing_when_a_later_output_fails(tmp_path: Path) -> None:
    """test that a failure in the second output removes the first one's temporary file."""
    (tmp_path / "old.tum").write_text("old")
    with pytest.raises(TrajectoryFileError), all_or_none():
        write_tum(tmp_path / "old.tum", _poses(3))
        write_pose_mcap(tmp_path / "missing" / "x.mcap", _poses(3), "ekf")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["old.tum"]
    assert (tmp_path / "old.tum").read_text() == "old"
    with all_or_none():
        write_tum(tmp_path / "old.tum", _poses(3))
        assert (tmp_path / "old.tum").read_text() == "old"  # renamed only at the end
    assert (tmp_path / "old.tum").read_text().startswith("#")


def test_output_paths_checked_up_front(tmp_path: Path) -> None:
    """test one-line errors for a directory, a missing folder and two options on one file."""
    (tmp_path / "d").mkdir()
    cases = [({"--mcap-out": tmp_path / "d"}, "names a directory"),
             ({"-o": tmp_path / "no" / "x.tum"}, "does not exist"),
             ({"-o": tmp_path / "x", "--cov-out": tmp_path / "x"}, "name the same file")]
    for paths, words in cases:
        with pytest.raises(TrajectoryFileError, match=words) as e:
            check_output_paths(paths, TrajectoryFileError)
        assert "\n" not in str(e.value)
    check_output_paths({"-o": tmp_path / "ok.tum", "--mcap-out": None}, TrajectoryFileError)
