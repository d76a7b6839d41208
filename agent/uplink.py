"""An agent's keyframes on their way to the base station: seqs within a keyframe chain,
the outbox that keeps each until it is acknowledged (at least once, resent in order,
agent/outbox.py), and a new chain for a base station that has none of the keyframes
acknowledged (its database lost: it answers -1, basestation/keyframe_store.py).

Threads: `on_ack` and `on_base_alive` run on Zenoh's; `send`, `resend` and `drain` on
the agent's main thread, which alone numbers keyframes (`next_seq`).
"""

from __future__ import annotations

import logging
import secrets
import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from agent.keyframe_history import KeyframeHistory
from agent.outbox import Outbox
from agent.resume import ResumePoint
from common.bus import Bus
from common.config import AgentConfig
from common.errors import ProtocolError
from common.geometry import pose7_to_pose4
from protocol import Keyframe, KeyframeAck, decode, encode

log = logging.getLogger(__name__)
# s of wall time with a base station up and no ack at all: named (the access control drops
# every keyframe of a drone whose certificate is another's, or of another fleet, silently)
NO_ACK_WARN_S = 60.0


class KeyframeUplink:
    def __init__(
        self, a: AgentConfig, robot_id: str, bus: Bus, resume: ResumePoint | None = None
    ) -> None:
        """`resume`: where an agent before this one stopped (its keyframes in
        `a.state_dir`): the ones it had not got acknowledged are sent again."""
        self.robot_id = robot_id
        self.bus = bus
        self.key = bus.keys.robot(robot_id, "keyframe")
        self.outbox = Outbox(
            a.outbox_max, a.outbox_warn_fraction, a.resend_timeout_s, a.resend_batch,
            history=KeyframeHistory(a.keyframe_history, a.state_dir or None),
        )  # fmt: skip
        self.next_seq = 0  # of this chain
        self.chain = 0  # Keyframe.chain
        self.last_pose: np.ndarray | None = None  # T_odom_base of the last keyframe sent
        self.refused = 0  # failed the checks the base station makes: not sent
        self._lost_chain = -1  # the chain an ack of -1 was about (-1: none since last)
        self._lost_lock = threading.Lock()  # (an Event's is_set then clear had lost one)
        # this agent's run (protocol MAX_SESSION): a resumed agent goes on in its session
        self.session = secrets.randbits(32) or 1 if resume is None else resume.session
        self.other_sessions = 0  # messages for another run of this robot, dropped
        self.acks_heard = 0  # KeyframeAcks of this run
        self._base_up_at: float | None = None  # monotonic s a base station came up
        self._unseen_since: float | None = time.monotonic()  # None: a base station was seen
        if resume is not None:
            self._resume(resume)

    def _resume(self, resume: ResumePoint) -> None:
        """Take up an agent's state; the history on disk may be a step ahead of it (a
        keyframe sent, or a new chain started, just before the kill: the state is saved
        after them): its last record then says where the agent was."""
        chain, next_seq, acked = resume.chain, resume.next_seq, resume.acked_seq
        h = self.outbox.history
        if h.next_seq is not None:
            last = decode(next(h.payloads(h.next_seq - 1)), Keyframe)
            if (last.chain, last.seq + 1) > (chain, next_seq):
                log.warning("keyframe %d of chain %d was sent after the state was saved: "
                            "going on from it", last.seq, last.chain)  # fmt: skip
                if last.chain != chain:
                    acked = -1
                chain, next_seq = last.chain, last.seq + 1
                self.last_pose = pose7_to_pose4(last.pose_odom)
        self.chain, self.next_seq = chain, next_seq
        self.outbox.chain = chain
        self.outbox.restore(acked, next_seq)

    def mine(self, callback: Callable[[Any, str], None]) -> Callable[[Any, str], None]:
        """`callback` for the messages sent to this agent's session (or to none: 0); those
        the base station sends another run of this robot (a second drone with its id, or
        the run before this one's restart) are counted and dropped."""

        def on(msg: Any, key: str) -> None:
            if msg.session in (0, self.session):
                return callback(msg, key)
            if not self.other_sessions:
                log.warning("%s for session %d of %s (this one is %d): dropped (for the "
                            "run before this one's restart, or a second drone with this id)",
                            type(msg).__name__, msg.session, self.robot_id,
                            self.session)  # fmt: skip
            self.other_sessions += 1

        return on

    def on_ack(self, msg: KeyframeAck, key: str = "") -> None:
        """(Zenoh thread) An ack of this chain; -1 after some were acknowledged: the base
        station has none of them (another one acknowledged them), a new chain is due."""
        self.acks_heard += 1
        if msg.chain != self.chain:  # about a chain this agent has left
            return
        if msg.acked_seq < 0 <= self.outbox.acked_seq:
            with self._lost_lock:
                self._lost_chain = msg.chain
        else:
            self.outbox.ack(msg.acked_seq, msg.chain)

    def on_base_alive(self, name: str, alive: bool, again: bool) -> None:
        """(Zenoh thread) Gone: the outbox keeps every keyframe. Back (`again`: not the
        first time): resend from the oldest unacknowledged at once."""
        if not alive:
            log.warning("base station %s lost: flying on local SLAM, %d keyframes kept in "
                        "the outbox", name, len(self.outbox))  # fmt: skip
            self._base_up_at = None
            return
        self._base_up_at = self._base_up_at or time.monotonic()
        self._unseen_since = None
        if again:
            log.info("base station %s is back: resending %d keyframes", name, len(self.outbox))
        self.outbox.kick()

    def send(self, **fields: Any) -> bool:
        """Number, queue and send a keyframe of `fields` (all but robot_id, chain, seq);
        False if it fails the base station's checks (not sent, no seq taken: one it
        refused had held back every later keyframe of its robot, for good)."""
        kf = Keyframe(robot_id=self.robot_id, chain=self.chain, seq=self.next_seq,
                      session=self.session, **fields)  # fmt: skip
        try:
            kf.validate()
        except ProtocolError as exc:
            log.error("keyframe at t=%.3f not sent: %s", kf.stamp, exc)
            self.refused += 1
            return False
        payload = encode(kf)
        self.outbox.add(self.next_seq, payload)
        self.next_seq += 1
        self.last_pose = pose7_to_pose4(kf.pose_odom)
        self.bus.put_raw(self.key, payload)
        return True

    def resend(self) -> bool:
        """Resend what is due (main thread); True if a new chain started first (the
        caller forgets the old base station's correction epochs)."""
        with self._lost_lock:
            lost, self._lost_chain = self._lost_chain, -1
        new = lost == self.chain  # (not twice for one chain)
        if new:
            self.chain += 1
            self.next_seq = self.outbox.new_chain(self.chain)
        up, unseen, now = self._base_up_at, self._unseen_since, time.monotonic()
        if up is not None and not self.acks_heard and len(self.outbox) and now - up > NO_ACK_WARN_S:
            self._base_up_at = None  # (once a link)
            log.error("a base station has been up %.0f s and acknowledged none of this "
                      "robot's %d keyframes: is it busy, or does the access control drop "
                      "them (a certificate for another robot id)?", NO_ACK_WARN_S,
                      len(self.outbox))  # fmt: skip
        if unseen is not None and len(self.outbox) and now - unseen > NO_ACK_WARN_S:
            self._unseen_since = None  # (once)
            log.error("no base station seen in %.0f s (%d keyframes kept): are its endpoint, "
                      "the fleet name (%r) and the certificates the base station's?",
                      NO_ACK_WARN_S, len(self.outbox), self.bus.keys.fleet)  # fmt: skip
        batch = self.outbox.due_for_resend()
        if batch:
            log.info("resending %d keyframes after seq %d (the last acknowledged)",
                     len(batch), self.outbox.acked_seq)  # fmt: skip
        for payload in batch:
            self.bus.put_raw(self.key, payload)
        return new

    def drain(self, timeout_s: float) -> bool:
        """Resend until every keyframe is acknowledged or the timeout passes."""
        deadline = time.monotonic() + timeout_s
        while len(self.outbox) and time.monotonic() < deadline:
            self.resend()
            time.sleep(0.05)
        if len(self.outbox):
            log.warning("%d keyframes still unacknowledged at shutdown", len(self.outbox))
        return len(self.outbox) == 0

    def stats(self) -> dict[str, Any]:
        return {
            "keyframes_sent": self.next_seq,
            "keyframes_acked": self.outbox.acked_seq + 1,
            "keyframes_resent": self.outbox.resent,
            "outbox_high_water": self.outbox.high_water,
            "keyframes_deferred": self.outbox.deferred,
            "keyframes_refused": self.refused,
            "keyframe_chain": self.chain,
            "session": self.session,
            "other_session_drops": self.other_sessions,
        }
