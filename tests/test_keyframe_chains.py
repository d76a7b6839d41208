"""Keyframe chains: an agent whose acknowledged keyframes a new base station has not
(its database lost) sends what it kept, on disk and in its outbox, renumbered from
seq 0 as a new chain; the base station follows it (end to end with real processes:
tests/test_basestation_recovery.py)."""

from __future__ import annotations

import logging
from pathlib import Path

import msgpack
import numpy as np
import pytest
from process_helpers import synthetic_keyframe

from agent import keyframe_history as kh
from agent.keyframe_history import KeyframeHistory
from agent.outbox import IDENTITY7, Outbox
from basestation.global_slam import GlobalSlam
from basestation.keyframe_store import KeyframeStore
from basestation.persistence import Recovered
from common.config import Config
from common.errors import ProtocolError
from protocol import Keyframe, KeyframeAck, decode, encode
from protocol.codec import relabel


def _kf(seq: int, chain: int = 0) -> Keyframe:
    """Keyframe `seq` of r0, 0.5 m apart along x (0.5 s each)."""
    kf = synthetic_keyframe("r0", seq, np.array([0.5 * seq, 0.0, 0.0]), np.array([0.5, 0, 0]))
    return Keyframe(**{**kf.__dict__, "chain": chain})


def test_history_keeps_the_latest_on_disk_in_two_files() -> None:
    h = KeyframeHistory(max_keyframes=10)
    for seq in range(23):
        h.add(seq, b"kf%d" % seq)
    # files of 5: 0-4, 5-9, 10-14, 15-19, 20-22; the two latest are kept
    assert (h.first_seq, len(h), h.dropped) == (15, 8, 15)
    assert list(h.payloads()) == [b"kf%d" % s for s in range(15, 23)]
    h.add(30, b"kf30")  # not the next one: what came before cannot precede it
    assert (h.first_seq, list(h.payloads())) == (30, [b"kf30"])
    off = KeyframeHistory(max_keyframes=0)
    off.add(0, b"x")
    assert len(off) == 0 and off.first_seq is None


def test_outbox_sends_history_and_pending_as_a_new_chain() -> None:
    box = Outbox(100, 0.8, 1.0, 50, history=KeyframeHistory(1000))
    for seq in range(8):
        box.add(seq, encode(_kf(seq)))
    assert box.ack(4) == 5
    assert len(box.history) == 8 and len(box) == 3  # every keyframe cut is on disk
    assert box.new_chain(1) == 8
    assert (box.acked_seq, box.added_seq, len(box), len(box.history)) == (-1, 7, 8, 8)
    sent = [decode(p, Keyframe) for p in box.due_for_resend()]  # at once, not on a timer
    assert [k.seq for k in sent] == list(range(8)) and {k.chain for k in sent} == {1}
    assert [k.stamp for k in sent] == [_kf(s).stamp for s in range(8)]  # the same ones
    np.testing.assert_array_equal(sent[0].delta, IDENTITY7)  # nothing precedes it now
    np.testing.assert_array_equal(sent[3].delta, _kf(3).delta)
    box.add(8, encode(_kf(8, chain=1)))  # the next keyframe cut follows on
    assert box.ack(8) == 9 and len(box.history) == 9
    assert [decode(p, Keyframe).chain for p in box.history.payloads()] == [1] * 9


def test_a_new_chain_starts_at_the_oldest_keyframe_kept(caplog) -> None:
    box = Outbox(100, 0.8, 1.0, 50, history=KeyframeHistory(4))  # keeps the latest 2-4
    for seq in range(8):
        box.add(seq, encode(_kf(seq)))
        if seq <= 4:
            box.ack(seq)
    with caplog.at_level(logging.WARNING):
        assert box.new_chain(1) == 4  # seqs 4 (acknowledged) to 7
    assert "(4 acknowledged before were not kept)" in caplog.text
    sent = [decode(p, Keyframe) for p in box.due_for_resend()]
    assert [k.stamp for k in sent] == [_kf(s).stamp for s in range(4, 8)]


def test_history_keeps_every_keyframe_not_acknowledged() -> None:
    """A restarted agent must send them again: the history's bound (latest 2-4 here)
    does not cut into them (before, 20,000 unacknowledged but 10,000 kept)."""
    box = Outbox(100, 0.8, 1.0, 50, history=KeyframeHistory(4))
    for seq in range(9):
        box.add(seq, encode(_kf(seq)))
    assert (box.history.first_seq, len(box.history)) == (0, 9)
    box.ack(6)
    box.add(9, encode(_kf(9)))
    box.add(10, encode(_kf(10)))  # a new file: the ones before 6 may go now
    assert box.history.first_seq == 6 and box.history.dropped == 6
    assert box.new_chain(1) == 5 and len(box.history) == 5  # none acknowledged: all kept


def test_store_follows_a_new_chain_from_the_keyframes_it_has(caplog) -> None:
    st = KeyframeStore()
    none = st.none_of("r0", 0, 300)  # an agent that says some were acknowledged is told -1
    assert (none.robot_id, none.acked_seq, none.chain) == ("r0", -1, 0)
    for seq in (300, 301):  # the old chain's, resent after the outage: held
        assert st.admit(_kf(seq)) == []
    assert st.ack("r0") is None  # nothing to acknowledge
    with caplog.at_level(logging.WARNING):
        assert st.admit(_kf(1, chain=1)) == []
        assert "starts keyframe chain 1" in caplog.text
    r = st.robot("r0")
    assert r.chain == 1 and list(r.held) == [1]  # the old chain's are dropped
    assert st.none_of("r0", 0, 300) is None  # a state from before the switch
    assert st.none_of("r0", 1, 5).chain == 1 and st.none_of("r9", 2, 5).chain == 2  # (twice)
    assert [k.seq for k in st.admit(_kf(0, chain=1))] == [0, 1]
    assert st.admit(_kf(302)) == [] and r.stale_chain == 1  # in flight before the switch
    ack = st.ack("r0")
    assert (ack.acked_seq, ack.chain) == (1, 1) and st.none_of("r0", 0, 300) is None
    assert st.none_of("r0", 1, 2) is None and st.acknowledges("r0", 1)  # what it acked
    assert st.none_of("r0", 1, 3).chain == 1  # more: another base station acked those
    assert st.none_of("r0", 2, 9).chain == 2  # another base station's chain: send it all
    assert st.admit(_kf(2, chain=2)) == [] and r.unchecked_chain == 1  # cannot check it
    with caplog.at_level(logging.WARNING):  # ... and resent from the first: followed on
        assert st.admit(_kf(0, chain=2)) == [] and r.duplicates == 1
    assert "followed on from chain 1 at seq 2" in caplog.text
    assert [k.seq for k in st.admit(_kf(2, chain=2))] == [2]
    assert (st.ack("r0").chain, st.none_of("r0", 2, 3), st.none_of("r0", 1, 9)) == (2, None, None)
    with caplog.at_level(logging.ERROR):  # renumbered from a later first: no way to join
        assert st.admit(Keyframe(**{**_kf(1, chain=3).__dict__, "stamp": 9.0})) == []
    assert r.chain_conflicts == 1 and "kept too few keyframes" in caplog.text
    assert (
        r.foreign
        and st.ack("r0") is None
        and st.none_of("r0", 4, 9) is None
        and not st.acknowledges("r0", 2)
    )


def test_a_restore_follows_the_chains_as_admitted() -> None:
    """The database holds a robot's keyframes as admitted, chain 0 and then the chain it
    followed on with: a restart takes them all up again."""
    cfg = Config()
    cfg.basestation.constraints.enabled = False
    slam = GlobalSlam(cfg)
    for kf in [_kf(0), _kf(1), _kf(0, chain=1), _kf(2, chain=1), _kf(3, chain=1)]:
        slam.admit(kf)
    kept = slam.take_journal()
    assert [(k.chain, k.seq) for k in kept.keyframes] == [(0, 0), (0, 1), (1, 2), (1, 3)]
    again = GlobalSlam(cfg)
    again.restore(Recovered([(0, k) for k in kept.keyframes], [], 0, 0, {}, 1))
    r = again.store.robot("r0")
    assert (r.next_seq, r.chain, again.store.ack("r0").acked_seq) == (4, 1, 3)


def test_a_chain_starting_on_the_way_is_placed_by_its_odometry() -> None:
    """A known start is the odometry frame's pose in `map`: a chain that starts at odom
    pose (3, 1, 90 deg) is placed there, not at the start."""
    cfg = Config()
    cfg.basestation.constraints.enabled = False
    slam = GlobalSlam(cfg, known_starts={"r0": np.array([10.0, 5.0, np.pi / 2])})
    kf = synthetic_keyframe("r0", 0, np.array([3.0, 1.0, np.pi / 2]), np.zeros(3))
    assert slam.admit(kf) == 1
    slam.optimize()
    x, y, yaw = slam.graph.pose("r0", 0)
    np.testing.assert_allclose([x, y, np.cos(yaw)], [9.0, 8.0, -1.0], atol=1e-6)
    np.testing.assert_allclose(slam.T_map_odom("r0"), [10, 5, np.pi / 2], atol=1e-6)


def test_relabel_replaces_fields_without_decoding() -> None:
    p = encode(_kf(7))
    kf = decode(relabel(p, Keyframe, seq=0, chain=3, delta=IDENTITY7), Keyframe)
    assert (kf.seq, kf.chain, kf.stamp) == (0, 3, _kf(7).stamp)
    np.testing.assert_array_equal(kf.scan2d.ranges_mm, _kf(7).scan2d.ranges_mm)
    with pytest.raises(ProtocolError, match="no fields"):
        relabel(p, Keyframe, sequence=1)
    with pytest.raises(ProtocolError, match="expected a KeyframeAck"):
        relabel(p, KeyframeAck, chain=1)


def test_a_field_added_later_may_be_absent() -> None:
    """An older peer's ack (or a database's keyframe) has no chain: chain 0. A field
    without a default is still required."""
    env = {"v": 2, "t": "KeyframeAck", "d": {"robot_id": "r0", "acked_seq": 4}}
    assert decode(msgpack.packb(env, use_bin_type=True), KeyframeAck).chain == 0
    del env["d"]["acked_seq"]
    with pytest.raises(ProtocolError, match="missing fields"):
        decode(msgpack.packb(env, use_bin_type=True), KeyframeAck)
    with pytest.raises(ProtocolError, match="chain"):
        decode(encode(_kf(0, chain=-1)), Keyframe)


def test_a_new_chain_replaces_the_files_whole_or_not_at_all(tmp_path: Path) -> None:
    """A kill while the kept keyframes were rewritten as a new chain had lost every one
    not rewritten yet (the old files were deleted first). Now the new files are written
    beside the old ones and take their place once whole."""
    h = KeyframeHistory(4, tmp_path)  # files of 2
    for seq in range(5):
        h.add(seq, b"old%d" % seq, keep_from=0)
    new = [b"new%d" % i for i in range(5)]

    class Killed(Exception):
        pass

    real_append = kh._Segment.append
    calls = {"n": 0}

    def dying_append(seg: kh._Segment, payload: bytes, sync: bool = True) -> None:
        calls["n"] += 1
        if calls["n"] == 4:  # killed with 3 of 5 written
            raise Killed
        real_append(seg, payload, sync)

    kh._Segment.append = dying_append  # type: ignore[method-assign]
    try:
        with pytest.raises(Killed):
            h.replace(new)
    finally:
        kh._Segment.append = real_append  # type: ignore[method-assign]
    again = KeyframeHistory(4, tmp_path)  # the next agent: the old ones, whole
    assert list(again.payloads()) == [b"old%d" % s for s in range(5)]
    assert not list(tmp_path.glob("next-*"))
    again.replace(new)
    assert list(again.payloads()) == new
    assert list(KeyframeHistory(4, tmp_path).payloads()) == new
    # killed after the new files were whole, before they took the old ones' place
    seg = kh._Segment.new(0, tmp_path, kh.NEXT)
    seg.append(b"x0")
    seg.append(b"x1")
    (tmp_path / kh.NEXT_DONE).touch()
    assert list(KeyframeHistory(4, tmp_path).payloads()) == [b"x0", b"x1"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["keyframes-0000000000.log"]


def test_fields_added_later_are_left_out_at_their_defaults() -> None:
    """A base station sending `session` 0 to an agent of the version before (which
    refuses fields it does not know) had every ack, correction and path refused; `chain`
    sent always had every ack refused by agents from before keyframe chains."""
    raw = msgpack.unpackb(encode(KeyframeAck("r0", 4)))["d"]
    assert raw == {"robot_id": "r0", "acked_seq": 4}  # chain 0 too: agents before chains
    assert msgpack.unpackb(encode(KeyframeAck("r0", 4, 2)))["d"]["chain"] == 2
    assert msgpack.unpackb(encode(KeyframeAck("r0", 4, 0, 7)))["d"]["session"] == 7
    assert decode(encode(KeyframeAck("r0", 4)), KeyframeAck).session == 0
    kf = _kf(0)
    assert "odom_origin" not in msgpack.unpackb(encode(kf))["d"]
