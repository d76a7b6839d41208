"""The odometry a CARMEN replay gives each scan: interpolated at the scan's stamp where
the log's ODOM stamps are regular (ACES), as logged with the scan where they come in
bursts (Intel)."""

from __future__ import annotations

import math
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from agent.carmen_log import carmen_time_span, odometry_stamps_regular, read_carmen
from agent.sensor_sources import CarmenReplay, OdometryTrack
from common.errors import ConfigError, FileFormatError
from common.geometry import pose7_to_pose4
from protocol import LaserScan, Odometry


def odom_line(x: float, y: float, th: float, stamp: float) -> str:
    return f"ODOM {x} {y} {th} 0.0 0.0 0.0 {stamp:.6f} nohost 0.0\n"


def flaser_line(pose: tuple[float, float, float], stamp: float) -> str:
    x, y, th = pose
    return f"FLASER 3 1.0 2.0 3.0 {x} {y} {th} {x} {y} {th} {stamp:.6f} nohost 0.0\n"


def regular_log(tmp_path: Path) -> Path:
    """ODOM at 4 Hz moving 1 m/s along x; each scan 0.1 s after an ODOM carries that
    ODOM's (0.1 s old) pose, as ACES's FLASER records do."""
    text = ""
    for k in range(12):
        t = 100.0 + 0.25 * k
        text += odom_line(0.25 * k, 0.0, 0.0, t)
        text += flaser_line((0.25 * k, 0.0, 0.0), t + 0.1)
    path = tmp_path / "regular.clf"
    path.write_text(text)
    return path


def replayed_odometry(path: Path) -> dict[float, np.ndarray]:
    out: dict[float, np.ndarray] = {}
    for m in CarmenReplay(path, "r0").messages(threading.Event()):
        if isinstance(m, Odometry):
            out[round(m.stamp, 6)] = pose7_to_pose4(m.pose)[[0, 1, 3]]
        else:
            assert isinstance(m, LaserScan)
    return out


def test_track_interpolates_position_and_yaw_the_short_way() -> None:
    track = OdometryTrack()
    track.add(1.0, np.array([0.0, 0.0, math.pi - 0.1]))
    track.add(0.0, np.array([-2.0, 4.0, 0.0]))  # older record added later: kept in order
    track.add(2.0, np.array([2.0, 2.0, -math.pi + 0.1]))
    np.testing.assert_allclose(track.at(0.5, np.zeros(3)), [-1.0, 2.0, (math.pi - 0.1) / 2])
    p = track.at(1.5, np.zeros(3))
    np.testing.assert_allclose(p[:2], [1.0, 1.0])
    assert abs(abs(p[2]) - math.pi) < 1e-9  # across +-pi, not through 0
    np.testing.assert_allclose(track.at(2.0, np.zeros(3)), [2.0, 2.0, -math.pi + 0.1])


def test_track_falls_back_outside_its_records_and_across_gaps() -> None:
    track = OdometryTrack(max_gap_s=1.0)
    fallback = np.array([7.0, 8.0, 0.5])
    assert len(track.at(1.0, fallback)) == 3 and np.array_equal(track.at(1.0, fallback), fallback)
    track.add(1.0, np.zeros(3))
    track.add(3.0, np.ones(3))  # 2 s apart: no interpolation between them
    for stamp in (0.5, 2.0, 3.5):
        np.testing.assert_array_equal(track.at(stamp, fallback), fallback)
    track.add(3.5, np.full(3, 2.0))
    track.forget_before(3.4)
    np.testing.assert_allclose(track.at(3.25, fallback), [1.5, 1.5, 1.5])  # one older kept


def test_regular_stamps_give_each_scan_the_odometry_at_its_stamp(tmp_path: Path) -> None:
    path = regular_log(tmp_path)
    assert odometry_stamps_regular(path)
    odometry = replayed_odometry(path)
    assert len(odometry) == 12
    for stamp, pose in odometry.items():
        if stamp < 102.75:  # bracketed by two ODOM records
            np.testing.assert_allclose(pose, [stamp - 100.0, 0.0, 0.0], atol=1e-9)
    # the last scan has no newer ODOM: the pose logged with it
    np.testing.assert_allclose(odometry[102.85], [2.75, 0.0, 0.0])


def test_bursty_stamps_keep_the_pose_logged_with_each_scan(tmp_path: Path) -> None:
    text = ""
    for k in range(12):  # ODOM pairs delivered 0.1 ms apart, as in the Intel log
        t = 100.0 + 0.25 * k
        text += odom_line(0.25 * k, 0.0, 0.0, t) + odom_line(0.25 * k + 0.1, 0.0, 0.0, t + 1e-4)
        text += flaser_line((0.25 * k + 0.1, 0.0, 0.0), t + 0.2)
    path = tmp_path / "bursty.clf"
    path.write_text(text)
    assert not odometry_stamps_regular(path)
    for stamp, pose in replayed_odometry(path).items():
        k = round((stamp - 100.2) / 0.25)
        np.testing.assert_allclose(pose, [0.25 * k + 0.1, 0.0, 0.0], atol=1e-9)


def test_no_odom_records_means_the_logged_poses(tmp_path: Path) -> None:
    path = tmp_path / "lasers_only.clf"
    path.write_text("".join(flaser_line((float(k), 0.0, 0.0), 100.0 + k) for k in range(3)))
    assert not odometry_stamps_regular(path)
    odometry = replayed_odometry(path)
    np.testing.assert_allclose([p[0] for p in odometry.values()], [0.0, 1.0, 2.0])


@pytest.mark.parametrize(("log", "regular"), [("aces", True), ("intel", False)])
def test_the_shipped_logs_are_told_apart(log: str, regular: bool, shared_data: Path) -> None:
    path = shared_data / "carmen" / f"{log}.clf.bz2"  # the shared real logs
    assert path.is_file(), f"shared CARMEN log {path} is missing"
    assert odometry_stamps_regular(path) is regular


def test_a_paced_replay_keeps_the_log_pace_from_a_shared_start(tmp_path: Path) -> None:
    """`rate` log seconds per wall second from `start_unix`: the 12 scans span 2.75 s of
    log, so at rate 10 the last comes no sooner than 0.275 s after the start (a lower
    bound: a loaded machine can only be later). Rate 0 replays at once."""
    path = regular_log(tmp_path)
    start = time.time() + 0.2  # a start shared by several replays may lie ahead
    stamps = []
    for m in CarmenReplay(path, "r0", rate=10.0, start_unix=start).messages(threading.Event()):
        if isinstance(m, LaserScan):
            stamps.append(time.time())
    assert len(stamps) == 12
    assert stamps[0] >= start
    assert stamps[-1] - start >= 0.275 - 1e-3
    with pytest.raises(ConfigError):
        CarmenReplay(path, "r0", rate=-1.0)


def test_a_log_or_segment_without_scans_is_refused_up_front(tmp_path: Path) -> None:
    """Not a replay that runs and reports "0 scans" at the end."""
    empty = tmp_path / "empty.clf"
    empty.write_text("# nothing but a comment\n")
    with pytest.raises(FileFormatError, match="no well-formed FLASER or ROBOTLASER1 record"):
        CarmenReplay(empty, "r0")
    path = regular_log(tmp_path)  # scans at 100.1-102.85 s
    with pytest.raises(ConfigError, match="holds no scan"):
        CarmenReplay(path, "r0", (200.0, None))
    with pytest.raises(ConfigError, match="holds no scan"):
        CarmenReplay(path, "r0", (None, 50.0))
    assert CarmenReplay(path, "r0", (101.0, 102.0)).scans == 0  # a segment inside is fine


def test_a_malformed_line_deep_in_a_log_is_dropped_and_the_replay_goes_on(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """A truncated FLASER and one with a word for a range, between good records: both are
    logged with their line numbers and dropped; every good scan is still replayed."""
    lines = regular_log(tmp_path).read_text().splitlines(keepends=True)
    lines.insert(9, "FLASER 3 1.0 2.0\n")  # truncated
    lines.insert(15, flaser_line((9.0, 0.0, 0.0), 101.6).replace(" 2.0 ", " nan? ", 1))
    path = tmp_path / "damaged.clf"
    path.write_text("".join(lines))
    with pytest.raises(FileFormatError, match=r"damaged\.clf:10: FLASER"):
        list(read_carmen(path))  # the strict reader (eval tools, tests) still refuses
    assert carmen_time_span(path) == (100.1, 102.85)  # not the truncated line's "1.0"
    with caplog.at_level("ERROR"):
        odometry = replayed_odometry(path)
    assert len(odometry) == 12  # all good scans, none of the bad
    dropped = [r.getMessage() for r in caplog.records if "line dropped" in r.getMessage()]
    assert len(dropped) == 2
    assert "damaged.clf:10:" in dropped[0] and "damaged.clf:16:" in dropped[1]


def test_a_laser_mounted_off_the_robot_is_named(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """The logged laser pose 0.3 m ahead of the robot's: the offset is not applied (local
    SLAM tracks the laser), which the replay says instead of silently scoring the laser's
    trajectory as the robot's (0.051 m against 0.003 m in the review's flight)."""
    path = tmp_path / "mounted.clf"
    path.write_text(
        "".join(
            f"FLASER 3 1.0 2.0 3.0 {0.25 * k + 0.3} 0.0 0.0 {0.25 * k} 0.0 0.0 {100 + k} nohost 0\n"
            for k in range(3)
        )
    )
    with caplog.at_level("WARNING"):
        replayed_odometry(path)
    assert "mounted at [0.3 0.  0. ] from the robot" in caplog.text
    caplog.clear()
    with caplog.at_level("WARNING"):
        replayed_odometry(regular_log(tmp_path))
    assert "mounted at" not in caplog.text
