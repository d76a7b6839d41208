"""Tests for common.trajectory_io (TUM format)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from common.errors import CollabSlamError, FileFormatError
from common.trajectory_io import Trajectory, read_tum, write_tum


def _traj(n: int = 25) -> Trajectory:
    rng = np.random.default_rng(3)
    stamps = 1.7e9 + np.cumsum(rng.uniform(0.01, 0.2, n))
    poses = np.column_stack([rng.normal(size=(n, 3)) * 10.0, rng.uniform(-np.pi, np.pi, n)])
    return Trajectory.from_pose4(stamps, poses)


def test_round_trip(tmp_path: Path) -> None:
    traj = _traj()
    path = tmp_path / "a" / "b" / "robot0.tum"  # parent directories are created
    write_tum(path, traj)
    back = read_tum(path)
    assert len(back) == len(traj) == 25
    np.testing.assert_allclose(back.stamps, traj.stamps, rtol=0, atol=1e-6)
    np.testing.assert_allclose(back.positions, traj.positions, rtol=0, atol=1e-9)
    np.testing.assert_allclose(back.quats_xyzw, traj.quats_xyzw, rtol=0, atol=1e-9)


def test_written_lines_are_plain_tum(tmp_path: Path) -> None:
    write_tum(tmp_path / "t.txt", _traj(3))
    lines = (tmp_path / "t.txt").read_text().splitlines()
    assert lines[0].startswith("#")
    fields = lines[1].split(" ")
    assert len(fields) == 8
    assert fields[0].startswith("1700000000.") and len(fields[0].split(".")[1]) == 9


def test_empty_round_trip(tmp_path: Path) -> None:
    write_tum(tmp_path / "e.tum", Trajectory(np.zeros(0), np.zeros((0, 3)), np.zeros((0, 4))))
    assert len(read_tum(tmp_path / "e.tum")) == 0


def test_reads_comments_blank_lines_and_commas(tmp_path: Path) -> None:
    (tmp_path / "t.txt").write_text(
        "# from evo\n\n1.0 1 2 3 0 0 0 1\n  # indented comment\n2.5,4,5,6,0,0,1,0\n"
    )
    traj = read_tum(tmp_path / "t.txt")
    np.testing.assert_array_equal(traj.stamps, [1.0, 2.5])
    np.testing.assert_array_equal(traj.positions[1], [4, 5, 6])
    np.testing.assert_allclose(traj.poses_se2(), [[1, 2, 0], [4, 5, np.pi]])


@pytest.mark.parametrize(
    ("bad_line", "message"),
    [
        ("3.0 1 2 3 0 0 0", "expected 8 values"),
        ("3.0 1 2 x 0 0 0 1", "expected 8 numbers"),
        ("3.0 1 2 nan 0 0 0 1", "non-finite"),
        ("3.0 1e308 2 3 0 0 0 1", "beyond"),  # an error of Infinity in the JSON had followed
        ("0.5 1 2 3 0 0 0 1", "timestamp goes backwards"),
        ("3.0 1 2 3 0 0 0 2", "not unit length"),
    ],
)
def test_malformed_line_names_line_number(tmp_path: Path, bad_line: str, message: str) -> None:
    (tmp_path / "t.txt").write_text(f"# header\n1.0 0 0 0 0 0 0 1\n2.0 0 0 0 0 0 0 1\n{bad_line}\n")
    with pytest.raises(FileFormatError, match=r"t\.txt:4: ") as info:
        read_tum(tmp_path / "t.txt")
    assert message in str(info.value)


def test_missing_file(tmp_path: Path) -> None:
    with pytest.raises(FileFormatError, match="cannot read trajectory"):
        read_tum(tmp_path / "missing.tum")


def test_pose4_and_se2() -> None:
    poses = np.array([[1.0, 2.0, 3.0, 0.5], [0.0, -1.0, 2.0, -3.0]])
    traj = Trajectory.from_pose4([0.0, 1.0], poses)
    np.testing.assert_allclose(traj.poses_se2(), poses[:, [0, 1, 3]])
    np.testing.assert_allclose(np.linalg.norm(traj.quats_xyzw, axis=1), 1.0)


def test_trajectory_validates() -> None:
    with pytest.raises(CollabSlamError, match="non-decreasing"):
        Trajectory.from_pose4([1.0, 0.0], np.zeros((2, 4)))
    with pytest.raises(CollabSlamError, match="expected 2 positions"):
        Trajectory(np.zeros(2), np.zeros((3, 3)), np.zeros((2, 4)))


def test_poses_stamped_out_of_time_order_are_left_out_the_fewest() -> None:
    """A stamp that went back once (-100) and one that jumped far ahead once (1e9) are
    left out; every other pose stays, in order."""
    t = np.array([0.0, 1.0, -100.0, 3.0, 1e9, 5.0, 6.0])
    poses = np.column_stack([np.arange(7.0), np.zeros((7, 3))])
    tr = Trajectory.in_time_order(t, poses, "r0")
    assert tr.stamps.tolist() == [0.0, 1.0, 3.0, 5.0, 6.0]
    assert tr.positions[:, 0].tolist() == [0.0, 1.0, 3.0, 5.0, 6.0]
    same = Trajectory.in_time_order(t[[0, 1, 3]], poses[[0, 1, 3]])
    assert same.stamps.tolist() == [0.0, 1.0, 3.0]
    with pytest.raises(CollabSlamError, match="non-decreasing"):
        Trajectory.from_pose4(t, poses)  # the plain constructor still refuses them
