"""CARMEN log reader: hand-written logs (plain and bzip2), malformed lines, the real Intel log."""

from __future__ import annotations

import bz2
import math
from pathlib import Path

import numpy as np
import pytest

from agent.carmen_log import (
    CarmenLaser,
    CarmenOdometry,
    carmen_time_span,
    laser_odometry_trajectory,
    odometry_stamps_regular,
    read_carmen,
    read_carmen_params,
    saturation_range_m,
)
from common.errors import FileFormatError

CARMEN = Path(__file__).resolve().parents[2] / "shared" / "data" / "carmen"

SMALL_LOG = """\
# message_name [message contents] ipc_timestamp ipc_hostname logger_timestamp
PARAM robot_frontlaser_offset 0.25 nohost 0
PARAM robot_use_laser on nohost 0
ODOM 1.0 2.0 0.5 0.3 -0.1 0.0 100.000000 nohost 0.0
FLASER 4 1.0 2.0 3.0 81.91 1.25 2.0 0.5 1.0 2.0 0.5 100.050000 nohost 0.05
TRUEPOS 1.0 2.0 0.5 1.0 2.0 0.5 100.060000 nohost 0.06

PARAM laser_front_laser_fov 100 nohost 0
PARAM laser_front_laser_resolution 50 nohost 0
PARAM robot_front_laser_max 30.0 nohost 0
FLASER 3 4.0 5.0 6.0 1.5 2.5 0.75 1.2 2.4 0.7 100.150000 nohost 0.15
ODOM 1.2 2.4 0.7 0.0 0.0 0.0 100.200000 nohost 0.2
"""
# type start fov res maxrange accuracy remission_mode, 3 ranges, 0 remissions, laser pose,
# robot pose, tv rv forward_safety side_safety turn_axis, ipc host logger
SMALL_LOG += (
    "ROBOTLASER1 0 -1.0 2.0 1.0 20.0 0.01 0 3 7.0 8.0 9.0 0 1.0 1.0 0.1 1.1 1.1 0.2 "
    "0.3 0.01 0.5 0.5 0.3 100.250000 nohost 0.25\n"
)


def write_log(folder: Path, text: str, name: str = "log.clf") -> Path:
    path = folder / name
    path.write_text(text, encoding="ascii")
    return path


def as_tuples(path: Path) -> list[tuple]:
    out: list[tuple] = []
    for r in read_carmen(path):
        if isinstance(r, CarmenLaser):
            out.append(
                ("L", r.stamp, r.ranges.tolist(), r.angle_min, r.angle_increment, r.range_max)
                + (r.odom_pose.tolist(), r.laser_pose.tolist())
            )
        else:
            out.append(("O", r.stamp, r.pose.tolist(), r.tv, r.rv))
    return out


def test_small_log_fields(tmp_path: Path) -> None:
    records = list(read_carmen(write_log(tmp_path, SMALL_LOG)))
    assert [type(r).__name__ for r in records] == [
        "CarmenOdometry",
        "CarmenLaser",
        "CarmenLaser",
        "CarmenOdometry",
        "CarmenLaser",
    ]
    odom, scan1, scan2, _, robotlaser = records
    assert isinstance(odom, CarmenOdometry)
    assert odom.stamp == 100.0 and odom.tv == 0.3 and odom.rv == -0.1
    np.testing.assert_array_equal(odom.pose, [1.0, 2.0, 0.5])

    assert isinstance(scan1, CarmenLaser)
    assert scan1.stamp == 100.05
    assert scan1.ranges.dtype == np.float32
    np.testing.assert_allclose(scan1.ranges, [1.0, 2.0, 3.0, 81.91], rtol=1e-6)
    np.testing.assert_array_equal(scan1.laser_pose, [1.25, 2.0, 0.5])
    np.testing.assert_array_equal(scan1.odom_pose, [1.0, 2.0, 0.5])
    # No laser PARAM yet: CARMEN's defaults (start -90 deg, 180 deg over n-1 steps, 80 m).
    assert scan1.angle_min == pytest.approx(-math.pi / 2)
    assert scan1.angle_increment == pytest.approx(math.pi / 3)
    assert scan1.range_max == 80.0

    # The PARAM lines in between change the beam geometry of later scans.
    assert isinstance(scan2, CarmenLaser)
    assert scan2.angle_min == pytest.approx(math.radians(-50.0))
    assert scan2.angle_increment == pytest.approx(math.radians(50.0))
    assert scan2.range_max == 30.0

    assert isinstance(robotlaser, CarmenLaser)
    assert robotlaser.stamp == 100.25
    assert (robotlaser.angle_min, robotlaser.angle_increment, robotlaser.range_max) == (
        -1.0,
        1.0,
        20.0,
    )
    np.testing.assert_array_equal(robotlaser.laser_pose, [1.0, 1.0, 0.1])
    np.testing.assert_array_equal(robotlaser.odom_pose, [1.1, 1.1, 0.2])


def test_bz2_reads_identically(tmp_path: Path) -> None:
    plain = write_log(tmp_path, SMALL_LOG)
    packed = tmp_path / "log.clf.bz2"
    packed.write_bytes(bz2.compress(SMALL_LOG.encode("ascii")))
    disguised = tmp_path / "log_without_suffix"  # detected by its magic bytes
    disguised.write_bytes(packed.read_bytes())
    expected = as_tuples(plain)
    assert len(expected) == 5
    assert as_tuples(packed) == expected
    assert as_tuples(disguised) == expected


def test_a_broken_bz2_log_is_a_clear_error(tmp_path: Path) -> None:
    packed = bz2.compress(SMALL_LOG.encode("ascii"))
    cut = tmp_path / "cut.clf.bz2"  # a download that broke off
    cut.write_bytes(packed[: len(packed) // 2])
    junk = tmp_path / "junk.clf.bz2"  # not bzip2 at all
    junk.write_bytes(b"this is not a bzip2 stream\n" * 10)
    for path in (cut, junk):
        with pytest.raises(FileFormatError, match="cannot read CARMEN log"):
            list(read_carmen(path))
        with pytest.raises(FileFormatError, match="cannot read CARMEN log"):
            carmen_time_span(path)


def test_start_end_filter(tmp_path: Path) -> None:
    path = write_log(tmp_path, SMALL_LOG)
    stamps = [r.stamp for r in read_carmen(path, start=100.05, end=100.2)]
    assert stamps == [100.05, 100.15, 100.2]
    assert list(read_carmen(path, start=200.0)) == []


def test_params_and_time_span(tmp_path: Path) -> None:
    path = write_log(tmp_path, SMALL_LOG)
    params = read_carmen_params(path)
    assert params.frontlaser_offset_m == 0.25
    assert params.laser_fov_rad == pytest.approx(math.radians(100.0))
    assert params.laser_resolution_rad == pytest.approx(math.radians(50.0))
    assert params.laser_range_max_m == 30.0
    assert params.raw["robot_use_laser"] == "on"
    assert carmen_time_span(path) == (100.05, 100.25)


@pytest.mark.parametrize(
    ("bad_line", "message"),
    [
        ("FLASER 4 1.0 2.0 3.0 1.0 2.0 0.5 1.0 2.0 0.5 100.3 nohost 0.3", "expected 4 ranges"),
        ("FLASER 3 1.0 oops 3.0 1.0 2.0 0.5 1.0 2.0 0.5 100.3 nohost 0.3", "'oops'"),
        ("FLASER x 1.0 2.0", "integer beam count"),
        ("ODOM 1.0 2.0 0.5 0.0 0.0 100.3 nohost 0.3", "expected 9 fields"),
        ("ODOM 1.0 2.0 nan 0.0 0.0 0.0 100.3 nohost 0.3", "non-finite"),
        ("PARAM robot_frontlaser_offset abc nohost 0", "expected a number"),
        # one of these had every keyframe refused, or every scan dropped unexplained
        ("PARAM laser_front_laser_maxrange nan nohost 0", "expected a finite number"),
        ("PARAM robot_front_laser_max -5 nohost 0", "expected a value > 0"),
        ("PARAM laser_front_laser_resolution 0 nohost 0", "expected a value > 0"),
        ("PARAM laser_front_laser_fov inf nohost 0", "expected a finite number"),
        ("PARAM laser_front_laser_fov 720 nohost 0", "at most 360"),
        (
            "ROBOTLASER1 0 -1.0 2.0 0.0 20.0 0.01 0 3 7.0 8.0 9.0 0 1.0 1.0 0.1 1.1 1.1 0.2 "
            "0.3 0.01 0.5 0.5 0.3 100.3 nohost 0.3",
            "angular resolution and a maximum range > 0",
        ),
    ],
)
def test_malformed_line_raises_with_line_number(
    tmp_path: Path, bad_line: str, message: str
) -> None:
    lines = SMALL_LOG.splitlines()
    lines.insert(4, bad_line)  # becomes line 5
    path = write_log(tmp_path, "\n".join(lines) + "\n")
    with pytest.raises(FileFormatError, match=rf"log\.clf:5: .*{message}"):
        list(read_carmen(path))


def test_missing_file_raises(tmp_path: Path) -> None:
    with pytest.raises(FileFormatError, match="cannot open"):
        list(read_carmen(tmp_path / "absent.clf"))


@pytest.fixture(scope="module")
def intel_records() -> list[CarmenLaser | CarmenOdometry]:
    path = CARMEN / "intel.clf.bz2"
    if not path.is_file():
        pytest.skip(f"shared CARMEN data {path} is not present on this machine")
    return list(read_carmen(path))


def test_real_intel_log(intel_records: list[CarmenLaser | CarmenOdometry]) -> None:
    scans = [r for r in intel_records if isinstance(r, CarmenLaser)]
    odoms = [r for r in intel_records if isinstance(r, CarmenOdometry)]
    assert len(scans) == 13631
    assert len(odoms) == 26915
    assert all(len(s.ranges) == 180 for s in scans)
    assert scans[0].angle_increment == pytest.approx(math.radians(1.0))
    stamps = np.array([s.stamp for s in scans])
    # ipc stamps are unique but NOT monotonic in file order: 631 scans are logged up to
    # 0.9 s after a newer one. The reader keeps file order; consumers sort.
    assert len(np.unique(stamps)) == len(stamps)
    steps = np.diff(stamps)
    assert int((steps < 0).sum()) == 631
    assert steps.min() > -1.0
    assert stamps.min() == pytest.approx(976052857.33753)
    assert stamps.max() == pytest.approx(976055548.63389)


def test_laser_odometry_trajectory_is_sorted(tmp_path: Path) -> None:
    text = SMALL_LOG.replace("100.150000", "100.010000")  # second scan logged out of order
    traj = laser_odometry_trajectory(write_log(tmp_path, text))
    np.testing.assert_array_equal(traj.stamps, [100.01, 100.05, 100.25])
    np.testing.assert_allclose(traj.poses_se2()[0], [1.2, 2.4, 0.7])


def test_no_return_ranges_may_be_inf_or_nan_but_poses_may_not(tmp_path: Path) -> None:
    """A ROS LaserScan written to CARMEN keeps its "no return" as inf or nan: the whole
    record had been refused (a converted log would not start). Ranges take them (the
    agent's preprocessing drops such beams); poses and stamps must be finite."""
    good = "FLASER 3 1.0 inf nan 1.0 2.0 0.5 1.0 2.0 0.5 100.3 nohost 0.3"
    robot = (
        "ROBOTLASER1 0 -1.0 2.0 1.0 20.0 0.01 0 3 7.0 -inf 9.0 0 1.0 1.0 0.1 1.1 1.1 0.2 "
        "0.3 0.01 0.5 0.5 0.3 100.4 nohost 0.4"
    )
    bad = "FLASER 3 1.0 2.0 3.0 1.0 nan 0.5 1.0 2.0 0.5 100.5 nohost 0.5"
    recs = list(read_carmen(write_log(tmp_path, f"{good}\n{robot}\n")))
    assert np.isinf(recs[0].ranges[1]) and np.isnan(recs[0].ranges[2])
    assert np.isneginf(recs[1].ranges[1])
    with pytest.raises(FileFormatError, match="non-finite"):
        list(read_carmen(write_log(tmp_path, f"{bad}\n", "bad.clf")))


def test_a_torn_odom_line_does_not_stop_the_replay_from_starting(tmp_path: Path) -> None:
    """A logger killed mid-write leaves a torn last line; the replay drops it, but the
    pre-pass that looks at the ODOM stamps raised on it and the agent did not start."""
    path = write_log(tmp_path, SMALL_LOG + "ODOM 1.3 2.5 0.8 0.0\n")
    assert odometry_stamps_regular(path) is True  # (the two whole ODOM records)


def test_a_saturated_lasers_no_return_reading_is_found(tmp_path: Path) -> None:
    """ACES's laser writes 50.00 m for "no return", under CARMEN's guessed 80 m: taken as
    returns they drew walls 50 m around the building. The largest reading, when at least
    0.1 % of the readings are exactly that, is the laser's no-return value."""

    def log(name: str, saturated_scans: int) -> Path:
        lines = []
        rng = np.random.default_rng(0)
        for k in range(50):
            r = rng.uniform(0.5, 30.0, 180).round(2)
            if k < saturated_scans:
                r[:3] = 50.0
            lines.append(f"FLASER 180 {' '.join(map(str, r))} 0 0 0 0 0 0 {100 + k} nohost 0")
        return write_log(tmp_path, "\n".join(lines) + "\n", name)

    assert saturation_range_m(log("a.clf", 50)) == 50.0  # 1.7 % of the readings
    assert saturation_range_m(log("b.clf", 1)) is None  # 0.03 %: a real far wall


def test_aces_no_return_reading_is_50_m_and_intels_is_past_its_range_max(
    shared_data: Path,
) -> None:
    """On the real logs (the `shared_data` fixture: ../shared/data beside the checkout)."""
    for name, expected in (("aces.clf.bz2", 50.0), ("intel.clf.bz2", None)):
        assert saturation_range_m(shared_data / "carmen" / name) == expected


def test_eval_carmen_refuses_relations_of_another_log_before_it_flies(tmp_path: Path) -> None:
    """Relations none of which fall within the log's scans (another log's) had run the
    whole mission, then written NaN into the JSON (not JSON) and exited 0."""
    from collabslam.eval_carmen import eval_carmen
    from common.config import Config
    from common.errors import CollabSlamError

    log_path = write_log(tmp_path, SMALL_LOG)
    rel = tmp_path / "other.relations"
    rel.write_text("5000.0 5001.0 0.1 0 0 0 0 0.01\n")
    with pytest.raises(CollabSlamError, match="relations of another log"):
        eval_carmen(Config(), log_path, rel, 2, tmp_path / "out.json")
    assert not (tmp_path / "out").exists() and not (tmp_path / "out.json").exists()
