"""An agent's state folder (`agent.state_dir`): its keyframes and where it was, read
back by an agent restarted on it (end to end: tests/test_agent_restart.py)."""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path

import numpy as np

from agent.keyframe_history import KeyframeHistory
from agent.local_trajectory_builder import LocalTrajectoryBuilder
from agent.outbox import Outbox
from agent.resume import STATE_FILE, ResumePoint, load, save
from common.config import Config


def test_keyframes_on_disk_are_read_back_up_to_a_torn_one(tmp_path: Path, caplog) -> None:
    h = KeyframeHistory(6, tmp_path)  # files of 3
    for seq in range(8):
        h.add(seq, b"kf%d" % seq)
    assert sorted(p.name for p in tmp_path.iterdir()) == [
        "keyframes-0000000003.log",
        "keyframes-0000000006.log",
    ]
    newest = tmp_path / "keyframes-0000000006.log"
    newest.write_bytes(newest.read_bytes() + b"\x10\x00\x00\x00kf8")  # killed mid-write
    with caplog.at_level(logging.WARNING):
        again = KeyframeHistory(6, tmp_path)
    assert "cut short" in caplog.text
    assert (again.first_seq, again.next_seq) == (3, 8)
    assert list(again.payloads()) == [b"kf%d" % s for s in range(3, 8)]
    assert list(again.payloads(start_seq=6)) == [b"kf6", b"kf7"]
    again.add(8, b"kf8")  # goes on after the torn record, not behind it
    assert list(KeyframeHistory(6, tmp_path).payloads(7)) == [b"kf7", b"kf8"]


def test_outbox_restored_from_disk_sends_what_was_not_acknowledged(tmp_path: Path) -> None:
    box = Outbox(100, 0.8, 1.0, 50, history=KeyframeHistory(100, tmp_path))
    for seq in range(6):
        box.add(seq, b"kf%d" % seq)
    box.ack(3)
    again = Outbox(100, 0.8, 1.0, 50, history=KeyframeHistory(100, tmp_path))
    again.restore(acked_seq=3, next_seq=6)
    assert (again.acked_seq, again.added_seq, len(again)) == (3, 5, 2)
    assert again.due_for_resend() == [b"kf4", b"kf5"]  # at once
    again.add(6, b"kf6")
    assert again.ack(6) == 3


def test_state_is_taken_up_only_when_recent_and_whole(tmp_path: Path, caplog) -> None:
    point = ResumePoint(0, 12, 9, 4, [1.0, 2.0, 0.0, 0.5], 30.0, [3, 4, 1, 0.1], [5, 6, 0.2],
                        [[0.0, 1.0], [2.0, 3.0]], 1, [2.9, 4, 1, 0.1], 0.5)  # fmt: skip
    save(tmp_path, point)
    (tmp_path / "keyframes-0000000000.log").write_bytes(b"")
    got = load(tmp_path, max_age_s=60.0)
    assert got is not None and (got.next_seq, got.acked_seq, got.epoch) == (12, 9, 4)
    assert got.path == [[0.0, 1.0], [2.0, 3.0]] and got.path_index == 1
    assert got.keyframe_pose == [2.9, 4, 1, 0.1] and got.clock_offset == 0.5
    raw = json.loads((tmp_path / STATE_FILE).read_text())
    raw["saved_unix"] = time.time() - 3600.0  # another mission's
    (tmp_path / STATE_FILE).write_text(json.dumps(raw))
    with caplog.at_level(logging.WARNING):
        assert load(tmp_path, max_age_s=60.0) is None
    # its 2 keyframes no base station acknowledged are kept aside, not sent (they had been
    # deleted: a drone restarted after a battery swap lost what it mapped with no link)
    (kept,) = tmp_path.iterdir()
    assert kept.name.startswith("unsent-") and "2 keyframes (seqs 10-11 of chain 0)" in caplog.text
    assert sorted(p.name for p in kept.iterdir()) == [
        "keyframes-0000000000.log",
        "path-0.json",
        STATE_FILE,
    ]
    kept.rename(tmp_path.parent / f"{tmp_path.name}-kept")
    save(tmp_path, ResumePoint(0, 12, 11, keyframe_pose=[0.0, 0.0, 1.0, 0.0]))  # all acked
    (tmp_path / "keyframes-0000000000.log").write_bytes(b"")
    raw = json.loads((tmp_path / STATE_FILE).read_text())
    raw["saved_unix"] = time.time() - 3600.0
    (tmp_path / STATE_FILE).write_text(json.dumps(raw))
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        assert load(tmp_path, max_age_s=60.0) is None
    assert "another mission's state" in caplog.text and not list(tmp_path.iterdir())
    for bad in ('{"chain": 0}', "[1, 2", json.dumps({**raw, "next_seq": -3})):
        (tmp_path / STATE_FILE).write_text(bad)
        assert load(tmp_path, max_age_s=1e9) is None  # logged, deleted, afresh
        assert not (tmp_path / STATE_FILE).exists()


def test_a_state_of_the_version_before_is_taken_up(tmp_path: Path) -> None:
    """Written before `session` and `odom_origin` were: taken up in session 0, not
    deleted with the keyframes it had not got acknowledged. A session beyond 32 bits
    (every keyframe would fail its check) is not."""
    point = ResumePoint(0, 12, 9, 4, [1.0, 2.0, 0.0, 0.5], 30.0, [3, 4, 1, 0.1], [5, 6, 0.2],
                        None, 0, [2.9, 4, 1, 0.1], 0.5, 7, [1.0, 2.0, 0.1])  # fmt: skip
    save(tmp_path, point)
    assert load(tmp_path, 60.0) == point  # (saved_unix set by save)
    raw = json.loads((tmp_path / STATE_FILE).read_text())
    old = {k: v for k, v in raw.items() if k not in ("session", "odom_origin")}
    (tmp_path / STATE_FILE).write_text(json.dumps(old))
    got = load(tmp_path, 60.0)
    assert got is not None and (got.next_seq, got.session, got.odom_origin) == (12, 0, None)
    (tmp_path / STATE_FILE).write_text(json.dumps({**raw, "session": 2**32}))
    assert load(tmp_path, 60.0) is None


def test_local_slam_goes_on_from_the_last_keyframe_by_the_odometry_since() -> None:
    cfg = Config().agent
    ltb = LocalTrajectoryBuilder(cfg.local_slam, cfg.local_keyframe_period_s)
    ltb.resume(10.0, np.array([3.0, 1.0, 1.0, np.pi / 2]), np.array([7.0, 0.0, 0.0]))
    ltb.add_odometry(11.0, np.array([8.0, 0.0, 0.0]))  # 1 m ahead in the source's frame
    np.testing.assert_allclose(ltb.extrapolator.predict(11.0), [3.0, 2.0, np.pi / 2])
    np.testing.assert_allclose(ltb.odometry_at(11.0), [8.0, 0.0, 0.0])


def _kf_payload(seq: int, chain: int = 0) -> bytes:
    from process_helpers import synthetic_keyframe

    from protocol import Keyframe, encode

    kf = synthetic_keyframe("r0", seq, np.array([0.5 * seq, 0.0, 0.0]), np.array([0.5, 0, 0]))
    return encode(Keyframe(**{**kf.__dict__, "chain": chain}))


def _uplink(cfg: Config, endpoint: str, state: Path, resume: ResumePoint):  # noqa: ANN202
    from agent.uplink import KeyframeUplink
    from common.bus import Bus
    from common.config import ZenohConfig

    cfg.agent.state_dir = str(state)
    bus = Bus(ZenohConfig(listen=[endpoint]), cfg.fleet)
    return bus, KeyframeUplink(cfg.agent, "r0", bus, resume)


def test_a_keyframe_sent_after_the_last_save_is_gone_on_from(
    cfg: Config, endpoint: str, tmp_path: Path
) -> None:
    """Killed between sending keyframe 5 and saving the state (which says 5 is next):
    the restarted agent had sent another keyframe 5 (two sources to the base station)
    and emptied its history; it goes on from the history's last record now."""
    h = KeyframeHistory(100, tmp_path)
    for seq in range(6):
        h.add(seq, _kf_payload(seq))
    point = ResumePoint(0, 5, 2, keyframe_pose=[2.0, 0.0, 1.0, 0.0])
    bus, up = _uplink(cfg, endpoint, tmp_path, point)
    with bus:
        assert (up.chain, up.next_seq, up.outbox.acked_seq, len(up.outbox)) == (0, 6, 2, 3)
        np.testing.assert_allclose(up.last_pose, [2.5, 0.0, 1.0, 0.0])  # keyframe 5's
        assert len(up.outbox.history) == 6


def test_a_new_chain_started_after_the_last_save_is_gone_on_with(
    cfg: Config, endpoint: str, tmp_path: Path
) -> None:
    h = KeyframeHistory(100, tmp_path)
    for seq in range(4):
        h.add(seq, _kf_payload(seq, chain=1))  # relabelled, then killed before the save
    bus, up = _uplink(cfg, endpoint, tmp_path, ResumePoint(0, 40, 30, keyframe_pose=[0] * 4))
    with bus:
        assert (up.chain, up.next_seq, up.outbox.acked_seq, len(up.outbox)) == (1, 4, -1, 4)


def test_one_lost_chain_starts_one_new_chain(cfg: Config, endpoint: str, tmp_path: Path) -> None:
    from protocol import KeyframeAck

    bus, up = _uplink(cfg, endpoint, tmp_path, ResumePoint())
    with bus:
        for seq in range(3):
            up.outbox.add(seq, _kf_payload(seq))
        up.on_ack(KeyframeAck("r0", 1, 0))
        up.on_ack(KeyframeAck("r0", -1, 0))  # a new base station has none of them ...
        up.on_ack(KeyframeAck("r0", -1, 0))  # ... said twice
        assert up.resend() and (up.chain, up.next_seq) == (1, 3)
        up.on_ack(KeyframeAck("r0", -1, 0))  # late, about chain 0: ignored
        assert not up.resend() and up.chain == 1
        assert up.outbox.ack(2, chain=0) == 0 and len(up.outbox) == 3  # nor its acks
        assert up.outbox.ack(2, chain=1) == 3


def test_a_disk_error_turns_the_history_off(tmp_path: Path, caplog) -> None:
    h = KeyframeHistory(4, tmp_path / "gone")
    (tmp_path / "gone").mkdir()
    h.add(0, b"kf0")
    h.add(1, b"kf1")
    (tmp_path / "gone" / "keyframes-0000000000.log").unlink()
    (tmp_path / "gone").rmdir()  # the next file cannot be made
    with caplog.at_level(logging.ERROR):
        h.add(2, b"kf2")  # no exception: the agent flies on
        h.add(3, b"kf3")
    assert "keyframe history off" in caplog.text and len(h) == 0


def test_a_state_that_cannot_be_written_is_logged_and_flown_on(tmp_path: Path, caplog) -> None:
    """A full or read-only disk had raised out of the agent's loop (it saves its state
    at every state message, 5 Hz, hovering too): the process died in flight."""
    (tmp_path / "file").write_text("")  # not a folder: every write fails
    point = ResumePoint(0, 12, 9, 4, None, 30.0, [3, 4, 1, 0.1], None, [], 0, [3, 4, 1, 0.1], 0.0)
    with caplog.at_level(logging.ERROR):
        assert not save(tmp_path / "file", point) and not save(tmp_path / "file", point)
        assert caplog.text.count("state not saved") == 1  # once, until one succeeds
        assert save(tmp_path, point) and (tmp_path / STATE_FILE).exists()


def test_keyframes_and_state_are_on_the_disk_itself_before_the_agent_goes_on(
    tmp_path: Path, monkeypatch
) -> None:
    """Flushed to the operating system only, a power cut and reboot within
    `agent.resume_within_s` left the files a few keyframes behind what the base station
    had acknowledged: the agent re-cut those seqs and the base station froze the robot
    out as another source. Each keyframe (in a state folder) and each state are now
    synced to the disk before the agent sends it on; temporary history files are not."""
    import os

    synced: list[int] = []
    real = os.fdatasync
    monkeypatch.setattr(os, "fdatasync", lambda fd: (synced.append(fd), real(fd))[1])
    kept = KeyframeHistory(10, tmp_path)
    kept.add(0, b"a")
    kept.add(1, b"b")
    assert len(synced) == 2
    KeyframeHistory(10).add(0, b"a")  # no folder: nothing to keep across a reboot
    assert len(synced) == 2
    save(tmp_path, ResumePoint(0, 2, 1, session=7, keyframe_pose=[0, 0, 1, 0], stamp=1.0))
    assert len(synced) == 3 and load(tmp_path, 60.0).session == 7
    kept.replace([b"%d" % k for k in range(12)])  # a new chain: once a file, not a keyframe
    assert len(synced) == 3 + 3 and len(list(kept.payloads())) == 12


def test_the_path_is_written_when_it_changes_not_at_every_state(tmp_path: Path) -> None:
    """A 2,000-waypoint tour had been written whole into every state (5 a second, on the
    control thread: ~10 ms a save). It goes to a file of its own when it changes; the
    state names it, and a resumed agent gets it back."""
    tour = [[0.5 * k, 1.0] for k in range(2000)]
    point = ResumePoint(0, 3, 1, keyframe_pose=[0.0, 0.0, 1.0, 0.0], path=tour, path_index=7)
    assert save(tmp_path, point)
    (written,) = tmp_path.glob("path-*.json")
    first = written.stat().st_ino
    for index in range(8, 12):  # states while flying it: the path file is not written again
        point.path, point.path_index = [list(p) for p in tour], index
        assert save(tmp_path, point)
    assert [p.stat().st_ino for p in tmp_path.glob("path-*.json")] == [first]
    assert (tmp_path / STATE_FILE).stat().st_size < 1000
    got = load(tmp_path, max_age_s=60.0)
    assert got is not None and got.path == tour and got.path_index == 11
    point.path = [[1.0, 2.0]]  # a new path: a new file, the old one gone
    assert save(tmp_path, point)
    assert [p.name for p in tmp_path.glob("path-*.json")] == ["path-1.json"]
    assert load(tmp_path, max_age_s=60.0).path == [[1.0, 2.0]]
    (tmp_path / "path-1.json").unlink()  # the state names a file that is gone: afresh
    assert load(tmp_path, max_age_s=60.0) is None and not list(tmp_path.iterdir())


def test_an_unreadable_state_keeps_its_keyframes_aside(tmp_path: Path, caplog) -> None:
    """A state this program cannot read (another version's, after a rollback: its path in
    a file the older one does not know) had been deleted with its keyframes."""
    save(tmp_path, ResumePoint(0, 5, 1, keyframe_pose=[0.0, 0.0, 1.0, 0.0]))
    (tmp_path / "keyframes-0000000000.log").write_bytes(b"kept")
    (tmp_path / STATE_FILE).write_text('{"chain": 0}')
    with caplog.at_level(logging.ERROR):
        assert load(tmp_path, max_age_s=60.0) is None
    (kept,) = tmp_path.iterdir()
    assert kept.name.startswith("unreadable-") and "its keyframes kept in" in caplog.text
    assert (kept / "keyframes-0000000000.log").read_bytes() == b"kept"


def test_a_second_agent_on_a_state_folder_in_use_is_refused(tmp_path: Path) -> None:
    """A second agent on a running one's folder (a manual start beside the systemd unit)
    had taken over its session and keyframe numbers: the base station then dropped the
    robot's keyframes for the rest of the mission."""
    import subprocess
    import sys

    load(tmp_path, 60.0)  # this process holds it now (and may load it again)
    load(tmp_path, 60.0)
    other = subprocess.run(
        [sys.executable, "-c", "import sys; from pathlib import Path; from agent.resume import "
         "load; load(Path(sys.argv[1]), 60.0)", str(tmp_path)],
        capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert other.returncode != 0 and "in use by another agent" in other.stderr
