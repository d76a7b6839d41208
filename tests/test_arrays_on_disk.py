"""Per-keyframe arrays kept in memory-mapped temporary files (`common.growable`): they
grow in their file, and a base station keeping them there computes what one keeping
them in memory does."""

from __future__ import annotations

import logging
import resource
import signal
from pathlib import Path

import numpy as np
import pytest
from process_helpers import synthetic_keyframe

from basestation.node import BaseStationNode
from collabslam.cli import arrays_on_disk
from common.bus import Bus
from common.config import Config
from common.errors import ConfigError
from common.geometry import se2_compose
from common.growable import Rows, empty, grown, keep_on_disk, on_disk


@pytest.fixture
def arrays_dir(tmp_path: Path):
    keep_on_disk(str(tmp_path))
    try:
        yield tmp_path
    finally:
        keep_on_disk(None)


def test_an_array_on_disk_grows_in_its_file(arrays_dir: Path) -> None:
    a = empty((3,), np.float32)
    assert a.shape == (0, 3) and on_disk(a)
    a = grown(a, 10, fill=-1)
    assert len(a) == 64 and on_disk(a) and np.all(a == -1)
    a[:10] = np.arange(30).reshape(10, 3)
    old = a[:10]
    b = grown(a, 65)
    assert len(b) == 80 and on_disk(b) and on_disk(b[5:7])
    np.testing.assert_array_equal(b[:10], np.arange(30).reshape(10, 3))
    assert np.all(b[64:] == 0)  # fill 0: the file's new bytes
    b[0] = 7  # one file: the rows before the growth see it
    assert old[0].tolist() == [7, 7, 7]
    r = Rows(2, np.int64)
    for i in range(1000):
        r.append((i, -i))
    assert on_disk(r.view()) and r[999].tolist() == [999, -999] and len(r) == 1000
    assert not on_disk(r.view() + 1) and not on_disk(np.zeros(3))
    assert not on_disk(grown(empty((2,), np.int64, memory=True), 5))
    keep_on_disk(None)
    assert not on_disk(empty((3,), np.float32)) and not on_disk(Rows(2).view())


def test_keep_on_disk_refuses_a_directory_it_cannot_write(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="not a writable directory"):
        keep_on_disk(str(tmp_path / "missing"))
    assert not on_disk(empty((), np.int32))


def _tour(robot: str, n: int, y: float) -> list:
    """Back and forth along a 4 m line, 0.2 m apart."""
    out, T = [], np.array([0.0, y, 0.0])
    for k in range(n):
        d = np.zeros(3) if k == 0 else np.array([0.2, 0.0, np.pi if k % 20 == 0 else 0.0])
        T = se2_compose(T, d)
        out.append(synthetic_keyframe(robot, k, T, d, 1081, 1.5 * np.pi, 3.0, 0.5, 0.1))
    return out


def _run(cfg: Config, bus: Bus, kfs: list) -> BaseStationNode:
    node = BaseStationNode(cfg, bus, None)
    for k in range(0, len(kfs), 40):
        node.process(kfs[k : k + 40])
        node.refresh_map()
    node.map.finish()
    return node


def test_a_base_station_with_its_arrays_on_disk_makes_the_same_map_and_poses(
    cfg: Config, endpoint: str, tmp_path: Path
) -> None:
    cfg.zenoh.listen = [endpoint]
    cfg.exploration.enabled = False
    cfg.basestation.constraints.enabled = False
    cfg.basestation.reduce_after_nodes = 100  # aliases too
    a, b = _tour("r0", 300, 0.0), _tour("r1", 300, 1.0)
    kfs = [kf for pair in zip(a, b, strict=True) for kf in pair]
    with Bus(cfg.zenoh, cfg.fleet) as bus:
        plain = _run(cfg, bus, kfs)
        keep_on_disk(str(tmp_path))
        try:
            disk = _run(cfg, bus, kfs)
        finally:
            keep_on_disk(None)
    chain = disk.slam.graph._chains["r0"]
    assert on_disk(chain.alias_key) and on_disk(chain.alias_offset) and on_disk(disk.map._pose)
    assert on_disk(disk.slam.store.robot("r1").poses_odom.view())
    assert not on_disk(plain.map._pose)
    assert np.sum(chain.alias_key[: chain.num_committed] >= 0) > 50  # the reduction ran
    for rid, t in plain.slam.trajectories().items():
        other = disk.slam.trajectories()[rid]
        assert len(t.stamps) == 300
        np.testing.assert_array_equal(other.stamps, t.stamps)
        np.testing.assert_array_equal(other.positions, t.positions)
        np.testing.assert_array_equal(other.quats_xyzw, t.quats_xyzw)
    np.testing.assert_array_equal(disk.map.grid.log_odds, plain.map.grid.log_odds)


def test_an_array_the_disk_has_no_room_for_goes_on_in_memory(
    arrays_dir: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """A full disk (here: a file-size limit) makes growth an error it survives, not a
    SIGBUS when a page of the file is first written."""
    a = grown(empty((4,), np.float64), 100, fill=1.0)
    assert on_disk(a)
    limit = resource.getrlimit(resource.RLIMIT_FSIZE)
    handler = signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # EFBIG instead of a kill
    try:
        resource.setrlimit(resource.RLIMIT_FSIZE, (a.nbytes + 8192, limit[1]))
        with caplog.at_level(logging.WARNING, logger="common.growable"):
            b = grown(a, 1000, fill=2.0)
    finally:
        resource.setrlimit(resource.RLIMIT_FSIZE, limit)
        signal.signal(signal.SIGXFSZ, handler)
    assert not on_disk(b) and len(b) == 1000
    assert np.all(b[:100] == 1.0) and np.all(b[100:] == 2.0)
    assert "cannot grow on disk" in caplog.text


def test_the_database_folder_is_made_for_the_arrays_next_to_it(tmp_path: Path) -> None:
    """`--db DIR/sub/mission.db` with sub/ missing (a systemd unit's state directory holds
    only its top folder): the folder is made, not refused."""
    db = tmp_path / "basestation" / "mission.db"
    try:
        arrays_on_disk("", str(db))
        assert db.parent.is_dir()
        assert on_disk(empty((3,), np.float64))
    finally:
        keep_on_disk(None)
    with pytest.raises(ConfigError, match="not a writable directory"):
        arrays_on_disk(str(tmp_path / "missing"), str(db))
