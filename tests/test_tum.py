# SPDX-License-Identifier: BSD-3-Clause
"""TUM and MCAP trajectory files: exact stamps, atomic writes, clear errors, readability."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from tests.helpers import real
from uwbfuse.errors import TrajectoryFileError
from uwbfuse.io.pose_mcap import pose_topic, write_pose_mcap
from uwbfuse.io.tum import read_tum, write_tum
from uwbfuse.streams import PoseStream


def _poses(n: int = 50, t0_ns: int = 1_664_959_673_400_324_106, seed: int = 0) -> PoseStream:
    rng = np.random.default_rng(seed)
    t = t0_ns + np.cumsum(rng.integers(1, 100_000_000, n)).astype(np.int64)
    return PoseStream(
        t, rng.uniform(-50, 50, (n, 3)), Rotation.random(n, random_state=seed).as_quat()
    )


def test_round_trip_keeps_stamps_exactly(tmp_path: Path) -> None:
    """test that write/read keeps every integer-ns stamp and the poses."""
    poses = _poses()
    path = tmp_path / "est.tum"
    write_tum(path, poses)
    back = read_tum(path)
    np.testing.assert_array_equal(back.t_ns, poses.t_ns)
    np.testing.assert_allclose(back.position, poses.position, atol=1e-6)
    same = np.abs(np.sum(back.quat_xyzw * poses.quat_xyzw, axis=1))
    np.testing.assert_allclose(same, 1.0, atol=1e-8)
    assert back.has_orientation


def test_stamp_format_has_nine_decimals(tmp_path: Path) -> None:
    """test that t is written as seconds with exactly 9 decimals, sub-second stamps too."""
    t = np.array([5, 1_000_000_000, 47_580_000_001], dtype=np.int64)
    path = tmp_path / "a.tum"
    write_tum(path, PoseStream(t, np.zeros((3, 3)), np.tile([0, 0, 0, 1.0], (3, 1))))
    rows = [ln.split()[0] for ln in path.read_text().splitlines() if not ln.startswith("#")]
    assert rows == ["0.000000005", "1.000000000", "47.580000001"]


def test_read_accepts_comments_commas_and_sorts(tmp_path: Path) -> None:
    """test that comments, blank lines and commas are accepted and rows come out sorted."""
    path = tmp_path / "b.tum"
    path.write_text(
        "# header\n\n"
        "2.5 1 2 3 0 0 0 2\n"
        "1.25,4,5,6,0,0,0.6,0.8\n"
        "  # indented comment\n"
        "1.5e0 7 8 9 0 0 0 1\n"
    )
    p = read_tum(path)
    np.testing.assert_array_equal(p.t_ns, [1_250_000_000, 1_500_000_000, 2_500_000_000])
    np.testing.assert_allclose(p.position[0], [4, 5, 6])
    np.testing.assert_allclose(p.quat_xyzw[2], [0, 0, 0, 1])  # normalised
    assert p.has_orientation


@pytest.mark.parametrize(
    ("row", "what"),
    [
        ("1.0 2 3 4 0 0 0", "expected 8 columns"),
        ("1.0 2 x 4 0 0 0 1", "not a number"),
        ("1.0 2 nan 4 0 0 0 1", "non-finite"),
        ("1.0 2 3 4 0 0 0 0", "zero quaternion"),
        ("abc 2 3 4 0 0 0 1", "not a number"),
    ],
)
def test_bad_rows_name_file_and_line(tmp_path: Path, row: str, what: str) -> None:
    """test that a bad row raises TrajectoryFileError naming the file and line number."""
    path = tmp_path / "bad.tum"
    path.write_text(f"# c\n0.5 0 0 0 0 0 0 1\n{row}\n")
    with pytest.raises(TrajectoryFileError, match=rf"bad\.tum:3: {what}"):
        read_tum(path)


def test_missing_and_empty_files(tmp_path: Path) -> None:
    """test that a missing file, a directory and a file without poses are clear errors."""
    with pytest.raises(TrajectoryFileError, match="not found"):
        read_tum(tmp_path / "nope.tum")
    with pytest.raises(TrajectoryFileError, match="directory"):
        read_tum(tmp_path)
    (tmp_path / "empty.tum").write_text("# nothing\n")
    with pytest.raises(TrajectoryFileError, match="no poses"):
        read_tum(tmp_path / "empty.tum")


def test_identity_quaternions_mean_position_only(tmp_path: Path) -> None:
    """test that a file whose quaternions are all identity reads as position-only."""
    path = tmp_path / "gt.tum"
    path.write_text("0.1 1 2 0 0 0 0 1\n0.2 1 3 0 0 0 0 1\n")
    assert not read_tum(path).has_orientation


def test_write_is_atomic(tmp_path: Path) -> None:
    """test that a failed write leaves the old file untouched and no temporary file."""
    path = tmp_path / "est.tum"
    write_tum(path, _poses(5))
    before = path.read_bytes()
    bad = _poses(5)
    bad.position[2, 1] = np.nan
    with pytest.raises(TrajectoryFileError, match="not finite"):
        write_tum(path, bad)
    with pytest.raises(TrajectoryFileError, match="cannot write"):
        write_tum(tmp_path / "missing_dir" / "x.tum", _poses(5))
    assert path.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["est.tum"]


def test_real_ground_truth_files() -> None:
    """test that the real GT files read: labyrinth is position-only, ISAS has orientation."""
    lab = read_tum(real("labyrinth/gt.tum"))
    assert not lab.has_orientation and len(lab) > 100
    isas = read_tum(real("isas-walk1/gt.tum"))
    assert isas.has_orientation and isas.t_ns[0] == 1_664_959_673_400_324_106


def test_pose_mcap_reads_back_with_mcap_ros2(tmp_path: Path) -> None:
    """test that the MCAP trajectory decodes with the mcap reader and the mcap_ros2 decoder."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    poses = _poses(20)
    path = tmp_path / "est.mcap"
    write_pose_mcap(path, poses, "isam2")
    with path.open("rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        assert reader.get_header().profile == "ros2"
        msgs = list(reader.iter_decoded_messages(topics=[pose_topic("isam2")]))
    assert len(msgs) == 20
    for k, (schema, channel, message, decoded) in enumerate(msgs):
        assert channel.topic == pose_topic("isam2") == "/uwbfuse/isam2/pose"
        assert channel.message_encoding == "cdr"
        assert schema.name == "geometry_msgs/msg/PoseStamped"
        assert decoded.header.frame_id == "map"
        stamp = decoded.header.stamp.sec * 1_000_000_000 + decoded.header.stamp.nanosec
        assert stamp == poses.t_ns[k] == message.log_time
        p, q = decoded.pose.position, decoded.pose.orientation
        np.testing.assert_array_equal([p.x, p.y, p.z], poses.position[k])
        np.testing.assert_array_equal([q.x, q.y, q.z, q.w], poses.quat_xyzw[k])


def test_pose_mcap_reads_with_evo(tmp_path: Path) -> None:
    """test that evo reads the MCAP trajectory through rosbags (as `evo_traj bag2` does)."""
    from evo.tools import file_interface
    from rosbags.rosbag2 import Reader

    poses = _poses(10, t0_ns=47_580_000_000)
    path = tmp_path / "est.mcap"
    write_pose_mcap(path, poses, "odom")
    with Reader(path) as reader:
        traj = file_interface.read_bag_trajectory(reader, "/uwbfuse/odom/pose")
    np.testing.assert_allclose(traj.timestamps, poses.t_s, rtol=0, atol=1e-9)
    np.testing.assert_array_equal(traj.positions_xyz, poses.position)
    np.testing.assert_array_equal(traj.orientations_quat_wxyz, poses.quat_xyzw[:, [3, 0, 1, 2]])


def test_pose_mcap_write_is_atomic(tmp_path: Path) -> None:
    """test that an unwritable target raises TrajectoryFileError and leaves nothing behind."""
    with pytest.raises(TrajectoryFileError, match="cannot write MCAP"):
        write_pose_mcap(tmp_path / "no" / "est.mcap", _poses(3), "ekf")
    assert list(tmp_path.iterdir()) == []
